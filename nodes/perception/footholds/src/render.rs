//! A picture like CNN Fig. 6: the depth image in grey with the predicted footholds of the regions
//! the method calls positive, a dot for a true positive and a cross for a false positive; the
//! labelled footholds it missed (false negatives) as small hollow squares.

use std::path::Path;

use patchwalk_fusion::camera::DepthImage;

use crate::error::FootholdError;

/// What kind of mark to draw.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Mark {
    TruePositive,
    FalsePositive,
    FalseNegative,
}

/// An RGB picture of a depth image.
pub struct Picture {
    pub width: usize,
    pub height: usize,
    pub rgb: Vec<u8>,
}

impl Picture {
    /// Grey depth (near bright, far dark) between the 2nd and 98th percentile; invalid pixels dark blue.
    pub fn of_depth(depth: &DepthImage) -> Self {
        let mut valid: Vec<f32> = depth.depth_m.iter().copied().filter(|d| d.is_finite()).collect();
        valid.sort_by(f32::total_cmp);
        let pick = |q: f64| valid.get(((valid.len().saturating_sub(1)) as f64 * q) as usize).copied().unwrap_or(1.0);
        let (near, far) = (pick(0.02), pick(0.98).max(pick(0.02) + 1e-3));
        let mut rgb = Vec::with_capacity(depth.depth_m.len() * 3);
        for d in &depth.depth_m {
            if d.is_finite() {
                let g = (255.0 * (1.0 - ((d - near) / (far - near)).clamp(0.0, 1.0))) as u8;
                rgb.extend_from_slice(&[g, g, g]);
            } else {
                rgb.extend_from_slice(&[10, 10, 40]);
            }
        }
        Self { width: depth.width, height: depth.height, rgb }
    }

    fn put(&mut self, u: i64, v: i64, colour: [u8; 3]) {
        if u >= 0 && v >= 0 && (u as usize) < self.width && (v as usize) < self.height {
            let i = 3 * (v as usize * self.width + u as usize);
            self.rgb[i..i + 3].copy_from_slice(&colour);
        }
    }

    /// Draws a mark at pixel (u, v).
    pub fn mark(&mut self, u: f64, v: f64, mark: Mark) {
        let (u, v) = (u.round() as i64, v.round() as i64);
        match mark {
            Mark::TruePositive => {
                for dv in -4i64..=4 {
                    for du in -4i64..=4 {
                        if du * du + dv * dv <= 16 {
                            self.put(u + du, v + dv, [230, 20, 20]);
                        }
                    }
                }
            }
            Mark::FalsePositive => {
                for t in -5i64..=5 {
                    for w in 0..2 {
                        self.put(u + t, v + t + w, [255, 200, 0]);
                        self.put(u + t, v - t + w, [255, 200, 0]);
                    }
                }
            }
            Mark::FalseNegative => {
                for t in -3i64..=3 {
                    for (a, b) in [(t, -3), (t, 3), (-3, t), (3, t)] {
                        self.put(u + a, v + b, [40, 120, 255]);
                    }
                }
            }
        }
    }

    /// Writes an 8-bit RGB PNG.
    pub fn save_png(&self, path: &Path) -> Result<(), FootholdError> {
        let picture_error = |reason: String| FootholdError::Picture { path: path.to_path_buf(), reason };
        if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
            std::fs::create_dir_all(parent).map_err(crate::error::io_error(parent))?;
        }
        let file = std::fs::File::create(path).map_err(crate::error::io_error(path))?;
        let mut encoder = png::Encoder::new(std::io::BufWriter::new(file), self.width as u32, self.height as u32);
        encoder.set_color(png::ColorType::Rgb);
        encoder.set_depth(png::BitDepth::Eight);
        let mut writer = encoder.write_header().map_err(|e| picture_error(e.to_string()))?;
        writer.write_image_data(&self.rgb).map_err(|e| picture_error(e.to_string()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn marks_are_drawn_and_the_png_reads_back() {
        let depth = DepthImage::new(40, 30, (0..1200).map(|i| 0.5 + 0.001 * i as f32).collect()).unwrap();
        let mut picture = Picture::of_depth(&depth);
        picture.mark(10.0, 10.0, Mark::TruePositive);
        picture.mark(30.0, 20.0, Mark::FalsePositive);
        picture.mark(5.0, 25.0, Mark::FalseNegative);
        assert_eq!(&picture.rgb[3 * (10 * 40 + 10)..3 * (10 * 40 + 10) + 3], &[230, 20, 20]);
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("p.png");
        picture.save_png(&path).unwrap();
        let decoder = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(&path).unwrap()));
        let reader = decoder.read_info().unwrap();
        assert_eq!((reader.info().width, reader.info().height), (40, 30));
    }
}
