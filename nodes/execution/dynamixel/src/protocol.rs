//! Dynamixel Protocol 2.0 framing, written from the ROBOTIS protocol description: packet layout
//! `FF FF FD 00 | ID | LEN_L LEN_H | INST | params… | CRC_L CRC_H` (LEN counts INST, params and CRC),
//! byte stuffing (`FF FF FD` in the body is followed by an extra `FD`), and CRC-16 (polynomial
//! 0x8005, initial value 0, no reflection) over everything before the CRC. Used by the simulated
//! servo chain (device side) and by tests that craft raw frames.

/// Packet header prefix.
pub const HEADER: [u8; 4] = [0xFF, 0xFF, 0xFD, 0x00];
/// Broadcast ID.
pub const BROADCAST_ID: u8 = 0xFE;
/// Largest packet the parser accepts (bytes, stuffed).
pub const MAX_PACKET: usize = 1024;

/// Instruction codes.
pub mod instruction {
    pub const PING: u8 = 0x01;
    pub const READ: u8 = 0x02;
    pub const WRITE: u8 = 0x03;
    pub const REG_WRITE: u8 = 0x04;
    pub const ACTION: u8 = 0x05;
    pub const FACTORY_RESET: u8 = 0x06;
    pub const REBOOT: u8 = 0x08;
    pub const CLEAR: u8 = 0x10;
    pub const STATUS: u8 = 0x55;
    pub const SYNC_READ: u8 = 0x82;
    pub const SYNC_WRITE: u8 = 0x83;
    pub const BULK_READ: u8 = 0x92;
    pub const BULK_WRITE: u8 = 0x93;
}

/// Status packet error numbers (lower 7 bits of the error byte; bit 7 is the hardware alert).
pub mod status_error {
    pub const RESULT_FAIL: u8 = 0x01;
    pub const INSTRUCTION: u8 = 0x02;
    pub const CRC: u8 = 0x03;
    pub const DATA_RANGE: u8 = 0x04;
    pub const DATA_LENGTH: u8 = 0x05;
    pub const DATA_LIMIT: u8 = 0x06;
    pub const ACCESS: u8 = 0x07;
    pub const ALERT: u8 = 0x80;
}

/// CRC-16 of Protocol 2.0 (poly 0x8005, init 0, MSB first).
pub fn crc16(data: &[u8]) -> u16 {
    let mut crc: u16 = 0;
    for &byte in data {
        crc ^= u16::from(byte) << 8;
        for _ in 0..8 {
            crc = if crc & 0x8000 != 0 { (crc << 1) ^ 0x8005 } else { crc << 1 };
        }
    }
    crc
}

/// Byte stuffing: after every `FF FF FD` insert `FD`.
pub fn stuff(body: &[u8]) -> Vec<u8> {
    let mut out = Vec::with_capacity(body.len() + 4);
    let mut run = 0usize;
    for &byte in body {
        out.push(byte);
        run = match (run, byte) {
            (0, 0xFF) | (1, 0xFF) => run + 1,
            (2, 0xFF) => 2,
            (2, 0xFD) => {
                out.push(0xFD);
                0
            }
            _ => 0,
        };
    }
    out
}

/// Undo byte stuffing: `FF FF FD FD` → `FF FF FD`.
pub fn unstuff(body: &[u8]) -> Vec<u8> {
    let mut out = Vec::with_capacity(body.len());
    // state = how much of the pattern FF FF FD (FD) the latest bytes match.
    let mut state = 0u8;
    for &byte in body {
        state = match (state, byte) {
            (3, 0xFD) => {
                state = 0;
                continue; // the stuffing byte
            }
            (0, 0xFF) | (3, 0xFF) => 1,
            (1, 0xFF) | (2, 0xFF) => 2,
            (2, 0xFD) => 3,
            _ => 0,
        };
        out.push(byte);
    }
    out
}

/// Encode a packet (instruction or status) with `body` = bytes after the instruction byte
/// (for status packets: error byte + data; only the data is stuffed, as the error byte precedes it).
pub fn encode(id: u8, instruction: u8, body: &[u8]) -> Vec<u8> {
    let stuffed = stuff(body);
    let length = (stuffed.len() + 3) as u16;
    let mut packet = Vec::with_capacity(10 + stuffed.len());
    packet.extend_from_slice(&HEADER);
    packet.push(id);
    packet.extend_from_slice(&length.to_le_bytes());
    packet.push(instruction);
    packet.extend_from_slice(&stuffed);
    let crc = crc16(&packet);
    packet.extend_from_slice(&crc.to_le_bytes());
    packet
}

/// Encode a status packet with an error byte and data.
pub fn encode_status(id: u8, error: u8, data: &[u8]) -> Vec<u8> {
    let mut body = Vec::with_capacity(data.len() + 1);
    body.push(error);
    body.extend_from_slice(data);
    encode(id, instruction::STATUS, &body)
}

/// A decoded packet.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Packet {
    pub id: u8,
    pub instruction: u8,
    /// Unstuffed parameters (for status packets: error byte first).
    pub params: Vec<u8>,
}

/// Framing problems found while parsing a stream.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum FrameError {
    #[error("packet for id {id}: CRC {received:#06x} != computed {computed:#06x}")]
    Crc { id: u8, received: u16, computed: u16 },
    #[error("packet for id {id}: invalid length {length}")]
    Length { id: u8, length: usize },
    #[error("packet for id {id}: re-encoding it does not give the same packet")]
    RoundTrip { id: u8 },
}

/// Incremental parser over a byte stream (skips garbage before a header).
#[derive(Debug, Default)]
pub struct PacketParser {
    buffer: Vec<u8>,
}

impl PacketParser {
    pub fn new() -> Self {
        Self::default()
    }

    /// Append received bytes.
    pub fn feed(&mut self, bytes: &[u8]) {
        self.buffer.extend_from_slice(bytes);
    }

    /// Bytes buffered but not yet consumed.
    pub fn pending(&self) -> usize {
        self.buffer.len()
    }

    /// Next complete packet, a framing error (the bad frame is consumed), or None if more bytes are needed.
    pub fn next_packet(&mut self) -> Option<Result<Packet, FrameError>> {
        let start = find_header(&self.buffer);
        self.buffer.drain(..start);
        if self.buffer.len() < 7 {
            return None;
        }
        let id = self.buffer[4];
        let length = usize::from(u16::from_le_bytes([self.buffer[5], self.buffer[6]]));
        if length < 3 || length + 7 > MAX_PACKET {
            // Not a real header: drop its first byte and resynchronise.
            self.buffer.drain(..1);
            return Some(Err(FrameError::Length { id, length }));
        }
        let total = 7 + length;
        if self.buffer.len() < total {
            return None;
        }
        let frame: Vec<u8> = self.buffer.drain(..total).collect();
        let received = u16::from_le_bytes([frame[total - 2], frame[total - 1]]);
        let computed = crc16(&frame[..total - 2]);
        if received != computed {
            return Some(Err(FrameError::Crc { id, received, computed }));
        }
        let instruction = frame[7];
        let raw = &frame[8..total - 2];
        let params = if instruction == instruction::STATUS && !raw.is_empty() {
            let mut params = vec![raw[0]];
            params.extend(unstuff(&raw[1..]));
            params
        } else {
            unstuff(raw)
        };
        Some(Ok(Packet { id, instruction, params }))
    }
}

/// What a master makes of a received byte stream: byte 0 sets the size of the chunks the rest is fed
/// in (1 + byte 0 % 64, as reads from a serial port split a stream anywhere), and every packet or
/// framing error the parser yields, in order. A parsed packet must survive re-encoding: encoding it
/// again and parsing that gives the same packet (a [`FrameError::RoundTrip`] otherwise).
pub fn parse_stream(bytes: &[u8]) -> Vec<Result<Packet, FrameError>> {
    let Some((&chunking, stream)) = bytes.split_first() else { return Vec::new() };
    let mut parser = PacketParser::new();
    let mut out = Vec::new();
    for chunk in stream.chunks(1 + usize::from(chunking % 64)) {
        parser.feed(chunk);
        while let Some(frame) = parser.next_packet() {
            out.push(frame.and_then(|packet| check_round_trip(&packet).map(|()| packet)));
        }
    }
    out
}

/// Encode `packet` as a device or master would and parse it back.
fn check_round_trip(packet: &Packet) -> Result<(), FrameError> {
    let bytes = match (packet.instruction, packet.params.split_first()) {
        (instruction::STATUS, Some((&error, data))) => encode_status(packet.id, error, data),
        _ => encode(packet.id, packet.instruction, &packet.params),
    };
    let mut parser = PacketParser::new();
    parser.feed(&bytes);
    match parser.next_packet() {
        Some(Ok(back)) if back == *packet => Ok(()),
        _ => Err(FrameError::RoundTrip { id: packet.id }),
    }
}

/// Position of the first (possibly partial, at the end) header prefix.
fn find_header(buffer: &[u8]) -> usize {
    (0..buffer.len())
        .find(|&i| {
            let n = HEADER.len().min(buffer.len() - i);
            buffer[i..i + n] == HEADER[..n]
        })
        .unwrap_or(buffer.len())
}

#[cfg(test)]
mod tests {
    use super::*;

    use patchwalk_test_support::stored_fuzz_inputs as stored_inputs;

    #[test]
    fn crc_of_manual_ping_example() {
        // Ping to ID 1: FF FF FD 00 01 03 00 01 | CRC 19 4E (e-Manual Protocol 2.0 example).
        let packet = encode(1, instruction::PING, &[]);
        assert_eq!(packet, vec![0xFF, 0xFF, 0xFD, 0x00, 0x01, 0x03, 0x00, 0x01, 0x19, 0x4E]);
        // Status from ID 1, model 1030 fw 38: ... 55 00 06 04 26 | 65 5D.
        let status = encode_status(1, 0, &[0x06, 0x04, 0x26]);
        assert_eq!(status, vec![0xFF, 0xFF, 0xFD, 0x00, 0x01, 0x07, 0x00, 0x55, 0x00, 0x06, 0x04, 0x26, 0x65, 0x5D]);
    }

    #[test]
    fn stuffing_round_trips() {
        let cases: Vec<Vec<u8>> = vec![
            vec![],
            vec![0xFF, 0xFF, 0xFD],
            vec![0xFF, 0xFF, 0xFD, 0xFD],
            vec![0xFF, 0xFF, 0xFF, 0xFD, 0x01],
            vec![1, 0xFF, 0xFF, 0xFD, 0xFF, 0xFF, 0xFD, 2],
        ];
        for body in cases {
            let stuffed = stuff(&body);
            assert_eq!(unstuff(&stuffed), body, "{body:02X?} -> {stuffed:02X?}");
        }
        assert_eq!(stuff(&[0xFF, 0xFF, 0xFD, 0x07]), vec![0xFF, 0xFF, 0xFD, 0xFD, 0x07]);
    }

    #[test]
    fn parser_skips_garbage_splits_and_reports_crc_errors() {
        let a = encode(3, instruction::WRITE, &[116, 0, 0xFF, 0xFF, 0xFD, 0x00]);
        let b = encode(4, instruction::PING, &[]);
        let mut bad = encode(5, instruction::PING, &[]);
        let last = bad.len() - 1;
        bad[last] ^= 0x55;
        let mut stream = vec![0x00, 0x12, 0xFF];
        stream.extend(&a);
        stream.extend(&bad);
        stream.extend(&b);
        let mut parser = PacketParser::new();
        let (first, rest) = stream.split_at(9);
        parser.feed(first);
        assert!(parser.next_packet().is_none());
        parser.feed(rest);
        let p = parser.next_packet().unwrap().unwrap();
        assert_eq!((p.id, p.instruction, p.params), (3, instruction::WRITE, vec![116, 0, 0xFF, 0xFF, 0xFD, 0x00]));
        assert!(matches!(parser.next_packet(), Some(Err(FrameError::Crc { id: 5, .. }))));
        assert_eq!(parser.next_packet().unwrap().unwrap().id, 4);
        assert!(parser.next_packet().is_none());
        assert_eq!(parser.pending(), 0);
    }

    #[test]
    fn parser_rejects_impossible_length() {
        let mut parser = PacketParser::new();
        parser.feed(&[0xFF, 0xFF, 0xFD, 0x00, 0x01, 0x01, 0x00, 0x01]);
        assert!(matches!(parser.next_packet(), Some(Err(FrameError::Length { .. }))));
        assert!(parser.next_packet().is_none());
    }

    #[test]
    fn streams_in_any_chunking_give_the_same_packets() {
        let mut stream = vec![0x42, 0xFF];
        stream.extend(encode_status(1, 0, &[0x06, 0x04, 0x26]));
        stream.extend(encode_status(2, status_error::ALERT, &[0xFF, 0xFF, 0xFD, 0x01]));
        let whole = parse_stream(&[&[63u8][..], &stream[1..]].concat());
        for chunking in 0..8u8 {
            assert_eq!(parse_stream(&[&[chunking][..], &stream[1..]].concat()), whole, "chunks of {}", chunking + 1);
        }
        let packets: Vec<Packet> = whole.into_iter().map(Result::unwrap).collect();
        assert_eq!(packets[1].params, vec![status_error::ALERT, 0xFF, 0xFF, 0xFD, 0x01]);
        assert!(parse_stream(&[]).is_empty());
    }

    #[test]
    fn stored_status_frame_inputs_are_parsed() {
        for (path, bytes) in stored_inputs("dynamixel_status_frames") {
            for frame in parse_stream(&bytes) {
                match frame {
                    Ok(packet) => assert!(packet.params.len() <= MAX_PACKET, "{}", path.display()),
                    Err(e) => assert!(!matches!(e, FrameError::RoundTrip { .. }), "{}: {e}", path.display()),
                }
            }
        }
    }
}
