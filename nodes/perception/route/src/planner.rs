//! The coarse route planner of CNN IV for the biped: holds → k-means (k = 30) → for every vertex of
//! the 60 × 80 grid of back-projected pixels the optimal stance σ*(v) = argmax_σ Flex(v, σ) →
//! Dijkstra over the 8-connected grid with Cost[u, v] = ‖u − v‖ · (1 − Flex(σ*(v))) → the optimal
//! stances along the body path, thinned (a foot does not move to a hold within the threshold).
//!
//! Vertices without a stance are impassable, so a gap wider than the legs can straddle cuts the
//! graph and the planner answers [`RouteError::NoRoute`] instead of a route through it. Neighbouring
//! vertices farther apart than `max_edge_m` (a depth discontinuity, e.g. a rock's occluding edge) are
//! not connected.

use std::time::Instant;

use nalgebra::Vector3;
use rayon::prelude::*;
use serde::Serialize;

use crate::biped::BipedModel;
use crate::dijkstra::shortest_path;
use crate::error::RouteError;
use crate::grid::TerrainGrid;
use crate::hold::{usable_holds, Hold};
use crate::kmeans::kmeans;
use crate::stance::{flex, flex_above, stance_heading, Stance, WorkspaceSamples};
use crate::thin::thin;

/// Planner parameters (CNN IV's values where they carry over to a 0.47 m biped; see each field).
#[derive(Debug, Clone, PartialEq, Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PlannerConfig {
    /// k of k-means (CNN IV: 30).
    pub clusters: usize,
    /// Seed of the k-means++ initialisation.
    pub seed: u64,
    /// Holds scoring below this are ignored (0.5: a predictor's "foothold" decision).
    pub min_score: f64,
    /// Samples of the body height workspace per stance.
    pub height_samples: usize,
    /// Samples of the body yaw workspace per stance.
    pub yaw_samples: usize,
    /// A foot does not move to a hold closer than this to its current one (m). CNN IV: 0.3 m for
    /// RoboSimian's 0.7 m limb workspace; the same ratio (3/7) of the RPBP's 0.235 m leg
    /// (thigh + shin + ankle-to-sole): 0.10 m, about one sole length.
    pub thinning_m: f64,
    /// A foot also keeps its hold while the stance with it keeps at least this fraction of the
    /// optimal stance's Flex (see [`crate::thin`]; above 1: CNN IV's distance rule only).
    pub keep_flex_ratio: f64,
    /// The start and the goal snap to the nearest vertex with a stance within this distance (m).
    pub snap_m: f64,
    /// Neighbouring vertices farther apart than this are not connected (m): depth discontinuities.
    pub max_edge_m: f64,
    /// Stances whose heading (the way the feet face) turns more than this from the start → goal
    /// bearing are not used (rad; π/2: a biped walks forwards or sideways, not backwards; above π:
    /// any heading, as CNN IV's symmetric RoboSimian).
    pub max_heading_deviation_rad: f64,
}

impl Default for PlannerConfig {
    fn default() -> Self {
        Self {
            clusters: 30,
            seed: 0,
            min_score: 0.5,
            height_samples: 5,
            yaw_samples: 7,
            thinning_m: 0.10,
            keep_flex_ratio: 0.5,
            snap_m: 0.15,
            max_edge_m: 0.10,
            max_heading_deviation_rad: std::f64::consts::FRAC_PI_2,
        }
    }
}

impl PlannerConfig {
    /// Checks every parameter, naming the first bad one.
    pub fn validate(&self) -> Result<(), RouteError> {
        let positive = |name: &str, v: f64| {
            if v.is_finite() && v > 0.0 {
                Ok(())
            } else {
                Err(RouteError::Config(format!("{name} must be a positive number, got {v}")))
            }
        };
        if self.clusters == 0 {
            return Err(RouteError::Config("clusters must be at least 1".into()));
        }
        if self.height_samples == 0 || self.yaw_samples == 0 {
            return Err(RouteError::Config("height_samples and yaw_samples must be at least 1".into()));
        }
        if !(0.0..=1.0).contains(&self.min_score) {
            return Err(RouteError::Config(format!("min_score must lie in [0, 1], got {}", self.min_score)));
        }
        positive("thinning_m", self.thinning_m)?;
        positive("keep_flex_ratio", self.keep_flex_ratio)?;
        positive("snap_m", self.snap_m)?;
        positive("max_edge_m", self.max_edge_m)?;
        positive("max_heading_deviation_rad", self.max_heading_deviation_rad)
    }
}

/// A start or goal: `x, y` in the fixed frame, `z` when known (else the nearest vertex is found
/// in the horizontal plane).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Target {
    pub x: f64,
    pub y: f64,
    pub z: Option<f64>,
}

impl Target {
    fn check(&self, what: &'static str) -> Result<(), RouteError> {
        let z = self.z.unwrap_or(0.0);
        if self.x.is_finite() && self.y.is_finite() && z.is_finite() {
            Ok(())
        } else {
            Err(RouteError::NonFinitePoint { what, x: self.x, y: self.y, z })
        }
    }

    fn distance(&self, p: &Vector3<f64>) -> f64 {
        let dz = self.z.map_or(0.0, |z| z - p.z);
        ((self.x - p.x).powi(2) + (self.y - p.y).powi(2) + dz * dz).sqrt()
    }
}

/// One stance of the route.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct RouteStance {
    /// The body-path vertex where the stance is taken (fixed frame, the terrain point under the body).
    pub body: [f64; 3],
    /// Its grid vertex `[row, col]`.
    pub vertex: [usize; 2],
    /// Left and right sole positions (the clustered holds).
    pub left: [f64; 3],
    pub right: [f64; 3],
    /// Indices into [`Route::holds`].
    pub left_hold: usize,
    pub right_hold: usize,
    /// Flex of this stance at the body vertex.
    pub flex: f64,
    /// Path cost from the start to the body vertex.
    pub cost: f64,
}

/// Where the planning time went and how big the problem was.
#[derive(Debug, Clone, Default, Serialize, PartialEq)]
pub struct PlanStats {
    pub holds_in: usize,
    pub holds_used: usize,
    pub clusters: usize,
    pub kmeans_iterations: usize,
    pub vertices: usize,
    pub vertices_with_stance: usize,
    pub stances_evaluated: usize,
    pub vertices_settled: usize,
    pub cluster_ms: f64,
    pub stance_ms: f64,
    pub search_ms: f64,
    pub total_ms: f64,
}

/// A planned route.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct Route {
    /// The body path: vertex positions from start to goal (fixed frame).
    pub body_path: Vec<[f64; 3]>,
    /// The body path's grid vertices `[row, col]`.
    pub body_vertices: Vec<[usize; 2]>,
    /// The thinned stance sequence, start to goal.
    pub stances: Vec<RouteStance>,
    /// Total Dijkstra cost Σ ‖u − v‖ (1 − Flex(σ*(v))).
    pub cost: f64,
    /// Length of the body path (m).
    pub length_m: f64,
    /// The clustered holds the stances index.
    pub holds: Vec<Hold>,
    pub stats: PlanStats,
}

/// The planner: a biped model, its workspace samples and the parameters.
#[derive(Debug, Clone)]
pub struct Planner {
    pub biped: BipedModel,
    pub config: PlannerConfig,
    samples: WorkspaceSamples,
}

impl Planner {
    /// A planner for `biped` with `config` (checked).
    pub fn new(biped: BipedModel, config: PlannerConfig) -> Result<Self, RouteError> {
        config.validate()?;
        let samples = WorkspaceSamples::new(&biped, config.height_samples, config.yaw_samples);
        Ok(Self { biped, config, samples })
    }

    /// The RPBP with the default parameters.
    pub fn rpbp() -> Result<Self, RouteError> {
        Self::new(BipedModel::rpbp()?, PlannerConfig::default())
    }

    /// σ*(v): the stance of largest Flex at `v` among ordered pairs of `holds` (None without any).
    /// Returns the stance and how many were evaluated. Pairs are tried nearest-midpoint first, and a
    /// pair's sampling stops once it cannot beat the best so far (same result, fewer IK solves).
    /// With `bearing` (rad), only stances heading within `max_heading_deviation_rad` of it count.
    pub fn best_stance(&self, v: &Vector3<f64>, holds: &[Vector3<f64>], bearing: Option<f64>) -> (Option<Stance>, usize) {
        let reach = self.biped.horizontal_reach_m();
        let near: Vec<usize> = (0..holds.len()).filter(|&i| (holds[i] - v).xy().norm() <= reach).collect();
        let mut pairs: Vec<(f64, usize, usize)> = Vec::new();
        for &l in &near {
            for &r in &near {
                let gap = (holds[l] - holds[r]).norm();
                if l == r || gap < self.biped.min_separation_m || gap > 2.0 * reach {
                    continue;
                }
                if let Some(b) = bearing {
                    let turn = angle_between(stance_heading(&holds[l], &holds[r]), b);
                    if turn > self.config.max_heading_deviation_rad + 1e-9 {
                        continue;
                    }
                }
                let middle = 0.5 * (holds[l] + holds[r]);
                pairs.push(((middle - v).xy().norm(), l, r));
            }
        }
        pairs.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)).then(a.2.cmp(&b.2)));
        let mut best: Option<Stance> = None;
        for &(_, l, r) in &pairs {
            let to_beat = best.map_or(0.0, |b| b.flex);
            if let Some(f) = flex_above(&self.biped, &self.samples, v, &holds[l], &holds[r], to_beat) {
                best = Some(Stance { left: l, right: r, flex: f });
            }
        }
        (best, pairs.len())
    }

    /// Flex of the stance (left, right) at `v`.
    pub fn flex_of(&self, v: &Vector3<f64>, left: &Vector3<f64>, right: &Vector3<f64>) -> f64 {
        flex(&self.biped, &self.samples, v, left, right)
    }

    /// Plans a route over `grid` standing on `holds` from `start` (None: the vertex with a stance
    /// nearest the bottom centre of the image, CNN IV's start) to `goal`.
    pub fn plan(&self, grid: &TerrainGrid, holds: &[Hold], start: Option<Target>, goal: Target) -> Result<Route, RouteError> {
        let t0 = Instant::now();
        goal.check("goal")?;
        if let Some(s) = &start {
            s.check("start")?;
        }
        if grid.valid() == 0 {
            return Err(RouteError::EmptyGrid);
        }
        let usable = usable_holds(holds, self.config.min_score)?;
        let clusters = kmeans(&usable, self.config.clusters, self.config.seed)?;
        let positions: Vec<Vector3<f64>> = clusters.holds.iter().map(Hold::point).collect();
        let cluster_ms = ms(t0);

        let t1 = Instant::now();
        // The general direction of travel: from the start (or the bottom centre of the grid) to the goal.
        let from = match &start {
            Some(s) => Some((s.x, s.y)),
            None => bottom_centre(grid, |i| grid.points[i].is_some()).and_then(|i| grid.points[i]).map(|p| (p.x, p.y)),
        };
        let bearing = from.filter(|(x, y)| (goal.x - x).hypot(goal.y - y) > 1e-6).map(|(x, y)| (goal.y - y).atan2(goal.x - x));
        let bearing = bearing.filter(|_| self.config.max_heading_deviation_rad < std::f64::consts::PI);
        let best: Vec<(Option<Stance>, usize)> = grid
            .points
            .par_iter()
            .map(|p| match p {
                Some(v) => self.best_stance(v, &positions, bearing),
                None => (None, 0),
            })
            .collect();
        let stance_ms = ms(t1);
        let stances: Vec<Option<Stance>> = best.iter().map(|b| b.0).collect();
        let feasible = stances.iter().filter(|s| s.is_some()).count();

        if feasible == 0 {
            return Err(RouteError::NoStanceAnywhere { clusters: positions.len(), vertices: grid.valid() });
        }
        let goal_vertex = self.snap(grid, &stances, &goal, "goal")?;
        let start_vertex = match &start {
            Some(s) => self.snap(grid, &stances, s, "start")?,
            None => bottom_centre(grid, |i| stances[i].is_some())
                .ok_or(RouteError::NoStanceAnywhere { clusters: positions.len(), vertices: grid.valid() })?,
        };

        let t2 = Instant::now();
        let edge = |u: usize, v: usize| edge_cost(grid, &stances, self.config.max_edge_m, u, v);
        let search = shortest_path(grid.rows, grid.cols, start_vertex, goal_vertex, edge);
        let Some(path) = search.path else {
            return Err(RouteError::NoRoute { reachable: search.settled, feasible });
        };
        let search_ms = ms(t2);

        let point = |i: usize| grid.points[i].unwrap_or_default();
        let mut cost_along = vec![0.0; path.len()];
        let mut length_m = 0.0;
        for k in 1..path.len() {
            cost_along[k] = cost_along[k - 1] + edge(path[k - 1], path[k]).unwrap_or(0.0);
            length_m += (point(path[k]) - point(path[k - 1])).norm();
        }
        let optimal: Vec<(usize, usize, f64)> =
            path.iter().map(|&i| stances[i].map_or((0, 0, 0.0), |s| (s.left, s.right, s.flex))).collect();
        let steps = thin(&optimal, &positions, self.config.thinning_m, self.config.keep_flex_ratio, |k, l, r| {
            self.flex_of(&point(path[k]), &positions[l], &positions[r])
        });
        let to_array = |v: Vector3<f64>| [v.x, v.y, v.z];
        let vertex = |i: usize| [i / grid.cols, i % grid.cols];
        let route_stances = steps
            .iter()
            .map(|s| RouteStance {
                body: to_array(point(path[s.path_index])),
                vertex: vertex(path[s.path_index]),
                left: to_array(positions[s.left]),
                right: to_array(positions[s.right]),
                left_hold: s.left,
                right_hold: s.right,
                flex: s.flex,
                cost: cost_along[s.path_index],
            })
            .collect();
        let stats = PlanStats {
            holds_in: holds.len(),
            holds_used: usable.len(),
            clusters: clusters.holds.len(),
            kmeans_iterations: clusters.iterations,
            vertices: grid.valid(),
            vertices_with_stance: feasible,
            stances_evaluated: best.iter().map(|b| b.1).sum(),
            vertices_settled: search.settled,
            cluster_ms,
            stance_ms,
            search_ms,
            total_ms: ms(t0),
        };
        Ok(Route {
            body_path: path.iter().map(|&i| to_array(point(i))).collect(),
            body_vertices: path.iter().map(|&i| vertex(i)).collect(),
            stances: route_stances,
            cost: search.cost,
            length_m,
            holds: clusters.holds,
            stats,
        })
    }

    /// The vertex with a stance nearest `target` within `snap_m`; errors say whether the target is
    /// off the observed terrain or on terrain without a stance.
    fn snap(&self, grid: &TerrainGrid, stances: &[Option<Stance>], target: &Target, what: &'static str) -> Result<usize, RouteError> {
        let mut nearest_any = f64::INFINITY;
        let mut nearest_feasible: Option<(usize, f64)> = None;
        for (i, p) in grid.points.iter().enumerate() {
            let Some(p) = p else { continue };
            let d = target.distance(p);
            nearest_any = nearest_any.min(d);
            if stances[i].is_some() && nearest_feasible.is_none_or(|(_, best)| d < best) {
                nearest_feasible = Some((i, d));
            }
        }
        let limit_m = self.config.snap_m;
        if nearest_any > limit_m {
            return Err(RouteError::OutsideTerrain { what, x: target.x, y: target.y, nearest_m: nearest_any, limit_m });
        }
        match nearest_feasible {
            Some((i, d)) if d <= limit_m => Ok(i),
            _ => Err(RouteError::NoStance { what, x: target.x, y: target.y, radius_m: limit_m }),
        }
    }
}

/// Cost[u, v] = ‖u − v‖ · (1 − Flex(σ*(v))) (CNN IV); no edge into a vertex without a stance or
/// across a step longer than `max_edge_m`.
fn edge_cost(grid: &TerrainGrid, stances: &[Option<Stance>], max_edge_m: f64, u: usize, v: usize) -> Option<f64> {
    let stance = stances[v]?;
    let (pu, pv) = (grid.points[u]?, grid.points[v]?);
    let d = (pv - pu).norm();
    (d <= max_edge_m).then_some(d * (1.0 - stance.flex))
}

/// CNN IV's start: in the lowest image row with a vertex passing `usable` (e.g. with a stance), the
/// one nearest the middle column.
fn bottom_centre(grid: &TerrainGrid, usable: impl Fn(usize) -> bool) -> Option<usize> {
    (0..grid.rows).rev().find_map(|r| {
        (0..grid.cols).filter(|&c| usable(r * grid.cols + c)).min_by_key(|&c| c.abs_diff(grid.cols / 2)).map(|c| r * grid.cols + c)
    })
}

/// The absolute difference of two angles, in [0, π].
fn angle_between(a: f64, b: f64) -> f64 {
    let d = (a - b).rem_euclid(std::f64::consts::TAU);
    d.min(std::f64::consts::TAU - d)
}

fn ms(t: Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn angles_between_wrap_around() {
        assert!((angle_between(0.1, -0.1) - 0.2).abs() < 1e-12);
        assert!((angle_between(3.0, -3.0) - (std::f64::consts::TAU - 6.0)).abs() < 1e-12);
        assert!((angle_between(0.0, std::f64::consts::PI) - std::f64::consts::PI).abs() < 1e-12);
    }

    #[test]
    fn bad_parameters_are_named() {
        let biped = BipedModel::rpbp().unwrap();
        for (config, key) in [
            (PlannerConfig { clusters: 0, ..Default::default() }, "clusters"),
            (PlannerConfig { yaw_samples: 0, ..Default::default() }, "yaw_samples"),
            (PlannerConfig { min_score: 1.5, ..Default::default() }, "min_score"),
            (PlannerConfig { snap_m: f64::NAN, ..Default::default() }, "snap_m"),
            (PlannerConfig { max_heading_deviation_rad: 0.0, ..Default::default() }, "max_heading_deviation_rad"),
        ] {
            let err = Planner::new(biped.clone(), config).unwrap_err();
            assert!(err.to_string().contains(key), "{err}");
        }
    }

    /// A stance facing the travel direction is kept, the same holds swapped (facing backwards) are not.
    #[test]
    fn stances_face_the_direction_of_travel() {
        let planner = Planner::rpbp().unwrap();
        let holds = [Vector3::new(0.0, 0.037, 0.0), Vector3::new(0.0, -0.037, 0.0)];
        let v = Vector3::zeros();
        let (forward, _) = planner.best_stance(&v, &holds, Some(0.0));
        assert_eq!(forward.map(|s| (s.left, s.right)), Some((0, 1)));
        let (backward, _) = planner.best_stance(&v, &holds, Some(std::f64::consts::PI));
        assert_eq!(backward.map(|s| (s.left, s.right)), Some((1, 0)));
        // Without a bearing both orders are candidates; the best is one of them.
        assert!(planner.best_stance(&v, &holds, None).0.is_some());
    }
}
