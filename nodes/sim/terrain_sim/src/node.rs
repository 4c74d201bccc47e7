//! ROS 2 wiring of the simulator: publishes `/camera/depth/image_raw` (16UC1 mm),
//! `/camera/depth/camera_info` (30 Hz) and `/imu/data` (100 Hz) with sensor-data QoS, stamped on one
//! clock (`start + t`); follows `/joint_states` (the simulated servo bus) by keeping the stance foot
//! planted; `/terrain_sim/place_at_rock` (std_msgs/UInt32) places the robot in front of rock i, and
//! `/terrain_sim/rock` (std_msgs/UInt32, 1 Hz and on change) reports where it stands. The rig's
//! mount goes on `/tf_static` (`base_link → camera → imu`, see `frames`). With `--clock [RATE]` the
//! simulator runs on its own time from 0 at RATE × real time and publishes it on `/clock` (100 Hz of
//! simulated time) for nodes started with `use_sim_time`.
//!
//! Threads: camera (render + publish), IMU (sample + publish), main (subscriptions). The simulator
//! itself is immutable and shared; only the robot's pose is behind a mutex.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use anyhow::Context as _;
use nalgebra::{Isometry3, UnitQuaternion};
use patchwalk_fusion::camera::{DepthImage, Intrinsics};
use patchwalk_msgs::builtin_interfaces::msg::Time;
use patchwalk_msgs::geometry_msgs::msg::{Quaternion as QuaternionMsg, Vector3 as Vector3Msg};
use patchwalk_msgs::sensor_msgs::msg::{CameraInfo, Image, Imu, JointState, RegionOfInterest};
use patchwalk_msgs::std_msgs::msg::{Header, UInt32};
use patchwalk_robot_model::kinematics::{positions_by_name, RobotModel};
use patchwalk_ros::clock::ClockPublisher;
use patchwalk_ros::declared::{Declared, ParameterSpec};
use patchwalk_ros::node::{self, NodeArgs, RateLimitedLog, RosNode, Shutdown};
use patchwalk_ros::param_server::ParameterServer;
use patchwalk_ros::tf::StaticTfBroadcaster;
use patchwalk_ros::wait::Wakeup;
use ros2_client::{MessageTypeName, Publisher, Subscription};
use terrain_sim::config::SimConfig;
use terrain_sim::imu::ImuSample;
use terrain_sim::motion::StanceTracker;
use terrain_sim::sim::Simulator;

/// Topic names in the root namespace (the README's table); the node creates them relative to itself
/// (`camera/depth/image_raw`, `~/rock`, see [`RosNode::relative`]).
pub const IMAGE_TOPIC: &str = "/camera/depth/image_raw";
pub const CAMERA_INFO_TOPIC: &str = "/camera/depth/camera_info";
pub const IMU_TOPIC: &str = "/imu/data";
pub const JOINT_STATES_TOPIC: &str = "/joint_states";
pub const PLACE_TOPIC: &str = "/terrain_sim/place_at_rock";
pub const ROCK_TOPIC: &str = "/terrain_sim/rock";

/// Every key of the simulator's config is a read-only parameter: the scene, camera and IMU are built
/// at start.
pub const PARAMETERS: ParameterSpec<SimConfig> =
    ParameterSpec { runtime: &[], restart: &[], applied: "never (the simulator is built at start)", validate: accept };

fn accept(_: &SimConfig) -> Result<(), String> {
    Ok(())
}

/// `terrain_sim run` options.
#[derive(clap::Args, Debug, Clone, Default)]
pub struct RunArgs {
    #[command(flatten)]
    pub node: NodeArgs,
    /// Publish simulated time on /clock, starting at 0 and running at RATE × real time (0.5 = half
    /// speed; 1 when RATE is omitted). Every stamp follows it; without it stamps are wall-clock time.
    #[arg(long, value_name = "RATE", num_args = 0..=1, default_missing_value = "1.0")]
    pub clock: Option<f64>,
}

/// Simulated time published on /clock (Hz of simulated time).
const CLOCK_RATE_HZ: f64 = 100.0;

/// Where the robot is: its station (rock index) and, when following the servos, the stance tracker.
#[derive(Clone)]
struct RobotPose {
    rock: usize,
    world_from_station: Isometry3<f64>,
    stance: Option<StanceTracker>,
    base_from_camera: Isometry3<f64>,
}

impl RobotPose {
    fn world_from_camera(&self, sim: &Simulator, t: f64) -> Isometry3<f64> {
        if sim.path.is_some() {
            // Walking a camera path (a terrain scene): the path is the pose.
            return sim.world_from_camera(t);
        }
        let world_from_base = match &self.stance {
            Some(tracker) => tracker.world_from_base() * sim.motion.sway(t),
            None => sim.motion.world_from_base(&self.world_from_station, t),
        };
        world_from_base * self.base_from_camera
    }
}

/// Forward kinematics of the robot for following joint states.
struct Robot {
    model: RobotModel,
    positions: HashMap<String, f64>,
}

impl Robot {
    /// `(base_from_left, base_from_right, base_from_camera)` at the current joint positions.
    fn feet_and_camera(&self) -> Option<(Isometry3<f64>, Isometry3<f64>, Isometry3<f64>)> {
        let left = self.model.base_from_foot("left_foot", &self.positions).ok()?;
        let right = self.model.base_from_foot("right_foot", &self.positions).ok()?;
        let camera = self.model.base_from_camera(&self.positions).ok()?;
        Some((left, right, camera))
    }
}

pub fn run(args: RunArgs) -> anyhow::Result<()> {
    node::init_tracing_with(&args.node.ros.log_levels);
    node::keep_memory_returnable();
    let names = args.node.names("terrain_sim")?;
    let loaded = args.node.load_config::<SimConfig>(&names)?;
    let config = loaded.config;
    let declared = Declared::new(&config, loaded.use_sim_time, &PARAMETERS)?;
    let sim = Arc::new(Simulator::new(config.clone())?);
    let mut robot = load_robot(&config, args.node.config.as_deref());
    let network = node::DdsNetwork::resolve(args.node.dds_network)?;
    let shutdown = Shutdown::install()?;
    let mut ros = RosNode::with_names("terrain_sim", names, network)?;
    let _parameters = ParameterServer::start(&mut ros, declared, None, patchwalk_ros::clock::NodeClock::wall())?;
    let image_pub = ros.publisher::<Image>(&ros.relative(IMAGE_TOPIC), node::sensor_data_qos())?;
    let info_pub = ros.publisher::<CameraInfo>(&ros.relative(CAMERA_INFO_TOPIC), node::sensor_data_qos())?;
    let imu_pub = ros.publisher::<Imu>(&ros.relative(IMU_TOPIC), node::sensor_data_qos())?;
    // Best effort matches both reliable and best-effort joint state publishers.
    let mut joint_sub = ros.subscription::<JointState>(&ros.relative(JOINT_STATES_TOPIC), node::sensor_data_qos())?;
    let mut place_sub: Subscription<UInt32> = std_msgs_subscription(&mut ros, PLACE_TOPIC, "UInt32")?;
    // The control loop sleeps until a placement or joint state arrives, or the rock report is due.
    let mut wakeup = Wakeup::new()?;
    if robot.is_some() {
        wakeup.watch(&mut joint_sub)?;
    }
    wakeup.watch(&mut place_sub)?;
    let rock_pub: Publisher<UInt32> = std_msgs_publisher(&mut ros, ROCK_TOPIC, "UInt32")?;
    let clock = match args.clock {
        None => Clock { start: Instant::now(), epoch: Some(SystemTime::now()), rate: 1.0 },
        Some(rate) if rate.is_finite() && rate > 0.0 => Clock { start: Instant::now(), epoch: None, rate },
        Some(rate) => anyhow::bail!("--clock {rate}: the rate must be a positive number (1 = real time)"),
    };
    let clock_pub = if clock.epoch.is_none() { Some(ClockPublisher::new(&mut ros)?) } else { None };
    let mut mount_pub = StaticTfBroadcaster::new(&mut ros)?;
    mount_pub.send(crate::frames::mount_transforms(&sim, clock.stamp(0.0)));

    let pose = Arc::new(Mutex::new(RobotPose {
        rock: config.start_rock,
        world_from_station: sim.world_from_station,
        stance: None,
        base_from_camera: sim.base_from_camera,
    }));
    tracing::info!(
        rocks = sim.scene.rocks.len(),
        rock = config.start_rock,
        following_joint_states = robot.is_some(),
        "terrain_sim publishing {IMAGE_TOPIC} at {} Hz and {IMU_TOPIC} at {} Hz",
        config.camera.rate_hz,
        config.imu.rate_hz
    );
    let camera_thread = {
        let (sim, pose, shutdown, frame_id) = (Arc::clone(&sim), Arc::clone(&pose), shutdown.clone(), config.node.camera_frame_id.clone());
        std::thread::Builder::new()
            .name("terrain_sim-camera".into())
            .spawn(move || camera_loop(&sim, &pose, &shutdown, clock, &frame_id, &image_pub, &info_pub))?
    };
    let imu_thread = {
        let (sim, pose, shutdown, frame_id) = (Arc::clone(&sim), Arc::clone(&pose), shutdown.clone(), config.node.imu_frame_id.clone());
        std::thread::Builder::new()
            .name("terrain_sim-imu".into())
            .spawn(move || imu_loop(&sim, &pose, &shutdown, clock, &frame_id, &imu_pub))?
    };

    let clock_thread = clock_pub
        .map(|publisher| {
            let shutdown = shutdown.clone();
            std::thread::Builder::new().name("terrain_sim-clock".into()).spawn(move || clock_loop(publisher, &shutdown, clock))
        })
        .transpose()?;

    let mut log = RateLimitedLog::default();
    let mut last_rock_report = Instant::now() - Duration::from_secs(10);
    while !shutdown.requested() {
        let mut placed = false;
        let mut requests = Vec::new();
        let mut more = node::drain(&place_sub, PLACE_TOPIC, 16, &mut log, |msg, _| requests.push(msg.data as usize)) >= 16;
        for index in requests {
            match sim.scene.station(index) {
                Ok(world_from_station) => {
                    let mut state = lock(&pose);
                    state.rock = index;
                    state.world_from_station = world_from_station;
                    // Re-plant the feet at the new station.
                    state.stance = robot
                        .as_ref()
                        .and_then(Robot::feet_and_camera)
                        .map(|(left, right, _)| StanceTracker::new(&world_from_station, &left, &right));
                    placed = true;
                    let name = sim.scene.rocks.get(index).map_or("?", |rock| rock.name.as_str());
                    tracing::info!(rock = index, name, "robot placed in front of rock");
                }
                Err(e) => {
                    log.warn(PLACE_TOPIC, format_args!("{PLACE_TOPIC}: {e}"));
                }
            }
        }
        if let Some(robot) = robot.as_mut() {
            let mut latest = None;
            more |= node::drain(&joint_sub, JOINT_STATES_TOPIC, 64, &mut log, |msg, _| latest = Some(msg)) >= 64;
            if let Some(msg) = latest {
                follow_joint_state(robot, &msg, &pose, &mut log);
            }
        }
        if placed || last_rock_report.elapsed() >= Duration::from_secs(1) {
            let rock = lock(&pose).rock as u32;
            node::publish(&rock_pub, ROCK_TOPIC, UInt32 { data: rock }, &mut log);
            last_rock_report = Instant::now();
        }
        let report_due = Duration::from_secs(1).saturating_sub(last_rock_report.elapsed());
        wakeup.wait(if more { Duration::ZERO } else { report_due.min(Duration::from_millis(100)) });
    }
    for (name, handle) in [("camera", Some(camera_thread)), ("imu", Some(imu_thread)), ("clock", clock_thread)] {
        let Some(handle) = handle else { continue };
        if handle.join().is_err() {
            tracing::error!("{name} thread panicked");
        }
    }
    tracing::info!("terrain_sim stopped");
    Ok(())
}

/// One time base for both sensors: sim time `t` (s since start) ↔ stamp `epoch + t` (wall clock), or
/// with `--clock` stamp `t` itself, sim time running at `rate` × real time.
#[derive(Clone, Copy)]
struct Clock {
    start: Instant,
    /// `None`: simulated time published on /clock.
    epoch: Option<SystemTime>,
    rate: f64,
}

impl Clock {
    fn stamp(&self, t: f64) -> Time {
        let since_start = Duration::from_secs_f64(t.max(0.0));
        match self.epoch {
            Some(epoch) => stamp_from(epoch + since_start),
            None => Time { sec: i32::try_from(since_start.as_secs()).unwrap_or(i32::MAX), nanosec: since_start.subsec_nanos() },
        }
    }

    /// Sleeps until sim time `t`; false if shutdown was requested meanwhile.
    fn sleep_until(&self, t: f64, shutdown: &Shutdown) -> bool {
        let due = self.start + Duration::from_secs_f64((t / self.rate).max(0.0));
        loop {
            if shutdown.requested() {
                return false;
            }
            let now = Instant::now();
            if now >= due {
                return true;
            }
            std::thread::sleep((due - now).min(Duration::from_millis(50)));
        }
    }

    fn now(&self) -> f64 {
        self.start.elapsed().as_secs_f64() * self.rate
    }
}

/// Publishes the simulated time on /clock every 1/CLOCK_RATE_HZ of it.
fn clock_loop(mut publisher: ClockPublisher, shutdown: &Shutdown, clock: Clock) {
    let period = 1.0 / CLOCK_RATE_HZ;
    let mut index = 0u64;
    while clock.sleep_until(index as f64 * period, shutdown) {
        publisher.publish(clock.stamp(index as f64 * period));
        index = ((clock.now() / period).floor() as u64 + 1).max(index + 1);
    }
}

fn camera_loop(
    sim: &Simulator,
    pose: &Mutex<RobotPose>,
    shutdown: &Shutdown,
    clock: Clock,
    frame_id: &str,
    image_pub: &Publisher<Image>,
    info_pub: &Publisher<CameraInfo>,
) {
    let period = 1.0 / sim.config.camera.rate_hz;
    let mut log = RateLimitedLog::default();
    let (mut index, mut skipped) = (0u64, 0u64);
    // While the robot stands still the ray casting of the last pose is reused.
    let mut cache = None;
    while clock.sleep_until(index as f64 * period, shutdown) {
        let t = index as f64 * period;
        let world_from_camera = lock(pose).world_from_camera(sim, t);
        let frame = sim.render_at_reusing(t, &world_from_camera, index, &mut cache);
        let stamp = clock.stamp(t);
        node::publish(info_pub, CAMERA_INFO_TOPIC, camera_info_msg(&sim.camera.intrinsics, stamp.clone(), frame_id), &mut log);
        node::publish(image_pub, IMAGE_TOPIC, depth_image_msg(&frame.depth, stamp, frame_id), &mut log);
        // Rendering fell behind: skip the missed frames rather than bursting them.
        let next = ((clock.now() / period).floor() as u64 + 1).max(index + 1);
        if next > index + 1 {
            skipped += next - index - 1;
            log.warn("camera-behind", format_args!("camera: rendering fell behind, {skipped} frame(s) skipped so far"));
        }
        index = next;
    }
}

fn imu_loop(sim: &Simulator, pose: &Mutex<RobotPose>, shutdown: &Shutdown, clock: Clock, frame_id: &str, imu_pub: &Publisher<Imu>) {
    let period = 1.0 / sim.config.imu.rate_hz;
    let mut log = RateLimitedLog::default();
    let mut index = 0u64;
    while clock.sleep_until(index as f64 * period, shutdown) {
        let t = index as f64 * period;
        let state = lock(pose).clone();
        let sample = sim.imu.sample(|time| state.world_from_camera(sim, time), t, terrain_sim::camera::mix(sim.config.seed ^ 0x1a0, index));
        node::publish(imu_pub, IMU_TOPIC, imu_msg(&sample, &sim.config.imu, clock.stamp(t), frame_id), &mut log);
        index = ((clock.now() / period).floor() as u64 + 1).max(index + 1);
    }
}

/// Applies a joint state: the base moves so the stance foot stays planted.
fn follow_joint_state(robot: &mut Robot, msg: &JointState, pose: &Mutex<RobotPose>, log: &mut RateLimitedLog) {
    if msg.name.len() != msg.position.len() {
        log.warn(
            "joint-state-size",
            format_args!("{JOINT_STATES_TOPIC}: {} names but {} positions, ignored", msg.name.len(), msg.position.len()),
        );
        return;
    }
    robot.positions.extend(positions_by_name(&msg.name, &msg.position));
    let Some((left, right, base_from_camera)) = robot.feet_and_camera() else {
        log.warn("joint-state-fk", format_args!("{JOINT_STATES_TOPIC}: joint state does not cover the legs, ignored"));
        return;
    };
    let mut state = lock(pose);
    let station = state.world_from_station;
    state.base_from_camera = base_from_camera;
    match state.stance.as_mut() {
        Some(tracker) => {
            tracker.update(&left, &right);
        }
        None => state.stance = Some(StanceTracker::new(&station, &left, &right)),
    }
}

/// Loads the URDF when following joint states; a missing or broken model only disables following.
fn load_robot(config: &SimConfig, config_path: Option<&Path>) -> Option<Robot> {
    if !config.node.follow_joint_states || config.node.urdf_path.as_os_str().is_empty() {
        return None;
    }
    let path = resolve_path(&config.node.urdf_path, config_path);
    match RobotModel::from_file(&path) {
        Ok(model) => {
            tracing::info!("robot model {} (following {JOINT_STATES_TOPIC})", path.display());
            // Start from zero joint angles (the lookdown pose of the URDF) until a joint state arrives.
            let positions = patchwalk_robot_model::DEFAULT_JOINTS.iter().map(|j| ((*j).to_string(), 0.0)).collect();
            Some(Robot { model, positions })
        }
        Err(e) => {
            tracing::warn!("not following {JOINT_STATES_TOPIC}: {}: {e}", path.display());
            None
        }
    }
}

/// A relative path is tried against the working directory, then the config file's workspace (the
/// parent of its `config/` directory), then the package's share directory (a colcon install, through
/// the ament index), then this source tree.
fn resolve_path(path: &Path, config_path: Option<&Path>) -> PathBuf {
    if path.is_absolute() || path.exists() {
        return path.to_path_buf();
    }
    if let Some(candidate) = config_path.and_then(Path::parent).and_then(Path::parent).map(|root| root.join(path)) {
        if candidate.exists() {
            return candidate;
        }
    }
    let source_root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../..");
    patchwalk_ros::share::find_data_file(path, "terrain_sim", &source_root).map_or_else(|| path.to_path_buf(), |(found, _)| found)
}

fn lock(pose: &Mutex<RobotPose>) -> MutexGuard<'_, RobotPose> {
    pose.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// Publisher of a `std_msgs` type (not covered by `RosMessage`), reliable.
fn std_msgs_publisher<M: ros2_client::Message>(ros: &mut RosNode, topic: &str, type_name: &str) -> anyhow::Result<Publisher<M>> {
    let name = ros.resolve(&ros.relative(topic))?;
    let qos = node::reliable_qos();
    let ros_node = ros.node_mut().context("node is shutting down")?;
    let dds_topic = ros_node
        .create_topic(&name, MessageTypeName::new("std_msgs", type_name), &qos)
        .map_err(|e| anyhow::anyhow!("cannot create topic {topic}: {e:?}"))?;
    ros_node.create_publisher(&dds_topic, Some(qos)).map_err(|e| anyhow::anyhow!("cannot create publisher {topic}: {e:?}"))
}

/// Subscription to a `std_msgs` type, reliable.
fn std_msgs_subscription<M: ros2_client::Message + 'static>(
    ros: &mut RosNode,
    topic: &str,
    type_name: &str,
) -> anyhow::Result<Subscription<M>> {
    let name = ros.resolve(&ros.relative(topic))?;
    let qos = node::reliable_qos();
    let ros_node = ros.node_mut().context("node is shutting down")?;
    let dds_topic = ros_node
        .create_topic(&name, MessageTypeName::new("std_msgs", type_name), &qos)
        .map_err(|e| anyhow::anyhow!("cannot create topic {topic}: {e:?}"))?;
    ros_node.create_subscription(&dds_topic, Some(qos)).map_err(|e| anyhow::anyhow!("cannot create subscription {topic}: {e:?}"))
}

// ---- message conversion -------------------------------------------------------------------------

/// `builtin_interfaces/Time` of a wall-clock instant.
pub fn stamp_from(time: SystemTime) -> Time {
    let since_epoch = time.duration_since(UNIX_EPOCH).unwrap_or_default();
    Time { sec: i32::try_from(since_epoch.as_secs()).unwrap_or(i32::MAX), nanosec: since_epoch.subsec_nanos() }
}

/// Depth as `sensor_msgs/Image` `16UC1` (millimetres, little endian, 0 = no data).
pub fn depth_image_msg(depth: &DepthImage, stamp: Time, frame_id: &str) -> Image {
    let data: Vec<u8> = terrain_sim::camera::to_millimetres(depth).iter().flat_map(|mm| mm.to_le_bytes()).collect();
    Image {
        header: Header { stamp, frame_id: frame_id.to_string() },
        height: depth.height as u32,
        width: depth.width as u32,
        encoding: "16UC1".to_string(),
        is_bigendian: 0,
        step: (depth.width * 2) as u32,
        data,
    }
}

/// `sensor_msgs/CameraInfo` of a distortion-free pinhole camera.
pub fn camera_info_msg(k: &Intrinsics, stamp: Time, frame_id: &str) -> CameraInfo {
    CameraInfo {
        header: Header { stamp, frame_id: frame_id.to_string() },
        height: k.height as u32,
        width: k.width as u32,
        distortion_model: "plumb_bob".to_string(),
        d: vec![0.0; 5],
        k: [k.fx, 0.0, k.cx, 0.0, k.fy, k.cy, 0.0, 0.0, 1.0],
        r: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        p: [k.fx, 0.0, k.cx, 0.0, 0.0, k.fy, k.cy, 0.0, 0.0, 0.0, 1.0, 0.0],
        binning_x: 0,
        binning_y: 0,
        roi: RegionOfInterest::default(),
    }
}

/// `sensor_msgs/Imu` with diagonal covariances from the configured noise.
pub fn imu_msg(sample: &ImuSample, config: &terrain_sim::imu::ImuConfig, stamp: Time, frame_id: &str) -> Imu {
    let diagonal = |sigma: f64| {
        let v = sigma * sigma;
        [v, 0.0, 0.0, 0.0, v, 0.0, 0.0, 0.0, v]
    };
    let vector = |v: &nalgebra::Vector3<f64>| Vector3Msg { x: v.x, y: v.y, z: v.z };
    let q: &UnitQuaternion<f64> = &sample.world_from_imu;
    Imu {
        header: Header { stamp, frame_id: frame_id.to_string() },
        orientation: QuaternionMsg { x: q.i, y: q.j, z: q.k, w: q.w },
        orientation_covariance: diagonal(config.orientation_noise_deg.to_radians()),
        angular_velocity: vector(&sample.angular_velocity_in_imu),
        angular_velocity_covariance: diagonal(config.gyro_noise_radps),
        linear_acceleration: vector(&sample.linear_acceleration_in_imu),
        linear_acceleration_covariance: diagonal(config.accel_noise_mps2),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn depth_image_is_16uc1_millimetres() {
        let depth = DepthImage::new(3, 2, vec![0.5, f32::NAN, 1.2345, 2.0, 0.001, 65.0]).unwrap();
        let msg = depth_image_msg(&depth, Time { sec: 1, nanosec: 2 }, "camera_optical");
        assert_eq!((msg.width, msg.height, msg.step, msg.encoding.as_str()), (3, 2, 6, "16UC1"));
        let mm: Vec<u16> = msg.data.chunks_exact(2).map(|b| u16::from_le_bytes([b[0], b[1]])).collect();
        assert_eq!(mm, vec![500, 0, 1235, 2000, 1, 65000]);
        assert_eq!(msg.header.frame_id, "camera_optical");
    }

    #[test]
    fn camera_info_matches_intrinsics() {
        let k = Intrinsics::new(640, 480, 570.3, 570.3, 319.5, 239.5).unwrap();
        let msg = camera_info_msg(&k, Time { sec: 0, nanosec: 0 }, "camera_optical");
        assert_eq!((msg.width, msg.height), (640, 480));
        assert_eq!(msg.k[0], 570.3);
        assert_eq!(msg.k[2], 319.5);
        assert_eq!(msg.p[6], 239.5);
    }

    #[test]
    fn imu_message_carries_gravity() {
        let sim = Simulator::new(SimConfig::default()).unwrap();
        let sample = sim.imu_sample(3);
        let msg = imu_msg(&sample, &sim.config.imu, stamp_from(UNIX_EPOCH + Duration::from_millis(1500)), "imu");
        let a = &msg.linear_acceleration;
        assert!(((a.x * a.x + a.y * a.y + a.z * a.z).sqrt() - 9.81).abs() < 0.1);
        assert_eq!((msg.header.stamp.sec, msg.header.stamp.nanosec), (1, 500_000_000));
        assert!(msg.linear_acceleration_covariance[0] > 0.0);
    }

    #[test]
    fn joint_states_move_the_camera_with_the_stance_foot_planted() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../urdf/rpbp.urdf");
        let model = RobotModel::from_file(&path).unwrap();
        let positions = patchwalk_robot_model::DEFAULT_JOINTS.iter().map(|j| ((*j).to_string(), 0.0)).collect();
        let mut robot = Robot { model, positions };
        let sim = Simulator::new(SimConfig::default()).unwrap();
        let pose = Mutex::new(RobotPose {
            rock: 0,
            world_from_station: sim.world_from_station,
            stance: None,
            base_from_camera: sim.base_from_camera,
        });
        let mut log = RateLimitedLog::default();
        let names: Vec<String> = patchwalk_robot_model::DEFAULT_JOINTS.iter().map(|j| (*j).to_string()).collect();
        let zero = JointState { name: names.clone(), position: vec![0.0; 12], ..JointState::default() };
        follow_joint_state(&mut robot, &zero, &pose, &mut log);
        let camera_at_zero = lock(&pose).world_from_camera(&sim, 0.0);
        // The URDF camera at zero angles is the lookdown pose of the motion config.
        let lookdown = sim.motion.world_from_camera(&sim.world_from_station, &sim.base_from_camera, 0.0);
        assert!(
            (camera_at_zero.translation.vector - lookdown.translation.vector).norm() < 1e-6,
            "{} vs {}",
            camera_at_zero.translation.vector,
            lookdown.translation.vector
        );
        assert!(camera_at_zero.rotation.angle_to(&lookdown.rotation) < 1e-6);
        // Bend both knees: the base (and camera) go down, the feet stay on the table.
        let mut bent = zero.clone();
        for (name, position) in bent.name.iter().zip(bent.position.iter_mut()) {
            if name.contains("knee") {
                *position = 0.6;
            } else if name.contains("hip_pitch") || name.contains("ankle_pitch") {
                *position = -0.3;
            }
        }
        follow_joint_state(&mut robot, &bent, &pose, &mut log);
        let camera_bent = lock(&pose).world_from_camera(&sim, 0.0);
        assert!(
            camera_bent.translation.z < camera_at_zero.translation.z - 0.005,
            "{} vs {}",
            camera_bent.translation.z,
            camera_at_zero.translation.z
        );
        // Malformed joint states are ignored.
        let bad = JointState { name: names, position: vec![0.0; 3], ..JointState::default() };
        follow_joint_state(&mut robot, &bad, &pose, &mut log);
        assert_eq!(lock(&pose).world_from_camera(&sim, 0.0), camera_bent);
    }
}
