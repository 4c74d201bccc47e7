//! The simulated world of J 6.3 (Fig. 10): a table top with rocks, four distinct training rocks in
//! fixed places plus rocks not in the training set (deterministic from a seed).
//!
//! Rocks are smooth analytic solids whose top surfaces are the kinds of patches the mapper fits
//! (J Table 1 / IROS Table I): ellipsoid caps (elliptic paraboloid tops), paraboloid bumps (circular
//! or elliptic), flat-topped boulders with a tilted top (planes) and cylinders lying on the table
//! (cylindric paraboloids). Each solid has an exact ray intersection and exposes its ground-truth
//! foothold (top point, normal, principal curvatures) for tests and the demo.
//!
//! Frames: `world` is gravity aligned, z up (REP-103, like the mapper's `map`), the table top is the
//! plane z = 0. Each rock has a local frame `rock` (z up, origin on the table under its centre);
//! each robot station is a `base_link` pose on the table in front of one rock, facing it (+x).
//!
//! Instead of the table and rocks, a scene can be a terrain read from a file (a heightmap image or
//! a point cloud, see `terrain`), held as a [`Heightfield`] with exact ground truth.
//!
//! Here: the table, the scene layout, the ray cast over the whole scene and its ground truth
//! ([`Scene::height_at`], [`Scene::normal_at`], [`Scene::ray_hit`]); one rock (its shapes,
//! intersection and foothold) is in the `rock` module, a terrain's surface in `heightfield`, its
//! files next to a dataset in `ground_truth`.

pub mod ground_truth;
pub mod heightfield;
pub mod heightmap_png;
pub mod lzf;
pub mod pcd;
pub mod ply;
pub mod point_cloud;
mod rock;
pub mod terrain;

use std::sync::Arc;

use nalgebra::{Isometry3, Vector3};
use rand::{Rng, SeedableRng};
use serde::{Deserialize, Serialize};

pub use heightfield::{Heightfield, HeightfieldError};
use rock::T_MIN;
pub use rock::{Foothold, Hit, Ray, Rock, RockShape, ShapeError};
pub use terrain::{TerrainConfig, TerrainError};

/// Most rocks a scene holds (every rock has its own station along the table; a config asking for
/// more is a typo, and generating them would stall the simulator's start).
pub const MAX_ROCKS: usize = 1000;

/// Errors building a scene from its configuration.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum SceneError {
    #[error("invalid rock {name:?}: {reason}")]
    InvalidRock { name: String, reason: ShapeError },
    #[error("invalid scene: {0}")]
    Invalid(String),
    #[error("no rock with index {index} (the scene has {count})")]
    NoSuchRock { index: usize, count: usize },
    #[error(transparent)]
    Terrain(#[from] TerrainError),
}

/// The table and the floor around it.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TableConfig {
    /// Table top extent along x (m), from x = 0.
    pub length_x_m: f64,
    /// Height of the table top above the floor (m); the floor is the plane z = −height.
    pub height_m: f64,
    /// Margin (m) of table beyond the first and last station along y.
    pub margin_y_m: f64,
}

impl Default for TableConfig {
    fn default() -> Self {
        // A lab walking table (J Fig. 10); sizes chosen so the camera in the lookdown pose sees
        // only table top around the rock.
        Self { length_x_m: 2.0, height_m: 0.75, margin_y_m: 0.4 }
    }
}

/// Scene layout and the untrained-rock generator.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SceneConfig {
    pub table: TableConfig,
    /// x of the rock centres on the table (m).
    pub rock_x_m: f64,
    /// Spacing of the stations along y (m); rock i sits at y = (i + ½)·spacing.
    pub station_spacing_m: f64,
    /// Distance (m) from the robot's `base_link` to the rock centre when placed in front of it.
    pub standoff_m: f64,
    /// The four training rocks (J 6.3: "4 solid rocks in fixed positions"); `None` = the built-in set.
    pub training_rocks: Option<Vec<RockShape>>,
    /// Number of procedurally generated rocks not in the training set.
    pub untrained_rocks: usize,
    /// Training rocks (by index) to duplicate as untrained rocks with identical geometry, the case
    /// where J 6.3 still executes the motion.
    pub twins_of_training: Vec<usize>,
    /// A terrain file instead of the table and rocks (`terrain.path` empty = table and rocks).
    pub terrain: TerrainConfig,
}

impl Default for SceneConfig {
    fn default() -> Self {
        Self {
            table: TableConfig::default(),
            rock_x_m: 0.9,
            station_spacing_m: 0.6,
            standoff_m: 0.28,
            training_rocks: None,
            untrained_rocks: 4,
            twins_of_training: Vec::new(),
            terrain: TerrainConfig::default(),
        }
    }
}

/// The four built-in training rocks: one per patch family the RPBP trained on (J 6.3, Fig. 10).
/// Each top is a valid foothold for J's validation: curvatures inside [κmin, κmax] =
/// [−13.6, 19.7] m⁻¹ (J 3.3.3) with room for the fit's noise, and wide enough for a foot-size
/// (r = 0.05 m) patch. The tops stand 3.5, 5, 6.5 and 8 cm high: the robot meets each at the same
/// spot, so the heights (1.5 cm apart, above J's rs = 0.01 m) keep a plane or a gentle cap on one
/// rock from matching another rock's trained patch.
pub fn default_training_rocks() -> Vec<RockShape> {
    vec![
        // rock 1: half ellipsoid, elliptic paraboloid top κ ≈ (−5.5, −9.6) m⁻¹: both curvatures
        // and their difference clearly non-zero for a foot-size patch (a flatter cap comes out
        // cylindric or elliptic from frame to frame, and J 6.3 matches on the type).
        RockShape::EllipsoidCap { semi_axes_m: [0.095, 0.072, 0.05], centre_z_m: 0.0 },
        // rock 2: flat-topped boulder 8 cm high, top tilted ≈ 8° down towards the robot.
        RockShape::FlatBoulder { radius_m: 0.07, height_m: 0.08, top_slope: [0.14, 0.0] },
        // rock 3: half-buried log across the robot's path, top 6.5 cm high, κ = (0, −11.1) m⁻¹.
        RockShape::LyingCylinder { radius_m: 0.09, length_m: 0.22, sunk_m: 0.115 },
        // rock 4: low round bump 3.5 cm high, circular paraboloid top κ = (−10, −10) m⁻¹.
        RockShape::ParaboloidBump { height_m: 0.035, curvatures_per_m: [10.0, 10.0] },
    ]
}

/// The whole scene: table, floor and rocks, or a terrain.
#[derive(Debug, Clone)]
pub struct Scene {
    pub table: TableConfig,
    /// Table top y extent `[min, max]`.
    pub table_y_m: [f64; 2],
    pub rocks: Vec<Rock>,
    /// A terrain from a file: when set it replaces the table and the floor (and the scene has no rocks).
    pub terrain: Option<Arc<Heightfield>>,
}

/// What a world ray hit.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Surface {
    Table,
    Floor,
    Rock(usize),
    Terrain,
}

/// Height above which [`Scene::height_at`] starts its downward ray in a rock scene (m).
const PROBE_HEIGHT_M: f64 = 100.0;

impl Scene {
    /// Builds the scene: the terrain file if one is configured, else training rocks (yaw 0, except the lying cylinder turned across the robot's
    /// path) then `untrained_rocks` random ones and the twins, each at its own station.
    pub fn new(config: &SceneConfig, seed: u64) -> Result<Self, SceneError> {
        if config.terrain.is_set() {
            return Ok(Self::from_terrain(config.terrain.load()?));
        }
        if !(config.station_spacing_m > 0.0 && config.standoff_m > 0.0 && config.table.length_x_m > config.rock_x_m) {
            return Err(SceneError::Invalid("need station_spacing_m > 0, standoff_m > 0 and rock_x_m inside the table".into()));
        }
        let training = config.training_rocks.clone().unwrap_or_else(default_training_rocks);
        let count = training.len().saturating_add(config.untrained_rocks).saturating_add(config.twins_of_training.len());
        if count > MAX_ROCKS {
            return Err(SceneError::Invalid(format!(
                "{count} rocks (training_rocks + untrained_rocks + twins_of_training); at most {MAX_ROCKS}, one station each"
            )));
        }
        let mut shapes: Vec<(String, RockShape, bool, f64)> = Vec::new();
        for (i, shape) in training.iter().enumerate() {
            let yaw = if matches!(shape, RockShape::LyingCylinder { .. }) { std::f64::consts::FRAC_PI_2 } else { 0.0 };
            shapes.push((format!("rock {}", i + 1), *shape, true, yaw));
        }
        let mut rng = rand::rngs::StdRng::seed_from_u64(seed ^ 0x5eed_0f7e_44a1);
        for i in 0..config.untrained_rocks {
            let shape = random_untrained_shape(&mut rng, &training);
            let yaw = rng.random_range(-std::f64::consts::PI..std::f64::consts::PI);
            shapes.push((format!("untrained {}", i + 1), shape, false, yaw));
        }
        for &index in &config.twins_of_training {
            let (_, shape, _, yaw) =
                shapes.get(index).filter(|entry| entry.2).cloned().ok_or(SceneError::NoSuchRock { index, count: training.len() })?;
            shapes.push((format!("twin of rock {}", index + 1), shape, false, yaw));
        }
        let mut rocks = Vec::with_capacity(shapes.len());
        for (i, (name, shape, trained, yaw)) in shapes.into_iter().enumerate() {
            let y = (i as f64 + 0.5) * config.station_spacing_m;
            rocks.push(Rock::new(&name, shape, trained, config.rock_x_m, y, yaw, config.standoff_m)?);
        }
        let y_max = rocks.len() as f64 * config.station_spacing_m;
        Ok(Self { table: config.table, table_y_m: [-config.table.margin_y_m, y_max + config.table.margin_y_m], rocks, terrain: None })
    }

    /// A scene that is only `terrain` (no table, floor or rocks).
    pub fn from_terrain(terrain: Heightfield) -> Self {
        Self { table: TableConfig::default(), table_y_m: [0.0, 0.0], rocks: Vec::new(), terrain: Some(Arc::new(terrain)) }
    }

    /// Ground truth: height (m, world z) of the topmost surface above `(x, y)`; `None` where there
    /// is none (outside a terrain, in its holes). Exact: the terrain's bilinear surface, or in a
    /// rock scene the analytic solids cut by a vertical ray.
    pub fn height_at(&self, x: f64, y: f64) -> Option<f64> {
        match &self.terrain {
            Some(terrain) => terrain.height_at(x, y),
            None => self.ray_hit(&Self::probe(x, y)).map(|hit| PROBE_HEIGHT_M - hit.t),
        }
    }

    /// Ground truth: upward unit normal of the topmost surface at `(x, y)`.
    pub fn normal_at(&self, x: f64, y: f64) -> Option<Vector3<f64>> {
        match &self.terrain {
            Some(terrain) => terrain.normal_at(x, y),
            None => self.ray_hit(&Self::probe(x, y)).map(|hit| hit.normal),
        }
    }

    /// Ground truth: nearest hit (ray parameter, outward normal) of a world ray with anything in the scene.
    pub fn ray_hit(&self, ray: &Ray) -> Option<Hit> {
        self.intersect(ray, |_| true).map(|(hit, _)| hit)
    }

    fn probe(x: f64, y: f64) -> Ray {
        Ray { origin: Vector3::new(x, y, PROBE_HEIGHT_M), direction: -Vector3::z() }
    }

    /// `world_from_base` of the station in front of rock `index`.
    pub fn station(&self, index: usize) -> Result<Isometry3<f64>, SceneError> {
        self.rocks.get(index).map(|rock| rock.world_from_station).ok_or(SceneError::NoSuchRock { index, count: self.rocks.len() })
    }

    /// Nearest hit of a world ray among table/floor and the rocks for which `consider(i)` is true.
    pub fn intersect(&self, ray: &Ray, consider: impl Fn(usize) -> bool) -> Option<(Hit, Surface)> {
        self.intersect_among(ray, (0..self.rocks.len()).filter(|&i| consider(i)))
    }

    /// Nearest hit of a world ray among table/floor and the rocks with the given indices (unknown
    /// indices are ignored).
    #[inline]
    pub fn intersect_among(&self, ray: &Ray, rocks: impl IntoIterator<Item = usize>) -> Option<(Hit, Surface)> {
        let mut best = self.intersect_ground(ray);
        for i in rocks {
            let Some(rock) = self.rocks.get(i) else { continue };
            if let Some(hit) = rock.intersect_world(ray) {
                if best.is_none_or(|(b, _)| hit.t < b.t) {
                    best = Some((hit, Surface::Rock(i)));
                }
            }
        }
        best
    }

    /// Hit with the terrain if there is one, else with the table top (z = 0 inside its extent) or
    /// else the floor (z = −height).
    #[inline]
    pub fn intersect_ground(&self, ray: &Ray) -> Option<(Hit, Surface)> {
        if let Some(terrain) = &self.terrain {
            return terrain.intersect(ray).map(|hit| (hit, Surface::Terrain));
        }
        if ray.direction.z >= 0.0 {
            return None;
        }
        let t = -ray.origin.z / ray.direction.z;
        if t > T_MIN {
            let p = ray.at(t);
            if (0.0..=self.table.length_x_m).contains(&p.x) && (self.table_y_m[0]..=self.table_y_m[1]).contains(&p.y) {
                return Some((Hit { t, normal: Vector3::z() }, Surface::Table));
            }
        }
        let t = (-self.table.height_m - ray.origin.z) / ray.direction.z;
        (t > T_MIN).then_some((Hit { t, normal: Vector3::z() }, Surface::Floor))
    }
}

/// A random rock not in the training set: kind and size drawn uniformly, rejected while its top is
/// within 2·rs in height of a training rock's top ([`similar_tops`]), so it should not match.
fn random_untrained_shape(rng: &mut impl Rng, training: &[RockShape]) -> RockShape {
    let mut candidate = RockShape::EllipsoidCap { semi_axes_m: [0.11, 0.08, 0.13], centre_z_m: 0.0 };
    for _ in 0..100 {
        candidate = match rng.random_range(0..4) {
            0 => RockShape::EllipsoidCap {
                semi_axes_m: [rng.random_range(0.05..0.12), rng.random_range(0.04..0.10), rng.random_range(0.02..0.14)],
                centre_z_m: rng.random_range(-0.015..0.0),
            },
            1 => RockShape::FlatBoulder {
                radius_m: rng.random_range(0.04..0.10),
                height_m: rng.random_range(0.03..0.14),
                top_slope: [rng.random_range(-0.35..0.35), rng.random_range(-0.35..0.35)],
            },
            2 => RockShape::LyingCylinder { radius_m: rng.random_range(0.025..0.07), length_m: rng.random_range(0.12..0.25), sunk_m: 0.0 },
            _ => RockShape::ParaboloidBump {
                height_m: rng.random_range(0.03..0.14),
                curvatures_per_m: [rng.random_range(5.0..40.0), rng.random_range(5.0..40.0)],
            },
        };
        if candidate.validate().is_ok() && !training.iter().any(|t| similar_tops(t, &candidate)) {
            break;
        }
    }
    candidate
}

/// Whether two shapes have tops that the J 6.3 matcher could confuse (loose test, for generation).
/// The robot meets every rock at the same spot, so a top's height is its position relative to the
/// robot; tops within 2·rs of each other in height are confusable whatever their shapes (a narrow or
/// steep top still yields plane-like patches on its flanks at about that height, and foot-size
/// patches on tops wider than the foot have the same boundary whatever the rock's size).
fn similar_tops(a: &RockShape, b: &RockShape) -> bool {
    (a.local_foothold().top_in_world.z - b.local_foothold().top_in_world.z).abs() < 0.02
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    pub(crate) fn down_ray(x: f64, y: f64) -> Ray {
        Ray { origin: Vector3::new(x, y, 1.0), direction: -Vector3::z() }
    }

    #[test]
    fn scene_is_deterministic_and_untrained_rocks_differ() {
        let config = SceneConfig { untrained_rocks: 6, twins_of_training: vec![0], ..SceneConfig::default() };
        let a = Scene::new(&config, 7).unwrap();
        let b = Scene::new(&config, 7).unwrap();
        let c = Scene::new(&config, 8).unwrap();
        assert_eq!(a.rocks, b.rocks);
        assert_ne!(a.rocks, c.rocks);
        assert_eq!(a.rocks.len(), 11);
        assert_eq!(a.rocks.iter().filter(|r| r.trained).count(), 4);
        let training = default_training_rocks();
        for rock in a.rocks.iter().filter(|r| r.name.starts_with("untrained")) {
            assert!(!training.iter().any(|t| similar_tops(t, &rock.shape)), "{rock:?}");
        }
        assert_eq!(a.rocks[10].shape, a.rocks[0].shape);
        // Station faces the rock from `standoff` behind.
        let station = a.station(2).unwrap();
        let rock = a.rocks[2].world_from_rock.translation.vector;
        assert!((rock - station.translation.vector - Vector3::new(0.28, 0.0, 0.0)).norm() < 1e-12);
        assert_eq!(a.station(99), Err(SceneError::NoSuchRock { index: 99, count: 11 }));
    }

    #[test]
    fn ground_is_table_then_floor() {
        let scene = Scene::new(&SceneConfig::default(), 1).unwrap();
        let (hit, surface) = scene.intersect_ground(&down_ray(0.5, 0.0)).unwrap();
        assert_eq!(surface, Surface::Table);
        assert!((hit.t - 1.0).abs() < 1e-12);
        let (hit, surface) = scene.intersect_ground(&down_ray(-0.5, 0.0)).unwrap();
        assert_eq!(surface, Surface::Floor);
        assert!((hit.t - 1.75).abs() < 1e-12);
        // Rocks occlude the table.
        let rock = scene.rocks[0].foothold().top_in_world;
        let (_, surface) = scene.intersect(&down_ray(rock.x, rock.y), |_| true).unwrap();
        assert_eq!(surface, Surface::Rock(0));
    }

    #[test]
    fn invalid_shapes_are_errors() {
        let bad = RockShape::EllipsoidCap { semi_axes_m: [0.1, -0.1, 0.1], centre_z_m: 0.0 };
        assert!(matches!(Rock::new("x", bad, false, 0.0, 0.0, 0.0, 0.2), Err(SceneError::InvalidRock { .. })));
        let config = SceneConfig { twins_of_training: vec![7], ..SceneConfig::default() };
        assert!(Scene::new(&config, 1).is_err());
    }
}
