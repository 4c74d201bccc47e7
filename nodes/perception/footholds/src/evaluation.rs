//! The comparison of CNN III-D/E on datasets held apart from training: classification and
//! regression error of the CNN, the CNN without tilt ("No angle"), the linear SVM on hand features,
//! the patch pipeline itself on each single frame (the geometric baseline), and the trivial answer
//! "a foothold at the centre of every region" (its classification error is the share of negatives,
//! its regression error the mean distance of the labels' (x, y) from the region centre), with the time
//! per frame of each; and the picture like CNN Fig. 6. Labels come from each sequence's fused map
//! ([`crate::labels`]).

use std::path::{Path, PathBuf};
use std::time::Instant;

use patchwalk_fusion::camera::DepthImage;
use serde::Serialize;

use crate::error::FootholdError;
use crate::eval::Scores;
use crate::labels::{is_foothold, painted_footholds, pipeline, region_label, Label, LabelConfig, LabelledFrame};
use crate::model::FootholdModel;
use crate::regions::Region;
use crate::render::{Mark, Picture};
use crate::sequence::Sequence;
use crate::svm::{features, LinearSvm};
use crate::train::Prediction;

/// The methods of the table, in order.
pub const METHODS: [&str; 5] =
    ["CNN (depth + tilt)", "CNN, no angle", "linear SVM (22 features)", "patch pipeline, single frame", "all positive, region centre"];

/// One group's table rows: (method, scores, classification error, median ms per frame).
#[derive(Default, Serialize)]
pub struct GroupResult {
    pub group: String,
    pub datasets: usize,
    pub frames: usize,
    pub regions: usize,
    pub positives: usize,
    pub scores: Vec<(String, Scores, f64, f64)>,
    /// Per method the time of every frame (ms), for merging groups.
    #[serde(skip)]
    pub frame_ms: Vec<Vec<f64>>,
    /// Every known region with each method's answer, for error analysis.
    #[serde(skip)]
    pub rows: Vec<RegionRow>,
}

/// One known region of an evaluated frame and what each method said of it.
#[derive(Debug, Clone)]
pub struct RegionRow {
    pub dataset: String,
    pub frame: usize,
    pub region: Region,
    /// The fraction of the region's resampled cells without a valid depth pixel.
    pub invalid_fraction: f64,
    pub tilt_deg: f64,
    /// The label's (x, y) when positive.
    pub target: Option<(f32, f32)>,
    /// Per method of [`METHODS`], its answer.
    pub predictions: [Prediction; METHODS.len()],
}

/// The rows as CSV: one line per known region and method answers side by side.
pub fn format_region_rows(results: &[GroupResult]) -> String {
    use std::fmt::Write;
    let mut out = String::from("group,dataset,frame,row,col,u,v,depth_m,size_px,invalid_fraction,tilt_deg,positive,x,y");
    for m in 0..METHODS.len() {
        let _ = write!(out, ",p{m},x{m},y{m}");
    }
    out.push('\n');
    for group in results {
        for row in &group.rows {
            let r = &row.region;
            let (positive, (x, y)) = row.target.map_or((0, (f32::NAN, f32::NAN)), |t| (1, t));
            let _ = write!(
                out,
                "{},{},{},{},{},{:.1},{:.1},{:.3},{},{:.3},{:.2},{positive},{x:.3},{y:.3}",
                group.group, row.dataset, row.frame, r.row, r.col, r.u, r.v, r.depth_m, r.size_px, row.invalid_fraction, row.tilt_deg
            );
            for p in &row.predictions {
                let _ = write!(out, ",{:.4},{:.3},{:.3}", p.p, p.x, p.y);
            }
            out.push('\n');
        }
    }
    out
}

fn median(values: &[f64]) -> f64 {
    let mut v = values.to_vec();
    v.sort_by(f64::total_cmp);
    v.get(v.len() / 2).copied().unwrap_or(f64::NAN)
}

impl GroupResult {
    fn from_scores(group: &str, scores: &[Scores], frame_ms: Vec<Vec<f64>>) -> Self {
        let rows =
            METHODS.iter().zip(scores).zip(&frame_ms).map(|((name, s), m)| (name.to_string(), *s, s.classification_error(), median(m)));
        GroupResult { group: group.to_string(), scores: rows.collect(), frame_ms, ..GroupResult::default() }
    }

    /// The groups together under a new name (counts and scores summed, medians over all frames).
    pub fn merged(group: &str, parts: &[GroupResult]) -> GroupResult {
        let mut scores = [Scores::default(); METHODS.len()];
        let mut frame_ms = vec![Vec::new(); METHODS.len()];
        for part in parts {
            for (m, (_, s, _, _)) in part.scores.iter().enumerate().take(METHODS.len()) {
                scores[m].merge(s);
            }
            for (all, ms) in frame_ms.iter_mut().zip(&part.frame_ms) {
                all.extend_from_slice(ms);
            }
        }
        let mut out = Self::from_scores(group, &scores, frame_ms);
        out.datasets = parts.iter().map(|p| p.datasets).sum();
        out.frames = parts.iter().map(|p| p.frames).sum();
        out.regions = parts.iter().map(|p| p.regions).sum();
        out.positives = parts.iter().map(|p| p.positives).sum();
        out
    }
}

/// The compared predictors.
pub struct Methods {
    pub cnn: FootholdModel,
    pub no_angle: FootholdModel,
    pub svm: LinearSvm,
}

/// Scores the methods on the frames of `paths` labelled with `label`; draws the first frame's CNN
/// predictions to `picture`.
pub fn evaluate_group(
    group: &str,
    paths: &[PathBuf],
    methods: &Methods,
    label: &LabelConfig,
    stride: usize,
    picture: &Path,
) -> Result<GroupResult, FootholdError> {
    let regions = &methods.cnn.regions;
    let region_px = regions.out_px as f64;
    let mut scores = [Scores::default(); METHODS.len()];
    let mut ms = vec![Vec::new(); METHODS.len()];
    let (mut frames, mut region_count, mut positives) = (0, 0, 0);
    let mut drawn = false;
    let mut rows = Vec::new();
    for path in paths {
        let dataset = path.file_name().map_or_else(|| path.display().to_string(), |n| n.to_string_lossy().into_owned());
        let sequence = Sequence::open(path)?;
        let (_, labelled) = sequence.label(stride, regions, label)?;
        for (index, frame) in &labelled {
            let known: Vec<usize> = (0..frame.labels.len()).filter(|&i| frame.labels[i].is_known()).collect();
            if known.is_empty() {
                continue;
            }
            frames += 1;
            region_count += known.len();
            positives += known.iter().filter(|&&i| matches!(frame.labels[i], Label::Positive { .. })).count();
            let targets: Vec<Option<(f32, f32)>> = known
                .iter()
                .map(|&i| match frame.labels[i] {
                    Label::Positive { x, y } => Some((x as f32, y as f32)),
                    _ => None,
                })
                .collect();
            let side = vec![frame.tilt.channels(); frame.regions.len()];
            let depth = sequence.dataset.load_depth(*index)?;
            // The networks: region proposal + inference of the whole frame, timed.
            let mut nets = Vec::new();
            for (m, model) in [&methods.cnn, &methods.no_angle].into_iter().enumerate() {
                let started = Instant::now();
                let predicted = model.predict_frame(&depth, &sequence.dataset.intrinsics, frame.tilt)?;
                ms[m].push(started.elapsed().as_secs_f64() * 1e3);
                if predicted.regions != frame.regions {
                    return Err(FootholdError::Config("the model's region proposal differs from the labelled one".into()));
                }
                let first: Vec<Prediction> = known.iter().map(|&i| predicted.predictions[i][0]).collect();
                scores[m] = add(scores[m], Scores::of(&first, &targets, region_px));
                nets.push(first);
            }
            // The SVM on the same regions.
            let started = Instant::now();
            let s = regions.out_px;
            let len = regions.input_len();
            let svm: Vec<Prediction> = known
                .iter()
                .map(|&i| methods.svm.predict_features(&features(&frame.inputs[i * len..i * len + s * s], s, side[i][2])))
                .collect();
            ms[2].push(started.elapsed().as_secs_f64() * 1e3);
            scores[2] = add(scores[2], Scores::of(&svm, &targets, region_px));
            // The patch pipeline on this frame alone.
            let (geometric, pipeline_ms) = single_frame_footholds(&sequence, *index, &depth, frame, label)?;
            ms[3].push(pipeline_ms);
            let geometric: Vec<Prediction> = known.iter().map(|&i| geometric[i]).collect();
            scores[3] = add(scores[3], Scores::of(&geometric, &targets, region_px));
            // The trivial answer.
            let everywhere = vec![Prediction { p: 1.0, x: 0.5, y: 0.5 }; known.len()];
            ms[4].push(0.0);
            scores[4] = add(scores[4], Scores::of(&everywhere, &targets, region_px));
            let cells = regions.out_px * regions.out_px;
            for (k, &i) in known.iter().enumerate() {
                let depth_cells = &frame.inputs[i * len..i * len + cells];
                rows.push(RegionRow {
                    dataset: dataset.clone(),
                    frame: *index,
                    region: frame.regions[i].clone(),
                    invalid_fraction: depth_cells.iter().filter(|&&c| c == 0.0).count() as f64 / cells as f64,
                    tilt_deg: frame.tilt.degrees,
                    target: targets[k],
                    predictions: [nets[0][k], nets[1][k], svm[k], geometric[k], everywhere[k]],
                });
            }
            if !drawn {
                draw(&depth, frame, &known, &nets[0], &targets, picture)?;
                drawn = true;
            }
        }
    }
    let mut result = GroupResult::from_scores(group, &scores, ms);
    result.datasets = paths.len();
    result.frames = frames;
    result.regions = region_count;
    result.positives = positives;
    result.rows = rows;
    Ok(result)
}

fn add(a: Scores, b: Scores) -> Scores {
    let mut out = a;
    out.merge(&b);
    out
}

/// The patch pipeline on one frame alone (a fresh volume): each region's "prediction" is its label
/// from that frame's footholds ([`region_label`]: p = 1 at the painted centroid when a visible
/// foothold centre lies in its central 80 %, else p = 0). Returns them and the
/// pipeline's time (ms).
fn single_frame_footholds(
    sequence: &Sequence,
    index: usize,
    depth: &DepthImage,
    frame: &LabelledFrame,
    label: &LabelConfig,
) -> Result<(Vec<Prediction>, f64), FootholdError> {
    let half_window = sequence.configs.mapper.acquire.accel_half_window_s;
    let mut single = pipeline(sequence.dataset.intrinsics, &sequence.configs, &sequence.camera_from_imu)?;
    let timestamp = sequence.dataset.frames[index].timestamp;
    for sample in sequence.dataset.accelerometer.iter().filter(|s| (s.timestamp - timestamp).abs() <= half_window) {
        let _ = single.push_imu(sample.timestamp, sample.acceleration_in_imu);
    }
    let output = single.process(depth, timestamp)?;
    let footholds: Vec<_> = single.map().patches().iter().filter(|m| is_foothold(&m.patch, label)).map(|m| m.patch.center).collect();
    let discs = painted_footholds(depth, &sequence.dataset.intrinsics, &output.map_from_camera, &footholds, label);
    let predictions = frame
        .regions
        .iter()
        .map(|r| match region_label(r, &discs, label.centre_fraction) {
            Label::Positive { x, y } => Prediction { p: 1.0, x: x as f32, y: y as f32 },
            _ => Prediction { p: 0.0, x: 0.5, y: 0.5 },
        })
        .collect();
    Ok((predictions, output.timings.total_ms))
}

/// CNN Fig. 6: the CNN's predictions on the frame's depth image.
fn draw(
    depth: &DepthImage,
    frame: &LabelledFrame,
    known: &[usize],
    predictions: &[Prediction],
    targets: &[Option<(f32, f32)>],
    path: &Path,
) -> Result<(), FootholdError> {
    let mut picture = Picture::of_depth(depth);
    for ((&i, p), t) in known.iter().zip(predictions).zip(targets) {
        let region = &frame.regions[i];
        match (p.p >= 0.5, t) {
            (true, Some(_)) => {
                let (u, v) = region.to_image(f64::from(p.x), f64::from(p.y));
                picture.mark(u, v, Mark::TruePositive);
            }
            (true, None) => {
                let (u, v) = region.to_image(f64::from(p.x), f64::from(p.y));
                picture.mark(u, v, Mark::FalsePositive);
            }
            (false, Some((x, y))) => {
                let (u, v) = region.to_image(f64::from(*x), f64::from(*y));
                picture.mark(u, v, Mark::FalseNegative);
            }
            (false, None) => {}
        }
    }
    picture.save_png(path)?;
    Ok(())
}

/// The table of CNN Tables I-II for the groups.
pub fn format_table(results: &[GroupResult]) -> String {
    use std::fmt::Write;
    let mut out = String::new();
    let _ =
        writeln!(out, "{:<32} {:>10} {:>10} {:>6} {:>6} {:>6} {:>10}", "method", "class err", "regr (px)", "TP", "FP", "FN", "ms/frame");
    for group in results {
        let _ = writeln!(
            out,
            "-- {} ({} datasets, {} frames, {} regions, {:.1} % positive)",
            group.group,
            group.datasets,
            group.frames,
            group.regions,
            100.0 * group.positives as f64 / group.regions.max(1) as f64
        );
        for (name, s, error, ms) in &group.scores {
            let _ = writeln!(
                out,
                "{:<32} {:>9.2}% {:>10.2} {:>6} {:>6} {:>6} {:>10.1}",
                name,
                100.0 * error,
                s.regression_px(),
                s.true_positives,
                s.false_positives,
                s.false_negatives,
                ms
            );
        }
    }
    let _ = writeln!(out, "(regression error in pixels of the 60 x 60 region over the true positives, as CNN Tables I-II; ms: CNN region proposal + inference, SVM features + decision, pipeline single-frame total; the last row answers \"foothold at the centre\" everywhere)");
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn group(name: &str, frames: usize, hit: bool, ms: f64) -> GroupResult {
        let mut scores = [Scores::default(); METHODS.len()];
        for s in &mut scores {
            s.add(hit.then_some((0.5, 0.5)), Some((0.5, 0.6)), 60.0);
            s.add(None, None, 60.0);
        }
        let mut g = GroupResult::from_scores(name, &scores, vec![vec![ms; frames]; METHODS.len()]);
        (g.datasets, g.frames, g.regions, g.positives) = (1, frames, 2, 1);
        g
    }

    #[test]
    fn merged_groups_sum_counts_and_rescore() {
        let total = GroupResult::merged("all", &[group("a", 1, true, 10.0), group("b", 2, false, 30.0)]);
        assert_eq!((total.datasets, total.frames, total.regions, total.positives), (2, 3, 4, 2));
        let (name, scores, error, ms) = &total.scores[0];
        assert_eq!(name, METHODS[0]);
        assert_eq!((scores.samples, scores.true_positives, scores.false_negatives), (4, 1, 1));
        assert!((error - 0.25).abs() < 1e-12 && (scores.regression_px() - 6.0).abs() < 1e-9);
        assert_eq!(*ms, 30.0);
        assert!(format_table(&[total]).contains("all (2 datasets, 3 frames, 4 regions, 50.0 % positive)"));
    }

    #[test]
    fn region_rows_are_a_csv_of_one_line_per_region_with_every_method() {
        let mut g = group("real frames", 1, true, 10.0);
        let region = Region { row: 3, col: 4, u: 100.0, v: 200.0, depth_m: 0.8, size_px: 96 };
        let answer = |p: f32| Prediction { p, x: 0.25, y: 0.75 };
        let predictions = [answer(0.9), answer(0.2), answer(0.6), answer(0.0), answer(1.0)];
        for target in [Some((0.5, 0.5)), None] {
            let row = RegionRow {
                dataset: "tum".into(),
                frame: 5,
                region: region.clone(),
                invalid_fraction: 0.125,
                tilt_deg: 44.0,
                target,
                predictions,
            };
            g.rows.push(row);
        }
        let csv = format_region_rows(&[g]);
        let lines: Vec<Vec<&str>> = csv.lines().map(|l| l.split(',').collect()).collect();
        assert_eq!(lines.len(), 3);
        assert!(lines.iter().all(|l| l.len() == 14 + 3 * METHODS.len()), "{csv}");
        assert_eq!(&lines[1][..12], ["real frames", "tum", "5", "3", "4", "100.0", "200.0", "0.800", "96", "0.125", "44.00", "1"]);
        assert_eq!(lines[2][11], "0");
        assert_eq!(&lines[1][14..17], ["0.9000", "0.250", "0.750"]);
    }
}
