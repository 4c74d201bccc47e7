//! Device side of Dynamixel Protocol 2.0: instruction bytes into the simulated MX-28 chain (12
//! servos), which answers with status packets.
#![no_main]
libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let _ = patchwalk_dynamixel::sim_chain::replay_instructions(data);
});
