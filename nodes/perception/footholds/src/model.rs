//! A trained foothold model: the network with the region proposal it was trained on, saved as one
//! safetensors file (the tensors plus JSON metadata: network and region configuration, how it was
//! trained), and the whole-frame prediction (through [`crate::inference`]).

use std::collections::HashMap;
use std::path::Path;

use candle_core::DType;
use patchwalk_fusion::camera::{DepthImage, Intrinsics};

use crate::error::FootholdError;
use crate::inference::FastNet;
use crate::network::{FootholdNet, NetConfig};
use crate::regions::{mirror_input, propose, Region, RegionConfig};
use crate::tensors_io;
use crate::tilt::Tilt;
use crate::train::{predict, Prediction};

/// The network, its region proposal, and free-form training notes.
pub struct FootholdModel {
    /// The network (candle variables, for training). Prediction uses a snapshot of its weights taken
    /// by [`FootholdModel::new`] and [`FootholdModel::load`]; after training `net` in place, call
    /// [`FootholdModel::refresh_inference`].
    pub net: FootholdNet,
    pub regions: RegionConfig,
    /// Training provenance (set sizes, seeds, epochs, losses), stored with the weights.
    pub notes: serde_json::Value,
    /// Average each region's answer with its mirror image's (the mirrored copies of CNN III-C's
    /// augmentation, at test time): p and y averaged, x averaged with the mirror's 1 − x. On by
    /// default; it doubles the network's work.
    pub mirror_average: bool,
    fast: FastNet,
}

/// Which forward pass computes the network's outputs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Inference {
    /// [`crate::inference::FastNet`] (the default).
    Fast,
    /// [`FootholdNet::forward`] on candle tensors, in batches (the training code's forward pass).
    Candle,
}

/// The regions of a frame and their predictions.
#[derive(Debug, Clone)]
pub struct FramePrediction {
    pub regions: Vec<Region>,
    /// Per region, per body part.
    pub predictions: Vec<Vec<Prediction>>,
    /// Wall time of the region proposal and of the network (ms).
    pub regions_ms: f64,
    pub network_ms: f64,
}

impl FramePrediction {
    /// Predicted footholds of body part 0 with p ≥ `threshold`: (image u, v, p).
    pub fn footholds(&self, threshold: f32) -> Vec<(f64, f64, f32)> {
        self.regions
            .iter()
            .zip(&self.predictions)
            .filter_map(|(r, p)| p.first().filter(|p| p.p >= threshold).map(|p| (r, p)))
            .map(|(r, p)| {
                let (u, v) = r.to_image(f64::from(p.x), f64::from(p.y));
                (u, v, p.p)
            })
            .collect()
    }
}

impl FootholdModel {
    /// A fresh model (seeded weights).
    pub fn new(net: NetConfig, regions: RegionConfig, seed: u64) -> Result<Self, FootholdError> {
        regions.validate()?;
        if regions.channels() != net.in_channels || regions.out_px != net.input_px {
            return Err(FootholdError::Config(format!(
                "the regions give {} channels of {} px, the network takes {} of {}",
                regions.channels(),
                regions.out_px,
                net.in_channels,
                net.input_px
            )));
        }
        let net = FootholdNet::new(net, seed, DType::F32)?;
        let fast = FastNet::from_net(&net)?;
        Ok(Self { net, regions, notes: serde_json::Value::Null, mirror_average: true, fast })
    }

    /// Takes a new snapshot of the network's weights for prediction (after training `net` in place).
    pub fn refresh_inference(&mut self) -> Result<(), FootholdError> {
        self.fast = FastNet::from_net(&self.net)?;
        Ok(())
    }

    /// Writes the weights and configuration.
    pub fn save(&self, path: &Path) -> Result<(), FootholdError> {
        let metadata = HashMap::from([
            ("network".to_string(), tensors_io::to_json(&self.net.config)?),
            ("regions".to_string(), tensors_io::to_json(&self.regions)?),
            ("notes".to_string(), tensors_io::to_json(&self.notes)?),
        ]);
        tensors_io::save(path, &self.net.named_tensors(), metadata)
    }

    /// Reads a model written by [`FootholdModel::save`].
    pub fn load(path: &Path) -> Result<Self, FootholdError> {
        let (tensors, metadata) = tensors_io::load(path)?;
        let net: NetConfig = tensors_io::meta_json(path, &metadata, "network")?;
        let regions: RegionConfig = tensors_io::meta_json(path, &metadata, "regions")?;
        let notes = tensors_io::meta_json(path, &metadata, "notes").unwrap_or(serde_json::Value::Null);
        let bad = |e: FootholdError| FootholdError::Weights { path: path.to_path_buf(), reason: e.to_string() };
        let mut model = Self::new(net, regions, 0).map_err(bad)?;
        model.net.load_tensors(&tensors).map_err(bad)?;
        model.refresh_inference().map_err(bad)?;
        model.notes = notes;
        Ok(model)
    }

    /// Predictions for region inputs of this model's region configuration.
    pub fn predict_inputs(&self, inputs: &[f32], side: &[[f32; 3]]) -> Result<Vec<Vec<Prediction>>, FootholdError> {
        self.predict_inputs_with(inputs, side, Inference::Fast)
    }

    /// [`FootholdModel::predict_inputs`] through the chosen forward pass: one pass over the regions
    /// and, with [`FootholdModel::mirror_average`], their mirror images in the same batch.
    pub fn predict_inputs_with(&self, inputs: &[f32], side: &[[f32; 3]], path: Inference) -> Result<Vec<Vec<Prediction>>, FootholdError> {
        let forward = |inputs: &[f32], side: &[[f32; 3]]| match path {
            Inference::Fast => self.fast.predict(inputs, side),
            Inference::Candle => predict(&self.net, inputs, side, 128),
        };
        if !self.mirror_average {
            return forward(inputs, side);
        }
        let len = self.regions.input_len();
        if inputs.len() != side.len() * len {
            return Err(FootholdError::Shape(format!("{} input values for {} regions of {len}", inputs.len(), side.len())));
        }
        let mut both = Vec::with_capacity(2 * inputs.len());
        both.extend_from_slice(inputs);
        both.extend_from_slice(inputs);
        for region in both[inputs.len()..].chunks_exact_mut(len) {
            mirror_input(region, self.regions.channels(), self.regions.out_px);
        }
        let mut sides = side.to_vec();
        sides.extend_from_slice(side);
        let mut predictions = forward(&both, &sides)?;
        let mirrored = predictions.split_off(side.len());
        for (parts, mirror) in predictions.iter_mut().zip(&mirrored) {
            for (p, m) in parts.iter_mut().zip(mirror) {
                *p = Prediction { p: 0.5 * (p.p + m.p), x: 0.5 * (p.x + 1.0 - m.x), y: 0.5 * (p.y + m.y) };
            }
        }
        Ok(predictions)
    }

    /// Regions and predictions of one depth frame at camera tilt `tilt`.
    pub fn predict_frame(&self, depth: &DepthImage, intrinsics: &Intrinsics, tilt: Tilt) -> Result<FramePrediction, FootholdError> {
        self.predict_frame_with(depth, intrinsics, tilt, Inference::Fast)
    }

    /// [`FootholdModel::predict_frame`] through the chosen forward pass.
    pub fn predict_frame_with(
        &self,
        depth: &DepthImage,
        intrinsics: &Intrinsics,
        tilt: Tilt,
        path: Inference,
    ) -> Result<FramePrediction, FootholdError> {
        let start = std::time::Instant::now();
        let mut inputs = Vec::new();
        let regions = propose(depth, intrinsics, &self.regions, &mut inputs)?;
        let regions_ms = start.elapsed().as_secs_f64() * 1e3;
        let side = vec![tilt.channels(); regions.len()];
        let start = std::time::Instant::now();
        let predictions = self.predict_inputs_with(&inputs, &side, path)?;
        let network_ms = start.elapsed().as_secs_f64() * 1e3;
        Ok(FramePrediction { regions, predictions, regions_ms, network_ms })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn save_load_gives_the_same_predictions() {
        let model = FootholdModel::new(NetConfig::default(), RegionConfig::default(), 3).unwrap();
        let k = Intrinsics::new(640, 480, 525.0, 525.0, 319.5, 239.5).unwrap();
        let depth: Vec<f32> = (0..640 * 480).map(|i| 1.0 + 0.0002 * ((i % 640) as f32) + 0.01 * ((i / 640 % 37) as f32 / 37.0)).collect();
        let depth = DepthImage::new(640, 480, depth).unwrap();
        let tilt = Tilt::from_degrees(45.0).unwrap();
        let before = model.predict_frame(&depth, &k, tilt).unwrap();
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("m.safetensors");
        model.save(&path).unwrap();
        let loaded = FootholdModel::load(&path).unwrap();
        let after = loaded.predict_frame(&depth, &k, tilt).unwrap();
        assert_eq!(before.predictions, after.predictions);
        assert_eq!(before.regions.len(), 266);
        let err = FootholdModel::new(NetConfig::default(), RegionConfig { normals: true, ..RegionConfig::default() }, 1).err().unwrap();
        assert!(err.to_string().contains("3 channels"), "{err}");
    }

    #[test]
    fn mirror_averaging_is_the_mean_with_the_mirror_image_and_mirrors_with_it() {
        let mut model = FootholdModel::new(NetConfig::default(), RegionConfig::default(), 7).unwrap();
        let len = model.regions.input_len();
        let out = model.regions.out_px;
        // Two regions: a ramp rising to the right with a bump left of centre, and its mirror image.
        let region: Vec<f32> = (0..len)
            .map(|i| {
                let (x, y) = ((i % out) as f32, (i / out) as f32);
                0.01 * x - 0.3 * (-((x - 20.0).powi(2) + (y - 25.0).powi(2)) / 40.0).exp()
            })
            .collect();
        let mut mirrored = region.clone();
        mirror_input(&mut mirrored, 1, out);
        let inputs = [region.clone(), mirrored.clone()].concat();
        let side = [[0.7f32, 0.7, 0.5]; 2];
        model.mirror_average = false;
        let single = model.predict_inputs(&inputs, &side).unwrap();
        assert_ne!(single[0][0], single[1][0], "the network is not mirror symmetric by itself");
        model.mirror_average = true;
        let averaged = model.predict_inputs(&inputs, &side).unwrap();
        let (a, m) = (single[0][0], single[1][0]);
        let expected = Prediction { p: 0.5 * (a.p + m.p), x: 0.5 * (a.x + 1.0 - m.x), y: 0.5 * (a.y + m.y) };
        let close = |p: Prediction, q: Prediction| (p.p - q.p).abs() < 1e-6 && (p.x - q.x).abs() < 1e-6 && (p.y - q.y).abs() < 1e-6;
        assert!(close(averaged[0][0], expected), "{:?} vs {expected:?}", averaged[0][0]);
        // The mirror image's answer is the original's, mirrored.
        let b = averaged[1][0];
        assert!(close(b, Prediction { x: 1.0 - averaged[0][0].x, ..averaged[0][0] }), "{b:?} vs {:?}", averaged[0][0]);
        // The candle forward averages the same way; a wrong input length is still refused.
        let candle = model.predict_inputs_with(&inputs, &side, Inference::Candle).unwrap();
        assert!(close(candle[0][0], averaged[0][0]));
        assert!(model.predict_inputs(&inputs[1..], &side).is_err());
    }

    /// The whole-frame prediction gives the candle forward's answers on a recorded frame.
    #[test]
    fn fast_and_candle_paths_agree_on_a_recorded_frame() {
        let model = FootholdModel::load(&crate::shipped_weights_path(false)).unwrap();
        let dataset = patchwalk_fusion::dataset::Dataset::open(&patchwalk_fusion::dataset::test_data_dir().join("tum_fr1_xyz")).unwrap();
        let depth = dataset.load_depth(0).unwrap();
        let tilt = Tilt::from_degrees(45.0).unwrap();
        let fast = model.predict_frame(&depth, &dataset.intrinsics, tilt).unwrap();
        let candle = model.predict_frame_with(&depth, &dataset.intrinsics, tilt, Inference::Candle).unwrap();
        assert_eq!(fast.regions, candle.regions);
        assert!(fast.regions.len() > 100, "{}", fast.regions.len());
        for (a, b) in fast.predictions.iter().flatten().zip(candle.predictions.iter().flatten()) {
            assert!((a.p - b.p).abs() < 1e-4 && (a.x - b.x).abs() < 1e-4 && (a.y - b.y).abs() < 1e-4, "{a:?} vs {b:?}");
        }
        assert_eq!(fast.predictions.len(), candle.predictions.len());
    }
}
