//! Master side of Dynamixel Protocol 2.0: a received byte stream (status packets, echoes, noise)
//! through the incremental frame parser, in chunks sized by byte 0. Every parsed packet must survive
//! re-encoding (a `FrameError::RoundTrip` is a bug of the parser or the encoder).
#![no_main]
use patchwalk_dynamixel::protocol::{parse_stream, FrameError};

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    for frame in parse_stream(data) {
        if let Err(e @ FrameError::RoundTrip { .. }) = frame {
            panic!("{e}");
        }
    }
});
