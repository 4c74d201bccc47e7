//! TF on the wire: the `/tf` + `/tf_static` listener that fills a [`TfBuffer`], the broadcasters,
//! and `geometry_msgs/TransformStamped` ↔ isometry. QoS as tf2_ros (`qos.hpp`): `/tf` reliable,
//! volatile, keep last 100 for both ends; `/tf_static` reliable, transient local, keep last 1, the
//! static broadcaster re-sending all of its transforms in one message each time one is added (so
//! the one kept sample holds them all for late joiners).
//!
//! A `TransformStamped` with `header.frame_id = parent`, `child_frame_id = child` carries
//! `parent_from_child`.

use std::sync::{Arc, Mutex, MutexGuard};

use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};
use patchwalk_msgs::builtin_interfaces::msg::Time;
use patchwalk_msgs::geometry_msgs::msg::{Quaternion as QuaternionMsg, Transform, TransformStamped, Vector3};
use patchwalk_msgs::std_msgs::msg::Header;
use patchwalk_msgs::tf2_msgs::msg::TFMessage;
use ros2_client::qos::{Durability, History, QosProfile, WhenFull};
use ros2_client::{Gid, Publisher, Subscription};

use crate::clock::stamp_ns;
use crate::node::{self, NodeError, RateLimitedLog, RosNode};
use crate::tf_buffer::{TfBuffer, TfError};

/// Dynamic transforms.
pub const TF_TOPIC: &str = "/tf";
/// Static transforms (latched).
pub const TF_STATIC_TOPIC: &str = "/tf_static";

/// tf2_ros `DynamicListenerQoS` / `DynamicBroadcasterQoS`: reliable, volatile, keep last 100.
pub fn tf_qos() -> QosProfile {
    QosProfile::publisher_default()
        .reliability_reliable(WhenFull::DEFAULT)
        .durability(Durability::Volatile)
        .history(History::KeepLast { depth: 100 })
}

/// tf2_ros `StaticListenerQoS` / `StaticBroadcasterQoS`: reliable, transient local, keep last 1.
pub fn tf_static_qos() -> QosProfile {
    QosProfile::publisher_default()
        .reliability_reliable(WhenFull::DEFAULT)
        .durability(Durability::TransientLocal)
        .history(History::KeepLast { depth: 1 })
}

/// `parent_from_child` of a transform message (quaternion normalised; zero or non-finite refused).
pub fn isometry_from_transform(transform: &TransformStamped) -> Result<Isometry3<f64>, TfError> {
    let invalid =
        |reason: String| TfError::Invalid { parent: transform.header.frame_id.clone(), child: transform.child_frame_id.clone(), reason };
    let (t, q) = (&transform.transform.translation, &transform.transform.rotation);
    let quaternion = Quaternion::new(q.w, q.x, q.y, q.z);
    let norm = quaternion.norm();
    if !(norm.is_finite() && norm > 1e-9) {
        return Err(invalid(format!("rotation ({}, {}, {}, {}) is not a rotation", q.x, q.y, q.z, q.w)));
    }
    if !(t.x.is_finite() && t.y.is_finite() && t.z.is_finite()) {
        return Err(invalid(format!("translation ({}, {}, {}) is not finite", t.x, t.y, t.z)));
    }
    Ok(Isometry3::from_parts(Translation3::new(t.x, t.y, t.z), UnitQuaternion::from_quaternion(quaternion)))
}

/// The message of `parent_from_child` at `stamp`.
pub fn transform_msg(parent: &str, child: &str, stamp: Time, parent_from_child: &Isometry3<f64>) -> TransformStamped {
    let (t, q) = (&parent_from_child.translation, parent_from_child.rotation.quaternion());
    TransformStamped {
        header: Header { stamp, frame_id: parent.to_string() },
        child_frame_id: child.to_string(),
        transform: Transform {
            translation: Vector3 { x: t.x, y: t.y, z: t.z },
            rotation: QuaternionMsg { x: q.i, y: q.j, z: q.k, w: q.w },
        },
    }
}

/// A [`TfBuffer`] shared between a node's loop (which fills it) and its workers (which look up).
#[derive(Clone, Default)]
pub struct SharedTf(Arc<Mutex<TfBuffer>>);

impl SharedTf {
    /// The buffer (a poisoned lock is taken over: the buffer has no invariants a panic could break).
    pub fn lock(&self) -> MutexGuard<'_, TfBuffer> {
        self.0.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
    }
}

/// Adds the transforms of one message to `buffer`; returns the refused ones' errors.
pub fn insert_message(buffer: &mut TfBuffer, msg: &TFMessage, is_static: bool) -> Vec<TfError> {
    let mut errors = Vec::new();
    for transform in &msg.transforms {
        let result = isometry_from_transform(transform).and_then(|parent_from_child| {
            let (parent, child) = (transform.header.frame_id.as_str(), transform.child_frame_id.as_str());
            if is_static {
                buffer.set_static(parent, child, parent_from_child)
            } else {
                buffer.set_dynamic(parent, child, stamp_ns(&transform.header.stamp), parent_from_child)
            }
        });
        if let Err(e) = result {
            errors.push(e);
        }
    }
    errors
}

/// Subscribes `/tf` and `/tf_static` into a [`SharedTf`]; the node's loop calls [`TfListener::drain`].
pub struct TfListener {
    pub dynamic: Subscription<TFMessage>,
    pub statics: Subscription<TFMessage>,
    buffer: SharedTf,
    log: RateLimitedLog,
    /// The node's own broadcaster, whose messages are not taken (see [`TfListener::ignore_own`]).
    own: Option<Gid>,
}

impl TfListener {
    pub fn new(ros: &mut RosNode, buffer: SharedTf) -> Result<Self, NodeError> {
        let dynamic = ros.subscription::<TFMessage>(TF_TOPIC, tf_qos())?;
        let statics = ros.subscription::<TFMessage>(TF_STATIC_TOPIC, tf_static_qos())?;
        Ok(Self { dynamic, statics, buffer, log: RateLimitedLog::default(), own: None })
    }

    /// Leave out what the node's own `broadcaster` publishes: the node computes those transforms
    /// and must not look them up again. (A hand-held camera's pose published as `odom → camera`
    /// would otherwise re-parent the camera frame in the node's own buffer, away from the driver's
    /// static tree it takes the IMU mount from.)
    pub fn ignore_own(&mut self, broadcaster: &TfBroadcaster) {
        self.own = Some(broadcaster.publisher.gid());
    }

    /// Register both subscriptions with the loop's wake-up.
    pub fn watch(&mut self, wakeup: &crate::wait::Wakeup) -> Result<(), NodeError> {
        wakeup.watch(&mut self.dynamic)?;
        wakeup.watch(&mut self.statics)
    }

    /// Takes the pending messages into the buffer (bad transforms logged, rate-limited); returns
    /// whether the bound per call was reached (more may be waiting).
    pub fn drain(&mut self) -> bool {
        const MAX: usize = 64;
        let mut more = false;
        for (sub, topic, is_static) in [(&self.statics, TF_STATIC_TOPIC, true), (&self.dynamic, TF_TOPIC, false)] {
            let mut messages = Vec::new();
            let own = self.own;
            more |= node::drain(sub, topic, MAX, &mut self.log, |msg, info| {
                if own != Some(info.publisher_gid()) {
                    messages.push(msg);
                }
            }) >= MAX;
            if messages.is_empty() {
                continue;
            }
            let mut buffer = self.buffer.lock();
            for msg in &messages {
                for e in insert_message(&mut buffer, msg, is_static) {
                    self.log.warn(topic, format_args!("{topic}: transform ignored: {e}"));
                }
            }
        }
        more
    }

    pub fn buffer(&self) -> &SharedTf {
        &self.buffer
    }
}

/// Publishes dynamic transforms on `/tf`.
pub struct TfBroadcaster {
    publisher: Publisher<TFMessage>,
    log: RateLimitedLog,
}

impl TfBroadcaster {
    pub fn new(ros: &mut RosNode) -> Result<Self, NodeError> {
        Ok(Self { publisher: ros.publisher::<TFMessage>(TF_TOPIC, tf_qos())?, log: RateLimitedLog::default() })
    }

    pub fn send(&mut self, transforms: Vec<TransformStamped>) {
        node::publish(&self.publisher, TF_TOPIC, TFMessage { transforms }, &mut self.log);
    }
}

/// Publishes static transforms on `/tf_static`: every send carries all transforms given so far (a
/// child's newer transform replaces its older one), as tf2_ros's `StaticTransformBroadcaster`.
pub struct StaticTfBroadcaster {
    publisher: Publisher<TFMessage>,
    transforms: Vec<TransformStamped>,
    log: RateLimitedLog,
}

impl StaticTfBroadcaster {
    pub fn new(ros: &mut RosNode) -> Result<Self, NodeError> {
        Ok(Self {
            publisher: ros.publisher::<TFMessage>(TF_STATIC_TOPIC, tf_static_qos())?,
            transforms: Vec::new(),
            log: RateLimitedLog::default(),
        })
    }

    pub fn send(&mut self, transforms: Vec<TransformStamped>) {
        merge_static(&mut self.transforms, transforms);
        node::publish(&self.publisher, TF_STATIC_TOPIC, TFMessage { transforms: self.transforms.clone() }, &mut self.log);
    }
}

/// Adds `new` to `all`, replacing the transforms of the same child frame.
fn merge_static(all: &mut Vec<TransformStamped>, new: Vec<TransformStamped>) {
    for transform in new {
        match all.iter_mut().find(|t| t.child_frame_id == transform.child_frame_id) {
            Some(slot) => *slot = transform,
            None => all.push(transform),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::tf_buffer::LookupTime;

    #[test]
    fn transforms_round_trip_through_messages() {
        let iso = Isometry3::from_parts(Translation3::new(0.1, -0.2, 0.3), UnitQuaternion::from_euler_angles(0.3, -0.2, 1.1));
        let msg = transform_msg("base_link", "camera_optical", Time { sec: 3, nanosec: 7 }, &iso);
        assert_eq!((msg.header.frame_id.as_str(), msg.child_frame_id.as_str()), ("base_link", "camera_optical"));
        let back = isometry_from_transform(&msg).unwrap();
        assert!((back.translation.vector - iso.translation.vector).norm() < 1e-15);
        assert!(back.rotation.angle_to(&iso.rotation) < 1e-12);
        let mut zero = msg.clone();
        zero.transform.rotation = QuaternionMsg { x: 0.0, y: 0.0, z: 0.0, w: 0.0 };
        let error = isometry_from_transform(&zero).unwrap_err().to_string();
        assert!(error.contains("base_link") && error.contains("not a rotation"), "{error}");
    }

    #[test]
    fn messages_fill_the_buffer_and_bad_transforms_are_reported() {
        let mut buffer = TfBuffer::default();
        let iso = Isometry3::translation(0.0, 0.0, 0.17);
        let statics = TFMessage { transforms: vec![transform_msg("base_link", "camera_optical", Time::default(), &iso)] };
        assert!(insert_message(&mut buffer, &statics, true).is_empty());
        let mut bad = transform_msg("odom", "base_link", Time { sec: 1, nanosec: 0 }, &Isometry3::identity());
        bad.transform.translation.x = f64::INFINITY;
        let good = transform_msg("odom", "base_link", Time { sec: 2, nanosec: 0 }, &Isometry3::translation(1.0, 0.0, 0.0));
        let errors = insert_message(&mut buffer, &TFMessage { transforms: vec![bad, good] }, false);
        assert_eq!(errors.len(), 1);
        let odom_from_camera = buffer.lookup("odom", "camera_optical", LookupTime::At(2_000_000_000)).unwrap();
        assert!((odom_from_camera.translation.vector - nalgebra::Vector3::new(1.0, 0.0, 0.17)).norm() < 1e-12);
    }

    #[test]
    fn static_sends_accumulate_per_child() {
        let mut all = Vec::new();
        let a = transform_msg("base_link", "camera_link", Time::default(), &Isometry3::identity());
        let b = transform_msg("camera_link", "imu", Time::default(), &Isometry3::identity());
        merge_static(&mut all, vec![a.clone(), b]);
        let moved = transform_msg("base_link", "camera_link", Time::default(), &Isometry3::translation(1.0, 0.0, 0.0));
        merge_static(&mut all, vec![moved.clone()]);
        assert_eq!(all.len(), 2);
        assert_eq!(all[0], moved);
    }

    #[test]
    fn qos_profiles_are_tf2_ros_ones() {
        assert_eq!(tf_qos().history, History::KeepLast { depth: 100 });
        assert_eq!(tf_qos().durability, Durability::Volatile);
        assert_eq!(tf_static_qos().history, History::KeepLast { depth: 1 });
        assert_eq!(tf_static_qos().durability, Durability::TransientLocal);
    }
}
