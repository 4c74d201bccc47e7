//! Node parameters: YAML files (optional — the config struct's `Default` are the embedded defaults)
//! plus `--param dotted.key=value` overrides, deserialised into the node's serde config struct.
//! Config structs use `#[serde(default, deny_unknown_fields)]`, so a misspelt key in the file or an
//! override is rejected with its name instead of being silently ignored.
//!
//! A file is either plain (the config's sections at the top level) or in the ROS 2 parameter file
//! format, recognised by its `ros__parameters` keys:
//!
//! ```yaml
//! /**/patch_mapper:          # or `patch_mapper:`, `/robot1/patch_mapper:`, `/**:`
//!   ros__parameters:
//!     ros:
//!       status_period_s: 1.0
//!     mapper.fit.max_iterations: 10   # dotted keys and nested sections both work
//! ```
//!
//! A block applies to a node when its key, with a leading `/` added if missing, matches the node's
//! fully qualified name token by token, `*` matching one token and `**` any number (rcl's rules);
//! matching blocks apply in file order, later ones over earlier ones. Without a node name (offline
//! tools) every block of the file applies. `use_sim_time` is taken out of the parameters (it is a
//! ROS parameter of every node, not a config key).

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
    #[error("ROS 2 parameter file {path}: `{key}` must hold a `ros__parameters` mapping")]
    BadRosBlock { path: PathBuf, key: String },
    #[error("use_sim_time must be true or false, got {value}")]
    BadUseSimTime { value: String },
}

/// A node's configuration and the ROS-level `use_sim_time` parameter.
#[derive(Debug, Clone, PartialEq)]
pub struct NodeConfig<T> {
    pub config: T,
    pub use_sim_time: bool,
}

/// Load `T` for the node `node_fqn` (`/ns/name`; `None`: every block of a ROS 2 file) from `files`
/// (plain or ROS 2 format, in order, later ones over earlier ones) and `overrides` (`a.b=value` or
/// `a.b:=value`, applied last).
pub fn load_node_config<T: DeserializeOwned>(
    node_fqn: Option<&str>,
    files: &[&Path],
    overrides: &[String],
) -> Result<NodeConfig<T>, ParamError> {
    let mut root = Mapping::new();
    for path in files {
        let layer = read_layer(path, node_fqn)?;
        merge(&mut root, layer);
    }
    let names: Vec<String> = files.iter().map(|p| p.display().to_string()).collect();
    let origin = match names.is_empty() {
        false => format!("{} with {} override(s)", names.join(", "), overrides.len()),
        true => format!("embedded defaults with {} override(s)", overrides.len()),
    };
    finish(root, overrides, origin)
}

/// [`load_config`] of a file's text already read (`path` names it in errors): the same parsing (plain
/// or ROS 2 format, every block applying), overrides and checks.
pub fn load_config_from_str<T: DeserializeOwned>(text: &str, path: &Path, overrides: &[String]) -> Result<T, ParamError> {
    let root = layer_of(mapping_from_text(text, path)?, path, None)?;
    Ok(finish(root, overrides, format!("{} with {} override(s)", path.display(), overrides.len()))?.config)
}

/// Apply `overrides` to the merged files' `root`, take `use_sim_time` out and deserialize `T`.
fn finish<T: DeserializeOwned>(mut root: Mapping, overrides: &[String], origin: String) -> Result<NodeConfig<T>, ParamError> {
    for text in overrides {
        apply_override(&mut root, text)?;
    }
    let use_sim_time = match root.remove("use_sim_time") {
        None | Some(Value::Null) => false,
        Some(Value::Bool(b)) => b,
        Some(other) => {
            return Err(ParamError::BadUseSimTime { value: serde_yaml_ng::to_string(&other).unwrap_or_default().trim().to_string() })
        }
    };
    // Through text so the deserializer's errors carry the dotted path of the offending key.
    let merged =
        serde_yaml_ng::to_string(&Value::Mapping(root)).map_err(|source| ParamError::Invalid { origin: origin.clone(), source })?;
    let config = serde_yaml_ng::from_str(&merged).map_err(|source| ParamError::Invalid { origin, source })?;
    Ok(NodeConfig { config, use_sim_time })
}

/// Whether a ROS 2 parameter file's node key (`patch_mapper`, `/robot1/patch_mapper`, `/**`,
/// `/*/patch_mapper`, `/**/patch_mapper`) applies to the node `node_fqn`.
pub fn node_key_matches(key: &str, node_fqn: &str) -> bool {
    fn tokens(s: &str) -> Vec<&str> {
        s.split('/').filter(|t| !t.is_empty()).collect()
    }
    fn matches(pattern: &[&str], name: &[&str]) -> bool {
        match pattern.split_first() {
            None => name.is_empty(),
            Some((&"**", rest)) => (0..=name.len()).any(|skip| matches(rest, &name[skip..])),
            Some((token, rest)) => {
                name.split_first().is_some_and(|(first, name_rest)| (*token == "*" || token == first) && matches(rest, name_rest))
            }
        }
    }
    matches(&tokens(key), &tokens(node_fqn))
}

/// Whether a YAML file is in the ROS 2 format (some top-level entry holds `ros__parameters`).
fn is_ros_format(root: &Mapping) -> bool {
    root.values().any(|v| v.as_mapping().is_some_and(|m| m.contains_key("ros__parameters")))
}

/// The parameters `path` holds for the node (`None`: every block).
fn read_layer(path: &Path, node_fqn: Option<&str>) -> Result<Mapping, ParamError> {
    layer_of(read_mapping(path)?, path, node_fqn)
}

/// The parameters a file's top-level mapping `root` holds for the node (`None`: every block).
fn layer_of(root: Mapping, path: &Path, node_fqn: Option<&str>) -> Result<Mapping, ParamError> {
    if !is_ros_format(&root) {
        return Ok(root);
    }
    let mut layer = Mapping::new();
    for (key, block) in root {
        let key_text =
            key.as_str().map(str::to_string).unwrap_or_else(|| serde_yaml_ng::to_string(&key).unwrap_or_default().trim().to_string());
        let bad = || ParamError::BadRosBlock { path: path.to_path_buf(), key: key_text.clone() };
        let params = match block.as_mapping().and_then(|m| m.get("ros__parameters")) {
            Some(Value::Mapping(params)) => params.clone(),
            Some(Value::Null) => Mapping::new(),
            _ => return Err(bad()),
        };
        if block.as_mapping().is_some_and(|m| m.len() > 1) {
            return Err(bad());
        }
        if node_fqn.is_none_or(|fqn| node_key_matches(&key_text, fqn)) {
            merge(&mut layer, expand_dotted(params));
        }
    }
    Ok(layer)
}

/// `a.b.c: v` as `a: {b: {c: v}}`, recursively.
fn expand_dotted(mapping: Mapping) -> Mapping {
    let mut out = Mapping::new();
    for (key, value) in mapping {
        let value = match value {
            Value::Mapping(m) => Value::Mapping(expand_dotted(m)),
            other => other,
        };
        let Some(text) = key.as_str().filter(|k| k.contains('.')).map(str::to_string) else {
            merge(&mut out, Mapping::from_iter([(key, value)]));
            continue;
        };
        let mut nested = value;
        for part in text.rsplit('.') {
            nested = Value::Mapping(Mapping::from_iter([(Value::String(part.to_string()), nested)]));
        }
        if let Value::Mapping(m) = nested {
            merge(&mut out, m);
        }
    }
    out
}

/// Lay `over` on `base`: sections merge key by key, values replace.
fn merge(base: &mut Mapping, over: Mapping) {
    for (key, value) in over {
        match (base.get_mut(&key), value) {
            (Some(Value::Mapping(slot)), Value::Mapping(section)) => merge(slot, section),
            (_, value) => {
                base.insert(key, value);
            }
        }
    }
}

/// Load `T` from `path` (or from nothing: `T`'s defaults) and apply `overrides` (`a.b=value`, also
/// accepting the ROS-style `a.b:=value`).
/// A ROS 2 format file contributes every one of its blocks (see [`load_node_config`] for one node's).
pub fn load_config<T: DeserializeOwned>(path: Option<&Path>, overrides: &[String]) -> Result<T, ParamError> {
    let files: Vec<&Path> = path.into_iter().collect();
    Ok(load_node_config(None, &files, overrides)?.config)
}

fn read_mapping(path: &Path) -> Result<Mapping, ParamError> {
    let text = std::fs::read_to_string(path).map_err(|source| ParamError::Read { path: path.to_path_buf(), source })?;
    mapping_from_text(&text, path)
}

fn mapping_from_text(text: &str, path: &Path) -> Result<Mapping, ParamError> {
    let value: Value = serde_yaml_ng::from_str(text).map_err(|source| ParamError::Yaml { path: path.to_path_buf(), source })?;
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
    fn ros_format_blocks_apply_by_rcl_node_name_rules() {
        let f = file(
            "/**:\n  ros__parameters:\n    enabled: true\n    use_sim_time: true\n\
             patch_mapper:\n  ros__parameters:\n    inner.rate_hz: 5.0\n\
             /robot1/patch_mapper:\n  ros__parameters:\n    inner:\n      name: r1\n\
             /**/patch_mapper:\n  ros__parameters:\n    inner.name: any\n",
        );
        let root: NodeConfig<Config> = load_node_config(Some("/patch_mapper"), &[f.path()], &[]).unwrap();
        assert_eq!(root.config, Config { inner: Inner { rate_hz: 5.0, name: "any".into() }, enabled: true });
        assert!(root.use_sim_time);
        let r1: NodeConfig<Config> = load_node_config(Some("/robot1/patch_mapper"), &[f.path()], &["inner.name:=cli".into()]).unwrap();
        assert_eq!(
            r1.config,
            Config { inner: Inner { rate_hz: 30.0, name: "cli".into() }, enabled: true },
            "`patch_mapper:` is /patch_mapper"
        );
        let other: NodeConfig<Config> = load_node_config(Some("/robot1/other"), &[f.path()], &[]).unwrap();
        assert_eq!(other.config, Config { enabled: true, ..Config::default() });
        // Offline (no node): every block, in order.
        let any: Config = load_config(Some(f.path()), &[]).unwrap();
        assert_eq!(any.inner.name, "any");
    }

    #[test]
    fn node_keys_match_token_by_token() {
        assert!(node_key_matches("/**", "/a/b/n"));
        assert!(node_key_matches("n", "/n"));
        assert!(!node_key_matches("n", "/a/n"));
        assert!(node_key_matches("/*/n", "/a/n"));
        assert!(!node_key_matches("/*/n", "/n"));
        assert!(node_key_matches("/**/n", "/n"));
        assert!(node_key_matches("/**/n", "/a/b/n"));
        assert!(!node_key_matches("/**/n", "/a/b/m"));
        assert!(node_key_matches("/a/*", "/a/m"));
    }

    #[test]
    fn later_files_lay_over_earlier_ones_and_bad_blocks_are_named() {
        let plain = file("inner:\n  rate_hz: 10\n  name: plain\n");
        let ros = file("/**:\n  ros__parameters:\n    inner.rate_hz: 20.0\n");
        let c: NodeConfig<Config> = load_node_config(Some("/n"), &[plain.path(), ros.path()], &[]).unwrap();
        assert_eq!(c.config.inner, Inner { rate_hz: 20.0, name: "plain".into() });
        let bad = file("n:\n  ros__parameters: {}\n  extra: 1\nm:\n  ros__parameters:\n    enabled: true\n");
        assert!(matches!(load_node_config::<Config>(Some("/n"), &[bad.path()], &[]), Err(ParamError::BadRosBlock { .. })));
        let sim = file("/**:\n  ros__parameters:\n    use_sim_time: 1\n");
        assert!(matches!(load_node_config::<Config>(Some("/n"), &[sim.path()], &[]), Err(ParamError::BadUseSimTime { .. })));
        let unknown = file("n:\n  ros__parameters:\n    inner.rate_hx: 1.0\n");
        let err = load_node_config::<Config>(Some("/n"), &[unknown.path()], &[]).unwrap_err().to_string();
        assert!(err.contains("rate_hx"), "{err}");
    }

    #[test]
    fn empty_file_means_defaults() {
        let f = file("# nothing\n");
        let c: Config = load_config(Some(f.path()), &[]).unwrap();
        assert_eq!(c, Config::default());
    }
}
