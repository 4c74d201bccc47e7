//! One page of a ROBOTIS action file: the 64-byte header and 7 steps of 64 bytes, every byte kept so
//! a parsed page writes back byte for byte.
//!
//! Layout (ROBOTIS DARwIn-OP / OP3 action file, little-endian):
//!
//! | bytes | header field |
//! | --- | --- |
//! | 0–13 | name, NUL-terminated (at most 13 characters) |
//! | 14 | reserved |
//! | 15 | repeat count |
//! | 16 | schedule: 0 speed based, 0x0a time based |
//! | 17–19 | reserved |
//! | 20 | step count (0–7) |
//! | 21 | reserved |
//! | 22 | play speed (32 = as written) |
//! | 23 | reserved |
//! | 24 | acceleration time (control cycles) |
//! | 25 | next page |
//! | 26 | exit page |
//! | 27–30 | reserved |
//! | 31 | checksum: the byte sum of the whole page is 0xFF |
//! | 32–62 | P gain per joint slot |
//! | 63 | reserved |
//!
//! Step `s` starts at byte `64 + 64 s`: 31 joint positions (u16, slot = servo ID, bit 0x4000 "no
//! position", bit 0x2000 "torque off"), then the pause (byte 62) and the move time (byte 63).

/// Bytes of one page.
pub const PAGE_BYTES: usize = 512;
/// Bytes of the page header and of each step.
pub const BLOCK_BYTES: usize = 64;
/// The most steps a page holds.
pub const MAX_STEPS: usize = 7;
/// Joint position slots per step (indexed by servo ID 0–30).
pub const JOINT_SLOTS: usize = 31;
/// Bytes of the name field (13 characters and a terminating NUL).
pub const NAME_BYTES: usize = 14;
/// Position flag: the slot holds no position (the joint keeps its previous target).
pub const INVALID_BIT: u16 = 0x4000;
/// Position flag: the joint's torque is switched off for the step.
pub const TORQUE_OFF_BIT: u16 = 0x2000;
/// Schedule byte of a speed-based page.
pub const SPEED_BASE_SCHEDULE: u8 = 0x00;
/// Schedule byte of a time-based page (the step's time byte is its move duration).
pub const TIME_BASE_SCHEDULE: u8 = 0x0a;
/// The play speed at which a page's pause and time bytes are taken as written.
pub const NOMINAL_SPEED: u8 = 32;

const CHECKSUM_AT: usize = 31;

/// Why bytes are not a page.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum PageError {
    #[error("a page is {PAGE_BYTES} bytes, got {0}")]
    Length(usize),
    #[error("bad checksum: the page's bytes sum to 0x{sum:02X} (mod 256), a valid page sums to 0xFF")]
    Checksum { sum: u8 },
    #[error("step count {0} is more than the {MAX_STEPS} steps a page holds")]
    StepCount(u8),
}

/// One step: the joint positions by slot (servo ID), the pause after the move and the move time,
/// both in control cycles at the nominal speed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Step {
    pub positions: [u16; JOINT_SLOTS],
    pub pause: u8,
    pub time: u8,
}

impl Step {
    /// A step with no positions and no timing (ROBOTIS' empty step).
    pub const EMPTY: Step = Step { positions: [INVALID_BIT; JOINT_SLOTS], pause: 0, time: 0 };
}

/// A page with every field of the format; the checksum is computed when written.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Page {
    pub name: [u8; NAME_BYTES],
    pub reserved1: u8,
    pub repeat: u8,
    pub schedule: u8,
    pub reserved2: [u8; 3],
    pub step_count: u8,
    pub reserved3: u8,
    pub speed: u8,
    pub reserved4: u8,
    pub accel: u8,
    pub next: u8,
    pub exit: u8,
    pub reserved5: [u8; 4],
    pub pgain: [u8; JOINT_SLOTS],
    pub reserved6: u8,
    /// All 7 steps; only the first `step_count` are played.
    pub steps: [Step; MAX_STEPS],
}

impl Page {
    /// The page ROBOTIS' tools write for an unused slot: no name, repeat 1, time based, speed 32,
    /// acceleration 32, P gain 0x55, no steps.
    pub fn empty() -> Self {
        Self {
            name: [0; NAME_BYTES],
            reserved1: 0,
            repeat: 1,
            schedule: TIME_BASE_SCHEDULE,
            reserved2: [0; 3],
            step_count: 0,
            reserved3: 0,
            speed: NOMINAL_SPEED,
            reserved4: 0,
            accel: 32,
            next: 0,
            exit: 0,
            reserved5: [0; 4],
            pgain: [0x55; JOINT_SLOTS],
            reserved6: 0,
            steps: [Step::EMPTY; MAX_STEPS],
        }
    }

    /// The name up to its first NUL (bytes that are not UTF-8 shown as U+FFFD).
    pub fn name_text(&self) -> String {
        let end = self.name.iter().position(|&b| b == 0).unwrap_or(NAME_BYTES);
        String::from_utf8_lossy(&self.name[..end]).into_owned()
    }

    /// The played steps.
    pub fn played_steps(&self) -> &[Step] {
        &self.steps[..usize::from(self.step_count).min(MAX_STEPS)]
    }

    /// The page's 512 bytes with its checksum set.
    pub fn to_bytes(&self) -> [u8; PAGE_BYTES] {
        let mut b = [0u8; PAGE_BYTES];
        b[..NAME_BYTES].copy_from_slice(&self.name);
        b[14] = self.reserved1;
        b[15] = self.repeat;
        b[16] = self.schedule;
        b[17..20].copy_from_slice(&self.reserved2);
        b[20] = self.step_count;
        b[21] = self.reserved3;
        b[22] = self.speed;
        b[23] = self.reserved4;
        b[24] = self.accel;
        b[25] = self.next;
        b[26] = self.exit;
        b[27..31].copy_from_slice(&self.reserved5);
        b[32..63].copy_from_slice(&self.pgain);
        b[63] = self.reserved6;
        for (step, block) in self.steps.iter().zip(b[BLOCK_BYTES..].chunks_exact_mut(BLOCK_BYTES)) {
            for (position, pair) in step.positions.iter().zip(block.chunks_exact_mut(2)) {
                pair.copy_from_slice(&position.to_le_bytes());
            }
            block[62] = step.pause;
            block[63] = step.time;
        }
        b[CHECKSUM_AT] = checksum_for(&b);
        b
    }
}

/// The byte sum (mod 256) of `bytes`.
pub fn byte_sum(bytes: &[u8]) -> u8 {
    bytes.iter().fold(0u8, |sum, &b| sum.wrapping_add(b))
}

/// The checksum byte that makes the sum of `page` 0xFF, ignoring what its checksum byte holds now.
pub fn checksum_for(page: &[u8; PAGE_BYTES]) -> u8 {
    0xFFu8.wrapping_sub(byte_sum(page).wrapping_sub(page[CHECKSUM_AT]))
}

/// Parse one page from exactly [`PAGE_BYTES`] bytes: checksum verified, at most [`MAX_STEPS`] steps.
/// Any byte string gives a page or an error, never a panic.
pub fn parse_page(bytes: &[u8]) -> Result<Page, PageError> {
    let b: &[u8; PAGE_BYTES] = bytes.try_into().map_err(|_| PageError::Length(bytes.len()))?;
    let sum = byte_sum(b);
    if sum != 0xFF {
        return Err(PageError::Checksum { sum });
    }
    if usize::from(b[20]) > MAX_STEPS {
        return Err(PageError::StepCount(b[20]));
    }
    let mut steps = [Step::EMPTY; MAX_STEPS];
    for (step, block) in steps.iter_mut().zip(b[BLOCK_BYTES..].chunks_exact(BLOCK_BYTES)) {
        for (position, pair) in step.positions.iter_mut().zip(block.chunks_exact(2)) {
            *position = u16::from_le_bytes([pair[0], pair[1]]);
        }
        step.pause = block[62];
        step.time = block[63];
    }
    Ok(Page {
        name: copy_array(&b[0..NAME_BYTES]),
        reserved1: b[14],
        repeat: b[15],
        schedule: b[16],
        reserved2: copy_array(&b[17..20]),
        step_count: b[20],
        reserved3: b[21],
        speed: b[22],
        reserved4: b[23],
        accel: b[24],
        next: b[25],
        exit: b[26],
        reserved5: copy_array(&b[27..31]),
        pgain: copy_array(&b[32..63]),
        reserved6: b[63],
        steps,
    })
}

fn copy_array<const N: usize>(bytes: &[u8]) -> [u8; N] {
    let mut out = [0u8; N];
    out.iter_mut().zip(bytes).for_each(|(o, b)| *o = *b);
    out
}

#[cfg(test)]
#[path = "page_tests.rs"]
mod tests;
