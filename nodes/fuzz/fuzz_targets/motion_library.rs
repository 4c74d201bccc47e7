//! step_executor's motion library file (YAML) through the loader and its validation.
#![no_main]
libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let _ = step_executor::inputs::library_file(data);
});
