//! The bus thread: owns the [`ServoBus`] and the [`Player`], runs the 8 ms control cycle on absolute
//! deadlines, and talks to the rest of the node through channels (commands in, telemetry out) and an
//! atomic e-stop flag (read at the start of every cycle, so a stop is honoured within one cycle).
//! A panic inside the bus implementation is already turned into an error by the bus; this thread
//! additionally isolates the node from any bus stall.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, OnceLock};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use crossbeam_channel::{Receiver, Sender};
use patchwalk_dynamixel::priority::raise_thread_priority;

use crate::config::BusConfig;
use crate::library::Motion;
use crate::player::{Player, PlayerEvent, PlayerState};
use patchwalk_dynamixel::mx28;
use patchwalk_dynamixel::servo_bus::{self, BusError, ServoBus};

/// Errors of executor commands.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ExecutorError {
    #[error("servo {id} ({joint}): {error}")]
    Servo { id: u8, joint: String, error: BusError },
    #[error("servo {id} reports model {model}, expected {expected}")]
    WrongModel { id: u8, model: u16, expected: u16 },
    #[error("bus: {0}")]
    Bus(BusError),
    #[error("{0}")]
    Refused(String),
    #[error("the bus thread has stopped")]
    Stopped,
}

type Reply<T> = Sender<Result<T, ExecutorError>>;

enum Command {
    Play(Box<Motion>, Reply<()>),
    SetTorque(bool, Reply<()>),
    Positions(Reply<Vec<f64>>),
}

/// One control cycle as seen from outside.
#[derive(Debug, Clone)]
pub struct Telemetry {
    /// When the cycle started (deadline-scheduled every `cycle`).
    pub started: Instant,
    /// Time the cycle's bus traffic took.
    pub busy: Duration,
    pub cycle_index: u64,
    /// Keyframe being played (0 when idle).
    pub keyframe_index: usize,
    /// Measured joint positions (rad, joint order) where known.
    pub positions: Vec<Option<f64>>,
    pub goal: Option<Vec<f64>>,
    pub state: PlayerState,
    pub torque: bool,
    pub event: Option<PlayerEvent>,
}

/// Handle of the running bus thread.
pub struct Executor {
    commands: Sender<Command>,
    telemetry: Receiver<Telemetry>,
    estop: Arc<AtomicBool>,
    shutdown: Arc<AtomicBool>,
    notify: Arc<OnceLock<Notify>>,
    thread: Option<JoinHandle<()>>,
}

/// Called by the bus thread after a cycle that the node should publish at once (a motion cycle or
/// an event): wakes the node's loop.
pub type Notify = Box<dyn Fn() + Send + Sync>;

/// Start-up sequence: ping every servo (model check), torque off, write the Return Delay Time.
pub fn initialise_bus(bus: &mut dyn ServoBus, player: &Player, config: &BusConfig) -> Result<(), ExecutorError> {
    let delay_register = u8::try_from(config.return_delay_us / 2).unwrap_or(u8::MAX).min(254);
    for joint in player.joints() {
        let id = joint.servo.id;
        let servo = |error| ExecutorError::Servo { id, joint: joint.servo.joint.clone(), error };
        let model = bus.ping(id).map_err(servo)?;
        if model != config.expected_model {
            return Err(ExecutorError::WrongModel { id, model, expected: config.expected_model });
        }
        bus.write(id, mx28::TORQUE_ENABLE, &[0]).map_err(servo)?;
        bus.write(id, mx28::RETURN_DELAY_TIME, &[delay_register]).map_err(servo)?;
    }
    Ok(())
}

impl Executor {
    /// Spawn the bus thread. `bus` must already be initialised (see [`initialise_bus`]).
    pub fn spawn(mut bus: Box<dyn ServoBus>, mut player: Player, cycle: Duration) -> Result<Self, ExecutorError> {
        let (command_tx, command_rx) = crossbeam_channel::unbounded::<Command>();
        let (telemetry_tx, telemetry_rx) = crossbeam_channel::bounded::<Telemetry>(1024);
        let estop = Arc::new(AtomicBool::new(false));
        let shutdown = Arc::new(AtomicBool::new(false));
        let thread_estop = Arc::clone(&estop);
        let thread_shutdown = Arc::clone(&shutdown);
        let notify: Arc<OnceLock<Notify>> = Arc::new(OnceLock::new());
        let thread_notify = Arc::clone(&notify);
        let thread = std::thread::Builder::new()
            .name("servo-bus".into())
            .spawn(move || {
                raise_thread_priority();
                let mut torque = false;
                let mut next = Instant::now();
                let mut cycle_index = 0u64;
                while !thread_shutdown.load(Ordering::SeqCst) {
                    let started = Instant::now();
                    let estop = thread_estop.swap(false, Ordering::SeqCst);
                    let report = player.cycle(bus.as_mut(), estop);
                    while let Ok(command) = command_rx.try_recv() {
                        handle(command, bus.as_mut(), &mut player, &mut torque);
                    }
                    let telemetry = Telemetry {
                        started,
                        busy: started.elapsed(),
                        cycle_index,
                        keyframe_index: player.keyframe_index(),
                        positions: report.present,
                        goal: report.goal,
                        state: player.state().clone(),
                        torque,
                        event: report.event,
                    };
                    let urgent = telemetry.goal.is_some() || telemetry.event.is_some();
                    // Never block the control loop on a slow consumer: drop telemetry instead.
                    let _ = telemetry_tx.try_send(telemetry);
                    if let (true, Some(notify)) = (urgent, thread_notify.get()) {
                        notify();
                    }
                    cycle_index += 1;
                    next += cycle;
                    let now = Instant::now();
                    if next > now {
                        std::thread::sleep(next - now);
                    } else {
                        next = now; // overrun: restart the schedule instead of bursting
                    }
                }
            })
            .map_err(|e| ExecutorError::Refused(format!("cannot start the bus thread: {e}")))?;
        Ok(Self { commands: command_tx, telemetry: telemetry_rx, estop, shutdown, notify, thread: Some(thread) })
    }

    /// Request an e-stop (honoured at the start of the next cycle).
    pub fn estop(&self) {
        self.estop.store(true, Ordering::SeqCst);
    }

    /// Have the bus thread call `notify` after every cycle of a motion and after every event (set
    /// once; later calls are ignored).
    pub fn set_notify(&self, notify: Notify) {
        let _ = self.notify.set(notify);
    }

    /// Telemetry of the cycles since the last call.
    pub fn telemetry(&self) -> &Receiver<Telemetry> {
        &self.telemetry
    }

    fn request<T>(&self, make: impl FnOnce(Reply<T>) -> Command) -> Result<T, ExecutorError> {
        let (tx, rx) = crossbeam_channel::bounded(1);
        self.commands.send(make(tx)).map_err(|_| ExecutorError::Stopped)?;
        rx.recv_timeout(Duration::from_secs(2)).map_err(|_| ExecutorError::Stopped)?
    }

    /// Start a motion (torque is enabled first if needed; limits are checked before anything moves).
    pub fn play(&self, motion: Motion) -> Result<(), ExecutorError> {
        self.request(|reply| Command::Play(Box::new(motion), reply))
    }

    /// Torque on (goal latched to the present pose) or off (compliant posing; clears a latched fault).
    pub fn set_torque(&self, on: bool) -> Result<(), ExecutorError> {
        self.request(|reply| Command::SetTorque(on, reply))
    }

    /// Present positions of all joints (rad), e.g. to record a keyframe.
    pub fn positions(&self) -> Result<Vec<f64>, ExecutorError> {
        self.request(Command::Positions)
    }
}

impl Drop for Executor {
    fn drop(&mut self) {
        self.shutdown.store(true, Ordering::SeqCst);
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

fn all_ids(player: &Player, value: u8) -> Vec<(u8, u8)> {
    player.ids().into_iter().map(|id| (id, value)).collect()
}

fn enable_torque(bus: &mut dyn ServoBus, player: &Player) -> Result<(), ExecutorError> {
    // Latch the goal to the measured pose first so nothing jumps when torque comes on.
    let goals: Vec<(u8, u32)> = player
        .joints()
        .iter()
        .zip(player.last_present())
        .filter_map(|(j, p)| p.map(|q| (j.servo.id, j.servo.ticks_from_joint(q).round().clamp(0.0, 4095.0) as u32)))
        .collect();
    if goals.len() != player.joints().len() {
        return Err(ExecutorError::Refused("cannot enable torque: not every servo position is known".into()));
    }
    servo_bus::sync_write_u32(bus, mx28::GOAL_POSITION, &goals).map_err(ExecutorError::Bus)?;
    servo_bus::sync_write_u8(bus, mx28::TORQUE_ENABLE, &all_ids(player, 1)).map_err(ExecutorError::Bus)
}

fn handle(command: Command, bus: &mut dyn ServoBus, player: &mut Player, torque: &mut bool) {
    match command {
        Command::Play(motion, reply) => {
            let result = (|| {
                if let PlayerState::Faulted(fault) = player.state() {
                    return Err(ExecutorError::Refused(format!("faulted ({fault}); toggle torque to clear")));
                }
                if !*torque {
                    enable_torque(bus, player)?;
                    *torque = true;
                }
                player.start(&motion).map(|_| ()).map_err(|e| ExecutorError::Refused(e.to_string()))
            })();
            let _ = reply.send(result);
        }
        Command::SetTorque(on, reply) => {
            let result = if on {
                enable_torque(bus, player)
            } else {
                servo_bus::sync_write_u8(bus, mx28::TORQUE_ENABLE, &all_ids(player, 0)).map_err(ExecutorError::Bus)
            };
            if result.is_ok() {
                *torque = on;
                if !on || !matches!(player.state(), PlayerState::Playing { .. }) {
                    player.reset();
                }
            }
            let _ = reply.send(result);
        }
        Command::Positions(reply) => {
            let positions: Option<Vec<f64>> = player.last_present().iter().copied().collect();
            let result = match (positions, player.state()) {
                (Some(p), _) => Ok(p),
                (None, PlayerState::Faulted(fault)) => Err(ExecutorError::Refused(format!("positions unknown: {fault}"))),
                (None, _) => Err(ExecutorError::Refused("positions not read yet".into())),
            };
            let _ = reply.send(result);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::ServoConfig;
    use crate::library::Keyframe;
    use crate::player::{JointSpec, PlayerConfig};
    use patchwalk_dynamixel::servo_bus::mock::MockBus;
    use patchwalk_robot_model::kinematics::JointLimits;
    use patchwalk_spl::patch::{BoundaryType, Patch, SurfaceType};

    fn player(n: u8) -> Player {
        let joints = (1..=n)
            .map(|id| JointSpec {
                servo: ServoConfig { joint: format!("j{id}"), id, zero_offset: 0.0, direction: 1 },
                limits: JointLimits { lower: -1.0, upper: 1.0 },
            })
            .collect();
        Player::new(PlayerConfig::default(), joints)
    }

    fn wait_for(executor: &Executor, mut predicate: impl FnMut(&Telemetry) -> bool) -> Telemetry {
        loop {
            let t = executor.telemetry().recv_timeout(Duration::from_secs(5)).unwrap();
            if predicate(&t) {
                return t;
            }
        }
    }

    #[test]
    fn initialise_checks_model_and_writes_return_delay() {
        let mut bus = MockBus::new(&[1, 2]);
        initialise_bus(&mut bus, &player(2), &BusConfig::default()).unwrap();
        let mut missing = MockBus::new(&[1]);
        let err = initialise_bus(&mut missing, &player(2), &BusConfig::default()).unwrap_err();
        assert!(matches!(err, ExecutorError::Servo { id: 2, .. }), "{err}");
    }

    #[test]
    fn play_estop_and_torque_through_the_bus_thread() {
        let bus = MockBus::new(&[1, 2, 3]);
        bus.state().max_step_ticks = 2;
        let executor = Executor::spawn(Box::new(bus.clone()), player(3), Duration::from_millis(2)).unwrap();
        wait_for(&executor, |t| t.positions.iter().all(Option::is_some));
        assert_eq!(executor.positions().unwrap(), vec![0.0; 3]);
        let motion = Motion {
            name: "m".into(),
            patch: Patch::new(
                SurfaceType::Plane,
                BoundaryType::Circle,
                vec![0.02],
                nalgebra::Vector2::zeros(),
                nalgebra::Vector3::zeros(),
                nalgebra::Vector3::zeros(),
            )
            .unwrap(),
            keyframes: vec![Keyframe { positions: vec![0.5; 3], move_s: 2.0, pause_s: 0.0 }],
        };
        executor.play(motion.clone()).unwrap();
        wait_for(&executor, |t| t.torque && matches!(t.state, PlayerState::Playing { .. }));
        executor.estop();
        let stopped = wait_for(&executor, |t| t.event.is_some());
        assert_eq!(stopped.event, Some(PlayerEvent::EStopped));
        // Out-of-limit motions are refused before anything moves.
        let mut bad = motion.clone();
        bad.keyframes[0].positions[1] = 2.0;
        assert!(matches!(executor.play(bad), Err(ExecutorError::Refused(_))));
        executor.set_torque(false).unwrap();
        assert!(bus.state().servos.values().all(|s| !s.torque));
    }
}
