//! `kiwi`: reconstruct episodes recorded on certified KIWI camera units.

use anyhow::Result;
use clap::{Parser, Subcommand};

mod batch;
mod evaluate;
mod export;
mod fuse;
mod gripper;
mod ingest;
mod inspect;
mod metric;
mod report;
mod run;
mod sync;
mod vision;

/// Reconstruct KIWI episodes: audio sync, fisheye maps, metric recovery, localization, IMU
/// fusion, gripper opening, head pose, floor height, dataset export, session report.
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
    /// The main job: run every stage of a session (sync, maps, localization, metric recovery,
    /// placement, observations, IMU fusion, gripper opening) and write each episode's tool-tip
    /// trajectories, TUM files and quality verdict under episodes/<ep>/out/.
    ///
    /// Stages whose inputs are unchanged are skipped; a killed run resumes where it stopped.
    /// Exit status: 0 when every episode is usable or suspect, 2 when some are unusable.
    Run(run::RunArgs),
    /// Show where every stage of a session stands: current, stale (and which input changed),
    /// failed (and why) or not run.
    Status(run::StatusArgs),
    /// Run a session's episodes on a Slurm cluster: plan, write and submit the batch scripts,
    /// follow them, resubmit what is missing or failed.
    #[command(subcommand)]
    Batch(batch::BatchCommand),
    /// Place cameras on one timeline from their audio (fingerprints + GCC-PHAT + drift fit).
    ///
    /// Either name audio files (`--audio NAME=FILE`, the first is the reference) or run the
    /// stage on a prepared episode (`--session session.toml --episode NAME`), which writes
    /// `episodes/NAME/work/sync/sync.json` as `kiwi run` does. Output clocks follow
    /// `session_time = local_video_time * (1 + drift_ppm*1e-6) + offset_s`.
    Sync(sync::SyncArgs),
    /// Fuse a wrist's IMU with visual pose observations (robust IMU factor graph, one node per
    /// frame) and write `scene_from_front_cam` per node with marginal sigmas.
    ///
    /// Inputs: `imu.csv` (`t,gx,gy,gz,ax,ay,az`), `frames.csv` (first column `t`, camera clock),
    /// `obs.csv` (`t,source,px,py,pz,qx,qy,qz,qw`, `scene_from_imu` on the IMU clock, source
    /// front|rear). Output `traj.csv`: `t,px,py,pz,qx,qy,qz,qw,sigma_p,sigma_r,support`.
    /// Without `--calibration` the fusion runs in the IMU frame (`scene_from_imu`) and needs
    /// `--imu-noise`.
    Fuse(fuse::FuseArgs),
    /// Make a visual map metric and z-up: scale, gravity and IMU biases from the mapping
    /// episode's localizations and IMU (visual-inertial graph); writes metric.json.
    Metric(metric::MetricArgs),
    /// Place the front map in the scene (rear) map from synchronized front and rear
    /// localizations of the mapping episode (paper eq. 2); writes placement.json.
    Place(metric::PlaceArgs),
    /// Build a visual map (.kmap) from one lens of a mapping episode: KLT/ORB tracks,
    /// incremental mapping with bundle adjustment, keyframe descriptors, place recognition.
    Map(vision::MapArgs),
    /// Localize every frame of one lens of an episode against a frozen map and write
    /// poses.csv (`map_from_cam`; status tracked, relocalized or lost).
    Localize(vision::LocalizeArgs),
    /// Gripper opening per front-lens frame (chopstick angle in deg, parallel-jaw gap in px):
    /// opening.csv (`t,opening,unit,confidence,status`), opening.svg, tool.json.
    Gripper(gripper::GripperArgs),
    /// Check a session: session.toml, unit calibrations and every prepared episode's files.
    Inspect(inspect::InspectArgs),
    /// Turn cameras' own files into a prepared episode of a session: Insta360 X5/X4 .insv and
    /// GO 3 recordings (IMU, exposure and lens data from the file's metadata trailer), or any
    /// video plus an IMU CSV. Lenses are resized to the processing resolution and stored as a
    /// video (or PNGs); frame times come from the container, audio.wav starts at video time 0.
    Ingest(ingest::IngestArgs),
    /// Write a session's episodes as a dataset robot-learning tools load as they are: a
    /// LeRobot v3.0 dataset (parquet + mp4), UMI's dataset.zarr.zip, or KIWI's full-detail
    /// sidecar. Episodes whose verdict is unusable are left out with the reason.
    Export(export::ExportArgs),
    /// Draw a session's report page: one self-contained HTML file (charts inline, opens from
    /// disk) with each episode's tool-tip paths over the scene map, support per stream over
    /// time, the sync graph, gripper openings, the verdict with its reasons and the stage
    /// timings. `kiwi run` writes the same page as its last stage (SESSION/report/index.html).
    Report(report::ReportArgs),
    /// The paper's evaluations on a session after `kiwi run`: `ablation` (front-only
    /// cross-hand localization against KIWI's support, per episode and in total).
    #[command(subcommand)]
    Evaluate(evaluate::EvaluateCommand),
}

/// Split `NAME=VALUE`.
pub(crate) fn named(arg: &str, flag: &str) -> Result<(String, String)> {
    arg.split_once('=')
        .map(|(n, v)| (n.to_string(), v.to_string()))
        .ok_or_else(|| anyhow::anyhow!("{flag} {arg}: expected NAME=VALUE"))
}

/// The file or folder a command writes (a stage run through a session writes in the
/// episode's work folders): never inside a dated calibration set.
fn output(command: &Command) -> Option<&std::path::Path> {
    match command {
        Command::Fuse(a) => Some(&a.out),
        Command::Metric(a) => Some(&a.out),
        Command::Place(a) => Some(&a.out),
        Command::Map(a) => Some(&a.out),
        Command::Localize(a) => Some(&a.out),
        Command::Gripper(a) => a.out.as_deref(),
        Command::Ingest(a) => Some(&a.session),
        Command::Export(a) => Some(&a.out),
        Command::Report(a) => a.out.as_deref(),
        Command::Run(_)
        | Command::Evaluate(_)
        | Command::Status(_)
        | Command::Batch(_)
        | Command::Sync(_)
        | Command::Inspect(_) => None,
    }
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
    if let Some(out) = output(&cli.command) {
        kiwi_core::io::ensure_outside_dated_set(out)?;
    }
    match cli.command {
        Command::Run(args) => {
            let code = run::run_cmd(args)?;
            if code != 0 {
                std::process::exit(code);
            }
        }
        Command::Status(args) => run::status_cmd(&args)?,
        Command::Batch(command) => batch::run_batch_cmd(command)?,
        Command::Sync(args) => sync::run_sync_cmd(args)?,
        Command::Fuse(args) => fuse::run_fuse_cmd(args)?,
        Command::Metric(args) => metric::run_metric_cmd(&args)?,
        Command::Place(args) => metric::run_place_cmd(&args)?,
        Command::Map(args) => vision::run_map(&args)?,
        Command::Localize(args) => vision::run_localize(&args)?,
        Command::Gripper(args) => gripper::run_gripper(&args)?,
        Command::Inspect(args) => inspect::run_inspect_cmd(args)?,
        Command::Ingest(args) => ingest::run_ingest_cmd(&args)?,
        Command::Export(args) => export::run_export_cmd(&args)?,
        Command::Report(args) => report::run_report_cmd(&args)?,
        Command::Evaluate(command) => evaluate::run_evaluate_cmd(&command)?,
    }
    Ok(())
}
