//! Training of the foothold network with CNN eq 1 (Adam, deterministic batches, optionally
//! class-balanced and with a decaying learning rate), and batched inference.

use candle_core::{DType, Device, Tensor};
use candle_nn::Optimizer;
use rand::seq::SliceRandom;
use rand::SeedableRng;

use crate::error::FootholdError;
use crate::network::{multitask_loss, FootholdNet, Targets};
use crate::samples::SampleSet;

/// Optimisation parameters.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TrainConfig {
    pub epochs: usize,
    pub batch: usize,
    /// Adam's learning rate.
    pub learning_rate: f64,
    /// λ of CNN eq 1 (the paper: 1).
    pub lambda: f64,
    /// Seed of the batch order (the weights have their own seed).
    pub seed: u64,
    /// The learning rate of epoch e is `learning_rate · lr_decay^e` (1: constant).
    pub lr_decay: f64,
    /// Balanced batches: this share of every batch is positive, the smaller class drawn again
    /// (reshuffled) when it runs out; an epoch ends when the larger class has been seen once.
    /// `None`: batches follow the set's own class shares.
    pub positive_share: Option<f64>,
    /// Dropout rate of the two fully connected layers while training (0: none).
    pub dropout: f64,
}

impl Default for TrainConfig {
    fn default() -> Self {
        Self { epochs: 6, batch: 64, learning_rate: 1e-3, lambda: 1.0, seed: 1, lr_decay: 1.0, positive_share: None, dropout: 0.0 }
    }
}

/// The sample order of one epoch: a shuffle of the set, or with `positive_share` batches of that
/// many positives (rounded, at least one of each class when both exist) and negatives.
pub fn epoch_order(set: &SampleSet, config: &TrainConfig, rng: &mut impl rand::Rng) -> Vec<usize> {
    let mut all: Vec<usize> = (0..set.len()).collect();
    let (mut positives, mut negatives): (Vec<usize>, Vec<usize>) = all.iter().partition(|&&i| set.targets[i].is_some());
    let Some(share) = config.positive_share.filter(|_| !positives.is_empty() && !negatives.is_empty()) else {
        all.shuffle(rng);
        return all;
    };
    let batch = config.batch.max(2);
    let per_batch = ((share.clamp(0.0, 1.0) * batch as f64).round() as usize).clamp(1, batch - 1);
    positives.shuffle(rng);
    negatives.shuffle(rng);
    // Batches until the class that needs more batches has been used once.
    let batches = positives.len().div_ceil(per_batch).max(negatives.len().div_ceil(batch - per_batch));
    fn draw(pool: &mut [usize], next: &mut usize, rng: &mut impl rand::Rng) -> usize {
        if *next == pool.len() {
            pool.shuffle(rng);
            *next = 0;
        }
        *next += 1;
        pool[*next - 1]
    }
    let (mut p, mut n) = (0, 0);
    let mut order = Vec::with_capacity(batches * batch);
    for _ in 0..batches {
        let start = order.len();
        for _ in 0..per_batch {
            order.push(draw(&mut positives, &mut p, rng));
        }
        for _ in per_batch..batch {
            order.push(draw(&mut negatives, &mut n, rng));
        }
        order[start..].shuffle(rng);
    }
    order
}

/// One prediction for one region and body part.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Prediction {
    /// p: probability that a foothold exists.
    pub p: f32,
    /// (x, y) ∈ [0, 1]² in the region.
    pub x: f32,
    pub y: f32,
}

/// Tensors of samples `indices` of a set.
fn batch(set: &SampleSet, indices: &[usize], dtype: DType) -> Result<(Tensor, Tensor, Targets), FootholdError> {
    let dev = Device::Cpu;
    let len = set.regions.input_len();
    let s = set.regions.out_px;
    let mut inputs = Vec::with_capacity(indices.len() * len);
    let mut side = Vec::with_capacity(indices.len() * 3);
    let mut labels = Vec::with_capacity(indices.len());
    let mut coords = Vec::with_capacity(indices.len() * 2);
    for &i in indices {
        inputs.extend_from_slice(set.input(i));
        side.extend_from_slice(&set.side[i]);
        labels.push(u32::from(set.targets[i].is_some()));
        let (x, y) = set.targets[i].unwrap_or((0.5, 0.5));
        coords.extend_from_slice(&[x, y]);
    }
    let n = indices.len();
    let inputs = Tensor::from_vec(inputs, (n, set.regions.channels(), s, s), &dev)?.to_dtype(dtype)?;
    let side = Tensor::from_vec(side, (n, 3), &dev)?.to_dtype(dtype)?;
    let labels = Tensor::from_vec(labels, (n, 1), &dev)?;
    let positive = labels.to_dtype(dtype)?;
    let coords = Tensor::from_vec(coords, (n, 2), &dev)?.to_dtype(dtype)?;
    Ok((inputs, side, Targets { labels, positive, coords }))
}

/// Mean loss of the network over a set (in batches).
pub fn mean_loss(net: &FootholdNet, set: &SampleSet, config: &TrainConfig) -> Result<f64, FootholdError> {
    if set.is_empty() {
        return Err(FootholdError::Empty("no samples to compute a loss on".into()));
    }
    let dtype = net.vars()[0].dtype();
    let indices: Vec<usize> = (0..set.len()).collect();
    let mut total = 0.0;
    for chunk in indices.chunks(config.batch.max(1)) {
        let (inputs, side, targets) = batch(set, chunk, dtype)?;
        let loss = multitask_loss(&net.forward(&inputs, &side)?, &targets, config.lambda)?;
        total += loss.to_dtype(DType::F64)?.to_scalar::<f64>()? * chunk.len() as f64;
    }
    Ok(total / set.len() as f64)
}

/// Trains `net` on `set`; calls `progress(epoch, mean training loss of the epoch)` after each epoch
/// and returns those losses (over the samples the epoch drew, see [`epoch_order`]).
pub fn train(
    net: &FootholdNet,
    set: &SampleSet,
    config: &TrainConfig,
    mut progress: impl FnMut(usize, f64),
) -> Result<Vec<f64>, FootholdError> {
    if set.is_empty() {
        return Err(FootholdError::Empty("no training samples".into()));
    }
    if set.regions.channels() != net.config.in_channels || set.regions.out_px != net.config.input_px {
        return Err(FootholdError::Shape(format!(
            "samples have {} channels of {} px, the network takes {} of {}",
            set.regions.channels(),
            set.regions.out_px,
            net.config.in_channels,
            net.config.input_px
        )));
    }
    if !(0.0..1.0).contains(&config.dropout) {
        return Err(FootholdError::Config(format!("dropout rate {} is not in [0, 1)", config.dropout)));
    }
    let dtype = net.vars()[0].dtype();
    let params = candle_nn::ParamsAdamW { lr: config.learning_rate, weight_decay: 0.0, ..Default::default() };
    let mut optimiser = candle_nn::AdamW::new(net.vars(), params)?;
    let mut rng = rand::rngs::StdRng::seed_from_u64(config.seed);
    let mut dropout_rng = rand::rngs::StdRng::seed_from_u64(config.seed.wrapping_add(1));
    let mut losses = Vec::with_capacity(config.epochs);
    for epoch in 0..config.epochs {
        optimiser.set_learning_rate(config.learning_rate * config.lr_decay.powi(epoch as i32));
        let order = epoch_order(set, config, &mut rng);
        let mut total = 0.0;
        for chunk in order.chunks(config.batch.max(1)) {
            let (inputs, side, targets) = batch(set, chunk, dtype)?;
            let output = net.forward_with_dropout(&inputs, &side, Some((config.dropout, &mut dropout_rng)))?;
            let loss = multitask_loss(&output, &targets, config.lambda)?;
            optimiser.backward_step(&loss)?;
            total += loss.to_dtype(DType::F64)?.to_scalar::<f64>()? * chunk.len() as f64;
        }
        let mean = total / order.len().max(1) as f64;
        progress(epoch, mean);
        losses.push(mean);
    }
    Ok(losses)
}

/// Predictions for `n` regions (`inputs`: n · input_len values) with their side channels.
pub fn predict(net: &FootholdNet, inputs: &[f32], side: &[[f32; 3]], batch_size: usize) -> Result<Vec<Vec<Prediction>>, FootholdError> {
    let c = &net.config;
    let len = c.in_channels * c.input_px * c.input_px;
    let n = side.len();
    if inputs.len() != n * len {
        return Err(FootholdError::Shape(format!("{} input values for {n} regions of {len}", inputs.len())));
    }
    let dtype = net.vars()[0].dtype();
    let dev = Device::Cpu;
    let mut out = Vec::with_capacity(n);
    let mut start = 0;
    while start < n {
        let end = (start + batch_size.max(1)).min(n);
        let m = end - start;
        let x = Tensor::from_slice(&inputs[start * len..end * len], (m, c.in_channels, c.input_px, c.input_px), &dev)?.to_dtype(dtype)?;
        let flat: Vec<f32> = side[start..end].iter().flatten().copied().collect();
        let s = Tensor::from_vec(flat, (m, 3), &dev)?.to_dtype(dtype)?;
        let output = net.forward(&x, &s)?;
        let p = candle_nn::ops::softmax_last_dim(&output.logits.reshape((m, c.body_parts, 2))?)?.to_dtype(DType::F32)?.to_vec3::<f32>()?;
        let xy = output.coords.reshape((m, c.body_parts, 2))?.to_dtype(DType::F32)?.to_vec3::<f32>()?;
        for (pr, co) in p.iter().zip(&xy) {
            out.push(pr.iter().zip(co).map(|(pp, cc)| Prediction { p: pp[1], x: cc[0], y: cc[1] }).collect());
        }
        start = end;
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::network::NetConfig;
    use crate::regions::RegionConfig;
    use crate::samples::SampleMeta;

    /// A small synthetic set: a bump in the region (positive at the bump) or a ramp (negative).
    fn synthetic(n: usize) -> SampleSet {
        let regions = RegionConfig { out_px: 16, ..RegionConfig::default() };
        let mut set = SampleSet::new(regions);
        for i in 0..n {
            let positive = i % 2 == 0;
            let (bx, by) = (4.0 + (i % 7) as f32, 5.0 + (i % 5) as f32);
            for y in 0..16 {
                for x in 0..16 {
                    let v = if positive {
                        0.5 * (-(((x as f32 - bx).powi(2) + (y as f32 - by).powi(2)) / 6.0)).exp()
                    } else {
                        0.05 * (x as f32 - 8.0) * ((i % 3) as f32 - 1.0)
                    };
                    set.inputs.push(v);
                }
            }
            set.side.push([0.7, 0.7, 0.5]);
            set.targets.push(positive.then_some((bx / 16.0, by / 16.0)));
            set.meta.push(SampleMeta {
                scene: "s".into(),
                frame: i,
                u: 0.0,
                v: 0.0,
                size_px: 16,
                depth_m: 0.5,
                tilt_deg: 45.0,
                augmented: false,
            });
        }
        set
    }

    fn tiny() -> NetConfig {
        NetConfig {
            in_channels: 1,
            input_px: 16,
            kernels: [8, 8, 12, 12],
            kernel_sizes: [3, 2, 2, 1],
            first_stride: 1,
            hidden: 16,
            side_channels: true,
            body_parts: 1,
        }
    }

    #[test]
    fn training_reduces_the_loss_deterministically() {
        let set = synthetic(48);
        let config = TrainConfig { epochs: 12, batch: 8, learning_rate: 5e-3, lr_decay: 0.95, ..TrainConfig::default() };
        let run = |config: &TrainConfig| {
            let net = FootholdNet::new(tiny(), 5, DType::F32).unwrap();
            let before = mean_loss(&net, &set, config).unwrap();
            train(&net, &set, config, |_, _| {}).unwrap();
            let after = mean_loss(&net, &set, config).unwrap();
            let weights = net.named_tensors()[0].1.flatten_all().unwrap().to_vec1::<f32>().unwrap();
            (before, after, weights)
        };
        let (before, after, weights) = run(&config);
        assert!(after < 0.7 * before, "loss {before} -> {after}");
        assert_eq!(run(&config), (before, after, weights.clone()));
        // With dropout: still learning, still reproducible, and not the same run.
        let dropout = TrainConfig { dropout: 0.3, ..config };
        let (before_d, after_d, weights_d) = run(&dropout);
        assert!(after_d < 0.7 * before_d, "loss with dropout {before_d} -> {after_d}");
        assert_ne!(weights_d, weights);
        assert_eq!(run(&dropout), (before_d, after_d, weights_d));
    }

    #[test]
    fn a_dropout_rate_outside_0_to_1_is_refused() {
        let set = synthetic(8);
        let net = FootholdNet::new(tiny(), 5, DType::F32).unwrap();
        for rate in [1.0, -0.1, f64::NAN] {
            let err = train(&net, &set, &TrainConfig { dropout: rate, ..TrainConfig::default() }, |_, _| {}).unwrap_err();
            assert!(err.to_string().contains("dropout"), "{err}");
        }
    }

    #[test]
    fn balanced_batches_hold_the_share_and_every_sample_of_the_larger_class() {
        // 3 positives in 40: 25 % of every batch of 8 positive, each negative once per epoch.
        let mut set = synthetic(40);
        for (i, t) in set.targets.iter_mut().enumerate() {
            if i % 2 == 0 && i >= 6 {
                *t = None;
            }
        }
        assert_eq!(set.positives(), 3);
        let config = TrainConfig { batch: 8, positive_share: Some(0.25), ..TrainConfig::default() };
        let mut rng = rand::rngs::StdRng::seed_from_u64(3);
        let order = epoch_order(&set, &config, &mut rng);
        assert_eq!(order.len(), 37usize.div_ceil(6) * 8);
        for chunk in order.chunks(8) {
            assert_eq!(chunk.iter().filter(|&&i| set.targets[i].is_some()).count(), 2);
        }
        let mut negatives: Vec<usize> = order.iter().copied().filter(|&i| set.targets[i].is_none()).collect();
        negatives.sort_unstable();
        negatives.dedup();
        assert_eq!(negatives.len(), 37);
        // Without a share: a permutation of the set.
        let mut plain = epoch_order(&set, &TrainConfig::default(), &mut rng);
        plain.sort_unstable();
        assert_eq!(plain, (0..40).collect::<Vec<_>>());
        assert_eq!(epoch_order(&set, &config, &mut rand::rngs::StdRng::seed_from_u64(3)), order);
    }

    #[test]
    fn predictions_have_one_entry_per_region_and_bad_sizes_are_refused() {
        let set = synthetic(5);
        let net = FootholdNet::new(tiny(), 5, DType::F32).unwrap();
        let out = predict(&net, &set.inputs, &set.side, 2).unwrap();
        assert_eq!(out.len(), 5);
        assert!(out.iter().all(|p| p.len() == 1 && (0.0..=1.0).contains(&p[0].p) && (0.0..=1.0).contains(&p[0].x)));
        assert!(predict(&net, &set.inputs[1..], &set.side, 2).is_err());
        let wrong = FootholdNet::new(NetConfig { input_px: 20, ..tiny() }, 5, DType::F32).unwrap();
        assert!(train(&wrong, &set, &TrainConfig::default(), |_, _| {}).unwrap_err().to_string().contains("16"));
        assert!(train(&net, &SampleSet::new(set.regions.clone()), &TrainConfig::default(), |_, _| {}).is_err());
    }
}
