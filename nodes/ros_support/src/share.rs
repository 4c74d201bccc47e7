//! Where a node finds its data files (URDF, YAML): the working directory, the package's share
//! directory in the ament index, then the source tree it was built from.
//!
//! A colcon install puts each node's `config/`, `urdf/` (and launch files) into
//! `<prefix>/share/<package>/`; `source install/setup.bash` lists the prefixes in `AMENT_PREFIX_PATH`.
//! A package is registered in a prefix by the marker file
//! `<prefix>/share/ament_index/resource_index/packages/<package>` (what `ament_index_python`'s
//! `get_package_share_directory` looks up), and the first prefix that has it wins.

use std::ffi::OsStr;
use std::path::{Path, PathBuf};

/// The variable listing the install prefixes (set by an install's `setup.bash`).
pub const AMENT_PREFIX_PATH: &str = "AMENT_PREFIX_PATH";

/// Where a data file was found (for the node's log line).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Origin {
    /// An absolute path, taken as given.
    Absolute,
    /// Relative to the working directory (a node started from the repository).
    WorkingDirectory,
    /// The package's share directory found through the ament index.
    PackageShare,
    /// The source tree the binary was built from.
    SourceTree,
}

impl std::fmt::Display for Origin {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Origin::Absolute => "absolute path",
            Origin::WorkingDirectory => "working directory",
            Origin::PackageShare => "package share (ament index)",
            Origin::SourceTree => "source tree",
        })
    }
}

/// The share directory of `package` in the first prefix of `prefix_path` (an `AMENT_PREFIX_PATH`
/// value) that registers it in the ament index.
pub fn package_share_in(prefix_path: &OsStr, package: &str) -> Option<PathBuf> {
    std::env::split_paths(prefix_path).filter(|prefix| !prefix.as_os_str().is_empty()).find_map(|prefix| {
        let marker = prefix.join("share/ament_index/resource_index/packages").join(package);
        marker.is_file().then(|| prefix.join("share").join(package))
    })
}

/// The share directory of `package` through this process's `AMENT_PREFIX_PATH`.
pub fn package_share(package: &str) -> Option<PathBuf> {
    std::env::var_os(AMENT_PREFIX_PATH).and_then(|paths| package_share_in(&paths, package))
}

/// Find a data file named by `path`: an absolute path as given; a relative one in the working
/// directory, then in `package`'s share directory (ament index), then under `source_root` (the
/// repository the binary was built from). `None` when it is in none of them.
pub fn find_data_file(path: &Path, package: &str, source_root: &Path) -> Option<(PathBuf, Origin)> {
    find_data_file_in(path, package_share(package).as_deref(), source_root)
}

/// [`find_data_file`] with the package's share directory given (`None`: not installed).
pub fn find_data_file_in(path: &Path, share: Option<&Path>, source_root: &Path) -> Option<(PathBuf, Origin)> {
    if path.is_absolute() {
        return path.exists().then(|| (path.to_path_buf(), Origin::Absolute));
    }
    let candidates = [
        Some((path.to_path_buf(), Origin::WorkingDirectory)),
        share.map(|share| (share.join(path), Origin::PackageShare)),
        Some((source_root.join(path), Origin::SourceTree)),
    ];
    candidates.into_iter().flatten().find(|(candidate, _)| candidate.exists())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn install(prefix: &Path, package: &str, file: &str) {
        let index = prefix.join("share/ament_index/resource_index/packages");
        std::fs::create_dir_all(&index).unwrap();
        std::fs::write(index.join(package), "").unwrap();
        let data = prefix.join("share").join(package).join(file);
        std::fs::create_dir_all(data.parent().unwrap()).unwrap();
        std::fs::write(data, "data").unwrap();
    }

    #[test]
    fn share_comes_from_the_first_prefix_that_registers_the_package() {
        let dir = tempfile::tempdir().unwrap();
        let (a, b, c) = (dir.path().join("a"), dir.path().join("b"), dir.path().join("c"));
        install(&b, "step_executor", "urdf/rpbp.urdf");
        install(&c, "step_executor", "urdf/rpbp.urdf");
        // `a` has a share directory of the name but no index marker: not an install of the package.
        std::fs::create_dir_all(a.join("share/step_executor")).unwrap();
        let paths = std::env::join_paths([&a, &b, &c]).unwrap();
        assert_eq!(package_share_in(&paths, "step_executor"), Some(b.join("share/step_executor")));
        assert_eq!(package_share_in(&paths, "terrain_sim"), None);
        assert_eq!(package_share_in(OsStr::new(""), "step_executor"), None);
    }

    #[test]
    fn data_file_order_is_working_directory_share_source_tree() {
        let dir = tempfile::tempdir().unwrap();
        let prefix = dir.path().join("install");
        install(&prefix, "terrain_sim", "urdf/only_installed.urdf");
        let share = prefix.join("share/terrain_sim");
        let source = dir.path().join("repo");
        std::fs::create_dir_all(source.join("urdf")).unwrap();
        std::fs::write(source.join("urdf/only_installed.urdf"), "source").unwrap();
        std::fs::write(source.join("urdf/only_source.urdf"), "source").unwrap();

        let installed = Path::new("urdf/only_installed.urdf");
        assert_eq!(find_data_file_in(installed, Some(&share), &source), Some((share.join(installed), Origin::PackageShare)));
        // Not installed: the source tree.
        assert_eq!(find_data_file_in(installed, None, &source), Some((source.join(installed), Origin::SourceTree)));
        let source_only = Path::new("urdf/only_source.urdf");
        assert_eq!(find_data_file_in(source_only, Some(&share), &source), Some((source.join(source_only), Origin::SourceTree)));
        assert_eq!(find_data_file_in(Path::new("urdf/nowhere.urdf"), Some(&share), &source), None);
        // The working directory comes first (this crate's tests run in its own directory).
        let cargo_toml = Path::new("Cargo.toml");
        assert_eq!(find_data_file_in(cargo_toml, Some(&share), &source), Some((cargo_toml.to_path_buf(), Origin::WorkingDirectory)));
    }

    #[test]
    fn absolute_paths_are_taken_as_given() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("model.urdf");
        assert_eq!(find_data_file_in(&file, None, dir.path()), None);
        std::fs::write(&file, "").unwrap();
        assert_eq!(find_data_file_in(&file, None, Path::new("/nonexistent")), Some((file.clone(), Origin::Absolute)));
    }
}
