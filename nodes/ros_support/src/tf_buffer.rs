//! A transform tree as tf2 keeps it (ROS-free): static transforms valid at every time, dynamic ones
//! with a bounded history, each frame with one parent. [`TfBuffer::lookup`] gives
//! `target_from_source` at a stamp through the tree (up from both frames to their common ancestor),
//! interpolating every dynamic link between its two neighbouring samples (translation linearly,
//! rotation by slerp, as tf2's `TimeCache` does). Names follow the `world_from_camera` convention: the
//! isometry maps a point given in the child (source) frame into the parent (target) frame.
//!
//! Frame ids are compared without a leading `/` (tf2 strips it too).

use std::collections::{HashMap, VecDeque};

use nalgebra::Isometry3;

/// How long a dynamic link's history reaches back from its newest sample (tf2's default cache time).
pub const DEFAULT_CACHE_NS: i64 = 10_000_000_000;

/// The deepest chain a lookup follows; a longer walk means a cycle in the data.
const MAX_DEPTH: usize = 64;

/// When a transform is wanted.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LookupTime {
    /// The newest time every dynamic link of the chain has (tf2's `TimePointZero`).
    Latest,
    /// This stamp (ns since the clock's epoch).
    At(i64),
}

/// Why a transform cannot be looked up or stored.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TfError {
    #[error("frame {0:?} is not in the transform tree")]
    UnknownFrame(String),
    #[error("frames {target:?} and {source_frame:?} are not connected (different trees)")]
    NotConnected { target: String, source_frame: String },
    #[error("transform {parent:?} → {child:?} at {stamp_s:.6} s: outside its history [{first_s:.6}, {last_s:.6}] s")]
    Extrapolation { parent: String, child: String, stamp_s: f64, first_s: f64, last_s: f64 },
    #[error("transform {parent:?} → {child:?} refused: {reason}")]
    Invalid { parent: String, child: String, reason: String },
    #[error("the transform tree has a cycle through {0:?}")]
    Cycle(String),
}

#[derive(Debug, Clone)]
struct Sample {
    stamp_ns: i64,
    parent_from_child: Isometry3<f64>,
}

#[derive(Debug, Clone)]
enum Link {
    Static { parent: String, parent_from_child: Isometry3<f64> },
    Dynamic { parent: String, history: VecDeque<Sample> },
}

impl Link {
    fn parent(&self) -> &str {
        match self {
            Link::Static { parent, .. } | Link::Dynamic { parent, .. } => parent,
        }
    }
}

/// The tree: one link per child frame.
#[derive(Debug, Clone)]
pub struct TfBuffer {
    links: HashMap<String, Link>,
    cache_ns: i64,
}

impl Default for TfBuffer {
    fn default() -> Self {
        Self::new(DEFAULT_CACHE_NS)
    }
}

fn frame(id: &str) -> &str {
    id.trim_start_matches('/')
}

fn seconds(ns: i64) -> f64 {
    ns as f64 * 1e-9
}

impl TfBuffer {
    /// An empty tree keeping `cache_ns` of history per dynamic link.
    pub fn new(cache_ns: i64) -> Self {
        Self { links: HashMap::new(), cache_ns: cache_ns.max(0) }
    }

    fn check(parent: &str, child: &str, parent_from_child: &Isometry3<f64>) -> Result<(), TfError> {
        let invalid = |reason: &str| TfError::Invalid { parent: parent.to_string(), child: child.to_string(), reason: reason.to_string() };
        if parent.is_empty() || child.is_empty() {
            return Err(invalid("empty frame id"));
        }
        if parent == child {
            return Err(invalid("a frame cannot be its own parent"));
        }
        let finite = parent_from_child.translation.vector.iter().chain(parent_from_child.rotation.coords.iter()).all(|v| v.is_finite());
        if !finite {
            return Err(invalid("non-finite translation or rotation"));
        }
        Ok(())
    }

    /// A static transform (`/tf_static`): valid at every time, replacing whatever `child` had.
    pub fn set_static(&mut self, parent: &str, child: &str, parent_from_child: Isometry3<f64>) -> Result<(), TfError> {
        let (parent, child) = (frame(parent), frame(child));
        Self::check(parent, child, &parent_from_child)?;
        self.links.insert(child.to_string(), Link::Static { parent: parent.to_string(), parent_from_child });
        Ok(())
    }

    /// A dynamic transform (`/tf`) at `stamp_ns`. A sample older than the newest one is inserted in
    /// order; a new parent restarts the history (the frame was re-parented); samples older than the
    /// cache time behind the newest are dropped.
    pub fn set_dynamic(&mut self, parent: &str, child: &str, stamp_ns: i64, parent_from_child: Isometry3<f64>) -> Result<(), TfError> {
        let (parent, child) = (frame(parent), frame(child));
        Self::check(parent, child, &parent_from_child)?;
        let sample = Sample { stamp_ns, parent_from_child };
        let cache_ns = self.cache_ns;
        match self.links.get_mut(child) {
            Some(Link::Dynamic { parent: p, history }) if p == parent => {
                let at = history.partition_point(|s| s.stamp_ns < stamp_ns);
                match history.get_mut(at) {
                    Some(existing) if existing.stamp_ns == stamp_ns => *existing = sample,
                    _ => history.insert(at, sample),
                }
                let newest = history.back().map_or(stamp_ns, |s| s.stamp_ns);
                while history.len() > 1 && history.front().is_some_and(|s| s.stamp_ns < newest.saturating_sub(cache_ns)) {
                    history.pop_front();
                }
            }
            _ => {
                self.links.insert(child.to_string(), Link::Dynamic { parent: parent.to_string(), history: VecDeque::from([sample]) });
            }
        }
        Ok(())
    }

    /// Forget every dynamic transform (a clock jumped back, e.g. a bag restarted); static ones stay.
    pub fn clear_dynamic(&mut self) {
        self.links.retain(|_, link| matches!(link, Link::Static { .. }));
    }

    /// Whether `frame_id` appears in the tree (as a child or a parent).
    pub fn has_frame(&self, frame_id: &str) -> bool {
        let id = frame(frame_id);
        self.links.contains_key(id) || self.links.values().any(|l| l.parent() == id)
    }

    /// The parent of `frame_id`, if it has one.
    pub fn parent_of(&self, frame_id: &str) -> Option<&str> {
        self.links.get(frame(frame_id)).map(Link::parent)
    }

    /// Frames from `frame_id` up to its root (itself first).
    fn path_to_root(&self, frame_id: &str) -> Result<Vec<String>, TfError> {
        let mut path = vec![frame_id.to_string()];
        let mut current = frame_id;
        while let Some(link) = self.links.get(current) {
            if path.len() > MAX_DEPTH {
                return Err(TfError::Cycle(frame_id.to_string()));
            }
            current = link.parent();
            path.push(current.to_string());
        }
        Ok(path)
    }

    /// The links from `source` and `target` up to their common ancestor.
    fn chain(&self, target: &str, source: &str) -> Result<(Vec<String>, Vec<String>), TfError> {
        for id in [target, source] {
            if !self.has_frame(id) {
                return Err(TfError::UnknownFrame(id.to_string()));
            }
        }
        let up_from_source = self.path_to_root(source)?;
        let up_from_target = self.path_to_root(target)?;
        let common = up_from_source
            .iter()
            .find(|f| up_from_target.contains(f))
            .cloned()
            .ok_or_else(|| TfError::NotConnected { target: target.to_string(), source_frame: source.to_string() })?;
        let cut = |path: Vec<String>| -> Vec<String> { path.into_iter().take_while(|f| *f != common).collect() };
        Ok((cut(up_from_source), cut(up_from_target)))
    }

    /// `parent_from_child` of the link of `child` at `stamp_ns`.
    fn link_at(&self, child: &str, stamp_ns: i64) -> Result<Isometry3<f64>, TfError> {
        match self.links.get(child) {
            None => Err(TfError::UnknownFrame(child.to_string())),
            Some(Link::Static { parent_from_child, .. }) => Ok(*parent_from_child),
            Some(Link::Dynamic { parent, history }) => interpolate(parent, child, history, stamp_ns),
        }
    }

    /// The newest stamp at which every dynamic link of the chain has data (`None`: all static).
    fn latest_common(&self, links: &[String]) -> Option<i64> {
        links
            .iter()
            .filter_map(|child| match self.links.get(child) {
                Some(Link::Dynamic { history, .. }) => history.back().map(|s| s.stamp_ns),
                _ => None,
            })
            .min()
    }

    /// `target_from_source` at `time`: maps a point given in `source` into `target`.
    pub fn lookup(&self, target: &str, source: &str, time: LookupTime) -> Result<Isometry3<f64>, TfError> {
        let (target, source) = (frame(target), frame(source));
        let (from_source, from_target) = self.chain(target, source)?;
        let stamp_ns = match time {
            LookupTime::At(stamp_ns) => stamp_ns,
            LookupTime::Latest => {
                let all: Vec<String> = from_source.iter().chain(from_target.iter()).cloned().collect();
                self.latest_common(&all).unwrap_or(0)
            }
        };
        // ancestor_from_source = link(s1→a)·…·link(source→s1), likewise for the target.
        let up = |path: &[String]| -> Result<Isometry3<f64>, TfError> {
            path.iter().try_fold(Isometry3::identity(), |child_side, child| Ok(self.link_at(child, stamp_ns)? * child_side))
        };
        let ancestor_from_source = up(&from_source)?;
        let ancestor_from_target = up(&from_target)?;
        Ok(ancestor_from_target.inverse() * ancestor_from_source)
    }

    /// Whether [`TfBuffer::lookup`] would succeed.
    pub fn can_lookup(&self, target: &str, source: &str, time: LookupTime) -> bool {
        self.lookup(target, source, time).is_ok()
    }
}

/// The sample at `stamp_ns`, interpolated between its neighbours; a single sample is valid only at
/// its own stamp (tf2 does not extrapolate either).
fn interpolate(parent: &str, child: &str, history: &VecDeque<Sample>, stamp_ns: i64) -> Result<Isometry3<f64>, TfError> {
    let (Some(first), Some(last)) = (history.front(), history.back()) else {
        return Err(TfError::UnknownFrame(child.to_string()));
    };
    if stamp_ns < first.stamp_ns || stamp_ns > last.stamp_ns {
        return Err(TfError::Extrapolation {
            parent: parent.to_string(),
            child: child.to_string(),
            stamp_s: seconds(stamp_ns),
            first_s: seconds(first.stamp_ns),
            last_s: seconds(last.stamp_ns),
        });
    }
    let after = history.partition_point(|s| s.stamp_ns < stamp_ns);
    let Some(b) = history.get(after) else {
        return Ok(last.parent_from_child);
    };
    if b.stamp_ns == stamp_ns || after == 0 {
        return Ok(b.parent_from_child);
    }
    let Some(a) = history.get(after - 1) else {
        return Ok(b.parent_from_child);
    };
    let s = (stamp_ns - a.stamp_ns) as f64 / (b.stamp_ns - a.stamp_ns) as f64;
    Ok(a.parent_from_child.lerp_slerp(&b.parent_from_child, s))
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Point3, Translation3, UnitQuaternion, Vector3};

    fn iso(x: f64, y: f64, z: f64, yaw: f64) -> Isometry3<f64> {
        Isometry3::from_parts(Translation3::new(x, y, z), UnitQuaternion::from_euler_angles(0.0, 0.0, yaw))
    }

    fn close(a: &Isometry3<f64>, b: &Isometry3<f64>) -> bool {
        (a.translation.vector - b.translation.vector).norm() < 1e-9 && a.rotation.angle_to(&b.rotation) < 1e-9
    }

    /// odom → base_link (dynamic) → camera_link → camera_optical, camera_link → imu (static).
    fn robot() -> (TfBuffer, Isometry3<f64>, Isometry3<f64>, Isometry3<f64>) {
        let mut tf = TfBuffer::default();
        let base_from_camera_link =
            Isometry3::from_parts(Translation3::new(0.04, 0.0, 0.17), UnitQuaternion::from_euler_angles(0.0, 0.85, 0.0));
        let camera_link_from_optical = Isometry3::from_parts(
            Translation3::identity(),
            UnitQuaternion::from_euler_angles(-std::f64::consts::FRAC_PI_2, 0.0, -std::f64::consts::FRAC_PI_2),
        );
        let camera_link_from_imu = iso(0.0, 0.0, 0.015, 0.0);
        tf.set_static("base_link", "camera_link", base_from_camera_link).unwrap();
        tf.set_static("camera_link", "camera_optical", camera_link_from_optical).unwrap();
        tf.set_static("/camera_link", "imu", camera_link_from_imu).unwrap();
        tf.set_dynamic("odom", "base_link", 1_000_000_000, iso(0.0, 0.0, 0.0, 0.0)).unwrap();
        tf.set_dynamic("odom", "base_link", 2_000_000_000, iso(1.0, 0.0, 0.0, 1.0)).unwrap();
        (tf, base_from_camera_link, camera_link_from_optical, camera_link_from_imu)
    }

    #[test]
    fn lookups_compose_the_chain_through_the_common_ancestor() {
        let (tf, base_from_link, link_from_optical, link_from_imu) = robot();
        let at = LookupTime::At(2_000_000_000);
        let odom_from_optical = tf.lookup("odom", "camera_optical", at).unwrap();
        assert!(close(&odom_from_optical, &(iso(1.0, 0.0, 0.0, 1.0) * base_from_link * link_from_optical)));
        // Sibling frames: through camera_link only, no dynamic link, so valid at any time.
        let optical_from_imu = tf.lookup("camera_optical", "imu", LookupTime::At(-5)).unwrap();
        assert!(close(&optical_from_imu, &(link_from_optical.inverse() * link_from_imu)));
        // The inverse direction is the inverse transform.
        let imu_from_odom = tf.lookup("imu", "odom", at).unwrap();
        assert!(close(&imu_from_odom, &tf.lookup("odom", "imu", at).unwrap().inverse()));
        // A point 1 m ahead of the camera lands ahead of the robot in odom.
        let p = odom_from_optical * Point3::new(0.0, 0.0, 1.0);
        assert!(p.z < 0.17 && p.coords.norm() > 1.0);
        assert!(close(&tf.lookup("odom", "odom", at).unwrap(), &Isometry3::identity()));
    }

    #[test]
    fn dynamic_links_interpolate_and_do_not_extrapolate() {
        let (tf, ..) = robot();
        let mid = tf.lookup("odom", "base_link", LookupTime::At(1_500_000_000)).unwrap();
        assert!((mid.translation.vector - Vector3::new(0.5, 0.0, 0.0)).norm() < 1e-12);
        assert!((mid.rotation.angle() - 0.5).abs() < 1e-12);
        let early = tf.lookup("odom", "camera_optical", LookupTime::At(999_999_999)).unwrap_err();
        assert!(matches!(early, TfError::Extrapolation { ref child, .. } if child == "base_link"), "{early}");
        assert!(early.to_string().contains("outside its history"));
        // Latest = the newest stamp of the chain's dynamic link.
        let latest = tf.lookup("base_link", "odom", LookupTime::Latest).unwrap();
        assert!(close(&latest, &iso(1.0, 0.0, 0.0, 1.0).inverse()));
    }

    #[test]
    fn unknown_and_disconnected_frames_are_named() {
        let (mut tf, ..) = robot();
        assert_eq!(tf.lookup("odom", "nowhere", LookupTime::Latest).unwrap_err(), TfError::UnknownFrame("nowhere".into()));
        tf.set_static("map", "other", iso(0.0, 0.0, 0.0, 0.0)).unwrap();
        assert!(matches!(tf.lookup("odom", "other", LookupTime::Latest), Err(TfError::NotConnected { .. })));
        assert!(matches!(tf.set_static("a", "a", Isometry3::identity()), Err(TfError::Invalid { .. })));
        let nan = Isometry3::from_parts(Translation3::new(f64::NAN, 0.0, 0.0), UnitQuaternion::identity());
        assert!(tf.set_dynamic("odom", "base_link", 3, nan).unwrap_err().to_string().contains("non-finite"));
        assert_eq!(tf.parent_of("camera_optical"), Some("camera_link"));
    }

    #[test]
    fn history_is_ordered_bounded_and_restarted_by_a_new_parent() {
        let mut tf = TfBuffer::new(1_000);
        for stamp in [30, 10, 20, 20] {
            tf.set_dynamic("odom", "base_link", stamp, iso(stamp as f64, 0.0, 0.0, 0.0)).unwrap();
        }
        let at_15 = tf.lookup("odom", "base_link", LookupTime::At(15)).unwrap();
        assert!((at_15.translation.x - 15.0).abs() < 1e-12);
        tf.set_dynamic("odom", "base_link", 5_000, iso(0.0, 0.0, 0.0, 0.0)).unwrap();
        assert!(matches!(tf.lookup("odom", "base_link", LookupTime::At(20)), Err(TfError::Extrapolation { .. })));
        tf.set_dynamic("map", "base_link", 6_000, iso(2.0, 0.0, 0.0, 0.0)).unwrap();
        assert_eq!(tf.parent_of("base_link"), Some("map"));
        assert!(!tf.has_frame("odom"));
        tf.clear_dynamic();
        assert!(!tf.has_frame("base_link"));
    }

    #[test]
    fn a_cycle_is_reported_not_followed_forever() {
        let mut tf = TfBuffer::default();
        tf.set_static("a", "b", iso(1.0, 0.0, 0.0, 0.0)).unwrap();
        tf.set_static("b", "a", iso(1.0, 0.0, 0.0, 0.0)).unwrap();
        tf.set_static("a", "c", iso(1.0, 0.0, 0.0, 0.0)).unwrap();
        assert!(matches!(tf.lookup("c", "b", LookupTime::Latest), Err(TfError::Cycle(_))));
    }
}
