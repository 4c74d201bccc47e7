//! Offline subcommands of the `patch_mapper` binary.
pub use patch_mapper::bag_input;
pub mod calibrate_imu;
pub mod fit;
pub mod map;
pub mod replay;
pub mod track;

use nalgebra::Vector3;

/// Errors of command-line values.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ArgError {
    /// Not three comma-separated finite numbers.
    #[error("expected three finite numbers x,y,z, got '{0}'")]
    NotVec3(String),
}

/// A vector `x,y,z` of three finite numbers (the `--sensor-origin` / `--gravity` values).
pub fn parse_vec3(s: &str) -> Result<Vector3<f64>, ArgError> {
    let v: Result<Vec<f64>, _> = s.split(',').map(|p| p.trim().parse::<f64>()).collect();
    match v.as_deref() {
        Ok([x, y, z]) if [x, y, z].iter().all(|c| c.is_finite()) => Ok(Vector3::new(*x, *y, *z)),
        _ => Err(ArgError::NotVec3(s.to_string())),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn vectors_parse_and_bad_ones_are_rejected() {
        assert_eq!(parse_vec3("0, 0.79,-0.62").unwrap(), Vector3::new(0.0, 0.79, -0.62));
        for bad in ["1,2", "1,2,3,4", "a,b,c", "1,inf,2", "1,NaN,2"] {
            assert_eq!(parse_vec3(bad), Err(ArgError::NotVec3(bad.to_string())), "{bad}");
        }
    }
}
