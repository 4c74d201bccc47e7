//! Scheduling priority of latency-critical threads (a control loop, a simulated servo chain).

/// Best effort: run the calling thread at nice -15 (control loops and the simulated servo chain are
/// latency-critical). Without the privilege the thread keeps its priority; nothing else changes.
pub fn raise_thread_priority() {
    // SAFETY: two syscalls on the calling thread with plain integer arguments; no memory is shared.
    unsafe {
        let tid = nix::libc::gettid();
        let _ = nix::libc::setpriority(nix::libc::PRIO_PROCESS, tid as nix::libc::id_t, -15);
    }
}
