//! A keep-latest hand-off between two threads: the producer never waits, an item still waiting when
//! a newer one comes is dropped (and counted), the consumer takes the newest item or times out.
//!
//! The foothold stage takes its frames through one, so a slow network drops frames instead of
//! holding the pipeline (and with it PatchArray) back.

use std::sync::{Condvar, Mutex};
use std::time::Duration;

/// One slot and its counters.
#[derive(Debug, Default)]
pub struct Latest<T> {
    state: Mutex<Slot<T>>,
    ready: Condvar,
}

#[derive(Debug)]
struct Slot<T> {
    item: Option<T>,
    offered: u64,
    dropped: u64,
    closed: bool,
}

impl<T> Default for Slot<T> {
    fn default() -> Self {
        Self { item: None, offered: 0, dropped: 0, closed: false }
    }
}

/// What [`Latest::take_timeout`] found.
#[derive(Debug, PartialEq)]
pub enum Taken<T> {
    Item(T),
    /// Nothing came within the timeout.
    Timeout,
    /// [`Latest::close`] was called: the consumer should stop.
    Closed,
}

/// Counters of a slot: items offered and items dropped for a newer one.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct LatestCounts {
    pub offered: u64,
    pub dropped: u64,
}

impl<T> Latest<T> {
    pub fn new() -> Self {
        Self { state: Mutex::new(Slot::default()), ready: Condvar::new() }
    }

    /// Puts `item` in the slot; returns true when it replaced an item nobody had taken (dropped).
    pub fn offer(&self, item: T) -> bool {
        let Ok(mut slot) = self.state.lock() else { return false };
        slot.offered += 1;
        let replaced = slot.item.replace(item).is_some();
        if replaced {
            slot.dropped += 1;
        }
        drop(slot);
        self.ready.notify_one();
        replaced
    }

    /// The newest item, waiting up to `timeout` for one.
    pub fn take_timeout(&self, timeout: Duration) -> Taken<T> {
        let Ok(slot) = self.state.lock() else { return Taken::Closed };
        let Ok((mut slot, _)) = self.ready.wait_timeout_while(slot, timeout, |s| s.item.is_none() && !s.closed) else {
            return Taken::Closed;
        };
        if slot.closed {
            return Taken::Closed;
        }
        slot.item.take().map_or(Taken::Timeout, Taken::Item)
    }

    /// Wakes the consumer for good (shutdown).
    pub fn close(&self) {
        if let Ok(mut slot) = self.state.lock() {
            slot.closed = true;
        }
        self.ready.notify_all();
    }

    pub fn counts(&self) -> LatestCounts {
        self.state.lock().map(|s| LatestCounts { offered: s.offered, dropped: s.dropped }).unwrap_or_default()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Arc;

    #[test]
    fn the_newest_item_wins_and_the_older_ones_are_counted_as_dropped() {
        let latest = Latest::new();
        assert_eq!(latest.take_timeout(Duration::from_millis(1)), Taken::Timeout);
        assert!(!latest.offer(1));
        assert!(latest.offer(2));
        assert!(latest.offer(3));
        assert_eq!(latest.take_timeout(Duration::ZERO), Taken::Item(3));
        assert_eq!(latest.take_timeout(Duration::from_millis(1)), Taken::Timeout);
        assert!(!latest.offer(4), "the slot was empty again");
        assert_eq!(latest.counts(), LatestCounts { offered: 4, dropped: 2 });
        latest.close();
        assert_eq!(latest.take_timeout(Duration::from_secs(10)), Taken::Closed);
    }

    #[test]
    fn a_slow_consumer_never_blocks_the_producer() {
        let latest = Arc::new(Latest::new());
        let consumer = {
            let latest = latest.clone();
            std::thread::spawn(move || {
                let mut seen = Vec::new();
                loop {
                    match latest.take_timeout(Duration::from_millis(5)) {
                        Taken::Item(i) => {
                            seen.push(i);
                            if i == 199 {
                                return seen;
                            }
                            // A consumer much slower than the producer.
                            std::thread::sleep(Duration::from_millis(20));
                        }
                        Taken::Timeout => {}
                        Taken::Closed => return seen,
                    }
                }
            })
        };
        // The producer offers 200 items without waiting on the consumer.
        for i in 0..200 {
            latest.offer(i);
            std::thread::sleep(Duration::from_micros(200));
        }
        // The consumer ends when it has the last item (which is never dropped: nothing replaces it).
        let seen = consumer.join().unwrap();
        let counts = latest.counts();
        assert_eq!(counts.offered, 200);
        assert!(!seen.is_empty() && seen.len() < 200, "{} taken", seen.len());
        assert!(seen.windows(2).all(|w| w[0] < w[1]), "items are taken in order, newest first: {seen:?}");
        assert_eq!(seen.last(), Some(&199), "the last item is not lost");
        // Every item was either taken or dropped for a newer one.
        assert_eq!(counts.dropped + seen.len() as u64, 200);
    }
}
