//! The operator's deadman: automatic execution may only be armed while heartbeats arrive on
//! [`HEARTBEAT_TOPIC`] (`std_msgs/Empty`, any rate faster than the timeout; best effort, so a
//! reliable or best-effort publisher both match). Once armed, the deadman stays engaged until the
//! armed step is over (disarmed, e-stopped, or the motion started by the match has ended); if no
//! heartbeat comes for `ros.heartbeat_timeout_s` (default 0.5 s) meanwhile, the executor disarms by
//! itself, holds a running motion and reports why (status `last_fault`, /diagnostics).
//!
//! Motions started directly (`play_motion` service or action) are not under the deadman: their
//! caller is present by definition, and can cancel or e-stop them.

use std::time::{Duration, Instant};

use ros2_client::qos::{Durability, History, QosProfile};

/// `std_msgs/Empty` from the operator's station (or anything that vouches for a person watching).
pub const HEARTBEAT_TOPIC: &str = "/step_executor/heartbeat";

/// Best effort, volatile, keep last 1: only the arrival matters.
pub fn heartbeat_qos() -> QosProfile {
    QosProfile::subscription_default().reliability_best_effort().durability(Durability::Volatile).history(History::KeepLast { depth: 1 })
}

/// Heartbeat bookkeeping (ROS-free: times are passed in).
#[derive(Debug, Clone)]
pub struct Deadman {
    timeout: Duration,
    last_beat: Option<Instant>,
    engaged: bool,
}

impl Deadman {
    pub fn new(timeout: Duration) -> Self {
        Self { timeout, last_beat: None, engaged: false }
    }

    /// A heartbeat arrived at `now`.
    pub fn beat(&mut self, now: Instant) {
        self.last_beat = Some(now);
    }

    /// Time since the last heartbeat (`None`: none seen yet).
    pub fn age(&self, now: Instant) -> Option<Duration> {
        self.last_beat.map(|at| now.saturating_duration_since(at))
    }

    /// Whether arming is allowed at `now`: a heartbeat within the timeout. The error says why not.
    pub fn check_arm(&self, now: Instant) -> Result<(), String> {
        match self.age(now) {
            None => Err(format!(
                "no heartbeat seen on {HEARTBEAT_TOPIC}; publish std_msgs/Empty there at least every {:.2} s to arm",
                self.timeout.as_secs_f64()
            )),
            Some(age) if age > self.timeout => Err(format!(
                "the last heartbeat on {HEARTBEAT_TOPIC} is {:.2} s old (timeout {:.2} s); publish std_msgs/Empty there to arm",
                age.as_secs_f64(),
                self.timeout.as_secs_f64()
            )),
            Some(_) => Ok(()),
        }
    }

    /// The armed step starts: watch the heartbeats from now on.
    pub fn engage(&mut self) {
        self.engaged = true;
    }

    /// The armed step is over (disarmed, e-stopped, motion ended).
    pub fn disengage(&mut self) {
        self.engaged = false;
    }

    /// The armed step ended by itself (its motion is over) at `now`: disengage. When the heartbeats
    /// had already stopped for longer than the timeout, the deadman should have held the motion
    /// before it ended, and the loop did not run in time to: say so.
    pub fn end_step(&mut self, now: Instant) -> Option<String> {
        let was_engaged = std::mem::replace(&mut self.engaged, false);
        let age = self.age(now).filter(|age| was_engaged && *age > self.timeout)?;
        Some(format!(
            "deadman: the armed step ended {:.2} s after the last heartbeat on {HEARTBEAT_TOPIC}, past the {:.2} s timeout, \
             without being held: the executor's loop did not run in between",
            age.as_secs_f64(),
            self.timeout.as_secs_f64()
        ))
    }

    pub fn engaged(&self) -> bool {
        self.engaged
    }

    /// When the deadman expires if no heartbeat comes (for the loop's wake-up), while engaged.
    pub fn deadline(&self) -> Option<Instant> {
        match (self.engaged, self.last_beat) {
            (true, Some(at)) => Some(at + self.timeout),
            _ => None,
        }
    }

    /// While engaged and the heartbeats stopped for longer than the timeout: disengage and say why.
    pub fn expired(&mut self, now: Instant) -> Option<String> {
        if !self.engaged {
            return None;
        }
        let age = self.age(now)?;
        if age <= self.timeout {
            return None;
        }
        self.engaged = false;
        Some(format!(
            "deadman: no heartbeat on {HEARTBEAT_TOPIC} for {:.2} s (timeout {:.2} s); disarmed, motion held",
            age.as_secs_f64(),
            self.timeout.as_secs_f64()
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const T: Duration = Duration::from_millis(500);

    #[test]
    fn arming_needs_a_recent_heartbeat() {
        let t0 = Instant::now();
        let mut deadman = Deadman::new(T);
        let refused = deadman.check_arm(t0).unwrap_err();
        assert!(refused.contains("no heartbeat") && refused.contains(HEARTBEAT_TOPIC), "{refused}");
        deadman.beat(t0);
        assert!(deadman.check_arm(t0 + Duration::from_millis(400)).is_ok());
        let stale = deadman.check_arm(t0 + Duration::from_millis(700)).unwrap_err();
        assert!(stale.contains("0.70 s old"), "{stale}");
    }

    #[test]
    fn an_engaged_deadman_expires_once_after_the_timeout() {
        let t0 = Instant::now();
        let mut deadman = Deadman::new(T);
        deadman.beat(t0);
        // Not engaged: never expires.
        assert_eq!(deadman.expired(t0 + Duration::from_secs(5)), None);
        assert_eq!(deadman.deadline(), None);
        deadman.engage();
        assert_eq!(deadman.deadline(), Some(t0 + T));
        deadman.beat(t0 + Duration::from_millis(300));
        assert_eq!(deadman.expired(t0 + Duration::from_millis(700)), None, "kept alive by the second beat");
        let reason = deadman.expired(t0 + Duration::from_millis(900)).unwrap();
        assert!(reason.contains("0.60 s") && reason.contains("disarmed"), "{reason}");
        assert!(!deadman.engaged());
        assert_eq!(deadman.expired(t0 + Duration::from_secs(2)), None, "reported once");
    }

    #[test]
    fn a_disengaged_deadman_stays_quiet() {
        let t0 = Instant::now();
        let mut deadman = Deadman::new(T);
        deadman.beat(t0);
        deadman.engage();
        deadman.disengage();
        assert_eq!(deadman.expired(t0 + Duration::from_secs(1)), None);
        // A step that ends in time says nothing; one that ends after the timeout unheld says so.
        deadman.engage();
        assert_eq!(deadman.end_step(t0 + Duration::from_millis(400)), None);
        assert!(!deadman.engaged());
        deadman.engage();
        let late = deadman.end_step(t0 + Duration::from_secs(4)).unwrap();
        assert!(late.contains("4.00 s") && late.contains("without being held"), "{late}");
        assert_eq!(deadman.end_step(t0 + Duration::from_secs(5)), None, "not engaged any more");
    }
}
