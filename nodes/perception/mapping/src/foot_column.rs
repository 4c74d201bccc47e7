//! The foot disc's column for the edge test (`patchwalk_spl::validate::edge`): every point of the
//! organized cloud C that gravity's up carries into the fitted patch's boundary, at most `h` above or
//! below its tangent plane ([`FootColumn`]) — the terrain the foot would stand on or hit as it comes
//! down, wherever it is, not only the r-ball's points the patch was fitted to (a ball around a seed
//! on a stair nosing never reaches the tread below).
//!
//! The column lies inside a prism (the boundary's bounding box slid by ±h along up); it is convex,
//! so with all its corners in front of the camera its image lies inside the bounding rectangle of
//! the eight projected corners, and only that rectangle is scanned. Each pixel's point is then tested
//! against the column. Large rectangles (a column seen along its axis from close by) are scanned on
//! a regular sub-grid of at most `max_pixels` pixels, which keeps the point density uniform.
//! The same scan gives the visibility test (`patchwalk_spl::validate::visibility`) its pixels: the
//! disc lies inside the column, so every pixel whose ray enters it lies in the rectangle.

use nalgebra::Vector3;
use patchwalk_fusion::camera::Intrinsics;
use patchwalk_spl::patch::Patch;
use patchwalk_spl::validate::{DiscView, FootColumn, PixelView};

use crate::acquire::OrganizedCloud;

/// How far (pixels) beyond a hole in the foot disc its nearest measured pixel is looked for.
pub const HOLE_SEARCH_PX: usize = 64;

/// Pixels scanned per column at most (a sub-grid beyond): a 5 cm disc's column in a 640×480 Kinect
/// frame at 1 m is about 100×250 pixels.
pub const DEFAULT_MAX_PIXELS: usize = 16_384;

/// Points of C in the column of `patch` along `up` (both in the camera frame) of half height
/// `half_height_m`, appended to `out` (cleared first); with `view`, every scanned pixel's ray and
/// depth are added to it too (the disc lies inside the column, so its image inside the scanned
/// rectangle): what the camera measured over the foot disc.
#[allow(clippy::too_many_arguments)]
pub fn foot_column(
    cloud: &OrganizedCloud,
    intrinsics: &Intrinsics,
    patch: &Patch,
    up: &Vector3<f64>,
    half_height_m: f64,
    max_pixels: usize,
    out: &mut Vec<Vector3<f64>>,
    mut view: Option<&mut DiscView>,
) {
    out.clear();
    if !(half_height_m.is_finite() && half_height_m >= 0.0 && patch.boundary_half_extents().iter().all(|v| v.is_finite())) {
        return;
    }
    let (width, height) = (cloud.width.min(intrinsics.width), cloud.height.min(intrinsics.height));
    if width == 0 || height == 0 {
        return;
    }
    let column = FootColumn::new(patch, Some(up), half_height_m);
    let mut rect = Some((f64::INFINITY, f64::INFINITY, f64::NEG_INFINITY, f64::NEG_INFINITY));
    for p in column.corners() {
        // A corner at or behind the camera plane: the column's image is unbounded, scan everything.
        match (p.z > 1e-3).then(|| intrinsics.project(&p)).flatten() {
            Some((u, v)) => {
                if let Some(r) = rect.as_mut() {
                    *r = (r.0.min(u), r.1.min(v), r.2.max(u), r.3.max(v));
                }
            }
            None => rect = None,
        }
    }
    let (u0, v0, u1, v1) = match rect {
        Some((a, b, c, d)) => {
            if !(c >= 0.0 && d >= 0.0 && a <= (width - 1) as f64 && b <= (height - 1) as f64) {
                return;
            }
            let clip = |x: f64, n: usize| x.clamp(0.0, (n - 1) as f64) as usize;
            (clip(a.floor(), width), clip(b.floor(), height), clip(c.ceil(), width), clip(d.ceil(), height))
        }
        None => (0, 0, width - 1, height - 1),
    };
    // The disc's centre in the image: holes are looked beyond away from it.
    let centre = (patch.center.z > 1e-3).then(|| intrinsics.project(&patch.center)).flatten();
    let pixels = (u1 - u0 + 1) * (v1 - v0 + 1);
    let max_pixels = max_pixels.max(1);
    let stride = if pixels > max_pixels { ((pixels as f64 / max_pixels as f64).sqrt().ceil() as usize).max(1) } else { 1 };
    for v in (v0..=v1).step_by(stride) {
        for u in (u0..=u1).step_by(stride) {
            let Some(p) = cloud.points_in_camera.get(v * cloud.width + u) else { continue };
            let p = p.cast::<f64>();
            if let Some(view) = view.as_deref_mut() {
                let ray = Vector3::new((u as f64 - intrinsics.cx) / intrinsics.fx, (v as f64 - intrinsics.cy) / intrinsics.fy, 1.0);
                if view.add(&Vector3::zeros(), &ray, Some(p.z)) == PixelView::Missing {
                    if let Some(beyond) = centre.and_then(|c| measured_beyond(cloud, c, (u, v))) {
                        view.add_beyond_hole(&beyond);
                    }
                }
            }
            if column.local_if_inside(&p).is_some() {
                out.push(p);
            }
        }
    }
}

/// The first measured point on the image line from `centre` through pixel `hole`, beyond the hole
/// (at most [`HOLE_SEARCH_PX`] pixels on), if any.
fn measured_beyond(cloud: &OrganizedCloud, centre: (f64, f64), hole: (usize, usize)) -> Option<Vector3<f64>> {
    let (du, dv) = (hole.0 as f64 - centre.0, hole.1 as f64 - centre.1);
    let length = du.hypot(dv);
    // A hole at the centre has no outward direction.
    if length.is_nan() || length < 0.5 {
        return None;
    }
    let (du, dv) = (du / length, dv / length);
    (1..=HOLE_SEARCH_PX).find_map(|step| {
        let (u, v) = ((hole.0 as f64 + du * step as f64).round(), (hole.1 as f64 + dv * step as f64).round());
        if u < 0.0 || v < 0.0 || u >= cloud.width as f64 || v >= cloud.height as f64 {
            return Some(None);
        }
        let p = cloud.points_in_camera.get(v as usize * cloud.width + u as usize)?;
        p.iter().all(|c| c.is_finite()).then(|| Some(p.cast::<f64>()))
    })?
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::acquire::organized_cloud;
    use patchwalk_fusion::camera::DepthImage;
    use patchwalk_spl::patch::{BoundaryType, SurfaceType};

    /// A camera 0.5 m above a floor with a 12 cm step at x = 0.02 (camera frame: looking straight down).
    fn step_cloud(intrinsics: &Intrinsics) -> OrganizedCloud {
        let mut depth = Vec::with_capacity(intrinsics.width * intrinsics.height);
        for _ in 0..intrinsics.height {
            for u in 0..intrinsics.width {
                let x = (u as f64 - intrinsics.cx) / intrinsics.fx;
                // Ray (x, y, 1): upper floor at z = 0.5, lower (x > 0.02) at z = 0.62.
                let z = if x * 0.5 > 0.02 { 0.62 } else { 0.5 };
                depth.push(z as f32);
            }
        }
        organized_cloud(&DepthImage::new(intrinsics.width, intrinsics.height, depth).unwrap(), intrinsics).unwrap()
    }

    fn disc_at(center: Vector3<f64>) -> Patch {
        // Normal towards the camera (−z in the camera frame).
        Patch::new(
            SurfaceType::Plane,
            BoundaryType::Circle,
            vec![0.05],
            nalgebra::Vector2::zeros(),
            Vector3::new(std::f64::consts::PI, 0.0, 0.0),
            center,
        )
        .unwrap()
    }

    #[test]
    fn the_column_holds_the_lower_tread_under_the_disc_and_matches_brute_force() {
        let intrinsics = Intrinsics::primesense_default().scaled(0.5);
        let cloud = step_cloud(&intrinsics);
        let patch = disc_at(Vector3::new(0.0, 0.0, 0.5));
        let mut out = Vec::new();
        let up = -Vector3::z();
        foot_column(&cloud, &intrinsics, &patch, &up, 0.25, usize::MAX, &mut out, None);
        let column = FootColumn::new(&patch, Some(&up), 0.25);
        let brute: Vec<_> =
            cloud.points_in_camera.iter().map(|p| p.cast::<f64>()).filter(|p| column.local_if_inside(p).is_some()).collect();
        assert_eq!(out, brute);
        let lower = out.iter().filter(|p| (p.z - 0.62).abs() < 1e-6).count();
        assert!(lower > 10 && lower < out.len(), "{lower} of {}", out.len());
        // A band lower than the step leaves the tread out; a capped scan keeps a uniform subset.
        foot_column(&cloud, &intrinsics, &patch, &up, 0.1, usize::MAX, &mut out, None);
        assert!(out.iter().all(|p| (p.z - 0.5).abs() < 1e-6));
        foot_column(&cloud, &intrinsics, &patch, &up, 0.25, 100, &mut out, None);
        assert!(!out.is_empty() && out.len() < brute.len() / 2);
    }

    #[test]
    fn columns_outside_the_view_or_through_the_camera_are_handled() {
        let intrinsics = Intrinsics::primesense_default().scaled(0.25);
        let cloud = step_cloud(&intrinsics);
        let mut out = vec![Vector3::zeros()];
        let up = -Vector3::z();
        foot_column(&cloud, &intrinsics, &disc_at(Vector3::new(5.0, 0.0, 0.5)), &up, 0.25, usize::MAX, &mut out, None);
        assert!(out.is_empty());
        // A column reaching the camera plane scans the whole image.
        foot_column(&cloud, &intrinsics, &disc_at(Vector3::new(0.0, 0.0, 0.2)), &up, 0.4, usize::MAX, &mut out, None);
        assert!(!out.is_empty());
        foot_column(&cloud, &intrinsics, &disc_at(Vector3::new(0.0, 0.0, 0.5)), &up, f64::NAN, usize::MAX, &mut out, None);
        assert!(out.is_empty());
    }

    #[test]
    fn the_view_sees_through_the_rim_over_the_step_and_counts_the_disc_on_the_tread_whole() {
        let intrinsics = Intrinsics::primesense_default().scaled(0.5);
        let cloud = step_cloud(&intrinsics);
        let up = -Vector3::z();
        let mut out = Vec::new();
        // A disc centred on the step's edge: the rays over its far half pass the upper floor and land
        // on the lower one, 12 cm behind the disc.
        let mut over = DiscView::new(&disc_at(Vector3::new(0.02, 0.0, 0.5)), 0.02);
        foot_column(&cloud, &intrinsics, &disc_at(Vector3::new(0.02, 0.0, 0.5)), &up, 0.25, usize::MAX, &mut out, Some(&mut over));
        assert!(over.pixels > 100 && (over.through_fraction() - 0.5).abs() < 0.1, "{over:?}");
        // A disc wholly on the upper floor is seen whole; the view does not change the column.
        let patch = disc_at(Vector3::new(-0.05, 0.0, 0.5));
        let mut on = DiscView::new(&patch, 0.02);
        foot_column(&cloud, &intrinsics, &patch, &up, 0.25, usize::MAX, &mut out, Some(&mut on));
        let with_view = out.clone();
        foot_column(&cloud, &intrinsics, &patch, &up, 0.25, usize::MAX, &mut out, None);
        assert_eq!(with_view, out);
        assert!(on.pixels > 100 && on.unseen_fraction() == 0.0, "{on:?}");
    }

    /// The step cloud with no depth in a band of image columns (the drop's face seen edge-on, or a
    /// hole of the sensor).
    fn with_hole(cloud: &OrganizedCloud, intrinsics: &Intrinsics, x_range: std::ops::Range<f64>) -> OrganizedCloud {
        let mut holed = cloud.clone();
        for (i, p) in holed.points_in_camera.iter_mut().enumerate() {
            let x = ((i % cloud.width) as f64 - intrinsics.cx) / intrinsics.fx * 0.5;
            if x_range.contains(&x) {
                *p = Vector3::repeat(f32::NAN);
            }
        }
        holed
    }

    #[test]
    fn a_hole_at_the_rim_opens_onto_the_drop_beyond_it_and_a_hole_in_the_floor_does_not() {
        let intrinsics = Intrinsics::primesense_default().scaled(0.5);
        let cloud = step_cloud(&intrinsics);
        let up = -Vector3::z();
        let mut out = Vec::new();
        // A disc on the upper floor whose rim reaches 1 cm past the step's edge (x = 2 cm); no depth
        // from 1.2 to 3 cm: the rim's pixels are holes with the lower floor beyond them.
        let patch = disc_at(Vector3::new(-0.02, 0.0, 0.5));
        let holed = with_hole(&cloud, &intrinsics, 0.012..0.03);
        let mut view = DiscView::new(&patch, 0.02);
        foot_column(&holed, &intrinsics, &patch, &up, 0.25, usize::MAX, &mut out, Some(&mut view));
        // Nearly all of the rim's holes have the lower floor beyond them (a few at the disc's top
        // and bottom look along the band and find the border of the image or nothing).
        assert!(view.missing > 20 && view.open * 10 >= view.missing * 8 && view.through == 0, "{view:?}");
        assert!(view.open_fraction() > 0.03, "{view:?}");
        // A disc wholly on the upper floor with a hole band inside it: the floor goes on beyond.
        let patch = disc_at(Vector3::new(-0.05, 0.0, 0.5));
        let flat = with_hole(&cloud, &intrinsics, -0.06..-0.05);
        let mut view = DiscView::new(&patch, 0.02);
        foot_column(&flat, &intrinsics, &patch, &up, 0.25, usize::MAX, &mut out, Some(&mut view));
        assert!(view.missing > 20 && view.open == 0 && view.open_fraction() == 0.0, "{view:?}");
    }
}
