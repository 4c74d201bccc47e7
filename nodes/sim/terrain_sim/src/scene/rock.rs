//! One rock of the scene: a smooth analytic solid on the table whose top is one of the patch kinds
//! the mapper fits (IROS Table I: ellipsoid cap, paraboloid bump, flat boulder with a tilted top,
//! lying cylinder), its exact ray intersection, and its ground-truth foothold (top point, normal,
//! principal curvatures) for tests and the demo.

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

use super::SceneError;

/// Why a rock shape is not a solid standing on the table ([`RockShape::validate`]).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ShapeError {
    /// A size that must be positive and finite.
    #[error("{name} = {value} must be positive and finite")]
    NotPositive { name: &'static str, value: f64 },
    /// An ellipsoid cap whose centre is too low to reach above the table.
    #[error("centre_z_m = {centre_z_m} puts the ellipsoid under the table")]
    UnderTable { centre_z_m: f64 },
    /// A flat boulder whose sloped top dips below the table.
    #[error("top slope ({sx}, {sy}) takes the top below the table")]
    SlopeBelowTable { sx: f64, sy: f64 },
    /// A lying cylinder sunk by less than nothing or by more than its diameter.
    #[error("sunk {sunk_m} m must be in [0, 2 r) for r = {radius_m} m")]
    SunkOutOfRange { sunk_m: f64, radius_m: f64 },
}

/// Smallest ray parameter accepted as a hit (metres along a unit-z camera ray).
pub(super) const T_MIN: f64 = 1e-6;

/// A ray `origin + t·direction`; `direction` need not be unit length (the camera uses unit z in
/// the camera frame, so `t` is the depth).
#[derive(Debug, Clone, Copy)]
pub struct Ray {
    pub origin: Vector3<f64>,
    pub direction: Vector3<f64>,
}

impl Ray {
    #[inline]
    pub fn at(&self, t: f64) -> Vector3<f64> {
        self.origin + self.direction * t
    }
}

/// The nearest intersection of a ray with a surface: ray parameter and outward unit normal (in the
/// frame the ray was given in).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hit {
    pub t: f64,
    pub normal: Vector3<f64>,
}

/// The analytic solid of one rock, in its local frame (z up, table at z = 0).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum RockShape {
    /// Ellipsoid with semi-axes `(a, b, c)` along local x, y, z, centred at height `centre_z`
    /// (≤ 0 sinks it into the table, leaving a cap). Top: elliptic paraboloid with
    /// κ = (−c/a², −c/b²).
    EllipsoidCap { semi_axes_m: [f64; 3], centre_z_m: f64 },
    /// Paraboloid bump `z = h − ½(κx x² + κy y²)` above the table (κ > 0). Top: circular paraboloid
    /// if κx = κy, else elliptic.
    ParaboloidBump { height_m: f64, curvatures_per_m: [f64; 2] },
    /// Upright cylinder of radius `r` with a flat top through `(0, 0, h)` tilted by
    /// `slope = (∂z/∂x, ∂z/∂y)`. Top: plane with a circular boundary.
    FlatBoulder { radius_m: f64, height_m: f64, top_slope: [f64; 2] },
    /// Cylinder of radius `r` and length `l` lying on the table, axis along local x, sunk
    /// `sunk_m` (0 ≤ sunk < 2r) into it like a half-buried log. Top at z = 2r − sunk: cylindric
    /// paraboloid with κ = (0, −1/r).
    LyingCylinder {
        radius_m: f64,
        length_m: f64,
        #[serde(default)]
        sunk_m: f64,
    },
}

/// Ground-truth foothold geometry of a rock's top, in the world frame.
///
/// Convention (J eq. 3, patch frame): with `z` along `normal` (outward), `x` along `direction_x`, the
/// surface near `top` is `z = ½(κx x² + κy y²)`, so a convex bump has negative curvatures.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Foothold {
    pub top_in_world: Vector3<f64>,
    pub normal_in_world: Vector3<f64>,
    /// Unit tangent of the first principal direction (curvature `curvatures[0]`).
    pub direction_x_in_world: Vector3<f64>,
    /// Principal curvatures (m⁻¹) along `direction_x` and `normal × direction_x`.
    pub curvatures_per_m: [f64; 2],
    /// Surface type name as `patchwalk_spl::patch::SurfaceType::name` spells it (`elliptic_paraboloid`, `circular_paraboloid`, `plane`,
    /// `cylindric_paraboloid`).
    pub surface_type: &'static str,
    /// Radius (m) of the top region around `top` that stays within the shape's smooth top.
    pub top_radius_m: f64,
}

/// One rock placed on the table.
#[derive(Debug, Clone, PartialEq)]
pub struct Rock {
    pub name: String,
    pub shape: RockShape,
    /// Whether this rock is one of the four training rocks (J 6.3).
    pub trained: bool,
    pub world_from_rock: Isometry3<f64>,
    /// Local axis-aligned bounds `[min, max]` of the solid (for culling).
    pub bounds_in_rock: [Vector3<f64>; 2],
    /// Where the robot stands (`base_link`) to look at this rock.
    pub world_from_station: Isometry3<f64>,
    /// `(cos, sin)` of the yaw in `world_from_rock` (rocks only turn about z): fast ray transforms.
    yaw_cos_sin: (f64, f64),
}

impl RockShape {
    /// Checks positive sizes and that the solid stands on the table.
    pub fn validate(&self) -> Result<(), ShapeError> {
        let positive = |name: &'static str, value: f64| {
            if value.is_finite() && value > 0.0 {
                Ok(())
            } else {
                Err(ShapeError::NotPositive { name, value })
            }
        };
        match *self {
            RockShape::EllipsoidCap { semi_axes_m: [a, b, c], centre_z_m } => {
                positive("a", a)?;
                positive("b", b)?;
                positive("c", c)?;
                if !(centre_z_m.is_finite() && centre_z_m > -c) {
                    return Err(ShapeError::UnderTable { centre_z_m });
                }
            }
            RockShape::ParaboloidBump { height_m, curvatures_per_m: [kx, ky] } => {
                positive("height", height_m)?;
                positive("κx", kx)?;
                positive("κy", ky)?;
            }
            RockShape::FlatBoulder { radius_m, height_m, top_slope: [sx, sy] } => {
                positive("radius", radius_m)?;
                positive("height", height_m)?;
                if !(sx.is_finite() && sy.is_finite()) || (sx.hypot(sy) * radius_m) >= height_m {
                    return Err(ShapeError::SlopeBelowTable { sx, sy });
                }
            }
            RockShape::LyingCylinder { radius_m, length_m, sunk_m } => {
                positive("radius", radius_m)?;
                positive("length", length_m)?;
                if !(sunk_m.is_finite() && (0.0..2.0 * radius_m).contains(&sunk_m)) {
                    return Err(ShapeError::SunkOutOfRange { sunk_m, radius_m });
                }
            }
        }
        Ok(())
    }

    /// Local bounds `[min, max]`.
    pub fn bounds(&self) -> [Vector3<f64>; 2] {
        match *self {
            RockShape::EllipsoidCap { semi_axes_m: [a, b, c], centre_z_m } => {
                [Vector3::new(-a, -b, 0.0), Vector3::new(a, b, centre_z_m + c)]
            }
            RockShape::ParaboloidBump { height_m, curvatures_per_m: [kx, ky] } => {
                let (rx, ry) = ((2.0 * height_m / kx).sqrt(), (2.0 * height_m / ky).sqrt());
                [Vector3::new(-rx, -ry, 0.0), Vector3::new(rx, ry, height_m)]
            }
            RockShape::FlatBoulder { radius_m, height_m, top_slope: [sx, sy] } => {
                let top = height_m + radius_m * sx.hypot(sy);
                [Vector3::new(-radius_m, -radius_m, 0.0), Vector3::new(radius_m, radius_m, top)]
            }
            RockShape::LyingCylinder { radius_m, length_m, sunk_m } => {
                [Vector3::new(-length_m / 2.0, -radius_m, 0.0), Vector3::new(length_m / 2.0, radius_m, 2.0 * radius_m - sunk_m)]
            }
        }
    }

    /// Nearest intersection with `t > T_MIN` of a ray given in the rock frame (normal in the rock
    /// frame). Only the part of the solid above the table (z ≥ 0) exists.
    pub fn intersect(&self, ray: &Ray) -> Option<Hit> {
        match *self {
            RockShape::EllipsoidCap { semi_axes_m: [a, b, c], centre_z_m } => {
                let scale = Vector3::new(1.0 / a, 1.0 / b, 1.0 / c);
                let o = (ray.origin - Vector3::new(0.0, 0.0, centre_z_m)).component_mul(&scale);
                let d = ray.direction.component_mul(&scale);
                let t = first_root(d.dot(&d), 2.0 * o.dot(&d), o.dot(&o) - 1.0, |t| ray.at(t).z >= 0.0)?;
                let p = ray.at(t) - Vector3::new(0.0, 0.0, centre_z_m);
                let normal = Vector3::new(p.x / (a * a), p.y / (b * b), p.z / (c * c)).normalize();
                Some(Hit { t, normal })
            }
            RockShape::ParaboloidBump { height_m, curvatures_per_m: [kx, ky] } => {
                let (o, d) = (ray.origin, ray.direction);
                // f(p) = z − h + ½(κx x² + κy y²) = 0 along the ray.
                let qa = 0.5 * (kx * d.x * d.x + ky * d.y * d.y);
                let qb = d.z + kx * o.x * d.x + ky * o.y * d.y;
                let qc = o.z - height_m + 0.5 * (kx * o.x * o.x + ky * o.y * o.y);
                let t = first_root(qa, qb, qc, |t| ray.at(t).z >= 0.0)?;
                let p = ray.at(t);
                Some(Hit { t, normal: Vector3::new(kx * p.x, ky * p.y, 1.0).normalize() })
            }
            RockShape::FlatBoulder { radius_m, height_m, top_slope: [sx, sy] } => {
                let (o, d) = (ray.origin, ray.direction);
                let top_z = |p: &Vector3<f64>| height_m + sx * p.x + sy * p.y;
                let mut best: Option<Hit> = None;
                // Top plane z − sx·x − sy·y = h, inside the circle.
                let denom = d.z - sx * d.x - sy * d.y;
                if denom.abs() > 1e-15 {
                    let t = (height_m - (o.z - sx * o.x - sy * o.y)) / denom;
                    let p = ray.at(t);
                    if t > T_MIN && p.x * p.x + p.y * p.y <= radius_m * radius_m {
                        best = Some(Hit { t, normal: Vector3::new(-sx, -sy, 1.0).normalize() });
                    }
                }
                // Side wall x² + y² = r², 0 ≤ z ≤ top.
                let t_side =
                    first_root(d.x * d.x + d.y * d.y, 2.0 * (o.x * d.x + o.y * d.y), o.x * o.x + o.y * o.y - radius_m * radius_m, |t| {
                        let p = ray.at(t);
                        p.z >= 0.0 && p.z <= top_z(&p)
                    });
                if let Some(t) = t_side {
                    if best.is_none_or(|hit| t < hit.t) {
                        let p = ray.at(t);
                        best = Some(Hit { t, normal: Vector3::new(p.x, p.y, 0.0) / radius_m });
                    }
                }
                best
            }
            RockShape::LyingCylinder { radius_m, length_m, sunk_m } => {
                let (o, d) = (ray.origin, ray.direction);
                let half = length_m / 2.0;
                let axis_z = radius_m - sunk_m;
                let mut best: Option<Hit> = None;
                // Side y² + (z − z_axis)² = r², |x| ≤ l/2.
                let oz = o.z - axis_z;
                let t_side =
                    first_root(d.y * d.y + d.z * d.z, 2.0 * (o.y * d.y + oz * d.z), o.y * o.y + oz * oz - radius_m * radius_m, |t| {
                        ray.at(t).x.abs() <= half
                    });
                if let Some(t) = t_side {
                    let p = ray.at(t);
                    best = Some(Hit { t, normal: Vector3::new(0.0, p.y, p.z - axis_z) / radius_m });
                }
                // End caps x = ±l/2 inside the disc.
                if d.x.abs() > 1e-15 {
                    for sign in [-1.0, 1.0] {
                        let t = (sign * half - o.x) / d.x;
                        let p = ray.at(t);
                        let inside = p.y * p.y + (p.z - axis_z).powi(2) <= radius_m * radius_m;
                        if t > T_MIN && inside && best.is_none_or(|hit| t < hit.t) {
                            best = Some(Hit { t, normal: Vector3::new(sign, 0.0, 0.0) });
                        }
                    }
                }
                best
            }
        }
    }

    /// Foothold geometry in the rock frame (the `*_in_world` fields hold rock-frame values here).
    pub(super) fn local_foothold(&self) -> Foothold {
        let foothold =
            |top: Vector3<f64>, normal: Vector3<f64>, direction_x: Vector3<f64>, k: [f64; 2], kind: &'static str, radius: f64| Foothold {
                top_in_world: top,
                normal_in_world: normal,
                direction_x_in_world: direction_x,
                curvatures_per_m: k,
                surface_type: kind,
                top_radius_m: radius,
            };
        let up = Vector3::z();
        match *self {
            RockShape::EllipsoidCap { semi_axes_m: [a, b, c], centre_z_m } => {
                let kind = if (a - b).abs() < 1e-12 { "circular_paraboloid" } else { "elliptic_paraboloid" };
                foothold(Vector3::new(0.0, 0.0, centre_z_m + c), up, Vector3::x(), [-c / (a * a), -c / (b * b)], kind, 0.5 * a.min(b))
            }
            RockShape::ParaboloidBump { height_m, curvatures_per_m: [kx, ky] } => {
                let kind = if (kx - ky).abs() < 1e-12 { "circular_paraboloid" } else { "elliptic_paraboloid" };
                let radius = 0.5 * (2.0 * height_m / kx.max(ky)).sqrt();
                foothold(Vector3::new(0.0, 0.0, height_m), up, Vector3::x(), [-kx, -ky], kind, radius)
            }
            RockShape::FlatBoulder { radius_m, height_m, top_slope: [sx, sy] } => {
                let normal = Vector3::new(-sx, -sy, 1.0).normalize();
                let direction_x = Vector3::new(1.0, 0.0, sx).normalize();
                foothold(Vector3::new(0.0, 0.0, height_m), normal, direction_x, [0.0, 0.0], "plane", radius_m)
            }
            RockShape::LyingCylinder { radius_m, length_m, sunk_m } => foothold(
                Vector3::new(0.0, 0.0, 2.0 * radius_m - sunk_m),
                up,
                Vector3::x(),
                [0.0, -1.0 / radius_m],
                "cylindric_paraboloid",
                (0.5 * length_m).min(0.5 * radius_m),
            ),
        }
    }
}

impl Rock {
    /// Places `shape` at `(x, y)` on the table rotated by `yaw` about z; the station is `standoff`
    /// behind it along −x, facing +x.
    pub fn new(name: &str, shape: RockShape, trained: bool, x: f64, y: f64, yaw: f64, standoff_m: f64) -> Result<Self, SceneError> {
        shape.validate().map_err(|reason| SceneError::InvalidRock { name: name.to_string(), reason })?;
        Ok(Self {
            name: name.to_string(),
            shape,
            trained,
            world_from_rock: Isometry3::from_parts(Translation3::new(x, y, 0.0), UnitQuaternion::from_euler_angles(0.0, 0.0, yaw)),
            bounds_in_rock: shape.bounds(),
            world_from_station: Isometry3::translation(x - standoff_m, y, 0.0),
            yaw_cos_sin: (yaw.cos(), yaw.sin()),
        })
    }

    /// Ground-truth foothold of the rock's top, in the world frame.
    pub fn foothold(&self) -> Foothold {
        let local = self.shape.local_foothold();
        Foothold {
            top_in_world: (self.world_from_rock * nalgebra::Point3::from(local.top_in_world)).coords,
            normal_in_world: self.world_from_rock.rotation * local.normal_in_world,
            direction_x_in_world: self.world_from_rock.rotation * local.direction_x_in_world,
            ..local
        }
    }

    /// Bounding sphere (centre in world, radius) of the solid.
    pub fn bounding_sphere(&self) -> (Vector3<f64>, f64) {
        let [min, max] = self.bounds_in_rock;
        let centre = (min + max) / 2.0;
        ((self.world_from_rock * nalgebra::Point3::from(centre)).coords, (max - min).norm() / 2.0)
    }

    /// Nearest hit of a world ray (normal in world).
    #[inline]
    pub fn intersect_world(&self, ray: &Ray) -> Option<Hit> {
        let (c, s) = self.yaw_cos_sin;
        // rock_from_world = Rz(−yaw)·(p − t).
        let to_rock = |v: Vector3<f64>| Vector3::new(c * v.x + s * v.y, -s * v.x + c * v.y, v.z);
        let local = Ray { origin: to_rock(ray.origin - self.world_from_rock.translation.vector), direction: to_rock(ray.direction) };
        let hit = self.shape.intersect(&local)?;
        let n = hit.normal;
        Some(Hit { t: hit.t, normal: Vector3::new(c * n.x - s * n.y, s * n.x + c * n.y, n.z) })
    }
}

/// Smallest root `t > T_MIN` of `a t² + b t + c` satisfying `accept` (handles `a ≈ 0`).
#[inline]
fn first_root(a: f64, b: f64, c: f64, accept: impl Fn(f64) -> bool) -> Option<f64> {
    if a.abs() < 1e-15 {
        if b.abs() < 1e-15 {
            return None;
        }
        let t = -c / b;
        return (t > T_MIN && accept(t)).then_some(t);
    }
    let discriminant = b * b - 4.0 * a * c;
    if discriminant < 0.0 {
        return None;
    }
    // Numerically stable roots.
    let q = -0.5 * (b + b.signum() * discriminant.sqrt());
    let (r1, r2) = if q.abs() < 1e-300 { (0.0, 0.0) } else { (q / a, c / q) };
    let (lo, hi) = if r1 < r2 { (r1, r2) } else { (r2, r1) };
    [lo, hi].into_iter().find(|&t| t > T_MIN && accept(t))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::default_training_rocks;
    use crate::scene::tests::down_ray;

    #[test]
    fn vertical_rays_hit_the_tops_at_their_heights() {
        for shape in default_training_rocks() {
            let f = shape.local_foothold();
            let (top, normal) = (f.top_in_world, f.normal_in_world);
            let hit = shape.intersect(&down_ray(top.x, top.y)).unwrap();
            assert!((1.0 - hit.t - top.z).abs() < 1e-9, "{shape:?}: {} vs {}", 1.0 - hit.t, top.z);
            assert!((hit.normal - normal).norm() < 1e-9, "{shape:?}");
        }
    }

    #[test]
    fn numeric_curvature_matches_the_foothold() {
        // Heights along the principal directions near the top fit z = ½κ s² (with the top normal up).
        for shape in default_training_rocks() {
            let f = shape.local_foothold();
            let (top, normal, direction_x, k) = (f.top_in_world, f.normal_in_world, f.direction_x_in_world, f.curvatures_per_m);
            if (normal - Vector3::z()).norm() > 1e-9 {
                continue; // tilted plane: curvature 0 checked by the flat test below
            }
            let direction_y = normal.cross(&direction_x);
            let s = 0.004;
            for (direction, kappa) in [(direction_x, k[0]), (direction_y, k[1])] {
                let p = top + direction * s;
                let z = 1.0 - shape.intersect(&down_ray(p.x, p.y)).unwrap().t;
                let numeric = 2.0 * (z - top.z) / (s * s);
                assert!((numeric - kappa).abs() < 0.05 * kappa.abs().max(1.0), "{shape:?}: {numeric} vs {kappa}");
            }
        }
    }

    #[test]
    fn tilted_flat_top_is_a_plane() {
        let shape = RockShape::FlatBoulder { radius_m: 0.07, height_m: 0.05, top_slope: [0.14, -0.05] };
        let f = shape.local_foothold();
        let (top, normal) = (f.top_in_world, f.normal_in_world);
        for (x, y) in [(0.03, 0.0), (-0.02, 0.04), (0.0, -0.05)] {
            let p = Vector3::new(x, y, 1.0 - shape.intersect(&down_ray(x, y)).unwrap().t);
            assert!((p - top).dot(&normal).abs() < 1e-9);
        }
        // A horizontal ray hits the side wall.
        let hit = shape.intersect(&Ray { origin: Vector3::new(-1.0, 0.0, 0.02), direction: Vector3::x() }).unwrap();
        assert!((hit.t - (1.0 - 0.07)).abs() < 1e-9 && (hit.normal + Vector3::x()).norm() < 1e-9);
        // Above the top edge misses.
        assert!(shape.intersect(&Ray { origin: Vector3::new(-1.0, 0.0, 0.2), direction: Vector3::x() }).is_none());
    }

    #[test]
    fn lying_cylinder_caps_and_side() {
        let shape = RockShape::LyingCylinder { radius_m: 0.05, length_m: 0.2, sunk_m: 0.0 };
        let hit = shape.intersect(&Ray { origin: Vector3::new(-1.0, 0.0, 0.05), direction: Vector3::x() }).unwrap();
        assert!((hit.t - 0.9).abs() < 1e-9 && (hit.normal + Vector3::x()).norm() < 1e-12);
        let hit = shape.intersect(&Ray { origin: Vector3::new(0.0, -1.0, 0.05), direction: Vector3::y() }).unwrap();
        assert!((hit.t - 0.95).abs() < 1e-9);
        assert!(shape.intersect(&down_ray(0.11, 0.0)).is_none());
    }

    #[test]
    fn yawed_rock_intersection_matches_isometry() {
        let shape = RockShape::EllipsoidCap { semi_axes_m: [0.09, 0.05, 0.04], centre_z_m: 0.0 };
        let rock = Rock::new("r", shape, true, 0.4, 0.3, 0.7, 0.2).unwrap();
        let ray = Ray { origin: Vector3::new(0.1, 0.05, 0.5), direction: Vector3::new(0.6, 0.5, -1.0) };
        let hit = rock.intersect_world(&ray).unwrap();
        let local = Ray {
            origin: rock.world_from_rock.inverse_transform_point(&ray.origin.into()).coords,
            direction: rock.world_from_rock.inverse_transform_vector(&ray.direction),
        };
        let reference = shape.intersect(&local).unwrap();
        assert!((hit.t - reference.t).abs() < 1e-12);
        assert!((hit.normal - rock.world_from_rock.rotation * reference.normal).norm() < 1e-12);
    }
}
