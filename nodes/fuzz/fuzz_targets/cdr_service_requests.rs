//! step_executor's service requests: byte 0 picks the patchwalk_msgs service, the rest is the
//! serialized request, decoded and checked by the runtime as the node's handlers do.
#![no_main]
libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let _ = step_executor::inputs::service_request(data);
});
