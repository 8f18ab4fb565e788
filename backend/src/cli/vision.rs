//! `kiwi map` and `kiwi localize`: command-line front of `kiwi_backend::vision::episode`.

use std::path::PathBuf;

use anyhow::{Context, Result};
use indicatif::{ProgressBar, ProgressStyle};

use kiwi_backend::vision::episode::{LensStream, build_map_with, localize_stream, write_poses_csv};
use kiwi_backend::vision::localize::LocalizerOptions;
use kiwi_backend::vision::map::VisualMap;

/// Lens of a wrist X5 unit (or `main` for the head camera).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum LensArg {
    /// The front lens (faces the tool).
    Front,
    /// The rear lens (faces the room behind the hand).
    Rear,
    /// The single lens of a GO 3 head camera.
    Main,
}

impl LensArg {
    fn name(self) -> &'static str {
        match self {
            Self::Front => "front",
            Self::Rear => "rear",
            Self::Main => "main",
        }
    }
}

/// Arguments of `kiwi map`.
#[derive(Debug, clap::Args)]
pub struct MapArgs {
    /// The prepared mapping episode folder (`<session>/episodes/<name>`).
    #[arg(long)]
    pub episode: PathBuf,
    /// The lens whose frames build the map.
    #[arg(long, value_enum)]
    pub lens: LensArg,
    /// The camera folder (`left`, `right`, `head`).
    #[arg(long)]
    pub camera: String,
    /// The unit's calibration.json [default: found through the session.toml two folders up].
    #[arg(long)]
    pub calibration: Option<PathBuf>,
    /// A static mask image of the lens (non-zero pixels may hold features: hide tool, hand and
    /// camera body).
    #[arg(long)]
    pub mask: Option<PathBuf>,
    /// Output map file (.kmap).
    #[arg(long)]
    pub out: PathBuf,
    /// Do not close loops. By default loops are closed before the map is written (place
    /// recognition, verification, Sim(3) pose graph, landmark fusion, global BA; docs/vision.md).
    #[arg(long)]
    pub no_loop_closure: bool,
    /// Close loops: the default since session 9, kept so that older scripts still run.
    #[arg(long, hide = true, conflicts_with = "no_loop_closure")]
    pub loop_closure: bool,
    /// Print a JSON summary.
    #[arg(long)]
    pub json: bool,
}

/// Arguments of `kiwi localize`.
#[derive(Debug, clap::Args)]
pub struct LocalizeArgs {
    /// The frozen map (.kmap) built by `kiwi map`.
    #[arg(long)]
    pub map: PathBuf,
    /// The prepared episode folder to localize.
    #[arg(long)]
    pub episode: PathBuf,
    /// The lens to localize (must be the map's lens).
    #[arg(long, value_enum)]
    pub lens: LensArg,
    /// The camera folder (`left`, `right`, `head`).
    #[arg(long)]
    pub camera: String,
    /// The unit's calibration.json [default: found through the session.toml two folders up].
    #[arg(long)]
    pub calibration: Option<PathBuf>,
    /// A static mask image of the lens (non-zero pixels may hold features).
    #[arg(long)]
    pub mask: Option<PathBuf>,
    /// Output poses.csv (`t,status,px,py,pz,qx,qy,qz,qw,inliers,reason`, `map_from_cam`).
    #[arg(long)]
    pub out: PathBuf,
    /// Threads for image decoding [default: all cores]; results are identical for any count.
    #[arg(long)]
    pub threads: Option<usize>,
    /// Print a JSON summary.
    #[arg(long)]
    pub json: bool,
}

fn bar(total: usize, quiet: bool, what: &str) -> ProgressBar {
    let bar = if quiet {
        ProgressBar::hidden()
    } else {
        ProgressBar::new(total as u64)
    };
    bar.set_style(
        ProgressStyle::with_template(
            "{msg:>10} [{bar:40}] {pos}/{len} frames ({per_sec}, eta {eta})",
        )
        .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    bar.set_message(what.to_string());
    bar
}

/// Run `kiwi map`.
pub fn run_map(a: &MapArgs) -> Result<()> {
    let stream = LensStream::open(
        &a.episode,
        &a.camera,
        a.lens.name(),
        a.calibration.as_deref(),
        a.mask.as_deref(),
    )?;
    let pb = bar(stream.frames.len(), a.json, "tracking");
    let (map, summary) = build_map_with(&stream, !a.no_loop_closure, &mut |done, _| {
        pb.set_position(done as u64);
    })
    .with_context(|| format!("mapping {}", a.episode.display()))?;
    pb.finish_and_clear();
    map.save(&a.out)?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&summary)?);
    } else {
        println!(
            "map {}: {} keyframes, {} landmarks from {} of {} frames{} in {:.1} s",
            a.out.display(),
            summary.keyframes,
            summary.landmarks,
            summary.frames_tracked,
            summary.frames,
            summary
                .lost_at
                .map_or_else(String::new, |f| format!(" (tracking lost at frame {f})")),
            summary.seconds
        );
        let q = &summary.quality;
        if q.trustworthy {
            println!("quality: {q}");
        } else {
            println!("quality: no pose will be localized in this map: {q}");
        }
    }
    Ok(())
}

/// Run `kiwi localize`.
pub fn run_localize(a: &LocalizeArgs) -> Result<()> {
    let map = VisualMap::load(&a.map)?;
    let stream = LensStream::open(
        &a.episode,
        &a.camera,
        a.lens.name(),
        a.calibration.as_deref(),
        a.mask.as_deref(),
    )?;
    let pb = bar(stream.frames.len(), a.json, "localizing");
    let options = LocalizerOptions::default();
    let run = || {
        localize_stream(&map, &stream, &options, &mut |done, _| {
            pb.set_position(done as u64);
        })
    };
    let (results, summary) = match a.threads {
        Some(n) => rayon::ThreadPoolBuilder::new()
            .num_threads(n.max(1))
            .build()
            .context("--threads: cannot start the thread pool")?
            .install(run),
        None => run(),
    }
    .with_context(|| format!("localizing {}", a.episode.display()))?;
    pb.finish_and_clear();
    write_poses_csv(&a.out, &results)?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&summary)?);
    } else {
        println!(
            "poses {}: {} of {} frames localized ({:.2} %: {} tracked, {} relocalized), median \
             {} inliers, {:.1} s ({:.1} frames/s)",
            a.out.display(),
            summary.localized,
            summary.frames,
            100.0 * summary.localized_fraction,
            summary.tracked,
            summary.relocalized,
            summary.median_inliers,
            summary.seconds,
            summary.frames_per_second
        );
    }
    Ok(())
}
