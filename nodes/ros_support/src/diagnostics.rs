//! REP-107 diagnostics shared by the nodes: the `/diagnostics` topic and period, and builders of
//! `diagnostic_msgs` key/values, statuses (named `<hardware id>: <name>`, the hardware id being the
//! node's name) and arrays.

use std::time::Duration;

use patchwalk_msgs::builtin_interfaces::msg::Time;
use patchwalk_msgs::diagnostic_msgs::msg::{DiagnosticArray, DiagnosticStatus, KeyValue};
use patchwalk_msgs::std_msgs::msg::Header;

/// The diagnostics topic (REP-107).
pub const DIAGNOSTICS_TOPIC: &str = "/diagnostics";
/// How often a node publishes its array.
pub const DIAGNOSTICS_PERIOD: Duration = Duration::from_secs(1);

/// One key/value of a status.
pub fn kv(key: &str, value: impl ToString) -> KeyValue {
    KeyValue { key: key.to_string(), value: value.to_string() }
}

/// A status of `hardware_id`, named `<hardware_id>: <name>`.
pub fn status(hardware_id: &str, level: u8, name: &str, message: impl Into<String>, values: Vec<KeyValue>) -> DiagnosticStatus {
    DiagnosticStatus {
        level,
        name: format!("{hardware_id}: {name}"),
        message: message.into(),
        hardware_id: hardware_id.to_string(),
        values,
    }
}

/// The array of `statuses`, stamped `stamp` (the node clock's now: `/clock` under `use_sim_time`).
pub fn array(stamp: Time, statuses: Vec<DiagnosticStatus>) -> DiagnosticArray {
    DiagnosticArray { header: Header { stamp, frame_id: String::new() }, status: statuses }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn statuses_are_named_by_their_hardware_id() {
        let s = status("step_executor", DiagnosticStatus::WARN, "servo bus", "slow", vec![kv("rate_hz", 5.0)]);
        assert_eq!(s.name, "step_executor: servo bus");
        assert_eq!(s.hardware_id, "step_executor");
        assert_eq!(s.values[0].value, "5");
        let stamp = Time { sec: 12, nanosec: 5 };
        let a = array(stamp.clone(), vec![s]);
        assert_eq!(a.status.len(), 1);
        assert_eq!(a.header.stamp, stamp);
    }
}
