//! Master side of Dynamixel Protocol 2.0: a received byte stream (status packets, echoes, noise)
//! through the incremental frame parser, in chunks sized by byte 0.
#![no_main]
libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let _ = patchwalk_dynamixel::protocol::parse_stream(data);
});
