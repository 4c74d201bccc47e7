//! The e-stop topic: a `std_msgs/Bool` `true` on [`ESTOP_TOPIC`], from anyone, latches the e-stop
//! exactly as the `stop` service does (every motion held within one cycle, new ones refused). The
//! latched state is republished on [`ESTOP_STATE_TOPIC`] (transient local, so a subscriber that
//! comes late sees it at once). Clearing stays the separate `reset_estop` service: a `false` on the
//! topic is ignored (and logged), so a stale or repeated publisher can never release a stop.
//!
//! Both topics are reliable, transient local, keep last 1: an e-stop published before the node
//! started (or before it matched the publisher) is still delivered once it matches.

use ros2_client::dds::{Publisher, Subscription};
use ros2_client::qos::{Durability, History, QosProfile, WhenFull};

use patchwalk_msgs::std_msgs::msg::Bool;
use patchwalk_ros::node::{self, NodeError, RateLimitedLog, RosNode};

/// `std_msgs/Bool`: `true` latches the e-stop.
pub const ESTOP_TOPIC: &str = "/step_executor/estop";
/// `std_msgs/Bool`: whether the e-stop is latched (published on every change and at start).
pub const ESTOP_STATE_TOPIC: &str = "/step_executor/estop_state";

/// Reliable, transient local, keep last 1: the last value reaches subscribers that join later.
pub fn latched_qos() -> QosProfile {
    QosProfile::publisher_default()
        .reliability_reliable(WhenFull::DEFAULT)
        .durability(Durability::TransientLocal)
        .history(History::KeepLast { depth: 1 })
}

/// The e-stop subscription and the latched-state publisher.
pub struct EStopTopic {
    sub: Subscription<Bool>,
    state_pub: Publisher<Bool>,
    /// The state last published (`None` before the first publication).
    published: Option<bool>,
}

impl EStopTopic {
    pub fn new(ros: &mut RosNode) -> Result<Self, NodeError> {
        let sub = ros.subscription::<Bool>(&ros.relative(ESTOP_TOPIC), latched_qos())?;
        let state_pub = ros.publisher::<Bool>(&ros.relative(ESTOP_STATE_TOPIC), latched_qos())?;
        Ok(Self { sub, state_pub, published: None })
    }

    /// The subscription, to wake the loop when a message arrives.
    pub fn source(&mut self) -> &mut Subscription<Bool> {
        &mut self.sub
    }

    /// Take every pending message and return how many were `true` (each one is an e-stop).
    pub fn take_stops(&self, log: &mut RateLimitedLog) -> usize {
        let mut stops = 0;
        let mut ignored = 0;
        // Bounded only to survive a flood; the e-stop path runs before anything else in a pass.
        node::drain(&self.sub, ESTOP_TOPIC, 1024, log, |msg, _| if msg.data { stops += 1 } else { ignored += 1 });
        if ignored > 0 {
            log.warn(
                "estop_false",
                format_args!("{ESTOP_TOPIC}: `false` ignored ({ignored}x); a latched e-stop is cleared only by the reset_estop service"),
            );
        }
        stops
    }

    /// Publish the latched state if it changed since the last publication (and the first time).
    pub fn publish_state(&mut self, estopped: bool, log: &mut RateLimitedLog) {
        if self.published != Some(estopped) {
            node::publish(&self.state_pub, ESTOP_STATE_TOPIC, Bool { data: estopped }, log);
            self.published = Some(estopped);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ros2_client::qos::Reliability;

    #[test]
    fn latched_qos_is_reliable_transient_local_depth_one() {
        let qos = latched_qos();
        assert!(matches!(qos.reliability, Reliability::Reliable { .. }));
        assert_eq!(qos.durability, Durability::TransientLocal);
        assert_eq!(qos.history, History::KeepLast { depth: 1 });
    }
}
