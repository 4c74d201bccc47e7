//! Topic and service names resolved as rcl resolves them, relative to the node:
//!
//! - `/x/y` is absolute and stays as it is;
//! - `x/y` is relative to the node's namespace: `/<ns>/x/y` (`/x/y` in the root namespace);
//! - `~/x` is private to the node: `/<ns>/<node>/x` (`~` alone is the node itself);
//! - `{node}` and `{ns}` / `{namespace}` are substituted.
//!
//! Remap rules (`-r from:=to`) are expanded the same way and compared with the expanded name; the
//! first rule that matches gives the name (rcl's order). A name's tokens are letters, digits and
//! `_`, not starting with a digit.

use crate::node::NodeError;
use crate::ros_args::RosArgs;

/// `token` is a valid name token (node name, namespace or name part).
pub fn check_token(token: &str) -> Result<(), String> {
    match token.chars().next() {
        None => Err("empty name part".to_string()),
        Some(c) if c.is_ascii_digit() => Err(format!("{token:?} starts with a digit")),
        Some(_) => match token.chars().find(|c| !(c.is_ascii_alphanumeric() || *c == '_')) {
            Some(c) => Err(format!("{token:?} contains {c:?} (letters, digits and `_` only)")),
            None => Ok(()),
        },
    }
}

/// An absolute namespace (`/` or `/a/b`).
pub fn check_namespace(namespace: &str) -> Result<(), String> {
    let Some(rest) = namespace.strip_prefix('/') else {
        return Err(format!("namespace {namespace:?} must start with `/`"));
    };
    if rest.is_empty() {
        return Ok(());
    }
    rest.split('/').try_for_each(check_token).map_err(|e| format!("namespace {namespace:?}: {e}"))
}

/// A topic or service name as written (absolute, relative or `~` private; substitutions allowed).
pub fn check_name(name: &str) -> Result<(), String> {
    let body = if name == "~" {
        return Ok(());
    } else if let Some(rest) = name.strip_prefix("~/") {
        rest
    } else if let Some(rest) = name.strip_prefix('/') {
        rest
    } else {
        name
    };
    if body.is_empty() {
        return Err("empty name".to_string());
    }
    body.split('/').try_for_each(|token| match token {
        "{node}" | "{ns}" | "{namespace}" => Ok(()),
        _ => check_token(token),
    })
}

/// A root-namespace name of a node with its default name (`/step_executor/stop`, `/joint_states`),
/// made relative to the node: `~/stop`, `joint_states`. In the root namespace with the default node
/// name it resolves to the name it was; under `__ns`/`__node` it moves with the node.
pub fn relative_to_node(default_node: &str, root_name: &str) -> String {
    let private_prefix = format!("/{default_node}/");
    if let Some(rest) = root_name.strip_prefix(&private_prefix) {
        format!("~/{rest}")
    } else if let Some(rest) = root_name.strip_prefix('/') {
        rest.to_string()
    } else {
        root_name.to_string()
    }
}

/// The node's name, namespace and remap rules: resolves every name the node uses.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct NodeNames {
    name: String,
    namespace: String,
    /// (expanded from, expanded to), in the order given.
    remaps: Vec<(String, String)>,
    /// The security enclave of `--ros-args --enclave` (with the node's identity for convenience).
    enclave: Option<String>,
}

impl NodeNames {
    /// The names of node `default_name` under the ROS arguments (`__node`, `__ns`, remaps for it).
    pub fn new(default_name: &str, ros: &RosArgs) -> Result<NodeNames, NodeError> {
        let name = ros.node_name(default_name);
        let namespace = ros.namespace(default_name);
        let bad = |name: &str, reason: String| NodeError::BadName { name: name.to_string(), reason };
        check_token(&name).map_err(|e| bad(&name, e))?;
        check_namespace(&namespace).map_err(|e| bad(&namespace, e))?;
        let namespace = if namespace.len() > 1 { namespace.trim_end_matches('/').to_string() } else { namespace };
        let mut names = NodeNames { name, namespace, remaps: Vec::new(), enclave: ros.enclave.clone() };
        let rules: Vec<(String, String)> = ros.remaps_for(default_name, &names.name).map(|r| (r.from.clone(), r.to.clone())).collect();
        for (from, to) in rules {
            let expanded = (names.expand(&from).map_err(|e| bad(&from, e))?, names.expand(&to).map_err(|e| bad(&to, e))?);
            names.remaps.push(expanded);
        }
        Ok(names)
    }

    /// Names of a node without ROS arguments: `/name`, no remaps.
    pub fn plain(name: &str) -> Result<NodeNames, NodeError> {
        NodeNames::new(name, &RosArgs::default())
    }

    pub fn name(&self) -> &str {
        &self.name
    }

    /// `--ros-args --enclave`, if given.
    pub fn enclave(&self) -> Option<&str> {
        self.enclave.as_deref()
    }

    pub fn namespace(&self) -> &str {
        &self.namespace
    }

    /// `/<ns>/<node>`.
    pub fn fully_qualified(&self) -> String {
        join(&self.namespace, &self.name)
    }

    /// The fully qualified form of `name` before remapping.
    pub fn expand(&self, name: &str) -> Result<String, String> {
        check_name(name)?;
        let substituted = name.replace("{node}", &self.name).replace("{ns}", &self.namespace).replace("{namespace}", &self.namespace);
        let expanded = if substituted == "~" {
            self.fully_qualified()
        } else if let Some(rest) = substituted.strip_prefix("~/") {
            join(&self.fully_qualified(), rest)
        } else if substituted.starts_with('/') {
            substituted
        } else {
            join(&self.namespace, &substituted)
        };
        // `{ns}` of the root namespace leaves a `//`.
        let expanded = expanded.replace("//", "/");
        check_name(&expanded)?;
        Ok(expanded)
    }

    /// The fully qualified name the node uses for `name`: expanded, then remapped.
    pub fn resolve(&self, name: &str) -> Result<String, NodeError> {
        let expanded = self.expand(name).map_err(|reason| NodeError::BadName { name: name.to_string(), reason })?;
        Ok(self.remaps.iter().find(|(from, _)| *from == expanded).map(|(_, to)| to.clone()).unwrap_or(expanded))
    }
}

fn join(namespace: &str, rest: &str) -> String {
    if namespace == "/" {
        format!("/{rest}")
    } else {
        format!("{namespace}/{rest}")
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ros_args::split;

    fn names(default: &str, args: &[&str]) -> NodeNames {
        let argv = std::iter::once("x").chain(std::iter::once("--ros-args")).chain(args.iter().copied()).map(std::ffi::OsString::from);
        let (_, ros) = split(argv).unwrap();
        NodeNames::new(default, &ros).unwrap()
    }

    #[test]
    fn root_namespace_with_default_names_gives_the_root_names_back() {
        let n = NodeNames::plain("step_executor").unwrap();
        for root in ["/step_executor/stop", "/joint_states", "/patch_mapper/patches", "/camera/depth/image_raw"] {
            assert_eq!(n.resolve(&relative_to_node("step_executor", root)).unwrap(), root);
        }
        assert_eq!(relative_to_node("step_executor", "/step_executor/stop"), "~/stop");
        assert_eq!(relative_to_node("step_executor", "/joint_states"), "joint_states");
        assert_eq!(n.fully_qualified(), "/step_executor");
    }

    #[test]
    fn namespace_and_node_name_move_relative_and_private_names_not_absolute_ones() {
        let n = names("step_executor", &["-r", "__ns:=/robot1", "-r", "__node:=exec"]);
        assert_eq!(n.fully_qualified(), "/robot1/exec");
        assert_eq!(n.resolve("~/stop").unwrap(), "/robot1/exec/stop");
        assert_eq!(n.resolve("patch_mapper/patches").unwrap(), "/robot1/patch_mapper/patches");
        assert_eq!(n.resolve("/tf").unwrap(), "/tf");
        assert_eq!(n.resolve("~").unwrap(), "/robot1/exec");
        assert_eq!(n.resolve("{ns}/{node}/x").unwrap(), "/robot1/exec/x");
        let root = NodeNames::plain("a").unwrap();
        assert_eq!(root.resolve("{ns}/x").unwrap(), "/x");
    }

    #[test]
    fn remaps_are_expanded_like_names_and_the_first_match_wins() {
        let n = names(
            "patch_mapper",
            &[
                "-r",
                "__ns:=/robot1",
                "-r",
                "camera/depth/image_raw:=/camera/camera/depth/image_rect_raw",
                "-r",
                "/robot1/camera/depth/image_raw:=/second",
                "-r",
                "~/patches:=patches_out",
                "-r",
                "other_node:imu/data:=/nope",
            ],
        );
        assert_eq!(n.resolve("camera/depth/image_raw").unwrap(), "/camera/camera/depth/image_rect_raw");
        assert_eq!(n.resolve("/robot1/camera/depth/image_raw").unwrap(), "/camera/camera/depth/image_rect_raw");
        assert_eq!(n.resolve("~/patches").unwrap(), "/robot1/patches_out");
        assert_eq!(n.resolve("imu/data").unwrap(), "/robot1/imu/data", "the rule is for another node");
    }

    #[test]
    fn bad_names_are_refused_with_the_reason() {
        let n = NodeNames::plain("a").unwrap();
        for bad in ["", "/", "a//b", "1abc", "a b", "~x", "a/"] {
            assert!(n.resolve(bad).is_err(), "{bad:?}");
        }
        assert!(check_namespace("robot1").is_err());
        assert!(check_namespace("/robot 1").is_err());
        assert!(NodeNames::plain("9").is_err());
    }
}
