//! A dedicated inference path for the foothold network of CNN III-B: the same layers and weights as
//! [`FootholdNet::forward`], computed without candle's generic tensor ops.
//!
//! Each convolution is an im2col into a row per output pixel (kernel rows × kernel columns ×
//! input channels) and one matrix product with the weights (the `gemm` crate's f32 kernels,
//! single-threaded); bias, ReLU and the 2 × 2 max-pooling are one fused pass over the product
//! (`max(relu(a + b)) = relu(max(a) + b)`). Activations are kept per pixel with the channels
//! innermost, so every kernel row of a patch is one contiguous copy. Regions are processed in small
//! groups in parallel (rayon) through the convolutions, then the fully connected layers run on all
//! regions' features at once, split by rows. Work buffers are kept between calls.
//!
//! The weights are a snapshot taken by [`FastNet::from_net`]: a network trained in place afterwards
//! needs a new snapshot.

use std::sync::Mutex;

use rayon::prelude::*;

use crate::error::FootholdError;
use crate::network::{FootholdNet, NetConfig, SIDE_CHANNELS};
use crate::train::Prediction;

/// Regions per group through the convolutions: the group's im2col and product buffers (≈ 250 kB per
/// region for the default network) stay in a core's L2 cache.
const GROUP: usize = 4;

/// Rows per task of the fully connected layers, at least.
const DENSE_ROWS: usize = 32;

/// One convolution with its fused bias, ReLU and optional 2 × 2 max-pooling.
#[derive(Debug, Clone)]
struct Conv {
    kernel: usize,
    stride: usize,
    in_channels: usize,
    out_channels: usize,
    in_side: usize,
    out_side: usize,
    pool: bool,
    /// `[kernel · kernel · in_channels, out_channels]`, row-major, rows in (ky, kx, channel) order.
    weight: Vec<f32>,
    bias: Vec<f32>,
}

impl Conv {
    fn patch_len(&self) -> usize {
        self.kernel * self.kernel * self.in_channels
    }

    fn pixels(&self) -> usize {
        self.out_side * self.out_side
    }

    /// Side after the optional pooling.
    fn next_side(&self) -> usize {
        if self.pool {
            self.out_side / 2
        } else {
            self.out_side
        }
    }

    /// Values per region after this layer (pooled).
    fn next_len(&self) -> usize {
        self.next_side() * self.next_side() * self.out_channels
    }
}

/// A fully connected layer, weights `[inputs, outputs]` row-major.
#[derive(Debug, Clone)]
struct Dense {
    inputs: usize,
    outputs: usize,
    weight: Vec<f32>,
    bias: Vec<f32>,
}

/// Work buffers of one group of regions.
#[derive(Default)]
struct Scratch {
    activations: Vec<f32>,
    next: Vec<f32>,
    columns: Vec<f32>,
    product: Vec<f32>,
}

/// The foothold network's weights laid out for inference, and reusable work buffers.
pub struct FastNet {
    config: NetConfig,
    convs: Vec<Conv>,
    dense: Vec<Dense>,
    pool: Mutex<Vec<Scratch>>,
}

impl std::fmt::Debug for FastNet {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FastNet").field("config", &self.config).finish_non_exhaustive()
    }
}

/// `c = a · b` for contiguous row-major `a` `[m, k]`, `b` `[k, n]`, `c` `[m, n]` (overwritten).
// The one unsafe block of this crate: `gemm::gemm` takes raw pointers and strides.
#[allow(unsafe_code)]
fn matmul(m: usize, k: usize, n: usize, a: &[f32], b: &[f32], c: &mut [f32]) -> Result<(), FootholdError> {
    let fits = |len: usize, rows: usize, cols: usize| rows.checked_mul(cols).is_some_and(|need| len >= need);
    if !(fits(a.len(), m, k) && fits(b.len(), k, n) && fits(c.len(), m, n)) {
        return Err(FootholdError::Shape(format!(
            "matrix product [{m}, {k}] · [{k}, {n}] with buffers of {}, {} and {}",
            a.len(),
            b.len(),
            c.len()
        )));
    }
    if m == 0 || n == 0 {
        return Ok(());
    }
    if k == 0 {
        c[..m * n].fill(0.0);
        return Ok(());
    }
    let (k_stride, n_stride) = (k as isize, n as isize);
    // SAFETY: the checks above guarantee that every element the strides address lies inside the
    // slices: a[i·k + j] for i < m, j < k; b[j·n + l] for j < k, l < n; c[i·n + l]. `c` is borrowed
    // mutably, so it aliases neither input. With `read_dst = false` gemm writes c = 1 · a · b
    // (alpha is unused) and reads no uninitialised memory.
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            c.as_mut_ptr(),
            1,
            n_stride,
            false,
            a.as_ptr(),
            1,
            k_stride,
            b.as_ptr(),
            1,
            n_stride,
            0.0f32,
            1.0f32,
            false,
            false,
            false,
            gemm::Parallelism::None,
        );
    }
    Ok(())
}

/// Rows of the im2col matrix of `regions` regions: for each output pixel (y, x) the kernel window
/// at (y · stride, x · stride), kernel row by kernel row (each row `kernel · channels` contiguous
/// values of the channels-innermost input).
fn im2col(conv: &Conv, input: &[f32], regions: usize, columns: &mut Vec<f32>) {
    let (k, c, s_in, s_out, stride) = (conv.kernel, conv.in_channels, conv.in_side, conv.out_side, conv.stride);
    let row_len = k * c;
    let plane = s_in * s_in * c;
    columns.resize(regions * conv.pixels() * conv.patch_len(), 0.0);
    let mut rows = columns.chunks_exact_mut(row_len);
    for region in input.chunks_exact(plane).take(regions) {
        for y in 0..s_out {
            for x in 0..s_out {
                for (ky, row) in (0..k).zip(rows.by_ref()) {
                    let start = ((y * stride + ky) * s_in + x * stride) * c;
                    // Element by element: the rows of the first layer are only a few values long.
                    for (to, from) in row.iter_mut().zip(&region[start..start + row_len]) {
                        *to = *from;
                    }
                }
            }
        }
    }
}

/// Bias, ReLU and the optional 2 × 2 max-pooling (floor: an odd last row or column is dropped, as
/// candle's `max_pool2d`) of a convolution's product `[regions · pixels, out_channels]`.
fn bias_relu_pool(conv: &Conv, product: &[f32], regions: usize, out: &mut Vec<f32>) {
    let (c, side) = (conv.out_channels, conv.out_side);
    out.clear();
    out.reserve(regions * conv.next_len());
    if !conv.pool {
        for pixel in product.chunks_exact(c).take(regions * conv.pixels()) {
            out.extend(pixel.iter().zip(&conv.bias).map(|(v, b)| (v + b).max(0.0)));
        }
        return;
    }
    let half = side / 2;
    for region in product.chunks_exact(side * side * c).take(regions) {
        for py in 0..half {
            for px in 0..half {
                let at = |y: usize, x: usize| &region[(y * side + x) * c..(y * side + x + 1) * c];
                let (a, b) = (at(2 * py, 2 * px), at(2 * py, 2 * px + 1));
                let (d, e) = (at(2 * py + 1, 2 * px), at(2 * py + 1, 2 * px + 1));
                for ch in 0..c {
                    let m = a[ch].max(b[ch]).max(d[ch]).max(e[ch]);
                    out.push((m + conv.bias[ch]).max(0.0));
                }
            }
        }
    }
}

impl FastNet {
    /// A snapshot of `net`'s weights in the inference layout.
    pub fn from_net(net: &FootholdNet) -> Result<Self, FootholdError> {
        let config = net.config.clone();
        config.validate()?;
        let tensors: std::collections::HashMap<String, Vec<f32>> = net
            .named_tensors()
            .into_iter()
            .map(|(name, t)| Ok((name, t.to_dtype(candle_core::DType::F32)?.flatten_all()?.to_vec1::<f32>()?)))
            .collect::<Result<_, candle_core::Error>>()?;
        let get = |name: &str, len: usize| -> Result<&[f32], FootholdError> {
            let values = tensors.get(name).ok_or_else(|| FootholdError::Shape(format!("tensor {name} missing")))?;
            if values.len() == len {
                Ok(values.as_slice())
            } else {
                Err(FootholdError::Shape(format!("tensor {name} has {} values, the network needs {len}", values.len())))
            }
        };
        let mut convs = Vec::with_capacity(4);
        let (mut side, mut channels) = (config.input_px, config.in_channels);
        for layer in 0..4 {
            let (k, n) = (config.kernel_sizes[layer], config.kernels[layer]);
            let stride = if layer == 0 { config.first_stride.max(1) } else { 1 };
            let out_side = (side - k) / stride + 1;
            let name = format!("conv{}", layer + 1);
            // candle's [out, in, ky, kx] to [(ky, kx, in), out].
            let w = get(&format!("{name}.weight"), n * channels * k * k)?;
            let mut weight = vec![0.0; w.len()];
            for o in 0..n {
                for i in 0..channels {
                    for ky in 0..k {
                        for kx in 0..k {
                            weight[((ky * k + kx) * channels + i) * n + o] = w[((o * channels + i) * k + ky) * k + kx];
                        }
                    }
                }
            }
            let conv = Conv {
                kernel: k,
                stride,
                in_channels: channels,
                out_channels: n,
                in_side: side,
                out_side,
                pool: layer != 2,
                weight,
                bias: get(&format!("{name}.bias"), n)?.to_vec(),
            };
            side = conv.next_side();
            channels = n;
            convs.push(conv);
        }
        let features = side * side * channels;
        let extra = if config.side_channels { SIDE_CHANNELS } else { 0 };
        let mut dense = Vec::with_capacity(3);
        let sizes = [(features + extra, config.hidden), (config.hidden, config.hidden), (config.hidden, config.outputs())];
        for (layer, (name, (inputs, outputs))) in ["fc1", "fc2", "out"].into_iter().zip(sizes).enumerate() {
            let w = get(&format!("{name}.weight"), outputs * inputs)?;
            let mut weight = vec![0.0; w.len()];
            for o in 0..outputs {
                for i in 0..inputs {
                    // fc1 sees candle's flattening (channel, y, x); ours is (y, x, channel).
                    let j = if layer == 0 && i < features {
                        let (pixel, ch) = (i / channels, i % channels);
                        ch * side * side + pixel
                    } else {
                        i
                    };
                    weight[i * outputs + o] = w[o * inputs + j];
                }
            }
            dense.push(Dense { inputs, outputs, weight, bias: get(&format!("{name}.bias"), outputs)?.to_vec() });
        }
        Ok(Self { config, convs, dense, pool: Mutex::new(Vec::new()) })
    }

    /// The network's configuration.
    pub fn config(&self) -> &NetConfig {
        &self.config
    }

    fn scratch(&self) -> Scratch {
        self.pool.lock().unwrap_or_else(std::sync::PoisonError::into_inner).pop().unwrap_or_default()
    }

    fn give_back(&self, scratch: Scratch) {
        self.pool.lock().unwrap_or_else(std::sync::PoisonError::into_inner).push(scratch);
    }

    /// The convolutions of up to [`GROUP`] regions (`inputs` channel planes per region, as
    /// [`crate::regions::propose`] writes them); their features (and side channels) into `features`,
    /// one row of `dense[0].inputs` per region.
    fn convolve(&self, inputs: &[f32], side: &[[f32; 3]], features: &mut [f32], scratch: &mut Scratch) -> Result<(), FootholdError> {
        let regions = side.len();
        let (px, ch) = (self.config.input_px, self.config.in_channels);
        let plane = px * px;
        // Channel planes to channels innermost.
        scratch.activations.clear();
        for region in inputs.chunks_exact(plane * ch).take(regions) {
            for p in 0..plane {
                scratch.activations.extend((0..ch).map(|c| region[c * plane + p]));
            }
        }
        for conv in &self.convs {
            im2col(conv, &scratch.activations, regions, &mut scratch.columns);
            let rows = regions * conv.pixels();
            scratch.product.resize(rows * conv.out_channels, 0.0);
            matmul(rows, conv.patch_len(), conv.out_channels, &scratch.columns, &conv.weight, &mut scratch.product)?;
            bias_relu_pool(conv, &scratch.product, regions, &mut scratch.next);
            std::mem::swap(&mut scratch.activations, &mut scratch.next);
        }
        let row = self.dense[0].inputs;
        let feature_len = self.convs[3].next_len();
        for ((out, conv), tilt) in features.chunks_exact_mut(row).zip(scratch.activations.chunks_exact(feature_len)).zip(side) {
            out[..feature_len].copy_from_slice(conv);
            if self.config.side_channels {
                out[feature_len..].copy_from_slice(tilt);
            }
        }
        Ok(())
    }

    /// The fully connected layers on `rows` feature rows; the raw outputs (per body part two logits
    /// and two regression values before the sigmoid) into `out`.
    fn dense_rows(&self, features: &[f32], rows: usize, out: &mut [f32], scratch: &mut Scratch) -> Result<(), FootholdError> {
        let [first, second, last] = &self.dense[..] else {
            return Err(FootholdError::Shape(format!("{} fully connected layers, the network has 3", self.dense.len())));
        };
        let hidden = |dense: &Dense, input: &[f32], target: &mut Vec<f32>| -> Result<(), FootholdError> {
            target.resize(rows * dense.outputs, 0.0);
            matmul(rows, dense.inputs, dense.outputs, input, &dense.weight, target)?;
            for row in target.chunks_exact_mut(dense.outputs) {
                for (v, b) in row.iter_mut().zip(&dense.bias) {
                    *v = (*v + b).max(0.0);
                }
            }
            Ok(())
        };
        hidden(first, features, &mut scratch.product)?;
        hidden(second, &scratch.product, &mut scratch.next)?;
        matmul(rows, last.inputs, last.outputs, &scratch.next, &last.weight, out)?;
        for row in out.chunks_exact_mut(last.outputs).take(rows) {
            for (v, b) in row.iter_mut().zip(&last.bias) {
                *v += b;
            }
        }
        Ok(())
    }

    /// Raw outputs of `n = side.len()` regions, `[n, 4 · body_parts]`: per body part the two class
    /// logits and the two coordinates (after the sigmoid), as [`FootholdNet::forward`] gives them.
    pub fn forward(&self, inputs: &[f32], side: &[[f32; 3]]) -> Result<Vec<f32>, FootholdError> {
        let c = &self.config;
        let len = c.in_channels * c.input_px * c.input_px;
        let n = side.len();
        if inputs.len() != n * len {
            return Err(FootholdError::Shape(format!("{} input values for {n} regions of {len}", inputs.len())));
        }
        let row = self.dense[0].inputs;
        let mut features = vec![0.0f32; n * row];
        features.par_chunks_mut(GROUP * row).zip(inputs.par_chunks(GROUP * len)).zip(side.par_chunks(GROUP)).try_for_each(
            |((features, inputs), side)| {
                let mut scratch = self.scratch();
                let result = self.convolve(inputs, side, features, &mut scratch);
                self.give_back(scratch);
                result
            },
        )?;
        let outputs = c.outputs();
        let mut out = vec![0.0f32; n * outputs];
        let rows = n.div_ceil(rayon::current_num_threads().max(1)).max(DENSE_ROWS);
        out.par_chunks_mut(rows * outputs).zip(features.par_chunks(rows * row)).try_for_each(|(out, features)| {
            let mut scratch = self.scratch();
            let result = self.dense_rows(features, out.len() / outputs, out, &mut scratch);
            self.give_back(scratch);
            result
        })?;
        for part in out.chunks_exact_mut(4) {
            for v in &mut part[2..] {
                *v = 1.0 / (1.0 + (-*v).exp());
            }
        }
        Ok(out)
    }

    /// Per region and body part: p (softmax of the two logits) and (x, y).
    pub fn predict(&self, inputs: &[f32], side: &[[f32; 3]]) -> Result<Vec<Vec<Prediction>>, FootholdError> {
        let out = self.forward(inputs, side)?;
        Ok(out
            .chunks_exact(self.config.outputs())
            .map(|region| {
                region
                    .chunks_exact(4)
                    .map(|o| {
                        let m = o[0].max(o[1]);
                        let (e0, e1) = ((o[0] - m).exp(), (o[1] - m).exp());
                        Prediction { p: e1 / (e0 + e1), x: o[2], y: o[3] }
                    })
                    .collect()
            })
            .collect())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{DType, Device, Tensor};

    /// The candle forward's outputs in the same `[n, 4 · parts]` layout.
    fn candle_outputs(net: &FootholdNet, inputs: &[f32], side: &[[f32; 3]]) -> Vec<f32> {
        let c = &net.config;
        let n = side.len();
        let x = Tensor::from_slice(inputs, (n, c.in_channels, c.input_px, c.input_px), &Device::Cpu).unwrap();
        let s = Tensor::from_vec(side.iter().flatten().copied().collect::<Vec<f32>>(), (n, 3), &Device::Cpu).unwrap();
        let out = net.forward(&x, &s).unwrap();
        let logits = out.logits.reshape((n, c.body_parts, 2)).unwrap();
        let coords = out.coords.reshape((n, c.body_parts, 2)).unwrap();
        Tensor::cat(&[&logits, &coords], 2).unwrap().flatten_all().unwrap().to_vec1::<f32>().unwrap()
    }

    /// Deterministic inputs in roughly the range of the region proposal's (a few units).
    fn inputs(n: usize, len: usize, seed: u64) -> (Vec<f32>, Vec<[f32; 3]>) {
        use rand::{Rng, SeedableRng};
        let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
        let x = (0..n * len).map(|_| rng.random_range(-1.5f32..1.5)).collect();
        let side = (0..n)
            .map(|_| {
                let t: f32 = rng.random_range(-1.0f32..1.0);
                let r = t * std::f32::consts::FRAC_PI_2;
                [r.cos(), r.sin(), t]
            })
            .collect();
        (x, side)
    }

    fn assert_close(fast: &[f32], reference: &[f32], tolerance: f32) {
        assert_eq!(fast.len(), reference.len());
        let worst = fast.iter().zip(reference).map(|(a, b)| (a - b).abs() / (1.0 + b.abs())).fold(0.0f32, f32::max);
        assert!(worst <= tolerance, "largest difference {worst}");
        assert!(reference.iter().any(|v| v.abs() > 1e-3), "outputs are all about zero");
    }

    #[test]
    fn shipped_weights_give_the_candle_outputs() {
        for no_angle in [false, true] {
            let model = crate::model::FootholdModel::load(&crate::shipped_weights_path(no_angle)).unwrap();
            let fast = FastNet::from_net(&model.net).unwrap();
            // 11 regions: groups of 4, 4 and 3.
            let (x, side) = inputs(11, model.regions.input_len(), 5);
            let reference = candle_outputs(&model.net, &x, &side);
            assert_close(&fast.forward(&x, &side).unwrap(), &reference, 1e-4);
            // The buffers kept from the first call give the same answer.
            assert_close(&fast.forward(&x, &side).unwrap(), &reference, 1e-4);
            let predictions = fast.predict(&x, &side).unwrap();
            let candle = crate::train::predict(&model.net, &x, &side, 128).unwrap();
            for (a, b) in predictions.iter().flatten().zip(candle.iter().flatten()) {
                assert!((a.p - b.p).abs() < 1e-4 && (a.x - b.x).abs() < 1e-4 && (a.y - b.y).abs() < 1e-4, "{a:?} vs {b:?}");
            }
        }
    }

    #[test]
    fn random_weights_of_other_shapes_give_the_candle_outputs() {
        // Three channels, stride 1, odd sides before two poolings (9 → 7 → 5 → 2), 2 × 2 final
        // features (fc1's column order matters), two body parts; and the default shape with and
        // without side channels.
        let other = NetConfig {
            in_channels: 3,
            input_px: 44,
            kernels: [4, 5, 6, 7],
            kernel_sizes: [5, 3, 3, 3],
            first_stride: 1,
            hidden: 9,
            side_channels: true,
            body_parts: 2,
        };
        assert_eq!(other.feature_len().unwrap(), 2 * 2 * 7);
        let configs = [other, NetConfig::default(), NetConfig { side_channels: false, ..NetConfig::default() }];
        for (seed, config) in configs.into_iter().enumerate() {
            let net = FootholdNet::new(config.clone(), seed as u64 + 11, DType::F32).unwrap();
            let fast = FastNet::from_net(&net).unwrap();
            let len = config.in_channels * config.input_px * config.input_px;
            for n in [1, 6] {
                let (x, side) = inputs(n, len, seed as u64 * 100 + n as u64);
                assert_close(&fast.forward(&x, &side).unwrap(), &candle_outputs(&net, &x, &side), 1e-4);
            }
        }
    }

    #[test]
    fn wrong_input_lengths_are_refused() {
        let net = FootholdNet::new(NetConfig::default(), 1, DType::F32).unwrap();
        let fast = FastNet::from_net(&net).unwrap();
        let err = fast.forward(&[0.0; 3600 * 2 - 1], &[[1.0, 0.0, 0.0]; 2]).unwrap_err();
        assert!(err.to_string().contains("7199 input values for 2 regions of 3600"), "{err}");
        assert!(fast.forward(&[], &[]).unwrap().is_empty());
        assert!(matmul(2, 3, 4, &[0.0; 6], &[0.0; 11], &mut [0.0; 8]).is_err());
    }

    #[test]
    fn matmul_matches_the_definition() {
        let (m, k, n) = (7, 5, 3);
        let a: Vec<f32> = (0..m * k).map(|i| (i as f32 * 0.37).sin()).collect();
        let b: Vec<f32> = (0..k * n).map(|i| (i as f32 * 0.11).cos()).collect();
        let mut c = vec![f32::NAN; m * n];
        matmul(m, k, n, &a, &b, &mut c).unwrap();
        for i in 0..m {
            for j in 0..n {
                let expected: f32 = (0..k).map(|l| a[i * k + l] * b[l * n + j]).sum();
                assert!((c[i * n + j] - expected).abs() < 1e-5);
            }
        }
    }
}
