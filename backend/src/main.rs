//! `kiwi`: reconstruct episodes recorded on certified KIWI camera units.

use std::path::PathBuf;

use anyhow::Result;
use clap::{Parser, Subcommand};

/// Reconstruct KIWI episodes: audio sync, fisheye maps, metric recovery, localization, IMU
/// fusion, gripper opening, head pose, floor height, dataset export.
#[derive(Parser)]
#[command(name = "kiwi", version, about, long_about = None)]
struct Cli {
    /// More log output (repeat for more).
    #[arg(short, long, action = clap::ArgAction::Count, global = true)]
    verbose: u8,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Place cameras on one timeline from their audio (fingerprints + GCC-PHAT + drift fit).
    ///
    /// Either name audio files (`--audio NAME=FILE`, the first is the reference) or run the
    /// stage on a prepared episode (`--session session.toml --episode NAME`), which writes
    /// `episodes/NAME/work/sync/sync.json`. Output clocks follow
    /// `session_time = local_video_time * (1 + drift_ppm*1e-6) + offset_s`.
    Sync {
        /// A camera's audio: NAME=path.wav (repeat; the first is the reference).
        #[arg(long = "audio", value_name = "NAME=FILE")]
        audio: Vec<String>,
        /// A camera's A/V delay in seconds: NAME=SECONDS.
        #[arg(long = "av-delay", value_name = "NAME=SECONDS")]
        av_delay: Vec<String>,
        /// A camera's unit calibration (its A/V delay is used): NAME=calibration.json.
        #[arg(long = "calibration", value_name = "NAME=FILE")]
        calibration: Vec<String>,
        /// A camera's recording mode, to pick the A/V delay from its calibration: NAME=MODE.
        #[arg(long = "mode", value_name = "NAME=MODE")]
        mode: Vec<String>,
        /// Run as a stage on this session's episode (with --episode).
        #[arg(long, conflicts_with = "audio")]
        session: Option<PathBuf>,
        /// The episode to synchronise (with --session).
        #[arg(long, requires = "session")]
        episode: Option<String>,
        /// Re-run the stage even if its inputs are unchanged.
        #[arg(long)]
        force: bool,
        /// Print the full JSON result.
        #[arg(long)]
        json: bool,
    },
    /// Check a session: session.toml, unit calibrations and every prepared episode's files.
    Inspect {
        /// The session's session.toml.
        session: PathBuf,
        /// Print a machine-readable JSON summary.
        #[arg(long)]
        json: bool,
    },
}

/// Split `NAME=VALUE`.
fn named(arg: &str, flag: &str) -> Result<(String, String)> {
    arg.split_once('=')
        .map(|(n, v)| (n.to_string(), v.to_string()))
        .ok_or_else(|| anyhow::anyhow!("{flag} {arg}: expected NAME=VALUE"))
}

fn sync_files(
    audio: &[String],
    av_delay: &[String],
    calibration: &[String],
    mode: &[String],
) -> Result<kiwi_backend::sync::SyncResult> {
    use anyhow::Context;
    if audio.len() < 2 {
        anyhow::bail!(
            "name at least two cameras with --audio NAME=FILE (or use --session and --episode)"
        );
    }
    let mut inputs = Vec::new();
    for a in audio {
        let (name, file) = named(a, "--audio")?;
        let path = PathBuf::from(&file);
        let decoded = kiwi_backend::sync::audio::read_audio(&path)
            .with_context(|| format!("camera {name}"))?;
        let mut delay = 0.0;
        for d in av_delay {
            let (n, v) = named(d, "--av-delay")?;
            if n == name {
                delay = v
                    .parse::<f64>()
                    .with_context(|| format!("--av-delay {d}: expected seconds"))?;
            }
        }
        for c in calibration {
            let (n, f) = named(c, "--calibration")?;
            if n == name {
                let cal = kiwi_core::artifact::UnitCalibration::load(std::path::Path::new(&f))?;
                let m = mode
                    .iter()
                    .filter_map(|m| named(m, "--mode").ok())
                    .find(|(n, _)| *n == name)
                    .map(|(_, m)| m);
                delay = kiwi_backend::sync::stage::av_delay_for(
                    &cal,
                    m.as_deref(),
                    std::path::Path::new(&f),
                )?;
            }
        }
        inputs.push(kiwi_backend::sync::SyncInput {
            name,
            audio: decoded,
            av_delay_s: delay,
        });
    }
    Ok(kiwi_backend::sync::synchronise(&inputs))
}

fn main() -> Result<()> {
    let cli = Cli::parse();
    let level = if cli.verbose == 0 { "warn" } else { "info" };
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(level));
    tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .init();
    match cli.command {
        Command::Sync {
            audio,
            av_delay,
            calibration,
            mode,
            session,
            episode,
            force,
            json,
        } => {
            let result = if let Some(session) = session {
                let episode =
                    episode.ok_or_else(|| anyhow::anyhow!("--session needs --episode NAME"))?;
                match kiwi_backend::sync::stage::run(&session, &episode, force)? {
                    kiwi_backend::sync::stage::StageOutcome::UpToDate(path) => {
                        println!(
                            "{} is up to date (inputs unchanged; --force re-runs)",
                            path.display()
                        );
                        return Ok(());
                    }
                    kiwi_backend::sync::stage::StageOutcome::Written(path, result) => {
                        eprintln!("wrote {}", path.display());
                        *result
                    }
                }
            } else {
                sync_files(&audio, &av_delay, &calibration, &mode)?
            };
            if json {
                println!("{}", serde_json::to_string_pretty(&result)?);
            } else {
                for c in &result.cameras {
                    println!(
                        "{:10} offset {:+12.6} s  drift {:+7.2} ppm  ({:?})",
                        c.name, c.offset_s, c.drift_ppm, c.status
                    );
                }
                for p in &result.pairs {
                    let detail = p.reason.clone().unwrap_or_else(|| {
                        format!(
                            "{} windows, {}",
                            p.windows,
                            p.class.clone().unwrap_or_default()
                        )
                    });
                    println!(
                        "pair {}-{}: {} (votes {}, ratio {:.1}) {detail}",
                        p.a, p.b, p.status, p.votes, p.peak_ratio
                    );
                }
            }
        }
        Command::Inspect { session, json } => {
            let report = kiwi_backend::inspect::inspect_session(&session)?;
            if json {
                println!("{}", serde_json::to_string_pretty(&report)?);
            } else {
                println!(
                    "session {} (maps from episode {})",
                    report.name, report.map_episode
                );
                for c in &report.cameras {
                    let verdict = match c.certified {
                        Some(true) => "certified",
                        Some(false) => "FAILED certification",
                        None => "not certified",
                    };
                    println!("  camera {:5} unit {} ({verdict})", c.camera, c.unit);
                }
                for e in &report.episodes {
                    let lenses: Vec<String> = e
                        .lenses
                        .iter()
                        .map(|(c, l, n)| format!("{c}/{l}: {n} frames"))
                        .collect();
                    println!("  episode {}: {}", e.name, lenses.join(", "));
                }
            }
        }
    }
    Ok(())
}
