//! A rosbag2 MCAP file's bytes through the bag reader of `patch_mapper replay` (`patchwalk_bag`'s
//! streaming reader, both passes of `patch_mapper::bag_input`): every message checked and decoded.
#![no_main]
libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let _ = patch_mapper::inputs::bag(data);
});
