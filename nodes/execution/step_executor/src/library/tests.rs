//! Tests of the motion library: round trips, malformed files, atomic saves, names, stale files.

use super::*;

fn joints() -> Vec<String> {
    crate::config::DEFAULT_JOINTS.iter().map(|s| (*s).to_string()).collect()
}

fn motion(name: &str) -> Motion {
    Motion {
        name: name.into(),
        patch: Patch::new(
            SurfaceType::EllipticParaboloid,
            BoundaryType::Ellipse,
            vec![0.04, 0.03],
            Vector2::new(12.0, 8.5),
            Vector3::new(0.01, -0.02, 0.3),
            Vector3::new(0.12, 0.04, -0.27),
        )
        .unwrap(),
        keyframes: vec![
            Keyframe { positions: vec![0.1; 12], move_s: 0.8, pause_s: 0.1 },
            Keyframe { positions: vec![-0.2; 12], move_s: 1.0, pause_s: 0.0 },
        ],
    }
}

#[test]
fn round_trip_through_file() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("motions.yaml");
    let mut library = MotionLibrary::new(&path, joints());
    library.insert(motion("rock1")).unwrap();
    library.insert(motion("rock2")).unwrap();
    library.save().unwrap();
    let back = MotionLibrary::load(&path, &joints()).unwrap();
    assert_eq!(back.motions(), library.motions());
    assert_eq!(back.names(), vec!["rock1", "rock2"]);
    // no temp files left behind
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
}

#[test]
fn duplicate_and_invalid_inserts_are_rejected() {
    let mut library = MotionLibrary::new(Path::new("x.yaml"), joints());
    library.insert(motion("a")).unwrap();
    assert!(matches!(library.insert(motion("a")), Err(LibraryError::Duplicate(_))));
    let mut bad = motion("b");
    bad.keyframes[1].positions.pop();
    let err = library.insert(bad).unwrap_err().to_string();
    assert!(err.contains("keyframes[1].positions"), "{err}");
    assert!(matches!(library.remove("zz"), Err(LibraryError::NotFound(_))));
    assert_eq!(library.remove("a").unwrap().name, "a");
}

#[test]
fn malformed_entry_error_names_entry_and_field() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("motions.yaml");
    let mut library = MotionLibrary::new(&path, joints());
    library.insert(motion("rock1")).unwrap();
    library.insert(motion("rock2")).unwrap();
    let text = library.to_yaml().unwrap();
    // Break the second entry's curvature list.
    let broken = text.replacen("- 12.0\n", "- twelve\n", 2).replacen("- twelve\n", "- 12.0\n", 1);
    std::fs::write(&path, &broken).unwrap();
    let err = MotionLibrary::load(&path, &joints()).unwrap_err().to_string();
    assert!(err.contains("motions[1] (name \"rock2\").patch.k"), "{err}");

    std::fs::write(&path, text.replace("pause_s: 0.1", "pause: 0.1")).unwrap();
    let err = MotionLibrary::load(&path, &joints()).unwrap_err().to_string();
    assert!(err.contains("motions[0] (name \"rock1\").keyframes[0].pause"), "{err}");
}

#[test]
fn corrupt_file_gives_empty_library_and_is_kept() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("motions.yaml");
    std::fs::write(&path, "schema_version: 1\njoints: [a\n").unwrap();
    let (mut library, err) = MotionLibrary::load_or_empty(&path, &joints());
    assert!(err.is_some());
    assert!(library.motions().is_empty());
    assert_eq!(std::fs::read_to_string(&path).unwrap(), "schema_version: 1\njoints: [a\n");
    library.insert(motion("fresh")).unwrap();
    library.save().unwrap();
    let corrupt = dir.path().join("motions.yaml.corrupt");
    assert_eq!(std::fs::read_to_string(corrupt).unwrap(), "schema_version: 1\njoints: [a\n");
    assert_eq!(MotionLibrary::load(&path, &joints()).unwrap().names(), vec!["fresh"]);
}

const WRITER_ENV: &str = "STEP_EXECUTOR_LIBRARY_WRITER";

/// SIGKILL a process that saves libraries in a loop, at varying moments: the file must always
/// load (old or new content, never partial). (A kill keeps the page cache, so this checks the
/// rename protocol; the fsyncs cover power loss.)
#[test]
fn killed_writer_leaves_old_or_new_file() {
    if let Ok(path) = std::env::var(WRITER_ENV) {
        // Child mode: save ever-changing libraries until killed.
        let path = PathBuf::from(path);
        for i in 0u64.. {
            let mut library = MotionLibrary::new(&path, joints());
            for n in 0..=(i % 25) {
                library.insert(motion(&format!("m{n}"))).unwrap();
            }
            library.save().unwrap();
        }
    }
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("motions.yaml");
    let mut library = MotionLibrary::new(&path, joints());
    library.insert(motion("initial")).unwrap();
    library.save().unwrap();
    let exe = std::env::current_exe().unwrap();
    let mut rewritten = 0;
    for round in 0..10u64 {
        let mut child = std::process::Command::new(&exe)
            .args(["--exact", "library::tests::killed_writer_leaves_old_or_new_file", "--nocapture"])
            .env(WRITER_ENV, &path)
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .spawn()
            .unwrap();
        std::thread::sleep(std::time::Duration::from_millis(30 + 17 * round));
        child.kill().unwrap();
        child.wait().unwrap();
        let loaded = MotionLibrary::load(&path, &joints()).unwrap();
        assert!(!loaded.names().is_empty(), "round {round}");
        rewritten += usize::from(loaded.names() != ["initial"]);
    }
    assert!(rewritten > 0, "the writer never replaced the file");
}

#[test]
fn wrong_schema_version_or_joint_order_rejected() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m.yaml");
    std::fs::write(&path, "schema_version: 7\njoints: []\nmotions: []\n").unwrap();
    assert!(MotionLibrary::load(&path, &joints()).unwrap_err().to_string().contains("schema_version"));
    std::fs::write(&path, "schema_version: 1\njoints: [a]\nmotions: []\n").unwrap();
    assert!(MotionLibrary::load(&path, &joints()).unwrap_err().to_string().contains("joints"));
}

#[test]
fn atomic_save_leaves_old_or_new_never_partial() {
    // Simulate a crash between writing the temp file and renaming: the target keeps the old
    // content, and a later save replaces it completely.
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("motions.yaml");
    let mut library = MotionLibrary::new(&path, joints());
    library.insert(motion("old")).unwrap();
    library.save().unwrap();
    let old = std::fs::read_to_string(&path).unwrap();
    // A stale temp file from a crashed writer must not disturb loading or saving.
    std::fs::write(dir.path().join(format!(".motions.yaml.tmp-{}", std::process::id())), "garbage: [").unwrap();
    assert_eq!(MotionLibrary::load(&path, &joints()).unwrap().names(), vec!["old"]);
    assert_eq!(std::fs::read_to_string(&path).unwrap(), old);
    library.insert(motion("new")).unwrap();
    library.save().unwrap();
    assert_eq!(MotionLibrary::load(&path, &joints()).unwrap().names(), vec!["old", "new"]);
    // Saving into a missing directory fails cleanly and leaves nothing behind.
    let mut orphan = MotionLibrary::new(&dir.path().join("no/such/dir/m.yaml"), joints());
    assert!(matches!(orphan.save(), Err(LibraryError::Io { .. })));
}

#[test]
fn a_file_starting_with_a_utf8_bom_loads() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("motions.yaml");
    let mut library = MotionLibrary::new(&path, joints());
    library.insert(motion("rock1")).unwrap();
    std::fs::write(&path, format!("\u{FEFF}{}", library.to_yaml().unwrap())).unwrap();
    assert_eq!(MotionLibrary::load(&path, &joints()).unwrap().names(), vec!["rock1"]);
}

#[test]
fn stale_temp_files_of_ours_are_removed_and_nothing_else() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("motions.yaml");
    let mut library = MotionLibrary::new(&path, joints());
    library.insert(motion("rock1")).unwrap();
    library.save().unwrap();
    // A pid no process has (above the kernel's pid_max of 2^22) and this process's own pid.
    let dead = dir.path().join(".motions.yaml.tmp-4194999");
    let own = dir.path().join(format!(".motions.yaml.tmp-{}", std::process::id()));
    // Not ours: other names, a live process's save (pid 1), a non-numeric suffix, a directory.
    let keep = [
        dir.path().join(".other.yaml.tmp-4194999"),
        dir.path().join("motions.yaml.tmp-4194999"),
        dir.path().join(".motions.yaml.tmp-1"),
        dir.path().join(".motions.yaml.tmp-12x"),
        dir.path().join(".motions.yaml.tmp-"),
        dir.path().join("notes.txt"),
    ];
    for file in keep.iter().chain([&dead, &own]) {
        std::fs::write(file, "garbage: [").unwrap();
    }
    let as_dir = dir.path().join(".motions.yaml.tmp-4194998");
    std::fs::create_dir(&as_dir).unwrap();
    let mut removed = remove_stale_temp_files(&path).unwrap();
    removed.sort();
    let mut expected = vec![dead.clone(), own.clone()];
    expected.sort();
    assert_eq!(removed, expected);
    assert!(!dead.exists() && !own.exists());
    assert!(keep.iter().all(|f| f.exists()) && as_dir.is_dir() && path.exists());
    assert_eq!(remove_stale_temp_files(&path).unwrap(), Vec::<PathBuf>::new());
    // A library in a directory that does not exist (yet) has nothing to clean.
    assert!(remove_stale_temp_files(&dir.path().join("no/such/m.yaml")).unwrap().is_empty());
}

#[test]
fn a_second_corrupt_file_does_not_overwrite_the_first_copy() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("motions.yaml");
    for (round, garbage) in ["first: [", "second: [", "third: ["].into_iter().enumerate() {
        std::fs::write(&path, garbage).unwrap();
        let (mut library, err) = MotionLibrary::load_or_empty(&path, &joints());
        assert!(err.is_some());
        library.insert(motion(&format!("fresh{round}"))).unwrap();
        library.save().unwrap();
    }
    let read = |name: &str| std::fs::read_to_string(dir.path().join(name)).unwrap();
    assert_eq!(read("motions.yaml.corrupt"), "first: [");
    assert_eq!(read("motions.yaml.corrupt.1"), "second: [");
    assert_eq!(read("motions.yaml.corrupt.2"), "third: [");
    assert_eq!(MotionLibrary::load(&path, &joints()).unwrap().names(), vec!["fresh2"]);
}

#[test]
fn motion_names_are_checked_naming_the_rule() {
    assert!(validate_name("rock 1 (left) – Grüße").is_ok());
    assert!(validate_name(&"x".repeat(MAX_NAME_BYTES)).is_ok());
    assert_eq!(validate_name(""), Err(NameError::Empty));
    assert_eq!(validate_name(" \t "), Err(NameError::Empty));
    assert_eq!(validate_name(" rock"), Err(NameError::OuterWhitespace));
    assert_eq!(validate_name(&"x".repeat(MAX_NAME_BYTES + 1)), Err(NameError::TooLong { bytes: 129 }));
    // 43 three-byte characters: 129 bytes.
    assert_eq!(validate_name(&"€".repeat(43)), Err(NameError::TooLong { bytes: 129 }));
    assert_eq!(validate_name("ab\ncd"), Err(NameError::Control { code: 0x0A, at: 2 }));
    assert_eq!(validate_name("a\u{7F}"), Err(NameError::Control { code: 0x7F, at: 1 }));
    assert_eq!(validate_name("a\u{85}"), Err(NameError::Control { code: 0x85, at: 1 }));
    for code in (0x202A..=0x202E).chain(0x2066..=0x2069) {
        let name = format!("step{}evil", char::from_u32(code).unwrap());
        assert_eq!(validate_name(&name), Err(NameError::Bidi { code, at: 4 }), "U+{code:04X}");
    }
    assert_eq!(validate_name("a\u{200B}b"), Err(NameError::Invisible { code: 0x200B, at: 1 }));
    assert_eq!(validate_name("\u{FEFF}a"), Err(NameError::Invisible { code: 0xFEFF, at: 0 }));
    let message = validate_name("step\u{202E}lave").unwrap_err().to_string();
    assert!(message.contains("U+202E") && message.contains("bidirectional") && message.starts_with("name "), "{message}");
    // The library applies the rules on insert and remove, and when loading a file.
    let mut library = MotionLibrary::new(Path::new("x.yaml"), joints());
    assert!(matches!(library.insert(motion("a\u{202E}b")), Err(LibraryError::InvalidName(NameError::Bidi { .. }))));
    assert!(matches!(library.remove(""), Err(LibraryError::InvalidName(NameError::Empty))));
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("motions.yaml");
    let mut library = MotionLibrary::new(&path, joints());
    library.insert(motion("rock1")).unwrap();
    std::fs::write(&path, library.to_yaml().unwrap().replace("name: rock1", "name: \"rock\\u202E1\"")).unwrap();
    let err = MotionLibrary::load(&path, &joints()).unwrap_err().to_string();
    assert!(err.contains("motions[0]") && err.contains("bidirectional"), "{err}");
}
