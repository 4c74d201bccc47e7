//! The real Protocol 2.0 master: `dynamixel2` (=0.9.1) on a serial port (the RS-485 adapter, or the
//! simulated chain's pty). Works around the crate's known defects:
//! - plain `sync_read` drops per-servo errors → only `sync_read_cb` is used, with per-ID checks;
//! - `bulk_read` with ≥ 2 entries is broken → never used;
//! - the default 128-byte write buffer cannot hold a 12-servo sync write → 1 KiB read/write buffers;
//! - malformed/echoed frames can panic inside the crate → every call runs under `catch_unwind`, so a
//!   panic becomes [`BusError::Panicked`] on the control thread that owns this bus, never a dead node.

use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::Path;

use dynamixel2::instructions::SyncWriteData;
use dynamixel2::{Bus, InvalidMessage, ReadError, TransferError, WriteError};

use super::{BusError, ServoBus, SyncReadData, SyncReadResult};

/// Read/write buffer size (bytes): a 12-servo 4-byte sync write is 10 + 4 + 12·5 = 74 bytes before
/// stuffing, a 12-servo sync read response burst 12·15 = 180 bytes; 1 KiB leaves ample room.
pub const BUFFER_SIZE: usize = 1024;

/// Protocol 2.0 master over `dynamixel2`.
pub struct DynamixelBus {
    bus: Bus<Vec<u8>, Vec<u8>>,
}

impl std::fmt::Debug for DynamixelBus {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("DynamixelBus").field("baud", &self.bus.baud_rate()).finish()
    }
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
        ReadError::BufferFull(e) => BusError::Protocol { id, detail: format!("read buffer too small ({} > {})", e.required_size, e.total_size) },
        ReadError::InvalidMessage(InvalidMessage::InvalidChecksum(_)) => BusError::Checksum { id },
        ReadError::InvalidMessage(other) => BusError::Protocol { id, detail: format!("{other:?}") },
        ReadError::MotorError(e) => BusError::Status { id, code: e.error_number() },
    }
}

fn write_error(error: WriteError) -> BusError {
    match error {
        WriteError::BufferTooSmall(e) => BusError::InvalidRequest(format!("write buffer too small ({} > {})", e.required_size, e.total_size)),
        WriteError::DiscardBuffer(e) | WriteError::Write(e) => BusError::Io(e.to_string()),
    }
}

fn transfer_error(id: u8, error: TransferError) -> BusError {
    match error {
        TransferError::WriteError(e) => write_error(e),
        TransferError::ReadError(e) => read_error(id, e),
    }
}

impl DynamixelBus {
    /// Open `port` at `baud` with 1 KiB buffers.
    pub fn open(port: &Path, baud: u32) -> Result<Self, BusError> {
        let bus = Bus::open_with_buffers(port, baud, vec![0u8; BUFFER_SIZE], vec![0u8; BUFFER_SIZE])
            .map_err(|e| BusError::Io(format!("{}: {e}", port.display())))?;
        Ok(Self { bus })
    }

    /// Run one transaction with panics turned into errors.
    fn guarded<T>(&mut self, f: impl FnOnce(&mut Bus<Vec<u8>, Vec<u8>>) -> Result<T, BusError>) -> Result<T, BusError> {
        let bus = &mut self.bus;
        match catch_unwind(AssertUnwindSafe(|| f(bus))) {
            Ok(result) => result,
            Err(payload) => Err(BusError::Panicked(panic_message(payload))),
        }
    }
}

impl ServoBus for DynamixelBus {
    fn ping(&mut self, id: u8) -> Result<u16, BusError> {
        self.guarded(|bus| bus.ping(id).map(|r| r.data.model).map_err(|e| transfer_error(id, e)))
    }

    fn read(&mut self, id: u8, address: u16, count: u16) -> Result<Vec<u8>, BusError> {
        self.guarded(|bus| bus.read(id, address, count).map(|r| r.data).map_err(|e| transfer_error(id, e)))
    }

    fn write(&mut self, id: u8, address: u16, data: &[u8]) -> Result<(), BusError> {
        self.guarded(|bus| bus.write(id, address, data).map(|_| ()).map_err(|e| transfer_error(id, e)))
    }

    fn sync_write(&mut self, address: u16, count: u16, data: &[(u8, Vec<u8>)]) -> Result<(), BusError> {
        if let Some((id, bytes)) = data.iter().find(|(_, bytes)| bytes.len() != usize::from(count)) {
            // dynamixel2 asserts on this; reject it as a typed error first.
            return Err(BusError::InvalidRequest(format!("servo {id}: {} bytes for a {count}-byte sync write", bytes.len())));
        }
        let entries: Vec<SyncWriteData<&[u8]>> = data.iter().map(|(id, bytes)| SyncWriteData { motor_id: *id, data: bytes.as_slice() }).collect();
        self.guarded(|bus| bus.sync_write(address, count, &entries).map_err(write_error))
    }

    fn sync_read(&mut self, ids: &[u8], address: u16, count: u16) -> Result<Vec<SyncReadResult>, BusError> {
        self.guarded(|bus| {
            let mut results: Vec<SyncReadResult> = Vec::with_capacity(ids.len());
            let mut next = ids.iter();
            bus.sync_read_cb(ids, address, count, |response| {
                // sync_read_cb calls back once per requested ID, in order; it has already checked
                // the packet ID and the parameter count of successful responses.
                let id = next.next().copied().unwrap_or(0);
                let result = match response {
                    Ok(r) if r.motor_id != id => Err(BusError::Protocol { id, detail: format!("response from servo {}", r.motor_id) }),
                    Ok(r) => Ok(SyncReadData { data: r.data.to_vec(), alert: r.alert }),
                    // The next servo's answer arrived in this servo's slot: this one is missing.
                    Err(ReadError::InvalidMessage(InvalidMessage::InvalidPacketId(_))) => Err(BusError::Timeout { id }),
                    Err(e) => Err(read_error(id, e)),
                };
                results.push((id, result));
            })
            .map_err(write_error)?;
            Ok(results)
        })
    }
}
