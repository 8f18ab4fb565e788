//! Feetech STS/SCS serial-bus servo protocol: packet framing, instruction packets and the
//! checked parsing of status replies.
//!
//! Every packet is `0xFF 0xFF id length instruction|error params… checksum`, where `length`
//! counts the bytes after itself (instruction or error byte, parameters, checksum) and
//! `checksum = !(id + length + instruction|error + Σ params) & 0xFF`.

use std::io::{self, Read};

use super::error::BenchError;

/// The two bytes every packet starts with.
pub const HEADER: [u8; 2] = [0xFF, 0xFF];
/// The id every servo on the bus listens to (no reply except to sync read).
pub const BROADCAST_ID: u8 = 0xFE;
/// Highest id a servo can have (0xFE is broadcast, 0xFF would read as a header byte).
pub const MAX_SERVO_ID: u8 = 0xFD;
/// Control-table address of the torque switch (1 byte: 0 off, 1 on).
pub const ADDR_TORQUE_ENABLE: u8 = 40;
/// Control-table address of the present position (2 bytes).
pub const ADDR_PRESENT_POSITION: u8 = 56;
/// Control-table address of the model number (2 bytes).
pub const ADDR_MODEL: u8 = 3;
/// Encoder counts per revolution of the STS magnetic encoder (12 bit).
pub const COUNTS_PER_REV: u16 = 4096;
/// Shortest `length` byte: error/instruction byte plus checksum.
const MIN_LENGTH: u8 = 2;

/// An instruction the host sends.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Instruction {
    /// Ask the servo to answer with an empty status packet.
    Ping,
    /// Read `len` bytes from an address: params `[address, len]`.
    Read,
    /// Write bytes at an address: params `[address, data…]`.
    Write,
    /// Buffered write, applied on `Action`.
    RegWrite,
    /// Apply buffered writes.
    Action,
    /// Factory reset.
    Reset,
    /// Read the same address of several servos: params `[address, len, id…]`.
    SyncRead,
    /// Write the same address of several servos.
    SyncWrite,
}

impl Instruction {
    /// The instruction's byte on the wire.
    pub fn code(self) -> u8 {
        match self {
            Self::Ping => 0x01,
            Self::Read => 0x02,
            Self::Write => 0x03,
            Self::RegWrite => 0x04,
            Self::Action => 0x05,
            Self::Reset => 0x06,
            Self::SyncRead => 0x82,
            Self::SyncWrite => 0x83,
        }
    }

    /// The instruction for a byte, if it is one.
    pub fn from_code(code: u8) -> Option<Self> {
        Some(match code {
            0x01 => Self::Ping,
            0x02 => Self::Read,
            0x03 => Self::Write,
            0x04 => Self::RegWrite,
            0x05 => Self::Action,
            0x06 => Self::Reset,
            0x82 => Self::SyncRead,
            0x83 => Self::SyncWrite,
            _ => return None,
        })
    }
}

/// Byte order of 2-byte registers: STS (e.g. STS3215) is little-endian, SCS big-endian.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Series {
    /// STS series: low byte first.
    #[default]
    Sts,
    /// SCS series: high byte first.
    Scs,
}

impl Series {
    /// A 2-byte register value from its bytes in wire order.
    pub fn decode_word(self, bytes: [u8; 2]) -> u16 {
        match self {
            Self::Sts => u16::from_le_bytes(bytes),
            Self::Scs => u16::from_be_bytes(bytes),
        }
    }

    /// The wire bytes of a 2-byte register value.
    pub fn encode_word(self, value: u16) -> [u8; 2] {
        match self {
            Self::Sts => value.to_le_bytes(),
            Self::Scs => value.to_be_bytes(),
        }
    }
}

/// `!(Σ bytes) & 0xFF` over id, length, instruction/error and parameters.
pub fn checksum(body: &[u8]) -> u8 {
    !body.iter().fold(0u8, |sum, &b| sum.wrapping_add(b))
}

/// Frame `id, instruction-or-error, params` into a packet with header, length and checksum.
fn frame(id: u8, code: u8, params: &[u8]) -> Result<Vec<u8>, BenchError> {
    let length = u8::try_from(params.len() + usize::from(MIN_LENGTH)).map_err(|_| {
        BenchError::PacketTooLong {
            params: params.len(),
        }
    })?;
    let mut out = Vec::with_capacity(params.len() + 6);
    out.extend_from_slice(&HEADER);
    out.extend_from_slice(&[id, length, code]);
    out.extend_from_slice(params);
    out.push(checksum(&out[2..]));
    Ok(out)
}

/// A packet from the host to one servo (or to all, with [`BROADCAST_ID`]).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct InstructionPacket {
    /// Target servo id.
    pub id: u8,
    /// What to do.
    pub instruction: Instruction,
    /// Instruction parameters.
    pub params: Vec<u8>,
}

impl InstructionPacket {
    /// Ping a servo.
    pub fn ping(id: u8) -> Self {
        Self {
            id,
            instruction: Instruction::Ping,
            params: vec![],
        }
    }

    /// Read `len` bytes of a servo's control table from `address`.
    pub fn read(id: u8, address: u8, len: u8) -> Self {
        Self {
            id,
            instruction: Instruction::Read,
            params: vec![address, len],
        }
    }

    /// Write `data` into a servo's control table at `address`.
    pub fn write(id: u8, address: u8, data: &[u8]) -> Self {
        let mut params = Vec::with_capacity(data.len() + 1);
        params.push(address);
        params.extend_from_slice(data);
        Self {
            id,
            instruction: Instruction::Write,
            params,
        }
    }

    /// Switch a servo's torque off so its horn turns freely (the jaw drives it).
    pub fn torque_off(id: u8) -> Self {
        Self::write(id, ADDR_TORQUE_ENABLE, &[0])
    }

    /// Read `len` bytes from `address` of every servo in `ids`; each answers in turn.
    pub fn sync_read(ids: &[u8], address: u8, len: u8) -> Self {
        let mut params = Vec::with_capacity(ids.len() + 2);
        params.extend_from_slice(&[address, len]);
        params.extend_from_slice(ids);
        Self {
            id: BROADCAST_ID,
            instruction: Instruction::SyncRead,
            params,
        }
    }

    /// The packet's bytes on the wire.
    pub fn encode(&self) -> Result<Vec<u8>, BenchError> {
        frame(self.id, self.instruction.code(), &self.params)
    }

    /// An instruction packet from a checked frame (the servo side of the bus).
    pub fn from_frame(frame: &Frame) -> Result<Self, BenchError> {
        let instruction =
            Instruction::from_code(frame.code).ok_or(BenchError::UnknownInstruction {
                id: frame.id,
                code: frame.code,
            })?;
        Ok(Self {
            id: frame.id,
            instruction,
            params: frame.params.clone(),
        })
    }
}

/// A servo's reply: its id, the error bits and the data read.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct StatusPacket {
    /// Replying servo id.
    pub id: u8,
    /// Error bits (0 = no error; see [`ServoFault`]).
    pub error: u8,
    /// Data read (empty for ping and write).
    pub params: Vec<u8>,
}

impl StatusPacket {
    /// The packet's bytes on the wire.
    pub fn encode(&self) -> Result<Vec<u8>, BenchError> {
        frame(self.id, self.error, &self.params)
    }

    /// Check a frame as the reply from servo `expected_id` carrying `expected_params` bytes:
    /// id first, then length, then the error byte.
    pub fn from_frame(
        frame: &Frame,
        expected_id: u8,
        expected_params: usize,
    ) -> Result<Self, BenchError> {
        if frame.id != expected_id {
            return Err(BenchError::WrongId {
                expected: expected_id,
                found: frame.id,
            });
        }
        if frame.params.len() != expected_params {
            return Err(BenchError::BadLength {
                id: frame.id,
                expected: expected_params + usize::from(MIN_LENGTH),
                found: frame.params.len() + usize::from(MIN_LENGTH),
            });
        }
        if frame.code != 0 {
            return Err(BenchError::ServoError {
                id: frame.id,
                bits: frame.code,
                faults: ServoFault::describe(frame.code),
            });
        }
        Ok(Self {
            id: frame.id,
            error: frame.code,
            params: frame.params.clone(),
        })
    }
}

/// The error bits of a status packet (Feetech STS/SCS).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ServoFault {
    /// Bit 0: input voltage out of range.
    Voltage,
    /// Bit 1: magnetic encoder (angle sensor) fault.
    Sensor,
    /// Bit 2: over temperature.
    Temperature,
    /// Bit 3: over current.
    Current,
    /// Bit 5: overload.
    Overload,
}

impl ServoFault {
    const ALL: [(u8, Self, &'static str); 5] = [
        (0x01, Self::Voltage, "voltage"),
        (0x02, Self::Sensor, "angle sensor"),
        (0x04, Self::Temperature, "overheat"),
        (0x08, Self::Current, "overcurrent"),
        (0x20, Self::Overload, "overload"),
    ];

    /// The faults set in an error byte.
    pub fn decode(bits: u8) -> Vec<Self> {
        Self::ALL
            .iter()
            .filter(|(mask, _, _)| bits & mask != 0)
            .map(|&(_, f, _)| f)
            .collect()
    }

    /// A readable list of the faults in an error byte.
    pub fn describe(bits: u8) -> String {
        let names: Vec<&str> = Self::ALL
            .iter()
            .filter(|(mask, _, _)| bits & mask != 0)
            .map(|&(_, _, name)| name)
            .collect();
        if names.is_empty() {
            format!("unknown error bits 0x{bits:02X}")
        } else {
            names.join(", ")
        }
    }
}

/// One framed packet with a verified checksum: `code` is the instruction (host to servo) or
/// the error byte (servo to host).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Frame {
    /// Id byte.
    pub id: u8,
    /// Instruction or error byte.
    pub code: u8,
    /// Parameters.
    pub params: Vec<u8>,
}

/// Read one packet from a byte stream and verify its header and checksum.
///
/// A read that times out is [`BenchError::Timeout`] (with how many bytes had arrived); any
/// other I/O failure is [`BenchError::Disconnected`].
pub fn read_frame<R: Read + ?Sized>(r: &mut R) -> Result<Frame, BenchError> {
    let mut got = 0usize;
    let mut head = [0u8; 4];
    read_exact(r, &mut head, &mut got)?;
    if head[..2] != HEADER {
        return Err(BenchError::BadHeader {
            found: [head[0], head[1]],
        });
    }
    let (id, length) = (head[2], head[3]);
    if length < MIN_LENGTH {
        return Err(BenchError::BadLength {
            id,
            expected: usize::from(MIN_LENGTH),
            found: usize::from(length),
        });
    }
    let mut body = vec![0u8; usize::from(length)];
    read_exact(r, &mut body, &mut got)?;
    let n = body.len();
    let sent = body[n - 1];
    let mut sum = vec![id, length];
    sum.extend_from_slice(&body[..n - 1]);
    let computed = checksum(&sum);
    if computed != sent {
        return Err(BenchError::BadChecksum {
            id,
            expected: computed,
            found: sent,
        });
    }
    Ok(Frame {
        id,
        code: body[0],
        params: body[1..n - 1].to_vec(),
    })
}

/// `read_exact` that tells a timeout (with the byte count so far) from a lost device.
fn read_exact<R: Read + ?Sized>(
    r: &mut R,
    buf: &mut [u8],
    got: &mut usize,
) -> Result<(), BenchError> {
    let mut filled = 0;
    while filled < buf.len() {
        match r.read(&mut buf[filled..]) {
            Ok(0) => {
                return Err(BenchError::Disconnected {
                    detail: "the port reached end of file".into(),
                });
            }
            Ok(n) => {
                filled += n;
                *got += n;
            }
            Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
            Err(e) if is_timeout(&e) => return Err(BenchError::Timeout { received: *got }),
            Err(e) => {
                return Err(BenchError::Disconnected {
                    detail: e.to_string(),
                });
            }
        }
    }
    Ok(())
}

/// Whether an I/O error is a read timeout rather than a lost device.
pub fn is_timeout(e: &io::Error) -> bool {
    matches!(
        e.kind(),
        io::ErrorKind::TimedOut | io::ErrorKind::WouldBlock
    )
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn parse(bytes: &[u8]) -> Result<Frame, BenchError> {
        read_frame(&mut io::Cursor::new(bytes.to_vec()))
    }

    #[test]
    fn ping_packet_matches_the_datasheet() {
        // Feetech manual example: ping id 1 → FF FF 01 02 01 FB.
        assert_eq!(
            InstructionPacket::ping(1).encode().unwrap(),
            vec![0xFF, 0xFF, 0x01, 0x02, 0x01, 0xFB]
        );
    }

    #[test]
    fn read_position_packet() {
        // FF FF 01 04 02 38 02 BE: read 2 bytes at 56 from id 1.
        assert_eq!(
            InstructionPacket::read(1, ADDR_PRESENT_POSITION, 2)
                .encode()
                .unwrap(),
            vec![0xFF, 0xFF, 0x01, 0x04, 0x02, 0x38, 0x02, 0xBE]
        );
    }

    #[test]
    fn torque_off_packet() {
        // FF FF 01 04 03 28 00 CF: write 0 at 40 on id 1.
        assert_eq!(
            InstructionPacket::torque_off(1).encode().unwrap(),
            vec![0xFF, 0xFF, 0x01, 0x04, 0x03, 0x28, 0x00, 0xCF]
        );
    }

    #[test]
    fn sync_read_packet() {
        let p = InstructionPacket::sync_read(&[1, 2], ADDR_PRESENT_POSITION, 2)
            .encode()
            .unwrap();
        assert_eq!(&p[..7], &[0xFF, 0xFF, 0xFE, 0x06, 0x82, 0x38, 0x02]);
        assert_eq!(&p[7..9], &[1, 2]);
        assert_eq!(p[9], checksum(&p[2..9]));
    }

    #[test]
    fn every_instruction_round_trips() {
        let all = [
            Instruction::Ping,
            Instruction::Read,
            Instruction::Write,
            Instruction::RegWrite,
            Instruction::Action,
            Instruction::Reset,
            Instruction::SyncRead,
            Instruction::SyncWrite,
        ];
        for ins in all {
            assert_eq!(Instruction::from_code(ins.code()), Some(ins));
            let p = InstructionPacket {
                id: 3,
                instruction: ins,
                params: vec![7, 8, 9],
            };
            let f = parse(&p.encode().unwrap()).unwrap();
            assert_eq!(InstructionPacket::from_frame(&f).unwrap(), p);
        }
        assert!(Instruction::from_code(0x42).is_none());
        let f = Frame {
            id: 1,
            code: 0x42,
            params: vec![],
        };
        assert!(matches!(
            InstructionPacket::from_frame(&f),
            Err(BenchError::UnknownInstruction { code: 0x42, .. })
        ));
    }

    #[test]
    fn status_reply_round_trips_and_decodes_position() {
        let reply = StatusPacket {
            id: 1,
            error: 0,
            params: Series::Sts.encode_word(3000).to_vec(),
        };
        let bytes = reply.encode().unwrap();
        assert_eq!(&bytes[..5], &[0xFF, 0xFF, 0x01, 0x04, 0x00]);
        let f = parse(&bytes).unwrap();
        let s = StatusPacket::from_frame(&f, 1, 2).unwrap();
        assert_eq!(Series::Sts.decode_word([s.params[0], s.params[1]]), 3000);
        assert_eq!(Series::Scs.encode_word(0x0102), [0x01, 0x02]);
        assert_eq!(Series::Sts.encode_word(0x0102), [0x02, 0x01]);
        assert_eq!(Series::Scs.decode_word([0x01, 0x02]), 0x0102);
    }

    #[test]
    fn ping_reply_has_no_params() {
        let bytes = [0xFF, 0xFF, 0x01, 0x02, 0x00, 0xFC];
        let s = StatusPacket::from_frame(&parse(&bytes).unwrap(), 1, 0).unwrap();
        assert!(s.params.is_empty());
    }

    #[test]
    fn bad_header_is_rejected() {
        let mut bytes = StatusPacket {
            id: 1,
            error: 0,
            params: vec![],
        }
        .encode()
        .unwrap();
        bytes[1] = 0xFE;
        assert!(matches!(
            parse(&bytes),
            Err(BenchError::BadHeader {
                found: [0xFF, 0xFE]
            })
        ));
    }

    #[test]
    fn bad_checksum_is_rejected() {
        let mut bytes = StatusPacket {
            id: 1,
            error: 0,
            params: vec![0x10, 0x02],
        }
        .encode()
        .unwrap();
        let n = bytes.len();
        bytes[n - 1] ^= 0x5A;
        assert!(matches!(
            parse(&bytes),
            Err(BenchError::BadChecksum { id: 1, .. })
        ));
        // A flipped data bit is caught too.
        let mut bytes2 = StatusPacket {
            id: 1,
            error: 0,
            params: vec![0x10, 0x02],
        }
        .encode()
        .unwrap();
        bytes2[5] ^= 0x01;
        assert!(matches!(
            parse(&bytes2),
            Err(BenchError::BadChecksum { .. })
        ));
    }

    #[test]
    fn wrong_id_is_rejected() {
        let bytes = StatusPacket {
            id: 2,
            error: 0,
            params: vec![0, 0],
        }
        .encode()
        .unwrap();
        let f = parse(&bytes).unwrap();
        assert!(matches!(
            StatusPacket::from_frame(&f, 1, 2),
            Err(BenchError::WrongId {
                expected: 1,
                found: 2
            })
        ));
    }

    #[test]
    fn wrong_length_is_rejected() {
        // A 3-byte reply where 2 bytes were asked for.
        let bytes = StatusPacket {
            id: 1,
            error: 0,
            params: vec![0, 0, 0],
        }
        .encode()
        .unwrap();
        let f = parse(&bytes).unwrap();
        assert!(matches!(
            StatusPacket::from_frame(&f, 1, 2),
            Err(BenchError::BadLength {
                expected: 4,
                found: 5,
                ..
            })
        ));
        // A length byte below the minimum.
        let mut short = vec![0xFF, 0xFF, 0x01, 0x01];
        short.push(checksum(&short[2..]));
        assert!(matches!(
            parse(&short),
            Err(BenchError::BadLength { found: 1, .. })
        ));
    }

    #[test]
    fn error_byte_is_reported_by_name() {
        let bytes = StatusPacket {
            id: 1,
            error: 0x24,
            params: vec![0, 0],
        }
        .encode()
        .unwrap();
        let f = parse(&bytes).unwrap();
        match StatusPacket::from_frame(&f, 1, 2) {
            Err(BenchError::ServoError { bits, faults, .. }) => {
                assert_eq!(bits, 0x24);
                assert_eq!(faults, "overheat, overload");
            }
            other => panic!("expected a servo error, got {other:?}"),
        }
        assert_eq!(
            ServoFault::decode(0x24),
            vec![ServoFault::Temperature, ServoFault::Overload]
        );
    }

    #[test]
    fn truncated_reply_is_a_timeout_with_the_byte_count() {
        let bytes = [0xFF, 0xFF, 0x01, 0x04, 0x00];
        struct Slow(io::Cursor<Vec<u8>>);
        impl Read for Slow {
            fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
                match self.0.read(buf)? {
                    0 => Err(io::Error::new(io::ErrorKind::TimedOut, "timeout")),
                    n => Ok(n),
                }
            }
        }
        let mut r = Slow(io::Cursor::new(bytes.to_vec()));
        assert!(matches!(
            read_frame(&mut r),
            Err(BenchError::Timeout { received: 5 })
        ));
        // Silence: nothing at all.
        let mut r = Slow(io::Cursor::new(vec![]));
        assert!(matches!(
            read_frame(&mut r),
            Err(BenchError::Timeout { received: 0 })
        ));
    }

    #[test]
    fn lost_device_is_a_disconnect() {
        struct Gone;
        impl Read for Gone {
            fn read(&mut self, _: &mut [u8]) -> io::Result<usize> {
                Err(io::Error::new(io::ErrorKind::BrokenPipe, "EPIPE"))
            }
        }
        assert!(matches!(
            read_frame(&mut Gone),
            Err(BenchError::Disconnected { .. })
        ));
        let mut eof = io::Cursor::new(vec![0xFF]);
        assert!(matches!(
            read_frame(&mut eof),
            Err(BenchError::Disconnected { .. })
        ));
    }

    #[test]
    fn oversized_packet_is_refused() {
        let p = InstructionPacket::write(1, 0, &[0u8; 300]);
        assert!(matches!(
            p.encode(),
            Err(BenchError::PacketTooLong { params: 301 })
        ));
    }
}
