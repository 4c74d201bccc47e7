//! The trained motion library (J 6.3 "Foot Placement Training"): named entries pairing a patch
//! relative to the robot with a keyframe motion, stored in one human-readable YAML file with a schema
//! version. Saves are atomic (temp file, fsync, rename, directory fsync), so a crash at any moment
//! leaves either the old or the new file. A malformed file yields an error naming the entry and field;
//! [`MotionLibrary::load_or_empty`] then starts empty and moves the bad file aside on the first save.

use std::io::Write;
use std::path::{Path, PathBuf};

use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};
use serde_yaml_ng::{Mapping, Value};

use nalgebra::{Vector2, Vector3};
use patchwalk_spl::patch::{BoundaryType, Patch, SurfaceType};

/// Current schema version of the library file.
pub const SCHEMA_VERSION: u32 = 1;

mod name;
pub use name::{validate_name, NameError, MAX_NAME_BYTES};

/// One keyframe: joint positions (rad, library joint order), the time to move there from the previous
/// keyframe, and a pause after arriving.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Keyframe {
    pub positions: Vec<f64>,
    /// Move duration (s).
    pub move_s: f64,
    /// Pause after the move (s).
    pub pause_s: f64,
}

/// One library entry: the trained patch (pose in `base_link`) and its motion.
#[derive(Debug, Clone, PartialEq)]
pub struct Motion {
    pub name: String,
    pub patch: Patch,
    pub keyframes: Vec<Keyframe>,
}

/// The whole file as read (its schema version checked).
struct ParsedLibrary {
    joints: Vec<String>,
    motions: Vec<Motion>,
}

/// The whole file as written.
#[derive(Serialize)]
struct LibraryFile<'a> {
    schema_version: u32,
    joints: &'a [String],
    motions: Vec<MotionRecord<'a>>,
}

/// A motion as written: the patch by its minimal parameters (J Table 1: surface and boundary type,
/// boundary `d`, curvatures `k`, exponential-map rotation `r`, centre `c`), which a person can read
/// and edit; the covariance of a training target is not stored.
#[derive(Serialize)]
struct MotionRecord<'a> {
    name: &'a str,
    patch: PatchRecord,
    keyframes: &'a [Keyframe],
}

#[derive(Serialize)]
struct PatchRecord {
    surface: SurfaceType,
    boundary: BoundaryType,
    d: Vec<f64>,
    k: Vec<f64>,
    r: [f64; 3],
    c: [f64; 3],
}

impl<'a> MotionRecord<'a> {
    fn new(motion: &'a Motion) -> Self {
        let p = &motion.patch;
        let patch = PatchRecord {
            surface: p.surface,
            boundary: p.boundary,
            d: p.boundary_params.clone(),
            k: p.curvature_params(),
            r: p.rotation.into(),
            c: p.center.into(),
        };
        Self { name: &motion.name, patch, keyframes: &motion.keyframes }
    }
}

/// The patch of the file's minimal parameters, validated by the Surface Patch Library (one of the 10
/// types, parameter counts, finiteness); `k` as in [`Patch::curvature_params`].
fn patch_from_record(
    surface: SurfaceType,
    boundary: BoundaryType,
    d: Vec<f64>,
    k: &[f64],
    r: [f64; 3],
    c: [f64; 3],
) -> Result<Patch, (String, String)> {
    let curvatures = match (surface.num_curvatures(), k) {
        (0, []) => Vector2::zeros(),
        (1, [kappa]) => Vector2::new(*kappa, *kappa),
        (2, [kx, ky]) => Vector2::new(*kx, *ky),
        (expected, got) => return Err(("k".into(), format!("{surface:?} has {expected} curvatures, got {}", got.len()))),
    };
    let field = |e: &patchwalk_spl::patch::PatchError| match e {
        patchwalk_spl::patch::PatchError::WrongLength { .. } => "d",
        patchwalk_spl::patch::PatchError::InvalidCombination { .. } => "boundary",
        patchwalk_spl::patch::PatchError::InvalidParameter(_) => "values",
    };
    Patch::new(surface, boundary, d, curvatures, Vector3::from(r), Vector3::from(c)).map_err(|e| (field(&e).to_string(), e.to_string()))
}

/// A snapshot of the library to write, made by [`MotionLibrary::save_job`].
#[derive(Debug, Clone)]
pub struct SaveJob {
    path: PathBuf,
    text: String,
    move_corrupt_aside: bool,
}

impl SaveJob {
    /// Move a corrupt file aside (once, to the first free `<path>.corrupt`, `<path>.corrupt.1`, …, so
    /// an earlier copy is never overwritten), then write atomically.
    pub fn run(&self) -> Result<(), LibraryError> {
        let io = |source| LibraryError::Io { path: self.path.clone(), source };
        if self.move_corrupt_aside && self.path.exists() {
            std::fs::rename(&self.path, free_corrupt_path(&self.path).map_err(io)?).map_err(io)?;
        }
        write_atomically(&self.path, self.text.as_bytes()).map_err(io)
    }
}

/// The most copies of corrupt files kept beside the library.
const MAX_CORRUPT_COPIES: usize = 1000;

/// The first of `<path>.corrupt`, `<path>.corrupt.1`, … that does not exist.
fn free_corrupt_path(path: &Path) -> std::io::Result<PathBuf> {
    for n in 0..MAX_CORRUPT_COPIES {
        let mut aside = path.as_os_str().to_os_string();
        aside.push(if n == 0 { ".corrupt".to_string() } else { format!(".corrupt.{n}") });
        let aside = PathBuf::from(aside);
        match std::fs::symlink_metadata(&aside) {
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(aside),
            Err(e) => return Err(e),
            Ok(_) => {}
        }
    }
    Err(std::io::Error::other(format!("{MAX_CORRUPT_COPIES} corrupt copies are already kept beside the library; remove some")))
}

/// The temp file name [`write_atomically`] uses for `file_name` in process `pid`.
fn temp_file_name(file_name: &std::ffi::OsStr, pid: u32) -> std::ffi::OsString {
    let mut temp_name = std::ffi::OsString::from(".");
    temp_name.push(file_name);
    temp_name.push(format!(".tmp-{pid}"));
    temp_name
}

/// Removes the temp files a crashed save left beside `path`: exactly `.<file name>.tmp-<pid>` for a
/// `pid` that is this process or (where `/proc` lists processes) no running process, so a save in
/// progress elsewhere is left alone. Returns the files removed.
pub fn remove_stale_temp_files(path: &Path) -> Result<Vec<PathBuf>, LibraryError> {
    let io = |source| LibraryError::Io { path: path.to_path_buf(), source };
    // Library paths that are not UTF-8 are not cleaned (nothing else is touched either).
    let Some(file_name) = path.file_name().and_then(|n| n.to_str()) else { return Ok(Vec::new()) };
    let prefix = format!(".{file_name}.tmp-");
    let dir = directory_of(path);
    let entries = match std::fs::read_dir(&dir) {
        Ok(entries) => entries,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(e) => return Err(io(e)),
    };
    let proc = Path::new("/proc");
    let mut removed = Vec::new();
    for entry in entries {
        let entry = entry.map_err(io)?;
        let name = entry.file_name();
        let Some(digits) = name.to_str().and_then(|n| n.strip_prefix(prefix.as_str())) else { continue };
        if !digits.bytes().all(|b| b.is_ascii_digit()) {
            continue;
        }
        let Ok(pid) = digits.parse::<u32>() else { continue };
        let running_elsewhere = pid != std::process::id() && proc.is_dir() && proc.join(pid.to_string()).exists();
        if running_elsewhere || !entry.file_type().map_err(io)?.is_file() {
            continue;
        }
        std::fs::remove_file(entry.path()).map_err(io)?;
        removed.push(entry.path());
    }
    Ok(removed)
}

fn directory_of(path: &Path) -> PathBuf {
    match path.parent() {
        Some(dir) if !dir.as_os_str().is_empty() => dir.to_path_buf(),
        _ => PathBuf::from("."),
    }
}

/// Library errors; parse errors name the entry and the field.
#[derive(Debug, thiserror::Error)]
pub enum LibraryError {
    #[error("motion library {path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("motion library {path}: {location}: {message}")]
    Malformed { path: PathBuf, location: String, message: String },
    #[error("motion {0:?} already exists")]
    Duplicate(String),
    #[error("no motion named {0:?}")]
    NotFound(String),
    #[error("invalid motion {name:?}: {message}")]
    Invalid { name: String, message: String },
    #[error(transparent)]
    InvalidName(#[from] NameError),
    #[error("cannot serialise motion library: {0}")]
    Serialize(String),
}

/// The in-memory library bound to its file.
#[derive(Debug, Clone)]
pub struct MotionLibrary {
    path: PathBuf,
    joints: Vec<String>,
    motions: Vec<Motion>,
    /// Set when the file on disk could not be parsed: it is moved aside before the next save.
    corrupt_on_disk: bool,
}

impl MotionLibrary {
    /// An empty library that will be saved at `path` for the given joint order.
    pub fn new(path: &Path, joints: Vec<String>) -> Self {
        Self { path: path.to_path_buf(), joints, motions: Vec::new(), corrupt_on_disk: false }
    }

    /// Load `path`; a missing file is an empty library. The file's joint order must equal `joints`.
    /// A UTF-8 byte order mark at the start (some editors write one) is skipped.
    pub fn load(path: &Path, joints: &[String]) -> Result<Self, LibraryError> {
        let text = match std::fs::read_to_string(path) {
            Ok(text) => text,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Self::new(path, joints.to_vec())),
            Err(source) => return Err(LibraryError::Io { path: path.to_path_buf(), source }),
        };
        Self::from_text(path, &text, joints)
    }

    /// [`MotionLibrary::load`] of a file's text already read (`path` is where it lives): the same
    /// parsing and validation, a leading byte order mark skipped.
    pub fn from_text(path: &Path, text: &str, joints: &[String]) -> Result<Self, LibraryError> {
        let text = text.strip_prefix('\u{FEFF}').unwrap_or(text);
        let file = parse_library(text, joints).map_err(|(location, message)| LibraryError::Malformed {
            path: path.to_path_buf(),
            location,
            message,
        })?;
        Ok(Self { path: path.to_path_buf(), joints: file.joints, motions: file.motions, corrupt_on_disk: false })
    }

    /// Load, or on a malformed/unreadable file start empty (the node must still start) and keep the
    /// file untouched until the next save moves it to the first free `<path>.corrupt`, `<path>.corrupt.1`, ….
    /// Returns the error for reporting.
    pub fn load_or_empty(path: &Path, joints: &[String]) -> (Self, Option<LibraryError>) {
        match Self::load(path, joints) {
            Ok(library) => (library, None),
            Err(err) => {
                let mut library = Self::new(path, joints.to_vec());
                library.corrupt_on_disk = true;
                (library, Some(err))
            }
        }
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    pub fn joints(&self) -> &[String] {
        &self.joints
    }

    pub fn motions(&self) -> &[Motion] {
        &self.motions
    }

    pub fn get(&self, name: &str) -> Option<&Motion> {
        self.motions.iter().find(|m| m.name == name)
    }

    pub fn names(&self) -> Vec<String> {
        self.motions.iter().map(|m| m.name.clone()).collect()
    }

    /// Add a motion (validated); names are unique and follow [`validate_name`].
    pub fn insert(&mut self, motion: Motion) -> Result<(), LibraryError> {
        validate_name(&motion.name)?;
        if self.get(&motion.name).is_some() {
            return Err(LibraryError::Duplicate(motion.name));
        }
        validate_motion(&motion, self.joints.len())
            .map_err(|(field, message)| LibraryError::Invalid { name: motion.name.clone(), message: format!("{field}: {message}") })?;
        self.motions.push(motion);
        Ok(())
    }

    /// Remove a motion by name.
    pub fn remove(&mut self, name: &str) -> Result<Motion, LibraryError> {
        validate_name(name)?;
        let index = self.motions.iter().position(|m| m.name == name).ok_or_else(|| LibraryError::NotFound(name.to_string()))?;
        Ok(self.motions.remove(index))
    }

    /// Serialise to YAML text.
    pub fn to_yaml(&self) -> Result<String, LibraryError> {
        let file = LibraryFile {
            schema_version: SCHEMA_VERSION,
            joints: &self.joints,
            motions: self.motions.iter().map(MotionRecord::new).collect(),
        };
        serde_yaml_ng::to_string(&file).map_err(|e| LibraryError::Serialize(e.to_string()))
    }

    /// Save atomically: write `<dir>/.<name>.tmp-<pid>`, fsync it, rename over the target, fsync the
    /// directory. A corrupt file found at load time is first renamed to the first free `<path>.corrupt[.N]`.
    pub fn save(&mut self) -> Result<(), LibraryError> {
        self.save_job()?.run()?;
        self.mark_saved();
        Ok(())
    }

    /// [`MotionLibrary::save`] in parts: the text to write now, the writing on any thread, then
    /// [`MotionLibrary::mark_saved`].
    pub fn save_job(&self) -> Result<SaveJob, LibraryError> {
        Ok(SaveJob { path: self.path.clone(), text: self.to_yaml()?, move_corrupt_aside: self.corrupt_on_disk })
    }

    /// The file on disk is this library now (a corrupt one has been moved aside).
    pub fn mark_saved(&mut self) {
        self.corrupt_on_disk = false;
    }
}

/// Atomic replace of `path` with `bytes` (temp + fsync + rename + directory fsync).
pub fn write_atomically(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    let dir = directory_of(path);
    let file_name =
        path.file_name().ok_or_else(|| std::io::Error::new(std::io::ErrorKind::InvalidInput, "library path has no file name"))?;
    let temp_path = dir.join(temp_file_name(file_name, std::process::id()));
    let result = (|| {
        let mut file = std::fs::File::create(&temp_path)?;
        file.write_all(bytes)?;
        file.sync_all()?;
        drop(file);
        std::fs::rename(&temp_path, path)?;
        std::fs::File::open(&dir)?.sync_all()
    })();
    if result.is_err() {
        // Best effort: never leave a stray temp file behind; the target is untouched.
        let _ = std::fs::remove_file(&temp_path);
    }
    result
}

type Located = (String, String);

/// Parse the file with errors located as `motions[i] (name "x").field`.
fn parse_library(text: &str, expected_joints: &[String]) -> Result<ParsedLibrary, Located> {
    let root: Value = serde_yaml_ng::from_str(text).map_err(|e| ("file".to_string(), e.to_string()))?;
    let root = root.as_mapping().ok_or_else(|| ("file".to_string(), "top level must be a mapping".to_string()))?;
    reject_unknown(root, &["schema_version", "joints", "motions"], "file")?;
    let schema_version: u32 = field(root, "schema_version", "file")?;
    if schema_version != SCHEMA_VERSION {
        return Err(("schema_version".into(), format!("unsupported version {schema_version} (this build reads {SCHEMA_VERSION})")));
    }
    let joints: Vec<String> = field(root, "joints", "file")?;
    if joints != expected_joints {
        return Err(("joints".into(), format!("file joint order {joints:?} differs from the configured {expected_joints:?}")));
    }
    let entries =
        root.get("motions").and_then(Value::as_sequence).ok_or_else(|| ("motions".to_string(), "missing or not a list".to_string()))?;
    let mut motions: Vec<Motion> = Vec::with_capacity(entries.len());
    for (i, entry) in entries.iter().enumerate() {
        let motion = parse_motion(entry, i, joints.len())?;
        if motions.iter().any(|m| m.name == motion.name) {
            return Err((format!("motions[{i}] (name {:?}).name", motion.name), "duplicate name".into()));
        }
        motions.push(motion);
    }
    Ok(ParsedLibrary { joints, motions })
}

fn parse_motion(entry: &Value, index: usize, joint_count: usize) -> Result<Motion, Located> {
    let mut location = format!("motions[{index}]");
    let map = entry.as_mapping().ok_or_else(|| (location.clone(), "entry must be a mapping".to_string()))?;
    reject_unknown(map, &["name", "patch", "keyframes"], &location)?;
    let name: String = field(map, "name", &location)?;
    location = format!("motions[{index}] (name {name:?})");
    let patch_map = map
        .get("patch")
        .and_then(Value::as_mapping)
        .ok_or_else(|| (format!("{location}.patch"), "missing or not a mapping".to_string()))?;
    let patch_location = format!("{location}.patch");
    reject_unknown(patch_map, &["surface", "boundary", "d", "k", "r", "c"], &patch_location)?;
    let k: Vec<f64> = field(patch_map, "k", &patch_location)?;
    let patch = patch_from_record(
        field(patch_map, "surface", &patch_location)?,
        field(patch_map, "boundary", &patch_location)?,
        field(patch_map, "d", &patch_location)?,
        &k,
        field(patch_map, "r", &patch_location)?,
        field(patch_map, "c", &patch_location)?,
    )
    .map_err(|(field, message)| (format!("{patch_location}.{field}"), message))?;
    let frames = map
        .get("keyframes")
        .and_then(Value::as_sequence)
        .ok_or_else(|| (format!("{location}.keyframes"), "missing or not a list".to_string()))?;
    let mut keyframes = Vec::with_capacity(frames.len());
    for (j, frame) in frames.iter().enumerate() {
        let frame_location = format!("{location}.keyframes[{j}]");
        let frame_map = frame.as_mapping().ok_or_else(|| (frame_location.clone(), "keyframe must be a mapping".to_string()))?;
        reject_unknown(frame_map, &["positions", "move_s", "pause_s"], &frame_location)?;
        keyframes.push(Keyframe {
            positions: field(frame_map, "positions", &frame_location)?,
            move_s: field(frame_map, "move_s", &frame_location)?,
            pause_s: field(frame_map, "pause_s", &frame_location)?,
        });
    }
    let motion = Motion { name, patch, keyframes };
    validate_motion(&motion, joint_count).map_err(|(field, message)| (format!("{location}.{field}"), message))?;
    Ok(motion)
}

/// Check patch parameters, keyframe sizes, finiteness and durations; returns (field, message).
fn validate_motion(motion: &Motion, joint_count: usize) -> Result<(), (String, String)> {
    if let Err(e) = validate_name(&motion.name) {
        return Err(("name".into(), e.to_string()));
    }
    if motion.keyframes.is_empty() {
        return Err(("keyframes".into(), "at least one keyframe is required".into()));
    }
    for (j, frame) in motion.keyframes.iter().enumerate() {
        if frame.positions.len() != joint_count {
            return Err((
                format!("keyframes[{j}].positions"),
                format!("expected {joint_count} joint positions, got {}", frame.positions.len()),
            ));
        }
        if frame.positions.iter().any(|p| !p.is_finite()) {
            return Err((format!("keyframes[{j}].positions"), "values must be finite".into()));
        }
        if !(frame.move_s.is_finite() && frame.move_s >= 0.0) {
            return Err((format!("keyframes[{j}].move_s"), "must be a finite duration ≥ 0".into()));
        }
        if !(frame.pause_s.is_finite() && frame.pause_s >= 0.0) {
            return Err((format!("keyframes[{j}].pause_s"), "must be a finite duration ≥ 0".into()));
        }
    }
    Ok(())
}

fn field<T: DeserializeOwned>(map: &Mapping, key: &str, location: &str) -> Result<T, Located> {
    let value = map.get(key).ok_or_else(|| (format!("{location}.{key}"), "missing field".to_string()))?;
    serde_yaml_ng::from_value(value.clone()).map_err(|e| (format!("{location}.{key}"), e.to_string()))
}

fn reject_unknown(map: &Mapping, known: &[&str], location: &str) -> Result<(), Located> {
    for key in map.keys() {
        let name = key.as_str().unwrap_or("<non-string key>");
        if !known.contains(&name) {
            return Err((format!("{location}.{name}"), format!("unknown field (expected one of {known:?})")));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests;
