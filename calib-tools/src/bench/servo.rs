//! The host side of the servo bus: transactions (request, checked reply) with one Feetech servo
//! over any byte link, and opening a real serial port.

use std::io::{Read, Write};
use std::time::Duration;

use super::error::BenchError;
use super::protocol::{ADDR_PRESENT_POSITION, InstructionPacket, Series, StatusPacket, read_frame};

/// Default bus speed of STS servos (baud).
pub const DEFAULT_BAUD: u32 = 1_000_000;
/// Default reply timeout: a 8-byte reply takes 80 µs at 1 Mbaud plus the servo's return delay
/// (≤ 0.5 ms by default); 20 ms leaves room for USB adapters' latency timers.
pub const DEFAULT_TIMEOUT: Duration = Duration::from_millis(20);

/// A byte link to the bus that can also drop stale input before a request.
pub trait Bus: Read + Write {
    /// Drop bytes received but not read (a late reply of an earlier request).
    fn discard_input(&mut self) -> std::io::Result<()>;
}

impl Bus for Box<dyn serialport::SerialPort> {
    fn discard_input(&mut self) -> std::io::Result<()> {
        self.clear(serialport::ClearBuffer::Input)
            .map_err(std::io::Error::other)
    }
}

/// Open a serial port for the bus: 8N1, raw, the given baud and reply timeout.
pub fn open_port(
    port: &str,
    baud: u32,
    timeout: Duration,
) -> Result<Box<dyn serialport::SerialPort>, BenchError> {
    serialport::new(port, baud)
        .timeout(timeout)
        .data_bits(serialport::DataBits::Eight)
        .parity(serialport::Parity::None)
        .stop_bits(serialport::StopBits::One)
        .flow_control(serialport::FlowControl::None)
        .open()
        .map_err(|e| BenchError::Open {
            port: port.to_string(),
            detail: e.to_string(),
        })
}

/// One servo on a bus.
pub struct Servo<B: Bus> {
    bus: B,
    id: u8,
    series: Series,
}

impl<B: Bus> Servo<B> {
    /// A servo `id` of `series` on `bus`.
    pub fn new(bus: B, id: u8, series: Series) -> Self {
        Self { bus, id, series }
    }

    /// The servo id.
    pub fn id(&self) -> u8 {
        self.id
    }

    /// Give the bus back.
    pub fn into_bus(self) -> B {
        self.bus
    }

    fn send(&mut self, packet: &InstructionPacket) -> Result<(), BenchError> {
        let bytes = packet.encode()?;
        let lost = |e: std::io::Error| BenchError::Disconnected {
            detail: e.to_string(),
        };
        self.bus.discard_input().map_err(lost)?;
        self.bus.write_all(&bytes).map_err(lost)?;
        self.bus.flush().map_err(lost)
    }

    fn transact(
        &mut self,
        packet: &InstructionPacket,
        reply_params: usize,
    ) -> Result<StatusPacket, BenchError> {
        self.send(packet)?;
        let frame = read_frame(&mut self.bus)?;
        StatusPacket::from_frame(&frame, self.id, reply_params)
    }

    /// Ping: succeeds when the servo answers with a clean status packet.
    pub fn ping(&mut self) -> Result<(), BenchError> {
        self.transact(&InstructionPacket::ping(self.id), 0)
            .map(|_| ())
    }

    /// Read `len` bytes of the control table at `address`.
    pub fn read(&mut self, address: u8, len: u8) -> Result<Vec<u8>, BenchError> {
        self.transact(
            &InstructionPacket::read(self.id, address, len),
            usize::from(len),
        )
        .map(|s| s.params)
    }

    /// The present position in encoder counts (0‥4095 per turn).
    pub fn present_position(&mut self) -> Result<u16, BenchError> {
        let p = self.read(ADDR_PRESENT_POSITION, 2)?;
        Ok(self.series.decode_word([p[0], p[1]]) & POSITION_MASK)
    }

    /// Switch torque off so the jaw turns the horn freely.
    pub fn torque_off(&mut self) -> Result<(), BenchError> {
        self.transact(&InstructionPacket::torque_off(self.id), 0)
            .map(|_| ())
    }
}

/// Present position of several servos with one sync-read request; each servo answers in turn
/// and every reply is checked.
pub fn sync_read_positions<B: Bus>(
    bus: &mut B,
    ids: &[u8],
    series: Series,
) -> Result<Vec<u16>, BenchError> {
    let bytes = InstructionPacket::sync_read(ids, ADDR_PRESENT_POSITION, 2).encode()?;
    let lost = |e: std::io::Error| BenchError::Disconnected {
        detail: e.to_string(),
    };
    bus.discard_input().map_err(lost)?;
    bus.write_all(&bytes).map_err(lost)?;
    bus.flush().map_err(lost)?;
    ids.iter()
        .map(|&id| {
            let frame = read_frame(bus)?;
            let s = StatusPacket::from_frame(&frame, id, 2)?;
            Ok(series.decode_word([s.params[0], s.params[1]]) & POSITION_MASK)
        })
        .collect()
}

/// Bits of the position register that hold the count (bit 15 is the STS direction bit).
const POSITION_MASK: u16 = 0x7FFF;

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use std::io::{self, Cursor};

    use super::*;
    use crate::bench::protocol::{Frame, checksum};

    /// A bus whose replies are canned and whose requests are kept.
    struct Canned {
        sent: Vec<u8>,
        replies: Cursor<Vec<u8>>,
    }
    impl Read for Canned {
        fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
            match self.replies.read(buf)? {
                0 => Err(io::Error::new(io::ErrorKind::TimedOut, "timeout")),
                n => Ok(n),
            }
        }
    }
    impl Write for Canned {
        fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
            self.sent.extend_from_slice(buf);
            Ok(buf.len())
        }
        fn flush(&mut self) -> io::Result<()> {
            Ok(())
        }
    }
    impl Bus for Canned {
        fn discard_input(&mut self) -> io::Result<()> {
            Ok(())
        }
    }

    fn servo(replies: Vec<u8>) -> Servo<Canned> {
        Servo::new(
            Canned {
                sent: vec![],
                replies: Cursor::new(replies),
            },
            1,
            Series::Sts,
        )
    }

    fn reply(id: u8, error: u8, params: &[u8]) -> Vec<u8> {
        StatusPacket {
            id,
            error,
            params: params.to_vec(),
        }
        .encode()
        .unwrap()
    }

    #[test]
    fn reads_position_little_endian() {
        let mut s = servo(reply(1, 0, &[0xD2, 0x04]));
        assert_eq!(s.present_position().unwrap(), 1234);
        let sent = s.into_bus().sent;
        assert_eq!(sent, InstructionPacket::read(1, 56, 2).encode().unwrap());
    }

    #[test]
    fn ping_and_torque_off() {
        let mut replies = reply(1, 0, &[]);
        replies.extend(reply(1, 0, &[]));
        let mut s = servo(replies);
        s.ping().unwrap();
        s.torque_off().unwrap();
        let sent = s.into_bus().sent;
        assert_eq!(sent[4], 0x01);
        assert_eq!(
            &sent[6..],
            &InstructionPacket::torque_off(1).encode().unwrap()[..]
        );
    }

    #[test]
    fn malformed_replies_are_errors() {
        let mut bad = reply(1, 0, &[1, 2]);
        let n = bad.len();
        bad[n - 1] = bad[n - 1].wrapping_add(1);
        assert!(matches!(
            servo(bad).present_position(),
            Err(BenchError::BadChecksum { .. })
        ));
        assert!(matches!(
            servo(reply(2, 0, &[1, 2])).present_position(),
            Err(BenchError::WrongId { .. })
        ));
        assert!(matches!(
            servo(reply(1, 0, &[1])).present_position(),
            Err(BenchError::BadLength { .. })
        ));
        assert!(matches!(
            servo(reply(1, 0x08, &[1, 2])).present_position(),
            Err(BenchError::ServoError { bits: 0x08, .. })
        ));
        assert!(matches!(
            servo(vec![0x00, 0xFF, 1, 4]).present_position(),
            Err(BenchError::BadHeader { .. })
        ));
        assert!(matches!(
            servo(vec![]).present_position(),
            Err(BenchError::Timeout { received: 0 })
        ));
    }

    #[test]
    fn sync_read_checks_each_reply() {
        let mut replies = reply(1, 0, &[0x10, 0x00]);
        replies.extend(reply(2, 0, &[0x20, 0x00]));
        let mut bus = Canned {
            sent: vec![],
            replies: Cursor::new(replies),
        };
        assert_eq!(
            sync_read_positions(&mut bus, &[1, 2], Series::Sts).unwrap(),
            vec![16, 32]
        );
        let f = read_frame(&mut Cursor::new(bus.sent.clone())).unwrap();
        assert_eq!(
            f,
            Frame {
                id: 0xFE,
                code: 0x82,
                params: vec![56, 2, 1, 2]
            }
        );
        assert_eq!(
            bus.sent[bus.sent.len() - 1],
            checksum(&bus.sent[2..bus.sent.len() - 1])
        );
        // Out-of-order replies are caught.
        let mut swapped = reply(2, 0, &[0x20, 0x00]);
        swapped.extend(reply(1, 0, &[0x10, 0x00]));
        let mut bus = Canned {
            sent: vec![],
            replies: Cursor::new(swapped),
        };
        assert!(matches!(
            sync_read_positions(&mut bus, &[1, 2], Series::Sts),
            Err(BenchError::WrongId {
                expected: 1,
                found: 2
            })
        ));
    }
}
