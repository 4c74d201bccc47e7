//! Page ↔ keyframe conversion on pages built byte by byte from the published layout.

use patchwalk_robot_model::kinematics::{JointLimits, RobotModel};
use patchwalk_robot_model::{DEFAULT_JOINTS, RPBP_URDF};

use super::*;
use crate::library::Keyframe;

const TAU: f64 = std::f64::consts::TAU;

fn joints() -> Vec<String> {
    DEFAULT_JOINTS.iter().map(|j| j.to_string()).collect()
}

fn limits() -> Vec<JointLimits> {
    let model = RobotModel::from_urdf_str(RPBP_URDF).unwrap();
    joints().iter().map(|j| model.joint_limits(j).unwrap().unwrap()).collect()
}

fn default_map() -> IdMap {
    IdMap::for_joints(&IdMap::darwin_op_legs(), &joints()).unwrap()
}

/// Leg ticks of step `s` for ID `id` (7..=18): knees (13, 14) bent forward, the rest near the centre.
fn leg_ticks(step: usize, id: usize) -> u16 {
    let base: u16 = if id == 13 || id == 14 { 2600 } else { 2000 };
    base + (step as u16) * 40 + id as u16
}

/// A DARwIn-OP-like page written from the published layout: `steps` steps with the legs (IDs 7–18)
/// at [`leg_ticks`], arms and head (IDs 1–6, 19, 20) at 2048 + ID, other slots 0x4000, step `s`
/// pausing `10 s` bytes and moving `60 + 20 s` bytes; header name "stand up", repeat 1, the given
/// schedule and speed, accel 24, next 3, exit 4, P gain 32, a reserved byte set.
fn darwin_page(steps: usize, schedule: u8, speed: u8) -> Vec<u8> {
    let mut b = vec![0u8; 512];
    b[..8].copy_from_slice(b"stand up");
    b[15] = 1;
    b[16] = schedule;
    b[18] = 0x5A;
    b[20] = steps as u8;
    b[22] = speed;
    b[24] = 24;
    b[25] = 3;
    b[26] = 4;
    b[32..63].fill(32);
    for step in 0..7 {
        let base = 64 + 64 * step;
        for id in 0..31 {
            let value = if step >= steps {
                0x4000
            } else if (7..=18).contains(&id) {
                leg_ticks(step, id)
            } else if (1..=6).contains(&id) || id == 19 || id == 20 {
                2048 + id as u16
            } else {
                0x4000
            };
            b[base + 2 * id..base + 2 * id + 2].copy_from_slice(&value.to_le_bytes());
        }
        if step < steps {
            b[base + 62] = 10 * step as u8;
            b[base + 63] = 60 + 20 * step as u8;
        }
    }
    fix_checksum(&mut b);
    b
}

fn fix_checksum(b: &mut [u8]) {
    b[31] = 0;
    let sum: u32 = b.iter().map(|&x| u32::from(x)).sum();
    b[31] = (0xFF - (sum % 256)) as u8;
}

fn set_position(b: &mut [u8], step: usize, id: usize, value: u16) {
    let at = 64 + 64 * step + 2 * id;
    b[at..at + 2].copy_from_slice(&value.to_le_bytes());
    fix_checksum(b);
}

fn import(bytes: &[u8]) -> Result<ImportedSteps, ImportError> {
    page_to_keyframes(&parse_page(bytes).unwrap(), &default_map(), &limits())
}

#[test]
fn a_time_based_page_becomes_keyframes_in_library_order() {
    let imported = import(&darwin_page(3, 0x0a, 32)).unwrap();
    assert_eq!(imported.keyframes.len(), 3);
    for (s, frame) in imported.keyframes.iter().enumerate() {
        for (j, &value) in frame.positions.iter().enumerate() {
            let ticks = f64::from(leg_ticks(s, 7 + j));
            assert!((value - (ticks - 2048.0) * TAU / 4096.0).abs() < 1e-12, "step {s} joint {j}");
        }
        // Speed 32: the bytes are 8 ms cycles.
        assert!((frame.move_s - (60 + 20 * s) as f64 * 0.008).abs() < 1e-12);
        assert!((frame.pause_s - (10 * s) as f64 * 0.008).abs() < 1e-12);
    }
    // ID 7 is r_hip_yaw (library joint 0), ID 14 l_knee (joint 7).
    assert!((imported.keyframes[0].positions[0] - (2007.0 - 2048.0) * TAU / 4096.0).abs() < 1e-12);
    assert!((imported.keyframes[0].positions[7] - (2614.0 - 2048.0) * TAU / 4096.0).abs() < 1e-12);
    assert_eq!(imported.unmapped_ids, vec![1, 2, 3, 4, 5, 6, 19, 20]);
}

#[test]
fn the_play_speed_scales_moves_up_and_pauses_down() {
    let imported = import(&darwin_page(2, 0x0a, 64)).unwrap();
    assert!((imported.keyframes[1].move_s - 80.0 * 2.0 * 0.008).abs() < 1e-12);
    assert!((imported.keyframes[1].pause_s - 5.0 * 0.008).abs() < 1e-12);
}

#[test]
fn import_then_export_over_the_same_page_is_byte_identical() {
    for (steps, speed) in [(3, 32), (7, 32), (1, 32), (4, 64)] {
        let bytes = darwin_page(steps, 0x0a, speed);
        let original = parse_page(&bytes).unwrap();
        let imported = import(&bytes).unwrap();
        let exported = keyframes_to_page(&imported.keyframes, &default_map(), &limits(), &original, original.name).unwrap();
        assert_eq!(exported.page.to_bytes().as_slice(), bytes.as_slice(), "{steps} steps at speed {speed}");
        assert!(exported.max_timing_error_s < 1e-12);
    }
}

#[test]
fn export_to_a_new_page_keeps_the_legs_and_timing() {
    let bytes = darwin_page(3, 0x0a, 32);
    let imported = import(&bytes).unwrap();
    let exported = keyframes_to_page(&imported.keyframes, &default_map(), &limits(), &Page::empty(), page_name("step").unwrap()).unwrap();
    let written = parse_page(&exported.page.to_bytes()).unwrap();
    assert_eq!(written.name_text(), "step");
    assert_eq!((written.step_count, written.speed, written.schedule, written.repeat), (3, 32, 0x0a, 1));
    for s in 0..3 {
        for id in 0..31 {
            let expected = if (7..=18).contains(&id) { leg_ticks(s, id) } else { 0x4000 };
            assert_eq!(written.steps[s].positions[id], expected, "step {s} id {id}");
        }
        assert_eq!((written.steps[s].pause, written.steps[s].time), (10 * s as u8, 60 + 20 * s as u8));
    }
    assert_eq!(written.steps[3], Step::EMPTY);
    assert_eq!(import(&written.to_bytes()).unwrap().keyframes, imported.keyframes);
}

#[test]
fn fewer_keyframes_over_a_longer_page_clear_its_old_steps() {
    let bytes = darwin_page(5, 0x0a, 32);
    let original = parse_page(&bytes).unwrap();
    let imported = import(&darwin_page(2, 0x0a, 32)).unwrap();
    let exported = keyframes_to_page(&imported.keyframes, &default_map(), &limits(), &original, original.name).unwrap();
    assert_eq!(exported.page.step_count, 2);
    assert_eq!(exported.page.steps[1].positions[3], 2051, "arms of a kept step stay");
    assert_eq!(exported.page.steps[2..5], [Step::EMPTY; 3]);
    assert_eq!((exported.page.next, exported.page.exit, exported.page.accel), (3, 4, 24));
}

#[test]
fn a_missing_position_keeps_the_previous_step_and_is_refused_in_the_first() {
    let mut bytes = darwin_page(2, 0x0a, 32);
    set_position(&mut bytes, 1, 9, 0x4000);
    let imported = import(&bytes).unwrap();
    assert_eq!(imported.keyframes[1].positions[2], imported.keyframes[0].positions[2]);
    set_position(&mut bytes, 0, 9, 0x4000);
    let err = import(&bytes).unwrap_err();
    assert_eq!(err, ImportError::MissingPosition { step: 1, id: 9, joint: "r_hip_roll".into() });
    assert!(err.to_string().contains("ID 9 (r_hip_roll)"), "{err}");
}

#[test]
fn pages_that_are_not_time_based_motions_are_refused() {
    assert_eq!(import(&darwin_page(0, 0x0a, 32)).unwrap_err(), ImportError::NoSteps);
    assert_eq!(import(&darwin_page(2, 0x00, 32)).unwrap_err(), ImportError::SpeedBased);
    assert_eq!(import(&darwin_page(2, 0x05, 32)).unwrap_err(), ImportError::Schedule(0x05));
    assert_eq!(import(&darwin_page(2, 0x0a, 0)).unwrap_err(), ImportError::ZeroSpeed);
    let mut bytes = darwin_page(2, 0x0a, 32);
    bytes[15] = 0;
    fix_checksum(&mut bytes);
    assert_eq!(import(&bytes).unwrap_err(), ImportError::NoRepeat);
}

#[test]
fn bad_positions_are_refused_naming_step_id_and_joint() {
    let mut bytes = darwin_page(2, 0x0a, 32);
    set_position(&mut bytes, 1, 12, 0x2000 | 2048);
    assert_eq!(import(&bytes).unwrap_err(), ImportError::TorqueOff { step: 2, id: 12, joint: "l_hip_pitch".into() });
    let mut bytes = darwin_page(2, 0x0a, 32);
    set_position(&mut bytes, 0, 8, 4096);
    assert_eq!(import(&bytes).unwrap_err(), ImportError::Ticks { step: 1, id: 8, joint: "l_hip_yaw".into(), raw: 4096 });
    // A knee bent backwards: 1800 ticks is −0.38 rad, the knee's limits are [0, 2.4].
    let mut bytes = darwin_page(2, 0x0a, 32);
    set_position(&mut bytes, 1, 13, 1800);
    let err = import(&bytes).unwrap_err();
    assert!(
        matches!(&err, ImportError::Limits { step: 2, id: 13, ticks: 1800, lower, upper, .. } if *lower == 0.0 && *upper == 2.4),
        "{err}"
    );
    assert!(err.to_string().contains("r_knee") && err.to_string().contains("outside the joint limits"), "{err}");
}

#[test]
fn a_table_direction_flips_the_joint() {
    let mut entries = IdMap::darwin_op_legs();
    entries[6].direction = -1; // r_knee, ID 13
    let map = IdMap::for_joints(&entries, &joints()).unwrap();
    let mut bytes = darwin_page(1, 0x0a, 32);
    set_position(&mut bytes, 0, 13, 1500);
    let imported = page_to_keyframes(&parse_page(&bytes).unwrap(), &map, &limits()).unwrap();
    assert!((imported.keyframes[0].positions[6] - 548.0 * TAU / 4096.0).abs() < 1e-12);
    let exported = keyframes_to_page(&imported.keyframes, &map, &limits(), &Page::empty(), [0; 14]).unwrap();
    assert_eq!(exported.page.steps[0].positions[13], 1500);
}

fn frame(positions: Vec<f64>, move_s: f64, pause_s: f64) -> Keyframe {
    Keyframe { positions, move_s, pause_s }
}

fn knees_bent() -> Vec<f64> {
    let mut p = vec![0.0; 12];
    p[6] = 0.5;
    p[7] = 0.5;
    p
}

#[test]
fn export_refuses_what_a_page_cannot_hold() {
    let map = default_map();
    let ok = frame(knees_bent(), 0.5, 0.1);
    let err = keyframes_to_page(&vec![ok.clone(); 8], &map, &limits(), &Page::empty(), [0; 14]).unwrap_err();
    assert_eq!(err, ExportError::StepCount(8));
    assert_eq!(keyframes_to_page(&[], &map, &limits(), &Page::empty(), [0; 14]).unwrap_err(), ExportError::StepCount(0));
    let mut over = knees_bent();
    over[7] = 2.5;
    let err = keyframes_to_page(&[ok.clone(), frame(over, 0.5, 0.0)], &map, &limits(), &Page::empty(), [0; 14]).unwrap_err();
    assert!(matches!(&err, ExportError::Limits { keyframe: 2, joint, .. } if joint == "l_knee"), "{err}");
    let err = keyframes_to_page(&[frame(knees_bent(), 16.0, 2.0)], &map, &limits(), &Page::empty(), [0; 14]).unwrap_err();
    assert!(matches!(err, ExportError::Timing { .. }), "{err}");
    let err = keyframes_to_page(&[frame(knees_bent(), f64::NAN, 0.0)], &map, &limits(), &Page::empty(), [0; 14]).unwrap_err();
    assert_eq!(err, ExportError::Duration { keyframe: 1 });
    let err = keyframes_to_page(&[frame(vec![0.0; 11], 0.5, 0.0)], &map, &limits(), &Page::empty(), [0; 14]).unwrap_err();
    assert_eq!(err, ExportError::Positions { keyframe: 1, got: 11, expected: 12 });
    assert!(page_name("a name that is too long").is_err());
    assert!(page_name("tab\there").is_err());
    assert_eq!(&page_name("walk 1").unwrap()[..7], b"walk 1\0");
}

#[test]
fn a_position_at_a_limit_is_written_inside_it() {
    let mut at_limit = knees_bent();
    at_limit[6] = 2.4; // r_knee's upper limit; 2.4 rad is 3612.4 ticks
    let exported = keyframes_to_page(&[frame(at_limit, 0.4, 0.0)], &default_map(), &limits(), &Page::empty(), [0; 14]).unwrap();
    assert_eq!(exported.page.steps[0].positions[13], 3612);
    import(&exported.page.to_bytes()).unwrap();
}

#[test]
fn a_long_move_is_written_at_a_faster_play_speed() {
    let exported = keyframes_to_page(&[frame(knees_bent(), 4.0, 0.0)], &default_map(), &limits(), &Page::empty(), [0; 14]).unwrap();
    assert!(exported.page.speed > 32);
    let back = import(&exported.page.to_bytes()).unwrap();
    assert!((back.keyframes[0].move_s - 4.0).abs() <= 0.004, "{}", back.keyframes[0].move_s);
}
