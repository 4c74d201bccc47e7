//! The MX-28 (Protocol 2.0 firmware) control table: addresses, sizes, access, factory defaults and
//! unit conversions (ROBOTIS e-Manual, "MX-28(2.0)"). Shared by the master side (player, real bus)
//! and the simulated servo chain.

/// Model number reported by ping / address 0 for an MX-28 running Protocol 2.0 firmware.
pub const MODEL_NUMBER: u16 = 30;
/// Firmware version reported by ping (any value ≥ 41 supports time-based profiles).
pub const FIRMWARE_VERSION: u8 = 46;
/// Size of the emulated control table (up to the indirect data area).
pub const TABLE_SIZE: usize = 228;
/// First RAM address; everything below is EEPROM (locked while torque is on).
pub const RAM_START: u16 = 64;

pub const MODEL_NUMBER_ADDR: u16 = 0;
pub const FIRMWARE_VERSION_ADDR: u16 = 6;
pub const ID: u16 = 7;
pub const BAUD_RATE: u16 = 8;
pub const RETURN_DELAY_TIME: u16 = 9;
pub const DRIVE_MODE: u16 = 10;
pub const OPERATING_MODE: u16 = 11;
pub const PROTOCOL_TYPE: u16 = 13;
pub const VELOCITY_LIMIT: u16 = 44;
pub const MAX_POSITION_LIMIT: u16 = 48;
pub const MIN_POSITION_LIMIT: u16 = 52;
pub const SHUTDOWN: u16 = 63;
pub const TORQUE_ENABLE: u16 = 64;
pub const LED: u16 = 65;
pub const STATUS_RETURN_LEVEL: u16 = 68;
pub const REGISTERED_INSTRUCTION: u16 = 69;
pub const HARDWARE_ERROR_STATUS: u16 = 70;
pub const PROFILE_ACCELERATION: u16 = 108;
pub const PROFILE_VELOCITY: u16 = 112;
pub const GOAL_POSITION: u16 = 116;
pub const REALTIME_TICK: u16 = 120;
pub const MOVING: u16 = 122;
pub const MOVING_STATUS: u16 = 123;
pub const PRESENT_LOAD: u16 = 126;
pub const PRESENT_VELOCITY: u16 = 128;
pub const PRESENT_POSITION: u16 = 132;
pub const PRESENT_INPUT_VOLTAGE: u16 = 144;
pub const PRESENT_TEMPERATURE: u16 = 146;

/// Hardware Error Status (70) bits.
pub const HW_INPUT_VOLTAGE: u8 = 1 << 0;
pub const HW_OVERHEATING: u8 = 1 << 2;
pub const HW_MOTOR_ENCODER: u8 = 1 << 3;
pub const HW_ELECTRICAL_SHOCK: u8 = 1 << 4;
pub const HW_OVERLOAD: u8 = 1 << 5;

/// Velocity unit of Velocity Limit / Profile Velocity / Present Velocity: 0.229 rpm.
pub const VELOCITY_UNIT_RPM: f64 = 0.229;

/// Access rights of one control-table field.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Access {
    Read,
    ReadWrite,
}

/// One field of the control table.
#[derive(Debug, Clone, Copy)]
pub struct Field {
    pub address: u16,
    pub size: u16,
    pub access: Access,
    /// Factory default (0 where the manual lists "-").
    pub default: u32,
}

const fn f(address: u16, size: u16, access: Access, default: u32) -> Field {
    Field { address, size, access, default }
}

use Access::{Read as R, ReadWrite as RW};

/// The MX-28(2.0) control table (indirect address/data areas omitted).
pub const FIELDS: &[Field] = &[
    f(0, 2, R, MODEL_NUMBER as u32),
    f(2, 4, R, 0),
    f(6, 1, R, FIRMWARE_VERSION as u32),
    f(7, 1, RW, 1),
    f(8, 1, RW, 1),
    f(9, 1, RW, 250),
    f(10, 1, RW, 0),
    f(11, 1, RW, 3),
    f(12, 1, RW, 255),
    f(13, 1, RW, 2),
    f(20, 4, RW, 0),
    f(24, 4, RW, 10),
    f(31, 1, RW, 80),
    f(32, 2, RW, 160),
    f(34, 2, RW, 95),
    f(36, 2, RW, 885),
    f(40, 4, RW, 32767),
    f(44, 4, RW, 230),
    f(48, 4, RW, 4095),
    f(52, 4, RW, 0),
    f(63, 1, RW, 52),
    f(64, 1, RW, 0),
    f(65, 1, RW, 0),
    f(68, 1, RW, 2),
    f(69, 1, R, 0),
    f(70, 1, R, 0),
    f(76, 2, RW, 1920),
    f(78, 2, RW, 100),
    f(80, 2, RW, 0),
    f(82, 2, RW, 0),
    f(84, 2, RW, 850),
    f(88, 2, RW, 0),
    f(90, 2, RW, 0),
    f(98, 1, RW, 0),
    f(100, 2, RW, 885),
    f(104, 4, RW, 0),
    f(108, 4, RW, 0),
    f(112, 4, RW, 0),
    f(116, 4, RW, 2048),
    f(120, 2, R, 0),
    f(122, 1, R, 0),
    f(123, 1, R, 0),
    f(124, 2, R, 0),
    f(126, 2, R, 0),
    f(128, 4, R, 0),
    f(132, 4, R, 2048),
    f(136, 4, R, 0),
    f(140, 4, R, 0),
    f(144, 2, R, 120),
    f(146, 1, R, 32),
];

/// The field containing `address`, if any.
pub fn field_at(address: u16) -> Option<&'static Field> {
    FIELDS.iter().find(|field| address >= field.address && address < field.address + field.size)
}

/// Baud Rate register value (address 8) for a baud rate.
pub fn baud_register(baud: u32) -> Option<u8> {
    match baud {
        9_600 => Some(0),
        57_600 => Some(1),
        115_200 => Some(2),
        1_000_000 => Some(3),
        2_000_000 => Some(4),
        3_000_000 => Some(5),
        4_000_000 => Some(6),
        4_500_000 => Some(7),
        _ => None,
    }
}

/// Baud rate for a Baud Rate register value.
pub fn baud_from_register(value: u8) -> Option<u32> {
    [9_600, 57_600, 115_200, 1_000_000, 2_000_000, 3_000_000, 4_000_000, 4_500_000].get(usize::from(value)).copied()
}

/// Human-readable names of the set Hardware Error Status bits.
pub fn hardware_error_names(bits: u8) -> Vec<&'static str> {
    [
        (HW_INPUT_VOLTAGE, "input voltage"),
        (HW_OVERHEATING, "overheating"),
        (HW_MOTOR_ENCODER, "motor encoder"),
        (HW_ELECTRICAL_SHOCK, "electrical shock"),
        (HW_OVERLOAD, "overload"),
    ]
    .iter()
    .filter(|(bit, _)| bits & bit != 0)
    .map(|(_, name)| *name)
    .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fields_are_sorted_and_disjoint() {
        for pair in FIELDS.windows(2) {
            assert!(pair[0].address + pair[0].size <= pair[1].address, "{:?} overlaps {:?}", pair[0], pair[1]);
        }
        assert!(FIELDS.iter().all(|f| usize::from(f.address + f.size) <= TABLE_SIZE));
    }

    #[test]
    fn key_addresses_match_manual() {
        assert_eq!(field_at(PRESENT_POSITION).map(|f| f.size), Some(4));
        assert_eq!(field_at(GOAL_POSITION).map(|f| f.size), Some(4));
        assert_eq!(field_at(HARDWARE_ERROR_STATUS).map(|f| f.access), Some(Access::Read));
        assert_eq!(field_at(0).map(|f| f.default), Some(30));
        assert_eq!(baud_register(1_000_000), Some(3));
        assert_eq!(baud_from_register(3), Some(1_000_000));
        assert_eq!(hardware_error_names(HW_OVERLOAD | HW_OVERHEATING), vec!["overheating", "overload"]);
    }
}
