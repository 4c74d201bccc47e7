//! A bounded single-producer single-consumer ring: the bus thread hands values to the node without
//! a lock and without allocating (the slots are allocated once, at creation). [`Producer::push`]
//! and [`Consumer::pop`] are wait-free: one acquire load of the other side's index, one slot move,
//! one release store of their own index (Lamport's ring; indices count up, the slot is the index
//! modulo the power-of-two capacity). A full ring refuses the value and hands it back, so the
//! producer never waits for a slow consumer.
// The one unsafe module of step_executor: the slots are written by the producer and read by the
// consumer through `UnsafeCell`, the indices decide who owns which slot (see the SAFETY notes).
#![allow(unsafe_code)]

use std::cell::UnsafeCell;
use std::mem::MaybeUninit;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;

struct Ring<T> {
    slots: Box<[UnsafeCell<MaybeUninit<T>>]>,
    mask: usize,
    /// Next slot to pop; written by the consumer only.
    head: AtomicUsize,
    /// Next slot to push; written by the producer only.
    tail: AtomicUsize,
}

// SAFETY: a slot is accessed by one side at a time (the producer between `head + capacity` and
// `tail`, the consumer between `head` and `tail`), handed over by the release/acquire pairs on
// `tail` (producer → consumer) and `head` (consumer → producer); the values cross threads, so `T`
// must be `Send`.
unsafe impl<T: Send> Sync for Ring<T> {}
// SAFETY: as above; the ring owns values of `T` only.
unsafe impl<T: Send> Send for Ring<T> {}

impl<T> Ring<T> {
    fn slot(&self, index: usize) -> Option<&UnsafeCell<MaybeUninit<T>>> {
        self.slots.get(index & self.mask)
    }
}

impl<T> Drop for Ring<T> {
    fn drop(&mut self) {
        let (head, tail) = (*self.head.get_mut(), *self.tail.get_mut());
        let mut index = head;
        while index != tail {
            if let Some(slot) = self.slot(index) {
                // SAFETY: the slots from head to tail hold values pushed and not popped; `&mut
                // self` means neither side exists any more.
                unsafe { (*slot.get()).assume_init_drop() };
            }
            index = index.wrapping_add(1);
        }
    }
}

/// The pushing half (one thread).
pub struct Producer<T> {
    ring: Arc<Ring<T>>,
}

/// The popping half (one thread at a time: it needs `&mut`).
pub struct Consumer<T> {
    ring: Arc<Ring<T>>,
}

/// A ring of at least `capacity` slots (rounded up to a power of two, at least 1).
pub fn ring<T>(capacity: usize) -> (Producer<T>, Consumer<T>) {
    let capacity = capacity.max(1).next_power_of_two();
    let slots = (0..capacity).map(|_| UnsafeCell::new(MaybeUninit::uninit())).collect();
    let ring = Arc::new(Ring { slots, mask: capacity - 1, head: AtomicUsize::new(0), tail: AtomicUsize::new(0) });
    (Producer { ring: Arc::clone(&ring) }, Consumer { ring })
}

impl<T> Producer<T> {
    /// Append `value`, or hand it back when the ring is full.
    pub fn push(&mut self, value: T) -> Result<(), T> {
        let ring = &*self.ring;
        let tail = ring.tail.load(Ordering::Relaxed);
        let head = ring.head.load(Ordering::Acquire);
        if tail.wrapping_sub(head) > ring.mask {
            return Err(value);
        }
        let Some(slot) = ring.slot(tail) else { return Err(value) };
        // SAFETY: `tail - head < capacity`, so this slot is free: the consumer has moved its value
        // out (its release store of `head` happened before our acquire load) or it never held one,
        // and the consumer does not read it until our release store of `tail` below.
        unsafe { (*slot.get()).write(value) };
        ring.tail.store(tail.wrapping_add(1), Ordering::Release);
        Ok(())
    }
}

impl<T> Consumer<T> {
    /// The oldest value, if any.
    pub fn pop(&mut self) -> Option<T> {
        let ring = &*self.ring;
        let head = ring.head.load(Ordering::Relaxed);
        let tail = ring.tail.load(Ordering::Acquire);
        if head == tail {
            return None;
        }
        let slot = ring.slot(head)?;
        // SAFETY: `head != tail`, so the producer wrote this slot and published it with its release
        // store of `tail` (acquired above); it does not write it again until our release store of
        // `head` below. The value is moved out exactly once.
        let value = unsafe { (*slot.get()).assume_init_read() };
        ring.head.store(head.wrapping_add(1), Ordering::Release);
        Some(value)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::AtomicUsize;

    #[test]
    fn fifo_order_full_refusal_and_wrap_around() {
        let (mut tx, mut rx) = ring::<u32>(3);
        for i in 0..4 {
            assert_eq!(tx.push(i), Ok(()));
        }
        assert_eq!(tx.push(9), Err(9), "capacity rounds up to 4");
        for round in 0..10u32 {
            assert_eq!(rx.pop(), Some(round));
            assert_eq!(tx.push(round + 4), Ok(()));
        }
        let rest: Vec<u32> = std::iter::from_fn(|| rx.pop()).collect();
        assert_eq!(rest, vec![10, 11, 12, 13]);
        assert_eq!(rx.pop(), None);
    }

    #[test]
    fn values_left_in_the_ring_are_dropped_once() {
        struct Counted(Arc<AtomicUsize>);
        impl Drop for Counted {
            fn drop(&mut self) {
                self.0.fetch_add(1, Ordering::SeqCst);
            }
        }
        let drops = Arc::new(AtomicUsize::new(0));
        let (mut tx, mut rx) = ring(8);
        for _ in 0..5 {
            assert!(tx.push(Counted(Arc::clone(&drops))).is_ok());
        }
        drop(rx.pop());
        assert_eq!(drops.load(Ordering::SeqCst), 1);
        drop((tx, rx));
        assert_eq!(drops.load(Ordering::SeqCst), 5);
    }

    #[test]
    fn two_threads_see_every_value_in_order() {
        let (mut tx, mut rx) = ring::<Box<u64>>(16);
        const N: u64 = 200_000;
        let producer = std::thread::spawn(move || {
            let mut next = 0;
            while next < N {
                match tx.push(Box::new(next)) {
                    Ok(()) => next += 1,
                    Err(_) => std::thread::yield_now(),
                }
            }
        });
        let mut expected = 0;
        while expected < N {
            match rx.pop() {
                Some(value) => {
                    assert_eq!(*value, expected);
                    expected += 1;
                }
                None => std::thread::yield_now(),
            }
        }
        producer.join().unwrap();
        assert_eq!(rx.pop(), None);
    }
}
