//! The `ServoBus` seam: Dynamixel Protocol 2.0 transactions the player needs (ping, read, write,
//! sync write, sync read with per-servo results), with three implementations: the real master
//! ([`dynamixel::DynamixelBus`], `dynamixel2` on a serial port or the simulated pty chain), and an
//! in-memory [`mock::MockBus`] for deterministic unit tests. Also the per-cycle helpers that turn
//! per-servo results into typed faults (missing servo, timeout, CRC, malformed frame, hardware error
//! bits), and REBOOT / reconnect for recovery.

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
    /// A status frame that cannot be parsed (e.g. a LEN field shorter than any status packet).
    #[error("servo {id}: malformed status frame ({detail})")]
    Malformed { id: u8, detail: String },
    /// Not read: an earlier servo's malformed frame broke the sync read's answer burst.
    #[error("servo {id}: not read (the answer burst broke at servo {after})")]
    Unread { id: u8, after: u8 },
    #[error("bus I/O error: {0}")]
    Io(String),
    /// The control loop cannot keep its cycle: answers take too long for the cycle budget.
    #[error("bus too slow: {rate_hz:.1} cycles/s of {nominal_hz:.0} ({detail})")]
    TooSlow { rate_hz: f64, nominal_hz: f64, detail: String },
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
            | BusError::Protocol { id, .. }
            | BusError::Malformed { id, .. }
            | BusError::Unread { id, .. } => Some(*id),
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
    /// Protocol 2.0 REBOOT (0x08): the servo answers, then restarts (hardware error cleared, torque
    /// off, RAM back to its defaults) and is silent for its boot time.
    fn reboot(&mut self, id: u8) -> Result<(), BusError>;
    /// Close and reopen the port (after the adapter was unplugged and plugged in again).
    fn reconnect(&mut self) -> Result<(), BusError>;
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
    fn reboot(&mut self, id: u8) -> Result<(), BusError> {
        (**self).reboot(id)
    }
    fn reconnect(&mut self) -> Result<(), BusError> {
        (**self).reconnect()
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
    let mut positions = vec![None; ids.len()];
    let mut errors = vec![None; ids.len()];
    match read_present_each(bus, ids, &mut positions, &mut errors) {
        Ok(()) => Ok(positions.into_iter().map(|p| p.unwrap_or(0)).collect()),
        Err(e) => Err((e, positions)),
    }
}

/// [`read_present_positions`] into the caller's slots (one per id, overwritten): every servo's own
/// result (position or error), and the first error as the result. The first servo with its alert
/// bit set gets its Hardware Error Status read (one more transaction) when nothing else failed.
pub fn read_present_each(
    bus: &mut dyn ServoBus,
    ids: &[u8],
    positions: &mut [Option<i32>],
    errors: &mut [Option<BusError>],
) -> Result<(), BusError> {
    positions.iter_mut().for_each(|p| *p = None);
    errors.iter_mut().for_each(|e| *e = None);
    let results = match bus.sync_read(ids, mx28::PRESENT_POSITION, 4) {
        Ok(results) => results,
        Err(e) => {
            errors.iter_mut().for_each(|slot| *slot = Some(e.clone()));
            return Err(e);
        }
    };
    let mut first_error: Option<BusError> = None;
    let mut alerted: Option<usize> = None;
    for (i, (id, result)) in results.iter().enumerate().take(ids.len()) {
        let outcome = match result {
            Ok(read) => match <[u8; 4]>::try_from(read.data.as_slice()) {
                Ok(bytes) => {
                    if let Some(slot) = positions.get_mut(i) {
                        *slot = Some(i32::from_le_bytes(bytes));
                    }
                    if read.alert && alerted.is_none() {
                        alerted = Some(i);
                    }
                    None
                }
                Err(_) => Some(BusError::Protocol { id: *id, detail: format!("{} bytes instead of 4", read.data.len()) }),
            },
            Err(e) => Some(e.clone()),
        };
        if let Some(e) = outcome {
            // An unread servo is not at fault: the servo that broke the burst is.
            if first_error.is_none() && !matches!(e, BusError::Unread { .. }) {
                first_error = Some(e.clone());
            }
            if let Some(slot) = errors.get_mut(i) {
                *slot = Some(e);
            }
        }
    }
    if results.len() < ids.len() {
        for (i, &id) in ids.iter().enumerate().skip(results.len()) {
            first_error.get_or_insert(BusError::Timeout { id });
            if let Some(slot) = errors.get_mut(i) {
                *slot = Some(BusError::Timeout { id });
            }
        }
    }
    if first_error.is_none() {
        if let Some((i, &id)) = alerted.and_then(|i| ids.get(i).map(|id| (i, id))) {
            let bits = bus.read(id, mx28::HARDWARE_ERROR_STATUS, 1).ok().and_then(|data| data.first().copied()).unwrap_or(0);
            let error = BusError::Hardware { id, bits };
            if let Some(slot) = errors.get_mut(i) {
                *slot = Some(error.clone());
            }
            first_error = Some(error);
        }
    }
    first_error.map_or(Ok(()), Err)
}
