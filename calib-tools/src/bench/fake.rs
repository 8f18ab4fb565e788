//! A simulated Feetech servo that speaks the protocol on a pseudo-terminal, so the bench can be
//! tried and tested without hardware. Its horn follows a known motion; faults (silence, a
//! corrupted checksum, a reply from the wrong id, an unplug/replug) are injected on chosen
//! requests. The pseudo-terminal's path changes on every replug, so the servo keeps a stable
//! symlink to it, as udev does for `/dev/serial/by-id/…`.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use serialport::{SerialPort, TTYPort};

use super::error::BenchError;
use super::protocol::{
    ADDR_MODEL, ADDR_PRESENT_POSITION, ADDR_TORQUE_ENABLE, BROADCAST_ID, COUNTS_PER_REV,
    Instruction, InstructionPacket, Series, StatusPacket, read_frame,
};

/// Model number the fake reports (the STS3215's).
const MODEL_STS3215: u16 = 777;
/// How long the servo thread waits for a request before checking whether to stop.
const POLL: Duration = Duration::from_millis(50);
/// Size of the Feetech control table.
const TABLE_LEN: usize = 256;

/// A fault injected on one request.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Fault {
    /// No reply at all.
    Silence,
    /// A reply with a corrupted checksum byte.
    CorruptChecksum,
    /// A well-formed reply that carries another servo's id.
    WrongId,
    /// The device disappears (its path vanishes) and comes back after the unplug time.
    Unplug,
}

impl Fault {
    /// Every fault kind, in the order `--fault-every` cycles through them.
    pub const ALL: [Self; 4] = [
        Self::Silence,
        Self::CorruptChecksum,
        Self::WrongId,
        Self::Unplug,
    ];
}

/// The horn's motion: `center + amplitude · sin(2π t / period)` in encoder counts.
#[derive(Debug, Clone, Copy)]
pub struct HornMotion {
    /// Mean position (counts).
    pub center: f64,
    /// Amplitude (counts).
    pub amplitude: f64,
    /// Period (s).
    pub period_s: f64,
}

impl Default for HornMotion {
    fn default() -> Self {
        Self {
            center: 1400.0,
            amplitude: 300.0,
            period_s: 2.0,
        }
    }
}

impl HornMotion {
    /// The encoder count `t` seconds after start.
    pub fn counts(&self, t: f64) -> u16 {
        let c = self.center + self.amplitude * (std::f64::consts::TAU * t / self.period_s).sin();
        c.round().clamp(0.0, f64::from(COUNTS_PER_REV - 1)) as u16
    }
}

/// Settings of a fake servo.
#[derive(Debug, Clone)]
pub struct FakeServoConfig {
    /// Servo id.
    pub id: u8,
    /// Register byte order.
    pub series: Series,
    /// Stable path (symlink) to the current pseudo-terminal.
    pub link: PathBuf,
    /// Horn motion.
    pub motion: HornMotion,
    /// Faults on given request numbers (0-based count of requests addressed to this servo).
    pub faults: Vec<(u64, Fault)>,
    /// Also inject a fault every this many requests (cycling through [`Fault::ALL`]); 0 = never.
    pub fault_every: u64,
    /// How long an unplug lasts.
    pub unplug: Duration,
}

impl FakeServoConfig {
    /// A servo `id` behind `link`, with no faults.
    pub fn new(id: u8, link: &Path) -> Self {
        Self {
            id,
            series: Series::Sts,
            link: link.to_path_buf(),
            motion: HornMotion::default(),
            faults: vec![],
            fault_every: 0,
            unplug: Duration::from_millis(300),
        }
    }

    fn fault_for(&self, request: u64) -> Option<Fault> {
        if let Some(&(_, f)) = self.faults.iter().find(|(k, _)| *k == request) {
            return Some(f);
        }
        if self.fault_every > 0 && request > 0 && request.is_multiple_of(self.fault_every) {
            let cycle = (request / self.fault_every - 1) % Fault::ALL.len() as u64;
            return Some(Fault::ALL[cycle as usize]);
        }
        None
    }
}

/// What the fake servo did.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct FakeStats {
    /// Requests addressed to this servo (or broadcast sync reads naming it).
    pub requests: u64,
    /// Clean replies sent.
    pub replies: u64,
    /// Requests left unanswered on purpose.
    pub silences: u64,
    /// Replies sent with a corrupted checksum.
    pub corrupted: u64,
    /// Replies sent with a wrong id.
    pub wrong_ids: u64,
    /// Unplug/replug cycles.
    pub unplugs: u64,
    /// Every position sent in a clean reply, in order.
    #[serde(skip)]
    pub served_positions: Vec<u16>,
}

/// A running fake servo (stopped and its link removed on drop).
pub struct FakeServo {
    stop: Arc<AtomicBool>,
    stats: Arc<Mutex<FakeStats>>,
    current: Arc<Mutex<String>>,
    thread: Option<JoinHandle<()>>,
    link: PathBuf,
}

/// One pseudo-terminal pair: the servo's end and the held-open device end (keeps the servo's
/// reads from failing while no client has the device open).
struct Pty {
    servo_end: TTYPort,
    _device_end: TTYPort,
    device_path: String,
}

fn open_pty(link: &Path) -> Result<Pty, BenchError> {
    let fail = |detail: String| BenchError::File {
        path: link.to_path_buf(),
        detail,
    };
    let (mut servo_end, device_end) =
        TTYPort::pair().map_err(|e| fail(format!("cannot create a pseudo-terminal: {e}")))?;
    servo_end
        .set_timeout(POLL)
        .map_err(|e| fail(format!("cannot set the pseudo-terminal timeout: {e}")))?;
    let device_path = device_end
        .name()
        .ok_or_else(|| fail("the pseudo-terminal has no device path".into()))?;
    let tmp = link.with_extension("kiwi-link-tmp");
    let _ = std::fs::remove_file(&tmp);
    std::os::unix::fs::symlink(&device_path, &tmp)
        .and_then(|()| std::fs::rename(&tmp, link))
        .map_err(|e| fail(format!("cannot point the link at {device_path}: {e}")))?;
    Ok(Pty {
        servo_end,
        _device_end: device_end,
        device_path,
    })
}

impl FakeServo {
    /// Create the pseudo-terminal, point the link at it and start answering.
    pub fn start(config: FakeServoConfig) -> Result<Self, BenchError> {
        if config.id > super::protocol::MAX_SERVO_ID {
            return Err(BenchError::Setting {
                name: "id",
                detail: format!("servo ids are 0..=253, got {}", config.id),
            });
        }
        let pty = open_pty(&config.link)?;
        let stop = Arc::new(AtomicBool::new(false));
        let stats = Arc::new(Mutex::new(FakeStats::default()));
        let current = Arc::new(Mutex::new(pty.device_path.clone()));
        let link = config.link.clone();
        let thread = {
            let (stop, stats, current) = (stop.clone(), stats.clone(), current.clone());
            std::thread::spawn(move || serve(&config, pty, &stop, &stats, &current))
        };
        Ok(Self {
            stop,
            stats,
            current,
            thread: Some(thread),
            link,
        })
    }

    /// The stable path clients open.
    pub fn link(&self) -> &Path {
        &self.link
    }

    /// The pseudo-terminal the link points at now.
    pub fn device_path(&self) -> String {
        self.current
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()
    }

    /// A snapshot of what the servo did so far.
    pub fn stats(&self) -> FakeStats {
        self.stats
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()
    }

    /// Whether the servo thread has ended (it ends only when stopped or on a fatal error).
    pub fn is_finished(&self) -> bool {
        self.thread.as_ref().is_none_or(JoinHandle::is_finished)
    }

    /// Stop answering, remove the link and return the final statistics.
    pub fn stop(mut self) -> FakeStats {
        self.shutdown();
        self.stats()
    }

    fn shutdown(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
        let _ = std::fs::remove_file(&self.link);
    }
}

impl Drop for FakeServo {
    fn drop(&mut self) {
        self.shutdown();
    }
}

fn serve(
    config: &FakeServoConfig,
    first: Pty,
    stop: &AtomicBool,
    stats: &Mutex<FakeStats>,
    current: &Mutex<String>,
) {
    let start = Instant::now();
    let mut table = [0u8; TABLE_LEN];
    let model = config.series.encode_word(MODEL_STS3215);
    table[usize::from(ADDR_MODEL)..usize::from(ADDR_MODEL) + 2].copy_from_slice(&model);
    table[5] = config.id;
    table[usize::from(ADDR_TORQUE_ENABLE)] = 1;
    let mut pty = Some(first);
    let mut request = 0u64;
    let stat = |f: &dyn Fn(&mut FakeStats)| {
        f(&mut stats.lock().unwrap_or_else(PoisonError::into_inner));
    };
    while !stop.load(Ordering::SeqCst) {
        let Some(p) = pty.as_mut() else {
            break;
        };
        let frame = match read_frame(&mut p.servo_end) {
            Ok(f) => f,
            Err(BenchError::Timeout { .. }) => continue,
            Err(BenchError::Disconnected { .. }) => {
                std::thread::sleep(POLL);
                continue;
            }
            Err(_) => {
                // Line noise: drop what is buffered and wait for the next request.
                let _ = p.servo_end.clear(serialport::ClearBuffer::Input);
                continue;
            }
        };
        let Ok(packet) = InstructionPacket::from_frame(&frame) else {
            continue;
        };
        let (addressed, reply_params) = match packet.instruction {
            Instruction::SyncRead => (
                packet.params.len() >= 2 && packet.params[2..].contains(&config.id),
                true,
            ),
            _ => (packet.id == config.id, packet.id != BROADCAST_ID),
        };
        if !addressed {
            continue;
        }
        let k = request;
        request += 1;
        stat(&|s| s.requests += 1);
        let t = start.elapsed().as_secs_f64();
        let pos = config.series.encode_word(config.motion.counts(t));
        let a = usize::from(ADDR_PRESENT_POSITION);
        table[a..a + 2].copy_from_slice(&pos);
        let Some(params) = apply(&mut table, &packet) else {
            continue;
        };
        if !reply_params {
            continue;
        }
        let reads_position = matches!(
            packet.instruction,
            Instruction::Read | Instruction::SyncRead
        ) && packet.params.first() == Some(&ADDR_PRESENT_POSITION)
            && params.len() == 2;
        let mut reply = StatusPacket {
            id: config.id,
            error: 0,
            params,
        };
        match config.fault_for(k) {
            Some(Fault::Silence) => {
                stat(&|s| s.silences += 1);
                continue;
            }
            Some(Fault::Unplug) => {
                stat(&|s| s.unplugs += 1);
                pty = None;
                let _ = std::fs::remove_file(&config.link);
                let until = Instant::now() + config.unplug;
                while Instant::now() < until && !stop.load(Ordering::SeqCst) {
                    std::thread::sleep(Duration::from_millis(10));
                }
                match open_pty(&config.link) {
                    Ok(p) => {
                        *current.lock().unwrap_or_else(PoisonError::into_inner) =
                            p.device_path.clone();
                        pty = Some(p);
                    }
                    Err(e) => tracing::error!("fake servo cannot replug: {e}"),
                }
                continue;
            }
            Some(Fault::WrongId) => {
                reply.id = if config.id == 0 { 1 } else { config.id - 1 };
                stat(&|s| s.wrong_ids += 1);
            }
            Some(Fault::CorruptChecksum) | None => {}
        }
        let Ok(mut bytes) = reply.encode() else {
            continue;
        };
        if config.fault_for(k) == Some(Fault::CorruptChecksum) {
            let n = bytes.len();
            bytes[n - 1] ^= 0x5A;
            stat(&|s| s.corrupted += 1);
        }
        let Some(p) = pty.as_mut() else {
            break;
        };
        if std::io::Write::write_all(&mut p.servo_end, &bytes).is_err() {
            continue;
        }
        if config.fault_for(k).is_none() {
            stat(&|s| {
                s.replies += 1;
                if reads_position {
                    s.served_positions.push(
                        config
                            .series
                            .decode_word([reply.params[0], reply.params[1]]),
                    );
                }
            });
        }
    }
    let _ = std::fs::remove_file(&config.link);
}

/// Apply a request to the control table; the reply's parameters, or `None` for a request a
/// servo ignores (out-of-range address, malformed parameters).
fn apply(table: &mut [u8; TABLE_LEN], packet: &InstructionPacket) -> Option<Vec<u8>> {
    match packet.instruction {
        Instruction::Ping | Instruction::Action | Instruction::Reset => Some(vec![]),
        Instruction::Read | Instruction::SyncRead => {
            let (&addr, &len) = (packet.params.first()?, packet.params.get(1)?);
            let (a, n) = (usize::from(addr), usize::from(len));
            (a + n <= TABLE_LEN).then(|| table[a..a + n].to_vec())
        }
        Instruction::Write | Instruction::RegWrite => {
            let (&addr, data) = packet.params.split_first()?;
            let a = usize::from(addr);
            if a + data.len() > TABLE_LEN {
                return None;
            }
            table[a..a + data.len()].copy_from_slice(data);
            Some(vec![])
        }
        Instruction::SyncWrite => None,
    }
}
