//! Labelled region samples: the training and evaluation sets, with the augmentations of CNN III-C
//! (horizontal mirroring; depth noise instead of the intensity channel's brightness and contrast),
//! stored as safetensors.

use std::collections::HashMap;
use std::path::Path;

use rand::Rng;
use rand_distr::Distribution;

use crate::error::FootholdError;
use crate::labels::{Label, LabelledFrame};
use crate::regions::{mirror_input, RegionConfig};
use crate::tensors_io::{self, RawTensor};
use safetensors::{Dtype, SafeTensors};

/// Where a sample came from and its region's geometry in its image.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SampleMeta {
    /// Sequence name (e.g. the dataset directory).
    pub scene: String,
    pub frame: usize,
    pub u: f64,
    pub v: f64,
    pub size_px: usize,
    pub depth_m: f64,
    pub tilt_deg: f64,
    /// A mirrored or noisy copy (augmentation), not an original region.
    pub augmented: bool,
}

/// Labelled regions: inputs, tilt side channels, labels, provenance.
#[derive(Debug, Clone, PartialEq)]
pub struct SampleSet {
    pub regions: RegionConfig,
    /// `len() · regions.input_len()` values.
    pub inputs: Vec<f32>,
    pub side: Vec<[f32; 3]>,
    /// `Some((x, y))` for a positive region, `None` for a negative one.
    pub targets: Vec<Option<(f32, f32)>>,
    pub meta: Vec<SampleMeta>,
}

/// Augmentation of a labelled frame's regions.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Augment {
    /// Add a horizontally mirrored copy of each region.
    pub mirror: bool,
    /// Add copies with Gaussian depth noise of this σ (m; 0: none), as many as `noisy_copies`.
    pub noise_sigma_m: f64,
    pub noisy_copies: usize,
    /// Add this many copies with holes in the depth ([`punch_holes`]).
    pub hole_copies: usize,
}

impl Augment {
    pub const NONE: Augment = Augment { mirror: false, noise_sigma_m: 0.0, noisy_copies: 0, hole_copies: 0 };
}

/// Removes the depth of one to three random elliptical blobs of a region's cells, 5–40 % of the
/// region in all, and re-centres the depth left on its mean (cells without depth are 0 in every
/// channel, as [`crate::regions`] makes them). A real depth camera loses dark, shiny and distant
/// surfaces anywhere in the image, where the simulator loses depth only at occlusion edges; a hole
/// says nothing about the ground's shape, so the label stays. Returns false, leaving `input` as it
/// was, when less than `min_valid_fraction` of the cells would keep a depth.
pub fn punch_holes(input: &mut [f32], channels: usize, side: usize, min_valid_fraction: f64, rng: &mut impl Rng) -> bool {
    let cells = side * side;
    let fraction = rng.random_range(0.05..0.40);
    let blobs = rng.random_range(1..=3usize);
    let mut hole = vec![false; cells];
    for _ in 0..blobs {
        let radius = side as f64 * (fraction / (blobs as f64 * std::f64::consts::PI)).sqrt();
        let aspect: f64 = rng.random_range(0.5..2.0);
        let (rx, ry) = (radius * aspect.sqrt(), radius / aspect.sqrt());
        let (cx, cy) = (rng.random_range(0.0..side as f64), rng.random_range(0.0..side as f64));
        for (k, h) in hole.iter_mut().enumerate() {
            let (x, y) = ((k % side) as f64 + 0.5, (k / side) as f64 + 0.5);
            if ((x - cx) / rx).powi(2) + ((y - cy) / ry).powi(2) <= 1.0 {
                *h = true;
            }
        }
    }
    let depth = &input[..cells];
    let kept: Vec<usize> = (0..cells).filter(|&k| !hole[k] && depth[k] != 0.0).collect();
    if (kept.len() as f64) < min_valid_fraction * cells as f64 {
        return false;
    }
    let mean = kept.iter().map(|&k| f64::from(depth[k])).sum::<f64>() / kept.len() as f64;
    for k in kept {
        input[k] -= mean as f32;
    }
    for c in 0..channels {
        for (k, _) in hole.iter().enumerate().filter(|(_, &h)| h) {
            input[c * cells + k] = 0.0;
        }
    }
    true
}

impl SampleSet {
    pub fn new(regions: RegionConfig) -> Self {
        Self { regions, inputs: Vec::new(), side: Vec::new(), targets: Vec::new(), meta: Vec::new() }
    }

    pub fn len(&self) -> usize {
        self.targets.len()
    }

    pub fn is_empty(&self) -> bool {
        self.targets.is_empty()
    }

    /// Number of positive samples.
    pub fn positives(&self) -> usize {
        self.targets.iter().filter(|t| t.is_some()).count()
    }

    /// The input of sample `i`.
    pub fn input(&self, i: usize) -> &[f32] {
        let len = self.regions.input_len();
        &self.inputs[i * len..(i + 1) * len]
    }

    fn push(&mut self, input: &[f32], side: [f32; 3], target: Option<(f32, f32)>, meta: SampleMeta) {
        self.inputs.extend_from_slice(input);
        self.side.push(side);
        self.targets.push(target);
        self.meta.push(meta);
    }

    /// Adds the known (positive or negative) regions of a frame, with augmented copies.
    pub fn add_frame(
        &mut self,
        frame: &LabelledFrame,
        scene: &str,
        index: usize,
        augment: Augment,
        rng: &mut impl Rng,
    ) -> Result<(), FootholdError> {
        let len = self.regions.input_len();
        if frame.inputs.len() != frame.regions.len() * len {
            return Err(FootholdError::Shape(format!("{} input values for {} regions of {len}", frame.inputs.len(), frame.regions.len())));
        }
        let side = frame.tilt.channels();
        let channels = self.regions.channels();
        let out = self.regions.out_px;
        let noise_scale = f64::from(self.regions.depth_gain) / self.regions.depth_range_m;
        for (i, (region, label)) in frame.regions.iter().zip(&frame.labels).enumerate() {
            let target = match label {
                Label::Unknown => continue,
                Label::Negative => None,
                Label::Positive { x, y } => Some((*x as f32, *y as f32)),
            };
            let input = &frame.inputs[i * len..(i + 1) * len];
            let meta = SampleMeta {
                scene: scene.to_string(),
                frame: index,
                u: region.u,
                v: region.v,
                size_px: region.size_px,
                depth_m: region.depth_m,
                tilt_deg: frame.tilt.degrees,
                augmented: false,
            };
            self.push(input, side, target, meta.clone());
            let augmented = SampleMeta { augmented: true, ..meta };
            if augment.mirror {
                let mut mirrored = input.to_vec();
                mirror_input(&mut mirrored, channels, out);
                self.push(&mirrored, side, target.map(|(x, y)| (1.0 - x, y)), augmented.clone());
            }
            if augment.noise_sigma_m > 0.0 {
                let normal =
                    rand_distr::Normal::new(0.0, augment.noise_sigma_m * noise_scale).map_err(|e| FootholdError::Config(e.to_string()))?;
                for _ in 0..augment.noisy_copies {
                    let mut noisy = input.to_vec();
                    for v in &mut noisy[..out * out] {
                        *v += normal.sample(rng) as f32;
                    }
                    self.push(&noisy, side, target, augmented.clone());
                }
            }
            for _ in 0..augment.hole_copies {
                let mut holed = input.to_vec();
                if punch_holes(&mut holed, channels, out, self.regions.min_valid_fraction, rng) {
                    self.push(&holed, side, target, augmented.clone());
                }
            }
        }
        Ok(())
    }

    /// Appends another set of the same region configuration.
    pub fn extend(&mut self, other: SampleSet) -> Result<(), FootholdError> {
        if other.regions != self.regions {
            return Err(FootholdError::Config("sample sets with different region configurations".into()));
        }
        self.inputs.extend(other.inputs);
        self.side.extend(other.side);
        self.targets.extend(other.targets);
        self.meta.extend(other.meta);
        Ok(())
    }

    /// The originals only (no augmented copies), e.g. for scoring.
    pub fn originals(&self) -> SampleSet {
        let mut out = SampleSet::new(self.regions.clone());
        for i in (0..self.len()).filter(|&i| !self.meta[i].augmented) {
            out.push(self.input(i), self.side[i], self.targets[i], self.meta[i].clone());
        }
        out
    }

    /// At most `max` samples drawn without replacement (a seeded shuffle of the indices, kept in
    /// their original order), e.g. to size the training set to the CPU budget.
    pub fn subsample(&self, max: usize, seed: u64) -> SampleSet {
        use rand::seq::SliceRandom;
        use rand::SeedableRng;
        let mut indices: Vec<usize> = (0..self.len()).collect();
        indices.shuffle(&mut rand::rngs::StdRng::seed_from_u64(seed));
        indices.truncate(max);
        indices.sort_unstable();
        let mut out = SampleSet::new(self.regions.clone());
        for i in indices {
            out.push(self.input(i), self.side[i], self.targets[i], self.meta[i].clone());
        }
        out
    }

    /// Writes the set as safetensors (`inputs` [N, C, S, S], `side` [N, 3], `positive` [N], `coords` [N, 2]),
    /// atomically and without copying the inputs.
    pub fn save(&self, path: &Path) -> Result<(), FootholdError> {
        let n = self.len();
        let s = self.regions.out_px;
        let side: Vec<f32> = self.side.iter().flatten().copied().collect();
        let positive: Vec<u8> = self.targets.iter().map(|t| u8::from(t.is_some())).collect();
        let coords: Vec<f32> = self.targets.iter().flat_map(|t| t.map_or([0.0, 0.0], |(x, y)| [x, y])).collect();
        let tensors = [
            ("inputs", RawTensor::f32(&self.inputs, vec![n, self.regions.channels(), s, s])),
            ("side", RawTensor::f32(&side, vec![n, 3])),
            ("positive", RawTensor::u8(&positive, vec![n])),
            ("coords", RawTensor::f32(&coords, vec![n, 2])),
        ];
        let metadata = HashMap::from([
            ("regions".to_string(), tensors_io::to_json(&self.regions)?),
            ("meta".to_string(), tensors_io::to_json(&self.meta)?),
        ]);
        tensors_io::save_views(path, tensors.iter().map(|(name, t)| (*name, t)), metadata)
    }

    /// Reads a set written by [`SampleSet::save`].
    pub fn load(path: &Path) -> Result<SampleSet, FootholdError> {
        let (bytes, metadata) = tensors_io::read(path)?;
        let regions: RegionConfig = tensors_io::meta_json(path, &metadata, "regions")?;
        let meta: Vec<SampleMeta> = tensors_io::meta_json(path, &metadata, "meta")?;
        let file =
            SafeTensors::deserialize(&bytes).map_err(|e| FootholdError::Format { path: path.to_path_buf(), reason: e.to_string() })?;
        let n = meta.len();
        let tensor = |name: &str, dtype: Dtype, len: usize| tensors_io::tensor_bytes(path, &file, name, dtype, len);
        let inputs = tensors_io::f32_from_le(tensor("inputs", Dtype::F32, n * regions.input_len())?);
        let side = tensors_io::f32_from_le(tensor("side", Dtype::F32, n * 3)?);
        let positive = tensor("positive", Dtype::U8, n)?;
        let coords = tensors_io::f32_from_le(tensor("coords", Dtype::F32, n * 2)?);
        let side = side.chunks_exact(3).map(|s| [s[0], s[1], s[2]]).collect();
        let targets = positive.iter().zip(coords.chunks_exact(2)).map(|(p, c)| (*p > 0).then(|| (c[0], c[1]))).collect();
        Ok(SampleSet { regions, inputs, side, targets, meta })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::regions::Region;
    use crate::tilt::Tilt;
    use rand::SeedableRng;

    fn frame() -> LabelledFrame {
        let regions = RegionConfig { out_px: 8, ..RegionConfig::default() };
        let region = |u| Region { row: 0, col: 0, u, v: 10.0, depth_m: 0.5, size_px: 40 };
        let inputs: Vec<f32> = (0..3 * regions.input_len()).map(|i| i as f32 * 0.01).collect();
        LabelledFrame {
            tilt: Tilt::from_degrees(45.0).unwrap(),
            regions: vec![region(10.0), region(20.0), region(30.0)],
            inputs,
            labels: vec![Label::Positive { x: 0.25, y: 0.5 }, Label::Unknown, Label::Negative],
        }
    }

    #[test]
    fn unknown_regions_are_left_out_and_mirrors_flip_x() {
        let mut set = SampleSet::new(RegionConfig { out_px: 8, ..RegionConfig::default() });
        let mut rng = rand::rngs::StdRng::seed_from_u64(1);
        set.add_frame(&frame(), "a", 3, Augment { mirror: true, noise_sigma_m: 0.002, noisy_copies: 1, hole_copies: 0 }, &mut rng).unwrap();
        // 2 known regions × (original + mirror + noisy).
        assert_eq!(set.len(), 6);
        assert_eq!(set.targets[0], Some((0.25, 0.5)));
        assert_eq!(set.targets[1], Some((0.75, 0.5)));
        assert_eq!(set.targets[3], None);
        assert_eq!(set.input(1)[0], set.input(0)[7]);
        assert_eq!(set.originals().len(), 2);
        assert_eq!(set.positives(), 3);
        let sub = set.subsample(4, 7);
        assert_eq!(sub.len(), 4);
        assert_eq!(sub, set.subsample(4, 7));
        assert_eq!(set.subsample(100, 7), set);
    }

    #[test]
    fn holes_take_depth_away_and_recentre_what_is_left() {
        // A 3-channel 20 × 20 region: a depth ramp (mean 0) with its first row already without depth.
        let side = 20;
        let cells = side * side;
        let mut region = vec![0.5f32; 3 * cells];
        for (k, depth) in region.iter_mut().take(cells).enumerate() {
            *depth = if k < side { 0.0 } else { (k % side) as f32 * 0.1 - 0.95 };
        }
        let mut rng = rand::rngs::StdRng::seed_from_u64(4);
        let mut fractions = Vec::new();
        for _ in 0..50 {
            let mut holed = region.clone();
            if !punch_holes(&mut holed, 3, side, 0.3, &mut rng) {
                assert_eq!(holed, region);
                continue;
            }
            let holes: Vec<usize> = (side..cells).filter(|&k| holed[k] == 0.0).collect();
            fractions.push(holes.len() as f64 / cells as f64);
            // Every channel is empty in the holes, the depth left has mean 0 and its slope.
            assert!(holes.iter().all(|&k| holed[cells + k] == 0.0 && holed[2 * cells + k] == 0.0));
            let kept: Vec<usize> = (side..cells).filter(|&k| holed[k] != 0.0).collect();
            let mean = kept.iter().map(|&k| f64::from(holed[k])).sum::<f64>() / kept.len() as f64;
            assert!(mean.abs() < 1e-5, "{mean}");
            let shift = holed[kept[0]] - region[kept[0]];
            assert!(kept.iter().all(|&k| (holed[k] - region[k] - shift).abs() < 1e-5));
        }
        assert!(fractions.len() > 40);
        let (least, most) = fractions.iter().fold((1.0f64, 0.0f64), |(a, b), &f| (a.min(f), b.max(f)));
        assert!(least > 0.01 && most < 0.45 && most > 0.2, "hole fractions {least}..{most}");
        // A region that would keep too little depth is left as it was.
        let mut sparse = region.clone();
        sparse[..cells / 2].fill(0.0);
        let before = sparse.clone();
        assert!(!punch_holes(&mut sparse, 3, side, 0.6, &mut rng));
        assert_eq!(sparse, before);
    }

    #[test]
    fn save_and_load_round_trip() {
        let mut set = SampleSet::new(RegionConfig { out_px: 8, ..RegionConfig::default() });
        let mut rng = rand::rngs::StdRng::seed_from_u64(1);
        set.add_frame(&frame(), "a", 3, Augment::NONE, &mut rng).unwrap();
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("set.safetensors");
        set.save(&path).unwrap();
        assert_eq!(SampleSet::load(&path).unwrap(), set);
        std::fs::write(&path, b"not a safetensors file").unwrap();
        assert!(SampleSet::load(&path).unwrap_err().to_string().contains("set.safetensors"));
        // A new save replaces the file whole and leaves nothing else behind.
        let mut bigger = set.clone();
        bigger.extend(set.clone()).unwrap();
        set.save(&path).unwrap();
        bigger.save(&path).unwrap();
        assert_eq!(SampleSet::load(&path).unwrap(), bigger);
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
        // A file cut short (a write killed half way) is refused with its name.
        let bytes = std::fs::read(&path).unwrap();
        std::fs::write(&path, &bytes[..bytes.len() - 8]).unwrap();
        assert!(SampleSet::load(&path).unwrap_err().to_string().contains("set.safetensors"));
        // Saving into a directory that cannot hold the file fails and leaves no temporary file.
        let blocked = dir.path().join("blocked");
        std::fs::create_dir(&blocked).unwrap();
        std::fs::create_dir(blocked.join("set.safetensors")).unwrap();
        assert!(set.save(&blocked.join("set.safetensors")).is_err());
        assert_eq!(std::fs::read_dir(&blocked).unwrap().count(), 1);
    }
}
