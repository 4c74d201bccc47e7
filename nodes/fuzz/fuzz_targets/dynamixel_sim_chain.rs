//! Device side of Dynamixel Protocol 2.0: instruction bytes into the simulated MX-28 chain (12
//! servos), which answers with status packets; every answer must be a well-formed status packet.
#![no_main]
use patchwalk_dynamixel::protocol::{instruction, parse_stream};
use patchwalk_dynamixel::sim_chain::replay_instructions;

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let answers = replay_instructions(data);
    for frame in parse_stream(&[&[63u8][..], &answers].concat()) {
        match frame {
            Ok(packet) => assert_eq!(packet.instruction, instruction::STATUS, "the chain sent a non-status packet"),
            Err(e) => panic!("the chain sent a bad frame: {e}"),
        }
    }
});
