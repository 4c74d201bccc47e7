//! A node configuration file plus `--param` overrides (NUL-separated after the file text) through
//! `patchwalk_ros::params` into step_executor's and terrain_sim's configs and their validation.
#![no_main]
libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let _ = step_executor::inputs::config_file(data);
    let _ = terrain_sim::config::config_file(data);
});
