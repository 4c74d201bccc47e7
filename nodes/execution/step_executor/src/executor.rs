//! The bus thread: owns the [`ServoBus`] and the [`Player`], runs the 8 ms control cycle on absolute
//! deadlines ([`CycleClock`], `SCHED_FIFO` where permitted), and talks to the rest of the node
//! through channels (commands in, telemetry out, never blocking: telemetry is dropped when the
//! consumer is behind), an atomic e-stop flag (read at the start of every cycle and between its
//! transactions, so a stop waits behind at most one bus transaction), and the bus health
//! ([`BusHealth`], handed over with a try-lock so the cycle never waits for a reader).
//!
//! Faults: every fault the player sees latches (see [`crate::player`]); a bus too slow for the cycle
//! is one too ([`SlowBusDetector`]). Recovery: torque off clears a latched fault; a hardware error
//! needs [`Executor::reboot`] (Protocol 2.0 REBOOT, then positions re-read, torque held off, and a
//! motion plays only after an explicit torque on); a lost port needs [`Executor::reconnect`].
//! A panic inside the bus implementation is already turned into an error by the bus.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, OnceLock};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use crossbeam_channel::{Receiver, Sender};
use patchwalk_dynamixel::priority::{make_realtime, raise_thread_priority, Priority};

use crate::config::{BusConfig, StepExecutorConfig};
use crate::cycle_clock::CycleClock;
use crate::health::{BusHealth, HealthTracker};
use crate::library::Motion;
use crate::player::{CycleReport, Player, PlayerEvent, PlayerState};
use crate::slow_bus::{SlowBusConfig, SlowBusDetector};
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
    Reboot(Vec<u8>, Reply<Vec<u8>>),
    Reconnect(Reply<()>),
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
    /// Commands the bus thread had taken when it sent this (see [`Executor::is_current`]).
    pub commands_taken: u64,
}

/// How the bus thread runs its cycle.
#[derive(Debug, Clone, PartialEq)]
pub struct LoopSettings {
    pub cycle: Duration,
    pub slow_bus: SlowBusConfig,
    /// Vitals (voltage, temperature) read every this many cycles; 0 = never.
    pub health_read_period_cycles: u32,
    /// Longest wait for a servo to answer after REBOOT.
    pub reboot_wait: Duration,
    /// SCHED_FIFO priority; 0 = keep nice -15 only.
    pub realtime_priority: i32,
}

impl LoopSettings {
    /// `cycle` with the configuration's defaults for the rest.
    pub fn new(cycle: Duration) -> Self {
        Self::from_bus(cycle, &BusConfig::default())
    }

    pub fn from_config(config: &StepExecutorConfig) -> Self {
        Self::from_bus(config.player.cycle(), &config.bus)
    }

    fn from_bus(cycle: Duration, bus: &BusConfig) -> Self {
        Self {
            cycle,
            slow_bus: bus.slow_bus.clone(),
            health_read_period_cycles: bus.health_read_period_cycles,
            reboot_wait: Duration::from_secs_f64(bus.reboot_wait_ms / 1000.0),
            realtime_priority: bus.realtime_priority,
        }
    }
}

/// Handle of the running bus thread.
pub struct Executor {
    commands: Sender<Command>,
    telemetry: Receiver<Telemetry>,
    estop: Arc<AtomicBool>,
    shutdown: Arc<AtomicBool>,
    notify: Arc<OnceLock<Notify>>,
    health: Arc<Mutex<BusHealth>>,
    reply_timeout: Duration,
    /// Sequence number of the last command sent (the bus thread takes them in this order).
    commands_sent: AtomicU64,
    /// Sequence number of the last command whose reply came back.
    commands_answered: AtomicU64,
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
    pub fn spawn(bus: Box<dyn ServoBus>, player: Player, settings: LoopSettings) -> Result<Self, ExecutorError> {
        let (command_tx, command_rx) = crossbeam_channel::unbounded::<Command>();
        let (telemetry_tx, telemetry_rx) = crossbeam_channel::bounded::<Telemetry>(1024);
        let estop = Arc::new(AtomicBool::new(false));
        let shutdown = Arc::new(AtomicBool::new(false));
        let notify: Arc<OnceLock<Notify>> = Arc::new(OnceLock::new());
        let tracker = HealthTracker::new(&player.ids(), settings.cycle);
        let health = Arc::new(Mutex::new(tracker.health.clone()));
        // A reboot waits for the servos to boot: the reply may take that long.
        let reply_timeout = Duration::from_secs(2) + settings.reboot_wait * 2;
        let bus_loop = BusLoop {
            bus,
            player,
            torque: false,
            needs_torque_on: false,
            detector: SlowBusDetector::new(settings.slow_bus.clone(), settings.cycle),
            tracker,
            settings,
            estop: Arc::clone(&estop),
            shutdown: Arc::clone(&shutdown),
            notify: Arc::clone(&notify),
            health: Arc::clone(&health),
            commands: command_rx,
            commands_taken: 0,
            telemetry: telemetry_tx,
        };
        let thread = std::thread::Builder::new()
            .name("servo-bus".into())
            .spawn(move || bus_loop.run())
            .map_err(|e| ExecutorError::Refused(format!("cannot start the bus thread: {e}")))?;
        Ok(Self {
            commands: command_tx,
            telemetry: telemetry_rx,
            estop,
            shutdown,
            notify,
            health,
            reply_timeout,
            commands_sent: AtomicU64::new(0),
            commands_answered: AtomicU64::new(0),
            thread: Some(thread),
        })
    }

    /// Request an e-stop (honoured at the start of the next cycle, or between the transactions of
    /// the current one).
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

    /// Whether `telemetry` was sent after the bus thread took every command answered so far. Older
    /// telemetry, still queued when a reply comes back, shows the state from before that command
    /// (e.g. idle just after a `play` was answered): its positions are measurements all the same,
    /// but its state, torque and keyframe are out of date.
    pub fn is_current(&self, telemetry: &Telemetry) -> bool {
        telemetry.commands_taken >= self.commands_answered.load(Ordering::SeqCst)
    }

    /// The bus health as of the last update (every `bus.health_read_period_cycles` cycles, at
    /// least every 25).
    pub fn health(&self) -> BusHealth {
        self.health.lock().unwrap_or_else(|poisoned| poisoned.into_inner()).clone()
    }

    fn request<T>(&self, make: impl FnOnce(Reply<T>) -> Command) -> Result<T, ExecutorError> {
        let (tx, rx) = crossbeam_channel::bounded(1);
        let sequence = self.commands_sent.fetch_add(1, Ordering::SeqCst) + 1;
        self.commands.send(make(tx)).map_err(|_| ExecutorError::Stopped)?;
        let reply = rx.recv_timeout(self.reply_timeout).map_err(|_| ExecutorError::Stopped)?;
        self.commands_answered.fetch_max(sequence, Ordering::SeqCst);
        reply
    }

    /// Start a motion (torque is enabled first if needed; limits are checked before anything moves).
    /// Refused while faulted, and after a reboot until torque is switched on explicitly.
    pub fn play(&self, motion: Motion) -> Result<(), ExecutorError> {
        self.request(|reply| Command::Play(Box::new(motion), reply))
    }

    /// Torque on (goal latched to the present pose) or off (compliant posing; clears a latched fault).
    pub fn set_torque(&self, on: bool) -> Result<(), ExecutorError> {
        self.request(|reply| Command::SetTorque(on, reply))
    }

    /// Present positions of all joints (rad), e.g. to record a keyframe; refused while faulted.
    pub fn positions(&self) -> Result<Vec<f64>, ExecutorError> {
        self.request(Command::Positions)
    }

    /// REBOOT servos `ids` (empty: the faulted ones), wait until they answer, torque off on all,
    /// re-read the positions, clear the fault. Refused while a motion plays. When the fault is a
    /// lost port, the port is reopened first (and with no ids and no hardware error, that is all).
    /// Returns the ids rebooted.
    pub fn reboot(&self, ids: Vec<u8>) -> Result<Vec<u8>, ExecutorError> {
        self.request(|reply| Command::Reboot(ids, reply))
    }

    /// Reopen the bus's port (it was unplugged and is back), re-read the positions, torque off on
    /// all, clear the fault. Refused while a motion plays.
    pub fn reconnect(&self) -> Result<(), ExecutorError> {
        self.request(Command::Reconnect)
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

/// Everything the bus thread owns.
struct BusLoop {
    bus: Box<dyn ServoBus>,
    player: Player,
    torque: bool,
    /// Set by a reboot or reconnect: a motion plays only after an explicit torque on.
    needs_torque_on: bool,
    detector: SlowBusDetector,
    tracker: HealthTracker,
    settings: LoopSettings,
    estop: Arc<AtomicBool>,
    shutdown: Arc<AtomicBool>,
    notify: Arc<OnceLock<Notify>>,
    health: Arc<Mutex<BusHealth>>,
    commands: Receiver<Command>,
    /// Commands taken so far (sent with every telemetry).
    commands_taken: u64,
    telemetry: Sender<Telemetry>,
}

/// How often the health summary is handed over when vitals are not read more often.
const HEALTH_PUBLISH_CYCLES: u64 = 25;

impl BusLoop {
    fn run(mut self) {
        let priority = if self.settings.realtime_priority > 0 {
            make_realtime(self.settings.realtime_priority)
        } else if raise_thread_priority() {
            Priority::Nice
        } else {
            Priority::Unchanged
        };
        match priority {
            Priority::Fifo(_) => tracing::info!("servo bus thread: {priority}"),
            _ => tracing::warn!("servo bus thread: {priority}"),
        }
        self.tracker.health.scheduling = priority.to_string();
        let mut clock = CycleClock::start(self.settings.cycle);
        let mut cycle_index = 0u64;
        let mut previous_start: Option<Instant> = None;
        while !self.shutdown.load(Ordering::SeqCst) {
            let started = Instant::now();
            let estop = self.estop.swap(false, Ordering::SeqCst);
            let flag = Arc::clone(&self.estop);
            let mut report = self.player.cycle_with_stop(self.bus.as_mut(), estop, &mut || flag.swap(false, Ordering::SeqCst));
            self.tracker.read(self.player.last_errors());
            let busy = started.elapsed();
            if matches!(self.player.state(), PlayerState::Faulted(_)) {
                // Latched already (a silent servo makes every cycle slow): count afresh once cleared.
                self.detector.reset();
            } else if let Some(fault) = self.detector.observe(started, busy) {
                if let Some(faulted) = self.player.fault_external(self.bus.as_mut(), fault) {
                    report = CycleReport { goal: faulted.goal.or(report.goal), present: faulted.present, event: faulted.event };
                }
            }
            let mut blocked = false;
            while let Ok(command) = self.commands.try_recv() {
                self.commands_taken += 1;
                blocked |= self.handle(command);
            }
            if blocked {
                self.detector.reset();
            }
            // Vitals at a low rate, only with time left in the cycle, no stop pending and a bus that answers.
            let period = u64::from(self.settings.health_read_period_cycles);
            let healthy_read = self.player.last_errors().iter().all(Option::is_none);
            if period > 0
                && cycle_index % period == 0
                && healthy_read
                && !self.estop.load(Ordering::SeqCst)
                && started.elapsed() < self.settings.cycle / 2
            {
                self.read_vitals();
            }
            let busy = started.elapsed();
            self.tracker.cycle(previous_start.map(|p| started.saturating_duration_since(p)), busy, busy > self.settings.cycle);
            previous_start = Some(started);
            // Every 25 cycles, and every overrun (a slow bus is seen at once, not 25 slow cycles later).
            if cycle_index % HEALTH_PUBLISH_CYCLES == 0 || (period > 0 && cycle_index % period == 0) || busy > self.settings.cycle {
                self.publish_health();
            }
            let telemetry = Telemetry {
                started,
                busy,
                cycle_index,
                keyframe_index: self.player.keyframe_index(),
                positions: report.present,
                goal: report.goal,
                state: self.player.state().clone(),
                torque: self.torque,
                event: report.event,
                commands_taken: self.commands_taken,
            };
            let urgent = telemetry.goal.is_some() || telemetry.event.is_some();
            // Never block the control loop on a slow consumer: drop telemetry instead.
            let _ = self.telemetry.try_send(telemetry);
            if let (true, Some(notify)) = (urgent, self.notify.get()) {
                notify();
            }
            cycle_index += 1;
            clock.wait();
        }
    }

    /// Present Input Voltage and Temperature (144..=146) of every servo in one sync read.
    fn read_vitals(&mut self) {
        let ids = self.player.ids();
        match self.bus.sync_read(&ids, mx28::PRESENT_INPUT_VOLTAGE, 3) {
            Ok(results) => {
                for (id, result) in results {
                    self.tracker.vitals(id, &result.map(|r| r.data));
                }
            }
            Err(e) => {
                for id in ids {
                    self.tracker.vitals(id, &Err(e.clone()));
                }
            }
        }
    }

    /// Hand the health over unless a reader holds it right now (then the next update does).
    fn publish_health(&mut self) {
        self.tracker.summarise();
        if let Ok(mut shared) = self.health.try_lock() {
            shared.clone_from(&self.tracker.health);
        }
    }

    /// One command; returns whether the slow-bus check should start afresh (the loop was blocked on
    /// purpose, e.g. a reboot's wait, or a fault was cleared).
    fn handle(&mut self, command: Command) -> bool {
        let (bus, player) = (self.bus.as_mut(), &mut self.player);
        match command {
            Command::Play(motion, reply) => {
                let result = (|| {
                    if let PlayerState::Faulted(fault) = player.state() {
                        let how = if matches!(fault.error, BusError::Hardware { .. }) {
                            "a hardware error needs reboot_servos, then set_torque true"
                        } else {
                            "toggle torque to clear"
                        };
                        return Err(ExecutorError::Refused(format!("faulted ({fault}); {how}")));
                    }
                    if self.needs_torque_on {
                        return Err(ExecutorError::Refused(
                            "the servos were rebooted or reconnected with torque off: call set_torque true first".into(),
                        ));
                    }
                    if !self.torque {
                        enable_torque(bus, player)?;
                        self.torque = true;
                    }
                    player.start(&motion).map(|_| ()).map_err(|e| ExecutorError::Refused(e.to_string()))
                })();
                let _ = reply.send(result);
                false
            }
            Command::SetTorque(on, reply) => {
                let result = if on {
                    enable_torque(bus, player)
                } else {
                    servo_bus::sync_write_u8(bus, mx28::TORQUE_ENABLE, &all_ids(player, 0)).map_err(ExecutorError::Bus)
                };
                if result.is_ok() {
                    self.torque = on;
                    if on {
                        self.needs_torque_on = false;
                    }
                    if !on || !matches!(player.state(), PlayerState::Playing { .. }) {
                        player.reset();
                    }
                }
                let _ = reply.send(result);
                true
            }
            Command::Positions(reply) => {
                let positions: Option<Vec<f64>> = player.last_present().iter().copied().collect();
                let result = match (player.state(), positions) {
                    (PlayerState::Faulted(fault), _) => Err(ExecutorError::Refused(format!("positions not current: {fault}"))),
                    (_, Some(p)) => Ok(p),
                    (_, None) => Err(ExecutorError::Refused("positions not read yet".into())),
                };
                let _ = reply.send(result);
                false
            }
            Command::Reboot(ids, reply) => {
                let result = self.reboot(ids);
                let _ = reply.send(result);
                true
            }
            Command::Reconnect(reply) => {
                let result = self.reconnect();
                let _ = reply.send(result);
                true
            }
        }
    }

    fn refuse_while_playing(&self, what: &str) -> Result<(), ExecutorError> {
        if matches!(self.player.state(), PlayerState::Playing { .. }) {
            return Err(ExecutorError::Refused(format!("{what} refused while a motion plays (stop it first)")));
        }
        Ok(())
    }

    fn servo_error(&self, id: u8, error: BusError) -> ExecutorError {
        let joint = self.player.joints().iter().find(|j| j.servo.id == id).map(|j| j.servo.joint.clone()).unwrap_or_default();
        ExecutorError::Servo { id, joint, error }
    }

    /// After a reboot or reconnect: torque off on every servo, positions re-read, fault cleared;
    /// a motion needs an explicit torque on.
    fn settle(&mut self) -> Result<(), ExecutorError> {
        servo_bus::sync_write_u8(self.bus.as_mut(), mx28::TORQUE_ENABLE, &all_ids(&self.player, 0)).map_err(ExecutorError::Bus)?;
        self.torque = false;
        self.needs_torque_on = true;
        self.player.reset();
        if let Err(error) = self.player.refresh(self.bus.as_mut()) {
            return Err(match error.servo_id() {
                Some(id) => self.servo_error(id, error),
                None => ExecutorError::Bus(error),
            });
        }
        Ok(())
    }

    fn reboot(&mut self, ids: Vec<u8>) -> Result<Vec<u8>, ExecutorError> {
        self.refuse_while_playing("reboot")?;
        // A lost port is reopened first: nothing can be rebooted through a dead port.
        let lost_port = matches!(self.player.state(), PlayerState::Faulted(fault) if matches!(fault.error, BusError::Io(_)));
        if lost_port {
            self.bus.reconnect().map_err(ExecutorError::Bus)?;
            if ids.is_empty() && self.tracker.hardware_faulted().next().is_none() {
                self.settle()?;
                return Ok(Vec::new());
            }
        }
        let known = self.player.ids();
        if let Some(bad) = ids.iter().find(|id| !known.contains(id)) {
            return Err(ExecutorError::Refused(format!("servo {bad} is not on this bus (ids {known:?})")));
        }
        let mut targets = ids;
        if targets.is_empty() {
            if let PlayerState::Faulted(fault) = self.player.state() {
                targets.extend(fault.servo_id);
            }
            targets.extend(self.tracker.hardware_faulted());
            targets.sort_unstable();
            targets.dedup();
        }
        if targets.is_empty() {
            return Err(ExecutorError::Refused("no faulted servo to reboot: name the ids".into()));
        }
        for &id in &targets {
            self.bus.reboot(id).map_err(|e| self.servo_error(id, e))?;
        }
        // Each servo is silent while it boots: wait until every one answers a ping.
        let deadline = Instant::now() + self.settings.reboot_wait;
        for &id in &targets {
            loop {
                match self.bus.ping(id) {
                    Ok(_) => break,
                    Err(e) if Instant::now() >= deadline => return Err(self.servo_error(id, e)),
                    Err(_) => std::thread::sleep(self.settings.cycle),
                }
            }
            self.tracker.rebooted(id);
        }
        self.settle()?;
        Ok(targets)
    }

    fn reconnect(&mut self) -> Result<(), ExecutorError> {
        self.refuse_while_playing("reconnect")?;
        self.bus.reconnect().map_err(ExecutorError::Bus)?;
        self.settle()
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

    /// A motion of one 2 s keyframe to 0.5 rad on every joint.
    fn slow_motion(joints: usize) -> Motion {
        Motion {
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
            keyframes: vec![Keyframe { positions: vec![0.5; joints], move_s: 2.0, pause_s: 0.0 }],
        }
    }

    #[test]
    fn play_estop_and_torque_through_the_bus_thread() {
        let bus = MockBus::new(&[1, 2, 3]);
        bus.state().max_step_ticks = 2;
        let executor = Executor::spawn(Box::new(bus.clone()), player(3), LoopSettings::new(Duration::from_millis(2))).unwrap();
        wait_for(&executor, |t| t.positions.iter().all(Option::is_some));
        assert_eq!(executor.positions().unwrap(), vec![0.0; 3]);
        let motion = slow_motion(3);
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

    /// Cycles queued while nobody read them still say idle when a `play` is answered: they are not
    /// current, and every cycle after the answer is (and plays).
    #[test]
    fn telemetry_queued_before_an_answered_command_is_not_current() {
        let bus = MockBus::new(&[1, 2, 3]);
        bus.state().max_step_ticks = 2;
        let executor = Executor::spawn(Box::new(bus), player(3), LoopSettings::new(Duration::from_millis(2))).unwrap();
        wait_for(&executor, |t| t.positions.iter().all(Option::is_some));
        std::thread::sleep(Duration::from_millis(40));
        executor.play(slow_motion(3)).unwrap();
        let queued: Vec<Telemetry> = executor.telemetry().try_iter().collect();
        let stale: Vec<&Telemetry> = queued.iter().filter(|t| !executor.is_current(t)).collect();
        assert!(!stale.is_empty(), "40 ms of 2 ms cycles were queued before the play");
        assert!(stale.iter().all(|t| t.state == PlayerState::Idle), "{:?}", stale.iter().map(|t| &t.state).collect::<Vec<_>>());
        let stale_count = stale.len();
        assert!(queued.iter().skip(stale_count).all(|t| executor.is_current(t)), "the stale cycles come first");
        let next = wait_for(&executor, |_| true);
        assert!(executor.is_current(&next));
        assert!(matches!(next.state, PlayerState::Playing { .. }), "{:?}", next.state);
        assert!(queued.iter().chain([&next]).filter(|t| executor.is_current(t)).all(|t| matches!(t.state, PlayerState::Playing { .. })));
    }
}
