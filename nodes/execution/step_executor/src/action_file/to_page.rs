//! Library keyframes written as a time-based page. The fields a library motion does not carry (repeat
//! count, acceleration, next and exit page, P gains, reserved bytes, the positions of IDs the table
//! does not map) come from a template page: the page being replaced, or [`Page::empty`]. The play
//! speed is the one whose bytes come closest to the keyframes' timing ([`choose_timing`]), so a page
//! imported and exported again is written with its own speed and bytes.

use patchwalk_robot_model::kinematics::JointLimits;

use super::id_map::IdMap;
use super::page::{Page, Step, INVALID_BIT, JOINT_SLOTS, MAX_STEPS, NAME_BYTES, TIME_BASE_SCHEDULE};
use super::timing::{choose_timing, CONTROL_CYCLE_S};
use super::to_keyframes::MAX_TICKS;
use crate::library::Keyframe;

/// Why keyframes cannot be written as a page. Keyframes are counted from 1.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ExportError {
    #[error("the motion has {0} keyframes; a page holds 1..={MAX_STEPS} steps")]
    StepCount(usize),
    #[error("keyframe {keyframe} has {got} positions, the ID table maps {expected} joints")]
    Positions { keyframe: usize, got: usize, expected: usize },
    #[error("keyframe {keyframe}: {joint} = {value:.4} rad is outside the joint limits [{lower:.4}, {upper:.4}]")]
    Limits { keyframe: usize, joint: String, value: f64, lower: f64, upper: f64 },
    #[error("keyframe {keyframe}: {joint} = {value:.4} rad is {ticks} ticks for ID {id}, outside the servo's 0..={MAX_TICKS}")]
    Ticks { keyframe: usize, joint: String, id: u8, value: f64, ticks: f64 },
    #[error("keyframe {keyframe}: move and pause must be finite durations ≥ 0")]
    Duration { keyframe: usize },
    #[error("the keyframes' timing does not fit a page: the closest play speed ({speed}) is {error_s:.3} s off (a step moves at most 255 time bytes × speed / 32 cycles of 8 ms and pauses at most 255 × 32 / speed cycles)")]
    Timing { speed: u8, error_s: f64 },
    #[error("page name {0:?}: at most 13 printable ASCII characters")]
    Name(String),
}

/// The page written and how far its timing is from the keyframes' (s, at most half a control cycle).
#[derive(Debug, Clone, PartialEq)]
pub struct ExportedPage {
    pub page: Page,
    pub max_timing_error_s: f64,
}

/// The page name field for `name`: at most 13 printable ASCII characters, NUL padded.
pub fn page_name(name: &str) -> Result<[u8; NAME_BYTES], ExportError> {
    if name.len() >= NAME_BYTES || !name.bytes().all(|b| b.is_ascii_graphic() || b == b' ') {
        return Err(ExportError::Name(name.to_string()));
    }
    let mut field = [0u8; NAME_BYTES];
    field[..name.len()].copy_from_slice(name.as_bytes());
    Ok(field)
}

/// Write `keyframes` (library joint order, the table's order) over `template` under `name`.
/// `limits` are per library joint.
pub fn keyframes_to_page(
    keyframes: &[Keyframe],
    map: &IdMap,
    limits: &[JointLimits],
    template: &Page,
    name: [u8; NAME_BYTES],
) -> Result<ExportedPage, ExportError> {
    if keyframes.is_empty() || keyframes.len() > MAX_STEPS {
        return Err(ExportError::StepCount(keyframes.len()));
    }
    let mut durations = Vec::with_capacity(keyframes.len());
    for (index, frame) in keyframes.iter().enumerate() {
        let keyframe = index + 1;
        if frame.positions.len() != map.servos().len() {
            return Err(ExportError::Positions { keyframe, got: frame.positions.len(), expected: map.servos().len() });
        }
        if !(frame.move_s.is_finite() && frame.move_s >= 0.0 && frame.pause_s.is_finite() && frame.pause_s >= 0.0) {
            return Err(ExportError::Duration { keyframe });
        }
        durations.push((frame.move_s, frame.pause_s));
    }
    let preferred = if template.speed == 0 { super::page::NOMINAL_SPEED } else { template.speed };
    let timing = choose_timing(&durations, preferred);
    if timing.max_error_s > CONTROL_CYCLE_S / 2.0 + 1e-9 {
        return Err(ExportError::Timing { speed: timing.speed, error_s: timing.max_error_s });
    }
    let mut page = template.clone();
    page.name = name;
    page.schedule = TIME_BASE_SCHEDULE;
    page.speed = timing.speed;
    let kept_steps = usize::from(template.step_count).min(MAX_STEPS);
    for (index, step) in page.steps.iter_mut().enumerate() {
        let Some(frame) = keyframes.get(index) else {
            // Steps past the motion: unused ones stay as they were, formerly played ones are cleared.
            if index < kept_steps {
                *step = Step::EMPTY;
            }
            continue;
        };
        let mut positions = if index < kept_steps { step.positions } else { [INVALID_BIT; JOINT_SLOTS] };
        for (servo, (&value, limit)) in map.servos().iter().zip(frame.positions.iter().zip(limits)) {
            positions[usize::from(servo.id)] = ticks_within(index + 1, servo, value, limit)?;
        }
        *step = Step { positions, pause: timing.steps[index].pause, time: timing.steps[index].time };
    }
    page.step_count = keyframes.len() as u8;
    Ok(ExportedPage { page, max_timing_error_s: timing.max_error_s })
}

/// The tick nearest `value` whose angle stays within the limits (a value at a limit is not rounded
/// past it), checked against the servo's range.
fn ticks_within(keyframe: usize, servo: &crate::config::ServoConfig, value: f64, limit: &JointLimits) -> Result<u16, ExportError> {
    if !(value >= limit.lower && value <= limit.upper) {
        return Err(ExportError::Limits { keyframe, joint: servo.joint.clone(), value, lower: limit.lower, upper: limit.upper });
    }
    let exact = servo.ticks_from_joint(value);
    let inside = |t: f64| {
        let angle = servo.joint_from_ticks(t);
        angle >= limit.lower && angle <= limit.upper
    };
    let nearest = exact.round();
    let ticks = if inside(nearest) {
        nearest
    } else if inside(exact.floor()) {
        exact.floor()
    } else {
        exact.ceil()
    };
    if !(0.0..=f64::from(MAX_TICKS)).contains(&ticks) {
        return Err(ExportError::Ticks { keyframe, joint: servo.joint.clone(), id: servo.id, value, ticks });
    }
    Ok(ticks as u16)
}
