//! A page's steps as library keyframes: the mapped IDs' positions converted to joint angles (4096
//! ticks per turn, 2048 ticks = 0 rad, then the table's direction and zero offset), checked against
//! the joint limits, with each step's move and pause from its bytes and the page's play speed.

use patchwalk_robot_model::kinematics::JointLimits;

use super::id_map::IdMap;
use super::page::{Page, INVALID_BIT, JOINT_SLOTS, SPEED_BASE_SCHEDULE, TIME_BASE_SCHEDULE, TORQUE_OFF_BIT};
use super::timing::{move_seconds, pause_seconds};
use crate::library::Keyframe;

/// The largest position an MX-28 takes (ticks).
pub const MAX_TICKS: u16 = 4095;

/// Why a page cannot become keyframes. Steps are counted from 1, as ROBOTIS' motion editor shows them.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ImportError {
    #[error("the page has 0 steps (an empty page)")]
    NoSteps,
    #[error("the page has repeat count 0, which ROBOTIS' players treat as an empty page")]
    NoRepeat,
    #[error("the page uses the speed-based schedule: its move times depend on each step's largest joint travel and the servo speed unit, not on the page; only time-based pages (schedule 0x0a) are imported")]
    SpeedBased,
    #[error("unknown schedule byte 0x{0:02X} (0x00 speed based, 0x0a time based)")]
    Schedule(u8),
    #[error("the page has play speed 0 (pauses would divide by zero)")]
    ZeroSpeed,
    #[error("step {step}: ID {id} ({joint}) has no position (0x4000 set) and there is no earlier step to keep it from")]
    MissingPosition { step: usize, id: u8, joint: String },
    #[error("step {step}: ID {id} ({joint}) switches torque off (0x2000 set); a library keyframe always holds its joints")]
    TorqueOff { step: usize, id: u8, joint: String },
    #[error("step {step}: ID {id} ({joint}) position 0x{raw:04X} is outside the servo's 0..={MAX_TICKS} ticks")]
    Ticks { step: usize, id: u8, joint: String, raw: u16 },
    #[error("step {step}: ID {id} ({joint}) at {ticks} ticks is {value:.4} rad, outside the joint limits [{lower:.4}, {upper:.4}]")]
    Limits { step: usize, id: u8, joint: String, ticks: u16, value: f64, lower: f64, upper: f64 },
}

/// The keyframes of a page and the IDs it positions that the table does not map (ignored).
#[derive(Debug, Clone, PartialEq)]
pub struct ImportedSteps {
    pub keyframes: Vec<Keyframe>,
    pub unmapped_ids: Vec<usize>,
}

/// Convert the page's played steps. `limits` are per library joint (the table's order). A slot with
/// "no position" keeps the previous step's value, as the players do; in the first step it is an error.
pub fn page_to_keyframes(page: &Page, map: &IdMap, limits: &[JointLimits]) -> Result<ImportedSteps, ImportError> {
    match page.schedule {
        TIME_BASE_SCHEDULE => {}
        SPEED_BASE_SCHEDULE => return Err(ImportError::SpeedBased),
        other => return Err(ImportError::Schedule(other)),
    }
    if page.step_count == 0 {
        return Err(ImportError::NoSteps);
    }
    if page.repeat == 0 {
        return Err(ImportError::NoRepeat);
    }
    if page.speed == 0 {
        return Err(ImportError::ZeroSpeed);
    }
    let mut keyframes: Vec<Keyframe> = Vec::with_capacity(page.played_steps().len());
    for (index, step) in page.played_steps().iter().enumerate() {
        let number = index + 1;
        let mut positions = Vec::with_capacity(map.servos().len());
        for (j, (servo, limit)) in map.servos().iter().zip(limits).enumerate() {
            let raw = step.positions[usize::from(servo.id)];
            let joint = || servo.joint.clone();
            if raw & INVALID_BIT != 0 {
                let previous = keyframes.last().map(|k| k.positions[j]);
                positions.push(previous.ok_or_else(|| ImportError::MissingPosition { step: number, id: servo.id, joint: joint() })?);
                continue;
            }
            if raw & TORQUE_OFF_BIT != 0 {
                return Err(ImportError::TorqueOff { step: number, id: servo.id, joint: joint() });
            }
            if raw > MAX_TICKS {
                return Err(ImportError::Ticks { step: number, id: servo.id, joint: joint(), raw });
            }
            let value = servo.joint_from_ticks(f64::from(raw));
            if !(value >= limit.lower && value <= limit.upper) {
                return Err(ImportError::Limits {
                    step: number,
                    id: servo.id,
                    joint: joint(),
                    ticks: raw,
                    value,
                    lower: limit.lower,
                    upper: limit.upper,
                });
            }
            positions.push(value);
        }
        keyframes.push(Keyframe { positions, move_s: move_seconds(step.time, page.speed), pause_s: pause_seconds(step.pause, page.speed) });
    }
    let unmapped_ids = (0..JOINT_SLOTS)
        .filter(|&slot| !map.maps(slot) && page.played_steps().iter().any(|s| s.positions[slot] & INVALID_BIT == 0))
        .collect();
    Ok(ImportedSteps { keyframes, unmapped_ids })
}
