#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic)] // an integration test
//! The fault-injection matrix: every fault of the simulated MX-28 chain × every phase (idle with
//! torque on, during a motion, during training with torque off), through the real Protocol 2.0
//! master (`dynamixel2` in `DynamixelBus`) and the executor's bus thread.
//!
//! Expected in every cell: the fault is reported within a cycle or two of the first read that sees
//! it (counted in cycles, not wall time), with the servo id and the reason; it latches (no motion,
//! no position handed out for recording); a motion is held at the measured pose and no goal is
//! written after the hold; and the documented recovery brings the robot back to playing:
//! torque off clears a communication fault once the cause is gone, `reboot` clears a hardware
//! error (torque stays off until switched on explicitly), `reboot` with no ids reopens a lost port.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use patchwalk_dynamixel::mx28;
use patchwalk_dynamixel::servo_bus::dynamixel::DynamixelBus;
use patchwalk_dynamixel::servo_bus::BusError;
use patchwalk_dynamixel::sim_chain::{SimChain, SimConfig};
use patchwalk_robot_model::kinematics::JointLimits;
use patchwalk_spl::patch::Patch;
use step_executor::config::{BusConfig, ServoConfig, DEFAULT_JOINTS};
use step_executor::executor::{initialise_bus, Executor, ExecutorError, LoopSettings, Telemetry};
use step_executor::library::{Keyframe, Motion};
use step_executor::player::{Fault, JointSpec, Player, PlayerConfig, PlayerEvent, PlayerState};

/// Answer budget: the chain is a thread behind a pty on a shared test host (see
/// `dynamixel_master_on_sim_bus.rs`).
const BUDGET: Duration = Duration::from_millis(200);
const CYCLE: Duration = Duration::from_millis(8);

#[derive(Debug, Clone, Copy, PartialEq)]
enum Phase {
    /// Torque on, holding, nothing playing.
    Idle,
    /// A motion is playing.
    Motion,
    /// Torque off, positions read for `record_keyframe`.
    Training,
}

const PHASES: [Phase; 3] = [Phase::Idle, Phase::Motion, Phase::Training];

/// One row of the matrix: how to inject, what must be reported, how to undo the cause.
struct Row {
    name: &'static str,
    inject: fn(&Rig),
    /// Expected fault servo id (None: not servo-specific).
    servo: Option<u8>,
    /// Expected reason.
    reason: fn(&BusError) -> bool,
    /// Remove the cause (the hardware-error rows leave it: only a reboot clears it).
    remove: fn(&Rig),
    /// How long the chain may still apply instructions sent before the fault (the simulated chain
    /// serves instructions in order, so a delayed answer delays the writes queued behind it).
    backlog: Duration,
    recovery: Recovery,
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum Recovery {
    /// Torque off clears the latched fault, torque on, play.
    TorqueToggle,
    /// REBOOT of the faulted servo, then torque on (refused to play before), play.
    Reboot,
    /// Plug back in, `reboot` with no ids reopens the port, torque on, play.
    Reconnect,
}

struct Rig {
    chain: SimChain,
    link: PathBuf,
    executor: Executor,
    _dir: tempfile::TempDir,
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

fn motion(target: f64, move_s: f64) -> Motion {
    Motion {
        name: "step".into(),
        patch: Patch::level_disc(0.02, nalgebra::Vector3::new(0.1, 0.0, -0.29)).unwrap(),
        keyframes: vec![Keyframe { positions: vec![target; 12], move_s, pause_s: 0.0 }],
    }
}

fn point_link(link: &Path, target: &Path) {
    let _ = std::fs::remove_file(link);
    std::os::unix::fs::symlink(target, link).unwrap();
}

fn rig() -> Rig {
    rig_with_budget(BUDGET)
}

fn rig_with_budget(budget: Duration) -> Rig {
    let mut config = SimConfig::with_servos(12);
    config.return_delay_register = 0;
    let chain = SimChain::spawn(config).unwrap();
    let dir = tempfile::tempdir().unwrap();
    // The master opens a stable name, as `bus.port` would be a udev symlink on the robot.
    let link = dir.path().join("servo-bus");
    point_link(&link, &chain.device_path());
    let mut bus = DynamixelBus::open(&link, 1_000_000).unwrap().with_response_timeout(budget);
    let player = Player::new(PlayerConfig::default(), joint_specs());
    initialise_bus(&mut bus, &player, &BusConfig::default()).unwrap();
    let executor = Executor::spawn(Box::new(bus), player, LoopSettings::new(CYCLE)).unwrap();
    let rig = Rig { chain, link, executor, _dir: dir };
    rig.wait(|t| t.positions.iter().all(Option::is_some), "first positions");
    rig
}

impl Rig {
    /// Telemetry until `predicate` holds (10 s at most: a loaded host, never a timing assert).
    fn wait(&self, mut predicate: impl FnMut(&Telemetry) -> bool, what: &str) -> Telemetry {
        let deadline = Instant::now() + Duration::from_secs(10);
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.executor.telemetry().recv_timeout(left) {
                Ok(t) if predicate(&t) => return t,
                Ok(_) => {}
                Err(_) => panic!("no telemetry with {what} within 10 s"),
            }
        }
    }

    /// Forget the telemetry queued so far (waits then see only cycles after this call).
    fn drain(&self) {
        while self.executor.telemetry().try_recv().is_ok() {}
    }

    /// The index of the latest cycle reported so far.
    fn latest_cycle(&self) -> u64 {
        let mut latest = self.wait(|_| true, "any cycle").cycle_index;
        while let Ok(t) = self.executor.telemetry().try_recv() {
            latest = t.cycle_index;
        }
        latest
    }

    fn goal_counts(&self) -> Vec<usize> {
        (1..=12).map(|id| self.chain.goal_history(id).len()).collect()
    }

    fn enter(&self, phase: Phase) {
        match phase {
            Phase::Idle => self.executor.set_torque(true).unwrap(),
            Phase::Motion => {
                self.executor.play(motion(0.6, 3.0)).unwrap();
                self.wait(|t| t.goal.is_some() && t.keyframe_index == 0, "a motion cycle");
            }
            Phase::Training => {
                self.executor.set_torque(false).unwrap();
                self.chain.set_present(3, 2300.0); // posed by hand
                self.wait(|t| t.positions[2].is_some_and(|q| q > 0.3), "the posed servo");
                assert!(self.executor.positions().is_ok());
            }
        }
    }

    /// Play a short motion to its end.
    fn play_to_end(&self, what: &str) {
        self.drain();
        self.executor.play(motion(0.1, 0.2)).unwrap_or_else(|e| panic!("{what}: play refused: {e}"));
        let t = self.wait(|t| matches!(t.event, Some(PlayerEvent::Finished { .. } | PlayerEvent::Fault(_))), "the end of the motion");
        assert!(matches!(t.event, Some(PlayerEvent::Finished { .. })), "{what}: {:?}", t.event);
    }
}

fn run_row(row: &Row) {
    for phase in PHASES {
        let cell = format!("{} during {phase:?}", row.name);
        let rig = rig();
        rig.enter(phase);
        let before = rig.latest_cycle();
        (row.inject)(&rig);
        let t = rig.wait(|t| matches!(t.event, Some(PlayerEvent::Fault(_))), "the fault");
        let Some(PlayerEvent::Fault(Fault { servo_id, error, .. })) = &t.event else { unreachable!() };
        // Reported with its servo and reason, by the first cycles that read after the injection.
        assert_eq!(*servo_id, row.servo, "{cell}: {error}");
        assert!((row.reason)(error), "{cell}: reason {error:?}");
        assert!(t.cycle_index <= before + 3, "{cell}: reported at cycle {} after injection at {before}", t.cycle_index);
        assert!(matches!(t.state, PlayerState::Faulted(_)), "{cell}: {:?}", t.state);
        if phase == Phase::Motion {
            // Held in the fault's cycle: the goal sent is the measured pose, not the trajectory's.
            let goal = t.goal.clone().unwrap_or_default();
            if row.recovery != Recovery::Reconnect {
                assert_eq!(goal.len(), 12, "{cell}: a hold in the fault's cycle");
                for (g, p) in goal.iter().zip(&t.positions) {
                    if let (false, Some(p)) = (g.is_nan(), p) {
                        assert!((g - p).abs() < 1e-9, "{cell}: hold {g} vs measured {p}");
                    }
                }
            }
        }
        // No goal written after the hold, nothing starts, nothing is recorded.
        std::thread::sleep(Duration::from_millis(30) + row.backlog); // the hold's sync write has no reply
        let goals = rig.goal_counts();
        for _ in 0..5 {
            rig.wait(|_| true, "later cycles");
        }
        assert!(matches!(rig.executor.play(motion(0.2, 0.2)), Err(ExecutorError::Refused(_))), "{cell}: play while faulted");
        assert!(rig.executor.positions().is_err(), "{cell}: positions while faulted");
        std::thread::sleep(Duration::from_millis(50));
        assert_eq!(rig.goal_counts(), goals, "{cell}: goals written while faulted");

        // Recovery.
        (row.remove)(&rig);
        match row.recovery {
            Recovery::TorqueToggle => {
                std::thread::sleep(BUDGET * 5); // late answers drain
                rig.executor.set_torque(false).unwrap();
                rig.drain();
                rig.wait(|t| t.state == PlayerState::Idle, "idle after clearing");
            }
            Recovery::Reboot => {
                // Clearing alone does not help: the error is still in the servo.
                rig.executor.set_torque(false).unwrap();
                // The cycle that took the command reports Idle, the next one the fault again.
                rig.wait(|t| t.state == PlayerState::Idle, "the cleared cycle");
                rig.wait(|t| matches!(t.event, Some(PlayerEvent::Fault(_))), "the fault again");
                let rebooted = rig.executor.reboot(Vec::new()).unwrap();
                assert_eq!(rebooted, vec![row.servo.unwrap()], "{cell}");
                assert_eq!(rig.chain.snapshot(row.servo.unwrap()).unwrap().hardware_error, 0);
                let refused = rig.executor.play(motion(0.1, 0.2));
                assert!(matches!(&refused, Err(ExecutorError::Refused(m)) if m.contains("set_torque")), "{cell}: {refused:?}");
            }
            Recovery::Reconnect => {
                let path = rig.chain.replug().unwrap();
                point_link(&rig.link, &path);
                assert_eq!(rig.executor.reboot(Vec::new()).unwrap(), Vec::<u8>::new(), "{cell}");
            }
        }
        rig.executor.set_torque(true).unwrap();
        rig.play_to_end(&cell);
    }
}

fn bits(expected: u8) -> impl Fn(&BusError) -> bool {
    move |e| matches!(e, BusError::Hardware { bits, .. } if *bits == expected)
}

macro_rules! hardware_row {
    ($test:ident, $bit:expr, $name:literal) => {
        #[test]
        fn $test() {
            run_row(&Row {
                name: $name,
                inject: |rig| rig.chain.set_hardware_error(7, $bit),
                servo: Some(7),
                reason: |e| bits($bit)(e),
                remove: |_| {},
                backlog: Duration::ZERO,
                recovery: Recovery::Reboot,
            });
        }
    };
}

#[test]
fn silence_of_one_servo() {
    run_row(&Row {
        name: "silent servo 5",
        inject: |rig| {
            rig.chain.set_faults(|f| {
                f.silent.insert(5);
            })
        },
        servo: Some(5),
        reason: |e| matches!(e, BusError::Timeout { id: 5 }),
        remove: |rig| rig.chain.set_faults(|f| f.silent.clear()),
        backlog: Duration::ZERO,
        recovery: Recovery::TorqueToggle,
    });
}

#[test]
fn silence_of_the_whole_chain() {
    run_row(&Row {
        name: "silent chain",
        inject: |rig| rig.chain.set_faults(|f| f.silent_all = true),
        servo: Some(1),
        reason: |e| matches!(e, BusError::Timeout { id: 1 }),
        remove: |rig| rig.chain.set_faults(|f| f.silent_all = false),
        backlog: Duration::ZERO,
        recovery: Recovery::TorqueToggle,
    });
}

#[test]
fn crc_errors() {
    run_row(&Row {
        name: "CRC errors of servo 3",
        inject: |rig| {
            rig.chain.set_faults(|f| {
                f.crc_errors.insert(3);
            })
        },
        servo: Some(3),
        reason: |e| matches!(e, BusError::Checksum { id: 3 }),
        remove: |rig| rig.chain.set_faults(|f| f.crc_errors.clear()),
        backlog: Duration::ZERO,
        recovery: Recovery::TorqueToggle,
    });
}

#[test]
fn malformed_frames() {
    run_row(&Row {
        name: "malformed frames of servo 4",
        inject: |rig| {
            rig.chain.set_faults(|f| {
                f.malformed.insert(4);
            })
        },
        servo: Some(4),
        reason: |e| matches!(e, BusError::Malformed { id: 4, .. }),
        remove: |rig| rig.chain.set_faults(|f| f.malformed.clear()),
        backlog: Duration::ZERO,
        recovery: Recovery::TorqueToggle,
    });
}

#[test]
fn wrong_id_in_the_answer() {
    run_row(&Row {
        name: "servo 6 answering as 200",
        inject: |rig| {
            rig.chain.set_faults(|f| {
                f.wrong_id.insert(6, 200);
            })
        },
        servo: Some(6),
        reason: |e| matches!(e, BusError::Protocol { id: 6, detail } if detail.contains("200")),
        remove: |rig| rig.chain.set_faults(|f| f.wrong_id.clear()),
        backlog: Duration::ZERO,
        recovery: Recovery::TorqueToggle,
    });
}

#[test]
fn latency_beyond_the_answer_budget() {
    run_row(&Row {
        name: "latency 3 x budget",
        inject: |rig| rig.chain.set_faults(|f| f.latency = BUDGET * 3),
        servo: Some(1),
        reason: |e| matches!(e, BusError::Timeout { id: 1 }),
        remove: |rig| rig.chain.set_faults(|f| f.latency = Duration::ZERO),
        backlog: BUDGET * 3 * 3,
        recovery: Recovery::TorqueToggle,
    });
}

#[test]
fn unplug_and_replug_of_the_port() {
    run_row(&Row {
        name: "unplugged port",
        inject: |rig| rig.chain.unplug(),
        servo: None,
        reason: |e| matches!(e, BusError::Io(_)),
        remove: |_| {},
        backlog: Duration::ZERO,
        recovery: Recovery::Reconnect,
    });
}

hardware_row!(hardware_error_input_voltage, mx28::HW_INPUT_VOLTAGE, "input voltage error of servo 7");
hardware_row!(hardware_error_overheating, mx28::HW_OVERHEATING, "overheating of servo 7");
hardware_row!(hardware_error_motor_encoder, mx28::HW_MOTOR_ENCODER, "motor encoder error of servo 7");
hardware_row!(hardware_error_electrical_shock, mx28::HW_ELECTRICAL_SHOCK, "electrical shock of servo 7");
hardware_row!(hardware_error_overload, mx28::HW_OVERLOAD, "overload of servo 7");

/// Answers of 200 ms inside a 500 ms budget: no single transaction fails, but the loop runs at
/// ~5 cycles/s; that is a fault too, held and reported with the rate.
#[test]
fn slow_bus_is_a_fault() {
    for phase in PHASES {
        let rig = rig_with_budget(Duration::from_millis(500));
        rig.enter(phase);
        rig.chain.set_faults(|f| f.latency = Duration::from_millis(200));
        let t = rig.wait(|t| matches!(t.event, Some(PlayerEvent::Fault(_))), "the slow-bus fault");
        let Some(PlayerEvent::Fault(fault)) = &t.event else { unreachable!() };
        let text = fault.error.to_string();
        assert!(matches!(fault.error, BusError::TooSlow { nominal_hz, .. } if nominal_hz == 125.0), "{phase:?}: {text}");
        assert!(text.starts_with("bus too slow: ") && text.contains("cycles/s of 125"), "{text}");
        assert_eq!(fault.servo_id, None);
        let health = rig.executor.health();
        assert!(health.deadline_misses >= 1, "{health:?}");
        rig.chain.set_faults(|f| f.latency = Duration::ZERO);
        std::thread::sleep(Duration::from_millis(500));
        rig.executor.set_torque(false).unwrap();
        rig.drain();
        rig.wait(|t| t.state == PlayerState::Idle, "idle after clearing");
        rig.executor.set_torque(true).unwrap();
        rig.play_to_end(&format!("slow bus during {phase:?}"));
    }
}

/// The brief's case: overheating → play faults at once → reboot → play works.
#[test]
fn overheating_then_reboot_then_play() {
    let rig = rig();
    rig.chain.set_hardware_error(9, mx28::HW_OVERHEATING);
    rig.wait(|t| matches!(t.event, Some(PlayerEvent::Fault(_))), "the overheating fault");
    rig.executor.set_torque(false).unwrap();
    rig.wait(|t| t.state == PlayerState::Idle, "the cleared cycle");
    rig.wait(|t| matches!(t.event, Some(PlayerEvent::Fault(_))), "the fault again: torque off does not clear a hardware error");
    let refused = rig.executor.play(motion(0.1, 0.2));
    assert!(matches!(&refused, Err(ExecutorError::Refused(m)) if m.contains("reboot_servos")), "{refused:?}");
    // Rebooting a servo that is not on the bus is refused, naming it.
    let err = rig.executor.reboot(vec![40]).unwrap_err();
    assert!(err.to_string().contains("servo 40"), "{err}");
    assert_eq!(rig.executor.reboot(vec![9]).unwrap(), vec![9]);
    let snapshot = rig.chain.snapshot(9).unwrap();
    assert_eq!((snapshot.hardware_error, snapshot.torque), (0, false));
    assert!(rig.executor.positions().is_ok(), "positions re-read after the reboot");
    rig.executor.set_torque(true).unwrap();
    rig.play_to_end("after the reboot");
    let health = rig.executor.health();
    assert_eq!(health.servos[8].hardware_error, 0);
    assert_eq!(health.servos[8].last_error, Some(BusError::Hardware { id: 9, bits: mx28::HW_OVERHEATING }));
}

/// Health: vitals are read at a low rate, the cycle statistics are filled.
#[test]
fn bus_health_reports_vitals_and_cycle_statistics() {
    let rig = rig();
    rig.chain.set_faults(|f| {
        f.crc_errors.insert(2);
    });
    rig.wait(|t| matches!(t.event, Some(PlayerEvent::Fault(_))), "the CRC fault");
    rig.chain.set_faults(|f| f.crc_errors.clear());
    rig.executor.set_torque(false).unwrap();
    let deadline = Instant::now() + Duration::from_secs(10);
    let health = loop {
        let health = rig.executor.health();
        if health.servos.iter().all(|s| s.temperature_c.is_some()) && health.cycles > 100 || Instant::now() > deadline {
            break health;
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    assert_eq!(health.servos.len(), 12);
    assert!(health.servos.iter().all(|s| s.temperature_c == Some(32) && s.input_voltage_v == Some(12.0)), "{health:?}");
    assert!(health.servos[1].comm_errors >= 1 && health.servos[0].comm_errors == 0, "{health:?}");
    assert_eq!(health.servos[1].last_error, Some(BusError::Checksum { id: 2 }));
    assert!(health.cycle_rate_hz > 0.0 && health.cycle_period_p50_ms > 0.0 && health.cycle_period_p99_ms >= health.cycle_period_p50_ms);
    assert!(!health.scheduling.is_empty());
}
