//! The `ServoBus` seam: Dynamixel Protocol 2.0 transactions the player needs (ping, read, write,
//! sync write, sync read with per-servo results), with three implementations: the real master
//! ([`dynamixel::DynamixelBus`], `dynamixel2` on a serial port or the simulated pty chain), and an
//! in-memory [`mock::MockBus`] for deterministic unit tests. Also the per-cycle helpers that turn
//! per-servo results into typed faults (missing servo, timeout, CRC, hardware error bits).

pub mod dynamixel;
pub mod mock;

use crate::mx28;

/// A failed bus transaction, naming the servo where known.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum BusError {
    #[error("servo {id}: no response (timeout)")]
    Timeout { id: u8 },
    #[error("servo {id}: status packet CRC mismatch")]
    Checksum { id: u8 },
    #[error("servo {id}: instruction failed with status error {code:#04x} ({})", status_error_name(*code))]
    Status { id: u8, code: u8 },
    #[error("servo {id}: hardware error {bits:#04x} ({})", mx28::hardware_error_names(*bits).join(", "))]
    Hardware { id: u8, bits: u8 },
    #[error("servo {id}: unexpected response: {detail}")]
    Protocol { id: u8, detail: String },
    #[error("bus I/O error: {0}")]
    Io(String),
    #[error("dynamixel2 panicked (isolated, bus still usable): {0}")]
    Panicked(String),
    #[error("invalid request: {0}")]
    InvalidRequest(String),
}

impl BusError {
    /// The servo this error is about, if any.
    pub fn servo_id(&self) -> Option<u8> {
        match self {
            BusError::Timeout { id }
            | BusError::Checksum { id }
            | BusError::Status { id, .. }
            | BusError::Hardware { id, .. }
            | BusError::Protocol { id, .. } => Some(*id),
            _ => None,
        }
    }
}

/// Name of a Protocol 2.0 status packet error number (lower 7 bits).
pub fn status_error_name(code: u8) -> &'static str {
    match code & 0x7F {
        0x01 => "result fail",
        0x02 => "instruction error",
        0x03 => "CRC error",
        0x04 => "data range error",
        0x05 => "data length error",
        0x06 => "data limit error",
        0x07 => "access error",
        _ => "unknown",
    }
}

/// Data from one servo of a sync read, with the status packet's alert bit (hardware error pending).
#[derive(Debug, Clone, PartialEq)]
pub struct SyncReadData {
    pub data: Vec<u8>,
    pub alert: bool,
}

/// Per-servo result of a sync read, in the order of the requested IDs.
pub type SyncReadResult = (u8, Result<SyncReadData, BusError>);

/// Dynamixel Protocol 2.0 master operations.
pub trait ServoBus: Send {
    /// Ping one servo; returns its model number.
    fn ping(&mut self, id: u8) -> Result<u16, BusError>;
    /// Read `count` bytes at `address`.
    fn read(&mut self, id: u8, address: u16, count: u16) -> Result<Vec<u8>, BusError>;
    /// Write bytes at `address` and wait for the status packet.
    fn write(&mut self, id: u8, address: u16, data: &[u8]) -> Result<(), BusError>;
    /// One broadcast sync write of `count` bytes per servo (no responses).
    fn sync_write(&mut self, address: u16, count: u16, data: &[(u8, Vec<u8>)]) -> Result<(), BusError>;
    /// One sync read; every requested ID gets its own result (never silently dropped).
    fn sync_read(&mut self, ids: &[u8], address: u16, count: u16) -> Result<Vec<SyncReadResult>, BusError>;
}

impl<B: ServoBus + ?Sized> ServoBus for Box<B> {
    fn ping(&mut self, id: u8) -> Result<u16, BusError> {
        (**self).ping(id)
    }
    fn read(&mut self, id: u8, address: u16, count: u16) -> Result<Vec<u8>, BusError> {
        (**self).read(id, address, count)
    }
    fn write(&mut self, id: u8, address: u16, data: &[u8]) -> Result<(), BusError> {
        (**self).write(id, address, data)
    }
    fn sync_write(&mut self, address: u16, count: u16, data: &[(u8, Vec<u8>)]) -> Result<(), BusError> {
        (**self).sync_write(address, count, data)
    }
    fn sync_read(&mut self, ids: &[u8], address: u16, count: u16) -> Result<Vec<SyncReadResult>, BusError> {
        (**self).sync_read(ids, address, count)
    }
}

/// Sync write of one 4-byte value per servo (e.g. Goal Position).
pub fn sync_write_u32(bus: &mut dyn ServoBus, address: u16, values: &[(u8, u32)]) -> Result<(), BusError> {
    let data: Vec<(u8, Vec<u8>)> = values.iter().map(|(id, v)| (*id, v.to_le_bytes().to_vec())).collect();
    bus.sync_write(address, 4, &data)
}

/// Sync write of one byte per servo (e.g. Torque Enable).
pub fn sync_write_u8(bus: &mut dyn ServoBus, address: u16, values: &[(u8, u8)]) -> Result<(), BusError> {
    let data: Vec<(u8, Vec<u8>)> = values.iter().map(|(id, v)| (*id, vec![*v])).collect();
    bus.sync_write(address, 1, &data)
}

/// Present positions (ticks, in `ids` order) from one sync read of address 132; the first failing
/// servo becomes the error. A set alert bit is resolved by reading Hardware Error Status (70).
pub fn read_present_positions(bus: &mut dyn ServoBus, ids: &[u8]) -> Result<Vec<i32>, (BusError, Vec<Option<i32>>)> {
    let results = bus.sync_read(ids, mx28::PRESENT_POSITION, 4).map_err(|e| (e, vec![None; ids.len()]))?;
    let mut positions: Vec<Option<i32>> = vec![None; ids.len()];
    let mut first_error: Option<BusError> = None;
    let mut alerted: Vec<u8> = Vec::new();
    for (slot, (id, result)) in positions.iter_mut().zip(results.iter()) {
        match result {
            Ok(read) => match <[u8; 4]>::try_from(read.data.as_slice()) {
                Ok(bytes) => {
                    *slot = Some(i32::from_le_bytes(bytes));
                    if read.alert {
                        alerted.push(*id);
                    }
                }
                Err(_) => {
                    first_error.get_or_insert(BusError::Protocol { id: *id, detail: format!("{} bytes instead of 4", read.data.len()) });
                }
            },
            Err(e) => {
                first_error.get_or_insert(e.clone());
            }
        }
    }
    if results.len() != ids.len() {
        let missing = ids.get(results.len()).copied().unwrap_or(0);
        first_error.get_or_insert(BusError::Timeout { id: missing });
    }
    if first_error.is_none() {
        if let Some(&id) = alerted.first() {
            let bits = bus.read(id, mx28::HARDWARE_ERROR_STATUS, 1).ok().and_then(|data| data.first().copied()).unwrap_or(0);
            first_error = Some(BusError::Hardware { id, bits });
        }
    }
    match first_error {
        None => Ok(positions.into_iter().map(|p| p.unwrap_or(0)).collect()),
        Some(e) => Err((e, positions)),
    }
}
