//! Errors of the servo bench: one variant per way a bus transaction can fail, so the recorder
//! can count each kind.

/// A failed servo-bus transaction or bench input.
#[derive(Debug, thiserror::Error)]
pub enum BenchError {
    /// No complete reply before the timeout.
    #[error(
        "servo reply timed out after {received} byte(s): check the id, baud rate, wiring and power"
    )]
    Timeout {
        /// Bytes of the reply that had arrived.
        received: usize,
    },
    /// The reply did not start with 0xFF 0xFF.
    #[error(
        "expected packet header FF FF, found {:02X} {:02X}: wrong baud rate or line noise",
        found[0],
        found[1]
    )]
    BadHeader {
        /// The two bytes found instead.
        found: [u8; 2],
    },
    /// The checksum byte does not match the packet.
    #[error(
        "servo {id}: checksum expected 0x{expected:02X}, found 0x{found:02X} (corrupted reply)"
    )]
    BadChecksum {
        /// Id byte of the packet.
        id: u8,
        /// Checksum computed over the packet.
        expected: u8,
        /// Checksum byte received.
        found: u8,
    },
    /// A reply came from another servo.
    #[error(
        "expected a reply from servo {expected}, got one from servo {found}: two servos share an id?"
    )]
    WrongId {
        /// The id asked.
        expected: u8,
        /// The id that answered.
        found: u8,
    },
    /// The length byte does not fit the request.
    #[error("servo {id}: packet length expected {expected}, found {found}")]
    BadLength {
        /// Id byte of the packet.
        id: u8,
        /// Expected length byte.
        expected: usize,
        /// Length byte found.
        found: usize,
    },
    /// The servo set error bits in its reply.
    #[error("servo {id} reports an error (0x{bits:02X}: {faults}): check its power and load")]
    ServoError {
        /// Replying servo.
        id: u8,
        /// The error byte.
        bits: u8,
        /// The faults, by name.
        faults: String,
    },
    /// An instruction byte the protocol does not define.
    #[error("packet for id {id} has unknown instruction 0x{code:02X}")]
    UnknownInstruction {
        /// Id byte of the packet.
        id: u8,
        /// The instruction byte.
        code: u8,
    },
    /// More parameters than a length byte can count.
    #[error("packet with {params} parameter bytes does not fit a length byte (at most 253)")]
    PacketTooLong {
        /// Parameter bytes asked for.
        params: usize,
    },
    /// The serial device went away or failed.
    #[error("serial device lost: {detail}")]
    Disconnected {
        /// What the OS said.
        detail: String,
    },
    /// The serial port could not be opened or configured.
    #[error(
        "{port}: cannot open the serial port ({detail}); check the path, permissions (dialout group) and that nothing else holds it"
    )]
    Open {
        /// The port path.
        port: String,
        /// What the OS said.
        detail: String,
    },
    /// A file of the bench could not be read or written.
    #[error("{path}: {detail}")]
    File {
        /// The file.
        path: std::path::PathBuf,
        /// What went wrong and the fix.
        detail: String,
    },
    /// A setting is out of range.
    #[error("{name}: {detail}")]
    Setting {
        /// The option.
        name: &'static str,
        /// What is allowed.
        detail: String,
    },
}

impl BenchError {
    /// A short name of the error kind, for fault counts.
    pub fn kind(&self) -> &'static str {
        match self {
            Self::Timeout { .. } => "timeout",
            Self::BadHeader { .. } => "bad_header",
            Self::BadChecksum { .. } => "bad_checksum",
            Self::WrongId { .. } => "wrong_id",
            Self::BadLength { .. } => "bad_length",
            Self::ServoError { .. } => "servo_error",
            Self::UnknownInstruction { .. } => "unknown_instruction",
            Self::PacketTooLong { .. } => "packet_too_long",
            Self::Disconnected { .. } => "disconnected",
            Self::Open { .. } => "open",
            Self::File { .. } => "file",
            Self::Setting { .. } => "setting",
        }
    }
}
