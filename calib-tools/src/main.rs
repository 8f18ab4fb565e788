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
    /// Check a unit's calibration.json and print a summary.
    Validate {
        /// The calibration.json to check.
        calibration: PathBuf,
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
    },
}

fn main() -> Result<()> {
    let cli = Cli::parse();
    init_logging(cli.verbose);
    match cli.command {
        Command::Validate { calibration, json } => {
            let cal = UnitCalibration::load(&calibration)?;
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
        } => {
            if out.exists() {
                anyhow::bail!(
                    "{} exists and is never overwritten; choose another --out",
                    out.display()
                );
            }
            let cal = kiwi_calib::export::import_kalibr(
                &camchain,
                imu.as_deref(),
                &unit_id,
                &camera_model,
                &kiwi_core::io::utc_today(),
            )
            .with_context(|| format!("importing {}", camchain.display()))?;
            cal.save(&out)?;
            println!("wrote {} ({} lenses)", out.display(), cal.lenses.len());
        }
    }
    Ok(())
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
