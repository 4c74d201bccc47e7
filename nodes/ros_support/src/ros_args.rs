//! The ROS 2 command line of a node (`--ros-args ... [--]`), parsed as rcl parses it, so the nodes
//! run under `ros2 run` and `ros2 launch`:
//!
//! - `-r/--remap [node:]from:=to`: a name remap; `__ns:=/robot1` (the node's namespace) and
//!   `__node:=name` (the node's name) are the special ones. A `node:` prefix limits a rule to the node
//!   of that name.
//! - `-p/--param name:=value`: a parameter (dotted config key), the value typed as YAML.
//! - `--params-file FILE`: parameters in the ROS 2 file format (see [`crate::params`]).
//! - `--log-level [logger:=]level`: `debug`, `info`, `warn`, `error` or `fatal` (mapped onto the
//!   `tracing` filter; `fatal` is `error`).
//! - `-e/--enclave NAME`: the node's DDS Security enclave (see [`crate::security`]).
//!
//! Several `--ros-args` blocks may be given; a block ends at `--` or at the end of the command line.
//! Everything outside the blocks is left for the node's own options. An unknown flag inside a block
//! is an error naming it.

use std::ffi::OsString;
use std::path::PathBuf;

use serde_yaml_ng::Value;

/// What is wrong with the `--ros-args` of a command line.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum RosArgsError {
    #[error("--ros-args: unknown flag {flag:?} (known: -r/--remap, -p/--param, --params-file, --log-level, -e/--enclave)")]
    UnknownFlag { flag: String },
    #[error("--ros-args: {flag} needs a value")]
    MissingValue { flag: String },
    #[error("--ros-args: argument {arg:?} is not valid UTF-8")]
    NotUtf8 { arg: String },
    #[error("--ros-args: remap {text:?} is not of the form `[node:]from:=to`")]
    BadRemap { text: String },
    #[error("--ros-args: remap {text:?}: {reason}")]
    BadRemapName { text: String, reason: String },
    #[error("--ros-args: parameter {text:?} is not of the form `name:=value`")]
    BadParam { text: String },
    #[error("--ros-args: parameter {text:?}: the value is not valid YAML: {reason}")]
    BadParamValue { text: String, reason: String },
    #[error("--ros-args: log level {text:?} is not one of debug, info, warn, error, fatal (optionally `logger:=level`)")]
    BadLogLevel { text: String },
}

/// One `-r [node:]from:=to` rule.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Remap {
    /// The node the rule is limited to (`node:from:=to`), else every node of the process.
    pub node: Option<String>,
    pub from: String,
    pub to: String,
}

/// One `-p name:=value`.
#[derive(Debug, Clone, PartialEq)]
pub struct ParamArg {
    pub name: String,
    pub value: Value,
}

impl ParamArg {
    /// As the `dotted.key=value` override text of [`crate::params::load_config`].
    pub fn as_override(&self) -> String {
        let value = serde_yaml_ng::to_string(&self.value).unwrap_or_default();
        format!("{}:={}", self.name, value.trim_end())
    }
}

/// A `--log-level`, as a `tracing` filter directive.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LogLevel {
    /// The logger (`patch_mapper`, `rcl`, `a.b`), or every logger.
    pub logger: Option<String>,
    /// `tracing`'s name of the level (`debug`, `info`, `warn`, `error`).
    pub level: &'static str,
}

impl LogLevel {
    /// The `tracing_subscriber::EnvFilter` directive: `level` or `target=level` (ROS's `a.b` logger
    /// hierarchy is Rust's `a::b`).
    pub fn directive(&self) -> String {
        match &self.logger {
            None => self.level.to_string(),
            Some(logger) => format!("{}={}", logger.replace('.', "::"), self.level),
        }
    }
}

/// Everything the `--ros-args` blocks of a command line said, in order.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct RosArgs {
    pub remaps: Vec<Remap>,
    pub params: Vec<ParamArg>,
    pub params_files: Vec<PathBuf>,
    pub log_levels: Vec<LogLevel>,
    pub enclave: Option<String>,
}

impl RosArgs {
    /// The node's name: the last `__node:=` for it (unprefixed or `default_name:__node:=`), else
    /// `default_name`.
    pub fn node_name(&self, default_name: &str) -> String {
        self.special("__node", default_name).unwrap_or_else(|| default_name.to_string())
    }

    /// The node's namespace (`__ns:=`, for every node or prefixed with the node's default name),
    /// else `/`.
    pub fn namespace(&self, default_name: &str) -> String {
        self.special("__ns", default_name).unwrap_or_else(|| "/".to_string())
    }

    /// The remap rules (not `__ns`/`__node`) that apply to the node: unprefixed ones, and those
    /// whose `node:` prefix is its default name or its name after `__node`.
    pub fn remaps_for<'a>(&'a self, default_name: &'a str, node_name: &'a str) -> impl Iterator<Item = &'a Remap> + 'a {
        self.remaps
            .iter()
            .filter(|r| !r.from.starts_with("__"))
            .filter(move |r| r.node.as_deref().is_none_or(|n| n == default_name || n == node_name))
    }

    fn special(&self, key: &str, default_name: &str) -> Option<String> {
        self.remaps.iter().rfind(|r| r.from == key && r.node.as_deref().is_none_or(|n| n == default_name)).map(|r| r.to.clone())
    }
}

/// Split a process's command line into the node's own arguments (program name first, the
/// `--ros-args` blocks removed) and the parsed ROS arguments.
pub fn split(args: impl IntoIterator<Item = OsString>) -> Result<(Vec<OsString>, RosArgs), RosArgsError> {
    let mut rest = Vec::new();
    let mut ros = RosArgs::default();
    let mut args = args.into_iter();
    while let Some(arg) = args.next() {
        if arg != "--ros-args" {
            rest.push(arg);
            continue;
        }
        // Inside a block until `--` or the end; a repeated `--ros-args` just continues it.
        while let Some(arg) = args.next() {
            let flag = utf8(arg)?;
            let mut value = |flag: &str| -> Result<String, RosArgsError> {
                match args.next() {
                    Some(v) => utf8(v),
                    None => Err(RosArgsError::MissingValue { flag: flag.to_string() }),
                }
            };
            match flag.as_str() {
                "--" => break,
                "--ros-args" => {}
                "-r" | "--remap" => ros.remaps.push(parse_remap(&value(&flag)?)?),
                "-p" | "--param" => ros.params.push(parse_param(&value(&flag)?)?),
                "--params-file" => ros.params_files.push(PathBuf::from(value(&flag)?)),
                "--log-level" => ros.log_levels.push(parse_log_level(&value(&flag)?)?),
                "-e" | "--enclave" => ros.enclave = Some(value(&flag)?),
                _ => return Err(RosArgsError::UnknownFlag { flag }),
            }
        }
    }
    Ok((rest, ros))
}

fn utf8(arg: OsString) -> Result<String, RosArgsError> {
    arg.into_string().map_err(|arg| RosArgsError::NotUtf8 { arg: arg.to_string_lossy().into_owned() })
}

/// `[node:]from:=to`. The node prefix is the part before a single `:` that is not the `:=`.
pub fn parse_remap(text: &str) -> Result<Remap, RosArgsError> {
    let (left, to) = text.split_once(":=").ok_or_else(|| RosArgsError::BadRemap { text: text.to_string() })?;
    let (node, from) = match left.split_once(':') {
        Some((node, from)) => (Some(node.to_string()), from),
        None => (None, left),
    };
    if from.is_empty() || to.is_empty() || node.as_deref() == Some("") {
        return Err(RosArgsError::BadRemap { text: text.to_string() });
    }
    let bad = |reason: String| RosArgsError::BadRemapName { text: text.to_string(), reason };
    match from {
        "__ns" => {
            if !to.starts_with('/') {
                return Err(bad(format!("the namespace {to:?} must be absolute (start with `/`)")));
            }
            crate::names::check_namespace(to).map_err(bad)?;
        }
        "__node" | "__name" => crate::names::check_token(to).map_err(|reason| bad(format!("node name {to:?}: {reason}")))?,
        _ if from.starts_with("__") => return Err(bad(format!("{from:?} is not a remappable special name (`__ns`, `__node`)"))),
        _ => {
            crate::names::check_name(from).map_err(|reason| bad(format!("{from:?}: {reason}")))?;
            crate::names::check_name(to).map_err(|reason| bad(format!("{to:?}: {reason}")))?;
        }
    }
    let from = if from == "__name" { "__node" } else { from };
    Ok(Remap { node, from: from.to_string(), to: to.to_string() })
}

/// `name:=value` with the value typed as YAML (`1` integer, `1.0` double, `true`, `[1, 2]`, text).
pub fn parse_param(text: &str) -> Result<ParamArg, RosArgsError> {
    let (name, value) = text.split_once(":=").ok_or_else(|| RosArgsError::BadParam { text: text.to_string() })?;
    if name.is_empty() || name.split('.').any(|part| part.is_empty() || !part.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')) {
        return Err(RosArgsError::BadParam { text: text.to_string() });
    }
    let value =
        serde_yaml_ng::from_str(value).map_err(|e| RosArgsError::BadParamValue { text: text.to_string(), reason: e.to_string() })?;
    Ok(ParamArg { name: name.to_string(), value })
}

/// `level` or `logger:=level`, case-insensitive as in rcl.
pub fn parse_log_level(text: &str) -> Result<LogLevel, RosArgsError> {
    let (logger, level) = match text.split_once(":=") {
        Some((logger, level)) if !logger.is_empty() => (Some(logger.to_string()), level),
        Some(_) => return Err(RosArgsError::BadLogLevel { text: text.to_string() }),
        None => (None, text),
    };
    let level = match level.to_ascii_lowercase().as_str() {
        "debug" => "debug",
        "info" => "info",
        "warn" | "warning" => "warn",
        "error" | "fatal" => "error",
        _ => return Err(RosArgsError::BadLogLevel { text: text.to_string() }),
    };
    Ok(LogLevel { logger, level })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(args: &[&str]) -> Result<(Vec<String>, RosArgs), RosArgsError> {
        let (rest, ros) = split(args.iter().map(OsString::from))?;
        Ok((rest.into_iter().map(|a| a.into_string().unwrap()).collect(), ros))
    }

    #[test]
    fn blocks_are_taken_out_and_the_rest_is_left_in_order() {
        let (rest, ros) = parse(&[
            "patch_mapper",
            "run",
            "--ros-args",
            "-r",
            "__ns:=/robot1",
            "-p",
            "mapper.fit.max_iterations:=7",
            "--",
            "--dds-network",
            "all",
            "--ros-args",
            "--params-file",
            "/tmp/p.yaml",
            "--remap",
            "patch_mapper:camera/depth/image_raw:=/camera/camera/depth/image_rect_raw",
            "--log-level",
            "patch_mapper:=DEBUG",
            "--enclave",
            "/e",
        ])
        .unwrap();
        assert_eq!(rest, ["patch_mapper", "run", "--dds-network", "all"]);
        assert_eq!(ros.namespace("patch_mapper"), "/robot1");
        assert_eq!(ros.node_name("patch_mapper"), "patch_mapper");
        assert_eq!(ros.params, [ParamArg { name: "mapper.fit.max_iterations".into(), value: Value::from(7) }]);
        assert_eq!(ros.params_files, [PathBuf::from("/tmp/p.yaml")]);
        assert_eq!(ros.log_levels[0].directive(), "patch_mapper=debug");
        assert_eq!(ros.enclave.as_deref(), Some("/e"));
        let remaps: Vec<&Remap> = ros.remaps_for("patch_mapper", "patch_mapper").collect();
        assert_eq!(remaps.len(), 1);
        assert_eq!(remaps[0].from, "camera/depth/image_raw");
        assert_eq!(remaps[0].to, "/camera/camera/depth/image_rect_raw");
        assert_eq!(ros.remaps_for("step_executor", "step_executor").count(), 0, "the rule names another node");
    }

    #[test]
    fn no_block_leaves_everything() {
        let (rest, ros) = parse(&["step_executor", "run", "--param", "ros.status_rate_hz=20"]).unwrap();
        assert_eq!(rest, ["step_executor", "run", "--param", "ros.status_rate_hz=20"]);
        assert_eq!(ros, RosArgs::default());
        assert_eq!(ros.namespace("step_executor"), "/");
    }

    #[test]
    fn node_name_and_namespace_remaps_last_one_wins_and_prefix_must_match() {
        let (_, ros) = parse(&["x", "--ros-args", "-r", "__node:=a", "-r", "__node:=b", "-r", "other:__ns:=/o"]).unwrap();
        assert_eq!(ros.node_name("terrain_sim"), "b");
        assert_eq!(ros.namespace("terrain_sim"), "/", "the namespace rule is for `other`");
        assert_eq!(ros.namespace("other"), "/o");
    }

    #[test]
    fn parameter_values_are_typed_as_yaml() {
        assert_eq!(parse_param("a.b:=1.5").unwrap().value, Value::from(1.5));
        assert_eq!(parse_param("a:=true").unwrap().value, Value::Bool(true));
        assert_eq!(parse_param("a:=/dev/ttyUSB0").unwrap().value, Value::from("/dev/ttyUSB0"));
        assert_eq!(parse_param("a:=[1, 2]").unwrap().value, serde_yaml_ng::from_str::<Value>("[1, 2]").unwrap());
        assert_eq!(parse_param("a.b:=2").unwrap().as_override(), "a.b:=2");
        assert!(matches!(parse_param("a=1"), Err(RosArgsError::BadParam { .. })));
        assert!(matches!(parse_param("a..b:=1"), Err(RosArgsError::BadParam { .. })));
        assert!(matches!(parse_param("a:=[1"), Err(RosArgsError::BadParamValue { .. })));
    }

    #[test]
    fn bad_input_is_named() {
        assert_eq!(parse(&["x", "--ros-args", "--bogus"]).unwrap_err(), RosArgsError::UnknownFlag { flag: "--bogus".into() });
        assert_eq!(parse(&["x", "--ros-args", "-p"]).unwrap_err(), RosArgsError::MissingValue { flag: "-p".into() });
        assert!(matches!(parse(&["x", "--ros-args", "-r", "a=b"]), Err(RosArgsError::BadRemap { .. })));
        assert!(matches!(parse(&["x", "--ros-args", "-r", "__ns:=robot1"]), Err(RosArgsError::BadRemapName { .. })));
        assert!(matches!(parse(&["x", "--ros-args", "-r", "__node:=9lives"]), Err(RosArgsError::BadRemapName { .. })));
        assert!(matches!(parse(&["x", "--ros-args", "-r", "a b:=c"]), Err(RosArgsError::BadRemapName { .. })));
        assert!(matches!(parse(&["x", "--ros-args", "--log-level", "loud"]), Err(RosArgsError::BadLogLevel { .. })));
        let err = parse(&["x", "--ros-args", "--bogus"]).unwrap_err().to_string();
        assert!(err.contains("--bogus"), "{err}");
    }

    #[test]
    fn log_levels_map_onto_tracing() {
        assert_eq!(parse_log_level("fatal").unwrap().directive(), "error");
        assert_eq!(parse_log_level("WARN").unwrap().directive(), "warn");
        assert_eq!(parse_log_level("a.b:=info").unwrap().directive(), "a::b=info");
        assert!(parse_log_level(":=info").is_err());
    }
}
