//! `kiwi evaluate`: the paper's evaluations on a lab's own session (§5).

use std::path::PathBuf;

use anyhow::{Result, bail};
use indicatif::{ProgressBar, ProgressStyle};

use kiwi_backend::evaluate::EVALUATION_DIR;
use kiwi_backend::evaluate::ablation::{ABLATION_FILE, ablation, table};
use kiwi_backend::evaluate::markers::{
    AlignmentKind, MarkerPair, PAPER_MARKER_SIZE_M, errors_csv, evaluate_markers, evaluation_files,
    table as markers_table,
};
use kiwi_backend::pipeline::SessionContext;

/// The evaluations.
#[derive(Debug, clap::Subcommand)]
pub enum EvaluateCommand {
    /// The map-sharing ablation (the paper's tab:eval-map-sharing): on the right wrist's front
    /// frames of each episode, the share supported by front-only cross-hand localization (the
    /// right front lens in the left front map) against the share KIWI's outputs support.
    /// Writes SESSION/evaluation/ablation.json.
    Ablation(AblationArgs),
    /// The marker-referenced pose accuracy (the paper's §5): two fixed ArUco markers in the
    /// workspace give each wrist's front lens eight-corner reference poses; their arrangement
    /// is fitted on the first 40 % of the episode, a fixed-scale rigid alignment too, and after a
    /// 10 % gap the median translation error over the last 50 % is reported, per hand with its
    /// own alignment and with the left-fitted one. Writes
    /// SESSION/evaluation/markers-EPISODE.json and the scored frames' errors beside it (.csv).
    Markers(MarkersArgs),
}

/// Arguments of `kiwi evaluate markers`.
#[derive(Debug, clap::Args)]
pub struct MarkersArgs {
    /// The session's session.toml (after `kiwi run`).
    #[arg(long)]
    pub session: PathBuf,
    /// The episode.
    #[arg(long)]
    pub episode: String,
    /// The two markers' ArUco ids, the reference marker first.
    #[arg(long, value_delimiter = ',', num_args = 1, default_values_t = [20, 21])]
    pub ids: Vec<usize>,
    /// Their ArUco dictionary.
    #[arg(long, default_value = "4x4_50")]
    pub dictionary: String,
    /// Their black square's side (mm), as printed and measured.
    #[arg(long, default_value_t = PAPER_MARKER_SIZE_M * 1e3, allow_negative_numbers = true)]
    pub size_mm: f64,
    /// Fit the rigid alignments on camera positions (trajectory ATE's usual alignment) or on
    /// whole poses (the rotation from the orientations: steadier when the first 40 % of the
    /// episode spans little space, and for the left-fitted alignment applied to the right hand).
    #[arg(long, value_enum, default_value = "positions")]
    pub align: AlignArg,
    /// Print the record as JSON instead of the table.
    #[arg(long)]
    pub json: bool,
}

/// `--align`.
#[derive(Debug, Clone, Copy, clap::ValueEnum)]
pub enum AlignArg {
    /// On camera positions.
    Positions,
    /// On whole poses.
    Poses,
}

/// Arguments of `kiwi evaluate ablation`.
#[derive(Debug, clap::Args)]
pub struct AblationArgs {
    /// The session's session.toml (after `kiwi run`).
    #[arg(long)]
    pub session: PathBuf,
    /// Episodes, comma-separated [default: all].
    #[arg(long, value_delimiter = ',')]
    pub episodes: Option<Vec<String>>,
    /// Print the record as JSON instead of the table.
    #[arg(long)]
    pub json: bool,
}

/// Run `kiwi evaluate …`.
pub fn run_evaluate_cmd(command: &EvaluateCommand) -> Result<()> {
    match command {
        EvaluateCommand::Ablation(args) => run_ablation(args),
        EvaluateCommand::Markers(args) => run_markers(args),
    }
}

fn run_markers(args: &MarkersArgs) -> Result<()> {
    let ctx = SessionContext::load(&args.session)?;
    let all = ctx.episode_names();
    if !all.contains(&args.episode) {
        bail!(
            "{}: no episode `{}` (the session has {})",
            args.session.display(),
            args.episode,
            all.join(", ")
        );
    }
    let [a, b] = args.ids[..] else {
        bail!(
            "--ids takes the two markers' ids, e.g. `--ids 20,21`; got {} ids",
            args.ids.len()
        );
    };
    if !(args.size_mm.is_finite() && args.size_mm > 0.0) {
        bail!(
            "--size-mm is the markers' black-square side in millimetres, e.g. 58; got {}",
            args.size_mm
        );
    }
    let pair = MarkerPair {
        dictionary: args.dictionary.clone(),
        ids: [a, b],
        size_m: args.size_mm * 1e-3,
    };
    let bar = ProgressBar::new(0);
    bar.set_style(
        ProgressStyle::with_template("{msg:>24} [{bar:30}] {pos}/{len} frames {eta}")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let kind = match args.align {
        AlignArg::Positions => AlignmentKind::Positions,
        AlignArg::Poses => AlignmentKind::Poses,
    };
    let evaluation = evaluate_markers(&ctx, &args.episode, &pair, kind, &|camera, done, total| {
        bar.set_message(format!("{camera} front: markers"));
        bar.set_length(total as u64);
        bar.set_position(done as u64);
    })?;
    bar.finish_and_clear();
    let dir = ctx.root.join(EVALUATION_DIR);
    let (json_name, csv_name) = evaluation_files(&args.episode);
    let (json_path, csv_path) = (dir.join(json_name), dir.join(csv_name));
    kiwi_core::io::ensure_outside_dated_set(&json_path)?;
    let text = serde_json::to_string_pretty(&evaluation)?;
    std::fs::create_dir_all(&dir)?;
    kiwi_core::io::write_atomic(&csv_path, errors_csv(&evaluation).as_bytes())?;
    kiwi_core::io::write_atomic(&json_path, text.as_bytes())?;
    if args.json {
        println!("{text}");
    } else {
        print!("{}", markers_table(&evaluation));
        println!("wrote {} and {}", json_path.display(), csv_path.display());
    }
    if evaluation.wrists.is_empty() {
        bail!(
            "no wrist could be scored: {}",
            evaluation
                .skipped
                .iter()
                .map(|(c, why)| format!("{c}: {why}"))
                .collect::<Vec<_>>()
                .join("; ")
        );
    }
    Ok(())
}

fn run_ablation(args: &AblationArgs) -> Result<()> {
    let ctx = SessionContext::load(&args.session)?;
    let all = ctx.episode_names();
    let episodes = match &args.episodes {
        Some(list) => {
            for e in list {
                if !all.contains(e) {
                    bail!(
                        "{}: no episode `{e}` (the session has {})",
                        args.session.display(),
                        all.join(", ")
                    );
                }
            }
            list.clone()
        }
        None => all,
    };
    let bar = ProgressBar::new(0);
    bar.set_style(
        ProgressStyle::with_template("{msg:>24} [{bar:30}] {pos}/{len} frames {eta}")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let report = ablation(&ctx, &episodes, &mut |episode, done, total| {
        bar.set_message(format!("{episode}: right front"));
        bar.set_length(total as u64);
        bar.set_position(done as u64);
    })?;
    bar.finish_and_clear();
    let path = ctx.root.join(EVALUATION_DIR).join(ABLATION_FILE);
    kiwi_core::io::ensure_outside_dated_set(&path)?;
    let text = serde_json::to_string_pretty(&report)?;
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir)?;
    }
    kiwi_core::io::write_atomic(&path, text.as_bytes())?;
    if args.json {
        println!("{text}");
    } else {
        print!("{}", table(&report));
        println!("wrote {}", path.display());
    }
    Ok(())
}
