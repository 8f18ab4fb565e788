//! `kiwi evaluate`: the paper's evaluations on a lab's own session (§5).

use std::path::PathBuf;

use anyhow::{Result, bail};
use indicatif::{ProgressBar, ProgressStyle};

use kiwi_backend::evaluate::EVALUATION_DIR;
use kiwi_backend::evaluate::ablation::{ABLATION_FILE, ablation, table};
use kiwi_backend::pipeline::SessionContext;

/// The evaluations.
#[derive(Debug, clap::Subcommand)]
pub enum EvaluateCommand {
    /// The map-sharing ablation (the paper's tab:eval-map-sharing): on the right wrist's front
    /// frames of each episode, the share supported by front-only cross-hand localization (the
    /// right front lens in the left front map) against the share KIWI's outputs support.
    /// Writes SESSION/evaluation/ablation.json.
    Ablation(AblationArgs),
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
    }
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
