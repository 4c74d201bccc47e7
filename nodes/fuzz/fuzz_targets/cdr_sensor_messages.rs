//! patch_mapper's sensor topics: byte 0 picks Image / CameraInfo / Imu, the rest is the serialized
//! payload (encapsulation header + CDR), decoded and converted as the node does.
#![no_main]
libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let _ = patch_mapper::inputs::sensor_message(data);
});
