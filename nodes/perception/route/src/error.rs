//! The errors of the route planner: bad input (holds, grid, goal, configuration) and the planning
//! outcomes that are not a route (no stance at the start or goal, goal not connected).

/// Everything that can go wrong in planning; every message names what was wrong.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum RouteError {
    /// The hold set is empty (nothing to stand on).
    #[error("no footholds given: the hold set is empty")]
    NoHolds,
    /// A hold's position is NaN or infinite.
    #[error("foothold {index} has a non-finite position [{x}, {y}, {z}]")]
    NonFiniteHold { index: usize, x: f64, y: f64, z: f64 },
    /// A hold's score is not a number in [0, 1].
    #[error("foothold {index} has score {score}, expected a number in [0, 1]")]
    BadScore { index: usize, score: f64 },
    /// Every hold scored below the threshold.
    #[error("none of the {count} footholds has a score of at least {min_score}")]
    NoHoldAboveScore { count: usize, min_score: f64 },
    /// k-means asked for zero clusters.
    #[error("k-means needs at least one cluster (k = 0)")]
    ZeroClusters,
    /// The terrain grid's size does not match its points, or is empty.
    #[error("terrain grid: {0}")]
    Grid(String),
    /// The terrain grid has no observed point.
    #[error("terrain grid has no valid point (no depth in any cell)")]
    EmptyGrid,
    /// A start or goal coordinate is NaN or infinite.
    #[error("{what} [{x}, {y}, {z}] is not finite")]
    NonFinitePoint { what: &'static str, x: f64, y: f64, z: f64 },
    /// The start or goal lies outside the observed terrain.
    #[error("{what} ({x:.3}, {y:.3}) is outside the observed terrain: the nearest observed point is {nearest_m:.3} m away (at most {limit_m:.3} m)")]
    OutsideTerrain { what: &'static str, x: f64, y: f64, nearest_m: f64, limit_m: f64 },
    /// No stance (a left and a right foothold both reachable) near the start or goal.
    #[error("{what} ({x:.3}, {y:.3}): no stance of two footholds is reachable from any body position within {radius_m:.3} m")]
    NoStance { what: &'static str, x: f64, y: f64, radius_m: f64 },
    /// No vertex of the terrain has a stance.
    #[error("no body position on the observed terrain has a stance ({clusters} clustered footholds, {vertices} terrain vertices): the holds are too sparse or out of the legs' reach")]
    NoStanceAnywhere { clusters: usize, vertices: usize },
    /// The goal is not connected to the start through body positions with a stance.
    #[error("no route: the goal is not reachable from the start ({reachable} of {feasible} body positions with a stance are reachable from the start; an impassable region separates them)")]
    NoRoute { reachable: usize, feasible: usize },
    /// A planner parameter is out of range.
    #[error("planner configuration: {0}")]
    Config(String),
    /// The robot model (URDF) cannot be used for the leg model.
    #[error("robot model: {0}")]
    Robot(String),
}
