//! `kiwi`: reconstruct episodes recorded on certified KIWI camera units.

use std::path::PathBuf;

use anyhow::Result;
use clap::{Parser, Subcommand};

mod gripper_cli;
mod metric_cli;
mod vision_cli;

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
    /// Fuse a wrist's IMU with visual pose observations (robust IMU factor graph, one node per
    /// frame) and write `scene_from_front_cam` per node with marginal sigmas.
    ///
    /// Inputs: `imu.csv` (`t,gx,gy,gz,ax,ay,az`), `frames.csv` (first column `t`, camera clock),
    /// `obs.csv` (`t,source,px,py,pz,qx,qy,qz,qw`, `scene_from_imu` on the IMU clock, source
    /// front|rear). Output `traj.csv`: `t,px,py,pz,qx,qy,qz,qw,sigma_p,sigma_r,support`.
    /// Without `--calibration` the fusion runs in the IMU frame (`scene_from_imu`) and needs
    /// `--imu-noise`.
    Fuse {
        /// The IMU log (imu.csv).
        #[arg(long)]
        imu: PathBuf,
        /// Node timestamps (first column `t`).
        #[arg(long)]
        frames: PathBuf,
        /// Visual pose observations.
        #[arg(long)]
        observations: PathBuf,
        /// Unit calibration.json (IMU noise, cam_from_imu and time shift of --lens).
        #[arg(long)]
        calibration: Option<PathBuf>,
        /// The lens whose frames are the nodes.
        #[arg(long, default_value = "front")]
        lens: String,
        /// IMU noise GN,GW,AN,AW: gyro noise (rad/s/√Hz), gyro random walk (rad/s²/√Hz),
        /// accel noise (m/s²/√Hz), accel random walk (m/s³/√Hz).
        #[arg(long, value_name = "GN,GW,AN,AW")]
        imu_noise: Option<String>,
        /// Pose noise of a source: SOURCE=METRES,RADIANS [defaults: front=0.001,0.001745,
        /// rear=0.002,0.00349].
        #[arg(long = "pose-sigma", value_name = "SOURCE=M,RAD")]
        pose_sigma: Vec<String>,
        /// Huber threshold on the whitened 6-dof residual norm; 0 disables it [default: 3.55].
        #[arg(long)]
        huber: Option<f64>,
        /// Keep at most this many visual factors per second and source (every frame stays a
        /// node) [default: all].
        #[arg(long)]
        visual_rate: Option<f64>,
        /// Output trajectory CSV.
        #[arg(long)]
        out: PathBuf,
        /// Print a JSON summary.
        #[arg(long)]
        json: bool,
    },
    /// Make a visual map metric and z-up: scale, gravity and IMU biases from the mapping
    /// episode's localizations and IMU (visual-inertial graph); writes metric.json.
    Metric(metric_cli::MetricArgs),
    /// Place the front map in the scene (rear) map from synchronized front and rear
    /// localizations of the mapping episode (paper eq. 2); writes placement.json.
    Place(metric_cli::PlaceArgs),
    /// Build a visual map (.kmap) from one lens of a mapping episode: KLT/ORB tracks,
    /// incremental mapping with bundle adjustment, keyframe descriptors, place recognition.
    Map(vision_cli::MapArgs),
    /// Localize every frame of one lens of an episode against a frozen map and write
    /// poses.csv (`map_from_cam`; status tracked, relocalized or lost).
    Localize(vision_cli::LocalizeArgs),
    /// Gripper opening per front-lens frame (chopstick angle in deg, parallel-jaw gap in px):
    /// opening.csv (`t,opening,unit,confidence,status`), opening.svg, tool.json.
    Gripper(gripper_cli::GripperArgs),
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
        Command::Fuse {
            imu,
            frames,
            observations,
            calibration,
            lens,
            imu_noise,
            pose_sigma,
            huber,
            visual_rate,
            out,
            json,
        } => {
            let mut config = kiwi_backend::estimate::fusion::FusionConfig::default();
            for arg in &pose_sigma {
                let (name, value) = named(arg, "--pose-sigma")?;
                let parts: Vec<f64> = value
                    .split(',')
                    .map(|v| v.trim().parse::<f64>())
                    .collect::<std::result::Result<_, _>>()
                    .map_err(|_| {
                        anyhow::anyhow!("--pose-sigma {arg}: expected SOURCE=METRES,RADIANS")
                    })?;
                let [p, r] = parts[..] else {
                    anyhow::bail!("--pose-sigma {arg}: expected SOURCE=METRES,RADIANS");
                };
                if !(p > 0.0 && r > 0.0 && p.is_finite() && r.is_finite()) {
                    anyhow::bail!("--pose-sigma {arg}: sigmas must be positive");
                }
                let sigma = kiwi_backend::estimate::fusion::PoseSigma {
                    position_m: p,
                    rotation_rad: r,
                };
                match name.as_str() {
                    "front" => config.front_sigma = sigma,
                    "rear" => config.rear_sigma = sigma,
                    other => anyhow::bail!(
                        "--pose-sigma {arg}: unknown source `{other}` (front or rear)"
                    ),
                }
            }
            if let Some(k) = huber {
                if !(k >= 0.0 && k.is_finite()) {
                    anyhow::bail!("--huber {k}: expected a non-negative threshold (0 disables)");
                }
                config.huber_k = (k > 0.0).then_some(k);
            }
            config.visual_rate_hz = visual_rate;
            let imu_noise = imu_noise
                .as_deref()
                .map(|s| {
                    metric_cli::positive_numbers::<4>("--imu-noise", s, "four numbers GN,GW,AN,AW")
                })
                .transpose()?;
            let summary = kiwi_backend::estimate::files::run_fuse(
                &kiwi_backend::estimate::files::FuseOptions {
                    imu,
                    frames,
                    observations,
                    calibration,
                    lens,
                    imu_noise,
                    config,
                    out: out.clone(),
                },
            )?;
            if json {
                println!("{}", serde_json::to_string(&summary)?);
            } else {
                println!(
                    "fused {} nodes from {} observations ({} downweighted) in {} iterations, \
                     {:.2} s -> {}",
                    summary.nodes,
                    summary.observations_used,
                    summary.outliers_downweighted,
                    summary.iterations,
                    summary.seconds,
                    out.display()
                );
            }
        }
        Command::Metric(args) => metric_cli::run_metric_cmd(&args)?,
        Command::Place(args) => metric_cli::run_place_cmd(&args)?,
        Command::Map(args) => vision_cli::run_map(&args)?,
        Command::Localize(args) => vision_cli::run_localize(&args)?,
        Command::Gripper(args) => gripper_cli::run_gripper(&args)?,
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
