//! The node clock: the wall clock, or with `use_sim_time` the time of `/clock`
//! (`rosgraph_msgs/Clock`, as rclcpp's `TimeSource` does), so a bag played with `--clock` or a
//! simulator drives the stamps. Every output of a node is stamped from its input's stamp or from
//! [`NodeClock::now`], never from the wall clock directly.
//!
//! `use_sim_time` is given like any parameter (`-p use_sim_time:=true`, `--param use_sim_time=true` or a
//! parameter file); [`crate::params::load_node_config`] takes it out of the node's config.

use std::sync::{Arc, Mutex};
use std::time::{SystemTime, UNIX_EPOCH};

use patchwalk_msgs::builtin_interfaces::msg::Time;
use patchwalk_msgs::rosgraph_msgs::msg::Clock;
use ros2_client::qos::{Durability, History, QosProfile};
use ros2_client::{Publisher, Subscription};

use crate::node::{self, NodeError, RateLimitedLog, RosNode};

/// The clock topic (rcl's default).
pub const CLOCK_TOPIC: &str = "/clock";

/// The parameter naming the clock source (rcl's name).
pub const USE_SIM_TIME: &str = "use_sim_time";

/// `rclcpp::ClockQoS`: best effort, volatile, keep last 1 (a late clock tick is worth nothing). A
/// best-effort reader also matches reliable `/clock` publishers (rosbag2 uses this profile too).
pub fn clock_qos() -> QosProfile {
    QosProfile::subscription_default().reliability_best_effort().durability(Durability::Volatile).history(History::KeepLast { depth: 1 })
}

/// Nanoseconds since the epoch of a `builtin_interfaces/Time`.
pub fn stamp_ns(time: &Time) -> i64 {
    i64::from(time.sec) * 1_000_000_000 + i64::from(time.nanosec)
}

/// Seconds since the epoch of a `builtin_interfaces/Time`.
pub fn stamp_s(time: &Time) -> f64 {
    f64::from(time.sec) + f64::from(time.nanosec) * 1e-9
}

/// `builtin_interfaces/Time` of nanoseconds since the epoch (saturating at the message's range).
pub fn time_from_ns(ns: i64) -> Time {
    let sec = ns.div_euclid(1_000_000_000);
    let nanosec = ns.rem_euclid(1_000_000_000) as u32;
    match i32::try_from(sec) {
        Ok(sec) => Time { sec, nanosec },
        Err(_) if sec < 0 => Time { sec: i32::MIN, nanosec: 0 },
        Err(_) => Time { sec: i32::MAX, nanosec: 999_999_999 },
    }
}

/// The time source of a node, cheap to clone and share between its threads.
#[derive(Debug, Clone, Default)]
pub struct NodeClock {
    /// `Some` with `use_sim_time`: the last `/clock` (ns), `None` inside until the first arrives.
    sim: Option<Arc<Mutex<Option<i64>>>>,
}

impl NodeClock {
    /// The wall clock.
    pub fn wall() -> Self {
        Self { sim: None }
    }

    /// Simulated time, set by [`NodeClock::set_sim_time`] (from `/clock` through [`ClockListener`]).
    pub fn sim() -> Self {
        Self { sim: Some(Arc::default()) }
    }

    /// [`NodeClock::sim`] or [`NodeClock::wall`].
    pub fn new(use_sim_time: bool) -> Self {
        if use_sim_time {
            Self::sim()
        } else {
            Self::wall()
        }
    }

    pub fn is_sim(&self) -> bool {
        self.sim.is_some()
    }

    /// The current time in ns, `None` for simulated time before the first `/clock`.
    pub fn now_ns_if_known(&self) -> Option<i64> {
        match &self.sim {
            None => {
                let since_epoch = SystemTime::now().duration_since(UNIX_EPOCH).unwrap_or_default();
                Some(i64::try_from(since_epoch.as_nanos()).unwrap_or(i64::MAX))
            }
            Some(sim) => sim.lock().ok().and_then(|t| *t),
        }
    }

    /// The current time (0 for simulated time before the first `/clock`, as rclcpp).
    pub fn now(&self) -> Time {
        time_from_ns(self.now_ns_if_known().unwrap_or(0))
    }

    /// The current time in s (0 before the first `/clock`).
    pub fn now_s(&self) -> f64 {
        stamp_s(&self.now())
    }

    /// Sets simulated time (ignored on the wall clock). Time may jump back (a bag restarted).
    pub fn set_sim_time(&self, time: &Time) {
        if let Some(sim) = &self.sim {
            if let Ok(mut t) = sim.lock() {
                *t = Some(stamp_ns(time));
            }
        }
    }
}

/// The `/clock` subscription of a node with `use_sim_time` (drained by its loop).
pub struct ClockListener {
    pub subscription: Subscription<Clock>,
    clock: NodeClock,
    log: RateLimitedLog,
}

impl ClockListener {
    /// Subscribes `/clock` when `clock` is simulated; `None` for the wall clock.
    pub fn new(ros: &mut RosNode, clock: &NodeClock) -> Result<Option<Self>, NodeError> {
        if !clock.is_sim() {
            return Ok(None);
        }
        let subscription = ros.subscription::<Clock>(CLOCK_TOPIC, clock_qos())?;
        Ok(Some(Self { subscription, clock: clock.clone(), log: RateLimitedLog::default() }))
    }

    /// Takes the pending `/clock` messages (the newest wins); returns how many.
    pub fn drain(&mut self) -> usize {
        let clock = &self.clock;
        node::drain(&self.subscription, CLOCK_TOPIC, 64, &mut self.log, |msg, _| clock.set_sim_time(&msg.clock))
    }
}

/// Publishes `/clock` (a simulator's time, [`clock_qos`]).
pub struct ClockPublisher {
    publisher: Publisher<Clock>,
    log: RateLimitedLog,
}

impl ClockPublisher {
    pub fn new(ros: &mut RosNode) -> Result<Self, NodeError> {
        let publisher = ros.publisher::<Clock>(CLOCK_TOPIC, clock_qos())?;
        Ok(Self { publisher, log: RateLimitedLog::default() })
    }

    pub fn publish(&mut self, time: Time) {
        node::publish(&self.publisher, CLOCK_TOPIC, Clock { clock: time }, &mut self.log);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stamps_convert_both_ways() {
        let t = Time { sec: 12, nanosec: 345_000_000 };
        assert_eq!(stamp_ns(&t), 12_345_000_000);
        assert_eq!(time_from_ns(12_345_000_000), t);
        assert_eq!(time_from_ns(-1), Time { sec: -1, nanosec: 999_999_999 });
        assert_eq!(time_from_ns(i64::MAX).sec, i32::MAX);
        assert!((stamp_s(&t) - 12.345).abs() < 1e-12);
    }

    #[test]
    fn sim_time_follows_the_clock_messages_and_starts_unknown() {
        let clock = NodeClock::sim();
        assert_eq!(clock.now_ns_if_known(), None);
        assert_eq!(clock.now(), Time { sec: 0, nanosec: 0 });
        let shared = clock.clone();
        shared.set_sim_time(&Time { sec: 5, nanosec: 500 });
        assert_eq!(clock.now_ns_if_known(), Some(5_000_000_500));
        shared.set_sim_time(&Time { sec: 1, nanosec: 0 });
        assert_eq!(clock.now().sec, 1, "a jump back (bag restart) is followed");
        let wall = NodeClock::wall();
        wall.set_sim_time(&Time { sec: 1, nanosec: 0 });
        assert!(wall.now().sec > 1_577_836_800);
    }
}
