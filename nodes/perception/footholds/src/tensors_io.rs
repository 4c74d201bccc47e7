//! safetensors files with string metadata (the sample sets and the shipped weights).

use std::borrow::Cow;
use std::collections::HashMap;
use std::path::Path;

use candle_core::{Device, Tensor};
use safetensors::tensor::View;
use safetensors::{Dtype, SafeTensors};

use crate::error::{io_error, FootholdError};

/// Writes named tensors and metadata to a safetensors file ([`save_views`]).
pub fn save(path: &Path, tensors: &[(String, Tensor)], metadata: HashMap<String, String>) -> Result<(), FootholdError> {
    save_views(path, tensors.iter().map(|(n, t)| (n.as_str(), t)), metadata)
}

/// Writes named tensors and metadata to a safetensors file atomically, the steps of the motion
/// library's `write_atomically` (temporary file beside it, synced, renamed over it, directory
/// synced), streamed from the views instead of one buffer: a write that is interrupted (a full
/// disk, a kill) leaves the old file, or none, never a truncated one.
pub fn save_views<'a, V: View>(
    path: &Path,
    tensors: impl IntoIterator<Item = (&'a str, V)>,
    metadata: HashMap<String, String>,
) -> Result<(), FootholdError> {
    let parent = path.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
    std::fs::create_dir_all(parent).map_err(io_error(parent))?;
    let name = path.file_name().map_or_else(|| "tensors".into(), |n| n.to_string_lossy().into_owned());
    let temporary = parent.join(format!(".{name}.{}.tmp", std::process::id()));
    let written = safetensors::serialize_to_file(tensors, Some(metadata), &temporary)
        .map_err(|e| FootholdError::Weights { path: path.to_path_buf(), reason: e.to_string() })
        .and_then(|()| std::fs::File::open(&temporary).and_then(|f| f.sync_all()).map_err(io_error(&temporary)))
        .and_then(|()| std::fs::rename(&temporary, path).map_err(io_error(path)))
        .and_then(|()| std::fs::File::open(parent).and_then(|d| d.sync_all()).map_err(io_error(parent)));
    if written.is_err() {
        let _ = std::fs::remove_file(&temporary);
    }
    written
}

/// A tensor written straight from memory the caller holds (little-endian bytes, borrowed on
/// little-endian machines): a sample set of several GB is not copied to be saved.
pub struct RawTensor<'a> {
    dtype: Dtype,
    shape: Vec<usize>,
    bytes: Cow<'a, [u8]>,
}

impl<'a> RawTensor<'a> {
    pub fn f32(values: &'a [f32], shape: Vec<usize>) -> Self {
        let bytes = if cfg!(target_endian = "little") {
            Cow::Borrowed(bytemuck::cast_slice(values))
        } else {
            Cow::Owned(values.iter().flat_map(|v| v.to_le_bytes()).collect())
        };
        Self { dtype: Dtype::F32, shape, bytes }
    }

    pub fn u8(values: &'a [u8], shape: Vec<usize>) -> Self {
        Self { dtype: Dtype::U8, shape, bytes: Cow::Borrowed(values) }
    }
}

impl View for &RawTensor<'_> {
    fn dtype(&self) -> Dtype {
        self.dtype
    }

    fn shape(&self) -> &[usize] {
        &self.shape
    }

    fn data(&self) -> Cow<'_, [u8]> {
        Cow::Borrowed(&self.bytes)
    }

    fn data_len(&self) -> usize {
        self.bytes.len()
    }
}

/// The bytes of one tensor of a safetensors buffer, checked for its dtype and element count.
pub fn tensor_bytes<'d>(path: &Path, file: &SafeTensors<'d>, name: &str, dtype: Dtype, len: usize) -> Result<&'d [u8], FootholdError> {
    let bad = |reason: String| FootholdError::Format { path: path.to_path_buf(), reason };
    let view = file.tensor(name).map_err(|e| bad(format!("tensor '{name}': {e}")))?;
    if view.dtype() != dtype || view.shape().iter().product::<usize>() != len {
        return Err(bad(format!("tensor '{name}' is {:?} {:?}, expected {dtype:?} with {len} values", view.dtype(), view.shape())));
    }
    Ok(view.data())
}

/// f32 values from little-endian bytes (a plain copy on little-endian machines).
pub fn f32_from_le(bytes: &[u8]) -> Vec<f32> {
    if cfg!(target_endian = "little") {
        let n = bytes.len() / 4;
        let mut values = vec![0f32; n];
        bytemuck::cast_slice_mut::<f32, u8>(&mut values).copy_from_slice(&bytes[..n * 4]);
        values
    } else {
        bytes.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect()
    }
}

/// Reads a safetensors file as bytes and its metadata, for [`tensor_bytes`].
pub fn read(path: &Path) -> Result<(Vec<u8>, HashMap<String, String>), FootholdError> {
    let bytes = std::fs::read(path).map_err(io_error(path))?;
    let (_, header) =
        SafeTensors::read_metadata(&bytes).map_err(|e| FootholdError::Weights { path: path.to_path_buf(), reason: e.to_string() })?;
    let metadata = header.metadata().clone().unwrap_or_default();
    Ok((bytes, metadata))
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
