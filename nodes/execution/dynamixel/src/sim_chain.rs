//! A simulated chain of MX-28 servos speaking Dynamixel Protocol 2.0 at the byte level on a pty pair,
//! so the real master code (dynamixel2, the ROBOTIS SDK, any Dynamixel tool) talks to it through the
//! slave device path. Implements ping (unicast and broadcast), read, write, sync read, sync write and
//! reboot over the MX-28(2.0) control table (model 30) with its semantics: EEPROM (addresses < 64)
//! locked while torque is on, read-only fields, goal limited to the position limits, Status Return
//! Level, Return Delay Time, and Present Position moving toward Goal Position at the profile velocity
//! (or the velocity limit, 230 × 0.229 rpm ≈ 53 rpm, the MX-28's no-load speed) while torque is on.
//! Wire time at the configured baud rate is simulated. Faults can be injected at run time: silence
//! (per servo or the whole chain), corrupted CRCs, hardware error bits (alert bit set, torque off as
//! with the Shutdown register), extra latency, answers carrying another servo's id, and unplugging
//! the device ([`SimChain::unplug`]: the pty closes, the master's I/O fails) and plugging it back
//! ([`SimChain::replug`]: a new pty, the servos as they were). REBOOT clears a servo's hardware
//! error and torque; the servo is then silent for [`SimConfig::boot_time`] before it answers again.

use std::collections::{BTreeMap, BTreeSet};
use std::os::fd::{AsFd, OwnedFd};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use crate::mx28;
use crate::protocol::{self, instruction, status_error, Packet, PacketParser};

/// Errors starting the simulated chain.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    #[error("cannot create pty: {0}")]
    Pty(String),
    #[error("invalid servo id {0} (1..=252)")]
    InvalidId(u8),
}

/// Runtime-injectable faults.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Faults {
    /// The whole chain stops answering.
    pub silent_all: bool,
    /// These servos stop answering.
    pub silent: BTreeSet<u8>,
    /// These servos answer with a corrupted CRC.
    pub crc_errors: BTreeSet<u8>,
    /// Extra delay before every response.
    pub latency: Duration,
    /// These servos answer with a malformed frame whose LEN field (2) is shorter than any status
    /// packet, with a valid CRC (a corrupted/echoed frame; it panics dynamixel2 0.9.1's parser).
    pub malformed: BTreeSet<u8>,
    /// These servos answer with another id in their status packets (servo → id it claims).
    pub wrong_id: BTreeMap<u8, u8>,
}

/// Chain configuration.
#[derive(Debug, Clone, PartialEq)]
pub struct SimConfig {
    /// Servo IDs on the chain.
    pub ids: Vec<u8>,
    /// Baud rate used for wire-time simulation (the pty itself has no baud rate).
    pub baud: u32,
    /// Simulate the wire time of responses at `baud`.
    pub simulate_wire_time: bool,
    /// Initial Return Delay Time register (2 µs units); factory default 250 (500 µs).
    pub return_delay_register: u8,
    /// How long a servo is silent after REBOOT.
    pub boot_time: Duration,
}

impl SimConfig {
    /// `n` servos with IDs 1..=n at 1 Mbps, factory return delay.
    pub fn with_servos(n: u8) -> Self {
        Self { ids: (1..=n).collect(), baud: 1_000_000, simulate_wire_time: true, return_delay_register: 250, boot_time: DEFAULT_BOOT_TIME }
    }
}

/// SCHED_FIFO priority of the chain's thread (below the control loop's; nice -15 where refused).
const SIM_PRIORITY: i32 = 40;

/// Boot time after REBOOT of the simulated servos.
pub const DEFAULT_BOOT_TIME: Duration = Duration::from_millis(100);

/// Snapshot of one simulated servo.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ServoSnapshot {
    pub id: u8,
    pub present: f64,
    pub goal: i32,
    pub torque: bool,
    pub hardware_error: u8,
}

#[derive(Debug, Clone)]
struct SimServo {
    table: [u8; mx28::TABLE_SIZE],
    /// Present position with sub-tick precision.
    present: f64,
    /// Goal positions received while torque is on (for tests: the servo "passes through" keyframes).
    goal_history: Vec<i32>,
    /// Silent until then after a REBOOT.
    booting_until: Option<Instant>,
}

impl SimServo {
    fn new(id: u8, return_delay: u8, present: f64) -> Self {
        let mut table = [0u8; mx28::TABLE_SIZE];
        for field in mx28::FIELDS {
            let bytes = field.default.to_le_bytes();
            let start = usize::from(field.address);
            table[start..start + usize::from(field.size)].copy_from_slice(&bytes[..usize::from(field.size)]);
        }
        table[usize::from(mx28::ID)] = id;
        table[usize::from(mx28::RETURN_DELAY_TIME)] = return_delay;
        let mut servo = Self { table, present, goal_history: Vec::new(), booting_until: None };
        servo.set_u32(mx28::GOAL_POSITION, present.round() as u32);
        servo.sync_present(0.0);
        servo
    }

    fn u8_at(&self, address: u16) -> u8 {
        self.table[usize::from(address)]
    }

    fn u32_at(&self, address: u16) -> u32 {
        let a = usize::from(address);
        u32::from_le_bytes([self.table[a], self.table[a + 1], self.table[a + 2], self.table[a + 3]])
    }

    fn set_u32(&mut self, address: u16, value: u32) {
        let a = usize::from(address);
        self.table[a..a + 4].copy_from_slice(&value.to_le_bytes());
    }

    fn id(&self) -> u8 {
        self.u8_at(mx28::ID)
    }

    fn torque(&self) -> bool {
        self.u8_at(mx28::TORQUE_ENABLE) != 0
    }

    /// Mirror `present` (and velocity) into the control table.
    fn sync_present(&mut self, velocity_ticks_s: f64) {
        self.set_u32(mx28::PRESENT_POSITION, self.present.round() as i32 as u32);
        let velocity_units = velocity_ticks_s * 60.0 / 4096.0 / mx28::VELOCITY_UNIT_RPM;
        self.set_u32(mx28::PRESENT_VELOCITY, velocity_units.round() as i32 as u32);
        self.table[usize::from(mx28::MOVING)] = u8::from(velocity_ticks_s != 0.0);
    }

    /// Move toward the goal for `dt` seconds at the profile velocity (0 = velocity limit).
    fn advance(&mut self, dt: f64) {
        let mut velocity = 0.0;
        if self.torque() && self.u8_at(mx28::HARDWARE_ERROR_STATUS) == 0 {
            let goal = f64::from(self.u32_at(mx28::GOAL_POSITION) as i32);
            let profile = self.u32_at(mx28::PROFILE_VELOCITY);
            let units = if profile == 0 { self.u32_at(mx28::VELOCITY_LIMIT) } else { profile };
            let speed = f64::from(units) * mx28::VELOCITY_UNIT_RPM / 60.0 * 4096.0; // ticks/s
            let delta = goal - self.present;
            let step = speed * dt;
            if delta.abs() <= step {
                self.present = goal;
            } else {
                self.present += step * delta.signum();
                velocity = speed * delta.signum();
            }
        }
        self.sync_present(velocity);
    }

    /// Apply a write; returns the status error number (0 = ok).
    fn write(&mut self, address: u16, data: &[u8]) -> u8 {
        let end = usize::from(address) + data.len();
        if data.is_empty() || end > mx28::TABLE_SIZE {
            return status_error::DATA_LENGTH;
        }
        // Every touched byte must belong to a writable field, fully covered; EEPROM locked with torque on.
        let mut a = address;
        while usize::from(a) < end {
            let Some(field) = mx28::field_at(a) else { return status_error::ACCESS };
            if field.access != mx28::Access::ReadWrite || field.address != a || usize::from(a + field.size) > end {
                return status_error::ACCESS;
            }
            if a < mx28::RAM_START && self.torque() {
                return status_error::ACCESS;
            }
            let offset = usize::from(a - address);
            let mut bytes = [0u8; 4];
            bytes[..usize::from(field.size)].copy_from_slice(&data[offset..offset + usize::from(field.size)]);
            let value = u32::from_le_bytes(bytes);
            if let Some(error) = self.check_range(a, value) {
                return error;
            }
            a += field.size;
        }
        let was_on = self.torque();
        let start = usize::from(address);
        self.table[start..end].copy_from_slice(data);
        if !was_on && self.torque() {
            // Enabling torque latches the goal to the present position (no jump).
            self.set_u32(mx28::GOAL_POSITION, self.present.round() as u32);
        }
        if address <= mx28::GOAL_POSITION && end >= usize::from(mx28::GOAL_POSITION) + 4 && self.torque() {
            let goal = self.u32_at(mx28::GOAL_POSITION) as i32;
            self.goal_history.push(goal);
        }
        0
    }

    fn check_range(&self, address: u16, value: u32) -> Option<u8> {
        let bad = match address {
            mx28::TORQUE_ENABLE | mx28::LED => value > 1,
            mx28::STATUS_RETURN_LEVEL => value > 2,
            mx28::ID => value > 252,
            mx28::BAUD_RATE => mx28::baud_from_register(value as u8).is_none(),
            mx28::RETURN_DELAY_TIME => value > 254,
            mx28::GOAL_POSITION => {
                let (min, max) = (self.u32_at(mx28::MIN_POSITION_LIMIT), self.u32_at(mx28::MAX_POSITION_LIMIT));
                value < min || value > max
            }
            mx28::MAX_POSITION_LIMIT | mx28::MIN_POSITION_LIMIT => value > 4095,
            _ => false,
        };
        bad.then_some(status_error::DATA_LIMIT)
    }

    fn read(&self, address: u16, count: u16) -> Result<Vec<u8>, u8> {
        let start = usize::from(address);
        let end = start + usize::from(count);
        if count == 0 || end > mx28::TABLE_SIZE {
            return Err(status_error::DATA_RANGE);
        }
        Ok(self.table[start..end].to_vec())
    }

    fn booting(&self, now: Instant) -> bool {
        self.booting_until.is_some_and(|until| now < until)
    }

    fn reboot(&mut self) {
        let id = self.id();
        let eeprom: Vec<u8> = self.table[..usize::from(mx28::RAM_START)].to_vec();
        let fresh = SimServo::new(id, self.u8_at(mx28::RETURN_DELAY_TIME), self.present);
        self.table = fresh.table;
        self.table[..usize::from(mx28::RAM_START)].copy_from_slice(&eeprom);
        self.sync_present(0.0);
    }

    fn error_byte(&self, error: u8) -> u8 {
        if self.u8_at(mx28::HARDWARE_ERROR_STATUS) != 0 {
            error | status_error::ALERT
        } else {
            error
        }
    }
}

struct Shared {
    faults: Mutex<Faults>,
    servos: Mutex<Vec<SimServo>>,
}

fn lock<T>(mutex: &Mutex<T>) -> MutexGuard<'_, T> {
    mutex.lock().unwrap_or_else(|poisoned| poisoned.into_inner())
}

/// A running simulated chain; dropping it stops the thread and closes the pty.
pub struct SimChain {
    shared: Arc<Shared>,
    config: SimConfig,
    /// The pty being served (`None` while unplugged).
    plugged: Mutex<Option<Plugged>>,
}

/// One pty and the thread serving it.
struct Plugged {
    device_path: PathBuf,
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<()>>,
    /// Kept open so the master never sees EIO when clients disconnect.
    _slave: OwnedFd,
}

impl Plugged {
    fn open(shared: &Arc<Shared>, config: &SimConfig) -> Result<Self, SimError> {
        let pty = nix::pty::openpty(None, None).map_err(|e| SimError::Pty(e.to_string()))?;
        let mut termios = nix::sys::termios::tcgetattr(pty.slave.as_fd()).map_err(|e| SimError::Pty(e.to_string()))?;
        nix::sys::termios::cfmakeraw(&mut termios);
        nix::sys::termios::tcsetattr(pty.slave.as_fd(), nix::sys::termios::SetArg::TCSANOW, &termios)
            .map_err(|e| SimError::Pty(e.to_string()))?;
        let device_path = nix::unistd::ttyname(pty.slave.as_fd()).map_err(|e| SimError::Pty(e.to_string()))?;
        let stop = Arc::new(AtomicBool::new(false));
        let (thread_shared, thread_stop, thread_config) = (Arc::clone(shared), Arc::clone(&stop), config.clone());
        let master = pty.master;
        let thread = std::thread::Builder::new()
            .name("sim-mx28-chain".into())
            .spawn(move || serve(master, thread_shared, thread_stop, thread_config))
            .map_err(|e| SimError::Pty(e.to_string()))?;
        Ok(Self { device_path, stop, thread: Some(thread), _slave: pty.slave })
    }

    fn close(mut self) {
        self.stop.store(true, Ordering::SeqCst);
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

impl std::fmt::Debug for SimChain {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SimChain").field("device_path", &self.device_path()).finish()
    }
}

impl SimChain {
    /// Open a pty pair and start serving the chain on its own thread.
    pub fn spawn(config: SimConfig) -> Result<Self, SimError> {
        if let Some(&bad) = config.ids.iter().find(|&&id| id == 0 || id > 252) {
            return Err(SimError::InvalidId(bad));
        }
        let servos = config.ids.iter().map(|&id| SimServo::new(id, config.return_delay_register, 2048.0)).collect();
        let shared = Arc::new(Shared { faults: Mutex::new(Faults::default()), servos: Mutex::new(servos) });
        let plugged = Plugged::open(&shared, &config)?;
        Ok(Self { shared, config, plugged: Mutex::new(Some(plugged)) })
    }

    /// The slave device to open with any Dynamixel master (e.g. `/dev/pts/3`); empty while unplugged.
    pub fn device_path(&self) -> PathBuf {
        lock(&self.plugged).as_ref().map(|p| p.device_path.clone()).unwrap_or_default()
    }

    /// Unplug: stop serving and close the pty (the master's reads and writes fail from now on; the
    /// device node goes away once the master closes it). The servos keep their state.
    pub fn unplug(&self) {
        if let Some(plugged) = lock(&self.plugged).take() {
            plugged.close();
        }
    }

    /// Plug back in: a new pty (a new device path) serving the same servos. Returns the new path.
    pub fn replug(&self) -> Result<PathBuf, SimError> {
        let mut slot = lock(&self.plugged);
        if let Some(old) = slot.take() {
            old.close();
        }
        let plugged = Plugged::open(&self.shared, &self.config)?;
        let path = plugged.device_path.clone();
        *slot = Some(plugged);
        Ok(path)
    }

    /// Change the injected faults.
    pub fn set_faults(&self, update: impl FnOnce(&mut Faults)) {
        update(&mut lock(&self.shared.faults));
    }

    /// Set hardware error bits on a servo (alert bit in its status packets; torque switched off).
    pub fn set_hardware_error(&self, id: u8, bits: u8) {
        let mut servos = lock(&self.shared.servos);
        if let Some(servo) = servos.iter_mut().find(|s| s.id() == id) {
            servo.table[usize::from(mx28::HARDWARE_ERROR_STATUS)] = bits;
            if bits != 0 {
                servo.table[usize::from(mx28::TORQUE_ENABLE)] = 0;
            }
        }
    }

    /// Move a servo by hand (torque off: compliant posing for keyframe recording).
    pub fn set_present(&self, id: u8, ticks: f64) {
        let mut servos = lock(&self.shared.servos);
        if let Some(servo) = servos.iter_mut().find(|s| s.id() == id) {
            servo.present = ticks;
            servo.sync_present(0.0);
        }
    }

    /// State of one servo.
    pub fn snapshot(&self, id: u8) -> Option<ServoSnapshot> {
        let servos = lock(&self.shared.servos);
        servos.iter().find(|s| s.id() == id).map(|s| ServoSnapshot {
            id,
            present: s.present,
            goal: s.u32_at(mx28::GOAL_POSITION) as i32,
            torque: s.torque(),
            hardware_error: s.u8_at(mx28::HARDWARE_ERROR_STATUS),
        })
    }

    /// Goal positions each servo accepted while torque was on (in order).
    pub fn goal_history(&self, id: u8) -> Vec<i32> {
        lock(&self.shared.servos).iter().find(|s| s.id() == id).map(|s| s.goal_history.clone()).unwrap_or_default()
    }

    /// Stop the thread and close the pty (also done on drop).
    pub fn stop(&mut self) {
        self.unplug();
    }
}

impl Drop for SimChain {
    fn drop(&mut self) {
        self.stop();
    }
}

/// Sleep for simulated bus time (skipped below the scheduler's resolution).
fn bus_sleep(duration: Duration) {
    if duration >= Duration::from_micros(20) {
        std::thread::sleep(duration);
    }
}

fn write_all(master: &OwnedFd, mut bytes: &[u8]) {
    while !bytes.is_empty() {
        match nix::unistd::write(master, bytes) {
            Ok(0) => return,
            Ok(n) => bytes = &bytes[n..],
            Err(nix::errno::Errno::EAGAIN) | Err(nix::errno::Errno::EINTR) => std::thread::sleep(Duration::from_micros(50)),
            Err(_) => return,
        }
    }
}

/// The chain's thread: read instructions, advance the servos, answer.
fn serve(master: OwnedFd, shared: Arc<Shared>, stop: Arc<AtomicBool>, config: SimConfig) {
    // Real servos answer from their own MCU whatever the host's load: the master's answer budget must
    // not trip because this thread waited for a CPU.
    crate::priority::make_realtime(SIM_PRIORITY);
    let mut parser = PacketParser::new();
    let mut buffer = [0u8; 1024];
    let mut last = Instant::now();
    while !stop.load(Ordering::SeqCst) {
        let readable = {
            let mut fds = [nix::poll::PollFd::new(master.as_fd(), nix::poll::PollFlags::POLLIN)];
            matches!(nix::poll::poll(&mut fds, nix::poll::PollTimeout::from(5u8)), Ok(n) if n > 0)
        };
        let now = Instant::now();
        let dt = now.duration_since(last).as_secs_f64();
        last = now;
        {
            let mut servos = lock(&shared.servos);
            let tick = (now.elapsed().as_millis() % 32768) as u16;
            for servo in servos.iter_mut() {
                servo.advance(dt);
                let a = usize::from(mx28::REALTIME_TICK);
                servo.table[a..a + 2].copy_from_slice(&tick.to_le_bytes());
            }
        }
        if !readable {
            continue;
        }
        match nix::unistd::read(std::os::fd::AsRawFd::as_raw_fd(&master), &mut buffer) {
            Ok(n) if n > 0 => parser.feed(&buffer[..n]),
            Err(nix::errno::Errno::EAGAIN) | Err(nix::errno::Errno::EINTR) => continue,
            // End of file or an error while readable: rest, never spin at real-time priority.
            Ok(_) | Err(_) => {
                std::thread::sleep(Duration::from_millis(5));
                continue;
            }
        }
        while let Some(frame) = parser.next_packet() {
            let responses = responses_to(frame, &shared, config.boot_time);
            respond(&master, &shared, &config, responses);
        }
    }
}

/// The chain's answers to one parsed frame. Frames with a bad CRC are ignored by MX-28s when
/// addressed by broadcast; for a unicast instruction the servo answers with a CRC error status.
fn responses_to(frame: Result<Packet, protocol::FrameError>, shared: &Shared, boot_time: Duration) -> Vec<Response> {
    match frame {
        Ok(packet) => handle(&packet, shared, boot_time),
        Err(protocol::FrameError::Crc { id, .. }) => crc_error_response(id, shared),
        Err(_) => Vec::new(),
    }
}

/// The device side without a pty or a thread: `bytes` (instruction packets, noise) go into a chain
/// of `SimConfig::with_servos(12)` in chunks, the servos advance 8 ms between frames, and the status
/// packets they would send come back, concatenated (no injected faults, no wire time, a reboot is
/// over at once so the answers do not depend on how fast the host replays).
pub fn replay_instructions(bytes: &[u8]) -> Vec<u8> {
    let config = SimConfig::with_servos(12);
    let servos = config.ids.iter().map(|&id| SimServo::new(id, config.return_delay_register, 2048.0)).collect();
    let shared = Shared { faults: Mutex::new(Faults::default()), servos: Mutex::new(servos) };
    let mut parser = PacketParser::new();
    let mut out = Vec::new();
    for chunk in bytes.chunks(64) {
        parser.feed(chunk);
        while let Some(frame) = parser.next_packet() {
            for (id, error, data) in responses_to(frame, &shared, Duration::ZERO) {
                out.extend(protocol::encode_status(id, error, &data));
            }
            for servo in lock(&shared.servos).iter_mut() {
                servo.advance(0.008);
            }
        }
    }
    out
}

/// A response: (responding servo id, error byte, data).
type Response = (u8, u8, Vec<u8>);

fn crc_error_response(id: u8, shared: &Shared) -> Vec<Response> {
    let servos = lock(&shared.servos);
    servos
        .iter()
        .filter(|s| s.id() == id && id != protocol::BROADCAST_ID && s.u8_at(mx28::STATUS_RETURN_LEVEL) == 2 && !s.booting(Instant::now()))
        .map(|s| (id, s.error_byte(status_error::CRC), Vec::new()))
        .collect()
}

/// Execute one instruction; returns the status packets to send, in bus order.
fn handle(packet: &Packet, shared: &Shared, boot_time: Duration) -> Vec<Response> {
    let mut guard = lock(&shared.servos);
    // A booting servo hears nothing.
    let now = Instant::now();
    let mut servos: Vec<&mut SimServo> = guard.iter_mut().filter(|s| !s.booting(now)).collect();
    let p = &packet.params;
    let u16_at = |i: usize| -> Option<u16> { Some(u16::from_le_bytes([*p.get(i)?, *p.get(i + 1)?])) };
    let broadcast = packet.id == protocol::BROADCAST_ID;
    let mut out = Vec::new();
    match packet.instruction {
        instruction::PING => {
            for servo in servos.iter().filter(|s| broadcast || s.id() == packet.id) {
                let model = mx28::MODEL_NUMBER.to_le_bytes();
                out.push((servo.id(), servo.error_byte(0), vec![model[0], model[1], servo.u8_at(mx28::FIRMWARE_VERSION_ADDR)]));
            }
        }
        instruction::SYNC_READ => {
            let (Some(address), Some(count)) = (u16_at(0), u16_at(2)) else { return out };
            for &id in p.get(4..).unwrap_or(&[]) {
                if let Some(servo) = servos.iter().find(|s| s.id() == id) {
                    if servo.u8_at(mx28::STATUS_RETURN_LEVEL) >= 1 {
                        match servo.read(address, count) {
                            Ok(data) => out.push((id, servo.error_byte(0), data)),
                            Err(e) => out.push((id, servo.error_byte(e), Vec::new())),
                        }
                    }
                }
            }
        }
        instruction::SYNC_WRITE => {
            let (Some(address), Some(count)) = (u16_at(0), u16_at(2)) else { return out };
            let stride = 1 + usize::from(count);
            for chunk in p.get(4..).unwrap_or(&[]).chunks_exact(stride) {
                if let Some(servo) = servos.iter_mut().find(|s| s.id() == chunk[0]) {
                    let _ = servo.write(address, &chunk[1..]);
                }
            }
        }
        _ => {
            for servo in servos.iter_mut().filter(|s| broadcast || s.id() == packet.id) {
                let (error, data) = match packet.instruction {
                    instruction::READ => match (u16_at(0), u16_at(2), p.len()) {
                        (Some(address), Some(count), 4) => match servo.read(address, count) {
                            Ok(data) => (0, data),
                            Err(e) => (e, Vec::new()),
                        },
                        _ => (status_error::DATA_LENGTH, Vec::new()),
                    },
                    instruction::WRITE => match u16_at(0) {
                        Some(address) if p.len() > 2 => (servo.write(address, &p[2..]), Vec::new()),
                        _ => (status_error::DATA_LENGTH, Vec::new()),
                    },
                    instruction::REBOOT => {
                        // Answered first (with the alert bit as it was), then the servo restarts
                        // and is silent while it boots.
                        let before = servo.error_byte(0);
                        servo.reboot();
                        servo.booting_until = Some(now + boot_time);
                        (before, Vec::new())
                    }
                    _ => (status_error::INSTRUCTION, Vec::new()),
                };
                let level = servo.u8_at(mx28::STATUS_RETURN_LEVEL);
                let answers = !broadcast && (level == 2 || (level == 1 && packet.instruction == instruction::READ));
                if answers {
                    out.push((servo.id(), servo.error_byte(error), data));
                }
            }
        }
    }
    out
}

/// `FF FF FD 00 | id | 02 00 | CRC` + one trailing byte: LEN = 2 leaves no room for the
/// instruction and error bytes of a status packet; the CRC over the first 7 bytes is valid.
fn malformed_frame(id: u8) -> Vec<u8> {
    let mut frame = vec![0xFF, 0xFF, 0xFD, 0x00, id, 0x02, 0x00];
    let crc = protocol::crc16(&frame);
    frame.extend_from_slice(&crc.to_le_bytes());
    frame.push(0x00);
    frame
}

/// Send responses honouring faults, return delay and wire time.
fn respond(master: &OwnedFd, shared: &Shared, config: &SimConfig, responses: Vec<Response>) {
    let faults = lock(&shared.faults).clone();
    if faults.silent_all {
        return;
    }
    let delays: BTreeMap<u8, u8> = lock(&shared.servos).iter().map(|s| (s.id(), s.u8_at(mx28::RETURN_DELAY_TIME))).collect();
    // The whole burst (e.g. 12 sync-read answers) is delayed by its total return delay and wire
    // time and then written at once: one wake-up per instruction keeps the chain responsive on a
    // loaded machine, and the master sees the same round-trip time.
    let mut wait = faults.latency;
    let mut burst = Vec::new();
    for (id, error, data) in responses {
        if faults.silent.contains(&id) {
            continue;
        }
        let claimed = faults.wrong_id.get(&id).copied().unwrap_or(id);
        let mut bytes =
            if faults.malformed.contains(&id) { malformed_frame(claimed) } else { protocol::encode_status(claimed, error, &data) };
        if faults.crc_errors.contains(&id) {
            let n = bytes.len();
            bytes[n - 1] ^= 0xA5;
        }
        wait += Duration::from_micros(2 * u64::from(delays.get(&id).copied().unwrap_or(0)));
        if config.simulate_wire_time && config.baud > 0 {
            wait += Duration::from_nanos(bytes.len() as u64 * 10 * 1_000_000_000 / u64::from(config.baud));
        }
        burst.extend_from_slice(&bytes);
    }
    if burst.is_empty() {
        return;
    }
    bus_sleep(wait);
    write_all(master, &burst);
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::{encode, PacketParser};

    use patchwalk_test_support::stored_fuzz_inputs as stored_inputs;
    use std::io::{Read, Write};

    /// Minimal raw client over the pty for framing-level checks.
    struct Raw {
        port: std::fs::File,
        parser: PacketParser,
    }

    impl Raw {
        fn open(chain: &SimChain) -> Self {
            let port = std::fs::OpenOptions::new().read(true).write(true).open(chain.device_path()).unwrap();
            Self { port, parser: PacketParser::new() }
        }

        fn send(&mut self, id: u8, inst: u8, params: &[u8]) {
            self.port.write_all(&encode(id, inst, params)).unwrap();
        }

        /// Read one status packet (blocking with a deadline).
        fn recv(&mut self) -> Option<Packet> {
            let deadline = Instant::now() + Duration::from_millis(300);
            let mut buf = [0u8; 256];
            loop {
                if let Some(Ok(p)) = self.parser.next_packet() {
                    return Some(p);
                }
                if Instant::now() > deadline {
                    return None;
                }
                let mut fds = [nix::poll::PollFd::new(self.port.as_fd(), nix::poll::PollFlags::POLLIN)];
                if matches!(nix::poll::poll(&mut fds, nix::poll::PollTimeout::from(20u8)), Ok(n) if n > 0) {
                    let n = self.port.read(&mut buf).unwrap();
                    self.parser.feed(&buf[..n]);
                }
            }
        }
    }

    fn chain(n: u8) -> SimChain {
        let mut config = SimConfig::with_servos(n);
        config.return_delay_register = 0;
        SimChain::spawn(config).unwrap()
    }

    fn raw_tty(chain: &SimChain) -> Raw {
        let raw = Raw::open(chain);
        let mut t = nix::sys::termios::tcgetattr(raw.port.as_fd()).unwrap();
        nix::sys::termios::cfmakeraw(&mut t);
        nix::sys::termios::tcsetattr(raw.port.as_fd(), nix::sys::termios::SetArg::TCSANOW, &t).unwrap();
        raw
    }

    #[test]
    fn broadcast_ping_answers_in_id_order() {
        let chain = chain(3);
        let mut raw = raw_tty(&chain);
        raw.send(protocol::BROADCAST_ID, instruction::PING, &[]);
        for id in 1..=3 {
            let p = raw.recv().unwrap();
            assert_eq!((p.id, p.instruction), (id, instruction::STATUS));
            assert_eq!(p.params, vec![0, 30, 0, mx28::FIRMWARE_VERSION]);
        }
    }

    #[test]
    fn eeprom_locked_while_torque_on_and_read_only_fields_refused() {
        let chain = chain(1);
        let mut raw = raw_tty(&chain);
        raw.send(1, instruction::WRITE, &[9, 0, 0]); // return delay 0, torque off: ok
        assert_eq!(raw.recv().unwrap().params, vec![0]);
        raw.send(1, instruction::WRITE, &[64, 0, 1]); // torque on
        assert_eq!(raw.recv().unwrap().params, vec![0]);
        raw.send(1, instruction::WRITE, &[9, 0, 5]);
        assert_eq!(raw.recv().unwrap().params, vec![status_error::ACCESS]);
        raw.send(1, instruction::WRITE, &[132, 0, 0, 0, 0, 0]); // present position is read-only
        assert_eq!(raw.recv().unwrap().params, vec![status_error::ACCESS]);
        raw.send(1, instruction::WRITE, &[116, 0, 0x00, 0x10, 0, 0]); // 4096 > max position limit
        assert_eq!(raw.recv().unwrap().params, vec![status_error::DATA_LIMIT]);
    }

    #[test]
    fn goal_is_reached_at_realistic_speed() {
        let chain = chain(1);
        let mut raw = raw_tty(&chain);
        raw.send(1, instruction::WRITE, &[64, 0, 1]);
        raw.recv().unwrap();
        let start = Instant::now();
        // +1024 ticks = 90°: at ≈ 52.7 rpm (316°/s) this takes ≈ 0.28 s.
        raw.send(1, instruction::WRITE, &[116, 0, 0x00, 0x0C, 0, 0]);
        raw.recv().unwrap();
        std::thread::sleep(Duration::from_millis(100));
        let mid = chain.snapshot(1).unwrap().present;
        assert!(mid > 2048.0 && mid < 3072.0, "{mid}");
        while chain.snapshot(1).unwrap().present < 3072.0 && start.elapsed() < Duration::from_secs(2) {
            std::thread::sleep(Duration::from_millis(10));
        }
        assert_eq!(chain.snapshot(1).unwrap().present, 3072.0);
    }

    #[test]
    fn hardware_error_sets_alert_bit_and_reboot_clears_it() {
        let chain = chain(2);
        let mut raw = raw_tty(&chain);
        chain.set_hardware_error(2, mx28::HW_OVERLOAD);
        raw.send(2, instruction::READ, &[70, 0, 1, 0]);
        let p = raw.recv().unwrap();
        assert_eq!(p.params, vec![status_error::ALERT, mx28::HW_OVERLOAD]);
        raw.send(2, instruction::REBOOT, &[]);
        raw.recv().unwrap();
        std::thread::sleep(DEFAULT_BOOT_TIME + Duration::from_millis(50));
        raw.send(2, instruction::READ, &[70, 0, 1, 0]);
        assert_eq!(raw.recv().unwrap().params, vec![0, 0]);
    }

    #[test]
    fn reboot_answers_then_the_servo_is_silent_while_it_boots() {
        let mut config = SimConfig::with_servos(1);
        config.return_delay_register = 0;
        config.boot_time = Duration::from_millis(400);
        let chain = SimChain::spawn(config).unwrap();
        let mut raw = raw_tty(&chain);
        chain.set_hardware_error(1, mx28::HW_OVERHEATING);
        raw.send(1, instruction::REBOOT, &[]);
        assert_eq!(raw.recv().unwrap().params, vec![status_error::ALERT]);
        raw.send(1, instruction::PING, &[]);
        assert!(raw.recv().is_none(), "silent while booting");
        std::thread::sleep(Duration::from_millis(400));
        raw.send(1, instruction::PING, &[]);
        let p = raw.recv().unwrap();
        assert_eq!(p.params[0], 0, "no alert after the reboot");
        assert_eq!(chain.snapshot(1).unwrap().hardware_error, 0);
        assert!(!chain.snapshot(1).unwrap().torque);
    }

    #[test]
    fn wrong_id_and_unplug_replug() {
        let chain = chain(2);
        let mut raw = raw_tty(&chain);
        chain.set_faults(|f| {
            f.wrong_id.insert(2, 9);
        });
        raw.send(2, instruction::PING, &[]);
        assert_eq!(raw.recv().unwrap().id, 9);
        let old = chain.device_path();
        chain.unplug();
        assert_eq!(chain.device_path(), PathBuf::new());
        let mut buf = [0u8; 8];
        assert!(raw.port.read(&mut buf).is_err() || raw.port.write_all(&[0]).is_err(), "I/O fails while unplugged");
        drop(raw);
        let new = chain.replug().unwrap();
        assert!(new.exists());
        let mut raw = raw_tty(&chain);
        raw.send(1, instruction::PING, &[]);
        assert_eq!(raw.recv().unwrap().id, 1);
        let _ = old;
    }

    #[test]
    fn silence_and_unsupported_instruction() {
        let chain = chain(2);
        let mut raw = raw_tty(&chain);
        chain.set_faults(|f| {
            f.silent.insert(1);
        });
        raw.send(1, instruction::PING, &[]);
        assert!(raw.recv().is_none());
        raw.send(2, instruction::FACTORY_RESET, &[0xFF]);
        assert_eq!(raw.recv().unwrap().params, vec![status_error::INSTRUCTION]);
    }

    #[test]
    fn replayed_instructions_are_answered_like_the_live_chain() {
        let mut bytes = encode(protocol::BROADCAST_ID, instruction::PING, &[]);
        bytes.extend(encode(3, instruction::READ, &[0, 0, 2, 0]));
        let answers = protocol::parse_stream(&[&[63u8][..], &replay_instructions(&bytes)].concat());
        let packets: Vec<Packet> = answers.into_iter().map(Result::unwrap).collect();
        assert_eq!(packets.len(), 13);
        assert_eq!(packets.iter().take(12).map(|p| p.id).collect::<Vec<_>>(), (1..=12).collect::<Vec<_>>());
        let model = mx28::MODEL_NUMBER.to_le_bytes();
        assert_eq!((packets[12].id, packets[12].params.clone()), (3, vec![0, model[0], model[1]]));
    }

    #[test]
    fn stored_sim_chain_inputs_are_answered() {
        for (path, bytes) in stored_inputs("dynamixel_sim_chain") {
            let answers = replay_instructions(&bytes);
            for frame in protocol::parse_stream(&[&[63u8][..], &answers].concat()) {
                let packet = frame.unwrap_or_else(|e| panic!("{}: the chain sent a bad frame: {e}", path.display()));
                assert_eq!(packet.instruction, instruction::STATUS, "{}", path.display());
            }
        }
    }
}
