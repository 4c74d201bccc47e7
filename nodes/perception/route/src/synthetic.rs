//! Synthetic heightfield terrains with known passable and impassable regions, for the planner's
//! tests and bench: a flat ground cut by a trench wider than the biped can straddle (optionally
//! bridged on one side), and a rock field. The planning grid is the terrain's top view (60 × 80,
//! row 0 the far end as in a camera image, column 0 on the left), and the holds are a jittered
//! lattice on the walkable surface, seeded.

use nalgebra::Vector3;
use rand::{Rng, SeedableRng};

use crate::grid::{TerrainGrid, CNN_COLS, CNN_ROWS};
use crate::hold::Hold;

/// A rock: a spherical cap on the ground.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Rock {
    pub x: f64,
    pub y: f64,
    /// Cap base radius (m).
    pub radius_m: f64,
    /// Cap height (m).
    pub height_m: f64,
}

/// The terrain's shape.
#[derive(Debug, Clone, PartialEq)]
pub enum Shape {
    /// A trench across x ∈ [x0, x1], `depth_m` deep, all along y except where y ≥ bridge_y (if any).
    Trench { x0: f64, x1: f64, depth_m: f64, bridge_y: Option<f64> },
    /// Flat ground with rocks.
    Rocks(Vec<Rock>),
}

/// A rectangle of terrain, ground at z = 0.
#[derive(Debug, Clone, PartialEq)]
pub struct Terrain {
    pub x: (f64, f64),
    pub y: (f64, f64),
    pub shape: Shape,
}

impl Terrain {
    /// 1.2 m × 0.8 m of flat ground with a 0.40 m wide, 0.3 m deep trench at x ∈ [0.45, 0.85]: wider
    /// than the RPBP's longest stride (≈ 0.37 m between the soles, each 0.186 m ahead of or behind the
    /// hips at the deepest crouch). With `bridge_y`, the ground continues across for y ≥ bridge_y.
    pub fn trench(bridge_y: Option<f64>) -> Self {
        Self { x: (0.0, 1.2), y: (-0.4, 0.4), shape: Shape::Trench { x0: 0.45, x1: 0.85, depth_m: 0.3, bridge_y } }
    }

    /// 1.2 m × 0.8 m of ground with `count` rocks (radius 4–10 cm, 2–8 cm high), seeded.
    pub fn rock_field(count: usize, seed: u64) -> Self {
        let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
        let rocks = (0..count)
            .map(|_| Rock {
                x: rng.random_range(0.1..1.1),
                y: rng.random_range(-0.35..0.35),
                radius_m: rng.random_range(0.04..0.10),
                height_m: rng.random_range(0.02..0.08),
            })
            .collect();
        Self { x: (0.0, 1.2), y: (-0.4, 0.4), shape: Shape::Rocks(rocks) }
    }

    /// Terrain height at (x, y).
    pub fn height(&self, x: f64, y: f64) -> f64 {
        match &self.shape {
            Shape::Trench { x0, x1, depth_m, bridge_y } => {
                let in_trench = x > *x0 && x < *x1 && bridge_y.is_none_or(|b| y < b);
                if in_trench {
                    -depth_m
                } else {
                    0.0
                }
            }
            Shape::Rocks(rocks) => rocks.iter().map(|r| cap_height(r, x, y)).fold(0.0, f64::max),
        }
    }

    /// Whether a foot can stand at (x, y): on the ground or a rock top, at least 3 cm from a trench
    /// edge, not on a rock's steep flank.
    pub fn walkable(&self, x: f64, y: f64) -> bool {
        match &self.shape {
            Shape::Trench { .. } => {
                let m = 0.03;
                [(0.0, 0.0), (m, 0.0), (-m, 0.0), (0.0, m), (0.0, -m)].iter().all(|(dx, dy)| self.height(x + dx, y + dy) == 0.0)
            }
            Shape::Rocks(rocks) => rocks.iter().all(|r| {
                let d = ((x - r.x).powi(2) + (y - r.y).powi(2)).sqrt();
                // off the rock, or on its top third
                d >= r.radius_m || d <= r.radius_m / 3.0
            }),
        }
    }

    /// The CNN-sized (60 × 80) top-view grid of the terrain.
    pub fn grid(&self) -> TerrainGrid {
        let (rows, cols) = (CNN_ROWS, CNN_COLS);
        let points = (0..rows * cols)
            .map(|i| {
                let (r, c) = ((i / cols) as f64 + 0.5, (i % cols) as f64 + 0.5);
                let x = self.x.1 - r / rows as f64 * (self.x.1 - self.x.0);
                let y = self.y.1 - c / cols as f64 * (self.y.1 - self.y.0);
                Some(Vector3::new(x, y, self.height(x, y)))
            })
            .collect();
        TerrainGrid { rows, cols, points, pixels: (0..rows * cols).map(|i| ((i % cols) as f64, (i / cols) as f64)).collect() }
    }

    /// Holds on a lattice of `spacing_m`, jittered by up to a quarter spacing, kept where walkable;
    /// scores in [0.6, 1].
    pub fn holds(&self, spacing_m: f64, seed: u64) -> Vec<Hold> {
        let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
        let mut holds = Vec::new();
        let nx = ((self.x.1 - self.x.0) / spacing_m).floor() as usize;
        let ny = ((self.y.1 - self.y.0) / spacing_m).floor() as usize;
        for i in 0..nx {
            for j in 0..ny {
                let x = self.x.0 + (i as f64 + 0.5) * spacing_m + rng.random_range(-0.25..0.25) * spacing_m;
                let y = self.y.0 + (j as f64 + 0.5) * spacing_m + rng.random_range(-0.25..0.25) * spacing_m;
                let score = rng.random_range(0.6..1.0);
                if self.walkable(x, y) {
                    holds.push(Hold::new(Vector3::new(x, y, self.height(x, y)), score));
                }
            }
        }
        holds
    }
}

fn cap_height(rock: &Rock, x: f64, y: f64) -> f64 {
    let d2 = (x - rock.x).powi(2) + (y - rock.y).powi(2);
    if d2 >= rock.radius_m * rock.radius_m {
        return 0.0;
    }
    // sphere through the cap's rim and top: R = (r² + h²) / 2h
    let h = rock.height_m;
    let big = (rock.radius_m * rock.radius_m + h * h) / (2.0 * h);
    ((big * big - d2).sqrt() - (big - h)).max(0.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn trench_and_rocks_have_the_stated_shape() {
        let open = Terrain::trench(None);
        assert_eq!(open.height(0.6, 0.3), -0.3);
        assert_eq!(open.height(0.3, 0.0), 0.0);
        assert!(!open.walkable(0.44, 0.0) && open.walkable(0.40, 0.0));
        let bridged = Terrain::trench(Some(0.15));
        assert_eq!(bridged.height(0.6, 0.3), 0.0);
        assert_eq!(bridged.height(0.6, 0.0), -0.3);
        let holds = open.holds(0.03, 1);
        assert!(holds.iter().all(|h| h.position[2] == 0.0 && !(0.42..0.88).contains(&h.position[0])));
        let rock = Rock { x: 0.0, y: 0.0, radius_m: 0.1, height_m: 0.05 };
        assert!((cap_height(&rock, 0.0, 0.0) - 0.05).abs() < 1e-12);
        assert!(cap_height(&rock, 0.0999, 0.0) < 0.002);
        let grid = Terrain::rock_field(10, 2).grid();
        assert_eq!((grid.rows, grid.cols, grid.valid()), (60, 80, 4800));
    }
}
