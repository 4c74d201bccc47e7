//! safetensors files with string metadata (the sample sets and the shipped weights).

use std::collections::HashMap;
use std::path::Path;

use candle_core::{Device, Tensor};

use crate::error::{io_error, FootholdError};

/// Writes named tensors and metadata to a safetensors file.
pub fn save(path: &Path, tensors: &[(String, Tensor)], metadata: HashMap<String, String>) -> Result<(), FootholdError> {
    if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent).map_err(io_error(parent))?;
    }
    let data: Vec<(&str, &Tensor)> = tensors.iter().map(|(n, t)| (n.as_str(), t)).collect();
    safetensors::serialize_to_file(data, Some(metadata), path)
        .map_err(|e| FootholdError::Weights { path: path.to_path_buf(), reason: e.to_string() })
}

/// Named tensors and string metadata of one file.
pub type TensorsAndMetadata = (HashMap<String, Tensor>, HashMap<String, String>);

/// Reads a safetensors file: its tensors (on the CPU) and its metadata.
pub fn load(path: &Path) -> Result<TensorsAndMetadata, FootholdError> {
    let bytes = std::fs::read(path).map_err(io_error(path))?;
    let bad = |reason: String| FootholdError::Weights { path: path.to_path_buf(), reason };
    let (_, header) = safetensors::SafeTensors::read_metadata(&bytes).map_err(|e| bad(e.to_string()))?;
    let metadata = header.metadata().clone().unwrap_or_default();
    let tensors = candle_core::safetensors::load_buffer(&bytes, &Device::Cpu).map_err(|e| bad(e.to_string()))?;
    Ok((tensors, metadata))
}

/// A metadata entry parsed as JSON.
pub fn meta_json<T: serde::de::DeserializeOwned>(path: &Path, metadata: &HashMap<String, String>, key: &str) -> Result<T, FootholdError> {
    let text =
        metadata.get(key).ok_or_else(|| FootholdError::Format { path: path.to_path_buf(), reason: format!("metadata '{key}' missing") })?;
    serde_json::from_str(text).map_err(|e| FootholdError::Format { path: path.to_path_buf(), reason: format!("metadata '{key}': {e}") })
}

/// A JSON metadata entry.
pub fn to_json<T: serde::Serialize>(value: &T) -> Result<String, FootholdError> {
    serde_json::to_string(value).map_err(|e| FootholdError::Config(e.to_string()))
}
