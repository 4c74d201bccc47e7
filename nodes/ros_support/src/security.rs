//! DDS Security (authentication, access control, encryption: the OMG DDS Security builtin plugins of
//! RustDDS) from a keystore in the SROS2 layout, configured through the environment exactly as rcl reads it:
//!
//! | variable | meaning |
//! |---|---|
//! | `ROS_SECURITY_ENABLE` | `true` turns security on (anything else: off, the default) |
//! | `ROS_SECURITY_STRATEGY` | `Enforce`: a node whose enclave files are missing refuses to start; otherwise (permissive) it runs unsecured with a warning |
//! | `ROS_SECURITY_KEYSTORE` | the keystore directory (`launch_scripts/create_keystore.sh` makes one) |
//! | `ROS_SECURITY_ENCLAVE_OVERRIDE` | the enclave, overriding the node's own (`--enclave`, default `/`) |
//!
//! The enclave `/patchwalk/step_executor` is the directory `<keystore>/enclaves/patchwalk/step_executor/`
//! holding `cert.pem`, `key.pem` (PKCS#8, unencrypted), `identity_ca.cert.pem`, `permissions_ca.cert.pem`,
//! `governance.p7s` and `permissions.p7s` — the names rmw_dds_common uses.

use std::path::{Path, PathBuf};

use rustdds::DomainParticipantSecurityConfigFiles;

/// The files every enclave directory must hold.
pub const ENCLAVE_FILES: [&str; 6] =
    ["identity_ca.cert.pem", "cert.pem", "key.pem", "permissions_ca.cert.pem", "governance.p7s", "permissions.p7s"];

/// Errors of the security configuration; each names the variable or file at fault.
#[derive(Debug, thiserror::Error)]
pub enum SecurityError {
    #[error("ROS_SECURITY_ENABLE=true but ROS_SECURITY_KEYSTORE is not set (the keystore directory)")]
    NoKeystore,
    #[error("enclave {enclave:?} is not an absolute enclave path (e.g. /patchwalk/step_executor)")]
    BadEnclave { enclave: String },
    #[error("ROS_SECURITY_STRATEGY=Enforce: enclave {enclave} has no {file} in {dir} (create it with launch_scripts/create_keystore.sh)")]
    MissingFile { enclave: String, file: &'static str, dir: PathBuf },
}

/// Security settings as read from the environment.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SecuritySettings {
    pub enabled: bool,
    pub enforce: bool,
    pub keystore: Option<PathBuf>,
    pub enclave_override: Option<String>,
}

impl SecuritySettings {
    /// Read `ROS_SECURITY_*` from the process environment.
    pub fn from_env() -> SecuritySettings {
        Self::from_lookup(|key| std::env::var(key).ok())
    }

    /// Read the settings through `lookup` (the environment, or a map in tests).
    pub fn from_lookup(lookup: impl Fn(&str) -> Option<String>) -> SecuritySettings {
        let non_empty = |key: &str| lookup(key).map(|v| v.trim().to_string()).filter(|v| !v.is_empty());
        SecuritySettings {
            // rcl compares exactly with "true".
            enabled: lookup("ROS_SECURITY_ENABLE").is_some_and(|v| v.trim() == "true"),
            enforce: lookup("ROS_SECURITY_STRATEGY").is_some_and(|v| v.trim() == "Enforce"),
            keystore: non_empty("ROS_SECURITY_KEYSTORE").map(PathBuf::from),
            enclave_override: non_empty("ROS_SECURITY_ENCLAVE_OVERRIDE"),
        }
    }
}

/// What the participant runs with: the enclave and its files, or unsecured (with the reason when security
/// was asked for but the permissive strategy let the node run without it).
#[derive(Debug)]
pub enum Security {
    Off,
    Permissive { reason: String },
    On { enclave: String, dir: PathBuf },
}

impl Security {
    /// The builtin plugins' configuration of an enclave (`None` when unsecured).
    pub fn config_files(&self) -> Option<DomainParticipantSecurityConfigFiles> {
        match self {
            // The keys create_keystore.sh writes are unencrypted (as SROS2's): no password.
            Security::On { dir, .. } => Some(DomainParticipantSecurityConfigFiles::with_ros_default_names(dir, String::new())),
            Security::Off | Security::Permissive { .. } => None,
        }
    }
}

/// The enclave directory of `enclave` (`/a/b` → `<keystore>/enclaves/a/b`).
pub fn enclave_dir(keystore: &Path, enclave: &str) -> Result<PathBuf, SecurityError> {
    let bad = || SecurityError::BadEnclave { enclave: enclave.to_string() };
    let relative = enclave.strip_prefix('/').ok_or_else(bad)?;
    let mut dir = keystore.join("enclaves");
    for part in relative.split('/').filter(|p| !p.is_empty()) {
        if part == "." || part == ".." {
            return Err(bad());
        }
        dir.push(part);
    }
    Ok(dir)
}

/// Decide the participant's security from `settings` and the node's own enclave (`--enclave`, `/` when
/// not given), checking that the enclave's files exist.
pub fn resolve(settings: &SecuritySettings, node_enclave: Option<&str>) -> Result<Security, SecurityError> {
    if !settings.enabled {
        return Ok(Security::Off);
    }
    let enclave = settings.enclave_override.as_deref().or(node_enclave).unwrap_or("/").to_string();
    let permissive_or =
        |error: SecurityError| if settings.enforce { Err(error) } else { Ok(Security::Permissive { reason: error.to_string() }) };
    let Some(keystore) = settings.keystore.as_deref() else {
        return permissive_or(SecurityError::NoKeystore);
    };
    let dir = enclave_dir(keystore, &enclave)?;
    if let Some(file) = ENCLAVE_FILES.into_iter().find(|file| !dir.join(file).is_file()) {
        return permissive_or(SecurityError::MissingFile { enclave, file, dir });
    }
    Ok(Security::On { enclave, dir })
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashMap;

    fn settings(pairs: &[(&str, &str)]) -> SecuritySettings {
        let map: HashMap<String, String> = pairs.iter().map(|(k, v)| (k.to_string(), v.to_string())).collect();
        SecuritySettings::from_lookup(|k| map.get(k).cloned())
    }

    fn enclave_with_files(root: &Path, enclave: &str) -> PathBuf {
        let dir = enclave_dir(root, enclave).unwrap();
        std::fs::create_dir_all(&dir).unwrap();
        for file in ENCLAVE_FILES {
            std::fs::write(dir.join(file), "x").unwrap();
        }
        dir
    }

    #[test]
    fn off_unless_enable_is_exactly_true() {
        assert!(matches!(resolve(&settings(&[]), None).unwrap(), Security::Off));
        assert!(matches!(resolve(&settings(&[("ROS_SECURITY_ENABLE", "1")]), None).unwrap(), Security::Off));
        assert!(matches!(resolve(&settings(&[("ROS_SECURITY_ENABLE", "True")]), None).unwrap(), Security::Off));
    }

    #[test]
    fn enforce_refuses_a_missing_keystore_or_file_and_permissive_runs_unsecured() {
        let root = tempfile::tempdir().unwrap();
        let keystore = root.path().to_str().unwrap();
        let enforce = settings(&[("ROS_SECURITY_ENABLE", "true"), ("ROS_SECURITY_STRATEGY", "Enforce")]);
        assert!(matches!(resolve(&enforce, None), Err(SecurityError::NoKeystore)));
        let enforce =
            settings(&[("ROS_SECURITY_ENABLE", "true"), ("ROS_SECURITY_STRATEGY", "Enforce"), ("ROS_SECURITY_KEYSTORE", keystore)]);
        let error = resolve(&enforce, Some("/patchwalk/step_executor")).unwrap_err();
        assert!(error.to_string().contains("identity_ca.cert.pem"), "{error}");
        let permissive = settings(&[("ROS_SECURITY_ENABLE", "true"), ("ROS_SECURITY_KEYSTORE", keystore)]);
        match resolve(&permissive, Some("/patchwalk/step_executor")).unwrap() {
            Security::Permissive { reason } => assert!(reason.contains("/patchwalk/step_executor"), "{reason}"),
            other => panic!("expected permissive, got {other:?}"),
        }
    }

    #[test]
    fn override_wins_over_the_node_enclave_and_paths_stay_inside_the_keystore() {
        let root = tempfile::tempdir().unwrap();
        let dir = enclave_with_files(root.path(), "/robot1/operator");
        let keystore = root.path().to_str().unwrap();
        let s = settings(&[
            ("ROS_SECURITY_ENABLE", "true"),
            ("ROS_SECURITY_STRATEGY", "Enforce"),
            ("ROS_SECURITY_KEYSTORE", keystore),
            ("ROS_SECURITY_ENCLAVE_OVERRIDE", "/robot1/operator"),
        ]);
        match resolve(&s, Some("/patchwalk/step_executor")).unwrap() {
            Security::On { enclave, dir: found, .. } => {
                assert_eq!(enclave, "/robot1/operator");
                assert_eq!(found, dir);
            }
            other => panic!("expected security on, got {other:?}"),
        }
        assert!(matches!(enclave_dir(root.path(), "/a/../../etc"), Err(SecurityError::BadEnclave { .. })));
        assert!(matches!(enclave_dir(root.path(), "relative"), Err(SecurityError::BadEnclave { .. })));
        assert_eq!(enclave_dir(root.path(), "/").unwrap(), root.path().join("enclaves"));
    }
}
