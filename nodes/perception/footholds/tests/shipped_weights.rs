//! Inference of the shipped weights on a fixed frame gives the stored output
//! (`weights/reference_predictions.json`): the first TUM fr1/xyz depth frame at a 49° tilt, every
//! region's p, x and y for both shipped networks. After regenerating the weights
//! (`scripts/make_weights.sh`), rewrite the stored output with
//! `PATCHWALK_WRITE_REFERENCE=1 cargo nextest run --release -p patchwalk_footholds --test shipped_weights`.

use std::path::{Path, PathBuf};

use patchwalk_footholds::model::FootholdModel;
use patchwalk_footholds::tilt::Tilt;
use patchwalk_fusion::dataset::Dataset;

#[derive(serde::Serialize, serde::Deserialize, PartialEq, Debug)]
struct Reference {
    tilt_deg: f64,
    /// Per network file name: per region [p, x, y].
    networks: Vec<(String, Vec<[f32; 3]>)>,
}

fn crate_dir() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

fn reference_path() -> PathBuf {
    crate_dir().join("weights").join("reference_predictions.json")
}

fn predict_all() -> Result<Reference, Box<dyn std::error::Error>> {
    let dataset = Dataset::open(&crate_dir().join("../../../tests/data/tum_fr1_xyz"))?;
    let depth = dataset.load_depth(0)?;
    let tilt = Tilt::from_degrees(49.0)?;
    let mut networks = Vec::new();
    for no_angle in [false, true] {
        let path = patchwalk_footholds::shipped_weights_path(no_angle);
        let model = FootholdModel::load(&path)?;
        let frame = model.predict_frame(&depth, &dataset.intrinsics, tilt)?;
        let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        networks.push((name, frame.predictions.iter().map(|p| [p[0].p, p[0].x, p[0].y]).collect()));
    }
    Ok(Reference { tilt_deg: 49.0, networks })
}

#[test]
fn shipped_weights_give_the_stored_output_on_a_fixed_frame() {
    let now = predict_all().unwrap();
    if std::env::var_os("PATCHWALK_WRITE_REFERENCE").is_some() {
        std::fs::write(reference_path(), serde_json::to_string(&now).unwrap()).unwrap();
    }
    let stored: Reference = serde_json::from_str(&std::fs::read_to_string(reference_path()).unwrap()).unwrap();
    assert_eq!(stored.tilt_deg, now.tilt_deg);
    assert_eq!(stored.networks.len(), 2);
    for ((name, want), (_, got)) in stored.networks.iter().zip(&now.networks) {
        assert!(want.len() > 200, "{name}: {} regions of the 640 x 480 frame", want.len());
        assert_eq!(want.len(), got.len(), "{name}");
        for (i, (w, g)) in want.iter().zip(got).enumerate() {
            for k in 0..3 {
                assert!((w[k] - g[k]).abs() <= 1e-4, "{name}: region {i} output {k}: stored {} now {}", w[k], g[k]);
            }
        }
        // The frame is not degenerate: the network tells regions apart.
        let (lo, hi) = want.iter().fold((f32::MAX, f32::MIN), |(lo, hi), p| (lo.min(p[0]), hi.max(p[0])));
        assert!(hi - lo > 0.05, "{name}: p spans only {lo}..{hi}");
    }
}
