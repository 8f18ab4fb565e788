//! `kiwi-calib`: certify a KIWI camera unit and convert its calibration for other tools.

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::{Parser, Subcommand};
use kiwi_core::artifact::UnitCalibration;
use kiwi_core::camera::CameraModel;

/// Certify KIWI camera units: lens intrinsics, camera–IMU extrinsics and time shifts, IMU
/// noise, A/V delay; convert calibrations to and from Kalibr and Basalt.
#[derive(Parser)]
#[command(name = "kiwi-calib", version, about, long_about = None)]
struct Cli {
    /// More log output (repeat for more).
    #[arg(short, long, action = clap::ArgAction::Count, global = true)]
    verbose: u8,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Render the QR-clock rig's display video: a QR code of the display clock every frame and
    /// chirps on a known schedule (needs ffmpeg; `make deps` installs it).
    QrClock {
        /// The video to write (.mp4); the chirp schedule goes beside it (.chirps.csv).
        #[arg(long)]
        out: PathBuf,
        /// Length in seconds.
        #[arg(long, default_value_t = 120.0, value_parser = kiwi_core::args::positive)]
        duration: f64,
        /// Display refresh rate of the video (Hz); play it full screen on a monitor of this rate.
        #[arg(long, default_value_t = 60.0, value_parser = kiwi_core::args::positive)]
        fps: f64,
        /// Print a JSON summary.
        #[arg(long)]
        json: bool,
    },
    /// Measure each camera's A/V delay per recording mode from QR-clock rig captures, and the
    /// optical offsets between cameras that filmed the rig together.
    AvDelay {
        /// A prepared camera folder of the rig (meta.json, audio.wav, <lens>/frames.csv); repeat.
        #[arg(long = "capture", required = true)]
        captures: Vec<PathBuf>,
        /// The units' calibration.json (readout times for the row correction; the delays are
        /// written into a copy in --out); repeat, matched by unit id.
        #[arg(long = "calibration")]
        calibrations: Vec<PathBuf>,
        /// Display refresh rate (Hz).
        #[arg(long, default_value_t = 60.0, value_parser = kiwi_core::args::positive)]
        refresh: f64,
        /// Distance from the rig's speaker to a capture's camera: NAME=METRES (removes the sound's
        /// travel time, 2.9 ms per metre). Without it a capture takes its distance from the
        /// `rig.toml` beside its camera folder (`[speaker_distance_m]`, `NAME = metres`), if any.
        #[arg(long = "speaker-distance", value_name = "NAME=METRES")]
        speaker_distance: Vec<String>,
        /// Report folder.
        #[arg(long)]
        out: PathBuf,
        /// Print the full JSON result.
        #[arg(long)]
        json: bool,
    },
    /// IMU noise from a long static log: overlapping Allan deviation per axis and a joint fit
    /// of quantization, white noise, bias instability, random walk and rate ramp.
    ImuNoise {
        /// The static log (imu.csv: t,gx,gy,gz,ax,ay,az in s, rad/s, m/s²); hours at up to 1 kHz.
        #[arg(long)]
        imu: PathBuf,
        /// Result folder (imu_noise.json, imu.yaml, allan.svg, report.md).
        #[arg(long)]
        out: PathBuf,
        /// Where to write the plot (default OUT/allan.svg).
        #[arg(long)]
        plot: Option<PathBuf>,
        /// The unit's calibration.json: a copy with this noise model is written to OUT.
        #[arg(long)]
        calibration: Option<PathBuf>,
        /// Averaging times per decade.
        #[arg(long, default_value_t = 20)]
        per_decade: usize,
        /// Terms to fit (comma-separated): quantization, white, bias-instability, random-walk,
        /// rate-ramp.
        #[arg(
            long,
            default_value = "quantization,white,bias-instability,random-walk,rate-ramp"
        )]
        terms: String,
        /// Terms that must be well determined, else the command fails and says how long a log
        /// is needed (comma-separated; empty for none).
        #[arg(long, default_value = "white,random-walk")]
        require: String,
        /// Print the JSON summary.
        #[arg(long)]
        json: bool,
    },
    /// Check a unit's calibration.json and print a summary. Fails (exit 3) when the
    /// calibration is valid but lacks what `kiwi` needs (IMU noise, camera–IMU extrinsics and
    /// time shifts), unless --partial.
    Validate {
        /// The calibration.json to check (or the set folder holding it).
        calibration: PathBuf,
        /// Accept a calibration in progress (e.g. intrinsics only).
        #[arg(long)]
        partial: bool,
        /// Print a machine-readable JSON summary.
        #[arg(long)]
        json: bool,
    },
    /// Write Kalibr (camchain-imucam.yaml, imu.yaml) and Basalt files for a calibration.
    Export {
        /// The unit's calibration.json.
        #[arg(long)]
        calibration: PathBuf,
        /// Folder to write the exports into (created if needed).
        #[arg(long)]
        out: PathBuf,
        /// Print a machine-readable JSON summary.
        #[arg(long)]
        json: bool,
    },
    /// Build a KIWI calibration.json from Kalibr's camchain (and optional imu.yaml).
    ImportKalibr {
        /// Kalibr camchain.yaml or camchain-imucam.yaml.
        #[arg(long)]
        camchain: PathBuf,
        /// Kalibr imu.yaml.
        #[arg(long)]
        imu: Option<PathBuf>,
        /// The unit's id.
        #[arg(long)]
        unit_id: String,
        /// Camera product name.
        #[arg(long, default_value = "Insta360 X5")]
        camera_model: String,
        /// Where to write calibration.json (an existing file is never overwritten).
        #[arg(long)]
        out: PathBuf,
        /// KIWI lens names of cam0, cam1, … (comma-separated; default: the names in the
        /// rostopics, else front,rear — main for a one-camera GO 3).
        #[arg(long, value_delimiter = ',')]
        lenses: Option<Vec<String>>,
    },
    /// Write print-ready targets: a Kalibr aprilgrid board (+ target yaml) or an ArUco tag.
    #[command(subcommand)]
    Target(kiwi_calib::lens_cli::TargetCommand),
    /// Convert corners from other tools (OpenCV FileStorage image and board points) into a
    /// corners file for `intrinsics --corners`.
    #[command(subcommand)]
    Corners(kiwi_calib::import::CornersCommand),
    /// Detect aprilgrid corners in a folder of images and write a corners file.
    Detect(kiwi_calib::lens_cli::DetectArgs),
    /// Calibrate a lens's intrinsics over its whole field of view (images or a corners file).
    Intrinsics(kiwi_calib::lens_cli::IntrinsicsArgs),
    /// Time detection + intrinsics fit of a folder of images (benchmark).
    BenchIntrinsics(kiwi_calib::lens_cli::BenchIntrinsicsArgs),
    /// Camera–IMU extrinsic and time shift of every lens from an excitation recording in front
    /// of aprilgrid boards (joint continuous-time batch estimate; docs/cam-imu.md).
    CamImu(kiwi_calib::cam_imu::report::CamImuArgs),
    /// Jaw bench: record a Feetech servo encoder, run a simulated servo, compare with vision.
    #[command(subcommand)]
    Bench(kiwi_calib::bench::cli::BenchCommand),
    /// Certify a unit from its capture folder: intrinsics, IMU noise, camera–IMU and A/V delay
    /// in one run, written to units/ID/YYYY-MM-DD[-N]/ with a verdict (docs/certify.md).
    Certify(kiwi_calib::certify::cli::CertifyArgs),
    /// List certified units, or show a unit's latest set.
    #[command(subcommand)]
    Units(kiwi_calib::certify::cli::UnitsCommand),
    /// Printed hardware: generate params.scad and the tool definitions from
    /// hardware/params.toml, render and check every part (docs/hardware.md).
    #[command(subcommand)]
    Hardware(kiwi_calib::hardware::cli::HardwareCommand),
}

/// Exit status of `validate` for a valid calibration that lacks what `kiwi` needs.
const EXIT_INCOMPLETE: i32 = 3;

fn main() -> Result<()> {
    let cli = Cli::parse();
    init_logging(cli.verbose);
    for path in outputs(&cli.command) {
        kiwi_core::io::ensure_outside_dated_set(path)?;
    }
    match cli.command {
        Command::QrClock {
            out,
            duration,
            fps,
            json,
        } => {
            let written = kiwi_calib::qr_clock::write_qr_clock(&out, duration, fps)?;
            if json {
                println!("{}", serde_json::to_string_pretty(&written)?);
            } else {
                println!(
                    "wrote {} ({} frames, {} chirps; schedule {})",
                    written.video.display(),
                    written.frames,
                    written.chirps,
                    written.schedule.display()
                );
            }
        }
        Command::AvDelay {
            captures,
            calibrations,
            refresh,
            speaker_distance,
            out,
            json,
        } => {
            let mut options = kiwi_calib::av_delay::AvDelayOptions {
                refresh_hz: refresh,
                speaker_distance_m: Vec::new(),
                calibrations: Vec::new(),
            };
            for c in &calibrations {
                options
                    .calibrations
                    .push((c.clone(), UnitCalibration::load(c)?));
            }
            for d in &speaker_distance {
                let (name, metres) = d.split_once('=').ok_or_else(|| {
                    anyhow::anyhow!("--speaker-distance {d}: expected NAME=METRES")
                })?;
                let metres: f64 = metres
                    .parse()
                    .with_context(|| format!("--speaker-distance {d}: expected metres"))?;
                let limit = kiwi_calib::av_delay::MAX_SPEAKER_DISTANCE_M;
                if !(metres.is_finite() && (0.0..limit).contains(&metres)) {
                    anyhow::bail!(
                        "--speaker-distance {d}: expected metres in [0, {limit}) (a distance in cm \
                         or mm?)"
                    );
                }
                options.speaker_distance_m.push((name.to_string(), metres));
            }
            let report = kiwi_calib::av_delay::analyse(&captures, &options)?;
            let written = kiwi_calib::av_delay::write_outputs(&report, &options, &out)?;
            if json {
                println!("{}", serde_json::to_string_pretty(&report)?);
            } else {
                for m in &report.modes {
                    println!(
                        "{} {}: d = {:.3} ± {:.3} ms over {} capture(s), spread {:.3} ms",
                        m.camera_model,
                        m.mode,
                        m.delay_s * 1e3,
                        m.std_s * 1e3,
                        m.repeats,
                        m.spread_s * 1e3
                    );
                }
                for o in &report.offsets {
                    println!(
                        "{} vs {}: offset {:.6} s ± {:.3} ms, drift {:+.2} ppm",
                        o.capture,
                        o.reference,
                        o.offset_s,
                        o.offset_std_s * 1e3,
                        o.drift_ppm
                    );
                }
                for p in written {
                    println!("wrote {}", p.display());
                }
            }
        }
        Command::ImuNoise {
            imu,
            out,
            plot,
            calibration,
            per_decade,
            terms,
            require,
            json,
        } => {
            let parse_terms = |list: &str, flag: &str| -> Result<Vec<kiwi_calib::allan::Term>> {
                list.split(',')
                    .filter(|t| !t.trim().is_empty())
                    .map(|t| {
                        kiwi_calib::allan::Term::parse(t).ok_or_else(|| {
                            anyhow::anyhow!(
                                "{flag} {t}: expected quantization, white, bias-instability, \
                                 random-walk or rate-ramp"
                            )
                        })
                    })
                    .collect()
            };
            let options = kiwi_calib::allan::AllanOptions {
                per_decade,
                terms: parse_terms(&terms, "--terms")?,
                require: parse_terms(&require, "--require")?,
                ..Default::default()
            };
            let calibration = match &calibration {
                Some(p) => Some((p.as_path(), UnitCalibration::load(p)?)),
                None => None,
            };
            let bar =
                indicatif::ProgressBar::new(0).with_style(indicatif::ProgressStyle::with_template(
                    "reading {msg} {bar:40} {bytes}/{total_bytes} ({eta})",
                )?);
            bar.set_message(imu.display().to_string());
            let log = kiwi_calib::allan::read_static_log(&imu, Some(&bar))?;
            bar.finish_and_clear();
            let report = kiwi_calib::allan::analyse(log, &options)?;
            let written =
                kiwi_calib::allan::write_outputs(&report, &out, plot.as_deref(), calibration)?;
            if json {
                println!(
                    "{}",
                    serde_json::to_string_pretty(&kiwi_calib::allan::summary_json(&report))?
                );
            } else {
                println!(
                    "{} samples at {:.2} Hz ({:.2} h)",
                    report.samples,
                    report.rate_hz,
                    report.duration_s / 3600.0
                );
                println!(
                    "gyroscope:     noise density {:.3e} rad/s/√Hz, random walk {:.3e} rad/s²/√Hz, \
                     bias instability {:.3e} rad/s",
                    report.gyroscope_noise_density,
                    report.gyroscope_random_walk,
                    report.gyroscope_bias_instability
                );
                println!(
                    "accelerometer: noise density {:.3e} m/s²/√Hz, random walk {:.3e} m/s³/√Hz, \
                     bias instability {:.3e} m/s²",
                    report.accelerometer_noise_density,
                    report.accelerometer_random_walk,
                    report.accelerometer_bias_instability
                );
                for w in &report.warnings {
                    println!("warning: {w}");
                }
                println!("wrote {}", written.result.display());
                println!("wrote {}", written.kalibr_imu.display());
                println!("wrote {}", written.plot.display());
                println!("wrote {}", written.report.display());
                if let Some(c) = &written.calibration {
                    println!("wrote {}", c.display());
                }
            }
        }
        Command::Validate {
            calibration,
            partial,
            json,
        } => {
            let calibration = if calibration.is_dir() {
                calibration.join("calibration.json")
            } else {
                calibration
            };
            let cal = UnitCalibration::load(&calibration)?;
            let missing = cal.missing_for_reconstruction();
            if json {
                println!("{}", serde_json::to_string_pretty(&summary(&cal))?);
            } else {
                println!(
                    "{}: valid (schema {}, unit {}, {})",
                    calibration.display(),
                    cal.schema_version,
                    cal.unit_id,
                    cal.date
                );
                for lens in &cal.lenses {
                    println!(
                        "  lens {:6} {} {}x{} fov {:.1}° rms {} extrinsic {} time shift {}",
                        lens.name,
                        lens.camera()?.kind(),
                        lens.resolution[0],
                        lens.resolution[1],
                        lens.valid_fov_rad.to_degrees(),
                        lens.rms_px.map_or("-".into(), |r| format!("{r:.3} px")),
                        if lens.cam_from_imu.is_some() {
                            "yes"
                        } else {
                            "no"
                        },
                        lens.time_shift_s
                            .map_or("-".into(), |s| format!("{:.3} ms", s * 1e3)),
                    );
                }
                println!(
                    "  imu noise model: {}",
                    if cal.imu.is_some() { "yes" } else { "no" }
                );
                println!("  A/V delays: {}", cal.av_delays.len());
                match &cal.certification {
                    Some(c) => println!(
                        "  certification: {}",
                        if c.passed { "PASSED" } else { "FAILED" }
                    ),
                    None => println!("  certification: none"),
                }
            }
            if !missing.is_empty() {
                eprintln!(
                    "{}: incomplete for reconstruction; missing {}",
                    calibration.display(),
                    missing.join(", ")
                );
                if !partial {
                    eprintln!("(pass --partial to accept a calibration in progress)");
                    std::process::exit(EXIT_INCOMPLETE);
                }
            }
        }
        Command::Export {
            calibration,
            out,
            json,
        } => {
            let cal = UnitCalibration::load(&calibration)?;
            let files = kiwi_calib::export::export_all(&cal, &out)?;
            if json {
                println!("{}", serde_json::to_string_pretty(&files)?);
            } else {
                println!("wrote {}", files.kalibr_camchain.display());
                for p in files.kalibr_imu.iter().chain(files.basalt.iter()) {
                    println!("wrote {}", p.display());
                }
                for s in &files.skipped {
                    println!("skipped {s}");
                }
            }
        }
        Command::ImportKalibr {
            camchain,
            imu,
            unit_id,
            camera_model,
            out,
            lenses,
        } => {
            if out.exists() {
                anyhow::bail!(
                    "{} exists and is never overwritten; choose another --out",
                    out.display()
                );
            }
            let (cal, mapping) = kiwi_calib::export::import_kalibr(
                &camchain,
                imu.as_deref(),
                &unit_id,
                &camera_model,
                &kiwi_core::io::utc_today(),
                lenses.as_deref(),
            )
            .with_context(|| format!("importing {}", camchain.display()))?;
            cal.save(&out)?;
            let names: Vec<String> = mapping
                .iter()
                .map(|m| format!("{} → {}", m.kalibr, m.lens))
                .collect();
            println!(
                "wrote {} ({} lenses: {})",
                out.display(),
                cal.lenses.len(),
                names.join(", ")
            );
        }
        Command::Target(cmd) => {
            for p in kiwi_calib::lens_cli::run_target(&cmd)? {
                println!("wrote {}", p.display());
            }
        }
        Command::Corners(cmd) => {
            let set = kiwi_calib::import::run_corners(&cmd)?;
            let kiwi_calib::import::CornersCommand::Import(args) = &cmd;
            if args.json {
                println!("{}", serde_json::to_string_pretty(&set.summary_json())?);
            } else {
                println!(
                    "{} views, {} corners; wrote {}",
                    set.images.len(),
                    set.total_corners(),
                    args.out.display()
                );
            }
        }
        Command::Detect(args) => {
            let set = kiwi_calib::lens_cli::run_detect(&args)?;
            if args.json {
                println!("{}", serde_json::to_string_pretty(&set.summary_json())?);
            } else {
                println!(
                    "{} images with the target, {} corners; wrote {}",
                    set.images.len(),
                    set.total_corners(),
                    args.out.display()
                );
            }
        }
        Command::Intrinsics(args) => {
            let summary = kiwi_calib::lens_cli::run_intrinsics(&args)?;
            if args.json {
                println!("{}", serde_json::to_string_pretty(&summary)?);
            } else {
                println!(
                    "{} rms {:.3} px over {} views, {} corners ({} rejected); params {}; wrote {}",
                    summary["model"],
                    summary["rms_px"].as_f64().unwrap_or(f64::NAN),
                    summary["n_views"],
                    summary["n_corners"],
                    summary["n_rejected"],
                    summary["params"],
                    args.out.display()
                );
            }
        }
        Command::BenchIntrinsics(args) => {
            println!("{}", kiwi_calib::lens_cli::run_bench(&args)?);
        }
        Command::CamImu(args) => {
            let (result, files) = kiwi_calib::cam_imu::report::run(&args)?;
            if args.json {
                println!(
                    "{}",
                    serde_json::to_string_pretty(&kiwi_calib::cam_imu::report::summary_json(
                        &result
                    ))?
                );
            } else {
                for l in &result.lenses {
                    println!(
                        "{}: rotation {:?} deg, translation {:?} m, time shift {:.3} ms \
                         (±{:.3}), RMS {:.3} px",
                        l.name,
                        l.rotation_deg,
                        l.translation_m,
                        l.time_shift_s * 1e3,
                        l.time_shift_std_s * 1e3,
                        l.rms_px
                    );
                }
                println!(
                    "wrote {} and the report in {}",
                    files.calibration.display(),
                    args.out.display()
                );
            }
        }
        Command::Bench(cmd) => {
            println!("{}", kiwi_calib::bench::cli::run(&cmd)?);
        }
        Command::Certify(args) => {
            let report = kiwi_calib::certify::cli::run_certify(&args)?;
            if !report.passed {
                std::process::exit(kiwi_calib::certify::cli::EXIT_NOT_CERTIFIED);
            }
        }
        Command::Units(cmd) => {
            print!("{}", kiwi_calib::certify::cli::run_units(&cmd)?);
        }
        Command::Hardware(cmd) => {
            print!("{}", kiwi_calib::hardware::cli::run(&cmd)?);
        }
    }
    Ok(())
}

/// Every file or folder a command writes: none of them may lie inside a dated set (only
/// `certify` creates sets, each in a folder of its own).
fn outputs(command: &Command) -> Vec<&std::path::Path> {
    use kiwi_calib::bench::cli::BenchCommand;
    use kiwi_calib::lens_cli::TargetCommand;
    match command {
        Command::QrClock { out, .. }
        | Command::AvDelay { out, .. }
        | Command::Export { out, .. }
        | Command::ImportKalibr { out, .. }
        | Command::Target(
            TargetCommand::Aprilgrid { out, .. } | TargetCommand::Aruco { out, .. },
        )
        | Command::Hardware(kiwi_calib::hardware::cli::HardwareCommand::Render { out, .. }) => {
            vec![out]
        }
        Command::ImuNoise { out, plot, .. } => std::iter::once(out)
            .chain(plot.as_ref())
            .map(PathBuf::as_path)
            .collect(),
        Command::Corners(kiwi_calib::import::CornersCommand::Import(a)) => vec![&a.out],
        Command::Detect(a) => vec![&a.out],
        Command::Intrinsics(a) => vec![&a.out],
        Command::CamImu(a) => vec![&a.out],
        Command::Bench(BenchCommand::Servo(a)) => vec![&a.out],
        Command::Bench(BenchCommand::Compare(a)) => vec![&a.out],
        Command::Bench(BenchCommand::FakeServo(a)) => vec![&a.link],
        Command::Certify(a) => vec![&a.out],
        Command::Hardware(kiwi_calib::hardware::cli::HardwareCommand::Generate { .. }) => {
            Vec::new()
        }
        Command::Validate { .. } | Command::BenchIntrinsics(_) | Command::Units(_) => Vec::new(),
    }
}

fn summary(cal: &UnitCalibration) -> serde_json::Value {
    serde_json::json!({
        "unit_id": cal.unit_id,
        "date": cal.date,
        "lenses": cal.lenses.iter().map(|l| serde_json::json!({
            "name": l.name,
            "params": l.intrinsics.params(),
            "rms_px": l.rms_px,
            "has_extrinsic": l.cam_from_imu.is_some(),
            "time_shift_s": l.time_shift_s,
        })).collect::<Vec<_>>(),
        "has_imu_noise": cal.imu.is_some(),
        "missing_for_reconstruction": cal.missing_for_reconstruction(),
        "av_delays": cal.av_delays.len(),
        "certified": cal.certification.as_ref().map(|c| c.passed),
    })
}

fn init_logging(verbose: u8) {
    let level = match verbose {
        0 => "warn",
        1 => "info",
        _ => "debug",
    };
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(level));
    tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .init();
}
