//! The labels of a recorded sequence are the same in every run, whatever thread pool the labelling
//! is called from: the TUM fr1/xyz excerpt (37 frames fused, every 5th labelled) three times in a
//! pool of four threads.

use std::path::Path;

use patchwalk_footholds::labels::{Label, LabelConfig};
use patchwalk_footholds::regions::RegionConfig;
use patchwalk_footholds::sequence::Sequence;

type Labelled = Vec<(usize, Vec<Label>, Vec<f32>)>;

fn labels_of_a_run() -> Result<Labelled, Box<dyn std::error::Error>> {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../tests/data/tum_fr1_xyz");
    let pool = rayon::ThreadPoolBuilder::new().num_threads(4).build()?;
    let frames = pool.install(|| -> Result<_, patchwalk_footholds::error::FootholdError> {
        let sequence = Sequence::open(&path)?;
        Ok(sequence.label(5, &RegionConfig::default(), &LabelConfig::default())?.1)
    })?;
    Ok(frames.into_iter().map(|(index, frame)| (index, frame.labels, frame.inputs)).collect())
}

#[test]
fn labelling_a_sequence_twice_gives_the_same_labels() {
    let first = labels_of_a_run().unwrap();
    let known: usize = first.iter().map(|(_, labels, _)| labels.iter().filter(|l| l.is_known()).count()).sum();
    let negatives: usize = first.iter().map(|(_, labels, _)| labels.iter().filter(|l| matches!(l, Label::Negative)).count()).sum();
    assert!(first.len() >= 7 && known > 600 && negatives > 10, "{} frames, {known} known regions, {negatives} negative", first.len());
    for run in 0..2 {
        assert!(labels_of_a_run().unwrap() == first, "run {} labelled differently", run + 2);
    }
}
