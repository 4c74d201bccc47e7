//! Scheduling priority of latency-critical threads (a control loop, a simulated servo chain).
//!
//! [`make_realtime`] asks for `SCHED_FIFO` at a given priority (Linux, root or `CAP_SYS_NICE`, or an
//! `RLIMIT_RTPRIO` allowing it). Where that is not permitted (an unprivileged user, a container
//! without the capability) it falls back to nice -15, and where that is not permitted either the
//! thread keeps its priority; the outcome says which, so the caller can log it once.

/// What [`make_realtime`] achieved for the calling thread.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Priority {
    /// `SCHED_FIFO` at this priority (1..=99): preempts every normal thread.
    Fifo(i32),
    /// `SCHED_FIFO` was refused; the thread runs at nice -15.
    Nice,
    /// Neither was permitted; the thread keeps its priority.
    Unchanged,
}

impl std::fmt::Display for Priority {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Priority::Fifo(p) => write!(f, "SCHED_FIFO priority {p}"),
            Priority::Nice => write!(f, "SCHED_FIFO not permitted; nice -15 (cycle jitter grows with the host's load)"),
            Priority::Unchanged => {
                write!(f, "neither SCHED_FIFO nor nice -15 permitted; normal priority (cycle jitter grows with the host's load)")
            }
        }
    }
}

/// Best effort: run the calling thread at nice -15 (control loops and the simulated servo chain are
/// latency-critical). Without the privilege the thread keeps its priority; nothing else changes.
/// Returns whether it was applied.
// The unsafe blocks of the workspace: nix 0.29 has no safe wrapper for setpriority on a thread id
// nor for sched_setscheduler.
#[allow(unsafe_code)]
pub fn raise_thread_priority() -> bool {
    // SAFETY: two syscalls on the calling thread with plain integer arguments; no memory is shared.
    unsafe {
        let tid = nix::libc::gettid();
        nix::libc::setpriority(nix::libc::PRIO_PROCESS, tid as nix::libc::id_t, -15) == 0
    }
}

/// Back to normal scheduling (`SCHED_OTHER`, nice 0) for the calling thread: for a worker started by
/// a real-time thread (threads inherit the policy of the thread that creates them). Returns whether
/// it was applied (lowering a priority is always permitted).
#[allow(unsafe_code)]
pub fn make_normal() -> bool {
    let param = nix::libc::sched_param { sched_priority: 0 };
    // SAFETY: as in `make_realtime`: a valid sched_param on the stack, pid 0 = the calling thread;
    // then setpriority on the calling thread's id with plain integers.
    unsafe {
        let other = nix::libc::sched_setscheduler(0, nix::libc::SCHED_OTHER, &param) == 0;
        let tid = nix::libc::gettid();
        other && nix::libc::setpriority(nix::libc::PRIO_PROCESS, tid as nix::libc::id_t, 0) == 0
    }
}

/// `SCHED_FIFO` at `priority` (clamped to 1..=99) for the calling thread, else nice -15.
#[allow(unsafe_code)]
pub fn make_realtime(priority: i32) -> Priority {
    let priority = priority.clamp(1, 99);
    let param = nix::libc::sched_param { sched_priority: priority };
    // SAFETY: `param` is a valid sched_param on the stack that the call only reads; pid 0 is the
    // calling thread (Linux applies the policy per thread).
    let fifo = unsafe { nix::libc::sched_setscheduler(0, nix::libc::SCHED_FIFO, &param) } == 0;
    if fifo {
        Priority::Fifo(priority)
    } else if raise_thread_priority() {
        Priority::Nice
    } else {
        Priority::Unchanged
    }
}
