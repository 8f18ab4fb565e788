//! The bench recorder: poll one servo's present position at a steady rate and stream
//! `t,raw,angle_rad` rows to disk with host timestamps, surviving timeouts, corrupted replies
//! and the device disappearing and returning.

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use serde::Serialize;

use super::error::BenchError;
use super::protocol::{COUNTS_PER_REV, MAX_SERVO_ID, Series};
use super::servo::{DEFAULT_BAUD, DEFAULT_TIMEOUT, Servo, open_port};

/// File name of the encoder log inside the output folder.
pub const ENCODER_CSV: &str = "encoder.csv";
/// File name of the recording report inside the output folder.
pub const REPORT_JSON: &str = "encoder_report.json";
/// Pause between attempts to reopen a vanished device (s): short, so a replug loses little.
const REOPEN_PAUSE: Duration = Duration::from_millis(20);
/// A recording whose servo has not answered once within this long fails (a wrong port or id)
/// instead of writing an empty log; a device plugged in just after the start is still waited for.
const STARTUP_GRACE: Duration = Duration::from_secs(3);
/// A period whose sample is this many periods late is skipped instead of taken late: a retry
/// after a timeout may run into the next period, a lost device makes the recorder fall behind.
const CATCH_UP_PERIODS: f64 = 5.0;
/// How often the log is forced to the disk (not just the OS cache).
const SYNC_EVERY: Duration = Duration::from_secs(1);

/// Settings of a recording.
#[derive(Debug, Clone)]
pub struct RecordConfig {
    /// Serial port path (e.g. `/dev/ttyUSB0` or a `/dev/serial/by-id/…` link).
    pub port: String,
    /// Servo id.
    pub id: u8,
    /// Baud rate.
    pub baud: u32,
    /// Register byte order.
    pub series: Series,
    /// Polling rate (Hz).
    pub rate_hz: f64,
    /// Length of the recording (s).
    pub duration_s: f64,
    /// Reply timeout.
    pub timeout: Duration,
    /// Encoder count written as angle 0 (the horn's count at a closed jaw, if known).
    pub zero_count: f64,
    /// Attempts per sample after the first fails (within the sample's period).
    pub retries: u32,
}

impl RecordConfig {
    /// Defaults for a port and id: 1 Mbaud, STS, 100 Hz, 60 s.
    pub fn new(port: &str, id: u8) -> Self {
        Self {
            port: port.to_string(),
            id,
            baud: DEFAULT_BAUD,
            series: Series::Sts,
            rate_hz: 100.0,
            duration_s: 60.0,
            timeout: DEFAULT_TIMEOUT,
            zero_count: 0.0,
            retries: 3,
        }
    }

    fn validate(&self) -> Result<(), BenchError> {
        let bad = |name, detail: String| Err(BenchError::Setting { name, detail });
        if self.id > MAX_SERVO_ID {
            return bad("id", format!("servo ids are 0..=253, got {}", self.id));
        }
        if !(self.rate_hz.is_finite() && self.rate_hz > 0.0 && self.rate_hz <= 1000.0) {
            return bad(
                "rate",
                format!("expected 0 < rate ≤ 1000 Hz, got {}", self.rate_hz),
            );
        }
        if !(self.duration_s.is_finite() && self.duration_s > 0.0) {
            return bad(
                "duration",
                format!("expected a positive duration in s, got {}", self.duration_s),
            );
        }
        if self.baud == 0 {
            return bad(
                "baud",
                "expected a positive baud rate (default 1000000)".into(),
            );
        }
        if !self.zero_count.is_finite() {
            return bad("zero-count", "expected a finite count".into());
        }
        Ok(())
    }
}

/// How a recording went: samples and every fault by kind.
#[derive(Debug, Clone, Default, Serialize)]
pub struct RecordReport {
    /// Port recorded from.
    pub port: String,
    /// Servo id.
    pub id: u8,
    /// Polling rate asked (Hz).
    pub rate_hz: f64,
    /// Sample periods that passed.
    pub ticks: u64,
    /// Rows written.
    pub samples: u64,
    /// Periods with no sample (device gone, or every attempt failed).
    pub missed: u64,
    /// Replies that timed out.
    pub timeouts: u64,
    /// Replies with a bad header.
    pub bad_headers: u64,
    /// Replies with a bad checksum.
    pub bad_checksums: u64,
    /// Replies from another id.
    pub wrong_ids: u64,
    /// Replies with an unexpected length.
    pub bad_lengths: u64,
    /// Replies with error bits set.
    pub servo_errors: u64,
    /// Times the device was lost.
    pub disconnects: u64,
    /// Times it was opened again after a loss.
    pub reconnects: u64,
    /// Longest time without a sample (s).
    pub longest_gap_s: f64,
    /// Host time of the first and last sample (UNIX s).
    pub first_t: Option<f64>,
    /// Host time of the last sample (UNIX s).
    pub last_t: Option<f64>,
}

impl RecordReport {
    /// Faults of every kind, summed.
    pub fn faults(&self) -> u64 {
        self.timeouts
            + self.bad_headers
            + self.bad_checksums
            + self.wrong_ids
            + self.bad_lengths
            + self.servo_errors
            + self.disconnects
    }

    fn count(&mut self, e: &BenchError) {
        match e {
            BenchError::Timeout { .. } => self.timeouts += 1,
            BenchError::BadHeader { .. } => self.bad_headers += 1,
            BenchError::BadChecksum { .. } => self.bad_checksums += 1,
            BenchError::WrongId { .. } => self.wrong_ids += 1,
            BenchError::BadLength { .. } => self.bad_lengths += 1,
            BenchError::ServoError { .. } => self.servo_errors += 1,
            _ => self.disconnects += 1,
        }
    }
}

/// A host clock in UNIX seconds that never goes backwards (wall-clock start + monotonic time).
struct HostClock {
    start: Instant,
    unix_start: f64,
}

impl HostClock {
    fn new() -> Self {
        let unix_start = SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map_or(0.0, |d| d.as_secs_f64());
        Self {
            start: Instant::now(),
            unix_start,
        }
    }

    fn at(&self, i: Instant) -> f64 {
        self.unix_start + i.duration_since(self.start).as_secs_f64()
    }
}

/// The streaming `t,raw,angle_rad` log.
struct EncoderLog {
    path: PathBuf,
    out: BufWriter<File>,
    last_sync: Instant,
}

impl EncoderLog {
    fn create(path: &Path) -> Result<Self, BenchError> {
        let file = File::create_new(path).map_err(|e| BenchError::File {
            path: path.to_path_buf(),
            detail: format!("cannot create the encoder log ({e}); choose a new --out folder, an earlier recording is never overwritten"),
        })?;
        let mut log = Self {
            path: path.to_path_buf(),
            out: BufWriter::new(file),
            last_sync: Instant::now(),
        };
        log.write_line("t,raw,angle_rad")?;
        Ok(log)
    }

    fn write_line(&mut self, line: &str) -> Result<(), BenchError> {
        let fail = |e: std::io::Error| BenchError::File {
            path: self.path.clone(),
            detail: format!("cannot write the encoder log: {e}"),
        };
        writeln!(self.out, "{line}").map_err(fail)?;
        self.out.flush().map_err(fail)?;
        if self.last_sync.elapsed() >= SYNC_EVERY {
            self.out.get_ref().sync_data().map_err(fail)?;
            self.last_sync = Instant::now();
        }
        Ok(())
    }
}

/// Record `config.duration_s` of encoder samples into `out_dir/encoder.csv` (flushed after
/// every row) and `out_dir/encoder_report.json`. `on_tick` sees the running report after each
/// sample period. The device may be absent at the start or vanish during the recording: the
/// recorder keeps trying to reopen it until the duration ends.
pub fn record(
    config: &RecordConfig,
    out_dir: &Path,
    on_tick: &mut dyn FnMut(&RecordReport),
) -> Result<RecordReport, BenchError> {
    config.validate()?;
    // A regular file or a folder is never a serial device (a missing device may still be
    // plugged in: it is waited for, up to STARTUP_GRACE).
    if Path::new(&config.port).exists() {
        check_serial_device(&config.port)?;
    }
    let created_dir = !out_dir.exists();
    std::fs::create_dir_all(out_dir).map_err(|e| BenchError::File {
        path: out_dir.to_path_buf(),
        detail: format!("cannot create the output folder: {e}"),
    })?;
    let mut log = EncoderLog::create(&out_dir.join(ENCODER_CSV))?;
    let mut report = RecordReport {
        port: config.port.clone(),
        id: config.id,
        rate_hz: config.rate_hz,
        ..RecordReport::default()
    };
    let clock = HostClock::new();
    let period = Duration::from_secs_f64(1.0 / config.rate_hz);
    let end = clock.start + Duration::from_secs_f64(config.duration_s);
    let mut servo: Option<Servo<Box<dyn serialport::SerialPort>>> = None;
    let mut ever_connected = false;
    let mut last_sample = clock.start;
    let mut k = 0u64;
    let backlog = period.mul_f64(CATCH_UP_PERIODS);
    loop {
        let tick = clock.start + period.mul_f64(k as f64);
        if tick >= end {
            break;
        }
        if !ever_connected && clock.start.elapsed() > STARTUP_GRACE {
            // Nothing answered: leave nothing behind that looks like a recording.
            drop(log);
            let _ = std::fs::remove_file(out_dir.join(ENCODER_CSV));
            if created_dir {
                let _ = std::fs::remove_dir(out_dir);
            }
            return Err(BenchError::Open {
                port: config.port.clone(),
                detail: format!(
                    "no servo answered within {:.0} s{}",
                    STARTUP_GRACE.as_secs_f64(),
                    if Path::new(&config.port).exists() {
                        format!(" (check the servo id {} and --baud)", config.id)
                    } else {
                        "; the device does not exist (is the adapter plugged in? `ls \
                         /dev/ttyUSB* /dev/ttyACM*`)"
                            .to_string()
                    }
                ),
            });
        }
        let now = Instant::now();
        if now < tick {
            std::thread::sleep(tick - now);
        } else if now - tick > backlog {
            // Too far behind (the device was gone): skip to the current period.
            let current =
                (now.duration_since(clock.start).as_secs_f64() * config.rate_hz).floor() as u64;
            let skipped = current.max(k + 1) - k;
            report.ticks += skipped;
            report.missed += skipped;
            k += skipped;
            on_tick(&report);
            continue;
        }
        let give_up = tick + backlog;
        let mut attempts = 0u32;
        let mut got = None;
        while got.is_none() && attempts <= config.retries {
            if servo.is_none() {
                match connect(config) {
                    Ok(s) => {
                        if ever_connected {
                            report.reconnects += 1;
                        }
                        ever_connected = true;
                        servo = Some(s);
                    }
                    Err(BenchError::Open { .. }) => {
                        if Instant::now() >= give_up {
                            break;
                        }
                        std::thread::sleep(REOPEN_PAUSE);
                        continue;
                    }
                    Err(e) => {
                        tracing::debug!("period {k}: connecting: {e}");
                        attempts += 1;
                        report.count(&e);
                        continue;
                    }
                }
            }
            let Some(s) = servo.as_mut() else {
                continue;
            };
            attempts += 1;
            let asked = Instant::now();
            match s.present_position() {
                Ok(raw) => {
                    let answered = Instant::now();
                    got = Some((asked + (answered - asked) / 2, raw));
                }
                Err(e) => {
                    tracing::debug!("period {k}: {e}");
                    report.count(&e);
                    if matches!(e, BenchError::Disconnected { .. }) {
                        servo = None;
                    }
                }
            }
        }
        report.ticks += 1;
        match got {
            Some((at, raw)) => {
                let t = clock.at(at);
                let angle = (f64::from(raw) - config.zero_count) / f64::from(COUNTS_PER_REV)
                    * std::f64::consts::TAU;
                log.write_line(&format!("{t:.6},{raw},{angle:.6}"))?;
                report.samples += 1;
                report.first_t.get_or_insert(t);
                report.last_t = Some(t);
                report.longest_gap_s = report
                    .longest_gap_s
                    .max(at.duration_since(last_sample).as_secs_f64());
                last_sample = at;
            }
            None => report.missed += 1,
        }
        on_tick(&report);
        k += 1;
    }
    let json = serde_json::to_string_pretty(&report).map_err(|e| BenchError::File {
        path: out_dir.join(REPORT_JSON),
        detail: e.to_string(),
    })?;
    kiwi_core::io::write_atomic(&out_dir.join(REPORT_JSON), json.as_bytes()).map_err(|e| {
        BenchError::File {
            path: out_dir.join(REPORT_JSON),
            detail: e.to_string(),
        }
    })?;
    Ok(report)
}

/// The serial port must be a character device (a USB adapter, or the pseudo-terminal of
/// `bench fake-servo`), not a missing path or a regular file.
fn check_serial_device(port: &str) -> Result<(), BenchError> {
    let open = |detail: String| BenchError::Open {
        port: port.to_string(),
        detail,
    };
    let meta = std::fs::metadata(port).map_err(|e| {
        open(format!(
            "{e}; is the adapter plugged in? (list ports with `ls /dev/ttyUSB* /dev/ttyACM*`)"
        ))
    })?;
    #[cfg(unix)]
    {
        use std::os::unix::fs::FileTypeExt as _;
        if !meta.file_type().is_char_device() {
            return Err(open(format!(
                "is a {}, not a serial device; give the adapter's device (e.g. /dev/ttyUSB0)",
                if meta.is_dir() {
                    "folder"
                } else {
                    "regular file"
                }
            )));
        }
    }
    #[cfg(not(unix))]
    let _ = meta;
    Ok(())
}

/// Open the port and switch torque off (the jaw must turn the horn freely).
fn connect(config: &RecordConfig) -> Result<Servo<Box<dyn serialport::SerialPort>>, BenchError> {
    let port = open_port(&config.port, config.baud, config.timeout)?;
    let mut servo = Servo::new(port, config.id, config.series);
    servo.torque_off()?;
    Ok(servo)
}
