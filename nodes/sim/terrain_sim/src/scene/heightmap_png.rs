//! Heightmap images as terrains: a PNG whose grey level is the height.
//!
//! Accepted: 8- and 16-bit grey, grey + alpha, RGB and RGBA (palette and 1/2/4-bit grey are
//! expanded to 8 bits). The level of a pixel is the mean of R, G and B for colour images (the grey
//! heightmaps of elevation-mapping stacks often carry ±1-level colour noise), the grey value
//! otherwise; it maps linearly to metres, level 0 → `height_min_m`, the largest level (255 or
//! 65535) → `height_max_m`. Alpha is ignored unless `alpha_is_mask` (then alpha 0 is a hole).
//!
//! Orientation: the image is a map seen from above with north up: column → +x, the image's bottom
//! row is grid row 0 (smallest y), so the top of the picture is +y. Pixel centres are the grid
//! samples, `metres_per_pixel` apart, sample (0, 0) (bottom-left pixel) at `origin_m`. Between
//! samples the surface is bilinear ([`Heightfield`]), so one-level steps of an 8-bit map (3.9 mm for
//! 0–1 m) become slopes across a pixel rather than stairs.

use std::io::Cursor;

use serde::{Deserialize, Serialize};

use super::heightfield::{Heightfield, HeightfieldError};

/// Why a heightmap image cannot be used.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum HeightmapError {
    #[error("not a readable PNG: {0}")]
    Png(String),
    #[error("unsupported PNG: {0}")]
    Unsupported(String),
    #[error("invalid heightmap parameter: {0}")]
    Parameter(String),
    #[error(transparent)]
    Heightfield(#[from] HeightfieldError),
}

/// How pixels become heights and positions.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct HeightmapScale {
    /// Distance between pixel centres (m).
    pub metres_per_pixel: f64,
    /// Height of level 0 (m).
    pub height_min_m: f64,
    /// Height of the largest level (m).
    pub height_max_m: f64,
    /// World `(x, y)` of the bottom-left pixel's centre (m).
    pub origin_m: [f64; 2],
    /// Alpha 0 = no surface (a hole).
    pub alpha_is_mask: bool,
}

impl Default for HeightmapScale {
    fn default() -> Self {
        // The elevation-mapping benchmark terrains: 4 cm per pixel, 0–1 m.
        Self { metres_per_pixel: 0.04, height_min_m: 0.0, height_max_m: 1.0, origin_m: [0.0, 0.0], alpha_is_mask: false }
    }
}

/// Decodes a PNG heightmap (see the module docs).
pub fn decode_heightmap(bytes: &[u8], scale: &HeightmapScale) -> Result<Heightfield, HeightmapError> {
    if !(scale.height_min_m.is_finite() && scale.height_max_m.is_finite()) {
        return Err(HeightmapError::Parameter(format!("height range {} .. {} m must be finite", scale.height_min_m, scale.height_max_m)));
    }
    if !(scale.metres_per_pixel.is_finite() && scale.metres_per_pixel > 0.0) {
        return Err(HeightmapError::Parameter(format!("metres_per_pixel = {} must be positive", scale.metres_per_pixel)));
    }
    let mut decoder = png::Decoder::new(Cursor::new(bytes));
    decoder.set_transformations(png::Transformations::EXPAND);
    let mut reader = decoder.read_info().map_err(|e| HeightmapError::Png(e.to_string()))?;
    let size = reader.output_buffer_size().ok_or_else(|| HeightmapError::Unsupported("image too large".into()))?;
    let mut buffer = vec![0u8; size];
    let info = reader.next_frame(&mut buffer).map_err(|e| HeightmapError::Png(e.to_string()))?;
    let (width, height) = (info.width as usize, info.height as usize);
    let channels = match info.color_type {
        png::ColorType::Grayscale => 1,
        png::ColorType::GrayscaleAlpha => 2,
        png::ColorType::Rgb => 3,
        png::ColorType::Rgba => 4,
        png::ColorType::Indexed => return Err(HeightmapError::Unsupported("palette image not expanded".into())),
    };
    let (bytes_per_sample, max_level) = match info.bit_depth {
        png::BitDepth::Eight => (1, 255.0),
        png::BitDepth::Sixteen => (2, 65535.0),
        other => return Err(HeightmapError::Unsupported(format!("bit depth {other:?}"))),
    };
    let sample = |row: &[u8], i: usize| -> f64 {
        match bytes_per_sample {
            1 => row.get(i).map_or(f64::NAN, |&b| f64::from(b)),
            _ => row.get(2 * i..2 * i + 2).map_or(f64::NAN, |b| f64::from(u16::from_be_bytes([b[0], b[1]]))),
        }
    };
    let span = scale.height_max_m - scale.height_min_m;
    let mut heights = vec![f32::NAN; width * height];
    for image_row in 0..height {
        let row = buffer.get(image_row * info.line_size..(image_row + 1) * info.line_size).unwrap_or(&[]);
        let grid_row = height - 1 - image_row;
        for column in 0..width {
            let base = column * channels;
            let level = match channels {
                1 | 2 => sample(row, base),
                _ => (sample(row, base) + sample(row, base + 1) + sample(row, base + 2)) / 3.0,
            };
            let alpha = match channels {
                2 => sample(row, base + 1),
                4 => sample(row, base + 3),
                _ => max_level,
            };
            if let Some(h) = heights.get_mut(grid_row * width + column) {
                *h = if scale.alpha_is_mask && alpha == 0.0 { f32::NAN } else { (scale.height_min_m + span * level / max_level) as f32 };
            }
        }
    }
    Ok(Heightfield::new(width, height, scale.metres_per_pixel, scale.origin_m, heights)?)
}

/// Encodes levels (row-major, top image row first) as a PNG (tests, tools).
pub fn encode_png(width: u32, height: u32, color: png::ColorType, depth: png::BitDepth, data: &[u8]) -> Result<Vec<u8>, HeightmapError> {
    let mut out = Vec::new();
    {
        let mut encoder = png::Encoder::new(&mut out, width, height);
        encoder.set_color(color);
        encoder.set_depth(depth);
        let mut writer = encoder.write_header().map_err(|e| HeightmapError::Png(e.to_string()))?;
        writer.write_image_data(data).map_err(|e| HeightmapError::Png(e.to_string()))?;
        writer.finish().map_err(|e| HeightmapError::Png(e.to_string()))?;
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use png::{BitDepth, ColorType};

    #[test]
    fn grey_8_and_16_bit_map_levels_to_metres_north_up() {
        // 3 × 2 image: top row 0 255 128, bottom row 0 0 51.
        let png8 = encode_png(3, 2, ColorType::Grayscale, BitDepth::Eight, &[0, 255, 128, 0, 0, 51]).unwrap();
        let scale = HeightmapScale { metres_per_pixel: 0.5, height_min_m: -0.2, height_max_m: 0.8, ..HeightmapScale::default() };
        let field = decode_heightmap(&png8, &scale).unwrap();
        assert_eq!((field.columns(), field.rows()), (3, 2));
        // Bottom row is y = 0: sample (2, 0) = level 51 → −0.2 + 0.2.
        assert!((field.height_at(1.0, 0.0).unwrap() - 0.0).abs() < 1e-6);
        // Top row at y = 0.5: (0.5, 0.5) = level 255 → 0.8.
        assert!((field.height_at(0.5, 0.5).unwrap() - 0.8).abs() < 1e-6);
        // Bilinear between (0.5, 0.5) = 0.8 and (1.0, 0.5) = 128/255 − 0.2.
        let mid = (0.8 + (-0.2 + 128.0 / 255.0)) / 2.0;
        assert!((field.height_at(0.75, 0.5).unwrap() - mid).abs() < 1e-6);
        let levels16: Vec<u8> = [0u16, 65535, 32768, 0, 0, 13107].iter().flat_map(|v| v.to_be_bytes()).collect();
        let png16 = encode_png(3, 2, ColorType::Grayscale, BitDepth::Sixteen, &levels16).unwrap();
        let field16 = decode_heightmap(&png16, &scale).unwrap();
        assert!((field16.height_at(1.0, 0.0).unwrap() - 0.0).abs() < 1e-6);
        assert!((field16.height_at(0.5, 0.5).unwrap() - 0.8).abs() < 1e-6);
    }

    #[test]
    fn rgba_uses_the_mean_of_rgb_and_alpha_as_an_optional_mask() {
        // 2 × 2 RGBA: (3, 4, 5, 255) → level 4; one transparent pixel.
        let data = [3, 4, 5, 255, 10, 10, 10, 255, 0, 0, 0, 0, 20, 20, 20, 255];
        let png = encode_png(2, 2, ColorType::Rgba, BitDepth::Eight, &data).unwrap();
        let scale = HeightmapScale { metres_per_pixel: 1.0, height_min_m: 0.0, height_max_m: 255.0, ..HeightmapScale::default() };
        let field = decode_heightmap(&png, &scale).unwrap();
        assert!((field.height_at(0.0, 1.0).unwrap() - 4.0).abs() < 1e-5);
        assert!((field.height_at(0.0, 0.0).unwrap() - 0.0).abs() < 1e-5);
        let masked = decode_heightmap(&png, &HeightmapScale { alpha_is_mask: true, ..scale }).unwrap_err();
        assert_eq!(masked, HeightmapError::Heightfield(HeightfieldError::NoSurface));
        // Grey + alpha 16-bit.
        let data: Vec<u8> = [1000u16, 65535, 2000, 65535, 3000, 65535, 4000, 65535].iter().flat_map(|v| v.to_be_bytes()).collect();
        let png = encode_png(2, 2, ColorType::GrayscaleAlpha, BitDepth::Sixteen, &data).unwrap();
        let field = decode_heightmap(&png, &HeightmapScale { height_max_m: 65.535, ..scale }).unwrap();
        assert!((field.height_at(1.0, 0.0).unwrap() - 4.0).abs() < 1e-4);
    }

    #[test]
    fn bad_images_and_parameters_are_errors() {
        assert!(matches!(decode_heightmap(b"not a png", &HeightmapScale::default()), Err(HeightmapError::Png(_))));
        let png = encode_png(2, 2, ColorType::Grayscale, BitDepth::Eight, &[0, 1, 2, 3]).unwrap();
        let truncated = &png[..png.len() - 20];
        assert!(matches!(decode_heightmap(truncated, &HeightmapScale::default()), Err(HeightmapError::Png(_))));
        let zero = HeightmapScale { metres_per_pixel: 0.0, ..HeightmapScale::default() };
        assert!(decode_heightmap(&png, &zero).unwrap_err().to_string().contains("metres_per_pixel = 0"));
        let nan = HeightmapScale { height_max_m: f64::NAN, ..HeightmapScale::default() };
        assert!(matches!(decode_heightmap(&png, &nan), Err(HeightmapError::Parameter(_))));
        // A one-pixel-wide image has no cell.
        let thin = encode_png(1, 3, ColorType::Grayscale, BitDepth::Eight, &[0, 1, 2]).unwrap();
        assert!(matches!(
            decode_heightmap(&thin, &HeightmapScale::default()),
            Err(HeightmapError::Heightfield(HeightfieldError::TooSmall { .. }))
        ));
    }
}
