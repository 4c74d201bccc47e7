//! A page of a ROBOTIS action file (DARwIn-OP / OP3 `motion_409x.bin`) as `step_executor
//! import-motion` reads it: byte 0 bit 0 fixes the checksum, then the 512 page bytes. A parsed page
//! must write back byte for byte, and keyframes exported again must re-import within a tick.
#![no_main]
use step_executor::inputs::{action_page, InputError};

/// One MX-28 tick (rad) and a little for the floating point.
const TICK_RAD: f64 = std::f64::consts::TAU / 4096.0 * 1.01;

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    match action_page(data) {
        Err(e @ InputError::PageRoundTrip) => panic!("{e}"),
        Ok(outcome) => {
            if let Ok(error) = outcome.reexport {
                assert!(error <= TICK_RAD, "re-exported keyframes are {error} rad off");
            }
        }
        Err(_) => {}
    }
});
