//! `kiwi-calib bench …`: record the servo encoder, run a simulated servo, compare with vision.

use std::path::PathBuf;
use std::time::Duration;

use clap::{Args, Subcommand, ValueEnum};

use super::compare::{self, EncoderMap};
use super::error::BenchError;
use super::fake::{FakeServo, FakeServoConfig, Fault, HornMotion};
use super::protocol::Series;
use super::record::{self, RecordConfig};
use super::servo::DEFAULT_BAUD;

/// The jaw bench commands.
#[derive(Subcommand, Debug)]
pub enum BenchCommand {
    /// Record a Feetech servo's encoder (t,raw,angle_rad on the host clock) at a steady rate.
    Servo(ServoArgs),
    /// Run a simulated servo on a pseudo-terminal (try the bench without hardware).
    FakeServo(FakeServoArgs),
    /// Compare the vision opening with the encoder: clock offset, RMSE, max error, bias, plot.
    Compare(CompareArgs),
}

/// Register byte order on the command line.
#[derive(ValueEnum, Clone, Copy, Debug)]
pub enum SeriesArg {
    /// STS series (STS3215, …): little-endian.
    Sts,
    /// SCS series: big-endian.
    Scs,
}

impl From<SeriesArg> for Series {
    fn from(s: SeriesArg) -> Self {
        match s {
            SeriesArg::Sts => Self::Sts,
            SeriesArg::Scs => Self::Scs,
        }
    }
}

/// `bench servo` options.
#[derive(Args, Debug)]
pub struct ServoArgs {
    /// Serial port (e.g. /dev/ttyUSB0, or the link `bench fake-servo` prints).
    #[arg(long)]
    pub port: String,
    /// Servo id.
    #[arg(long, default_value_t = 1)]
    pub id: u8,
    /// Recording length (s).
    #[arg(long, default_value_t = 60.0)]
    pub duration: f64,
    /// Output folder (gets encoder.csv and encoder_report.json; never overwritten).
    #[arg(long)]
    pub out: PathBuf,
    /// Baud rate.
    #[arg(long, default_value_t = DEFAULT_BAUD)]
    pub baud: u32,
    /// Polling rate (Hz).
    #[arg(long, default_value_t = 100.0)]
    pub rate: f64,
    /// Reply timeout (ms).
    #[arg(long, default_value_t = 20)]
    pub timeout_ms: u64,
    /// Encoder count written as angle 0.
    #[arg(long, default_value_t = 0.0)]
    pub zero_count: f64,
    /// Servo series (register byte order).
    #[arg(long, value_enum, default_value_t = SeriesArg::Sts)]
    pub series: SeriesArg,
    /// Print the report as JSON.
    #[arg(long)]
    pub json: bool,
}

/// `bench fake-servo` options.
#[derive(Args, Debug)]
pub struct FakeServoArgs {
    /// Stable path to create (a symlink to the current pseudo-terminal).
    #[arg(long, default_value = "/tmp/kiwi-fake-servo")]
    pub link: PathBuf,
    /// Servo id.
    #[arg(long, default_value_t = 1)]
    pub id: u8,
    /// Inject a fault every N requests, cycling silence, bad checksum, wrong id, unplug (0: none).
    #[arg(long, default_value_t = 0)]
    pub fault_every: u64,
    /// How long an unplug lasts (ms).
    #[arg(long, default_value_t = 500)]
    pub unplug_ms: u64,
    /// Period of the horn's sinusoidal motion (s).
    #[arg(long, default_value_t = 2.0)]
    pub period: f64,
    /// Stop after this many seconds (0: run until interrupted).
    #[arg(long, default_value_t = 0.0)]
    pub duration: f64,
}

/// `bench compare` options.
#[derive(Args, Debug)]
pub struct CompareArgs {
    /// Encoder log from `bench servo`.
    #[arg(long)]
    pub encoder: PathBuf,
    /// Opening CSV from `kiwi gripper`.
    #[arg(long)]
    pub vision: PathBuf,
    /// Output folder (compare.json, compare.svg, aligned.csv).
    #[arg(long)]
    pub out: PathBuf,
    /// The tool: chopstick, parallel_jaw, a definition (.toml) or a JSON artifact with one
    /// (kiwi gripper's tool.json, a tool calibration). Its [encoder] section maps counts to
    /// the opening. Default: tool.json beside --vision when it exists.
    #[arg(long)]
    pub tool: Option<String>,
    /// Override: encoder count at a closed jaw (without a tool: the angle_rad column).
    #[arg(long)]
    pub zero_count: Option<f64>,
    /// Override: opening per horn radian (jaw rad/rad; −1 if the horn turns the other way).
    #[arg(long, allow_negative_numbers = true)]
    pub scale: Option<f64>,
    /// Print `{"rmse", "unit", "offset_s", "n"}` as JSON.
    #[arg(long)]
    pub json: bool,
}

/// Run a bench command; returns what to print.
pub fn run(cmd: &BenchCommand) -> Result<String, BenchError> {
    match cmd {
        BenchCommand::Servo(a) => run_servo(a),
        BenchCommand::FakeServo(a) => run_fake(a),
        BenchCommand::Compare(a) => {
            let map = encoder_map(a)?;
            let (c, out) = compare::run(&a.encoder, &a.vision, &map, &a.out)?;
            if a.json {
                Ok(serde_json::json!({
                    "rmse": c.rmse, "unit": c.unit, "offset_s": c.offset_s, "n": c.n,
                })
                .to_string())
            } else {
                let u = match c.unit {
                    compare::OpeningUnit::Deg => "deg",
                    compare::OpeningUnit::Px => "px",
                };
                Ok(format!(
                    "rmse {:.3} {u}, max {:.3} {u}, bias {:+.3} {u} over {} samples; clock offset {:.4} s (host = video + offset); encoder map: {}; wrote {}, {}, {}",
                    c.rmse,
                    c.max_error,
                    c.bias,
                    c.n,
                    c.offset_s,
                    c.map_source,
                    out.json.display(),
                    out.plot.display(),
                    out.aligned.display()
                ))
            }
        }
    }
}

/// The encoder map of `bench compare`: the tool's, then the command-line overrides.
fn encoder_map(a: &CompareArgs) -> Result<EncoderMap, BenchError> {
    let beside = a.vision.with_file_name("tool.json");
    let spec = match &a.tool {
        Some(t) => Some(t.clone()),
        None if beside.exists() => Some(beside.display().to_string()),
        None => None,
    };
    let mut map = match &spec {
        Some(spec) => {
            let (def, px_per_m) = compare::load_tool(spec)?;
            EncoderMap::from_tool(&def, px_per_m, spec)
        }
        None => EncoderMap::default(),
    };
    if let Some(z) = a.zero_count {
        map.zero_count = Some(z);
        map.source = format!("--zero-count {z} over {}", map.source);
    }
    if let Some(s) = a.scale {
        map.scale = s;
        map.source = format!("--scale {s} over {}", map.source);
    }
    Ok(map)
}

fn run_servo(a: &ServoArgs) -> Result<String, BenchError> {
    let config = RecordConfig {
        port: a.port.clone(),
        id: a.id,
        baud: a.baud,
        series: a.series.into(),
        rate_hz: a.rate,
        duration_s: a.duration,
        timeout: Duration::from_millis(a.timeout_ms),
        zero_count: a.zero_count,
        retries: 3,
    };
    let bar = indicatif::ProgressBar::new((a.duration * a.rate).max(0.0) as u64);
    if let Ok(style) = indicatif::ProgressStyle::with_template(
        "{bar:40} {pos}/{len} periods {msg} [{elapsed_precise}]",
    ) {
        bar.set_style(style);
    }
    let report = record::record(&config, &a.out, &mut |r| {
        bar.set_position(r.ticks);
        bar.set_message(format!("{} samples, {} faults", r.samples, r.faults()));
    })?;
    bar.finish_and_clear();
    if a.json {
        return serde_json::to_string_pretty(&report).map_err(|e| BenchError::File {
            path: a.out.clone(),
            detail: e.to_string(),
        });
    }
    Ok(format!(
        "{} samples in {} periods ({} missed); faults: {} timeouts, {} bad checksums, {} wrong ids, {} bad lengths, {} bad headers, {} servo errors, {} disconnects ({} reconnects); longest gap {:.3} s; wrote {}",
        report.samples,
        report.ticks,
        report.missed,
        report.timeouts,
        report.bad_checksums,
        report.wrong_ids,
        report.bad_lengths,
        report.bad_headers,
        report.servo_errors,
        report.disconnects,
        report.reconnects,
        report.longest_gap_s,
        a.out.join(record::ENCODER_CSV).display()
    ))
}

fn run_fake(a: &FakeServoArgs) -> Result<String, BenchError> {
    if !(a.period.is_finite() && a.period > 0.0) {
        return Err(BenchError::Setting {
            name: "period",
            detail: format!("expected a positive period in s, got {}", a.period),
        });
    }
    let mut config = FakeServoConfig::new(a.id, &a.link);
    config.fault_every = a.fault_every;
    config.unplug = Duration::from_millis(a.unplug_ms);
    config.motion = HornMotion {
        period_s: a.period,
        ..HornMotion::default()
    };
    let servo = FakeServo::start(config)?;
    eprintln!(
        "fake servo id {} on {} (link {}); faults every {} requests cycling {:?}; Ctrl-C to stop",
        a.id,
        servo.device_path(),
        servo.link().display(),
        a.fault_every,
        Fault::ALL
    );
    let start = std::time::Instant::now();
    while a.duration <= 0.0 || start.elapsed().as_secs_f64() < a.duration {
        if servo.is_finished() {
            break;
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    let stats = servo.stop();
    Ok(format!(
        "{} requests, {} clean replies, {} silences, {} corrupted, {} wrong ids, {} unplugs",
        stats.requests,
        stats.replies,
        stats.silences,
        stats.corrupted,
        stats.wrong_ids,
        stats.unplugs
    ))
}
