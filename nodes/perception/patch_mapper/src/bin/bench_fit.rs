//! Patch-fit benchmark: accuracy, covariance honesty and type classification over random synthetic
//! patches seen by a virtual Kinect (Murray–Little noise), and the speed of fit + validate.
//!
//! `cargo run --release -p patch_mapper --bin bench_fit -- [--trials 1000] [--points 150] [--seed 1]
//! [--skip-accuracy] [--skip-speed] [--noise-scale 1] [--significance α]` (`--noise-scale` multiplies the Kinect's σp and σd,
//! e.g. 0.01 to see the covariance at small noise).

use anyhow::{bail, Context, Result};
use nalgebra::{Matrix3, Vector3};
use patchwalk_spl::fit::simulate::{
    chi2_95, error_on_manifold, mahalanobis, random_visible_patch as random_patch, sample_sensor, truth_params, SceneConfig,
};
use patchwalk_spl::fit::{
    fit_patch, fit_patch_with_boundary_points, BoundaryRequest, FitConfig, FitError, FitRequest, SurfaceRequest, WeightDerivative,
};
use patchwalk_spl::patch::{BoundaryType, Patch, SurfaceType, PATCH_TYPES};
use patchwalk_spl::sensor::{ErrorModel, StereoErrorParams};
use patchwalk_spl::validate::{validate_patch, ValidateConfig};
use rand::SeedableRng;
use std::time::Instant;

const AUTO_FAMILY: [(SurfaceType, BoundaryType); 5] = [
    (SurfaceType::Plane, BoundaryType::Ellipse),
    (SurfaceType::CircularParaboloid, BoundaryType::Circle),
    (SurfaceType::CylindricParaboloid, BoundaryType::Rectangle),
    (SurfaceType::EllipticParaboloid, BoundaryType::Ellipse),
    (SurfaceType::HyperbolicParaboloid, BoundaryType::Ellipse),
];

struct Args {
    trials: usize,
    points: usize,
    seed: u64,
    accuracy: bool,
    speed: bool,
    noise_scale: f64,
    /// Points the boundary moments (and the apex's centroid) are taken over: the N fit points plus
    /// more samples of the same patch, as the mapper fits nf = 50 points and takes the moments over
    /// the whole neighbourhood.
    boundary_points: BoundaryPoints,
    fit: FitConfig,
}

fn parse_args() -> Result<Args> {
    let mut args = Args {
        trials: 1000,
        points: 150,
        seed: 1,
        accuracy: true,
        speed: true,
        noise_scale: 1.0,
        boundary_points: BoundaryPoints::Count(0),
        fit: FitConfig::default(),
    };
    let mut it = std::env::args().skip(1);
    while let Some(a) = it.next() {
        match a.as_str() {
            "--trials" => args.trials = it.next().context("--trials N")?.parse()?,
            "--points" => args.points = it.next().context("--points N")?.parse()?,
            "--seed" => args.seed = it.next().context("--seed N")?.parse()?,
            "--skip-accuracy" => args.accuracy = false,
            "--skip-speed" => args.speed = false,
            "--noise-scale" => args.noise_scale = it.next().context("--noise-scale X")?.parse()?,
            "--significance" => args.fit.significance = it.next().context("--significance α")?.parse()?,
            "--boundary-points" => {
                args.boundary_points = match it.next().context("--boundary-points M|pixels")?.as_str() {
                    "pixels" => BoundaryPoints::Pixels,
                    m => BoundaryPoints::Count(m.parse()?),
                }
            }
            "--no-apex-from-centroid" => args.fit.apex_from_centroid = false,
            "--weight-derivative" => {
                args.fit.weight_derivative = match it.next().context("--weight-derivative never|distance_like|always")?.as_str() {
                    "never" => WeightDerivative::Never,
                    "distance_like" => WeightDerivative::DistanceLike,
                    "always" => WeightDerivative::Always,
                    other => bail!("unknown --weight-derivative {other}"),
                }
            }
            other => bail!("unknown argument {other}"),
        }
    }
    Ok(args)
}

fn quantile(v: &mut [f64], q: f64) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    let idx = ((v.len() - 1) as f64 * q).round() as usize;
    v.get(idx).copied().unwrap_or(f64::NAN)
}

/// The Kinect Murray–Little model with σp and σd multiplied by `scale`.
fn kinect_scaled(scale: f64) -> ErrorModel {
    let p = StereoErrorParams::default();
    ErrorModel::MurrayLittle(StereoErrorParams {
        sigma_pointing_px: p.sigma_pointing_px * scale,
        sigma_disparity_px: p.sigma_disparity_px * scale,
        ..p
    })
}

/// How many points the boundary moments are taken over.
#[derive(Clone, Copy)]
enum BoundaryPoints {
    /// This many (at least the fit points).
    Count(usize),
    /// As many as the Kinect's pixels on the patch (the mapper's whole neighbourhood).
    Pixels,
}

/// Pixels of the error model's camera (its focal length) the patch covers: its area foreshortened along the ray to
/// its centre, over the pixel footprint `(z/f)²`.
fn pixels_on(truth: &Patch) -> usize {
    let focal = StereoErrorParams::default().focal_px;
    let range = truth.center.norm();
    let cos = truth.normal().dot(&truth.center).abs() / range.max(1e-9);
    (truth.boundary_area() * cos * (focal / range).powi(2)).round() as usize
}

/// One trial's noisy samples: the points to fit (with their covariances) and the points the boundary
/// moments are taken over (the fit points plus `--boundary-points − N` more of the same patch).
struct Sample {
    fit_points: Vec<Vector3<f64>>,
    covariances: Vec<Matrix3<f64>>,
    boundary_points: Vec<Vector3<f64>>,
}

impl Sample {
    fn draw<R: rand::Rng + ?Sized>(rng: &mut R, truth: &Patch, args: &Args, model: &ErrorModel) -> Self {
        let m = match args.boundary_points {
            BoundaryPoints::Count(m) => m,
            BoundaryPoints::Pixels => pixels_on(truth),
        };
        let (boundary_points, mut covariances) = sample_sensor(rng, truth, m.max(args.points), model);
        let fit_points = boundary_points[..args.points.min(boundary_points.len())].to_vec();
        covariances.truncate(fit_points.len());
        Self { fit_points, covariances, boundary_points }
    }

    fn fit(&self, request: &FitRequest, cfg: &FitConfig) -> Result<Patch, FitError> {
        fit_patch_with_boundary_points(&self.fit_points, Some(&self.covariances), &self.boundary_points, request, cfg)
    }
}

/// Normal angle (°), centre distance (mm) and, for curved types, the largest curvature error
/// (1/m; elliptic/hyperbolic compared in either axis order) of `fit` against `truth`.
fn errors(fit: &Patch, truth: &Patch) -> (f64, f64, Option<f64>) {
    let normal = fit.normal().dot(&truth.normal()).clamp(-1.0, 1.0).acos().to_degrees();
    let centre = (fit.center - truth.center).norm() * 1000.0;
    let curv = (truth.surface != SurfaceType::Plane).then(|| {
        let swapped = nalgebra::Vector2::new(fit.curvatures.y, fit.curvatures.x);
        let direct = (fit.curvatures - truth.curvatures).abs().max();
        let alt = (swapped - truth.curvatures).abs().max();
        let symmetric = matches!(truth.surface, SurfaceType::EllipticParaboloid | SurfaceType::HyperbolicParaboloid);
        if symmetric {
            direct.min(alt)
        } else {
            direct
        }
    });
    (normal, centre, curv)
}

/// A patch with parameters drawn from `N(fit.params(), fit.covariance)` (by the symmetric eigen
/// decomposition, so a rank-deficient Σ is fine); `None` if Σ is not finite or the draw is not a
/// valid patch (e.g. a negative extent).
fn draw_from_covariance<R: rand::Rng + ?Sized>(rng: &mut R, fit: &Patch) -> Option<Patch> {
    use rand_distr::{Distribution, StandardNormal};
    if !fit.covariance.iter().all(|v| v.is_finite()) {
        return None;
    }
    let eig = fit.covariance.clone().symmetric_eigen();
    let mut params = fit.params();
    for (i, lambda) in eig.eigenvalues.iter().enumerate() {
        let z: f64 = StandardNormal.sample(rng);
        params.axpy(z * lambda.max(0.0).sqrt(), &eig.eigenvectors.column(i), 1.0);
    }
    Patch::from_params(fit.surface, fit.boundary, params.as_slice()).ok()
}

fn accuracy(args: &Args) {
    let model = kinect_scaled(args.noise_scale);
    let scene = SceneConfig::default();
    let cfg = args.fit;
    let mut rng = rand::rngs::StdRng::seed_from_u64(args.seed);
    println!(
        "== accuracy: {} trials/type, {} points, range {:.1}-{:.1} m, Kinect Murray-Little noise x {} (requested type) ==",
        args.trials, args.points, scene.range.0, scene.range.1, args.noise_scale
    );
    println!(
        "{:<34} {:>6} {:>14} {:>14} {:>16} {:>9} {:>9} {:>9}",
        "type", "fails", "normal ° med/p95", "centre mm med/p95", "curv 1/m med/p95", "in95%", "in95%srf", "in95%r-r"
    );
    println!("  (in95%: truth inside the 95% ellipsoid of Σ, rotation error on SO(3); in95%srf: the same without the");
    println!("  boundary extents; in95%r-r: rotation error as a plain difference of exp-map vectors. Last two columns:");
    println!("  the fitted surface at the true centre — normal ° and distance mm, med/p95. Row 'Σ-predicted': the same");
    println!("  errors for draws from N(fit, Σ), i.e. the floor an efficient estimator with the fit's Σ would reach)");
    let mut all_in = (0usize, 0usize);
    let mut all_chart = 0usize;
    for (s, b) in PATCH_TYPES {
        let (mut normal, mut centre, mut curv) = (Vec::new(), Vec::new(), Vec::new());
        let (mut s_normal, mut s_offset) = (Vec::new(), Vec::new());
        let mut floor: [Vec<f64>; 3] = Default::default();
        let (mut inside, mut inside_surf, mut inside_chart, mut counted, mut fails) = (0usize, 0usize, 0usize, 0usize, 0usize);
        let debug = std::env::var("BENCH_DEBUG").is_ok();
        let mut z2 = [0.0; 11];
        let mut worse = 0usize;
        for _ in 0..args.trials {
            let Ok(truth) = random_patch(&mut rng, s, b, &scene) else { continue };
            let data = Sample::draw(&mut rng, &truth, args, &model);
            let (pts, covs) = (&data.fit_points, &data.covariances);
            let request =
                FitRequest { surface: SurfaceRequest::Exactly(s), boundary: BoundaryRequest::Exactly(b), ..FitRequest::default() };
            let Ok(fit) = data.fit(&request, &cfg) else {
                fails += 1;
                continue;
            };
            let (n_deg, c_mm, k_err) = errors(&fit, &truth);
            normal.push(n_deg);
            centre.push(c_mm);
            curv.extend(k_err);
            // The same errors for a draw from N(fit, Σ): what an efficient estimator whose
            // covariance is Σ would show (Σ is first-order, i.e. the Cramér–Rao bound at the fit).
            if let Some(draw) = draw_from_covariance(&mut rng, &fit) {
                let (n_deg, c_mm, k_err) = errors(&draw, &fit);
                floor[0].push(n_deg);
                floor[1].push(c_mm);
                floor[2].extend(k_err);
            }
            {
                // The fitted surface where the true centre is: closest point and its normal.
                let q_l = fit.to_local(&truth.center);
                let p = fit.closest_point_local(&q_l);
                let g = fit.height(&p.xy()).map(|(_, g)| g).unwrap_or_default();
                let n_w = fit.rotation_matrix() * Vector3::new(-g.x, -g.y, 1.0).normalize();
                s_normal.push(n_w.dot(&truth.normal()).clamp(-1.0, 1.0).acos().to_degrees());
                s_offset.push((p - q_l).norm() * 1000.0);
            }
            if let Some(tp) = truth_params(&mut rng, &truth, &fit, 0.95) {
                if let Some((m2, rank)) = mahalanobis(&(fit.params() - &tp), &fit.covariance) {
                    if m2 <= chi2_95(rank) {
                        inside_chart += 1;
                    }
                }
                let err = error_on_manifold(&fit, &tp);
                if debug {
                    for i in 0..err.len() {
                        z2[i] += err[i] * err[i] / fit.covariance[(i, i)].max(1e-300);
                    }
                    let truth_res = patchwalk_spl::fit::chi_square(&truth, pts, Some(covs), &cfg);
                    let fit_res = patchwalk_spl::fit::chi_square(&fit, pts, Some(covs), &cfg);
                    if fit_res > truth_res + 1e-6 {
                        worse += 1;
                    }
                }
                if let Some((m2, rank)) = mahalanobis(&err, &fit.covariance) {
                    counted += 1;
                    if m2 <= chi2_95(rank) {
                        inside += 1;
                    }
                }
                // Surface + pose only (without the boundary extents).
                let nd = b.num_params();
                let p = fit.dof();
                let sub_err = err.rows(nd, p - nd).into_owned();
                let sub_cov = fit.covariance.view((nd, nd), (p - nd, p - nd)).into_owned();
                if let Some((m2, rank)) = mahalanobis(&sub_err, &sub_cov) {
                    if m2 <= chi2_95(rank) {
                        inside_surf += 1;
                    }
                }
            }
        }
        if debug {
            let z: Vec<String> = z2
                .iter()
                .take(b.num_params() + s.num_curvatures() + 6)
                .map(|v| format!("{:.2}", (v / counted.max(1) as f64).sqrt()))
                .collect();
            println!("  rms z per param {:?}; fit χ² above the truth's in {worse} trials", z);
        }
        all_in.0 += inside;
        all_in.1 += counted;
        let name = format!("{}/{}", s.name(), b.name());
        let (nm, n95) = (quantile(&mut normal, 0.5), quantile(&mut normal, 0.95));
        let (cm, c95) = (quantile(&mut centre, 0.5), quantile(&mut centre, 0.95));
        let (km, k95) = (quantile(&mut curv, 0.5), quantile(&mut curv, 0.95));
        let (sn, sn95) = (quantile(&mut s_normal, 0.5), quantile(&mut s_normal, 0.95));
        let (so, so95) = (quantile(&mut s_offset, 0.5), quantile(&mut s_offset, 0.95));
        let pct = |a: usize| 100.0 * a as f64 / counted.max(1) as f64;
        println!(
            "{name:<34} {fails:>6} {nm:>6.2} / {n95:>5.2} {cm:>6.2} / {c95:>5.2}   {km:>6.2} / {k95:>5.2}  {:>7.1}% {:>7.1}% {:>7.1}%   {sn:>5.2} / {sn95:>5.2}  {so:>5.2} / {so95:>5.2}",
            pct(inside),
            pct(inside_surf),
            pct(inside_chart)
        );
        let [mut fn_, mut fc, mut fk] = floor;
        println!(
            "  {:<32} {:>6} {:>6.2} / {:>5.2} {:>6.2} / {:>5.2}   {:>6.2} / {:>5.2}",
            "Σ-predicted (efficient estimator)",
            "",
            quantile(&mut fn_, 0.5),
            quantile(&mut fn_, 0.95),
            quantile(&mut fc, 0.5),
            quantile(&mut fc, 0.95),
            quantile(&mut fk, 0.5),
            quantile(&mut fk, 0.95)
        );
        all_chart += inside_chart;
    }
    println!(
        "covariance honesty over all types: {:.1}% of {} trials inside the 95% ellipsoid ({:.1}% with exp-map vector differences)",
        100.0 * all_in.0 as f64 / all_in.1.max(1) as f64,
        all_in.1,
        100.0 * all_chart as f64 / all_in.1.max(1) as f64
    );

    println!("\n== type classification (surface auto, {} trials/type, significance α = {}) ==", args.trials, cfg.significance);
    println!("  SNR = (smallest curvature feature's sag ½|κ|d²) · √N / σ_z; columns: all | SNR < 10 | 10–30 | ≥ 30");
    let mut tally = [[0usize; 2]; 4];
    for (s, b) in AUTO_FAMILY {
        let mut counts = std::collections::BTreeMap::<&'static str, usize>::new();
        let mut t = [[0usize; 2]; 4];
        for _ in 0..args.trials {
            let Ok(truth) = random_patch(&mut rng, s, b, &scene) else { continue };
            let data = Sample::draw(&mut rng, &truth, args, &model);
            let ok = match data.fit(&FitRequest::default(), &cfg) {
                Ok(fit) => {
                    *counts.entry(fit.surface.name()).or_default() += 1;
                    fit.surface == s
                }
                Err(_) => {
                    *counts.entry("error").or_default() += 1;
                    false
                }
            };
            let bin = match snr(&truth, data.fit_points.len()) {
                x if x < 10.0 => 1,
                x if x < 30.0 => 2,
                _ => 3,
            };
            for idx in [0, bin] {
                t[idx][0] += usize::from(ok);
                t[idx][1] += 1;
            }
        }
        let rate =
            |x: [usize; 2]| if x[1] == 0 { "   -  ".to_string() } else { format!("{:5.1}% ({})", 100.0 * x[0] as f64 / x[1] as f64, x[1]) };
        println!("{:<24} {} | {} | {} | {}  {:?}", s.name(), rate(t[0]), rate(t[1]), rate(t[2]), rate(t[3]), counts);
        for i in 0..4 {
            tally[i][0] += t[i][0];
            tally[i][1] += t[i][1];
        }
    }
    let rate = |x: [usize; 2]| 100.0 * x[0] as f64 / x[1].max(1) as f64;
    println!(
        "overall classification rate: {:.1}% of {} | SNR<10 {:.1}% | 10-30 {:.1}% | >=30 {:.1}%",
        rate(tally[0]),
        tally[0][1],
        rate(tally[1]),
        rate(tally[2]),
        rate(tally[3])
    );
}

/// Signal-to-noise of the weakest curvature feature that separates the type from its simpler
/// neighbours: sag `½|κ|d²` of the smallest non-zero curvature (or curvature difference) over the
/// smallest boundary extent, times √N, over the Kinect depth noise at the patch range.
fn snr(truth: &Patch, n: usize) -> f64 {
    let k = truth.curvatures;
    let feature = match truth.surface {
        SurfaceType::EllipticParaboloid => k.x.abs().min((k.x - k.y).abs()),
        SurfaceType::HyperbolicParaboloid => k.x.abs().min(k.y.abs()),
        SurfaceType::Plane => return f64::INFINITY,
        _ => k.y.abs(),
    };
    let d = truth.boundary_half_extents().min();
    let p = patchwalk_spl::sensor::StereoErrorParams::default();
    let z = truth.center.z;
    let sigma_z = z * z * p.sigma_disparity_px / (p.focal_px * p.baseline_m);
    0.5 * feature * d * d * (n as f64).sqrt() / sigma_z
}

fn speed(args: &Args) {
    let model = ErrorModel::default();
    let scene = SceneConfig::default();
    let cfg = args.fit;
    let vcfg = ValidateConfig::default();
    let mut rng = rand::rngs::StdRng::seed_from_u64(args.seed + 1);
    let load = std::fs::read_to_string("/proc/loadavg").unwrap_or_default();
    println!("\n== speed: fit (surface auto) + validate on the same points, one thread; loadavg {}", load.trim());
    for nf in [50usize, 150] {
        let samples: Vec<_> = (0..2000)
            .filter_map(|i| {
                let (s, b) = AUTO_FAMILY[i % AUTO_FAMILY.len()];
                let truth = random_patch(&mut rng, s, b, &scene).ok()?;
                Some(sample_sensor(&mut rng, &truth, nf, &model))
            })
            .collect();
        let mut fit_us = Vec::with_capacity(samples.len());
        let mut total_us = Vec::with_capacity(samples.len());
        for _round in 0..3 {
            for (pts, covs) in &samples {
                let t0 = Instant::now();
                let fit = fit_patch(pts, Some(covs), &FitRequest::default(), &cfg);
                let t1 = Instant::now();
                if let Ok(p) = &fit {
                    std::hint::black_box(validate_patch(p, pts, &vcfg));
                }
                let t2 = Instant::now();
                fit_us.push((t1 - t0).as_secs_f64() * 1e6);
                total_us.push((t2 - t0).as_secs_f64() * 1e6);
            }
        }
        let (f50, f95, f99) = (quantile(&mut fit_us, 0.5), quantile(&mut fit_us, 0.95), quantile(&mut fit_us, 0.99));
        let (t50, t95, t99) = (quantile(&mut total_us, 0.5), quantile(&mut total_us, 0.95), quantile(&mut total_us, 0.99));
        println!("nf = {nf:>3}: fit µs median {f50:.1} p95 {f95:.1} p99 {f99:.1} | fit+validate µs median {t50:.1} p95 {t95:.1} p99 {t99:.1} ({} calls)", fit_us.len());
    }
}

fn main() -> Result<()> {
    let args = parse_args()?;
    if args.accuracy {
        accuracy(&args);
    }
    if args.speed {
        speed(&args);
    }
    Ok(())
}
