#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic)] // an integration test
//! The real Protocol 2.0 master (`dynamixel2` through `DynamixelBus`) against the simulated MX-28
//! chain on a pty: ping, sync write, sync read, and injected faults (CRC error, timeout, hardware
//! error) surfacing as typed `BusError`s; then the player driving 12 servos end to end.

use std::time::{Duration, Instant};

use patchwalk_dynamixel::mx28;
use patchwalk_dynamixel::servo_bus::dynamixel::DynamixelBus;
use patchwalk_dynamixel::servo_bus::{self, BusError, ServoBus};
use patchwalk_dynamixel::sim_chain::{SimChain, SimConfig};
use patchwalk_robot_model::kinematics::JointLimits;
use patchwalk_spl::patch::Patch;
use step_executor::config::{ServoConfig, DEFAULT_JOINTS};
use step_executor::library::{Keyframe, Motion};
use step_executor::player::{JointSpec, Player, PlayerConfig, PlayerEvent, PlayerState};

const ANSWER_BUDGET: Duration = Duration::from_millis(300);

fn setup(n: u8) -> (SimChain, DynamixelBus) {
    let mut config = SimConfig::with_servos(n);
    config.return_delay_register = 0;
    let chain = SimChain::spawn(config).unwrap();
    // The chain is a user thread behind a pty: on a loaded test host (nextest in parallel, other
    // builds) its answers can lag far beyond RS-485's 34 ms, so the tests allow 300 ms.
    let bus = DynamixelBus::open(&chain.device_path(), 1_000_000).unwrap().with_response_timeout(ANSWER_BUDGET);
    (chain, bus)
}

fn ids(n: u8) -> Vec<u8> {
    (1..=n).collect()
}

#[test]
fn ping_every_servo_reports_mx28_model() {
    let (_chain, mut bus) = setup(12);
    for id in ids(12) {
        assert_eq!(bus.ping(id).unwrap(), mx28::MODEL_NUMBER);
    }
    assert_eq!(bus.ping(13), Err(BusError::Timeout { id: 13 }));
}

#[test]
fn twelve_servo_sync_write_then_sync_read() {
    let (chain, mut bus) = setup(12);
    servo_bus::sync_write_u8(&mut bus, mx28::TORQUE_ENABLE, &ids(12).iter().map(|&id| (id, 1)).collect::<Vec<_>>()).unwrap();
    let goals: Vec<(u8, u32)> = ids(12).iter().map(|&id| (id, 2048 + 10 * u32::from(id))).collect();
    servo_bus::sync_write_u32(&mut bus, mx28::GOAL_POSITION, &goals).unwrap();
    let goal_back = bus.sync_read(&ids(12), mx28::GOAL_POSITION, 4).unwrap();
    for ((id, result), (_, goal)) in goal_back.iter().zip(&goals) {
        let data = result.as_ref().unwrap();
        assert_eq!(u32::from_le_bytes(data.data.clone().try_into().unwrap()), *goal, "servo {id}");
        assert!(!data.alert);
    }
    // Present positions converge to the goals (120 ticks at ~3700 ticks/s: ~30 ms).
    let deadline = Instant::now() + Duration::from_secs(2);
    loop {
        let present = servo_bus::read_present_positions(&mut bus, &ids(12)).unwrap();
        if present.iter().zip(&goals).all(|(p, (_, g))| *p == *g as i32) || Instant::now() > deadline {
            assert_eq!(present, goals.iter().map(|(_, g)| *g as i32).collect::<Vec<_>>());
            break;
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    assert_eq!(chain.snapshot(12).unwrap().goal, 2168);
}

#[test]
fn injected_crc_error_is_a_checksum_error_for_that_servo_only() {
    let (chain, mut bus) = setup(4);
    chain.set_faults(|f| {
        f.crc_errors.insert(3);
    });
    let results = bus.sync_read(&ids(4), mx28::PRESENT_POSITION, 4).unwrap();
    for (id, result) in &results {
        if *id == 3 {
            assert_eq!(result, &Err(BusError::Checksum { id: 3 }));
        } else {
            assert!(result.is_ok(), "servo {id}: {result:?}");
        }
    }
    assert_eq!(bus.ping(3), Err(BusError::Checksum { id: 3 }));
}

#[test]
fn silent_servo_or_chain_times_out_with_its_id() {
    let (chain, mut bus) = setup(3);
    chain.set_faults(|f| {
        f.silent.insert(2);
    });
    let err = servo_bus::read_present_positions(&mut bus, &ids(3)).unwrap_err().0;
    assert_eq!(err, BusError::Timeout { id: 2 });
    chain.set_faults(|f| {
        f.silent.clear();
        f.silent_all = true;
    });
    assert_eq!(bus.read(1, mx28::PRESENT_POSITION, 4), Err(BusError::Timeout { id: 1 }));
    chain.set_faults(|f| f.silent_all = false);
    assert_eq!(bus.ping(1).unwrap(), mx28::MODEL_NUMBER);
}

#[test]
fn a_port_unplugged_while_an_answer_is_awaited_is_a_lost_port_not_a_silent_servo() {
    let (chain, bus) = setup(2);
    let mut bus = bus.with_response_timeout(Duration::from_millis(400));
    chain.set_faults(|f| f.silent_all = true); // the request stays unanswered, the read in flight
    let chain = std::sync::Arc::new(chain);
    let unplugger = {
        let chain = std::sync::Arc::clone(&chain);
        std::thread::spawn(move || {
            std::thread::sleep(Duration::from_millis(50));
            chain.unplug();
        })
    };
    let single = bus.read(1, mx28::PRESENT_POSITION, 4);
    unplugger.join().unwrap();
    assert!(matches!(&single, Err(BusError::Io(detail)) if detail.contains("hung up")), "{single:?}");
    let burst = servo_bus::read_present_positions(&mut bus, &ids(2)).unwrap_err().0;
    assert!(matches!(&burst, BusError::Io(_)), "{burst:?}");
}

#[test]
fn latency_beyond_the_timeout_is_a_timeout() {
    let (chain, mut bus) = setup(1);
    chain.set_faults(|f| f.latency = ANSWER_BUDGET * 2);
    assert_eq!(bus.ping(1), Err(BusError::Timeout { id: 1 }));
    chain.set_faults(|f| f.latency = Duration::ZERO);
    std::thread::sleep(ANSWER_BUDGET * 3); // let the late reply drain
    assert_eq!(bus.ping(1).unwrap(), mx28::MODEL_NUMBER);
}

#[test]
fn malformed_frame_panic_inside_dynamixel2_becomes_an_error_and_the_bus_survives() {
    let (chain, mut bus) = setup(2);
    chain.set_faults(|f| {
        f.malformed.insert(2);
    });
    // Silence the default panic hook's message for this expected panic.
    let hook = std::panic::take_hook();
    std::panic::set_hook(Box::new(|_| {}));
    let result = bus.ping(2);
    std::panic::set_hook(hook);
    assert!(matches!(result, Err(BusError::Malformed { id: 2, .. })), "{result:?}");
    chain.set_faults(|f| f.malformed.clear());
    assert_eq!(bus.ping(2).unwrap(), mx28::MODEL_NUMBER);
    assert_eq!(bus.ping(1).unwrap(), mx28::MODEL_NUMBER);
}

#[test]
fn hardware_error_alert_becomes_typed_error_with_bits() {
    let (chain, mut bus) = setup(12);
    chain.set_hardware_error(7, mx28::HW_OVERHEATING | mx28::HW_OVERLOAD);
    let err = servo_bus::read_present_positions(&mut bus, &ids(12)).unwrap_err().0;
    assert_eq!(err, BusError::Hardware { id: 7, bits: mx28::HW_OVERHEATING | mx28::HW_OVERLOAD });
}

#[test]
fn eeprom_write_with_torque_on_is_an_access_error() {
    let (_chain, mut bus) = setup(1);
    bus.write(1, mx28::RETURN_DELAY_TIME, &[0]).unwrap();
    bus.write(1, mx28::TORQUE_ENABLE, &[1]).unwrap();
    assert_eq!(bus.write(1, mx28::RETURN_DELAY_TIME, &[5]), Err(BusError::Status { id: 1, code: 0x07 }));
}

fn joint_specs() -> Vec<JointSpec> {
    DEFAULT_JOINTS
        .iter()
        .zip(1u8..)
        .map(|(joint, id)| JointSpec {
            servo: ServoConfig { joint: (*joint).to_string(), id, zero_offset: 0.0, direction: 1 },
            limits: JointLimits { lower: -1.0, upper: 1.0 },
        })
        .collect()
}

fn step_motion() -> Motion {
    Motion {
        name: "rock1".into(),
        patch: Patch::level_disc(0.02, nalgebra::Vector3::new(0.1, 0.0, -0.29)).unwrap(),
        keyframes: vec![
            Keyframe { positions: vec![0.2; 12], move_s: 0.16, pause_s: 0.04 },
            Keyframe { positions: vec![-0.1; 12], move_s: 0.16, pause_s: 0.0 },
        ],
    }
}

#[test]
fn player_drives_twelve_simulated_servos_through_the_keyframes() {
    let (chain, mut bus) = setup(12);
    servo_bus::sync_write_u8(&mut bus, mx28::TORQUE_ENABLE, &ids(12).iter().map(|&id| (id, 1)).collect::<Vec<_>>()).unwrap();
    let mut player = Player::new(PlayerConfig::default(), joint_specs());
    player.cycle(&mut bus, false);
    player.start(&step_motion()).unwrap();
    let mut finished = false;
    for _ in 0..200 {
        let report = player.cycle(&mut bus, false);
        assert!(!matches!(report.event, Some(PlayerEvent::Fault(_))), "{report:?}");
        if matches!(report.event, Some(PlayerEvent::Finished { .. })) {
            finished = true;
            break;
        }
        std::thread::sleep(Duration::from_millis(8));
    }
    assert!(finished);
    // Each servo accepted goals rising to keyframe 1 then falling to keyframe 2.
    let k1 = (2048.0 + 0.2 * 4096.0 / std::f64::consts::TAU).round() as i32;
    let k2 = (2048.0 - 0.1 * 4096.0 / std::f64::consts::TAU).round() as i32;
    for id in ids(12) {
        let history = chain.goal_history(id);
        let peak = history.iter().position(|g| *g == k1).unwrap();
        assert!(history[..=peak].windows(2).all(|w| w[1] >= w[0]), "servo {id}");
        assert!(history[peak..].windows(2).all(|w| w[1] <= w[0]), "servo {id}");
        assert_eq!(history.last(), Some(&k2));
    }
}

#[test]
fn fault_mid_motion_stops_and_holds_on_the_pty_bus() {
    let (chain, mut bus) = setup(12);
    servo_bus::sync_write_u8(&mut bus, mx28::TORQUE_ENABLE, &ids(12).iter().map(|&id| (id, 1)).collect::<Vec<_>>()).unwrap();
    let mut player = Player::new(PlayerConfig::default(), joint_specs());
    player.cycle(&mut bus, false);
    player.start(&step_motion()).unwrap();
    for _ in 0..10 {
        player.cycle(&mut bus, false);
    }
    chain.set_faults(|f| {
        f.silent.insert(5);
    });
    let report = player.cycle(&mut bus, false);
    let Some(PlayerEvent::Fault(fault)) = report.event else { panic!("{report:?}") };
    assert_eq!(fault.servo_id, Some(5));
    assert_eq!(fault.joint.as_deref(), Some(DEFAULT_JOINTS[4]));
    assert!(matches!(player.state(), PlayerState::Faulted(_)));
    // Holding: the other servos' goals equal their last measured positions and stay put.
    std::thread::sleep(Duration::from_millis(20)); // sync write has no reply: let the chain apply it
    let goal_before: Vec<i32> = ids(12).iter().map(|&id| chain.snapshot(id).unwrap().goal).collect();
    for _ in 0..5 {
        player.cycle(&mut bus, false);
    }
    let goal_after: Vec<i32> = ids(12).iter().map(|&id| chain.snapshot(id).unwrap().goal).collect();
    assert_eq!(goal_before, goal_after);
}
