//! `kiwi batch`: a session's episodes on a Slurm cluster (plan, scripts and submission,
//! status, resubmission of what is missing or failed).

use std::path::PathBuf;

use anyhow::{Result, bail};

use kiwi_backend::batch::{
    DEFAULT_CPUS, Plan, Progress, SlurmOptions, episode_states, plan, submit, to_resubmit,
    write_slurm_scripts,
};

/// `kiwi batch` subcommands.
#[derive(Debug, clap::Subcommand)]
pub enum BatchCommand {
    /// Plan a session: one job that builds the maps (a run of the map episode), one array task
    /// per other episode depending on it, one job for the session's datasets; resources per
    /// task from the recording's size.
    Plan(PlanArgs),
    /// Write the plan's Slurm batch scripts (and with --submit, submit them and print the job
    /// ids).
    Slurm(SlurmArgs),
    /// Where every episode of a plan stands: done (with its verdict), failed (with the
    /// episode's own error) or not run, and its job in the scheduler's queue.
    Status(StatusArgs),
    /// Submit again only the episodes whose outputs are missing or failed (and not queued).
    Resubmit(ResubmitArgs),
}

/// Arguments of `kiwi batch plan`.
#[derive(Debug, clap::Args)]
pub struct PlanArgs {
    /// The session's session.toml.
    #[arg(long)]
    pub session: PathBuf,
    /// Episodes to plan, comma-separated [default: all; the map episode always comes first].
    #[arg(long, value_delimiter = ',')]
    pub episodes: Option<Vec<String>>,
    /// Folder of the plan, its scripts and logs [default: SESSION/batch].
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// CPUs per task (and `kiwi run --threads`).
    #[arg(long, default_value_t = DEFAULT_CPUS)]
    pub cpus: u32,
    /// The kiwi program the tasks run, on storage the cluster's nodes share [default: this
    /// one].
    #[arg(long)]
    pub kiwi: Option<PathBuf>,
}

/// Slurm options shared by `slurm` and `resubmit`.
#[derive(Debug, clap::Args)]
pub struct SlurmFlags {
    /// Partition (queue) of every job [default: the cluster's].
    #[arg(long)]
    pub partition: Option<String>,
    /// Account to charge, where the cluster asks for one.
    #[arg(long)]
    pub account: Option<String>,
    /// Episodes running at once (the array's `%N` cap).
    #[arg(long)]
    pub max_parallel: Option<u32>,
}

impl SlurmFlags {
    fn options(&self) -> SlurmOptions {
        SlurmOptions {
            partition: self.partition.clone(),
            max_parallel: self.max_parallel,
            account: self.account.clone(),
        }
    }
}

/// Arguments of `kiwi batch slurm`.
#[derive(Debug, clap::Args)]
pub struct SlurmArgs {
    /// The plan (its plan.json or folder).
    #[arg(long)]
    pub plan: PathBuf,
    #[command(flatten)]
    pub flags: SlurmFlags,
    /// Submit the jobs with sbatch and print their ids.
    #[arg(long)]
    pub submit: bool,
}

/// Arguments of `kiwi batch status`.
#[derive(Debug, clap::Args)]
pub struct StatusArgs {
    /// The plan (its plan.json or folder).
    #[arg(long)]
    pub plan: PathBuf,
    /// Leave the scheduler out (stage states only, e.g. off the cluster).
    #[arg(long)]
    pub no_queue: bool,
    /// Print JSON.
    #[arg(long)]
    pub json: bool,
}

/// Arguments of `kiwi batch resubmit`.
#[derive(Debug, clap::Args)]
pub struct ResubmitArgs {
    /// The plan (its plan.json or folder).
    #[arg(long)]
    pub plan: PathBuf,
    #[command(flatten)]
    pub flags: SlurmFlags,
    /// Only print what would be submitted.
    #[arg(long)]
    pub dry_run: bool,
}

/// Run `kiwi batch`.
pub fn run_batch_cmd(command: BatchCommand) -> Result<()> {
    match command {
        BatchCommand::Plan(a) => {
            let kiwi = match a.kiwi {
                Some(k) => k,
                None => std::env::current_exe()?,
            };
            let p = plan(&a.session, a.episodes.as_deref(), &kiwi, a.cpus)?;
            let dir = match a.out {
                Some(d) => d,
                None => p
                    .session
                    .parent()
                    .map_or_else(|| PathBuf::from("batch"), |r| r.join("batch")),
            };
            let path = p.write(&dir)?;
            println!("plan: {}", path.display());
            let line = |name: &str, r: &kiwi_backend::batch::PlannedRun| {
                println!(
                    "  {name:<14} {:>7.1} s of recording, {:>6} frames: {} CPUs, {} MB, {} min",
                    r.duration_s,
                    r.frames,
                    r.resources.cpus,
                    r.resources.memory_mb,
                    r.resources.time_limit_s / 60
                );
            };
            line(
                &format!("maps ({})", p.maps.episode.as_deref().unwrap_or("")),
                &p.maps,
            );
            for t in &p.episodes {
                line(t.episode.as_deref().unwrap_or(""), t);
            }
            if p.finish.is_some() {
                println!("  then the session's datasets, after every episode");
            }
            println!(
                "next: kiwi batch slurm --plan {} [--partition P] --submit",
                dir.display()
            );
        }
        BatchCommand::Slurm(a) => {
            let (p, dir) = Plan::read(&a.plan)?;
            let opts = a.flags.options();
            if a.submit {
                let episodes = p.task_episodes();
                let s = submit(&p, &dir, &opts, &episodes, true)?;
                println!("submitted:");
                if let Some(m) = &s.maps {
                    println!("  maps      job {m}");
                }
                if let Some(x) = &s.array {
                    println!("  episodes  array job {x} ({} tasks)", s.tasks.len());
                }
                if let Some(d) = &s.datasets {
                    println!("  datasets  job {d}");
                }
                println!("follow with: kiwi batch status --plan {}", dir.display());
            } else {
                for (name, path) in write_slurm_scripts(&p, &dir, &opts)? {
                    println!("{name}: {}", path.display());
                }
                println!("submit with --submit (maps first, the array with --dependency=afterok)");
            }
        }
        BatchCommand::Status(a) => {
            let (p, dir) = Plan::read(&a.plan)?;
            let states = episode_states(&p, &dir, !a.no_queue)?;
            if a.json {
                println!("{}", serde_json::to_string_pretty(&states)?);
                return Ok(());
            }
            for s in &states {
                let queue = match (&s.job, &s.queue) {
                    (Some(j), Some(q)) => format!("job {j} {q}"),
                    (Some(j), None) => format!("job {j} ended"),
                    _ => "not submitted".into(),
                };
                let verdict = s.verdict.as_deref().unwrap_or("");
                println!(
                    "{:<12} {:<8} {verdict:<9} {queue}",
                    s.episode,
                    s.state.as_str()
                );
                if !s.detail.is_empty() {
                    println!("{:<12}   {}", "", s.detail);
                }
            }
            let done = states.iter().filter(|s| s.state == Progress::Done).count();
            let failed = states
                .iter()
                .filter(|s| s.state == Progress::Failed)
                .count();
            println!("{done} of {} episodes done, {failed} failed", states.len());
        }
        BatchCommand::Resubmit(a) => {
            let (p, dir) = Plan::read(&a.plan)?;
            let states = episode_states(&p, &dir, true)?;
            let mut episodes = to_resubmit(&states);
            let maps_episode = p.maps.episode.clone().unwrap_or_default();
            let with_maps = episodes.contains(&maps_episode);
            episodes.retain(|e| e != &maps_episode);
            if episodes.is_empty() && !with_maps {
                println!("nothing to resubmit: every episode is done or in the queue");
                return Ok(());
            }
            if a.dry_run {
                if with_maps {
                    println!("would submit the maps job ({maps_episode})");
                }
                println!("would submit: {}", episodes.join(", "));
                return Ok(());
            }
            if !with_maps
                && states
                    .iter()
                    .any(|s| s.episode == maps_episode && s.queue.is_some())
            {
                bail!(
                    "the maps job of {maps_episode} is still in the queue; resubmit after it \
                     ends (`kiwi batch status --plan {}`)",
                    dir.display()
                );
            }
            let s = submit(&p, &dir, &a.flags.options(), &episodes, with_maps)?;
            if let Some(m) = &s.maps {
                println!("maps      job {m}");
            }
            if let Some(x) = &s.array {
                println!(
                    "episodes  array job {x}: {}",
                    s.tasks.values().cloned().collect::<Vec<_>>().join(", ")
                );
            }
            if let Some(d) = &s.datasets {
                println!("datasets  job {d}");
            }
        }
    }
    Ok(())
}
