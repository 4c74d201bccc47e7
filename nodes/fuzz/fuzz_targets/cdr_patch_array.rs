//! step_executor's `/patch_mapper/patches` input: a serialized PatchArray, converted patch by patch
//! (`patchwalk_ros::patch_msg`) and matched against a trained library as the node does.
#![no_main]
libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let _ = step_executor::inputs::patch_map(data);
});
