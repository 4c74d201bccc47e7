//! Waiting for input instead of polling: a node's loop registers its subscriptions and service
//! servers (ros2-client's mio sources) with a [`Wakeup`] and sleeps in [`Wakeup::wait`] until one of
//! them has data, another thread calls the [`mio::Waker`], or the next periodic duty is due.
//!
//! One token serves every source: on any wake-up the loop drains all its inputs without blocking,
//! which is cheap, so it does not need to know which one fired. A loop that stopped draining before
//! an input was empty (a bound per pass) waits with a zero timeout, because readiness is reported
//! once per arrival, not while data is left.

use std::sync::Arc;
use std::time::Duration;

use mio::{Events, Interest, Poll, Token, Waker};

use crate::node::NodeError;

const SOURCES: Token = Token(0);
const WAKER: Token = Token(1);

/// The readiness set of one node loop.
pub struct Wakeup {
    poll: Poll,
    events: Events,
    waker: Arc<Waker>,
}

impl Wakeup {
    pub fn new() -> Result<Self, NodeError> {
        let poll = Poll::new().map_err(NodeError::Wait)?;
        let waker = Arc::new(Waker::new(poll.registry(), WAKER).map_err(NodeError::Wait)?);
        Ok(Self { poll, events: Events::with_capacity(64), waker })
    }

    /// Wake the loop when `source` (a `Subscription` or `Server`) has data.
    pub fn watch(&self, source: &mut impl mio::event::Source) -> Result<(), NodeError> {
        self.poll.registry().register(source, SOURCES, Interest::READABLE).map_err(NodeError::Wait)
    }

    /// For other threads (a worker finishing a job, a control thread with news): `wake()` it.
    pub fn waker(&self) -> Arc<Waker> {
        Arc::clone(&self.waker)
    }

    /// Block until an input is ready, the waker is called, or `timeout` has passed. Returns whether
    /// anything woke it before the timeout. An interrupted wait (a signal) returns at once.
    pub fn wait(&mut self, timeout: Duration) -> bool {
        match self.poll.poll(&mut self.events, Some(timeout)) {
            Ok(()) => !self.events.is_empty(),
            Err(_) => true,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Instant;

    #[test]
    fn the_waker_ends_a_wait_and_a_timeout_ends_an_idle_one() {
        let mut wakeup = Wakeup::new().unwrap();
        let waker = wakeup.waker();
        let thread = std::thread::spawn(move || {
            std::thread::sleep(Duration::from_millis(20));
            waker.wake().unwrap();
        });
        assert!(wakeup.wait(Duration::from_secs(10)), "woken by the other thread");
        thread.join().unwrap();
        let start = Instant::now();
        assert!(!wakeup.wait(Duration::from_millis(10)), "nothing to report");
        assert!(start.elapsed() >= Duration::from_millis(10));
    }
}
