//! Patch matching of J 6.3: every map patch (pose in `base_link`) against every trained patch,
//! checking (1) same surface type, (2) |Δ boundary params| < ds, (3) |Δ curvatures| < ks, (4) angle
//! between normals < as over the patch's discrete symmetries, (5) |Δ position| < rs. Returns the best
//! match and, for diagnostics, why the nearest candidates failed.
//!
//! Discrete symmetries: the same geometry has several parameter vectors. For ellipse and rectangle
//! boundaries a quarter turn about the local z swaps (d_x, d_y) and (κ_x, κ_y) and a half turn leaves
//! them unchanged; for every type, a half turn about the local x flips the normal and negates the
//! curvatures (z' = −z). Each trained patch is expanded into these equivalents once
//! ([`Matcher::new`]); a map patch matches if any equivalent passes (2)–(4).
//!
//! Speed: trained patches are sorted by their x coordinate in `base_link`, so each map patch only
//! visits the trained ones within ±rs in x (criterion 5 is the most selective), then checks the full
//! distance, the type and the remaining criteria.

use nalgebra::{Rotation3, Vector3};
use serde::{Deserialize, Serialize};

use patchwalk_spl::patch::{BoundaryType, Patch, SurfaceType};

/// How criterion (4) compares orientations.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum OrientationCheck {
    /// Angle between the normals (local z axes), as in J 6.3 (4).
    Normal,
    /// Full relative rotation angle (normal and in-plane heading), modulo the discrete symmetries.
    Frame,
}

/// Thresholds of J 6.3 (all configurable).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MatcherConfig {
    /// ds: max |Δ boundary parameter| (m), J 6.3 (2): 0.015 m.
    pub boundary_tolerance_m: f64,
    /// ks: max |Δ curvature| (1/m), J 6.3 (3): 5 m⁻¹.
    pub curvature_tolerance_per_m: f64,
    /// as: max angle between normals (deg), J 6.3 (4): 20°.
    pub normal_tolerance_deg: f64,
    /// rs: max distance between positions relative to the robot (m), J 6.3 (5): 0.01 m.
    pub position_tolerance_m: f64,
    /// Criterion (4) variant; J 6.3 compares normals.
    pub orientation: OrientationCheck,
    /// Consider the normal flip (half turn about local x, curvatures negated); J 6.3 "every possible symmetry".
    pub allow_normal_flip: bool,
    /// How many failed nearest candidates to explain in a report.
    pub diagnostics: usize,
}

impl Default for MatcherConfig {
    fn default() -> Self {
        Self {
            boundary_tolerance_m: 0.015,
            curvature_tolerance_per_m: 5.0,
            normal_tolerance_deg: 20.0,
            position_tolerance_m: 0.01,
            orientation: OrientationCheck::Normal,
            allow_normal_flip: true,
            diagnostics: 3,
        }
    }
}

impl MatcherConfig {
    /// All tolerances must be positive and finite.
    pub fn validate(&self) -> Result<(), crate::config::InvalidSetting> {
        for (name, value) in [
            ("matcher.boundary_tolerance_m", self.boundary_tolerance_m),
            ("matcher.curvature_tolerance_per_m", self.curvature_tolerance_per_m),
            ("matcher.normal_tolerance_deg", self.normal_tolerance_deg),
            ("matcher.position_tolerance_m", self.position_tolerance_m),
        ] {
            if !(value.is_finite() && value > 0.0) {
                return Err(crate::config::InvalidSetting { key: name, rule: "must be positive", value });
            }
        }
        Ok(())
    }
}

/// Why a (map, trained) pair did not match: the first failed criterion of J 6.3 with its value.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub enum Rejection {
    /// (1) surface types differ.
    SurfaceType { map: SurfaceType, trained: SurfaceType },
    /// (2) boundary types differ (their parameters are not comparable).
    BoundaryType { map: BoundaryType, trained: BoundaryType },
    /// (2) largest |Δd| over the best symmetry (m).
    BoundaryParams { max_abs_diff_m: f64 },
    /// (3) largest |Δk| over the best symmetry (1/m).
    Curvature { max_abs_diff_per_m: f64 },
    /// (4) smallest normal (or frame) angle over the symmetries (deg).
    Orientation { angle_deg: f64 },
    /// (5) distance between the centres (m).
    Position { distance_m: f64 },
}

impl std::fmt::Display for Rejection {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Rejection::SurfaceType { map, trained } => write!(f, "surface type {map:?} != trained {trained:?}"),
            Rejection::BoundaryType { map, trained } => write!(f, "boundary type {map:?} != trained {trained:?}"),
            Rejection::BoundaryParams { max_abs_diff_m } => write!(f, "boundary params differ by {max_abs_diff_m:.4} m"),
            Rejection::Curvature { max_abs_diff_per_m } => write!(f, "curvatures differ by {max_abs_diff_per_m:.2} 1/m"),
            Rejection::Orientation { angle_deg } => write!(f, "normals {angle_deg:.1} deg apart"),
            Rejection::Position { distance_m } => write!(f, "positions {distance_m:.4} m apart"),
        }
    }
}

/// A successful match.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Match {
    pub map_index: usize,
    pub trained_index: usize,
    /// Sum of the criteria normalised by their thresholds (lower is better, each term < 1).
    pub score: f64,
    /// Index of the symmetry equivalent that matched (0 = identity).
    pub symmetry: usize,
}

/// A near miss for diagnostics.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct NearMiss {
    pub map_index: usize,
    pub trained_index: usize,
    /// Centre distance (m), the ranking key.
    pub distance_m: f64,
    pub reason: Rejection,
}

/// Result of matching a whole map.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct MatchReport {
    pub best: Option<Match>,
    /// Nearest (by centre distance) failing pairs, with the reason, at most `diagnostics`.
    pub near_misses: Vec<NearMiss>,
}

/// One symmetry-equivalent parameterisation of a trained patch.
#[derive(Debug, Clone)]
struct Equivalent {
    d: Vec<f64>,
    k: Vec<f64>,
    rotation: Rotation3<f64>,
}

#[derive(Debug, Clone)]
struct TrainedEntry {
    index: usize,
    surface: SurfaceType,
    boundary: BoundaryType,
    centre: Vector3<f64>,
    equivalents: Vec<Equivalent>,
}

/// The matcher over a fixed set of trained patches.
#[derive(Debug, Clone)]
pub struct Matcher {
    config: MatcherConfig,
    /// Sorted by centre x.
    entries: Vec<TrainedEntry>,
    cos_tolerance: f64,
}

/// All parameterisations of the same geometry (see module doc).
fn equivalents(patch: &Patch, allow_normal_flip: bool) -> Vec<Equivalent> {
    let base = rotation_of(patch);
    let two_axes = matches!(patch.boundary, BoundaryType::Ellipse | BoundaryType::Rectangle);
    // A single curvature (cylindric paraboloid, cylinder) is bound to the local y axis: only half
    // turns keep that form. Circles are continuously symmetric; quadrilaterals have none for free.
    let quarter_turns: &[u8] = match (two_axes, patch.surface.num_curvatures()) {
        (true, 1) => &[0, 2],
        (true, _) => &[0, 1, 2, 3],
        (false, _) => &[0],
    };
    let flips: &[bool] = if allow_normal_flip && patch.boundary != BoundaryType::Quadrilateral { &[false, true] } else { &[false] };
    let mut out = Vec::new();
    for &flip in flips {
        for &turns in quarter_turns {
            let swap = turns % 2 == 1;
            let mut d = patch.boundary_params.clone();
            let mut k = patch.curvature_params();
            if swap && d.len() >= 2 {
                d.swap(0, 1);
                if k.len() == 2 {
                    k.swap(0, 1);
                }
            }
            let mut local = Rotation3::from_axis_angle(&Vector3::z_axis(), f64::from(turns) * std::f64::consts::FRAC_PI_2);
            if flip {
                // z' = −z, y' = −y: curvatures change sign.
                k.iter_mut().for_each(|v| *v = -*v);
                local *= Rotation3::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI);
            }
            out.push(Equivalent { d, k, rotation: base * local });
        }
    }
    out
}

/// `R(r)` of a patch (IROS eq 2).
fn rotation_of(patch: &Patch) -> Rotation3<f64> {
    Rotation3::from_scaled_axis(patch.rotation)
}

/// The minimal curvature parameters of a patch without allocating (`[κx κy]`, `[κ]` or none).
fn curvatures(patch: &Patch) -> ([f64; 2], usize) {
    match patch.surface.num_curvatures() {
        2 => ([patch.curvatures.x, patch.curvatures.y], 2),
        1 => ([patch.curvatures.y, 0.0], 1),
        _ => ([0.0; 2], 0),
    }
}

fn max_abs_diff(a: &[f64], b: &[f64]) -> f64 {
    if a.len() != b.len() {
        return f64::INFINITY;
    }
    a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0, f64::max)
}

/// Result of checking one pair.
enum PairResult {
    Match { score: f64, symmetry: usize },
    Miss(Rejection),
}

impl Matcher {
    /// Build over trained patches (index = position in the slice, e.g. library order).
    pub fn new<'a>(config: MatcherConfig, trained: impl IntoIterator<Item = &'a Patch>) -> Self {
        let mut entries: Vec<TrainedEntry> = trained
            .into_iter()
            .enumerate()
            .map(|(index, patch)| TrainedEntry {
                index,
                surface: patch.surface,
                boundary: patch.boundary,
                centre: patch.center,
                equivalents: equivalents(patch, config.allow_normal_flip),
            })
            .collect();
        entries.sort_by(|a, b| a.centre.x.total_cmp(&b.centre.x));
        let cos_tolerance = config.normal_tolerance_deg.to_radians().cos();
        Self { config, entries, cos_tolerance }
    }

    pub fn config(&self) -> &MatcherConfig {
        &self.config
    }

    pub fn trained_count(&self) -> usize {
        self.entries.len()
    }

    /// Criteria (1)–(5) for one pair; `map_rotation` precomputed.
    fn check_pair(&self, entry: &TrainedEntry, map: &Patch, map_rotation: &Rotation3<f64>, distance: f64) -> PairResult {
        let cfg = &self.config;
        if map.surface != entry.surface {
            return PairResult::Miss(Rejection::SurfaceType { map: map.surface, trained: entry.surface });
        }
        if map.boundary != entry.boundary {
            return PairResult::Miss(Rejection::BoundaryType { map: map.boundary, trained: entry.boundary });
        }
        // Best (smallest) violation per criterion over the symmetries, to explain a miss.
        let mut best_d = f64::INFINITY;
        let mut best_k = f64::INFINITY;
        let mut best_angle = f64::INFINITY;
        let mut best: Option<(f64, usize)> = None;
        let map_normal = map_rotation * Vector3::z();
        let (map_k, map_nk) = curvatures(map);
        let map_k = map_k.get(..map_nk).unwrap_or_default();
        for (s, eq) in entry.equivalents.iter().enumerate() {
            let dd = max_abs_diff(&map.boundary_params, &eq.d);
            best_d = best_d.min(dd);
            if dd >= cfg.boundary_tolerance_m {
                continue;
            }
            let dk = max_abs_diff(map_k, &eq.k);
            best_k = best_k.min(dk);
            if dk >= cfg.curvature_tolerance_per_m {
                continue;
            }
            let angle = match cfg.orientation {
                OrientationCheck::Normal => {
                    let cos = map_normal.dot(&(eq.rotation * Vector3::z())).clamp(-1.0, 1.0);
                    if cos <= self.cos_tolerance {
                        best_angle = best_angle.min(cos.acos());
                        continue;
                    }
                    cos.acos()
                }
                OrientationCheck::Frame => {
                    let angle = (eq.rotation.inverse() * map_rotation).angle();
                    if angle >= cfg.normal_tolerance_deg.to_radians() {
                        best_angle = best_angle.min(angle);
                        continue;
                    }
                    angle
                }
            };
            let score = dd / cfg.boundary_tolerance_m
                + dk / cfg.curvature_tolerance_per_m
                + angle.to_degrees() / cfg.normal_tolerance_deg
                + distance / cfg.position_tolerance_m;
            if best.is_none_or(|(b, _)| score < b) {
                best = Some((score, s));
            }
        }
        match best {
            Some((score, symmetry)) if distance < cfg.position_tolerance_m => PairResult::Match { score, symmetry },
            Some(_) => PairResult::Miss(Rejection::Position { distance_m: distance }),
            None if best_d >= cfg.boundary_tolerance_m => PairResult::Miss(Rejection::BoundaryParams { max_abs_diff_m: best_d }),
            None if best_k >= cfg.curvature_tolerance_per_m => PairResult::Miss(Rejection::Curvature { max_abs_diff_per_m: best_k }),
            None => PairResult::Miss(Rejection::Orientation { angle_deg: best_angle.to_degrees() }),
        }
    }

    /// Fast path: the best match over all (map, trained) pairs, visiting only trained patches within
    /// ±rs in x of each map patch.
    pub fn best_match(&self, map: &[Patch]) -> Option<Match> {
        let rs = self.config.position_tolerance_m;
        let mut best: Option<Match> = None;
        for (map_index, patch) in map.iter().enumerate() {
            let centre = patch.center;
            let start = self.entries.partition_point(|e| e.centre.x <= centre.x - rs);
            let mut rotation: Option<Rotation3<f64>> = None;
            for entry in self.entries.get(start..).unwrap_or(&[]) {
                if entry.centre.x >= centre.x + rs {
                    break;
                }
                let distance = (entry.centre - centre).norm();
                if distance >= rs || entry.surface != patch.surface {
                    continue;
                }
                let rotation = *rotation.get_or_insert_with(|| rotation_of(patch));
                if let PairResult::Match { score, symmetry } = self.check_pair(entry, patch, &rotation, distance) {
                    let better = best.as_ref().is_none_or(|b| score < b.score);
                    if better {
                        best = Some(Match { map_index, trained_index: entry.index, score, symmetry });
                    }
                }
            }
        }
        best
    }

    /// Full report: the best match plus the `diagnostics` nearest failing pairs with their reason
    /// (checks every pair; use for status/diagnostics, not in the tight loop).
    pub fn report(&self, map: &[Patch]) -> MatchReport {
        let best = self.best_match(map);
        let keep = self.config.diagnostics;
        let mut near_misses: Vec<NearMiss> = Vec::new();
        if keep > 0 {
            for (map_index, patch) in map.iter().enumerate() {
                let centre = patch.center;
                let rotation = rotation_of(patch);
                for entry in &self.entries {
                    let distance = (entry.centre - centre).norm();
                    let worst_kept = near_misses.last().map_or(f64::INFINITY, |m| m.distance_m);
                    if near_misses.len() >= keep && distance >= worst_kept {
                        continue;
                    }
                    if let PairResult::Miss(reason) = self.check_pair(entry, patch, &rotation, distance) {
                        let at = near_misses.partition_point(|m| m.distance_m <= distance);
                        near_misses.insert(at, NearMiss { map_index, trained_index: entry.index, distance_m: distance, reason });
                        near_misses.truncate(keep);
                    }
                }
            }
        }
        MatchReport { best, near_misses }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    use nalgebra::Vector2;

    fn trained() -> Patch {
        Patch::new(
            SurfaceType::EllipticParaboloid,
            BoundaryType::Ellipse,
            vec![0.05, 0.03],
            Vector2::new(20.0, 10.0),
            Vector3::new(0.1, -0.05, 0.4),
            Vector3::new(0.12, 0.05, -0.27),
        )
        .unwrap()
    }

    fn matcher(patches: &[Patch]) -> Matcher {
        Matcher::new(MatcherConfig::default(), patches)
    }

    fn single_reason(m: &Matcher, map: Patch) -> Rejection {
        let report = m.report(&[map]);
        assert!(report.best.is_none(), "{report:?}");
        report.near_misses[0].reason.clone()
    }

    #[test]
    fn identical_patch_matches_with_identity_symmetry() {
        let m = matcher(&[trained()]);
        let best = m.best_match(&[trained()]).unwrap();
        assert_eq!((best.map_index, best.trained_index, best.symmetry), (0, 0, 0));
        assert!(best.score < 1e-9);
    }

    #[test]
    fn criterion_1_surface_type() {
        let m = matcher(&[trained()]);
        let mut p = trained();
        p.surface = SurfaceType::HyperbolicParaboloid;
        assert!(matches!(single_reason(&m, p), Rejection::SurfaceType { .. }));
    }

    #[test]
    fn criterion_2_boundary_threshold() {
        let m = matcher(&[trained()]);
        let mut p = trained();
        p.boundary_params[0] += 0.014;
        assert!(m.best_match(&[p.clone()]).is_some());
        p.boundary_params[0] += 0.002;
        assert!(matches!(single_reason(&m, p), Rejection::BoundaryParams { max_abs_diff_m } if (max_abs_diff_m - 0.016).abs() < 1e-9));
    }

    #[test]
    fn criterion_3_curvature_threshold() {
        let m = matcher(&[trained()]);
        let mut p = trained();
        p.curvatures.y -= 4.9;
        assert!(m.best_match(&[p.clone()]).is_some());
        p.curvatures.y -= 0.2;
        assert!(matches!(single_reason(&m, p), Rejection::Curvature { .. }));
    }

    #[test]
    fn criterion_4_normal_angle_threshold() {
        let m = matcher(&[trained()]);
        let tilt = |deg: f64| {
            let mut p = trained();
            // Tilt about an axis perpendicular to the normal, so the normals differ by exactly `deg`.
            let axis = nalgebra::Unit::new_normalize(p.normal().cross(&Vector3::x()));
            let r = Rotation3::from_axis_angle(&axis, deg.to_radians()) * rotation_of(&p);
            p.rotation = r.scaled_axis();
            p
        };
        assert!(m.best_match(&[tilt(19.0)]).is_some());
        assert!(matches!(single_reason(&m, tilt(21.0)), Rejection::Orientation { angle_deg } if (angle_deg - 21.0).abs() < 1e-6));
    }

    #[test]
    fn criterion_5_position_threshold() {
        let m = matcher(&[trained()]);
        let mut p = trained();
        p.center.y += 0.0095;
        assert!(m.best_match(&[p.clone()]).is_some());
        p.center.y += 0.001;
        assert!(matches!(single_reason(&m, p), Rejection::Position { distance_m } if (distance_m - 0.0105).abs() < 1e-9));
    }

    #[test]
    fn symmetry_quarter_turn_swaps_axes() {
        let m = matcher(&[trained()]);
        // Same ellipse described with x/y swapped: frame rotated 90° about its normal.
        let mut p = trained();
        p.boundary_params.swap(0, 1);
        p.curvatures = Vector2::new(p.curvatures.y, p.curvatures.x);
        let r = rotation_of(&p) * Rotation3::from_axis_angle(&Vector3::z_axis(), std::f64::consts::FRAC_PI_2);
        p.rotation = r.scaled_axis();
        let best = m.best_match(&[p.clone()]).unwrap();
        assert_ne!(best.symmetry, 0);
        // In full-frame mode the quarter turn is also matched (same geometry).
        let frame = Matcher::new(MatcherConfig { orientation: OrientationCheck::Frame, ..Default::default() }, &[trained()]);
        assert!(frame.best_match(&[p]).is_some());
    }

    #[test]
    fn symmetry_normal_flip_negates_curvature() {
        let m = matcher(&[trained()]);
        let mut p = trained();
        p.curvatures = Vector2::new(-20.0, -10.0);
        let r = rotation_of(&p) * Rotation3::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI);
        p.rotation = r.scaled_axis();
        assert!(m.best_match(&[p.clone()]).is_some());
        let no_flip = Matcher::new(MatcherConfig { allow_normal_flip: false, ..Default::default() }, &[trained()]);
        assert!(no_flip.best_match(&[p]).is_none());
    }

    #[test]
    fn symmetry_half_turn_of_rectangle_in_frame_mode() {
        let rect = Patch::new(
            SurfaceType::Plane,
            BoundaryType::Rectangle,
            vec![0.06, 0.03],
            Vector2::zeros(),
            Vector3::new(0.0, 0.0, 0.3),
            Vector3::new(0.1, 0.0, -0.28),
        )
        .unwrap();
        let frame = Matcher::new(MatcherConfig { orientation: OrientationCheck::Frame, ..Default::default() }, std::slice::from_ref(&rect));
        let mut half = rect.clone();
        half.rotation = Vector3::new(0.0, 0.0, 0.3 + std::f64::consts::PI);
        assert!(frame.best_match(&[half]).is_some());
        // A 45° yaw is not a symmetry of a 6×3 cm rectangle.
        let mut yawed = rect.clone();
        yawed.rotation = Vector3::new(0.0, 0.0, 0.3 + std::f64::consts::FRAC_PI_4);
        assert!(matches!(frame.report(&[yawed.clone()]).near_misses[0].reason, Rejection::Orientation { .. }));
        // Normal mode (J 6.3) ignores in-plane heading.
        assert!(matcher(&[rect]).best_match(&[yawed]).is_some());
    }

    #[test]
    fn best_of_many_and_near_misses_sorted() {
        let mut a = trained();
        a.center = Vector3::new(0.10, 0.0, -0.27);
        let mut b = trained();
        b.center = Vector3::new(0.20, 0.0, -0.27);
        let m = matcher(&[a.clone(), b.clone()]);
        let mut map_b = b.clone();
        map_b.center.x += 0.002;
        let far = Patch { center: Vector3::new(0.5, 0.5, 0.0), ..trained() };
        let report = m.report(&[far, map_b]);
        let best = report.best.unwrap();
        assert_eq!((best.map_index, best.trained_index), (1, 1));
        assert_eq!(report.near_misses.len(), 3);
        assert!(report.near_misses.windows(2).all(|w| w[0].distance_m <= w[1].distance_m));
    }

    #[test]
    fn empty_inputs() {
        let m = matcher(&[]);
        assert!(m.best_match(&[trained()]).is_none());
        assert!(m.report(&[]).near_misses.is_empty());
    }
}
