//! The `ServoBus` seam: Dynamixel Protocol 2.0 transactions the player needs (ping, read, write,
//! sync write, sync read with per-servo results), with three implementations: the real master
//! ([`dynamixel::DynamixelBus`], `dynamixel2` on a serial port or the simulated pty chain), and an
//! in-memory [`mock::MockBus`] for deterministic unit tests. Also the per-cycle helpers that turn
//! per-servo results into typed faults (missing servo, timeout, CRC, malformed frame, hardware error
//! bits), and REBOOT / reconnect for recovery.

pub mod dynamixel;
pub mod mock;

use crate::mx28;
pub use crate::servo_array::{ServoArray, MAX_SERVOS};

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

/// The longest register block one sync read returns per servo (Present Position is 4 bytes, the
/// vitals 3).
pub const MAX_READ_BYTES: usize = 8;

/// Data from one servo of a sync read (inline, at most [`MAX_READ_BYTES`]), with the status
/// packet's alert bit (hardware error pending).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct SyncReadData {
    bytes: [u8; MAX_READ_BYTES],
    len: u8,
    pub alert: bool,
}

impl SyncReadData {
    /// `data` (refused when longer than [`MAX_READ_BYTES`]) and the alert bit.
    pub fn new(data: &[u8], alert: bool) -> Result<Self, BusError> {
        let mut bytes = [0u8; MAX_READ_BYTES];
        let slot = bytes.get_mut(..data.len()).ok_or_else(|| too_long(data.len()))?;
        slot.copy_from_slice(data);
        Ok(Self { bytes, len: data.len() as u8, alert })
    }

    /// The bytes read.
    pub fn data(&self) -> &[u8] {
        self.bytes.get(..usize::from(self.len)).unwrap_or(&[])
    }
}

fn too_long(count: usize) -> BusError {
    BusError::InvalidRequest(format!("{count} bytes per servo; a sync read returns at most {MAX_READ_BYTES}"))
}

/// Per-servo result of a sync read, in the order of the requested IDs.
pub type SyncReadResult = (u8, Result<SyncReadData, BusError>);

/// The caller-owned answer of one sync read: one result per requested servo (at most
/// [`MAX_SERVOS`]), overwritten by every [`ServoBus::sync_read`] into it, so a control loop reads
/// every cycle into the same buffer.
#[derive(Debug, Clone, PartialEq)]
pub struct SyncReadBuffer {
    ids: ServoArray<u8>,
    results: [Result<SyncReadData, BusError>; MAX_SERVOS],
}

impl Default for SyncReadBuffer {
    fn default() -> Self {
        Self { ids: ServoArray::default(), results: std::array::from_fn(|_| Ok(SyncReadData::default())) }
    }
}

impl SyncReadBuffer {
    pub fn new() -> Self {
        Self::default()
    }

    /// Forget the results (a sync read starts with this).
    pub fn clear(&mut self) {
        self.ids.clear();
    }

    /// Append the result for servo `id`; `false` when [`MAX_SERVOS`] results are there already.
    pub fn push(&mut self, id: u8, result: Result<SyncReadData, BusError>) -> bool {
        let Some(slot) = self.results.get_mut(self.ids.len()) else { return false };
        *slot = result;
        self.ids.push(id)
    }

    /// Number of results.
    pub fn len(&self) -> usize {
        self.ids.len()
    }

    pub fn is_empty(&self) -> bool {
        self.ids.is_empty()
    }

    /// Result `i` (request order): the servo's id and its data or error.
    pub fn get(&self, i: usize) -> Option<(u8, &Result<SyncReadData, BusError>)> {
        Some((*self.ids.get(i)?, self.results.get(i)?))
    }

    /// The results in request order.
    pub fn iter(&self) -> impl Iterator<Item = (u8, &Result<SyncReadData, BusError>)> + '_ {
        self.ids.iter().copied().zip(self.results.iter())
    }

    /// The results as owned pairs (for tools and tests; a control loop reads them in place).
    pub fn to_vec(&self) -> Vec<SyncReadResult> {
        self.iter().map(|(id, result)| (id, result.clone())).collect()
    }
}

/// Dynamixel Protocol 2.0 master operations. The transactions of a control cycle (`read`,
/// `sync_write`, `sync_read`) take caller-owned buffers and allocate nothing when they succeed.
pub trait ServoBus: Send {
    /// Ping one servo; returns its model number.
    fn ping(&mut self, id: u8) -> Result<u16, BusError>;
    /// Read `out.len()` bytes at `address` into `out`.
    fn read(&mut self, id: u8, address: u16, out: &mut [u8]) -> Result<(), BusError>;
    /// Write bytes at `address` and wait for the status packet.
    fn write(&mut self, id: u8, address: u16, data: &[u8]) -> Result<(), BusError>;
    /// One broadcast sync write of `count` bytes per servo (no responses): `data` holds `count`
    /// bytes for each of `ids`, in that order.
    fn sync_write(&mut self, address: u16, count: u16, ids: &[u8], data: &[u8]) -> Result<(), BusError>;
    /// One sync read of `count` bytes (at most [`MAX_READ_BYTES`]) from each of `ids` (at most
    /// [`MAX_SERVOS`]) into `out`; every requested ID gets its own result (never silently dropped).
    fn sync_read(&mut self, ids: &[u8], address: u16, count: u16, out: &mut SyncReadBuffer) -> Result<(), BusError>;
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
    fn read(&mut self, id: u8, address: u16, out: &mut [u8]) -> Result<(), BusError> {
        (**self).read(id, address, out)
    }
    fn write(&mut self, id: u8, address: u16, data: &[u8]) -> Result<(), BusError> {
        (**self).write(id, address, data)
    }
    fn sync_write(&mut self, address: u16, count: u16, ids: &[u8], data: &[u8]) -> Result<(), BusError> {
        (**self).sync_write(address, count, ids, data)
    }
    fn sync_read(&mut self, ids: &[u8], address: u16, count: u16, out: &mut SyncReadBuffer) -> Result<(), BusError> {
        (**self).sync_read(ids, address, count, out)
    }
    fn reboot(&mut self, id: u8) -> Result<(), BusError> {
        (**self).reboot(id)
    }
    fn reconnect(&mut self) -> Result<(), BusError> {
        (**self).reconnect()
    }
}

fn too_many(n: usize) -> BusError {
    BusError::InvalidRequest(format!("{n} servos in one transaction, at most {MAX_SERVOS}"))
}

/// The checks every implementation makes before a sync write: `count` bytes for each id, at most
/// [`MAX_SERVOS`] ids.
pub fn check_sync_write(count: u16, ids: &[u8], data: &[u8]) -> Result<(), BusError> {
    if ids.len() > MAX_SERVOS {
        return Err(too_many(ids.len()));
    }
    if data.len() != ids.len() * usize::from(count) {
        return Err(BusError::InvalidRequest(format!("{} bytes for {} servos of {count} bytes each", data.len(), ids.len())));
    }
    Ok(())
}

/// The checks every implementation makes before a sync read.
pub fn check_sync_read(ids: &[u8], count: u16) -> Result<(), BusError> {
    if ids.len() > MAX_SERVOS {
        return Err(too_many(ids.len()));
    }
    if usize::from(count) > MAX_READ_BYTES {
        return Err(too_long(usize::from(count)));
    }
    Ok(())
}

/// Sync write of one `N`-byte value per servo (`bytes` turns a value into its bytes), from stack
/// buffers: allocates nothing.
fn sync_write_values<V: Copy, const N: usize>(
    bus: &mut dyn ServoBus,
    address: u16,
    values: &[(u8, V)],
    bytes: impl Fn(V) -> [u8; N],
) -> Result<(), BusError> {
    if values.len() > MAX_SERVOS {
        return Err(too_many(values.len()));
    }
    let mut ids = [0u8; MAX_SERVOS];
    let mut data = [0u8; MAX_READ_BYTES * MAX_SERVOS];
    for (i, (id, value)) in values.iter().enumerate() {
        if let (Some(slot), Some(chunk)) = (ids.get_mut(i), data.get_mut(i * N..(i + 1) * N)) {
            *slot = *id;
            chunk.copy_from_slice(&bytes(*value));
        }
    }
    let n = values.len();
    bus.sync_write(address, N as u16, ids.get(..n).unwrap_or(&[]), data.get(..n * N).unwrap_or(&[]))
}

/// Sync write of one 4-byte value per servo (e.g. Goal Position); allocates nothing.
pub fn sync_write_u32(bus: &mut dyn ServoBus, address: u16, values: &[(u8, u32)]) -> Result<(), BusError> {
    sync_write_values(bus, address, values, u32::to_le_bytes)
}

/// Sync write of one byte per servo (e.g. Torque Enable); allocates nothing.
pub fn sync_write_u8(bus: &mut dyn ServoBus, address: u16, values: &[(u8, u8)]) -> Result<(), BusError> {
    sync_write_values(bus, address, values, |v| [v])
}

/// [`ServoBus::read`] into a new `Vec` (for tools and tests).
pub fn read_vec(bus: &mut dyn ServoBus, id: u8, address: u16, count: u16) -> Result<Vec<u8>, BusError> {
    let mut out = vec![0u8; usize::from(count)];
    bus.read(id, address, &mut out)?;
    Ok(out)
}

/// [`ServoBus::sync_read`] into a new `Vec` (for tools and tests).
pub fn sync_read_vec(bus: &mut dyn ServoBus, ids: &[u8], address: u16, count: u16) -> Result<Vec<SyncReadResult>, BusError> {
    let mut out = SyncReadBuffer::new();
    bus.sync_read(ids, address, count, &mut out)?;
    Ok(out.to_vec())
}

/// Present positions (ticks, in `ids` order) from one sync read of address 132; the first failing
/// servo becomes the error. A set alert bit is resolved by reading Hardware Error Status (70).
pub fn read_present_positions(bus: &mut dyn ServoBus, ids: &[u8]) -> Result<Vec<i32>, (BusError, Vec<Option<i32>>)> {
    let mut positions = vec![None; ids.len()];
    let mut errors = vec![None; ids.len()];
    match read_present_each(bus, ids, &mut positions, &mut errors, &mut SyncReadBuffer::new()) {
        Ok(()) => Ok(positions.into_iter().map(|p| p.unwrap_or(0)).collect()),
        Err(e) => Err((e, positions)),
    }
}

/// [`read_present_positions`] into the caller's slots (one per id, overwritten), through the
/// caller's `answer` buffer: every servo's own result (position or error), and the first error as
/// the result. The first servo with its alert bit set gets its Hardware Error Status read (one more
/// transaction) when nothing else failed. Allocates nothing when every servo answers.
pub fn read_present_each(
    bus: &mut dyn ServoBus,
    ids: &[u8],
    positions: &mut [Option<i32>],
    errors: &mut [Option<BusError>],
    answer: &mut SyncReadBuffer,
) -> Result<(), BusError> {
    positions.iter_mut().for_each(|p| *p = None);
    errors.iter_mut().for_each(|e| *e = None);
    if let Err(e) = bus.sync_read(ids, mx28::PRESENT_POSITION, 4, answer) {
        errors.iter_mut().for_each(|slot| *slot = Some(e.clone()));
        return Err(e);
    }
    let mut first_error: Option<BusError> = None;
    let mut alerted: Option<usize> = None;
    for (i, (id, result)) in answer.iter().enumerate().take(ids.len()) {
        let outcome = match result {
            Ok(read) => match <[u8; 4]>::try_from(read.data()) {
                Ok(bytes) => {
                    if let Some(slot) = positions.get_mut(i) {
                        *slot = Some(i32::from_le_bytes(bytes));
                    }
                    if read.alert && alerted.is_none() {
                        alerted = Some(i);
                    }
                    None
                }
                Err(_) => Some(BusError::Protocol { id, detail: format!("{} bytes instead of 4", read.data().len()) }),
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
    if answer.len() < ids.len() {
        for (i, &id) in ids.iter().enumerate().skip(answer.len()) {
            first_error.get_or_insert(BusError::Timeout { id });
            if let Some(slot) = errors.get_mut(i) {
                *slot = Some(BusError::Timeout { id });
            }
        }
    }
    if first_error.is_none() {
        if let Some((i, &id)) = alerted.and_then(|i| ids.get(i).map(|id| (i, id))) {
            let mut bits = [0u8; 1];
            let bits = bus.read(id, mx28::HARDWARE_ERROR_STATUS, &mut bits).map_or(0, |()| bits[0]);
            let error = BusError::Hardware { id, bits };
            if let Some(slot) = errors.get_mut(i) {
                *slot = Some(error.clone());
            }
            first_error = Some(error);
        }
    }
    first_error.map_or(Ok(()), Err)
}
