//! CameraInfo + Imu + depth Image payloads through patch_mapper's conversions and one frame of the
//! mapping pipeline (`Pipeline::process`) on a small image budget.
#![no_main]
libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let _ = patch_mapper::inputs::pipeline_frame(data);
});
