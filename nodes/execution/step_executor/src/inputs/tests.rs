//! The entry points on well-formed inputs, and every stored fuzz input (seeds, minimised corpus,
//! inputs that once crashed) replayed through them: each must give a result or a typed error.

use super::*;
use patchwalk_msgs::geometry_msgs::msg::Point;

use patchwalk_test_support::stored_fuzz_inputs as stored_inputs;

fn selected(selector: u8, payload: Vec<u8>) -> Vec<u8> {
    [vec![selector], payload].concat()
}

#[test]
fn requests_are_answered_as_the_node_answers_them() {
    let list = service_request(&selected(3, wire::encode(&srv::ListMotionsRequest::default()).unwrap())).unwrap();
    assert!(list.success && list.message == "1 motions", "{list:?}");
    let nan = srv::RecordKeyframeRequest { duration: f64::NAN, pause: 0.0 };
    let answer = service_request(&selected(0, wire::encode(&nan).unwrap())).unwrap();
    assert!(!answer.success && answer.message.contains("duration"), "{answer:?}");
    let fit = srv::SelectTargetRequest { mode: 1, point: Point { x: 0.1, y: 0.0, z: 0.0 }, radius: 2.0 };
    let answer = service_request(&selected(1, wire::encode(&fit).unwrap())).unwrap();
    assert!(!answer.success && answer.message.contains("radius"), "{answer:?}");
    let bidi = srv::SaveMotionRequest { name: "a\u{202E}b".into() };
    let answer = service_request(&selected(2, wire::encode(&bidi).unwrap())).unwrap();
    assert!(!answer.success, "{answer:?}");
    let play = srv::PlayMotionRequest { name: "replay_step".into() };
    let answer = service_request(&selected(5, wire::encode(&play).unwrap())).unwrap();
    assert!(!answer.success && answer.message.contains("bus"), "{answer:?}");
    assert!(matches!(service_request(&[7, 0, 1, 0, 0]), Err(InputError::Selector(7))));
    assert!(matches!(service_request(&[2, 0, 1, 0, 0, 200, 0, 0, 0]), Err(InputError::Wire(_))));
}

#[test]
fn patch_maps_are_validated_and_matched() {
    let mut map = PatchArray::default();
    map.camera_pose.orientation.w = 1.0;
    let outcome = patch_map(&wire::encode(&map).unwrap()).unwrap();
    assert_eq!((outcome.patches, outcome.skipped, outcome.matched), (0, 0, None));
    map.patches.push(patchwalk_msgs::msg::Patch { surface: 42, ..Default::default() });
    assert_eq!(patch_map(&wire::encode(&map).unwrap()).unwrap().skipped, 1);
    map.camera_pose.orientation.w = 0.0;
    assert!(matches!(patch_map(&wire::encode(&map).unwrap()), Err(InputError::Pose(_))));
}

#[test]
fn library_and_config_files_load_or_name_the_fault() {
    assert!(library_file(b"schema_version: 1\njoints: []\nmotions: []\n").is_err());
    assert!(library_file(&[0xFF, 0xFE]).unwrap_err().to_string().contains("UTF-8"));
    assert!(config_file(b"").is_ok());
    let err = config_file(b"player:\n  cycle_ms: 0.5\n").unwrap_err().to_string();
    assert!(err.contains("cycle_ms"), "{err}");
    let err = config_file(b"\0bus.baud=12").unwrap_err().to_string();
    assert!(err.contains("baud"), "{err}");
}

#[test]
fn stored_service_request_inputs_are_handled() {
    for (path, bytes) in stored_inputs("cdr_service_requests") {
        match service_request(&bytes) {
            Ok(answer) => assert!(!answer.message.is_empty(), "{}", path.display()),
            Err(e) => assert!(!e.to_string().is_empty(), "{}", path.display()),
        }
    }
}

#[test]
fn stored_patch_array_inputs_are_handled() {
    for (path, bytes) in stored_inputs("cdr_patch_array") {
        if let Ok(outcome) = patch_map(&bytes) {
            assert!(outcome.matched.is_none_or(|i| i == 0), "{}: {outcome:?}", path.display());
        }
    }
}

#[test]
fn stored_motion_library_inputs_are_handled() {
    let mut loaded = 0;
    for (path, bytes) in stored_inputs("motion_library") {
        match library_file(&bytes) {
            Ok(_) => loaded += 1,
            Err(e) => assert!(!e.to_string().is_empty(), "{}", path.display()),
        }
    }
    assert!(loaded > 0, "the seed libraries must load");
}

#[test]
fn stored_params_inputs_are_handled() {
    let mut loaded = 0;
    for (path, bytes) in stored_inputs("params_yaml") {
        match config_file(&bytes) {
            Ok(_) => loaded += 1,
            Err(e) => assert!(!e.to_string().is_empty(), "{}", path.display()),
        }
    }
    assert!(loaded > 0, "config/step_executor.yaml must load");
}

/// A three-step page written by the exporter over an empty page (knees bent a little more each step).
fn exported_page() -> Vec<u8> {
    let (map, limits) = import_tables().unwrap();
    let keyframes: Vec<Keyframe> = (0..3)
        .map(|i| {
            let mut positions = vec![0.0; 12];
            positions[6] = 0.3 + 0.1 * f64::from(i);
            positions[7] = 0.3 + 0.1 * f64::from(i);
            Keyframe { positions, move_s: 0.4, pause_s: 0.1 }
        })
        .collect();
    let name = action_file::page_name("step up").unwrap();
    action_file::keyframes_to_page(&keyframes, &map, &limits, &action_file::Page::empty(), name).unwrap().page.to_bytes().to_vec()
}

#[test]
fn action_pages_import_and_export_again_within_a_tick() {
    let page = exported_page();
    let outcome = action_page(&[&[0u8][..], &page].concat()).unwrap();
    assert_eq!(outcome.keyframes, 3);
    let error = outcome.reexport.unwrap();
    assert!(error <= std::f64::consts::TAU / 4096.0, "{error}");
    // One position tick changed: the checksum refuses it, unless byte 0 asks to fix it first.
    let mut changed = page.clone();
    changed[64 + 2 * 7] ^= 1;
    assert!(matches!(action_page(&[&[0u8][..], &changed].concat()), Err(InputError::Page(PageError::Checksum { .. }))));
    assert_eq!(action_page(&[&[1u8][..], &changed].concat()).unwrap().keyframes, 3);
    assert!(matches!(action_page(&[1, 2, 3]), Err(InputError::Page(PageError::Length(2)))));
    assert!(matches!(action_page(&[]), Err(InputError::Empty)));
}

#[test]
fn stored_action_page_inputs_are_handled() {
    let mut imported = 0;
    for (path, bytes) in stored_inputs("action_page") {
        match action_page(&bytes) {
            Ok(outcome) => {
                imported += 1;
                if let Ok(error) = outcome.reexport {
                    assert!(error <= std::f64::consts::TAU / 4096.0 * 1.01, "{}: re-export {error} rad off", path.display());
                }
            }
            Err(InputError::PageRoundTrip) => panic!("{}: the page does not write back byte for byte", path.display()),
            Err(e) => assert!(!e.to_string().is_empty(), "{}", path.display()),
        }
    }
    assert!(imported > 0, "the seed pages must import");
}
