//! What the bus thread hands to the rest of the node, without a lock or an allocation on its side:
//! - telemetry, one record per cycle, through a bounded [`spsc`] ring ([`TelemetryReceiver`] on the
//!   node's side; a full ring drops the record instead of waiting);
//! - the bus health, through a [`triple_buffer`]: the bus thread copies the current health into
//!   its buffer (reusing its text and per-servo storage) and publishes it; the reader takes the
//!   newest.
//!
//! The receiving halves serialise their own callers with a mutex that the bus thread never takes.

use std::sync::Mutex;
use std::time::{Duration, Instant};

use crate::health::BusHealth;
use crate::spsc::{self, Consumer, Producer};
use crate::triple_buffer::{triple_buffer, Reader, Writer};

/// No telemetry arrived (within the timeout, for [`TelemetryReceiver::recv_timeout`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("no telemetry from the bus thread")]
pub struct NoTelemetry;

/// How often [`TelemetryReceiver::recv_timeout`] looks for a record.
const POLL: Duration = Duration::from_micros(250);

/// The node's end of the telemetry ring.
pub struct TelemetryReceiver<T> {
    ring: Mutex<Consumer<T>>,
}

/// A telemetry ring of `capacity` records: the bus thread's producer and the node's receiver.
pub fn telemetry<T>(capacity: usize) -> (Producer<T>, TelemetryReceiver<T>) {
    let (tx, rx) = spsc::ring(capacity);
    (tx, TelemetryReceiver { ring: Mutex::new(rx) })
}

impl<T> TelemetryReceiver<T> {
    /// The oldest record not taken yet.
    pub fn try_recv(&self) -> Result<T, NoTelemetry> {
        self.ring.lock().unwrap_or_else(|poisoned| poisoned.into_inner()).pop().ok_or(NoTelemetry)
    }

    /// Every record not taken yet, oldest first.
    pub fn try_iter(&self) -> impl Iterator<Item = T> + '_ {
        std::iter::from_fn(|| self.try_recv().ok())
    }

    /// The oldest record, waiting up to `timeout` for one (checking every 0.25 ms).
    pub fn recv_timeout(&self, timeout: Duration) -> Result<T, NoTelemetry> {
        let deadline = Instant::now() + timeout;
        loop {
            if let Ok(record) = self.try_recv() {
                return Ok(record);
            }
            if Instant::now() >= deadline {
                return Err(NoTelemetry);
            }
            std::thread::sleep(POLL);
        }
    }
}

/// The bus thread's end of the health hand-over.
pub struct HealthSender {
    buffers: Writer<BusHealth>,
}

/// The node's end of the health hand-over.
pub struct HealthReceiver {
    buffers: Mutex<Reader<BusHealth>>,
}

/// The health hand-over, starting at `initial` (its three buffers are allocated here).
pub fn health(initial: &BusHealth) -> (HealthSender, HealthReceiver) {
    let (writer, reader) = triple_buffer(initial);
    (HealthSender { buffers: writer }, HealthReceiver { buffers: Mutex::new(reader) })
}

impl HealthSender {
    /// Hand `health` over: copied into the bus thread's buffer (reusing its text and per-servo
    /// storage, so nothing is allocated once the buffers have held texts as long), then published.
    pub fn publish(&mut self, health: &BusHealth) {
        self.buffers.input().copy_from(health);
        self.buffers.publish();
    }
}

impl HealthReceiver {
    /// The newest health handed over.
    pub fn latest(&self) -> BusHealth {
        self.buffers.lock().unwrap_or_else(|poisoned| poisoned.into_inner()).read().clone()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_reader_sees_the_newest_health() {
        let mut health = BusHealth { cycles: 1, scheduling: "start".into(), ..Default::default() };
        let (mut tx, rx) = super::health(&health);
        assert_eq!(rx.latest().cycles, 1);
        for cycles in 2..10 {
            health.cycles = cycles;
            tx.publish(&health);
        }
        assert_eq!(rx.latest().cycles, 9);
        health.scheduling = "SCHED_FIFO priority 50".into();
        tx.publish(&health);
        let latest = rx.latest();
        assert_eq!((latest.cycles, latest.scheduling.as_str()), (9, "SCHED_FIFO priority 50"));
    }

    #[test]
    fn telemetry_in_order_and_timeout() {
        let (mut tx, rx) = telemetry::<u32>(4);
        assert_eq!(rx.try_recv(), Err(NoTelemetry));
        assert_eq!(rx.recv_timeout(Duration::from_millis(1)), Err(NoTelemetry));
        for i in 0..5 {
            let _ = tx.push(i);
        }
        assert_eq!(rx.try_iter().collect::<Vec<_>>(), vec![0, 1, 2, 3], "the fifth was dropped, not waited for");
    }
}
