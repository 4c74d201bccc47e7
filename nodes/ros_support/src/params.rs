//! Node parameters: a YAML file (optional — the config struct's `Default` are the embedded defaults)
//! plus `--param dotted.key=value` overrides, deserialised into the node's serde config struct.
//! Config structs use `#[serde(default, deny_unknown_fields)]`, so a misspelt key in the file or an
//! override is rejected with its name instead of being silently ignored.

use std::path::{Path, PathBuf};

use serde::de::DeserializeOwned;
use serde_yaml_ng::{Mapping, Value};

/// Errors of parameter loading; each names the file, key or override at fault.
#[derive(Debug, thiserror::Error)]
pub enum ParamError {
    #[error("cannot read parameter file {path}: {source}")]
    Read { path: PathBuf, source: std::io::Error },
    #[error("parameter file {path} is not valid YAML: {source}")]
    Yaml { path: PathBuf, source: serde_yaml_ng::Error },
    #[error("parameter file {path} must contain a mapping at the top level")]
    NotAMapping { path: PathBuf },
    #[error("parameter override {text:?} is not of the form `dotted.key=value`")]
    BadOverride { text: String },
    #[error("parameter override {text:?}: value is not valid YAML: {source}")]
    BadOverrideValue { text: String, source: serde_yaml_ng::Error },
    #[error("parameter override {text:?}: `{key}` is not a section (it holds a value)")]
    NotASection { text: String, key: String },
    #[error("invalid parameters ({origin}): {source}")]
    Invalid { origin: String, source: serde_yaml_ng::Error },
}

/// Load `T` from `path` (or from nothing: `T`'s defaults) and apply `overrides` (`a.b=value`, also
/// accepting the ROS-style `a.b:=value`).
pub fn load_config<T: DeserializeOwned>(path: Option<&Path>, overrides: &[String]) -> Result<T, ParamError> {
    let mut root = match path {
        Some(path) => read_mapping(path)?,
        None => Mapping::new(),
    };
    for text in overrides {
        apply_override(&mut root, text)?;
    }
    let origin = match path {
        Some(path) => format!("{} with {} override(s)", path.display(), overrides.len()),
        None => format!("embedded defaults with {} override(s)", overrides.len()),
    };
    // Through text so the deserializer's errors carry the dotted path of the offending key.
    let merged =
        serde_yaml_ng::to_string(&Value::Mapping(root)).map_err(|source| ParamError::Invalid { origin: origin.clone(), source })?;
    serde_yaml_ng::from_str(&merged).map_err(|source| ParamError::Invalid { origin, source })
}

fn read_mapping(path: &Path) -> Result<Mapping, ParamError> {
    let text = std::fs::read_to_string(path).map_err(|source| ParamError::Read { path: path.to_path_buf(), source })?;
    let value: Value = serde_yaml_ng::from_str(&text).map_err(|source| ParamError::Yaml { path: path.to_path_buf(), source })?;
    match value {
        Value::Mapping(mapping) => Ok(mapping),
        // An empty file (or one with only comments) means "all defaults".
        Value::Null => Ok(Mapping::new()),
        _ => Err(ParamError::NotAMapping { path: path.to_path_buf() }),
    }
}

/// Set `dotted.key` in `root` to the YAML value after `=`, creating sections on the way.
fn apply_override(root: &mut Mapping, text: &str) -> Result<(), ParamError> {
    let bad = || ParamError::BadOverride { text: text.to_string() };
    let (key, value) = text.split_once(":=").or_else(|| text.split_once('=')).ok_or_else(bad)?;
    let key = key.trim();
    if key.is_empty() || key.split('.').any(|part| part.trim().is_empty()) {
        return Err(bad());
    }
    let value: Value = serde_yaml_ng::from_str(value).map_err(|source| ParamError::BadOverrideValue { text: text.to_string(), source })?;
    let parts: Vec<&str> = key.split('.').map(str::trim).collect();
    let Some((last, sections)) = parts.split_last() else {
        return Err(bad());
    };
    let mut current = root;
    for section in sections {
        let entry = current.entry(Value::String((*section).to_string())).or_insert_with(|| Value::Mapping(Mapping::new()));
        if entry.is_null() {
            *entry = Value::Mapping(Mapping::new());
        }
        current = match entry {
            Value::Mapping(mapping) => mapping,
            _ => return Err(ParamError::NotASection { text: text.to_string(), key: (*section).to_string() }),
        };
    }
    current.insert(Value::String((*last).to_string()), value);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde::Deserialize;

    #[derive(Debug, Deserialize, PartialEq)]
    #[serde(default, deny_unknown_fields)]
    struct Inner {
        rate_hz: f64,
        name: String,
    }
    impl Default for Inner {
        fn default() -> Self {
            Inner { rate_hz: 30.0, name: "x".into() }
        }
    }

    #[derive(Debug, Deserialize, PartialEq, Default)]
    #[serde(default, deny_unknown_fields)]
    struct Config {
        inner: Inner,
        enabled: bool,
    }

    fn file(text: &str) -> tempfile::NamedTempFile {
        let mut f = tempfile::NamedTempFile::new().unwrap();
        std::io::Write::write_all(&mut f, text.as_bytes()).unwrap();
        f
    }

    #[test]
    fn no_file_gives_defaults() {
        let c: Config = load_config(None, &[]).unwrap();
        assert_eq!(c, Config::default());
    }

    #[test]
    fn file_values_and_overrides_apply_in_order() {
        let f = file("inner:\n  rate_hz: 10\nenabled: false\n");
        let c: Config = load_config(Some(f.path()), &["inner.name=abc".into(), "enabled:=true".into()]).unwrap();
        assert_eq!(c.inner.rate_hz, 10.0);
        assert_eq!(c.inner.name, "abc");
        assert!(c.enabled);
        let c: Config = load_config(Some(f.path()), &["inner.rate_hz=2.5".into()]).unwrap();
        assert_eq!(c.inner.rate_hz, 2.5);
    }

    #[test]
    fn unknown_keys_are_rejected_by_name() {
        let f = file("inner:\n  rate_hx: 10\n");
        let err = load_config::<Config>(Some(f.path()), &[]).unwrap_err().to_string();
        assert!(err.contains("rate_hx"), "{err}");
        let err = load_config::<Config>(None, &["bogus.key=1".into()]).unwrap_err().to_string();
        assert!(err.contains("bogus"), "{err}");
    }

    #[test]
    fn malformed_overrides_and_files_are_errors() {
        assert!(matches!(load_config::<Config>(None, &["novalue".into()]), Err(ParamError::BadOverride { .. })));
        assert!(matches!(load_config::<Config>(None, &["a..b=1".into()]), Err(ParamError::BadOverride { .. })));
        assert!(matches!(load_config::<Config>(None, &["enabled=1".into(), "enabled.x=2".into()]), Err(ParamError::NotASection { .. })));
        let f = file("- a\n- b\n");
        assert!(matches!(load_config::<Config>(Some(f.path()), &[]), Err(ParamError::NotAMapping { .. })));
        let f = file("inner: [\n");
        assert!(matches!(load_config::<Config>(Some(f.path()), &[]), Err(ParamError::Yaml { .. })));
        let err = load_config::<Config>(None, &["inner.rate_hz=fast".into()]).unwrap_err().to_string();
        assert!(err.contains("rate_hz"), "{err}");
    }

    #[test]
    fn empty_file_means_defaults() {
        let f = file("# nothing\n");
        let c: Config = load_config(Some(f.path()), &[]).unwrap();
        assert_eq!(c, Config::default());
    }
}
