//! ROS 2 type names of every message and service patchwalk sends or serves, so the node plumbing can
//! create typed endpoints from the Rust type alone (`RosMessage::type_name()`,
//! `RosService::type_name()`), for our own interfaces and for the standard ones we use.

use ros2_client::{ActionTypeName, Message, MessageTypeName, ServiceTypeName};

use crate::{
    action, diagnostic_msgs, geometry_msgs, msg, nav_msgs, rcl_interfaces, rosgraph_msgs, sensor_msgs, srv, std_msgs, std_srvs, tf2_msgs,
    visualization_msgs,
};

/// A message type with its ROS 2 name `package/msg/Name`.
pub trait RosMessage: Message + Clone + Send + 'static {
    const PACKAGE: &'static str;
    const NAME: &'static str;

    fn type_name() -> MessageTypeName {
        MessageTypeName::new(Self::PACKAGE, Self::NAME)
    }
}

/// A service type with its ROS 2 name `package/srv/Name` and its request/response structs.
pub trait RosService {
    type Request: Message + Clone + Send + 'static;
    type Response: Message + Clone + Send + 'static;
    const PACKAGE: &'static str;
    const NAME: &'static str;

    fn type_name() -> ServiceTypeName {
        ServiceTypeName::new(Self::PACKAGE, Self::NAME)
    }
}

/// An action type with its ROS 2 name `package/action/Name` and its goal/result/feedback structs.
pub trait RosAction {
    type Goal: Message + Clone + Send + 'static;
    type Result: Message + Clone + Send + 'static;
    type Feedback: Message + Clone + Send + 'static;
    const PACKAGE: &'static str;
    const NAME: &'static str;

    fn type_name() -> ActionTypeName {
        ActionTypeName::new(Self::PACKAGE, Self::NAME)
    }
}

macro_rules! ros_message {
    ($package:literal, $($ty:path => $name:literal),+ $(,)?) => {
        $(
            impl RosMessage for $ty {
                const PACKAGE: &'static str = $package;
                const NAME: &'static str = $name;
            }
        )+
    };
}

macro_rules! ros_service {
    ($package:literal, $($ty:path => ($name:literal, $req:path, $resp:path)),+ $(,)?) => {
        $(
            impl RosService for $ty {
                type Request = $req;
                type Response = $resp;
                const PACKAGE: &'static str = $package;
                const NAME: &'static str = $name;
            }
        )+
    };
}

macro_rules! impl_message {
    ($($ty:path),+ $(,)?) => { $( impl Message for $ty {} )+ };
}

impl_message!(
    msg::Patch,
    msg::PatchArray,
    msg::MapperStatus,
    msg::ExecutorStatus,
    msg::MotionSummary,
    srv::RecordKeyframeRequest,
    srv::RecordKeyframeResponse,
    srv::SelectTargetRequest,
    srv::SelectTargetResponse,
    srv::SaveMotionRequest,
    srv::SaveMotionResponse,
    srv::ListMotionsRequest,
    srv::ListMotionsResponse,
    srv::DeleteMotionRequest,
    srv::DeleteMotionResponse,
    srv::PlayMotionRequest,
    srv::PlayMotionResponse,
    action::PlayMotionGoal,
    action::PlayMotionResult,
    action::PlayMotionFeedback,
    srv::RebootServosRequest,
    srv::RebootServosResponse,
);

ros_message!("patchwalk_msgs",
    msg::Patch => "Patch",
    msg::PatchArray => "PatchArray",
    msg::MapperStatus => "MapperStatus",
    msg::ExecutorStatus => "ExecutorStatus",
    msg::MotionSummary => "MotionSummary",
);

ros_message!("sensor_msgs",
    sensor_msgs::msg::Image => "Image",
    sensor_msgs::msg::CameraInfo => "CameraInfo",
    sensor_msgs::msg::Imu => "Imu",
    sensor_msgs::msg::JointState => "JointState",
    sensor_msgs::msg::PointCloud2 => "PointCloud2",
);

ros_message!("std_msgs",
    std_msgs::msg::Bool => "Bool",
    std_msgs::msg::Empty => "Empty",
);

ros_message!("diagnostic_msgs",
    diagnostic_msgs::msg::DiagnosticArray => "DiagnosticArray",
);

ros_message!("visualization_msgs",
    visualization_msgs::msg::MarkerArray => "MarkerArray",
);

ros_message!("geometry_msgs",
    geometry_msgs::msg::PoseArray => "PoseArray",
    geometry_msgs::msg::PoseStamped => "PoseStamped",
);

ros_message!("nav_msgs",
    nav_msgs::msg::Path => "Path",
);

ros_message!("std_msgs",
    std_msgs::msg::String => "String",
);

ros_message!("tf2_msgs",
    tf2_msgs::msg::TFMessage => "TFMessage",
);

ros_message!("rosgraph_msgs",
    rosgraph_msgs::msg::Clock => "Clock",
);

ros_message!("rcl_interfaces",
    rcl_interfaces::msg::Log => "Log",
);

ros_service!("patchwalk_msgs",
    srv::RecordKeyframe => ("RecordKeyframe", srv::RecordKeyframeRequest, srv::RecordKeyframeResponse),
    srv::SelectTarget => ("SelectTarget", srv::SelectTargetRequest, srv::SelectTargetResponse),
    srv::SaveMotion => ("SaveMotion", srv::SaveMotionRequest, srv::SaveMotionResponse),
    srv::ListMotions => ("ListMotions", srv::ListMotionsRequest, srv::ListMotionsResponse),
    srv::DeleteMotion => ("DeleteMotion", srv::DeleteMotionRequest, srv::DeleteMotionResponse),
    srv::PlayMotion => ("PlayMotion", srv::PlayMotionRequest, srv::PlayMotionResponse),
    srv::RebootServos => ("RebootServos", srv::RebootServosRequest, srv::RebootServosResponse),
);

ros_service!("std_srvs",
    std_srvs::srv::Trigger => ("Trigger", std_srvs::srv::TriggerRequest, std_srvs::srv::TriggerResponse),
    std_srvs::srv::SetBool => ("SetBool", std_srvs::srv::SetBoolRequest, std_srvs::srv::SetBoolResponse),
);

impl RosAction for action::PlayMotion {
    type Goal = action::PlayMotionGoal;
    type Result = action::PlayMotionResult;
    type Feedback = action::PlayMotionFeedback;
    const PACKAGE: &'static str = "patchwalk_msgs";
    const NAME: &'static str = "PlayMotion";
}
