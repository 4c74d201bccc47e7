//! `/diagnostics` (`diagnostic_msgs/DiagnosticArray`, 1 Hz) of the step_executor, hardware id
//! `step_executor`: the servo bus, one status per servo, the control cycle, the motion library and
//! the safety state (e-stop, armed, deadman heartbeat). Levels: OK, WARN (works, but a person
//! should look: e-stop latched, empty library, slow cycle), ERROR (cannot move: no bus, a bus fault).

use std::time::{Duration, Instant};

use patchwalk_msgs::builtin_interfaces::msg::Time;
use patchwalk_msgs::diagnostic_msgs::msg::{DiagnosticArray, DiagnosticStatus, KeyValue};
use step_executor::config::ServoConfig;
use step_executor::executor::Telemetry;
use step_executor::health::BusHealth;
use step_executor::runtime::{RunState, RuntimeStatus};

use patchwalk_ros::diagnostics::kv;
pub use patchwalk_ros::diagnostics::{DIAGNOSTICS_PERIOD, DIAGNOSTICS_TOPIC};
/// The hardware id of every status: the node's name.
pub const HARDWARE_ID: &str = "step_executor";

const OK: u8 = DiagnosticStatus::OK;
const WARN: u8 = DiagnosticStatus::WARN;
const ERROR: u8 = DiagnosticStatus::ERROR;

/// What the bus thread's telemetry showed since the last publication.
#[derive(Debug, Clone, Default)]
pub struct CycleWindow {
    cycles: u64,
    max_busy: Duration,
    since: Option<Instant>,
    /// Latest telemetry (per-servo readings).
    latest: Option<Telemetry>,
    /// Cycles in the window in which a servo gave no position, per servo (joint order).
    missed: Vec<u64>,
}

impl CycleWindow {
    /// Account the cycles of one loop pass.
    pub fn add(&mut self, telemetry: &[Telemetry]) {
        for t in telemetry {
            self.cycles += 1;
            self.max_busy = self.max_busy.max(t.busy);
            if self.missed.len() < t.positions.len() {
                self.missed.resize(t.positions.len(), 0);
            }
            for (missed, p) in self.missed.iter_mut().zip(&t.positions) {
                *missed += u64::from(p.is_none());
            }
        }
        if let Some(last) = telemetry.last() {
            self.latest = Some(last.clone());
        }
    }

    /// Start a new window at `now` (keeps the latest telemetry).
    fn restart(&mut self, now: Instant) {
        self.cycles = 0;
        self.max_busy = Duration::ZERO;
        self.since = Some(now);
        self.missed.iter_mut().for_each(|m| *m = 0);
    }
}

/// The node state the diagnostics describe (gathered by the loop).
pub struct Snapshot<'a> {
    pub status: &'a RuntimeStatus,
    pub has_bus: bool,
    pub servos: &'a [ServoConfig],
    /// Nominal control cycle.
    pub cycle: Duration,
    pub heartbeat_age: Option<Duration>,
    pub heartbeat_timeout: Duration,
    pub deadman_engaged: bool,
    pub action_goal_active: bool,
    /// The bus thread's health record (per servo and for the cycle), when there is a bus.
    pub health: Option<&'a BusHealth>,
}

/// Present temperature from which a servo is reported WARN (the MX-28 shuts down at its limit, 80 °C
/// by default).
pub const HOT_C: u8 = 70;
/// The MX-28's default input voltage limits (Min/Max Voltage Limit, 9.5 V and 16.0 V): outside them
/// the servo sets its input-voltage error.
pub const VOLTAGE_RANGE_V: (f64, f64) = (9.5, 16.0);

fn status(level: u8, name: &str, message: impl Into<String>, values: Vec<KeyValue>) -> DiagnosticStatus {
    patchwalk_ros::diagnostics::status(HARDWARE_ID, level, name, message, values)
}

/// The whole array for `snapshot` and the cycles of `window` (which is restarted).
pub fn diagnostics(snapshot: &Snapshot<'_>, window: &mut CycleWindow, now: Instant, stamp: Time) -> DiagnosticArray {
    let mut statuses = vec![bus_status(snapshot)];
    statuses.extend(servo_statuses(snapshot, window));
    statuses.push(cycle_status(snapshot, window, now));
    statuses.push(library_status(snapshot));
    statuses.push(safety_status(snapshot));
    window.restart(now);
    patchwalk_ros::diagnostics::array(stamp, statuses)
}

fn bus_status(s: &Snapshot<'_>) -> DiagnosticStatus {
    let st = s.status;
    let values = vec![
        kv("state", format!("{:?}", st.state)),
        kv("torque", st.torque_enabled),
        kv("current_motion", &st.current_motion),
        kv("fault_servo_id", st.fault_servo_id),
        kv("last_fault", &st.last_fault),
    ];
    if !s.has_bus {
        return status(ERROR, "servo bus", format!("no servo bus: {}", st.last_fault), values);
    }
    match st.state {
        RunState::HoldingFault => {
            let servo = if st.fault_servo_id == 0 { String::new() } else { format!(" (servo {})", st.fault_servo_id) };
            status(ERROR, "servo bus", format!("bus fault{servo}, holding: {}; set_torque false clears it", st.last_fault), values)
        }
        RunState::Playing => status(OK, "servo bus", format!("playing {:?}", st.current_motion), values),
        RunState::EStopped => status(OK, "servo bus", "holding (e-stop latched)", values),
        RunState::Idle => status(OK, "servo bus", if st.torque_enabled { "idle, torque on" } else { "idle, torque off" }, values),
    }
}

/// One status per servo: whether it answered its position read, the position, and from the bus
/// health its communication errors, hardware-error bits, temperature and input voltage.
pub fn servo_statuses(s: &Snapshot<'_>, window: &CycleWindow) -> Vec<DiagnosticStatus> {
    if !s.has_bus {
        return Vec::new();
    }
    let latest = window.latest.as_ref();
    s.servos
        .iter()
        .enumerate()
        .map(|(i, servo)| {
            let position = latest.and_then(|t| t.positions.get(i).copied().flatten());
            let missed = window.missed.get(i).copied().unwrap_or(0);
            let name = format!("servo {} ({})", servo.id, servo.joint);
            let mut values = vec![kv("id", servo.id), kv("joint", &servo.joint), kv("missed_position_reads", missed)];
            if let Some(q) = position {
                values.push(kv("position_rad", format!("{q:.4}")));
            }
            let health = s.health.and_then(|h| h.servos.iter().find(|v| v.id == servo.id));
            if let Some(h) = health {
                values.push(kv("comm_errors", h.comm_errors));
                values.push(kv("hardware_error", format!("0x{:02x}", h.hardware_error)));
                if let Some(e) = &h.last_error {
                    values.push(kv("last_error", e));
                }
                if let Some(t) = h.temperature_c {
                    values.push(kv("temperature_c", t));
                }
                if let Some(v) = h.input_voltage_v {
                    values.push(kv("input_voltage_v", format!("{v:.1}")));
                }
            }
            let faulted = s.status.state == RunState::HoldingFault && s.status.fault_servo_id == servo.id;
            let hardware = health.map_or(0, |h| h.hardware_error);
            let hot = health.and_then(|h| h.temperature_c).filter(|t| *t >= HOT_C);
            let voltage = health.and_then(|h| h.input_voltage_v).filter(|v| *v < VOLTAGE_RANGE_V.0 || *v > VOLTAGE_RANGE_V.1);
            match (faulted, position, missed) {
                (true, _, _) => status(ERROR, &name, format!("faulted: {}", s.status.last_fault), values),
                _ if hardware != 0 => {
                    let names = patchwalk_dynamixel::mx28::hardware_error_names(hardware).join(", ");
                    status(ERROR, &name, format!("hardware error 0x{hardware:02x} ({names}): reboot_servos clears it"), values)
                }
                _ if hot.is_some() => status(WARN, &name, format!("{} °C, near the shutdown limit", hot.unwrap_or_default()), values),
                _ if voltage.is_some() => {
                    status(WARN, &name, format!("input {:.1} V outside 9.5–16.0 V", voltage.unwrap_or_default()), values)
                }
                (false, None, _) => status(WARN, &name, "no position reading in the last cycle", values),
                (false, Some(_), m) if m > 0 => status(WARN, &name, format!("{m} position reads failed in the last second"), values),
                _ => status(OK, &name, "answering", values),
            }
        })
        .collect()
}

fn cycle_status(s: &Snapshot<'_>, window: &CycleWindow, now: Instant) -> DiagnosticStatus {
    let nominal_hz = 1.0 / s.cycle.as_secs_f64();
    let seconds = window.since.map_or(0.0, |since| now.duration_since(since).as_secs_f64());
    let rate = if seconds > 0.0 { window.cycles as f64 / seconds } else { 0.0 };
    let mut values = vec![
        kv("rate_hz", format!("{rate:.1}")),
        kv("nominal_hz", format!("{nominal_hz:.1}")),
        kv("max_bus_time_ms", format!("{:.2}", window.max_busy.as_secs_f64() * 1e3)),
    ];
    if let Some(h) = s.health {
        values.push(kv("period_p50_ms", format!("{:.3}", h.cycle_period_p50_ms)));
        values.push(kv("period_p99_ms", format!("{:.3}", h.cycle_period_p99_ms)));
        values.push(kv("bus_time_p99_ms", format!("{:.3}", h.cycle_busy_p99_ms)));
        values.push(kv("deadline_misses", h.deadline_misses));
        values.push(kv("scheduling", &h.scheduling));
    }
    if !s.has_bus {
        return status(OK, "control cycle", "not running (no servo bus)", values);
    }
    if seconds > 0.0 && rate < 0.9 * nominal_hz {
        return status(WARN, "control cycle", format!("{rate:.0} Hz, below the nominal {nominal_hz:.0} Hz"), values);
    }
    status(OK, "control cycle", format!("{rate:.0} Hz"), values)
}

fn library_status(s: &Snapshot<'_>) -> DiagnosticStatus {
    let st = s.status;
    let values = vec![kv("motions", st.library_size), kv("recorded_keyframes", st.recorded_keyframes), kv("last_match", &st.last_match)];
    if st.library_size == 0 {
        return status(WARN, "motion library", "empty: nothing to match (train and save_motion)", values);
    }
    status(OK, "motion library", format!("{} motions", st.library_size), values)
}

fn safety_status(s: &Snapshot<'_>) -> DiagnosticStatus {
    let st = s.status;
    let age = s.heartbeat_age.map_or("never".to_string(), |a| format!("{:.2}", a.as_secs_f64()));
    let values = vec![
        kv("estop_latched", st.state == RunState::EStopped),
        kv("armed", st.armed),
        kv("deadman_engaged", s.deadman_engaged),
        kv("heartbeat_age_s", age),
        kv("heartbeat_timeout_s", format!("{:.2}", s.heartbeat_timeout.as_secs_f64())),
        kv("action_goal_active", s.action_goal_active),
    ];
    if st.state == RunState::EStopped {
        return status(WARN, "safety", "e-stop latched: motions refused until reset_estop", values);
    }
    if st.last_fault.starts_with("deadman") {
        return status(WARN, "safety", st.last_fault.clone(), values);
    }
    let message = if st.armed { "armed (heartbeats arriving)" } else { "disarmed" };
    status(OK, "safety", message, values)
}

#[cfg(test)]
mod tests {
    use super::*;
    use step_executor::player::PlayerState;

    fn runtime_status(state: RunState) -> RuntimeStatus {
        RuntimeStatus {
            state,
            armed: false,
            torque_enabled: true,
            current_motion: String::new(),
            keyframe_index: 0,
            last_match: String::new(),
            fault_servo_id: 0,
            last_fault: String::new(),
            library_size: 2,
            recorded_keyframes: 0,
        }
    }

    fn servos() -> Vec<ServoConfig> {
        (1..=2).map(|id| ServoConfig { joint: format!("j{id}"), id, zero_offset: 0.0, direction: 1 }).collect()
    }

    fn telemetry(positions: Vec<Option<f64>>) -> Telemetry {
        Telemetry {
            started: Instant::now(),
            busy: Duration::from_millis(2),
            cycle_index: 0,
            keyframe_index: 0,
            positions,
            goal: None,
            state: PlayerState::Idle,
            torque: true,
            event: None,
            commands_taken: 0,
        }
    }

    fn snapshot<'a>(status: &'a RuntimeStatus, servos: &'a [ServoConfig]) -> Snapshot<'a> {
        Snapshot {
            status,
            has_bus: true,
            servos,
            cycle: Duration::from_millis(8),
            heartbeat_age: None,
            heartbeat_timeout: Duration::from_millis(500),
            deadman_engaged: false,
            action_goal_active: false,
            health: None,
        }
    }

    fn find<'a>(array: &'a DiagnosticArray, name: &str) -> &'a DiagnosticStatus {
        array.status.iter().find(|s| s.name == format!("{HARDWARE_ID}: {name}")).unwrap()
    }

    #[test]
    fn a_bus_fault_is_an_error_naming_the_servo() {
        let mut st = runtime_status(RunState::HoldingFault);
        st.fault_servo_id = 2;
        st.last_fault = "j2: servo 2: hardware error: overheating".into();
        let servos = servos();
        let mut window = CycleWindow::default();
        window.add(&[telemetry(vec![Some(0.1), None])]);
        let array = diagnostics(&snapshot(&st, &servos), &mut window, Instant::now(), Time::default());
        let bus = find(&array, "servo bus");
        assert_eq!(bus.level, ERROR);
        assert!(bus.message.contains("servo 2") && bus.message.contains("overheating"), "{}", bus.message);
        assert_eq!(find(&array, "servo 2 (j2)").level, ERROR);
        assert_eq!(find(&array, "servo 1 (j1)").level, OK);
        assert!(array.status.iter().all(|s| s.hardware_id == HARDWARE_ID));
    }

    #[test]
    fn missing_readings_warn_and_a_latched_estop_is_reported() {
        let st = runtime_status(RunState::EStopped);
        let servos = servos();
        let mut window = CycleWindow::default();
        window.add(&[telemetry(vec![Some(0.1), None])]);
        let array = diagnostics(&snapshot(&st, &servos), &mut window, Instant::now(), Time::default());
        assert_eq!(find(&array, "servo 2 (j2)").level, WARN);
        let safety = find(&array, "safety");
        assert_eq!(safety.level, WARN);
        assert!(safety.message.contains("reset_estop"), "{}", safety.message);
        assert!(safety.values.iter().any(|v| v.key == "heartbeat_age_s" && v.value == "never"));
    }

    #[test]
    fn bus_health_reports_hardware_errors_heat_and_voltage_per_servo() {
        use step_executor::health::ServoHealth;
        let st = runtime_status(RunState::Idle);
        let servos = servos();
        let mut window = CycleWindow::default();
        window.add(&[telemetry(vec![Some(0.1), Some(0.2)])]);
        let health = BusHealth {
            servos: vec![
                ServoHealth { id: 1, hardware_error: 0x04, temperature_c: Some(81), input_voltage_v: Some(12.0), ..Default::default() },
                ServoHealth { id: 2, comm_errors: 3, temperature_c: Some(72), input_voltage_v: Some(12.1), ..Default::default() },
            ],
            cycle_period_p99_ms: 8.2,
            scheduling: "SCHED_FIFO priority 50".into(),
            ..Default::default()
        };
        let snap = Snapshot { health: Some(&health), ..snapshot(&st, &servos) };
        let array = diagnostics(&snap, &mut window, Instant::now(), Time::default());
        let one = find(&array, "servo 1 (j1)");
        assert_eq!(one.level, ERROR);
        assert!(one.message.contains("overheating") && one.message.contains("reboot_servos"), "{}", one.message);
        assert!(one.values.iter().any(|v| v.key == "temperature_c" && v.value == "81"));
        let two = find(&array, "servo 2 (j2)");
        assert_eq!(two.level, WARN, "{}", two.message);
        assert!(two.message.contains("72 °C"), "{}", two.message);
        assert!(two.values.iter().any(|v| v.key == "comm_errors" && v.value == "3"));
        let cycle = find(&array, "control cycle");
        assert!(cycle.values.iter().any(|v| v.key == "scheduling" && v.value.contains("SCHED_FIFO")));
        let cool =
            BusHealth { servos: vec![ServoHealth { id: 2, input_voltage_v: Some(8.1), ..Default::default() }], ..Default::default() };
        let snap = Snapshot { health: Some(&cool), ..snapshot(&st, &servos) };
        let low = diagnostics(&snap, &mut window, Instant::now(), Time::default());
        assert!(find(&low, "servo 2 (j2)").message.contains("8.1 V"));
    }

    #[test]
    fn without_a_bus_the_bus_is_an_error_and_no_servo_is_listed() {
        let mut st = runtime_status(RunState::Idle);
        st.last_fault = "servo bus not available: /dev/ttyUSB0: no such file".into();
        st.library_size = 0;
        let servos = servos();
        let snap = Snapshot { has_bus: false, ..snapshot(&st, &servos) };
        let array = diagnostics(&snap, &mut CycleWindow::default(), Instant::now(), Time::default());
        assert_eq!(find(&array, "servo bus").level, ERROR);
        assert!(!array.status.iter().any(|s| s.name.contains("servo 1")));
        assert_eq!(find(&array, "motion library").level, WARN);
    }
}
