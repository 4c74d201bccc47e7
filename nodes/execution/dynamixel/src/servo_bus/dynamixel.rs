//! The real Protocol 2.0 master: `dynamixel2` (=0.9.1) on a serial port (the RS-485 adapter, or the
//! simulated chain's pty). Works around the crate's known defects:
//! - plain `sync_read` drops per-servo errors, and its `_cb` variants lose the rest of a burst after
//!   one missing servo → sync read is built from the crate's `write_instruction` +
//!   `read_status_response_deadline` with a per-ID check that re-aligns on the next servo's answer;
//! - the crate's fixed answer budget (transfer time + 34 ms, as the ROBOTIS SDK) is configurable
//!   (`bus.response_timeout_ms`) for slow hosts; the same lower-level calls serve ping/read/write;
//! - `bulk_read` with ≥ 2 entries is broken → never used;
//! - the default 128-byte write buffer cannot hold a 12-servo sync write → 1 KiB read/write buffers;
//! - malformed/echoed frames can panic inside the crate → every call runs under `catch_unwind`, so a
//!   panic becomes an error on the control thread that owns this bus, never a dead node; a panic
//!   while reading a servo's status packet is [`BusError::Malformed`] naming that servo (in a sync
//!   read: the servo whose answer was due; the servos after it are [`BusError::Unread`]).
//!
//! A port that hung up (an unplugged USB adapter, a closed pty) reads as end of file, which the crate
//! retries until its deadline: a timeout on a hung-up port is reported as [`BusError::Io`] naming
//! the port, not as a silent servo. [`ServoBus::reconnect`] reopens the same path (an adapter or pty
//! that came back).

use std::cell::Cell;
use std::os::fd::AsFd;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::Path;
use std::sync::Once;
use std::time::{Duration, Instant};

use dynamixel2::instructions::{instruction_id, packet_id, SyncWriteData};
use dynamixel2::{Bus, InvalidMessage, ReadError, WriteError};

use super::{BusError, ServoBus, SyncReadData, SyncReadResult};

/// Read/write buffer size (bytes): a 12-servo 4-byte sync write is 10 + 4 + 12·5 = 74 bytes before
/// stuffing, a 12-servo sync read response burst 12·15 = 180 bytes; 1 KiB leaves ample room.
pub const BUFFER_SIZE: usize = 1024;

/// Protocol 2.0 master over `dynamixel2`.
pub struct DynamixelBus {
    bus: Bus<Vec<u8>, Vec<u8>>,
    port: std::path::PathBuf,
    /// Time allowed for an answer beyond its transfer time.
    response_timeout: Duration,
}

/// Default answer budget beyond the transfer time (ROBOTIS SDK: 2 × 16 ms latency timer + 2 ms).
pub const DEFAULT_RESPONSE_TIMEOUT: Duration = Duration::from_millis(34);

impl std::fmt::Debug for DynamixelBus {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("DynamixelBus").field("baud", &self.bus.baud_rate()).finish()
    }
}

thread_local! {
    /// Set while a transaction runs under [`DynamixelBus::guarded`].
    static GUARDED: Cell<bool> = const { Cell::new(false) };
}

static QUIET_HOOK: Once = Once::new();

/// A panic caught by [`DynamixelBus::guarded`] is an error of the transaction, reported as such: the
/// default hook's "panicked at" message on stderr is replaced by a debug log for those panics only
/// (every other panic still goes to the previous hook).
fn install_quiet_hook() {
    QUIET_HOOK.call_once(|| {
        let previous = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            if GUARDED.with(Cell::get) {
                tracing::debug!("dynamixel2 panicked inside a guarded transaction: {info}");
            } else {
                previous(info);
            }
        }));
    });
}

fn panic_message(payload: Box<dyn std::any::Any + Send>) -> String {
    payload
        .downcast_ref::<&str>()
        .map(|s| (*s).to_string())
        .or_else(|| payload.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "unknown panic".to_string())
}

/// Map a dynamixel2 read error for servo `id` to a typed [`BusError`].
fn read_error(id: u8, error: ReadError) -> BusError {
    match error {
        ReadError::Io(e) if e.kind() == std::io::ErrorKind::TimedOut => BusError::Timeout { id },
        ReadError::Io(e) => BusError::Io(e.to_string()),
        ReadError::BufferFull(e) => {
            BusError::Protocol { id, detail: format!("read buffer too small ({} > {})", e.required_size, e.total_size) }
        }
        ReadError::InvalidMessage(InvalidMessage::InvalidChecksum(_)) => BusError::Checksum { id },
        ReadError::InvalidMessage(other) => BusError::Protocol { id, detail: format!("{other:?}") },
        ReadError::MotorError(e) => BusError::Status { id, code: e.error_number() },
    }
}

fn write_error(error: WriteError) -> BusError {
    match error {
        WriteError::BufferTooSmall(e) => {
            BusError::InvalidRequest(format!("write buffer too small ({} > {})", e.required_size, e.total_size))
        }
        WriteError::DiscardBuffer(e) | WriteError::Write(e) => BusError::Io(e.to_string()),
    }
}

impl DynamixelBus {
    /// Open `port` at `baud` with 1 KiB buffers.
    pub fn open(port: &Path, baud: u32) -> Result<Self, BusError> {
        let bus = Bus::open_with_buffers(port, baud, vec![0u8; BUFFER_SIZE], vec![0u8; BUFFER_SIZE])
            .map_err(|e| BusError::Io(format!("{}: {e}", port.display())))?;
        install_quiet_hook();
        Ok(Self { bus, port: port.to_path_buf(), response_timeout: DEFAULT_RESPONSE_TIMEOUT })
    }

    /// Change the answer budget beyond the transfer time.
    pub fn with_response_timeout(mut self, timeout: Duration) -> Self {
        self.response_timeout = timeout;
        self
    }

    /// Deadline for a status packet with `params` parameter bytes.
    fn deadline(&self, params: usize) -> Instant {
        let bytes = 11 + params as u64; // header 7 + instruction + error + CRC 2
        let baud = u64::from(self.bus.baud_rate().max(1));
        Instant::now() + Duration::from_nanos(bytes * 10 * 1_000_000_000 / baud) + self.response_timeout
    }

    /// One instruction to one servo and its status packet: (parameters, alert bit).
    fn transfer(&mut self, id: u8, instruction: u8, params: &[u8], expected: usize) -> Result<(Vec<u8>, bool), BusError> {
        let budget = self.deadline(expected).saturating_duration_since(Instant::now());
        let result = self.guarded(|bus| {
            bus.write_instruction(id, instruction, params.len(), |buffer| buffer.copy_from_slice(params)).map_err(write_error)?;
            let response = bus.read_status_response_deadline(Instant::now() + budget).map_err(|e| read_error(id, e))?;
            if response.packet_id() != id {
                return Err(BusError::Protocol { id, detail: format!("answer from servo {}", response.packet_id()) });
            }
            if response.parameters().len() != expected {
                return Err(BusError::Protocol {
                    id,
                    detail: format!("{} parameter bytes instead of {expected}", response.parameters().len()),
                });
            }
            Ok((response.parameters().to_vec(), response.alert()))
        });
        result.map_err(|e| match e {
            BusError::Panicked(detail) => BusError::Malformed { id, detail },
            BusError::Timeout { .. } if self.hung_up() => self.lost_port(),
            other => other,
        })
    }

    /// Whether the port has hung up: the device is gone (POLLHUP, POLLERR or POLLNVAL without waiting).
    fn hung_up(&self) -> bool {
        use nix::poll::{poll, PollFd, PollFlags, PollTimeout};
        let mut fds = [PollFd::new(self.bus.serial_port().as_fd(), PollFlags::empty())];
        let gone = PollFlags::POLLHUP | PollFlags::POLLERR | PollFlags::POLLNVAL;
        matches!(poll(&mut fds, PollTimeout::ZERO), Ok(n) if n > 0) && fds[0].revents().is_some_and(|r| r.intersects(gone))
    }

    fn lost_port(&self) -> BusError {
        BusError::Io(format!("{}: the port hung up (adapter unplugged?)", self.port.display()))
    }

    /// Run one transaction with panics turned into errors.
    fn guarded<T>(&mut self, f: impl FnOnce(&mut Bus<Vec<u8>, Vec<u8>>) -> Result<T, BusError>) -> Result<T, BusError> {
        let bus = &mut self.bus;
        GUARDED.with(|g| g.set(true));
        let outcome = catch_unwind(AssertUnwindSafe(|| f(bus)));
        GUARDED.with(|g| g.set(false));
        match outcome {
            Ok(result) => result,
            Err(payload) => Err(BusError::Panicked(panic_message(payload))),
        }
    }
}

impl ServoBus for DynamixelBus {
    fn ping(&mut self, id: u8) -> Result<u16, BusError> {
        let (params, _) = self.transfer(id, instruction_id::PING, &[], 3)?;
        Ok(u16::from_le_bytes([params.first().copied().unwrap_or(0), params.get(1).copied().unwrap_or(0)]))
    }

    fn read(&mut self, id: u8, address: u16, count: u16) -> Result<Vec<u8>, BusError> {
        let [a0, a1] = address.to_le_bytes();
        let [c0, c1] = count.to_le_bytes();
        self.transfer(id, instruction_id::READ, &[a0, a1, c0, c1], usize::from(count)).map(|(data, _)| data)
    }

    fn write(&mut self, id: u8, address: u16, data: &[u8]) -> Result<(), BusError> {
        let mut params = address.to_le_bytes().to_vec();
        params.extend_from_slice(data);
        self.transfer(id, instruction_id::WRITE, &params, 0).map(|_| ())
    }

    fn sync_write(&mut self, address: u16, count: u16, data: &[(u8, Vec<u8>)]) -> Result<(), BusError> {
        if let Some((id, bytes)) = data.iter().find(|(_, bytes)| bytes.len() != usize::from(count)) {
            // dynamixel2 asserts on this; reject it as a typed error first.
            return Err(BusError::InvalidRequest(format!("servo {id}: {} bytes for a {count}-byte sync write", bytes.len())));
        }
        let entries: Vec<SyncWriteData<&[u8]>> =
            data.iter().map(|(id, bytes)| SyncWriteData { motor_id: *id, data: bytes.as_slice() }).collect();
        self.guarded(|bus| bus.sync_write(address, count, &entries).map_err(write_error))
    }

    fn sync_read(&mut self, ids: &[u8], address: u16, count: u16) -> Result<Vec<SyncReadResult>, BusError> {
        let mut params = Vec::with_capacity(4 + ids.len());
        params.extend_from_slice(&address.to_le_bytes());
        params.extend_from_slice(&count.to_le_bytes());
        params.extend_from_slice(ids);
        let per_answer = self.deadline(usize::from(count)).saturating_duration_since(Instant::now());
        self.guarded(|bus| {
            bus.write_instruction(packet_id::BROADCAST, instruction_id::SYNC_READ, params.len(), |buffer| buffer.copy_from_slice(&params))
                .map_err(write_error)
        })?;
        let mut results: Vec<SyncReadResult> = Vec::with_capacity(ids.len());
        while let Some(&id) = ids.get(results.len()) {
            let rest = ids.get(results.len()..).unwrap_or(&[]);
            // Each answer is read under its own guard: a frame that panics the parser is that
            // servo's fault, the answers before it stay good.
            let answer = self.guarded(|bus| {
                Ok(bus
                    .read_status_response_deadline(Instant::now() + per_answer)
                    .map(|response| (response.packet_id(), response.parameters().to_vec(), response.alert())))
            });
            let (from, result) = match answer {
                Err(BusError::Panicked(detail)) => {
                    // The crate's read buffer still holds the broken frame: nothing after it can be read.
                    results.push((id, Err(BusError::Malformed { id, detail })));
                    results.extend(rest.iter().skip(1).map(|&later| (later, Err(BusError::Unread { id: later, after: id }))));
                    break;
                }
                Err(other) => return Err(other),
                Ok(Err(ReadError::Io(e))) if e.kind() == std::io::ErrorKind::TimedOut => {
                    if self.hung_up() {
                        return Err(self.lost_port());
                    }
                    // Nothing more will come: every remaining servo is missing.
                    results.extend(rest.iter().map(|&id| (id, Err(BusError::Timeout { id }))));
                    break;
                }
                Ok(Err(ReadError::Io(e))) => return Err(BusError::Io(e.to_string())),
                Ok(Err(e)) => (id, Err(read_error(id, e))),
                Ok(Ok((from, data, _))) if data.len() != usize::from(count) => {
                    (from, Err(BusError::Protocol { id: from, detail: format!("{} bytes instead of {count}", data.len()) }))
                }
                Ok(Ok((from, data, alert))) => (from, Ok(SyncReadData { data, alert })),
            };
            // Servos answer in the requested order: an answer from a later servo means the ones
            // in between are missing.
            match rest.iter().position(|&expected| expected == from) {
                Some(skipped) => {
                    results.extend(rest.iter().take(skipped).map(|&id| (id, Err(BusError::Timeout { id }))));
                    results.push((from, result));
                }
                None => {
                    results.push((id, result.and_then(|_| Err(BusError::Protocol { id, detail: format!("answer from servo {from}") }))))
                }
            }
        }
        Ok(results)
    }

    fn reboot(&mut self, id: u8) -> Result<(), BusError> {
        self.transfer(id, instruction_id::REBOOT, &[], 0).map(|_| ())
    }

    fn reconnect(&mut self) -> Result<(), BusError> {
        let reopened = Self::open(&self.port, self.bus.baud_rate())?;
        self.bus = reopened.bus;
        Ok(())
    }
}
