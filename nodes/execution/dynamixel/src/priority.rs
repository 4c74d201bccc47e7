//! Scheduling priority of latency-critical threads (a control loop, a simulated servo chain).

/// Best effort: run the calling thread at nice -15 (control loops and the simulated servo chain are
/// latency-critical). Without the privilege the thread keeps its priority; nothing else changes.
// The one unsafe block of the workspace: nix 0.29 has no safe wrapper for setpriority on a thread id.
#[allow(unsafe_code)]
pub fn raise_thread_priority() {
    // SAFETY: two syscalls on the calling thread with plain integer arguments; no memory is shared.
    unsafe {
        let tid = nix::libc::gettid();
        let _ = nix::libc::setpriority(nix::libc::PRIO_PROCESS, tid as nix::libc::id_t, -15);
    }
}
