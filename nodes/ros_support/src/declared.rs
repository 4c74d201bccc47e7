//! A node's serde config as declared ROS 2 parameters: every leaf of the config, flattened to its
//! dotted key (`mapper.fit.max_iterations`) with the ROS type of its value, so the parameter list is
//! derived from the config struct and cannot drift from it.
//!
//! Types: booleans, integers, doubles and strings map onto the ROS types of the same name, flat
//! lists of one of them onto the ROS arrays; anything else (a list of sections, a matrix, an enum
//! with data, an empty list) is a string parameter holding the value as YAML text. An optional key
//! that is unset is a parameter without a value (`NOT_SET`, any type may be given).
//!
//! A set is checked the way the config file is: the new value goes into the config tree, the tree is
//! deserialised into the config struct (wrong types, out-of-range integers and unknown enum values
//! are refused there) and the node's own validation runs on the result. The reason of a refusal
//! names the key.

use std::collections::BTreeMap;
use std::marker::PhantomData;

use ros2_client::parameters::{ParameterDescriptor, ParameterType, ParameterValue};
use serde::de::DeserializeOwned;
use serde::Serialize;
use serde_yaml_ng::{Mapping, Value};

/// Why a config could not be declared as parameters.
#[derive(Debug, thiserror::Error)]
pub enum DeclareError {
    #[error("the config does not serialise to a YAML mapping: {0}")]
    NotAMapping(String),
    #[error("config key {key:?} is not a valid parameter name")]
    BadKey { key: String },
}

/// The built-in parameter of every ROS 2 node.
pub const USE_SIM_TIME: &str = "use_sim_time";

/// How a node's parameters may change: the dotted prefixes that can change while it runs (`ros`,
/// `matcher.position_tolerance_m`), those under them that still need a restart, what "applied"
/// means for this node, and the node's validation beyond the types.
pub struct ParameterSpec<T> {
    pub runtime: &'static [&'static str],
    pub restart: &'static [&'static str],
    /// Completes "changes while the node runs: applied ..." (e.g. "at the next frame").
    pub applied: &'static str,
    pub validate: fn(&T) -> Result<(), String>,
}

impl<T> ParameterSpec<T> {
    /// Whether `key` can change while the node runs.
    pub fn is_runtime(&self, key: &str) -> bool {
        let under = |prefix: &&str| key == *prefix || key.strip_prefix(*prefix).is_some_and(|rest| rest.starts_with('.'));
        self.runtime.iter().any(under) && !self.restart.iter().any(under)
    }
}

/// How a parameter's ROS value maps back onto the config tree.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Kind {
    /// The ROS type is the config value's own.
    Typed(ParameterType),
    /// A string holding YAML text.
    Yaml,
    /// An unset optional key: any type.
    Unset,
}

#[derive(Debug, Clone)]
struct Entry {
    kind: Kind,
    value: ParameterValue,
    read_only: bool,
}

/// The declared parameters of one node and its current config.
pub struct Declared<T> {
    tree: Value,
    entries: BTreeMap<String, Entry>,
    applied: &'static str,
    validate: fn(&T) -> Result<(), String>,
    _config: PhantomData<T>,
}

/// An accepted change: the node's new config and the keys that changed.
#[derive(Debug, Clone)]
pub struct Change<T> {
    pub config: T,
    pub keys: Vec<String>,
}

impl<T: Serialize + DeserializeOwned> Declared<T> {
    /// Declare every key of `config` (and `use_sim_time`).
    pub fn new(config: &T, use_sim_time: bool, spec: &ParameterSpec<T>) -> Result<Declared<T>, DeclareError> {
        let tree = serde_yaml_ng::to_value(config).map_err(|e| DeclareError::NotAMapping(e.to_string()))?;
        let Value::Mapping(root) = &tree else {
            return Err(DeclareError::NotAMapping("not a mapping".into()));
        };
        let mut leaves = Vec::new();
        flatten("", root, &mut leaves);
        let mut entries = BTreeMap::new();
        for (key, value) in leaves {
            if !key.split('.').all(|part| crate::names::check_token(part).is_ok()) {
                return Err(DeclareError::BadKey { key });
            }
            let (kind, value) = to_parameter(&value);
            entries.insert(key.clone(), Entry { kind, value, read_only: !spec.is_runtime(&key) });
        }
        let sim_time = Entry { kind: Kind::Typed(ParameterType::Bool), value: ParameterValue::Boolean(use_sim_time), read_only: true };
        entries.insert(USE_SIM_TIME.to_string(), sim_time);
        Ok(Declared { tree, entries, applied: spec.applied, validate: spec.validate, _config: PhantomData })
    }

    pub fn names(&self) -> impl Iterator<Item = &str> {
        self.entries.keys().map(String::as_str)
    }

    /// The value of `name` (`NotSet` for an unknown name, as rcl answers).
    pub fn get(&self, name: &str) -> ParameterValue {
        self.entries.get(name).map(|e| e.value.clone()).unwrap_or(ParameterValue::NotSet)
    }

    /// The descriptor `ros2 param describe` shows.
    pub fn describe(&self, name: &str) -> ParameterDescriptor {
        let Some(entry) = self.entries.get(name) else {
            return ParameterDescriptor::unknown(name);
        };
        let description = if name == USE_SIM_TIME {
            "read-only: use the simulated /clock; these nodes keep the wall clock".to_string()
        } else if entry.read_only {
            "read-only: read at start; restart the node to change it (--params-file, -p)".to_string()
        } else {
            format!("changes while the node runs: applied {}", self.applied)
        };
        let additional_constraints = match entry.kind {
            Kind::Yaml => "YAML text of the config value".to_string(),
            Kind::Unset => "optional: unset by default".to_string(),
            Kind::Typed(_) => String::new(),
        };
        ParameterDescriptor {
            name: name.to_string(),
            param_type: entry.value.to_parameter_type(),
            description,
            additional_constraints,
            read_only: entry.read_only,
            dynamic_typing: entry.kind == Kind::Unset,
            range: ros2_client::parameters::NumericRange::NotSpecified,
        }
    }

    /// Set `params` together (all or none). Refusals name the key and the reason.
    pub fn set(&mut self, params: &[(String, ParameterValue)]) -> Result<Change<T>, String> {
        let mut tree = self.tree.clone();
        let mut updated = Vec::new();
        for (name, value) in params {
            let entry = self.entries.get(name).ok_or_else(|| format!("parameter '{name}' is not declared"))?;
            if entry.read_only {
                return Err(format!("parameter '{name}' is read-only: it is read at start; restart the node to change it"));
            }
            let yaml = from_parameter(name, entry.kind, value)?;
            set_at(&mut tree, name, yaml);
            updated.push(name.clone());
        }
        let text = serde_yaml_ng::to_string(&tree).map_err(|e| format!("{}: {e}", updated.join(", ")))?;
        let config: T = serde_yaml_ng::from_str(&text).map_err(|e| format!("{}: {e}", updated.join(", ")))?;
        (self.validate)(&config).map_err(|e| format!("{}: {e}", updated.join(", ")))?;
        for (name, value) in params {
            if let Some(entry) = self.entries.get_mut(name) {
                entry.value = value.clone();
            }
        }
        self.tree = tree;
        Ok(Change { config, keys: updated })
    }

    /// `ListParameters`, with rclcpp's semantics: without `prefixes`, the names with fewer than
    /// `depth` dots (0: all); else the names equal to a prefix or under `prefix.` within `depth`
    /// further levels. Also the distinct namespaces (up to the last dot) of the names listed.
    pub fn list(&self, prefixes: &[String], depth: u64) -> (Vec<String>, Vec<String>) {
        let within = |rest: &str| depth == 0 || (rest.matches('.').count() as u64) < depth;
        let mut names = Vec::new();
        let mut namespaces: Vec<String> = Vec::new();
        for name in self.entries.keys() {
            let listed = if prefixes.is_empty() {
                within(name)
            } else {
                prefixes.iter().any(|p| name == p || name.strip_prefix(p.as_str()).and_then(|r| r.strip_prefix('.')).is_some_and(within))
            };
            if listed {
                names.push(name.clone());
                if let Some((namespace, _)) = name.rsplit_once('.') {
                    if !namespaces.iter().any(|n| n == namespace) {
                        namespaces.push(namespace.to_string());
                    }
                }
            }
        }
        (names, namespaces)
    }
}

fn flatten(prefix: &str, mapping: &Mapping, out: &mut Vec<(String, Value)>) {
    for (key, value) in mapping {
        let key = match key {
            Value::String(s) => s.clone(),
            other => serde_yaml_ng::to_string(other).unwrap_or_default().trim().to_string(),
        };
        let dotted = if prefix.is_empty() { key } else { format!("{prefix}.{key}") };
        match value {
            Value::Mapping(section) if !section.is_empty() => flatten(&dotted, section, out),
            leaf => out.push((dotted, leaf.clone())),
        }
    }
}

fn to_parameter(value: &Value) -> (Kind, ParameterValue) {
    let yaml = || (Kind::Yaml, ParameterValue::String(flow_yaml(value)));
    match value {
        Value::Null => (Kind::Unset, ParameterValue::NotSet),
        Value::Bool(b) => (Kind::Typed(ParameterType::Bool), ParameterValue::Boolean(*b)),
        Value::Number(n) if n.is_f64() => (Kind::Typed(ParameterType::Double), ParameterValue::Double(n.as_f64().unwrap_or(f64::NAN))),
        Value::Number(n) => match n.as_i64() {
            Some(i) => (Kind::Typed(ParameterType::Integer), ParameterValue::Integer(i)),
            None => yaml(),
        },
        Value::String(s) => (Kind::Typed(ParameterType::String), ParameterValue::String(s.clone())),
        Value::Sequence(items) if !items.is_empty() => {
            if let Some(v) = items.iter().map(Value::as_bool).collect::<Option<Vec<bool>>>() {
                (Kind::Typed(ParameterType::BoolArray), ParameterValue::BooleanArray(v))
            } else if let Some(v) = items.iter().map(|i| if is_float(i) { None } else { i.as_i64() }).collect::<Option<Vec<i64>>>() {
                (Kind::Typed(ParameterType::IntegerArray), ParameterValue::IntegerArray(v))
            } else if let Some(v) = items.iter().map(|i| if is_float(i) { i.as_f64() } else { None }).collect::<Option<Vec<f64>>>() {
                (Kind::Typed(ParameterType::DoubleArray), ParameterValue::DoubleArray(v))
            } else if let Some(v) = items.iter().map(|i| i.as_str().map(str::to_string)).collect::<Option<Vec<String>>>() {
                (Kind::Typed(ParameterType::StringArray), ParameterValue::StringArray(v))
            } else {
                yaml()
            }
        }
        _ => yaml(),
    }
}

/// One-line YAML (flow style) of a value: `[[1.0, 0.0], [0.0, 1.0]]`, `{joint: a, id: 1}`.
fn flow_yaml(value: &Value) -> String {
    let scalar = |v: &Value| serde_yaml_ng::to_string(v).unwrap_or_default().trim_end().to_string();
    match value {
        Value::Sequence(items) => format!("[{}]", items.iter().map(flow_yaml).collect::<Vec<_>>().join(", ")),
        Value::Mapping(m) => {
            format!("{{{}}}", m.iter().map(|(k, v)| format!("{}: {}", flow_yaml(k), flow_yaml(v))).collect::<Vec<_>>().join(", "))
        }
        Value::Tagged(t) => format!("{} {}", t.tag, flow_yaml(&t.value)),
        other => scalar(other),
    }
}

fn is_float(value: &Value) -> bool {
    matches!(value, Value::Number(n) if n.is_f64())
}

fn type_name(t: ParameterType) -> &'static str {
    match t {
        ParameterType::NotSet => "not set",
        ParameterType::Bool => "a bool",
        ParameterType::Integer => "an integer",
        ParameterType::Double => "a double",
        ParameterType::String => "a string",
        ParameterType::ByteArray => "a byte array",
        ParameterType::BoolArray => "a bool array",
        ParameterType::IntegerArray => "an integer array",
        ParameterType::DoubleArray => "a double array",
        ParameterType::StringArray => "a string array",
    }
}

/// The config value a ROS value stands for, refused when the type is not the parameter's.
fn from_parameter(name: &str, kind: Kind, value: &ParameterValue) -> Result<Value, String> {
    let given = value.to_parameter_type();
    let expected = match kind {
        Kind::Typed(t) => Some(t),
        Kind::Yaml => Some(ParameterType::String),
        Kind::Unset => None,
    };
    if let Some(expected) = expected {
        if expected != given {
            let hint =
                if (expected, given) == (ParameterType::Double, ParameterType::Integer) { " (write it with a decimal point)" } else { "" };
            return Err(format!("parameter '{name}' is {}, got {}{hint}", type_name(expected), type_name(given)));
        }
    }
    Ok(match value {
        ParameterValue::NotSet => Value::Null,
        ParameterValue::Boolean(b) => Value::Bool(*b),
        ParameterValue::Integer(i) => Value::from(*i),
        ParameterValue::Double(d) => Value::from(*d),
        ParameterValue::String(s) if kind == Kind::Yaml => {
            serde_yaml_ng::from_str(s).map_err(|e| format!("parameter '{name}': the value is not valid YAML: {e}"))?
        }
        ParameterValue::String(s) => Value::String(s.clone()),
        ParameterValue::ByteArray(v) => Value::Sequence(v.iter().map(|b| Value::from(*b)).collect()),
        ParameterValue::BooleanArray(v) => Value::Sequence(v.iter().map(|b| Value::Bool(*b)).collect()),
        ParameterValue::IntegerArray(v) => Value::Sequence(v.iter().map(|i| Value::from(*i)).collect()),
        ParameterValue::DoubleArray(v) => Value::Sequence(v.iter().map(|d| Value::from(*d)).collect()),
        ParameterValue::StringArray(v) => Value::Sequence(v.iter().map(|s| Value::String(s.clone())).collect()),
    })
}

/// Put `value` at the dotted `key` of `tree` (the sections exist: the key was flattened from it).
fn set_at(tree: &mut Value, key: &str, value: Value) {
    let mut current = tree;
    let parts: Vec<&str> = key.split('.').collect();
    let Some((last, sections)) = parts.split_last() else { return };
    for part in sections {
        let Value::Mapping(mapping) = current else { return };
        current = mapping.entry(Value::String((*part).to_string())).or_insert_with(|| Value::Mapping(Mapping::new()));
    }
    if let Value::Mapping(mapping) = current {
        mapping.insert(Value::String((*last).to_string()), value);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde::Deserialize;

    #[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
    #[serde(default, deny_unknown_fields)]
    struct Inner {
        threshold: f64,
        iterations: u8,
        topic: String,
        flags: Vec<bool>,
        matrix: [[f64; 2]; 2],
        past_s: Option<f64>,
    }
    impl Default for Inner {
        fn default() -> Self {
            Inner {
                threshold: 0.5,
                iterations: 10,
                topic: "camera/depth".into(),
                flags: vec![true, false],
                matrix: [[1.0, 0.0], [0.0, 1.0]],
                past_s: None,
            }
        }
    }
    #[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
    #[serde(default, deny_unknown_fields)]
    struct Config {
        inner: Inner,
        enabled: bool,
    }

    fn positive(c: &Config) -> Result<(), String> {
        if c.inner.threshold > 0.0 {
            Ok(())
        } else {
            Err(format!("inner.threshold = {} must be positive", c.inner.threshold))
        }
    }

    const SPEC: ParameterSpec<Config> =
        ParameterSpec { runtime: &["inner", "enabled"], restart: &["inner.topic"], applied: "at the next frame", validate: positive };

    fn declared() -> Declared<Config> {
        Declared::new(&Config::default(), false, &SPEC).unwrap()
    }

    fn set(d: &mut Declared<Config>, name: &str, value: ParameterValue) -> Result<Change<Config>, String> {
        d.set(&[(name.to_string(), value)])
    }

    #[test]
    fn every_leaf_is_declared_with_its_type() {
        let d = declared();
        let names: Vec<&str> = d.names().collect();
        assert_eq!(
            names,
            [
                "enabled",
                "inner.flags",
                "inner.iterations",
                "inner.matrix",
                "inner.past_s",
                "inner.threshold",
                "inner.topic",
                "use_sim_time"
            ]
        );
        assert_eq!(d.get("inner.threshold"), ParameterValue::Double(0.5));
        assert_eq!(d.get("inner.iterations"), ParameterValue::Integer(10));
        assert_eq!(d.get("inner.flags"), ParameterValue::BooleanArray(vec![true, false]));
        assert_eq!(d.get("inner.past_s"), ParameterValue::NotSet);
        assert_eq!(d.get("use_sim_time"), ParameterValue::Boolean(false));
        assert_eq!(d.get("inner.matrix"), ParameterValue::String("[[1.0, 0.0], [0.0, 1.0]]".into()));
        assert_eq!(d.get("nope"), ParameterValue::NotSet);
    }

    #[test]
    fn runtime_keys_change_and_restart_keys_are_read_only_with_a_description() {
        let mut d = declared();
        let change = set(&mut d, "inner.threshold", ParameterValue::Double(0.25)).unwrap();
        assert_eq!(change.config.inner.threshold, 0.25);
        assert_eq!(change.keys, ["inner.threshold"]);
        assert_eq!(d.get("inner.threshold"), ParameterValue::Double(0.25));
        let topic = d.describe("inner.topic");
        assert!(topic.read_only && topic.description.contains("restart"), "{}", topic.description);
        let threshold = d.describe("inner.threshold");
        assert!(!threshold.read_only && threshold.description.contains("at the next frame"));
        let err = set(&mut d, "inner.topic", ParameterValue::String("x".into())).unwrap_err();
        assert!(err.contains("inner.topic") && err.contains("read-only"), "{err}");
        // YAML-text values and unset optionals.
        let change = set(&mut d, "inner.matrix", ParameterValue::String("[[2.0, 0.0], [0.0, 2.0]]".into())).unwrap();
        assert_eq!(change.config.inner.matrix, [[2.0, 0.0], [0.0, 2.0]]);
        let change = set(&mut d, "inner.past_s", ParameterValue::Double(3600.0)).unwrap();
        assert_eq!(change.config.inner.past_s, Some(3600.0));
        assert_eq!(change.config.inner.threshold, 0.25, "earlier changes are kept");
    }

    #[test]
    fn bad_values_are_refused_naming_the_key_and_leave_the_config_unchanged() {
        let mut d = declared();
        let err = set(&mut d, "inner.threshold", ParameterValue::String("high".into())).unwrap_err();
        assert!(err.contains("inner.threshold") && err.contains("a double"), "{err}");
        let err = set(&mut d, "inner.threshold", ParameterValue::Integer(1)).unwrap_err();
        assert!(err.contains("decimal point"), "{err}");
        let err = set(&mut d, "inner.threshold", ParameterValue::Double(-1.0)).unwrap_err();
        assert!(err.contains("inner.threshold") && err.contains("positive"), "{err}");
        let err = set(&mut d, "inner.iterations", ParameterValue::Integer(300)).unwrap_err();
        assert!(err.contains("inner.iterations"), "{err}");
        let err = set(&mut d, "inner.matrix", ParameterValue::String("[[1.0".into())).unwrap_err();
        assert!(err.contains("YAML"), "{err}");
        let err = set(&mut d, "use_sim_time", ParameterValue::Boolean(true)).unwrap_err();
        assert!(err.contains("read-only"), "{err}");
        assert!(set(&mut d, "nope", ParameterValue::Boolean(true)).unwrap_err().contains("not declared"));
        assert_eq!(d.get("inner.threshold"), ParameterValue::Double(0.5));
        // All or nothing.
        let both = [("enabled".to_string(), ParameterValue::Boolean(true)), ("inner.threshold".to_string(), ParameterValue::Double(0.0))];
        assert!(d.set(&both).is_err());
        assert_eq!(d.get("enabled"), ParameterValue::Boolean(false));
    }

    #[test]
    fn list_follows_rclcpp() {
        let d = declared();
        let (names, prefixes) = d.list(&[], 0);
        assert_eq!(names.len(), 8);
        assert_eq!(prefixes, ["inner"]);
        let (names, _) = d.list(&[], 1);
        assert_eq!(names, ["enabled", "use_sim_time"]);
        let (names, _) = d.list(&["inner".to_string()], 1);
        assert_eq!(names.len(), 6);
    }
}
