//! Pictures: the depth image with the fitted patches drawn as filled, outlined projections coloured
//! by validation result (J Fig. 6: valid red; rejected yellow = curvature, purple = residual,
//! green = coverage), and the hiking-saliency label mask (J Fig. 7-(ii): salient points red).

use std::path::{Path, PathBuf};

use nalgebra::{Vector2, Vector3};

use crate::mapper::{SeedOutcome, Verdict};
use crate::saliency::{Saliency, SaliencyLabel};
use patchwalk_fusion::camera::{DepthImage, Intrinsics};
use patchwalk_spl::patch::Patch;

/// Errors writing pictures.
#[derive(Debug, thiserror::Error)]
pub enum RenderError {
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("{path}: PNG encoding failed: {reason}")]
    Png { path: PathBuf, reason: String },
}

/// An 8-bit RGB picture.
#[derive(Debug, Clone, PartialEq)]
pub struct Rgb {
    pub width: usize,
    pub height: usize,
    pub pixels: Vec<[u8; 3]>,
}

/// J Fig. 6 colours.
pub const VALID: [u8; 3] = [230, 20, 20];
pub const CURVATURE: [u8; 3] = [240, 220, 0];
pub const RESIDUAL: [u8; 3] = [150, 40, 190];
pub const COVERAGE: [u8; 3] = [30, 200, 60];
/// Failed the tilt test (beyond J Fig. 6): orange.
pub const TILT: [u8; 3] = [255, 140, 0];
/// Failed the edge test (beyond J Fig. 6): cyan.
pub const EDGE: [u8; 3] = [0, 200, 230];
/// Failed the visibility test (beyond J Fig. 6): grey.
pub const UNSEEN: [u8; 3] = [150, 150, 150];

impl Rgb {
    /// Depth as grey levels (near = bright), invalid black.
    pub fn from_depth(depth: &DepthImage) -> Self {
        let valid = depth.depth_m.iter().copied().filter(|z| z.is_finite());
        let (lo, hi) = valid.fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), z| (lo.min(z), hi.max(z)));
        let span = (hi - lo).max(1e-6);
        let pixels = depth
            .depth_m
            .iter()
            .map(|&z| {
                if z.is_finite() {
                    let level = (40.0 + 200.0 * (1.0 - (z - lo) / span)) as u8;
                    [level; 3]
                } else {
                    [0; 3]
                }
            })
            .collect();
        Self { width: depth.width, height: depth.height, pixels }
    }

    fn blend(&mut self, x: i64, y: i64, colour: [u8; 3], alpha: f32) {
        if x < 0 || y < 0 || x >= self.width as i64 || y >= self.height as i64 {
            return;
        }
        if let Some(p) = self.pixels.get_mut(y as usize * self.width + x as usize) {
            for (c, &t) in p.iter_mut().zip(&colour) {
                *c = (f32::from(*c) * (1.0 - alpha) + f32::from(t) * alpha).round() as u8;
            }
        }
    }

    /// Fills a polygon (even-odd scanline) with `colour` at opacity `alpha`.
    pub fn fill_polygon(&mut self, polygon: &[Vector2<f64>], colour: [u8; 3], alpha: f32) {
        if polygon.len() < 3 {
            return;
        }
        let (y_min, y_max) = polygon.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), p| (lo.min(p.y), hi.max(p.y)));
        let y0 = y_min.ceil().max(0.0) as i64;
        let y1 = y_max.floor().min(self.height as f64 - 1.0) as i64;
        let mut crossings = Vec::new();
        for y in y0..=y1 {
            let yf = y as f64;
            crossings.clear();
            for (a, b) in polygon.iter().zip(polygon.iter().cycle().skip(1)) {
                if (a.y <= yf && b.y > yf) || (b.y <= yf && a.y > yf) {
                    crossings.push(a.x + (yf - a.y) / (b.y - a.y) * (b.x - a.x));
                }
            }
            crossings.sort_by(f64::total_cmp);
            for pair in crossings.chunks_exact(2) {
                let x0 = pair[0].ceil().max(0.0) as i64;
                let x1 = pair[1].floor().min(self.width as f64 - 1.0) as i64;
                for x in x0..=x1 {
                    self.blend(x, y, colour, alpha);
                }
            }
        }
    }

    /// Draws a closed polyline (1 px, DDA).
    pub fn outline(&mut self, polygon: &[Vector2<f64>], colour: [u8; 3]) {
        for (a, b) in polygon.iter().zip(polygon.iter().cycle().skip(1)) {
            let steps = (b - a).abs().max().ceil().clamp(1.0, 10_000.0) as usize;
            for i in 0..=steps {
                let p = a + (b - a) * (i as f64 / steps as f64);
                self.blend(p.x.round() as i64, p.y.round() as i64, colour, 1.0);
            }
        }
    }

    /// Writes the picture as an 8-bit RGB PNG.
    pub fn save_png(&self, path: &Path) -> Result<(), RenderError> {
        let io = |source| RenderError::Io { path: path.to_path_buf(), source };
        let png_error = |e: png::EncodingError| RenderError::Png { path: path.to_path_buf(), reason: e.to_string() };
        let file = std::fs::File::create(path).map_err(io)?;
        let mut encoder = png::Encoder::new(std::io::BufWriter::new(file), self.width as u32, self.height as u32);
        encoder.set_color(png::ColorType::Rgb);
        encoder.set_depth(png::BitDepth::Eight);
        let mut writer = encoder.write_header().map_err(png_error)?;
        let bytes: Vec<u8> = self.pixels.iter().flatten().copied().collect();
        writer.write_image_data(&bytes).map_err(png_error)?;
        writer.finish().map_err(png_error)
    }
}

/// The colour of a verdict (J Fig. 6), `None` for seeds without a fitted patch.
pub fn verdict_colour(verdict: &Verdict) -> Option<[u8; 3]> {
    match verdict {
        Verdict::Valid { .. } => Some(VALID),
        Verdict::Curvature => Some(CURVATURE),
        Verdict::Residual => Some(RESIDUAL),
        Verdict::Coverage => Some(COVERAGE),
        Verdict::Tilt => Some(TILT),
        Verdict::Edge => Some(EDGE),
        Verdict::Unseen => Some(UNSEEN),
        Verdict::TooFewPoints | Verdict::FitFailed(_) | Verdict::Skipped => None,
    }
}

/// The patch boundary sampled in its local xy-plane, lifted onto the surface (patch frame = camera
/// frame for `patch_in_camera`) and projected into the image.
pub fn projected_outline(patch: &Patch, intrinsics: &Intrinsics) -> Vec<Vector2<f64>> {
    let boundary: Vec<Vector2<f64>> = match patch.boundary_vertices() {
        Some(vertices) => vertices
            .iter()
            .zip(vertices.iter().cycle().skip(1))
            .flat_map(|(a, b)| (0..12).map(move |i| a + (b - a) * (f64::from(i) / 12.0)))
            .collect(),
        None => {
            let h = patch.boundary_half_extents();
            (0..64)
                .map(|i| {
                    let t = f64::from(i) / 64.0 * std::f64::consts::TAU;
                    Vector2::new(h.x * t.cos(), h.y * t.sin())
                })
                .collect()
        }
    };
    boundary
        .iter()
        .filter_map(|u| patch.explicit_world(u))
        .filter_map(|p: Vector3<f64>| intrinsics.project(&p))
        .map(|(u, v)| Vector2::new(u, v))
        .collect()
}

/// The per-frame picture: depth with every fitted patch filled (semi-transparent) and outlined in
/// its verdict colour.
pub fn render_patches(depth: &DepthImage, intrinsics: &Intrinsics, outcomes: &[SeedOutcome]) -> Rgb {
    let mut picture = Rgb::from_depth(depth);
    for outcome in outcomes {
        let (Some(colour), Some(patch)) = (verdict_colour(&outcome.verdict), &outcome.patch_in_camera) else { continue };
        let outline = projected_outline(patch, intrinsics);
        picture.fill_polygon(&outline, colour, 0.45);
        picture.outline(&outline, colour);
    }
    picture
}

/// Colour of a saliency label: salient red (J Fig. 7), dropped by DoN orange, by DoNG blue,
/// no normal dark blue, outside the DtFP ball dark grey, invalid black.
pub fn label_colour(label: SaliencyLabel) -> [u8; 3] {
    match label {
        SaliencyLabel::Invalid => [0, 0, 0],
        SaliencyLabel::Distant => [60, 60, 60],
        SaliencyLabel::NoNormal => [20, 20, 90],
        SaliencyLabel::Irregular => [255, 140, 0],
        SaliencyLabel::Steep => [40, 120, 255],
        SaliencyLabel::Salient => [230, 20, 20],
        SaliencyLabel::DepthEdge => [200, 0, 200],
        SaliencyLabel::ImageBorder => [120, 60, 0],
        SaliencyLabel::Uneven => [255, 220, 0],
    }
}

/// The saliency mask of D as a picture.
pub fn render_saliency(saliency: &Saliency) -> Rgb {
    Rgb { width: saliency.width, height: saliency.height, pixels: saliency.labels.iter().map(|&l| label_colour(l)).collect() }
}

#[cfg(test)]
mod tests {
    use super::*;
    use patchwalk_spl::patch::{BoundaryType, SurfaceType};

    #[test]
    fn polygon_fill_covers_the_inside_only() {
        let mut picture = Rgb { width: 20, height: 20, pixels: vec![[0; 3]; 400] };
        let square = [Vector2::new(5.0, 5.0), Vector2::new(14.0, 5.0), Vector2::new(14.0, 14.0), Vector2::new(5.0, 14.0)];
        picture.fill_polygon(&square, VALID, 1.0);
        let filled = picture.pixels.iter().filter(|p| **p == VALID).count();
        assert_eq!(filled, 9 * 10);
        assert_eq!(picture.pixels[0], [0; 3]);
        assert_eq!(picture.pixels[10 * 20 + 10], VALID);
        // Off-image polygons are clipped, not a panic.
        picture.fill_polygon(&[Vector2::new(-50.0, -50.0), Vector2::new(100.0, -40.0), Vector2::new(0.0, 100.0)], COVERAGE, 0.5);
        picture.outline(&[Vector2::new(-50.0, -50.0), Vector2::new(100.0, 100.0)], RESIDUAL);
    }

    #[test]
    fn patch_outline_projects_around_its_centre_and_png_round_trips() {
        let intrinsics = Intrinsics::primesense_default();
        let patch = Patch::new(
            SurfaceType::Plane,
            BoundaryType::Circle,
            vec![0.05],
            nalgebra::Vector2::zeros(),
            Vector3::zeros(),
            Vector3::new(0.0, 0.0, 1.0),
        )
        .unwrap();
        let outline = projected_outline(&patch, &intrinsics);
        assert_eq!(outline.len(), 64);
        for p in &outline {
            // Radius 0.05 m at 1 m: 26.25 px around the principal point.
            assert!(((p - Vector2::new(319.5, 239.5)).norm() - 26.25).abs() < 1e-6);
        }
        let depth = DepthImage::new(640, 480, vec![1.0; 640 * 480]).unwrap();
        let mut picture = Rgb::from_depth(&depth);
        picture.fill_polygon(&outline, VALID, 1.0);
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("p.png");
        picture.save_png(&path).unwrap();
        let decoder = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(&path).unwrap()));
        let reader = decoder.read_info().unwrap();
        assert_eq!((reader.info().width, reader.info().height), (640, 480));
    }
}
