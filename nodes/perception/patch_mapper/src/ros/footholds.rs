//! The learned foothold stage of patch_mapper (CNN paper): footholds predicted from each depth frame
//! and the camera tilt (`patchwalk_footholds`), published in the fixed frame, handed to the mapper's
//! learned seed orders (`mapper.seeds.order`), and the coarse route of CNN IV (`patchwalk_route`)
//! toward a goal from `~/route_goal`.
//!
//! It runs off the PatchArray path, on its own thread with its own rayon pool (`ros.footholds.threads`
//! workers, so the network never takes the pipeline's cores): the pipeline thread offers each mapped
//! frame (depth, intrinsics, the tracked pose) through a keep-latest slot ([`Latest`]) after it has
//! published the PatchArray; the stage takes the newest frame when it is free and the rate limit
//! allows, and a frame still waiting when a newer one comes is dropped and counted (`/diagnostics`,
//! `patch_mapper: footholds`). The predictions it hands back reach the mapper at the pipeline's next
//! frame, so a slow network makes the seeds older, never the patches later.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use nalgebra::{Isometry3, Point3, Vector3};
use patchwalk_footholds::model::FootholdModel;
use patchwalk_footholds::tilt::Tilt;
use patchwalk_fusion::camera::{DepthImage, Intrinsics};
use patchwalk_mapping::patch_map::PatchMap;
use patchwalk_msgs::builtin_interfaces::msg::Time;
use patchwalk_msgs::geometry_msgs::msg::{PoseArray, PoseStamped};
use patchwalk_msgs::nav_msgs::msg::Path;
use patchwalk_msgs::sensor_msgs::msg::PointCloud2;
use patchwalk_msgs::visualization_msgs::msg::MarkerArray;
use patchwalk_ros::node::{self, RateLimitedLog};
use patchwalk_ros::tf_buffer::{LookupTime, TfBuffer};
use patchwalk_route::grid::{CNN_COLS, CNN_ROWS};
use patchwalk_route::{BipedModel, Hold, Pinhole, Planner, PlannerConfig, Route, Target, TerrainGrid};
use ros2_client::Publisher;
use serde::{Deserialize, Serialize};

use super::foothold_msgs;
use super::latest::{Latest, Taken};
use patch_mapper::foothold_points::{lift, ScoredHold};

/// Output and input names of the stage (root namespace; created relative to the node).
pub const FOOTHOLDS_TOPIC: &str = "/patch_mapper/footholds";
pub const FOOTHOLD_MARKERS_TOPIC: &str = "/patch_mapper/footholds/markers";
pub const FOOTHOLD_SCORES_TOPIC: &str = "/patch_mapper/footholds/scored";
pub const ROUTE_TOPIC: &str = "/patch_mapper/route";
pub const ROUTE_MARKERS_TOPIC: &str = "/patch_mapper/route/markers";
pub const ROUTE_GOAL_TOPIC: &str = "/patch_mapper/route_goal";

/// The shipped weights (depth + tilt), looked up in the working directory, the package's share
/// directory (`share/patch_mapper/weights/`), then `nodes/perception/footholds/` of the source tree.
pub const DEFAULT_WEIGHTS: &str = "weights/foot_d.safetensors";

/// `ros.footholds`: the learned foothold stage.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FootholdParams {
    /// Run the stage. Off by default: it takes a core's share of 10–50 ms per 640 × 480 frame
    /// (`bench_footholds_cnn`) that the mapper would otherwise have.
    pub enabled: bool,
    /// Weights (safetensors with their network and region configuration, `patch_mapper footholds
    /// train`); relative paths are looked up as [`DEFAULT_WEIGHTS`] is.
    pub weights_path: String,
    /// Footholds are the regions with p ≥ this (CNN III: 0.5).
    pub threshold: f64,
    /// At most this many predictions per second (0: as fast as the network goes).
    pub max_rate_hz: f64,
    /// Threads of the stage's own rayon pool (network and route planning).
    pub threads: usize,
    /// Publish `~/footholds/markers`.
    pub publish_markers: bool,
    /// Hand the predictions to the mapper's learned seed orders (`mapper.seeds.order`).
    pub seed_priors: bool,
    /// Average each region's answer with its mirror image's (`FootholdModel::mirror_average`): fewer
    /// errors, twice the network's time.
    pub mirror_average: bool,
}

impl Default for FootholdParams {
    fn default() -> Self {
        Self {
            enabled: false,
            weights_path: DEFAULT_WEIGHTS.into(),
            threshold: 0.5,
            max_rate_hz: 2.0,
            threads: 1,
            publish_markers: true,
            seed_priors: true,
            mirror_average: true,
        }
    }
}

/// Where the route's holds come from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RouteHolds {
    /// The footholds predicted on the frame (needs `ros.footholds.enabled`).
    Footholds,
    /// The patch map's patches no steeper than `max_slope_deg` (score 1).
    Patches,
}

/// `ros.route`: the coarse route toward `~/route_goal`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RouteParams {
    /// Plan and publish `~/route` (off by default).
    pub enabled: bool,
    pub holds: RouteHolds,
    /// Patches steeper than this (normal from vertical, degrees) are not holds (`holds: patches`).
    pub max_slope_deg: f64,
    /// The planner's parameters (`patchwalk_route::PlannerConfig`, CNN IV's values).
    pub planner: PlannerConfig,
}

impl Default for RouteParams {
    fn default() -> Self {
        Self { enabled: false, holds: RouteHolds::Footholds, max_slope_deg: 30.0, planner: PlannerConfig::default() }
    }
}

/// Checks `ros.footholds` and `ros.route` (at start and on every parameter set).
pub fn validate(footholds: &FootholdParams, route: &RouteParams) -> Result<(), String> {
    if !(footholds.threshold.is_finite() && (0.0..=1.0).contains(&footholds.threshold)) {
        return Err(format!("ros.footholds.threshold = {} must lie in [0, 1]", footholds.threshold));
    }
    if !(footholds.max_rate_hz.is_finite() && footholds.max_rate_hz >= 0.0) {
        return Err(format!("ros.footholds.max_rate_hz = {} must be >= 0 (0: no limit)", footholds.max_rate_hz));
    }
    if !(1..=64).contains(&footholds.threads) {
        return Err(format!("ros.footholds.threads = {} must be in 1..=64", footholds.threads));
    }
    if footholds.weights_path.trim().is_empty() {
        return Err("ros.footholds.weights_path must not be empty".into());
    }
    if !(route.max_slope_deg.is_finite() && route.max_slope_deg > 0.0 && route.max_slope_deg <= 90.0) {
        return Err(format!("ros.route.max_slope_deg = {} must be in (0, 90]", route.max_slope_deg));
    }
    route.planner.validate().map_err(|e| format!("ros.route.planner: {e}"))?;
    if route.enabled && route.holds == RouteHolds::Footholds && !footholds.enabled {
        return Err("ros.route.holds = footholds needs ros.footholds.enabled = true (or ros.route.holds = patches)".into());
    }
    Ok(())
}

/// Finds a weights file: absolute as given, else the working directory, `share/patch_mapper/`, then
/// the footholds crate of the source tree.
pub fn find_weights(path: &str) -> Option<std::path::PathBuf> {
    let source_root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../footholds");
    patchwalk_ros::share::find_data_file(std::path::Path::new(path), "patch_mapper", &source_root).map(|(found, _)| found)
}

/// A mapped frame offered to the stage.
pub struct FootholdFrame {
    pub depth: DepthImage,
    pub intrinsics: Intrinsics,
    pub stamp: Time,
    /// The tracked camera pose in the fixed frame (z up).
    pub fixed_from_camera: Isometry3<f64>,
    /// The patch map's holds (fixed frame), for `ros.route.holds = patches`.
    pub patch_holds: Vec<Hold>,
}

/// The patch map's patches no steeper than `max_slope_deg` as holds of score 1 (map = fixed frame).
pub fn patch_holds(map: &PatchMap, max_slope_deg: f64) -> Vec<Hold> {
    let min_cos = max_slope_deg.to_radians().cos();
    map.patches().iter().filter(|m| m.patch.normal().normalize().z.abs() >= min_cos).map(|m| Hold::new(m.patch.center, 1.0)).collect()
}

/// What the stage reports for `/diagnostics`.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct FootholdHealth {
    /// Frames predicted so far.
    pub predicted: u64,
    /// Offered to the stage / dropped for a newer one (the slot's counters).
    pub offered: u64,
    pub dropped: u64,
    /// The last prediction: region proposal and network wall time (ms), footholds found.
    pub last_regions_ms: f64,
    pub last_network_ms: f64,
    pub last_holds: usize,
    /// Routes planned, and the last outcome ("" before the first goal).
    pub routes: u64,
    pub last_route: String,
    pub last_error: String,
    /// `ros.footholds.max_rate_hz` in effect.
    pub max_rate_hz: f64,
}

/// Parameters the stage takes while it runs (`ros.footholds.threshold`, `.max_rate_hz`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StageSettings {
    pub threshold: f64,
    pub max_rate_hz: f64,
}

/// Predicted footholds for the mapper's seeds: points in the fixed (= map) frame and their scores.
pub type SeedPriors = Vec<(Vector3<f64>, f64)>;

/// What the pipeline thread, the ROS loop and the stage thread share.
pub struct FootholdStage {
    frames: Latest<FootholdFrame>,
    goal: Mutex<Option<Target>>,
    priors: Mutex<Option<SeedPriors>>,
    health: Mutex<FootholdHealth>,
    settings: Mutex<StageSettings>,
    /// Whether the pipeline wants predictions for its seeds.
    pub seed_priors: bool,
    /// Whether the route wants the patch holds with each frame.
    pub wants_patch_holds: bool,
    /// `ros.route.max_slope_deg`.
    pub max_slope_deg: f64,
    stop: AtomicBool,
}

impl FootholdStage {
    pub fn new(footholds: &FootholdParams, route: &RouteParams) -> Self {
        Self {
            frames: Latest::new(),
            goal: Mutex::new(None),
            priors: Mutex::new(None),
            health: Mutex::new(FootholdHealth { max_rate_hz: footholds.max_rate_hz, ..Default::default() }),
            settings: Mutex::new(StageSettings { threshold: footholds.threshold, max_rate_hz: footholds.max_rate_hz }),
            seed_priors: footholds.enabled && footholds.seed_priors,
            wants_patch_holds: route.enabled && route.holds == RouteHolds::Patches,
            max_slope_deg: route.max_slope_deg,
            stop: AtomicBool::new(false),
        }
    }

    /// The pipeline thread hands over a mapped frame (never waits).
    pub fn offer(&self, frame: FootholdFrame) {
        self.frames.offer(frame);
    }

    /// New predictions for the mapper's seeds, once each (fixed = map frame).
    pub fn take_priors(&self) -> Option<SeedPriors> {
        self.priors.lock().ok().and_then(|mut p| p.take())
    }

    /// A route goal (fixed frame), `None` to stop planning.
    pub fn set_goal(&self, goal: Option<Target>) {
        if let Ok(mut slot) = self.goal.lock() {
            *slot = goal;
        }
    }

    pub fn goal(&self) -> Option<Target> {
        self.goal.lock().ok().and_then(|g| *g)
    }

    pub fn set_settings(&self, settings: StageSettings) {
        if let Ok(mut s) = self.settings.lock() {
            *s = settings;
        }
        if let Ok(mut h) = self.health.lock() {
            h.max_rate_hz = settings.max_rate_hz;
        }
    }

    fn settings(&self) -> Option<StageSettings> {
        self.settings.lock().ok().map(|s| *s)
    }

    /// The health with the slot's counters.
    pub fn health(&self) -> FootholdHealth {
        let counts = self.frames.counts();
        let mut health = self.health.lock().map(|h| h.clone()).unwrap_or_default();
        health.offered = counts.offered;
        health.dropped = counts.dropped;
        health
    }

    fn update(&self, f: impl FnOnce(&mut FootholdHealth)) {
        if let Ok(mut h) = self.health.lock() {
            f(&mut h);
        }
    }

    /// Ends the stage thread.
    pub fn close(&self) {
        self.stop.store(true, Ordering::Relaxed);
        self.frames.close();
    }
}

/// `~/route_goal` (`geometry_msgs/PoseStamped`, as RViz's 2D goal tool sends it) as a planner
/// target in the fixed frame: the position, moved through TF when stamped in another frame; z is
/// left to the terrain (the tool sends z = 0).
pub fn goal_in_fixed(msg: &PoseStamped, fixed_frame: &str, tf: &TfBuffer) -> Result<Target, String> {
    let p = &msg.pose.position;
    if !(p.x.is_finite() && p.y.is_finite() && p.z.is_finite()) {
        return Err(format!("route goal ({}, {}, {}) is not finite", p.x, p.y, p.z));
    }
    let frame = msg.header.frame_id.trim_start_matches('/');
    let point = if frame.is_empty() || frame == fixed_frame.trim_start_matches('/') {
        Point3::new(p.x, p.y, p.z)
    } else {
        let fixed_from_goal = tf
            .lookup(fixed_frame, frame, LookupTime::Latest)
            .map_err(|e| format!("route goal in '{frame}': no transform to '{fixed_frame}': {e}"))?;
        fixed_from_goal * Point3::new(p.x, p.y, p.z)
    };
    Ok(Target { x: point.x, y: point.y, z: None })
}

/// Publishers the stage thread owns.
pub struct StageOutputs {
    pub footholds: Publisher<PoseArray>,
    pub markers: Option<Publisher<MarkerArray>>,
    pub scores: Publisher<PointCloud2>,
    pub route: Option<(Publisher<Path>, Publisher<MarkerArray>)>,
}

/// The stage thread's state.
pub struct StageWorker {
    pub stage: Arc<FootholdStage>,
    pub model: Option<FootholdModel>,
    pub planner: Option<(Planner, RouteHolds)>,
    pub outputs: StageOutputs,
    pub fixed_frame: String,
    /// The foot radius the normals are fitted over (`mapper.foot_radius_m`).
    pub foot_radius_m: f64,
    pub pool: rayon::ThreadPool,
    pub log: RateLimitedLog,
}

/// The route planner for `ros.route` (`None` when off).
pub fn route_planner(route: &RouteParams) -> Result<Option<(Planner, RouteHolds)>, patchwalk_route::RouteError> {
    if !route.enabled {
        return Ok(None);
    }
    Ok(Some((Planner::new(BipedModel::rpbp()?, route.planner.clone())?, route.holds)))
}

impl StageWorker {
    /// Takes frames until the stage is closed.
    pub fn run(mut self) {
        let mut next_allowed = Instant::now();
        while !self.stage.stop.load(Ordering::Relaxed) {
            // The rate limit: wait (in short steps, to see a shutdown) until the next prediction is due.
            let now = Instant::now();
            if now < next_allowed {
                std::thread::sleep((next_allowed - now).min(Duration::from_millis(50)));
                continue;
            }
            let frame = match self.stage.frames.take_timeout(Duration::from_millis(100)) {
                Taken::Item(frame) => frame,
                Taken::Timeout => continue,
                Taken::Closed => break,
            };
            let started = Instant::now();
            let Some(settings) = self.stage.settings() else { break };
            self.process(&frame, settings);
            if settings.max_rate_hz > 0.0 {
                next_allowed = started + Duration::from_secs_f64(1.0 / settings.max_rate_hz);
            }
        }
    }

    fn process(&mut self, frame: &FootholdFrame, settings: StageSettings) {
        let holds = match &self.model {
            Some(model) => match self.predict(model, frame, settings.threshold) {
                Ok(holds) => Some(holds),
                Err(message) => {
                    self.fail("predict", message);
                    None
                }
            },
            None => None,
        };
        if let Some(holds) = &holds {
            let frame_id = self.fixed_frame.as_str();
            node::publish(
                &self.outputs.footholds,
                FOOTHOLDS_TOPIC,
                foothold_msgs::pose_array(holds, &frame.stamp, frame_id),
                &mut self.log,
            );
            node::publish(
                &self.outputs.scores,
                FOOTHOLD_SCORES_TOPIC,
                foothold_msgs::scored_cloud(holds, &frame.stamp, frame_id),
                &mut self.log,
            );
            if let Some(markers) = &self.outputs.markers {
                node::publish(markers, FOOTHOLD_MARKERS_TOPIC, foothold_msgs::hold_markers(holds, &frame.stamp, frame_id), &mut self.log);
            }
            if self.stage.seed_priors {
                if let Ok(mut priors) = self.stage.priors.lock() {
                    *priors = Some(holds.iter().map(|h| (h.position, h.score)).collect());
                }
            }
        }
        if let (Some(goal), Some((planner, source))) = (self.stage.goal(), &self.planner) {
            let route_holds: Vec<Hold> = match source {
                RouteHolds::Footholds => holds.iter().flatten().map(|h| Hold::new(h.position, h.score)).collect(),
                RouteHolds::Patches => frame.patch_holds.clone(),
            };
            let planned = self.pool.install(|| plan(planner, frame, &route_holds, goal));
            match planned {
                Ok(route) => {
                    if let Some((path, markers)) = &self.outputs.route {
                        let frame_id = self.fixed_frame.as_str();
                        node::publish(path, ROUTE_TOPIC, foothold_msgs::route_path(&route, &frame.stamp, frame_id), &mut self.log);
                        node::publish(
                            markers,
                            ROUTE_MARKERS_TOPIC,
                            foothold_msgs::route_markers(&route, &frame.stamp, frame_id),
                            &mut self.log,
                        );
                    }
                    let summary =
                        format!("{} stances over {:.2} m toward ({:.2}, {:.2})", route.stances.len(), route.length_m, goal.x, goal.y);
                    self.stage.update(|h| {
                        h.routes += 1;
                        h.last_route = summary;
                    });
                }
                Err(message) => {
                    let message = format!("no route toward ({:.2}, {:.2}) over {} holds: {message}", goal.x, goal.y, route_holds.len());
                    self.stage.update(|h| h.last_route = message.clone());
                    self.log.warn("route", format_args!("{message}"));
                }
            }
        }
    }

    /// The frame's predicted footholds in the fixed frame.
    fn predict(&self, model: &FootholdModel, frame: &FootholdFrame, threshold: f64) -> Result<Vec<ScoredHold>, String> {
        let gravity_in_camera = frame.fixed_from_camera.inverse_transform_vector(&-Vector3::z());
        let tilt = Tilt::from_gravity_in_camera(&gravity_in_camera).map_err(|e| format!("camera tilt: {e}"))?;
        let prediction = self
            .pool
            .install(|| model.predict_frame(&frame.depth, &frame.intrinsics, tilt))
            .map_err(|e| format!("foothold prediction failed: {e}"))?;
        let predicted = prediction.footholds(threshold as f32);
        let holds = lift(&predicted, &frame.depth, &frame.intrinsics, &frame.fixed_from_camera, self.foot_radius_m);
        let count = holds.len();
        self.stage.update(|h| {
            h.predicted += 1;
            h.last_regions_ms = prediction.regions_ms;
            h.last_network_ms = prediction.network_ms;
            h.last_holds = count;
            h.last_error.clear();
        });
        Ok(holds)
    }

    fn fail(&mut self, key: &str, message: String) {
        self.log.warn(key, format_args!("{message}"));
        self.stage.update(|h| h.last_error = message);
    }
}

/// CNN IV on one frame: the terrain grid of its depth in the fixed frame, the holds, the goal.
fn plan(planner: &Planner, frame: &FootholdFrame, holds: &[Hold], goal: Target) -> Result<Route, String> {
    let k = &frame.intrinsics;
    let pinhole = Pinhole { fx: k.fx, fy: k.fy, cx: k.cx, cy: k.cy };
    let depth = &frame.depth;
    let grid = TerrainGrid::from_depth(depth.width, depth.height, &depth.depth_m, &pinhole, &frame.fixed_from_camera, CNN_ROWS, CNN_COLS)
        .map_err(|e| e.to_string())?;
    planner.plan(&grid, holds, None, goal).map_err(|e| e.to_string())
}

#[cfg(test)]
mod tests {
    use super::*;
    use patchwalk_msgs::geometry_msgs::msg::{Point, Pose};
    use patchwalk_msgs::std_msgs::msg::Header;

    #[test]
    fn parameters_are_validated_naming_the_key() {
        let (f, r) = (FootholdParams::default(), RouteParams::default());
        assert_eq!(validate(&f, &r), Ok(()));
        let bad = |f: FootholdParams, r: RouteParams, key: &str| {
            let err = validate(&f, &r).unwrap_err();
            assert!(err.contains(key), "{err}");
        };
        bad(FootholdParams { threshold: 1.5, ..f.clone() }, r.clone(), "ros.footholds.threshold");
        bad(FootholdParams { threshold: f64::NAN, ..f.clone() }, r.clone(), "ros.footholds.threshold");
        bad(FootholdParams { max_rate_hz: -1.0, ..f.clone() }, r.clone(), "max_rate_hz");
        bad(FootholdParams { threads: 0, ..f.clone() }, r.clone(), "threads");
        bad(FootholdParams { weights_path: " ".into(), ..f.clone() }, r.clone(), "weights_path");
        bad(f.clone(), RouteParams { max_slope_deg: 0.0, ..r.clone() }, "max_slope_deg");
        let planner = PlannerConfig { clusters: 0, ..PlannerConfig::default() };
        bad(f.clone(), RouteParams { planner, ..r.clone() }, "ros.route.planner");
        // A route over predicted footholds needs the predictor; over patches it does not.
        bad(f.clone(), RouteParams { enabled: true, ..r.clone() }, "ros.footholds.enabled");
        assert_eq!(validate(&f, &RouteParams { enabled: true, holds: RouteHolds::Patches, ..r.clone() }), Ok(()));
        assert_eq!(validate(&FootholdParams { enabled: true, ..f }, &RouteParams { enabled: true, ..r }), Ok(()));
    }

    #[test]
    fn the_shipped_weights_are_found_and_load() {
        let path = find_weights(DEFAULT_WEIGHTS).expect("shipped weights");
        assert!(path.ends_with("weights/foot_d.safetensors"), "{}", path.display());
        FootholdModel::load(&path).unwrap();
        assert_eq!(find_weights("weights/no_such.safetensors"), None);
    }

    #[test]
    fn goals_in_the_fixed_frame_or_through_tf_become_targets() {
        let mut tf = TfBuffer::new(10_000_000_000);
        tf.set_static("odom", "base_link", Isometry3::translation(1.0, 2.0, 0.3)).unwrap();
        let goal = |frame: &str, x: f64| PoseStamped {
            header: Header { frame_id: frame.into(), ..Default::default() },
            pose: Pose { position: Point { x, y: 0.5, z: 0.0 }, ..Default::default() },
        };
        assert_eq!(goal_in_fixed(&goal("odom", 0.4), "odom", &tf), Ok(Target { x: 0.4, y: 0.5, z: None }));
        assert_eq!(goal_in_fixed(&goal("", 0.4), "odom", &tf), Ok(Target { x: 0.4, y: 0.5, z: None }));
        assert_eq!(goal_in_fixed(&goal("base_link", 0.4), "odom", &tf), Ok(Target { x: 1.4, y: 2.5, z: None }));
        assert!(goal_in_fixed(&goal("nowhere", 0.4), "odom", &tf).unwrap_err().contains("nowhere"));
        assert!(goal_in_fixed(&goal("odom", f64::NAN), "odom", &tf).unwrap_err().contains("not finite"));
    }

    #[test]
    fn the_stage_keeps_the_latest_frame_and_hands_predictions_over_once() {
        let stage = FootholdStage::new(&FootholdParams { enabled: true, ..Default::default() }, &RouteParams::default());
        let k = Intrinsics::new(4, 3, 3.0, 3.0, 1.5, 1.0).unwrap();
        let frame = |sec: i32| FootholdFrame {
            depth: DepthImage::new(4, 3, vec![1.0; 12]).unwrap(),
            intrinsics: k,
            stamp: Time { sec, nanosec: 0 },
            fixed_from_camera: Isometry3::identity(),
            patch_holds: Vec::new(),
        };
        for sec in 1..=3 {
            stage.offer(frame(sec));
        }
        let Taken::Item(taken) = stage.frames.take_timeout(Duration::ZERO) else { panic!("a frame waits") };
        assert_eq!(taken.stamp.sec, 3, "the newest frame");
        let health = stage.health();
        assert_eq!((health.offered, health.dropped), (3, 2));
        assert!(stage.seed_priors);
        *stage.priors.lock().unwrap() = Some(vec![(Vector3::new(1.0, 2.0, 3.0), 0.8)]);
        assert_eq!(stage.take_priors().map(|p| p.len()), Some(1));
        assert_eq!(stage.take_priors(), None, "handed over once");
        stage.set_settings(StageSettings { threshold: 0.7, max_rate_hz: 5.0 });
        assert_eq!(stage.settings().map(|s| s.threshold), Some(0.7));
        assert_eq!(stage.health().max_rate_hz, 5.0);
        stage.close();
        assert!(matches!(stage.frames.take_timeout(Duration::from_secs(5)), Taken::Closed));
    }
}
