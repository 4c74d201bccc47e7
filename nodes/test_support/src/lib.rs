//! Test helpers shared by the patchwalk crates, used only as a dev-dependency.
//!
//! [`stored_fuzz_inputs`] reads the stored inputs of one fuzz target (seeds, minimised corpus,
//! inputs that once crashed) from `tests/data/fuzz/<target>/`, so the unit tests next to each entry
//! point replay the same corpus the fuzz targets in `nodes/fuzz` grow.

use std::path::{Path, PathBuf};

/// The repository's stored fuzz inputs: `tests/data/fuzz/` at the repository root.
pub fn fuzz_corpus_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/data/fuzz")
}

/// Every file of `tests/data/fuzz/<target>/` with its bytes, sorted by path.
///
/// # Panics
/// When the directory is missing, unreadable or empty: the corpus is part of the repository, so a
/// test that finds none must fail rather than pass over nothing.
#[allow(clippy::panic)] // a test helper: failing loudly is its job
pub fn stored_fuzz_inputs(target: &str) -> Vec<(PathBuf, Vec<u8>)> {
    let dir = fuzz_corpus_dir().join(target);
    let mut inputs: Vec<(PathBuf, Vec<u8>)> = std::fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .map(|entry| entry.unwrap_or_else(|e| panic!("{}: {e}", dir.display())).path())
        .map(|path| {
            let bytes = std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
            (path, bytes)
        })
        .collect();
    inputs.sort();
    assert!(!inputs.is_empty(), "no stored inputs in {}", dir.display());
    inputs
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_target_directory_holds_inputs() {
        let targets: Vec<String> =
            std::fs::read_dir(fuzz_corpus_dir()).unwrap().map(|entry| entry.unwrap().file_name().to_string_lossy().into_owned()).collect();
        assert!(targets.iter().any(|t| t == "params_yaml"), "{targets:?}");
        for target in &targets {
            let inputs = stored_fuzz_inputs(target);
            assert!(inputs.windows(2).all(|w| w[0].0 < w[1].0), "{target}: not sorted");
        }
    }
}
