//! `kiwi run` and `kiwi status`: the main job, and where it stands.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::Mutex;

use anyhow::Result;
use indicatif::{MultiProgress, ProgressBar, ProgressDrawTarget, ProgressStyle};

use kiwi_backend::pipeline::SessionContext;
use kiwi_backend::pipeline::runner::{Outcome, Progress, RunOptions, run};
use kiwi_backend::pipeline::stage::StageId;
use kiwi_backend::pipeline::status::status;
use kiwi_backend::quality::Verdict;

/// Arguments of `kiwi run`.
#[derive(Debug, clap::Args)]
pub struct RunArgs {
    /// The session's session.toml.
    #[arg(long)]
    pub session: PathBuf,
    /// Episodes to process, comma-separated [default: all].
    #[arg(long, value_delimiter = ',')]
    pub episodes: Option<Vec<String>>,
    /// Re-run this stage and every stage after it: a family (sync, map, tool, localize,
    /// metric, placement, observations, fusion, gripper, head, floor, outputs, export,
    /// report), a stage as `kiwi status` lists it (`localize-left-front`) or one episode's
    /// (`ep001/localize-left-front`).
    #[arg(long, value_name = "STAGE")]
    pub from: Option<String>,
    /// Re-run these stages even if their inputs are unchanged (`all` for every stage; names as
    /// for --from).
    #[arg(long, value_name = "STAGE|all", value_delimiter = ',')]
    pub force: Vec<String>,
    /// Run only these stages; what they read must be current.
    #[arg(long, value_name = "STAGE", value_delimiter = ',', hide = true)]
    pub only: Option<Vec<String>>,
    /// Worker threads [default: the machine's cores]. Results do not depend on it.
    #[arg(long)]
    pub threads: Option<usize>,
    /// Print the report as JSON (and no progress display).
    #[arg(long)]
    pub json: bool,
}

/// Arguments of `kiwi status`.
#[derive(Debug, clap::Args)]
pub struct StatusArgs {
    /// The session's session.toml.
    #[arg(long)]
    pub session: PathBuf,
    /// Episodes to show, comma-separated [default: all].
    #[arg(long, value_delimiter = ',')]
    pub episodes: Option<Vec<String>>,
    /// Print JSON.
    #[arg(long)]
    pub json: bool,
}

/// A terminal display: one line per running stage and one for the whole run.
struct Display {
    multi: MultiProgress,
    total: ProgressBar,
    bars: Mutex<BTreeMap<StageId, ProgressBar>>,
}

impl Display {
    fn new(quiet: bool) -> Self {
        let multi = MultiProgress::with_draw_target(if quiet {
            ProgressDrawTarget::hidden()
        } else {
            ProgressDrawTarget::stderr()
        });
        let total = multi.add(ProgressBar::new_spinner());
        total.set_style(
            ProgressStyle::with_template("{spinner} {elapsed_precise} {msg}")
                .unwrap_or_else(|_| ProgressStyle::default_spinner()),
        );
        total.enable_steady_tick(std::time::Duration::from_millis(200));
        Self {
            multi,
            total,
            bars: Mutex::new(BTreeMap::new()),
        }
    }
}

impl Progress for Display {
    fn start(&self, stage: &StageId) {
        let bar = self.multi.add(ProgressBar::new(0));
        bar.set_style(
            ProgressStyle::with_template(
                "{prefix:>32} [{bar:30}] {pos}/{len} ({per_sec}, eta {eta})",
            )
            .unwrap_or_else(|_| ProgressStyle::default_bar())
            .progress_chars("=> "),
        );
        bar.set_prefix(stage.label());
        if let Ok(mut bars) = self.bars.lock() {
            bars.insert(stage.clone(), bar);
        }
    }

    fn update(&self, stage: &StageId, done: usize, total: usize) {
        if let Ok(bars) = self.bars.lock()
            && let Some(bar) = bars.get(stage)
        {
            bar.set_length(total as u64);
            bar.set_position(done as u64);
        }
    }

    fn finish(&self, stage: &StageId, outcome: &Outcome) {
        if let Ok(mut bars) = self.bars.lock()
            && let Some(bar) = bars.remove(stage)
        {
            bar.finish_and_clear();
            self.multi.remove(&bar);
        }
        let line = match outcome {
            Outcome::Ran { seconds } => format!("{:>32}  done in {seconds:.1} s", stage.label()),
            Outcome::Failed { reason } => format!("{:>32}  FAILED: {reason}", stage.label()),
            _ => return,
        };
        let _ = self.multi.println(line);
        self.total.set_message(format!("last: {}", stage.label()));
    }
}

/// Run `kiwi run`. Exit status: 0 when every episode is usable or suspect, 2 when some
/// episodes are unusable (the others finished), and 1 on an error that stops the run.
pub fn run_cmd(args: RunArgs) -> Result<i32> {
    let ctx = SessionContext::load(&args.session)?;
    let display = Display::new(args.json);
    let report = run(
        &ctx,
        &RunOptions {
            episodes: args.episodes,
            from: args.from,
            force: args.force,
            only: args.only,
            threads: args.threads,
        },
        &display,
    )?;
    display.total.finish_and_clear();
    if args.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        let counts: Vec<String> = report
            .counts
            .iter()
            .map(|(k, v)| format!("{v} {k}"))
            .collect();
        println!(
            "session {}: stages {} in {:.1} s",
            ctx.session.name,
            counts.join(", "),
            report.seconds
        );
        for e in &report.episodes {
            println!(
                "  {:<12} {:<9} {}",
                e.episode,
                e.verdict.as_str(),
                e.out.display()
            );
            for r in &e.reasons {
                println!("  {:<12}   - {r}", "");
            }
        }
        let page = ctx
            .root
            .join(kiwi_backend::report::REPORT_DIR)
            .join(kiwi_backend::report::PAGE_FILE);
        if report.stages.iter().any(|s| {
            s.stage == "session/report"
                && matches!(s.outcome, Outcome::Ran { .. } | Outcome::Current)
        }) {
            println!("report: {}", page.display());
        }
        let failed = report.failed_episodes();
        println!(
            "{} of {} episodes usable, {} suspect, {failed} unusable",
            report
                .episodes
                .iter()
                .filter(|e| e.verdict == Verdict::Usable)
                .count(),
            report.episodes.len(),
            report
                .episodes
                .iter()
                .filter(|e| e.verdict == Verdict::Suspect)
                .count(),
        );
    }
    Ok(if report.failed_episodes() > 0 { 2 } else { 0 })
}

/// Run `kiwi status`.
pub fn status_cmd(args: &StatusArgs) -> Result<()> {
    let ctx = SessionContext::load(&args.session)?;
    let rows = status(&ctx, args.episodes.as_deref())?;
    if args.json {
        println!("{}", serde_json::to_string_pretty(&rows)?);
        return Ok(());
    }
    let mut scope = String::new();
    for r in &rows {
        if r.scope != scope {
            println!("{}", r.scope);
            scope.clone_from(&r.scope);
        }
        let time = r.seconds.map(|s| format!("{s:.1} s")).unwrap_or_default();
        let detail = if r.detail.is_empty() {
            String::new()
        } else {
            format!("  {}", r.detail)
        };
        println!("  {:<24} {:<8} {time:>9}{detail}", r.stage, r.state);
    }
    Ok(())
}
