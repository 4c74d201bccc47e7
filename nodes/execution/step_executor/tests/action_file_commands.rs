#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic)] // an integration test
//! `step_executor import-motion` / `export-motion` run as a user runs them, on action files written
//! byte by byte from the published ROBOTIS layout: the round trip, and every refusal leaving the
//! library and the action file as they were.

use std::path::PathBuf;
use std::process::Command;

use nalgebra::{Vector2, Vector3};
use patchwalk_spl::patch::{BoundaryType, Patch, SurfaceType};
use step_executor::config::DEFAULT_JOINTS;
use step_executor::library::{Keyframe, Motion, MotionLibrary};

const PAGE: usize = 512;

fn fix_checksum(page: &mut [u8]) {
    page[31] = 0;
    let sum: u32 = page.iter().map(|&b| u32::from(b)).sum();
    page[31] = (0xFF - sum % 256) as u8;
}

/// ROBOTIS' empty page: repeat 1, time based (0x0a), speed 32, accel 32, P gain 0x55, all 0x4000.
fn empty_page() -> Vec<u8> {
    let mut p = vec![0u8; PAGE];
    p[15] = 1;
    p[16] = 0x0a;
    p[22] = 32;
    p[24] = 32;
    p[32..63].fill(0x55);
    for slot in 0..7 * 31 {
        let at = 64 + (slot / 31) * 64 + (slot % 31) * 2;
        p[at..at + 2].copy_from_slice(&0x4000u16.to_le_bytes());
    }
    fix_checksum(&mut p);
    p
}

/// A 3-step page: legs (IDs 7–18) within the RPBP limits, arms (1–6) and head (19, 20) set too.
fn motion_page() -> Vec<u8> {
    let mut p = empty_page();
    p[..9].copy_from_slice(b"r_kick_01");
    p[20] = 3;
    p[24] = 20;
    p[25] = 12; // next page
    for step in 0..3 {
        let base = 64 + 64 * step;
        for id in 1..=20usize {
            let ticks: u16 = match id {
                13 | 14 => 2500 + 30 * step as u16,
                7..=18 => 2030 + (id as u16) + 10 * step as u16,
                _ => 1900 + id as u16,
            };
            p[base + 2 * id..base + 2 * id + 2].copy_from_slice(&ticks.to_le_bytes());
        }
        p[base + 62] = [0, 12, 40][step];
        p[base + 63] = [80, 45, 120][step];
    }
    fix_checksum(&mut p);
    p
}

fn action_file(pages: &[(usize, Vec<u8>)]) -> Vec<u8> {
    let mut file: Vec<u8> = (0..256).flat_map(|_| empty_page()).collect();
    for (n, page) in pages {
        file[n * PAGE..(n + 1) * PAGE].copy_from_slice(page);
    }
    file
}

fn joints() -> Vec<String> {
    DEFAULT_JOINTS.iter().map(|j| j.to_string()).collect()
}

fn trained(name: &str, keyframes: usize) -> Motion {
    let patch = Patch::new(
        SurfaceType::EllipticParaboloid,
        BoundaryType::Ellipse,
        vec![0.04, 0.03],
        Vector2::new(12.0, 8.5),
        Vector3::new(0.01, -0.02, 0.3),
        Vector3::new(0.12, 0.04, -0.27),
    )
    .unwrap();
    let frame = Keyframe { positions: vec![0.1; 12], move_s: 0.8, pause_s: 0.0 };
    Motion { name: name.into(), patch, keyframes: vec![frame; keyframes] }
}

struct Workspace {
    dir: tempfile::TempDir,
}

impl Workspace {
    /// A library with "rock1" (2 keyframes) and "long" (8 keyframes), and `motion_4096.bin` holding
    /// [`motion_page`] on page 5, a corrupt page 7 and 8 steps claimed on page 8.
    fn new() -> Self {
        let dir = tempfile::tempdir().unwrap();
        let mut library = MotionLibrary::new(&dir.path().join("motions.yaml"), joints());
        library.insert(trained("rock1", 2)).unwrap();
        library.insert(trained("long", 8)).unwrap();
        library.save().unwrap();
        let mut corrupt = motion_page();
        corrupt[300] ^= 0x10;
        let mut eight = motion_page();
        eight[20] = 8;
        fix_checksum(&mut eight);
        std::fs::write(dir.path().join("motion_4096.bin"), action_file(&[(5, motion_page()), (7, corrupt), (8, eight)])).unwrap();
        Self { dir }
    }

    fn path(&self, name: &str) -> PathBuf {
        self.dir.path().join(name)
    }

    fn run(&self, args: &[&str]) -> (bool, String, String) {
        let output = Command::new(env!("CARGO_BIN_EXE_step_executor"))
            .args(args)
            .arg("--library")
            .arg(self.path("motions.yaml"))
            .current_dir(self.dir.path())
            .output()
            .unwrap();
        (
            output.status.success(),
            String::from_utf8_lossy(&output.stdout).into_owned(),
            String::from_utf8_lossy(&output.stderr).into_owned(),
        )
    }

    fn snapshot(&self) -> Vec<(String, Vec<u8>)> {
        let mut files: Vec<(String, Vec<u8>)> = std::fs::read_dir(self.dir.path())
            .unwrap()
            .map(|e| e.unwrap().path())
            .map(|p| (p.file_name().unwrap().to_string_lossy().into_owned(), std::fs::read(&p).unwrap()))
            .collect();
        files.sort();
        files
    }
}

fn import<'a>(file: &'a str, page: &'a str, name: &'a str) -> Vec<&'a str> {
    vec!["import-motion", file, "--page", page, "--name", name, "--target-from", "rock1"]
}

#[test]
fn import_then_export_writes_the_page_back_byte_for_byte() {
    let ws = Workspace::new();
    let (ok, stdout, stderr) = ws.run(&import("motion_4096.bin", "5", "kick"));
    assert!(ok, "{stderr}");
    assert!(stdout.contains("3 keyframes") && stdout.contains("[1, 2, 3, 4, 5, 6, 19, 20]"), "{stdout}");
    let library = MotionLibrary::load(&ws.path("motions.yaml"), &joints()).unwrap();
    let kick = library.get("kick").unwrap();
    assert_eq!(kick.patch, library.get("rock1").unwrap().patch);
    assert_eq!(kick.keyframes.len(), 3);
    assert!((kick.keyframes[1].move_s - 45.0 * 0.008).abs() < 1e-12 && (kick.keyframes[1].pause_s - 12.0 * 0.008).abs() < 1e-12);
    let r_knee = 6; // ID 13
    assert!((kick.keyframes[2].positions[r_knee] - (2560.0 - 2048.0) * std::f64::consts::TAU / 4096.0).abs() < 1e-12);

    // Back over the same page of a copy: the copy equals the original file.
    std::fs::copy(ws.path("motion_4096.bin"), ws.path("copy_4096.bin")).unwrap();
    let (ok, _, stderr) = ws.run(&["export-motion", "--name", "kick", "--out", "copy_4096.bin", "--page", "5", "--replace"]);
    assert!(ok, "{stderr}");
    assert_eq!(std::fs::read(ws.path("copy_4096.bin")).unwrap(), std::fs::read(ws.path("motion_4096.bin")).unwrap());

    // Into a new file: 256 pages, page 9 the legs of page 5 under the motion's name, the rest empty.
    let (ok, stdout, stderr) = ws.run(&["export-motion", "--name", "kick", "--out", "new_4095.bin", "--page", "9"]);
    assert!(ok && stdout.contains("new file"), "{stdout}{stderr}");
    let new = std::fs::read(ws.path("new_4095.bin")).unwrap();
    assert_eq!(new.len(), 256 * PAGE);
    let page9 = &new[9 * PAGE..10 * PAGE];
    assert_eq!(page9.iter().map(|&b| u32::from(b)).sum::<u32>() % 256, 0xFF);
    assert_eq!(&page9[..5], b"kick\0");
    assert_eq!(page9[20], 3);
    let original = motion_page();
    for step in 0..3 {
        let base = 64 + 64 * step;
        for id in 0..31 {
            let at = base + 2 * id;
            let expected = if (7..=18).contains(&id) { &original[at..at + 2] } else { &[0x00, 0x40][..] };
            assert_eq!(&page9[at..at + 2], expected, "step {step} id {id}");
        }
        assert_eq!(&page9[base + 62..base + 64], &original[base + 62..base + 64]);
    }
    assert!((0..256).filter(|&n| n != 9).all(|n| new[n * PAGE..(n + 1) * PAGE] == empty_page()[..]));
    // The new page imports to the same keyframes.
    let (ok, _, stderr) = ws.run(&import("new_4095.bin", "9", "kick again"));
    assert!(ok, "{stderr}");
    let library = MotionLibrary::load(&ws.path("motions.yaml"), &joints()).unwrap();
    assert_eq!(library.get("kick again").unwrap().keyframes, library.get("kick").unwrap().keyframes);
}

/// Each refusal: the command fails naming the problem, and no file changes.
#[test]
fn every_refusal_names_the_problem_and_writes_nothing() {
    let ws = Workspace::new();
    std::fs::write(ws.path("short.bin"), vec![0u8; 1000]).unwrap();
    std::fs::write(ws.path("motion_1024.bin"), action_file(&[(5, motion_page())])).unwrap();
    std::fs::write(ws.path("bad_id.yaml"), "- { id: 31, joint: r_hip_yaw }\n").unwrap();
    std::fs::write(ws.path("bad_joint.yaml"), "- { id: 7, joint: r_elbow }\n").unwrap();
    let mut knee_back = motion_page();
    knee_back[64 + 64 + 2 * 14..64 + 64 + 2 * 14 + 2].copy_from_slice(&1900u16.to_le_bytes());
    fix_checksum(&mut knee_back);
    std::fs::write(ws.path("knee_4096.bin"), action_file(&[(5, knee_back)])).unwrap();
    std::fs::copy(ws.path("motion_4096.bin"), ws.path("out_4096.bin")).unwrap();
    let before = ws.snapshot();
    let with_map = |map: &'static str| {
        let mut args = import("motion_4096.bin", "5", "x");
        args.extend(["--id-map", map]);
        args
    };
    let cases: Vec<(Vec<&str>, &str)> = vec![
        (import("motion_4096.bin", "7", "x"), "bad checksum"),
        (import("motion_4096.bin", "0", "x"), "page 0 is out of range"),
        (import("motion_4096.bin", "256", "x"), "page 256 is out of range"),
        (import("motion_4096.bin", "6", "x"), "0 steps"),
        (import("motion_4096.bin", "8", "x"), "step count 8"),
        (import("knee_4096.bin", "5", "x"), "step 2: ID 14 (l_knee) at 1900 ticks"),
        (import("motion_4096.bin", "5", "rock1"), "motion \"rock1\" already exists"),
        (import("motion_4096.bin", "5", " x"), "whitespace"),
        (import("short.bin", "5", "x"), "not an action file: it is 1000 bytes"),
        (import("motion_1024.bin", "5", "x"), "1024-tick"),
        (import("missing.bin", "5", "x"), "cannot read"),
        (with_map("bad_id.yaml"), "ID 31 is not a position slot"),
        (with_map("bad_joint.yaml"), "unknown joint \"r_elbow\""),
        (vec!["import-motion", "motion_4096.bin", "--page", "5", "--name", "x", "--target-from", "nope"], "no motion named \"nope\""),
        (vec!["export-motion", "--name", "rock1", "--out", "out_4096.bin", "--page", "5"], "already holds \"r_kick_01\" with 3 steps"),
        (vec!["export-motion", "--name", "rock1", "--out", "out_4096.bin", "--page", "7"], "bad checksum"),
        (vec!["export-motion", "--name", "rock1", "--out", "out_4096.bin", "--page", "0"], "out of range"),
        (vec!["export-motion", "--name", "nope", "--out", "out_4096.bin", "--page", "9"], "no motion named \"nope\""),
        (vec!["export-motion", "--name", "long", "--out", "out_4096.bin", "--page", "9"], "8 keyframes"),
        (vec!["export-motion", "--name", "rock1", "--out", "short.bin", "--page", "9"], "not an action file"),
        (
            vec!["export-motion", "--name", "rock1", "--out", "out_4096.bin", "--page", "9", "--page-name", "far too long a name"],
            "page name",
        ),
    ];
    for (args, expected) in cases {
        let (ok, stdout, stderr) = ws.run(&args);
        assert!(!ok, "{args:?} succeeded: {stdout}");
        assert!(stderr.contains(expected), "{args:?}: expected {expected:?} in {stderr}");
        assert!(!stderr.contains("panicked"), "{stderr}");
        assert_eq!(ws.snapshot(), before, "{args:?} changed a file");
    }
}

#[test]
fn the_help_lists_both_commands() {
    let output = Command::new(env!("CARGO_BIN_EXE_step_executor")).arg("--help").output().unwrap();
    let text = String::from_utf8_lossy(&output.stdout);
    assert!(text.contains("import-motion") && text.contains("export-motion"), "{text}");
}
