//! Coarse route planning over footholds for patchwalk's biped (CNN IV, "Application to coarse route
//! planning", made for the RPBP's two legs). ROS-free.
//!
//! Input: footholds from any source — a list of 3D points with scores in the fixed, gravity-aligned
//! frame ([`Hold`]: CNN predictions, the patch pipeline's valid patches, a file) — and the terrain as
//! a grid of back-projected depth pixels ([`TerrainGrid`], CNN's 60 × 80). Output: a [`Route`], the
//! body path and its thinned stance sequence (left and right sole positions).
//!
//! Stages, each in its own module: [`kmeans`] (k = 30, seeded) → [`leg`] and [`biped`] (the legs'
//! IK, reach, minimum foot separation and body workspace from the URDF) → [`stance`] (Flex: the
//! fraction of the height/yaw workspace in which a stance is reachable) → [`dijkstra`] over the
//! 8-connected [`grid`] with Cost[u, v] = ‖u − v‖ · (1 − Flex(σ*(v))) → [`thin`] (a foot does not
//! move to a hold within the threshold). [`planner`] runs them; [`synthetic`] builds heightfield
//! terrains with known passable and impassable regions for tests and the bench.
//!
//! ```
//! use patchwalk_route::{synthetic, Planner, Target};
//! let terrain = synthetic::Terrain::trench(Some(0.15));
//! let (grid, holds) = (terrain.grid(), terrain.holds(0.03, 1));
//! let planner = Planner::rpbp()?;
//! let route = planner.plan(&grid, &holds, Some(Target { x: 0.15, y: -0.2, z: None }), Target { x: 1.05, y: -0.2, z: None })?;
//! assert!(route.stances.len() >= 2);
//! # Ok::<(), patchwalk_route::RouteError>(())
//! ```

pub mod biped;
pub mod dijkstra;
pub mod error;
pub mod grid;
pub mod hold;
pub mod kmeans;
pub mod leg;
pub mod planner;
pub mod stance;
pub mod synthetic;
pub mod thin;

pub use biped::BipedModel;
pub use error::RouteError;
pub use grid::{Pinhole, TerrainGrid};
pub use hold::Hold;
pub use planner::{PlanStats, Planner, PlannerConfig, Route, RouteStance, Target};
