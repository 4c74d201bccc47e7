//! The real Protocol 2.0 master: `dynamixel2` (=0.9.1) on a serial port (the RS-485 adapter, or the
//! simulated chain's pty). Works around the crate's known defects:
//! - plain `sync_read` drops per-servo errors, and its `_cb` variants lose the rest of a burst after
//!   one missing servo → sync read is built from the crate's `write_instruction` +
//!   `read_status_response_deadline` with a per-ID check that re-aligns on the next servo's answer;
//! - the crate's fixed answer budget (transfer time + 34 ms, as the ROBOTIS SDK) is configurable
//!   (`bus.response_timeout_ms`) for slow hosts; the same lower-level calls serve ping/read/write;
//! - `bulk_read` with ≥ 2 entries is broken → never used;
//! - the default 128-byte write buffer cannot hold a 12-servo sync write → 1 KiB read/write buffers;
//! - every instruction is encoded in place into that write buffer (the crate's `write_instruction`)
//!   and every answer is parsed in place in the read buffer and copied into the caller's buffer, so
//!   a control cycle's transactions allocate nothing;
//! - malformed/echoed frames can panic inside the crate → every call runs under `catch_unwind`, so a
//!   panic becomes an error on the control thread that owns this bus, never a dead node; a panic
//!   while reading a servo's status packet is [`BusError::Malformed`] naming that servo (in a sync
//!   read: the servo whose answer was due; the servos after it are [`BusError::Unread`]).
//!
//! [`ServoBus::reconnect`] reopens the same path (an unplugged USB adapter or pty that came back).

use std::cell::Cell;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::Path;
use std::sync::Once;
use std::time::{Duration, Instant};

use dynamixel2::instructions::{instruction_id, packet_id};
use dynamixel2::{Bus, InvalidMessage, ReadError, WriteError};

use super::{check_sync_read, check_sync_write, BusError, ServoBus, SyncReadBuffer, SyncReadData};

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

    /// One instruction to one servo (`encode` writes its `param_len` parameter bytes in place) and
    /// its status packet, whose parameters (exactly `out.len()` bytes) go into `out`. Returns the
    /// alert bit.
    fn transfer(
        &mut self,
        id: u8,
        instruction: u8,
        param_len: usize,
        encode: impl FnOnce(&mut [u8]),
        out: &mut [u8],
    ) -> Result<bool, BusError> {
        let expected = out.len();
        let budget = self.deadline(expected).saturating_duration_since(Instant::now());
        let result = self.guarded(|bus| {
            bus.write_instruction(id, instruction, param_len, encode).map_err(write_error)?;
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
            out.copy_from_slice(response.parameters());
            Ok(response.alert())
        });
        result.map_err(|e| match e {
            BusError::Panicked(detail) => BusError::Malformed { id, detail },
            other => other,
        })
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
        let mut answer = [0u8; 3];
        self.transfer(id, instruction_id::PING, 0, |_| {}, &mut answer)?;
        Ok(u16::from_le_bytes([answer[0], answer[1]]))
    }

    fn read(&mut self, id: u8, address: u16, out: &mut [u8]) -> Result<(), BusError> {
        let count = u16::try_from(out.len()).map_err(|_| BusError::InvalidRequest(format!("read of {} bytes", out.len())))?;
        let [a0, a1] = address.to_le_bytes();
        let [c0, c1] = count.to_le_bytes();
        self.transfer(id, instruction_id::READ, 4, |buffer| buffer.copy_from_slice(&[a0, a1, c0, c1]), out).map(|_| ())
    }

    fn write(&mut self, id: u8, address: u16, data: &[u8]) -> Result<(), BusError> {
        let encode = |buffer: &mut [u8]| {
            let (head, tail) = buffer.split_at_mut(2);
            head.copy_from_slice(&address.to_le_bytes());
            tail.copy_from_slice(data);
        };
        self.transfer(id, instruction_id::WRITE, 2 + data.len(), encode, &mut []).map(|_| ())
    }

    fn sync_write(&mut self, address: u16, count: u16, ids: &[u8], data: &[u8]) -> Result<(), BusError> {
        // dynamixel2 asserts on a wrong length; reject it as a typed error first.
        check_sync_write(count, ids, data)?;
        let stride = usize::from(count);
        // Parameters: address, count, then (id, count bytes) per servo (Protocol 2.0 SYNC WRITE).
        let encode = |buffer: &mut [u8]| {
            let (head, entries) = buffer.split_at_mut(4);
            head[..2].copy_from_slice(&address.to_le_bytes());
            head[2..].copy_from_slice(&count.to_le_bytes());
            for ((entry, id), bytes) in entries.chunks_exact_mut(stride + 1).zip(ids).zip(data.chunks_exact(stride.max(1))) {
                entry[0] = *id;
                entry[1..].copy_from_slice(bytes);
            }
        };
        let len = 4 + ids.len() * (stride + 1);
        self.guarded(|bus| bus.write_instruction(packet_id::BROADCAST, instruction_id::SYNC_WRITE, len, encode).map_err(write_error))
    }

    fn sync_read(&mut self, ids: &[u8], address: u16, count: u16, out: &mut SyncReadBuffer) -> Result<(), BusError> {
        check_sync_read(ids, count)?;
        out.clear();
        let encode = |buffer: &mut [u8]| {
            let (head, tail) = buffer.split_at_mut(4);
            head[..2].copy_from_slice(&address.to_le_bytes());
            head[2..].copy_from_slice(&count.to_le_bytes());
            tail.copy_from_slice(ids);
        };
        let per_answer = self.deadline(usize::from(count)).saturating_duration_since(Instant::now());
        self.guarded(|bus| {
            bus.write_instruction(packet_id::BROADCAST, instruction_id::SYNC_READ, 4 + ids.len(), encode).map_err(write_error)
        })?;
        while let Some(&id) = ids.get(out.len()) {
            let rest = ids.get(out.len()..).unwrap_or(&[]);
            // Each answer is read under its own guard: a frame that panics the parser is that
            // servo's fault, the answers before it stay good.
            let answer = self.guarded(|bus| {
                Ok(bus.read_status_response_deadline(Instant::now() + per_answer).map(|response| {
                    let (from, params) = (response.packet_id(), response.parameters());
                    let data = if params.len() == usize::from(count) {
                        SyncReadData::new(params, response.alert())
                    } else {
                        Err(BusError::Protocol { id: from, detail: format!("{} bytes instead of {count}", params.len()) })
                    };
                    (from, data)
                }))
            });
            let (from, result) = match answer {
                Err(BusError::Panicked(detail)) => {
                    // The crate's read buffer still holds the broken frame: nothing after it can be read.
                    out.push(id, Err(BusError::Malformed { id, detail }));
                    for &later in rest.iter().skip(1) {
                        out.push(later, Err(BusError::Unread { id: later, after: id }));
                    }
                    break;
                }
                Err(other) => return Err(other),
                Ok(Err(ReadError::Io(e))) if e.kind() == std::io::ErrorKind::TimedOut => {
                    // Nothing more will come: every remaining servo is missing.
                    for &missing in rest {
                        out.push(missing, Err(BusError::Timeout { id: missing }));
                    }
                    break;
                }
                Ok(Err(ReadError::Io(e))) => return Err(BusError::Io(e.to_string())),
                Ok(Err(e)) => (id, Err(read_error(id, e))),
                Ok(Ok(answer)) => answer,
            };
            // Servos answer in the requested order: an answer from a later servo means the ones
            // in between are missing.
            match rest.iter().position(|&expected| expected == from) {
                Some(skipped) => {
                    for &missing in rest.iter().take(skipped) {
                        out.push(missing, Err(BusError::Timeout { id: missing }));
                    }
                    out.push(from, result);
                }
                None => {
                    out.push(id, result.and_then(|_| Err(BusError::Protocol { id, detail: format!("answer from servo {from}") })));
                }
            }
        }
        Ok(())
    }

    fn reboot(&mut self, id: u8) -> Result<(), BusError> {
        self.transfer(id, instruction_id::REBOOT, 0, |_| {}, &mut []).map(|_| ())
    }

    fn reconnect(&mut self) -> Result<(), BusError> {
        let reopened = Self::open(&self.port, self.bus.baud_rate())?;
        self.bus = reopened.bus;
        Ok(())
    }
}
