//! A triple buffer: one writer thread publishes a value, one reader thread takes the newest one,
//! neither ever waits for the other nor allocates. Three buffers: the writer owns one (it fills it),
//! the reader owns one (it reads it), the third is the hand-over slot. Publishing swaps the writer's
//! buffer with the hand-over slot and marks it fresh; reading swaps the reader's buffer with the
//! hand-over slot when that is fresh. Each swap is one atomic exchange of a 2-bit buffer index (plus
//! the fresh bit), so every buffer has exactly one owner at any time.
// The second unsafe module of step_executor: the buffers are shared through `UnsafeCell`, and the
// index exchanges decide who owns which (see the SAFETY notes).
#![allow(unsafe_code)]

use std::cell::UnsafeCell;
use std::sync::atomic::{AtomicU8, Ordering};
use std::sync::Arc;

const FRESH: u8 = 0b100;
const INDEX: u8 = 0b011;

struct Shared<T> {
    buffers: [UnsafeCell<T>; 3],
    /// The hand-over slot's buffer index, with [`FRESH`] when published and not read yet.
    back: AtomicU8,
}

// SAFETY: a buffer is reached only by the side whose index names it (writer, reader) and the
// hand-over index changes hands by atomic exchange with acquire-release ordering, which orders the
// writer's writes before the reader's reads; values cross threads, so `T` must be `Send`.
unsafe impl<T: Send> Sync for Shared<T> {}
// SAFETY: as above.
unsafe impl<T: Send> Send for Shared<T> {}

/// The publishing half.
pub struct Writer<T> {
    shared: Arc<Shared<T>>,
    index: u8,
}

/// The reading half.
pub struct Reader<T> {
    shared: Arc<Shared<T>>,
    index: u8,
}

/// A triple buffer whose three buffers start as `initial`.
pub fn triple_buffer<T: Clone>(initial: &T) -> (Writer<T>, Reader<T>) {
    let shared = Arc::new(Shared {
        buffers: [UnsafeCell::new(initial.clone()), UnsafeCell::new(initial.clone()), UnsafeCell::new(initial.clone())],
        back: AtomicU8::new(1),
    });
    (Writer { shared: Arc::clone(&shared), index: 0 }, Reader { shared, index: 2 })
}

fn buffer<T>(shared: &Shared<T>, index: u8) -> &UnsafeCell<T> {
    // The index is always 0, 1 or 2 (masked); the fallback is never taken.
    let [first, second, third] = &shared.buffers;
    match index & INDEX {
        1 => second,
        2 => third,
        _ => first,
    }
}

impl<T> Writer<T> {
    /// The writer's buffer, to fill before [`Writer::publish`] (it holds an older value).
    pub fn input(&mut self) -> &mut T {
        // SAFETY: `self.index` names the buffer this writer owns: no one else reaches it until
        // `publish` hands it over, and `&mut self` makes this the only reference.
        unsafe { &mut *buffer(&self.shared, self.index).get() }
    }

    /// Hand the filled buffer to the reader (replacing a value it has not read yet).
    pub fn publish(&mut self) {
        let previous = self.shared.back.swap(self.index | FRESH, Ordering::AcqRel);
        self.index = previous & INDEX;
    }
}

impl<T> Reader<T> {
    /// The newest published value (the same as last time when nothing new was published).
    pub fn read(&mut self) -> &T {
        if self.shared.back.load(Ordering::Relaxed) & FRESH != 0 {
            let previous = self.shared.back.swap(self.index, Ordering::AcqRel);
            self.index = previous & INDEX;
        }
        // SAFETY: `self.index` names the buffer this reader owns (taken by the exchange above, or
        // kept); the writer never reaches it, and `&mut self` ties the reference to this reader.
        unsafe { &*buffer(&self.shared, self.index).get() }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_reader_sees_the_newest_value_and_never_a_torn_one() {
        let (mut writer, mut reader) = triple_buffer(&0u32);
        assert_eq!(*reader.read(), 0);
        for i in 1..=5 {
            *writer.input() = i;
            writer.publish();
        }
        assert_eq!(*reader.read(), 5, "the newest, unread ones replaced");
        assert_eq!(*reader.read(), 5, "nothing new: the same");
        let (mut writer, mut reader) = triple_buffer(&[0u64; 64]);
        let thread = std::thread::spawn(move || {
            for i in 1..=100_000u64 {
                *writer.input() = [i; 64];
                writer.publish();
            }
        });
        let mut last = 0;
        while last < 100_000 {
            let value = *reader.read();
            assert!(value.iter().all(|v| *v == value[0]), "torn read");
            assert!(value[0] >= last, "went back from {last} to {}", value[0]);
            last = value[0];
        }
        thread.join().unwrap();
    }
}
