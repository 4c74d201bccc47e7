use super::*;

/// A page written byte by byte from the published layout (not by [`Page::to_bytes`]): name "sit
/// down", repeat 1, time based, 2 steps, speed 32, accel 32, next 0, exit 0, P gain 0x55, step 0 at
/// ID 7 = 2048 and ID 8 = 1800 (pause 10, time 100), step 1 at ID 7 = 2300 (pause 0, time 50), every
/// other slot 0x4000.
pub(crate) fn published_page() -> Vec<u8> {
    let mut b = vec![0u8; 512];
    b[..8].copy_from_slice(b"sit down");
    b[15] = 1; // repeat
    b[16] = 0x0a; // time based
    b[20] = 2; // steps
    b[22] = 32; // speed
    b[24] = 32; // accel
    b[32..63].fill(0x55);
    for step in 0..7 {
        let base = 64 + 64 * step;
        for slot in 0..31 {
            b[base + 2 * slot..base + 2 * slot + 2].copy_from_slice(&0x4000u16.to_le_bytes());
        }
    }
    let put = |b: &mut Vec<u8>, step: usize, id: usize, ticks: u16| {
        let at = 64 + 64 * step + 2 * id;
        b[at] = (ticks & 0xFF) as u8;
        b[at + 1] = (ticks >> 8) as u8;
    };
    put(&mut b, 0, 7, 2048);
    put(&mut b, 0, 8, 1800);
    b[64 + 62] = 10;
    b[64 + 63] = 100;
    put(&mut b, 1, 7, 2300);
    b[128 + 63] = 50;
    let sum: u32 = b.iter().map(|&x| u32::from(x)).sum();
    b[31] = (0xFF - (sum % 256)) as u8;
    b
}

#[test]
fn a_page_from_the_published_layout_parses_field_by_field() {
    let bytes = published_page();
    assert_eq!(bytes.iter().map(|&x| u32::from(x)).sum::<u32>() % 256, 0xFF);
    let page = parse_page(&bytes).unwrap();
    assert_eq!(page.name_text(), "sit down");
    assert_eq!((page.repeat, page.schedule, page.step_count, page.speed, page.accel), (1, TIME_BASE_SCHEDULE, 2, 32, 32));
    assert_eq!((page.next, page.exit), (0, 0));
    assert_eq!(page.pgain, [0x55; JOINT_SLOTS]);
    assert_eq!(page.played_steps().len(), 2);
    assert_eq!(page.steps[0].positions[7], 2048);
    assert_eq!(page.steps[0].positions[8], 1800);
    assert_eq!(page.steps[0].positions[9], INVALID_BIT);
    assert_eq!((page.steps[0].pause, page.steps[0].time), (10, 100));
    assert_eq!(page.steps[1].positions[7], 2300);
    assert_eq!((page.steps[1].pause, page.steps[1].time), (0, 50));
    assert_eq!(page.steps[2], Step::EMPTY);
}

#[test]
fn a_parsed_page_writes_back_byte_for_byte() {
    let bytes = published_page();
    assert_eq!(parse_page(&bytes).unwrap().to_bytes().as_slice(), bytes.as_slice());
    // Reserved bytes survive too (the checksum is recomputed over them).
    let mut odd = bytes.clone();
    odd[14] = 0x11;
    odd[19] = 0x22;
    odd[30] = 0x33;
    odd[63] = 0x44;
    odd[31] = odd[31].wrapping_sub(0x11 + 0x22 + 0x33 + 0x44);
    assert_eq!(parse_page(&odd).unwrap().to_bytes().as_slice(), odd.as_slice());
}

#[test]
fn the_empty_page_matches_the_tools_reset_page() {
    let bytes = Page::empty().to_bytes();
    assert_eq!(byte_sum(&bytes), 0xFF);
    assert_eq!((bytes[15], bytes[16], bytes[20], bytes[22], bytes[24]), (1, 0x0a, 0, 32, 32));
    assert!(bytes[32..63].iter().all(|&g| g == 0x55));
    assert_eq!(&bytes[64..66], &[0x00, 0x40]);
}

#[test]
fn a_bad_checksum_is_refused_with_the_sum() {
    let mut bytes = published_page();
    bytes[200] = bytes[200].wrapping_add(1);
    assert_eq!(parse_page(&bytes).unwrap_err(), PageError::Checksum { sum: 0x00 });
    assert!(parse_page(&bytes).unwrap_err().to_string().contains("0xFF"));
}

#[test]
fn a_wrong_length_is_refused() {
    assert_eq!(parse_page(&[]).unwrap_err(), PageError::Length(0));
    assert_eq!(parse_page(&[0u8; 513]).unwrap_err(), PageError::Length(513));
}

#[test]
fn more_than_seven_steps_is_refused() {
    let mut bytes = published_page();
    bytes[20] = 8;
    bytes[31] = bytes[31].wrapping_sub(6);
    assert_eq!(parse_page(&bytes).unwrap_err(), PageError::StepCount(8));
}

/// What a fuzz target does: arbitrary bytes (any length, random content, half of the 512-byte ones
/// with a valid checksum) give a page or an error, and every page parsed writes back as its input.
#[test]
fn arbitrary_bytes_parse_or_fail_without_panicking() {
    let mut state = 0x9E37_79B9_7F4A_7C15u64;
    let mut next = move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        state
    };
    let mut parsed = 0;
    for round in 0..4000 {
        let len = if round % 2 == 0 { PAGE_BYTES } else { (next() % 1100) as usize };
        let mut bytes: Vec<u8> = (0..len).map(|_| next() as u8).collect();
        if round % 4 == 0 {
            bytes[20] = (next() % 8) as u8;
            let sum = byte_sum(&bytes).wrapping_sub(bytes[31]);
            bytes[31] = 0xFFu8.wrapping_sub(sum);
        }
        match parse_page(&bytes) {
            Ok(page) => {
                parsed += 1;
                assert_eq!(page.to_bytes().as_slice(), bytes.as_slice());
            }
            Err(PageError::Length(n)) => assert_ne!(n, PAGE_BYTES),
            Err(PageError::Checksum { sum }) => assert_ne!(sum, 0xFF),
            Err(PageError::StepCount(n)) => assert!(n > 7),
        }
    }
    assert!(parsed >= 1000, "{parsed}");
}
