//! Scale-out on a cluster (`kiwi batch`): a session's plan — one job that builds the maps (a
//! run of the map episode), then one array task per other episode that depends on it, then one
//! job that writes the session's datasets — the Slurm batch scripts for it, and where each
//! episode stands (the scheduler's queue and the episode's own stage states).
//!
//! KIWI does not schedule: each task is `kiwi run --session … --episodes <one>`, which writes
//! only inside its episode folder once the maps are current, resumes from its finished stages
//! when the scheduler killed it, and changes nothing when it runs twice. The same plan runs
//! with GNU parallel or a plain loop (see docs/batch.md).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;

use serde::{Deserialize, Serialize};

use kiwi_core::layout::EpisodeLayout;

use crate::error::{BackendError, Result};
use crate::frames::FrameSource;
use crate::pipeline::SessionContext;
use crate::pipeline::graph::AFTER_EPISODE_FAMILIES;
use crate::pipeline::status::status;

/// Version of `plan.json`.
pub const PLAN_SCHEMA_VERSION: u32 = 1;
/// The plan's file in its folder.
pub const PLAN_FILE: &str = "plan.json";
/// The submitted jobs' ids, in the plan's folder.
pub const JOBS_FILE: &str = "jobs.json";
/// Batch scripts and the scheduler's logs live in these sub-folders of the plan's folder.
pub const SCRIPTS_DIR: &str = "slurm";
/// The tasks' own logs.
pub const LOGS_DIR: &str = "logs";

// The cost model below was measured with `kiwi run --threads 2` on simulated sessions (a 15 s
// survey map episode, a 6 s tabletop and a 6 s walk, at 320 and 480 px, 29.97 Hz; docs/batch.md
// has the figures): CPU time grows with the frame count and only a little with the pixels (the
// trackers keep a bounded number of features per frame).

/// CPU time per lens frame of an episode (s): the walk's 0.026-0.027 s, the most of the
/// measured episodes, rounded up.
const CPU_S_PER_FRAME: f64 = 0.03;
/// Extra CPU time per lens frame per megapixel of that frame (s): the map episode's growth
/// from 320 to 480 px (0.045 to 0.052 s per frame), rounded up.
const CPU_S_PER_FRAME_MEGAPIXEL: f64 = 0.06;
/// The maps job costs this many times an episode of its size (mapping, the reversed check and
/// the metric recovery come on top of localization): 1.7-2.0 times the walk per frame.
const MAPS_COST_FACTOR: f64 = 2.0;
/// Resident memory of a run before its frames' size counts (MB): the measured peaks'
/// intercept at zero frame size, 166 MB (episodes) to 209 MB (maps), rounded up.
const BASE_MEMORY_MB: f64 = 200.0;
/// Resident memory per megapixel of one lens frame (MB) with two worker threads: the maps
/// job's peak grew 508 MB per megapixel from 320 to 480 px (episodes: 172), rounded up.
const MEMORY_MB_PER_FRAME_MEGAPIXEL: f64 = 600.0;
/// Memory requests are this many times the estimate: a task over its request is killed, and
/// maps of long recordings hold more keyframes than the measured 15 s.
const MEMORY_SAFETY: f64 = 1.5;
/// Time limits are this many times the estimate: a scheduler kills a task at its limit, and a
/// killed task only resumes from its finished stages.
const TIME_SAFETY: f64 = 4.0;
/// Wall time of the datasets job per second of recording over all episodes (s): the export
/// bench's LeRobot, UMI and sidecar exports together (22.6 + 14.3 + 0.15 s per minute of two
/// wrists at 480 px), rounded up.
const DATASETS_S_PER_RECORDED_S: f64 = 0.7;
/// Memory of the datasets job (MB): an export holds one decoded frame per view and one
/// episode's rows at a time.
const DATASETS_MEMORY_MB: u64 = 1000;
/// No time limit is shorter (s): start-up, reading calibrations, a queue's clock granularity.
const MIN_TIME_LIMIT_S: f64 = 600.0;
/// Worker threads per task: the setting the cost model was measured with.
pub const DEFAULT_CPUS: u32 = 2;

fn batch_err(message: String) -> BackendError {
    BackendError::Batch(message)
}

/// What one job or task needs from the scheduler.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Resources {
    /// CPUs (`--cpus-per-task`, and `kiwi run --threads`).
    pub cpus: u32,
    /// Memory (MB, `--mem`).
    pub memory_mb: u64,
    /// Time limit (s, `--time`).
    pub time_limit_s: u64,
}

impl Resources {
    /// Enough for either run.
    pub fn max(&self, other: &Resources) -> Resources {
        Resources {
            cpus: self.cpus.max(other.cpus),
            memory_mb: self.memory_mb.max(other.memory_mb),
            time_limit_s: self.time_limit_s.max(other.time_limit_s),
        }
    }
}

/// One job of the plan: a run of one episode (or of the whole session for the datasets).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PlannedRun {
    /// The episode (`None`: the whole session, after every episode).
    pub episode: Option<String>,
    /// Recording length (s): the longest lens stream of the episode.
    pub duration_s: f64,
    /// Lens frames over every stream the pipeline reads.
    pub frames: usize,
    /// Their pixels (millions).
    pub megapixels: f64,
    /// What it asks the scheduler for.
    pub resources: Resources,
}

/// A session's plan (`plan.json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Plan {
    /// [`PLAN_SCHEMA_VERSION`].
    pub schema_version: u32,
    /// The session's `session.toml` (absolute).
    pub session: PathBuf,
    /// The `kiwi` program the tasks run (absolute; on shared storage on a cluster).
    pub kiwi: PathBuf,
    /// The map episode's run: builds the session's maps (and that episode's outputs).
    pub maps: PlannedRun,
    /// One task per other episode, in array order; each depends on `maps`.
    pub episodes: Vec<PlannedRun>,
    /// A run of every episode after the tasks: the session's datasets (only when the plan
    /// holds every episode of the session).
    pub finish: Option<PlannedRun>,
}

/// Resources for a run over `frames` lens frames of `frame_megapixels` each.
fn resources(frames: usize, frame_megapixels: f64, cost_factor: f64, cpus: u32) -> Resources {
    let per_frame = CPU_S_PER_FRAME + CPU_S_PER_FRAME_MEGAPIXEL * frame_megapixels;
    let cpu_s = frames as f64 * per_frame * cost_factor;
    let threads = f64::from(cpus.max(1)) / 2.0;
    let memory = (BASE_MEMORY_MB
        + MEMORY_MB_PER_FRAME_MEGAPIXEL * frame_megapixels * threads.max(1.0))
        * MEMORY_SAFETY;
    Resources {
        cpus,
        memory_mb: memory.ceil() as u64,
        time_limit_s: time_limit(cpu_s / f64::from(cpus.max(1))),
    }
}

/// A time limit for a run estimated at `wall_s`: with the margin, at least the floor, in whole
/// minutes.
fn time_limit(wall_s: f64) -> u64 {
    let limit = (wall_s * TIME_SAFETY).max(MIN_TIME_LIMIT_S);
    (limit / 60.0).ceil() as u64 * 60
}

/// An episode's run: its wrist streams' length, lens frames and their pixels, and what that
/// asks of the scheduler (`cost_factor` times an episode's cost per frame).
fn planned(ctx: &SessionContext, episode: &str, cost_factor: f64, cpus: u32) -> Result<PlannedRun> {
    let layout = EpisodeLayout::new(ctx.session.episode_dir(&ctx.root, episode));
    let (mut duration_s, mut frames, mut megapixels) = (0.0f64, 0usize, 0.0f64);
    for wrist in ctx.wrists.values() {
        for lens in ["front", "rear"] {
            let source = FrameSource::open(&layout.lens_dir(wrist.camera, lens))?;
            // The lens' calibrated image size (the pipeline holds frames to it): a plan must not
            // depend on the first frame being readable — a corrupt one is the task's error.
            let (w, h) = match wrist.calibration.lenses.iter().find(|l| l.name == lens) {
                Some(l) => (l.resolution[0], l.resolution[1]),
                None => source.resolution()?,
            };
            let records = source.frames();
            if let (Some(a), Some(b)) = (records.first(), records.last()) {
                duration_s = duration_s.max(b.t - a.t);
            }
            frames += records.len();
            megapixels += records.len() as f64 * f64::from(w) * f64::from(h) / 1e6;
        }
    }
    let frame_megapixels = if frames > 0 {
        megapixels / frames as f64
    } else {
        0.0
    };
    Ok(PlannedRun {
        episode: Some(episode.to_string()),
        duration_s,
        frames,
        megapixels,
        resources: resources(frames, frame_megapixels, cost_factor, cpus),
    })
}

/// `path` made absolute (the plan runs on other machines, from other folders).
fn absolute(path: &Path) -> Result<PathBuf> {
    std::path::absolute(path).map_err(|e| {
        batch_err(format!(
            "{}: cannot make the path absolute ({e})",
            path.display()
        ))
    })
}

/// Plan a session: the map episode's run, then the `episodes` given (all when `None`), then the
/// datasets when every episode is in the plan. `kiwi` is the program the tasks run.
pub fn plan(
    session_toml: &Path,
    episodes: Option<&[String]>,
    kiwi: &Path,
    cpus: u32,
) -> Result<Plan> {
    let session = absolute(session_toml)?;
    let ctx = SessionContext::load(&session)?;
    let map_episode = ctx.session.map_episode.clone();
    let selected = crate::pipeline::runner::selected_episodes(&ctx, episodes)?;
    let maps = planned(&ctx, &map_episode, MAPS_COST_FACTOR, cpus)?;
    let mut tasks = Vec::new();
    for name in &selected {
        if name != &map_episode {
            tasks.push(planned(&ctx, name, 1.0, cpus)?);
        }
    }
    let every = ctx
        .session
        .episodes
        .iter()
        .all(|e| selected.contains(&e.name));
    let recorded: f64 = std::iter::once(&maps)
        .chain(&tasks)
        .map(|t| t.duration_s)
        .sum();
    let finish = every.then(|| PlannedRun {
        episode: None,
        duration_s: recorded,
        frames: 0,
        megapixels: 0.0,
        resources: Resources {
            cpus,
            memory_mb: DATASETS_MEMORY_MB,
            time_limit_s: time_limit(recorded * DATASETS_S_PER_RECORDED_S),
        },
    });
    Ok(Plan {
        schema_version: PLAN_SCHEMA_VERSION,
        session,
        kiwi: absolute(kiwi)?,
        maps,
        episodes: tasks,
        finish,
    })
}

impl Plan {
    /// Write the plan to `dir/plan.json` (atomically).
    pub fn write(&self, dir: &Path) -> Result<PathBuf> {
        std::fs::create_dir_all(dir)
            .map_err(|e| batch_err(format!("{}: cannot create ({e})", dir.display())))?;
        let path = dir.join(PLAN_FILE);
        crate::formats::results::write_json(&path, self)?;
        Ok(path)
    }

    /// Read `plan.json` (`path` is the file or its folder).
    pub fn read(path: &Path) -> Result<(Self, PathBuf)> {
        let file = if path.is_dir() {
            path.join(PLAN_FILE)
        } else {
            path.to_path_buf()
        };
        let dir = file
            .parent()
            .map_or_else(|| PathBuf::from("."), Path::to_path_buf);
        let text = std::fs::read_to_string(&file).map_err(|e| {
            batch_err(format!(
                "{}: cannot read the plan ({e}); write one with `kiwi batch plan`",
                file.display()
            ))
        })?;
        let plan: Plan = serde_json::from_str(&text).map_err(|e| {
            batch_err(format!(
                "{}: not a plan ({e}); write one with `kiwi batch plan`",
                file.display()
            ))
        })?;
        if plan.schema_version != PLAN_SCHEMA_VERSION {
            return Err(batch_err(format!(
                "{}: plan version {}, this kiwi reads {PLAN_SCHEMA_VERSION}; plan again with \
                 `kiwi batch plan`",
                file.display(),
                plan.schema_version
            )));
        }
        Ok((plan, dir))
    }

    /// The episode names of the array, in task order.
    pub fn task_episodes(&self) -> Vec<String> {
        self.episodes
            .iter()
            .filter_map(|t| t.episode.clone())
            .collect()
    }
}

/// Slurm settings of the scripts.
#[derive(Debug, Clone, Default)]
pub struct SlurmOptions {
    /// `--partition` of every job (the cluster's default when `None`).
    pub partition: Option<String>,
    /// Array tasks running at once (`--array=…%N`).
    pub max_parallel: Option<u32>,
    /// `--account`, when the cluster charges one.
    pub account: Option<String>,
}

/// Slurm's `--time` format.
fn slurm_time(seconds: u64) -> String {
    let (h, m, s) = (seconds / 3600, (seconds / 60) % 60, seconds % 60);
    format!("{h:02}:{m:02}:{s:02}")
}

/// Single-quote a word for bash.
fn quoted(p: &Path) -> String {
    format!("'{}'", p.display().to_string().replace('\'', r"'\''"))
}

/// The `#SBATCH` header of a job.
fn header(name: &str, r: &Resources, opts: &SlurmOptions, log: &str) -> String {
    let mut s = format!(
        "#!/bin/bash\n#SBATCH --job-name={name}\n#SBATCH --cpus-per-task={}\n#SBATCH --mem={}M\n\
         #SBATCH --time={}\n#SBATCH --output={log}\n",
        r.cpus,
        r.memory_mb,
        slurm_time(r.time_limit_s)
    );
    if let Some(p) = &opts.partition {
        s.push_str(&format!("#SBATCH --partition={p}\n"));
    }
    if let Some(a) = &opts.account {
        s.push_str(&format!("#SBATCH --account={a}\n"));
    }
    s
}

/// The body of a job: `kiwi run` with `args`, where exit status 2 (the run finished and some
/// episode is unusable: its verdict says why, and `kiwi batch status` shows it) counts as done
/// for the scheduler.
fn run_body(plan: &Plan, args: &str) -> String {
    format!(
        "{} run --session {} {args}\ncode=$?\n\
         # 2: the run finished and some episode is unusable; `kiwi batch status` says why.\n\
         if [ \"$code\" -eq 2 ]; then exit 0; fi\nexit \"$code\"\n",
        quoted(&plan.kiwi),
        quoted(&plan.session),
    )
}

/// The scripts of a plan, by file name.
pub fn slurm_scripts(plan: &Plan, dir: &Path, opts: &SlurmOptions) -> BTreeMap<String, String> {
    let logs = dir.join(LOGS_DIR);
    let script = |name: &str, log: &str, r: &Resources, prologue: &str, args: String| {
        let log = logs.join(log).display().to_string();
        format!(
            "{}{prologue}{}",
            header(name, r, opts, &log),
            run_body(plan, &format!("{args} --threads {}", r.cpus))
        )
    };
    let mut out = BTreeMap::new();
    let maps = &plan.maps;
    out.insert(
        "maps.sbatch".into(),
        script(
            "kiwi-maps",
            "maps-%j.out",
            &maps.resources,
            "",
            format!("--episodes {}", maps.episode.as_deref().unwrap_or("")),
        ),
    );
    // One request for every task of the array: the largest episode's.
    if let Some(r) = plan
        .episodes
        .iter()
        .map(|t| t.resources.clone())
        .reduce(|a, b| a.max(&b))
    {
        let prologue = format!(
            "EPISODES=({} )\nEPISODE=\"${{EPISODES[$SLURM_ARRAY_TASK_ID]}}\"\n",
            plan.task_episodes()
                .iter()
                .map(|e| format!(" {e}"))
                .collect::<String>()
        );
        out.insert(
            "episodes.sbatch".into(),
            script(
                "kiwi-episodes",
                "episode-%A_%a.out",
                &r,
                &prologue,
                "--episodes \"$EPISODE\"".into(),
            ),
        );
    }
    if let Some(f) = &plan.finish {
        // Only the stages after the episodes: a failed or cancelled episode stays as its task
        // left it (its datasets leave it out, naming why) until it is resubmitted.
        out.insert(
            "datasets.sbatch".into(),
            script(
                "kiwi-datasets",
                "datasets-%j.out",
                &f.resources,
                "",
                format!("--only {}", AFTER_EPISODE_FAMILIES.join(",")),
            ),
        );
    }
    out
}

/// Write the scripts into `dir/slurm/` (and create `dir/logs/`); returns their paths.
pub fn write_slurm_scripts(
    plan: &Plan,
    dir: &Path,
    opts: &SlurmOptions,
) -> Result<BTreeMap<String, PathBuf>> {
    let scripts_dir = dir.join(SCRIPTS_DIR);
    for d in [&scripts_dir, &dir.join(LOGS_DIR)] {
        std::fs::create_dir_all(d)
            .map_err(|e| batch_err(format!("{}: cannot create ({e})", d.display())))?;
    }
    let mut out = BTreeMap::new();
    for (name, text) in slurm_scripts(plan, dir, opts) {
        let path = scripts_dir.join(&name);
        kiwi_core::io::write_atomic(&path, text.as_bytes())?;
        out.insert(name, path);
    }
    Ok(out)
}

/// The jobs submitted for a plan (`jobs.json`): every submission, oldest first.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Jobs {
    /// Each `submit` or `resubmit`.
    pub submissions: Vec<Submission>,
}

/// One submission's job ids.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Submission {
    /// The maps job (`None` when the maps were current).
    pub maps: Option<String>,
    /// The episode array's job id.
    pub array: Option<String>,
    /// The array's tasks: task index → episode.
    pub tasks: BTreeMap<u32, String>,
    /// The datasets job.
    pub datasets: Option<String>,
}

impl Jobs {
    /// Read `dir/jobs.json` (empty when there is none yet).
    pub fn read(dir: &Path) -> Result<Self> {
        let path = dir.join(JOBS_FILE);
        match std::fs::read_to_string(&path) {
            Ok(text) => serde_json::from_str(&text)
                .map_err(|e| batch_err(format!("{}: not a job list ({e})", path.display()))),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(Self::default()),
            Err(e) => Err(batch_err(format!("{}: cannot read ({e})", path.display()))),
        }
    }

    /// Write `dir/jobs.json` atomically.
    pub fn write(&self, dir: &Path) -> Result<()> {
        crate::formats::results::write_json(&dir.join(JOBS_FILE), self)
    }

    /// The latest job of `episode` (its array task or the maps job), as squeue names it.
    pub fn latest_job_of(&self, episode: &str, plan: &Plan) -> Option<String> {
        self.submissions.iter().rev().find_map(|s| {
            if plan.maps.episode.as_deref() == Some(episode) {
                return s.maps.clone();
            }
            let (index, _) = s.tasks.iter().find(|(_, e)| e.as_str() == episode)?;
            Some(format!("{}_{index}", s.array.as_ref()?))
        })
    }
}

/// Run a Slurm command, returning its standard output.
fn slurm(program: &str, args: &[String]) -> Result<String> {
    let out = Command::new(program).args(args).output().map_err(|e| {
        batch_err(format!(
            "cannot run `{program}` ({e}): is this a Slurm login node? (`kiwi batch slurm` \
             without --submit writes the scripts only)"
        ))
    })?;
    if !out.status.success() {
        return Err(batch_err(format!(
            "`{program} {}` failed ({}): {}",
            args.join(" "),
            out.status,
            String::from_utf8_lossy(&out.stderr).trim()
        )));
    }
    Ok(String::from_utf8_lossy(&out.stdout).into_owned())
}

/// `sbatch --parsable` a script with extra arguments; returns the job id.
fn sbatch(script: &Path, extra: &[String]) -> Result<String> {
    let mut args = vec!["--parsable".to_string()];
    args.extend_from_slice(extra);
    args.push(script.display().to_string());
    let out = slurm("sbatch", &args)?;
    // `--parsable` prints `jobid` or `jobid;cluster`.
    let id = out.trim().split(';').next().unwrap_or("").to_string();
    if id.is_empty() || !id.chars().all(|c| c.is_ascii_digit()) {
        return Err(batch_err(format!(
            "sbatch {}: expected a job id, got `{}`",
            script.display(),
            out.trim()
        )));
    }
    Ok(id)
}

/// Write the plan's scripts and submit them: the maps job when `with_maps`, then the tasks of
/// `episodes` as one array that depends on it, then the datasets job after the array. Records the ids in `jobs.json` and returns the submission.
pub fn submit(
    plan: &Plan,
    dir: &Path,
    opts: &SlurmOptions,
    episodes: &[String],
    with_maps: bool,
) -> Result<Submission> {
    let scripts = write_slurm_scripts(plan, dir, opts)?;
    let script = |name: &str| {
        scripts
            .get(name)
            .cloned()
            .ok_or_else(|| batch_err(format!("no {name} for this plan (it has no such job)")))
    };
    let maps = if with_maps {
        Some(sbatch(&script("maps.sbatch")?, &[])?)
    } else {
        None
    };
    let order = plan.task_episodes();
    let mut tasks = BTreeMap::new();
    for e in episodes {
        let index = order.iter().position(|x| x == e).ok_or_else(|| {
            batch_err(format!(
                "episode {e} is not a task of the plan (its tasks: {})",
                order.join(", ")
            ))
        })?;
        tasks.insert(index as u32, e.clone());
    }
    let array = if tasks.is_empty() {
        None
    } else {
        let list: Vec<String> = tasks.keys().map(u32::to_string).collect();
        let mut spec = list.join(",");
        if let Some(n) = opts.max_parallel {
            spec.push_str(&format!("%{n}"));
        }
        let mut extra = vec![format!("--array={spec}")];
        if let Some(m) = &maps {
            extra.push(format!("--dependency=afterok:{m}"));
            extra.push("--kill-on-invalid-dep=yes".into());
        }
        Some(sbatch(&script("episodes.sbatch")?, &extra)?)
    };
    // The datasets follow whatever this submission runs.
    let datasets = match &plan.finish {
        None => None,
        Some(_) => {
            let after: Vec<String> = array
                .as_ref()
                .or(maps.as_ref())
                .map(|j| format!("--dependency=afterany:{j}"))
                .into_iter()
                .collect();
            Some(sbatch(&script("datasets.sbatch")?, &after)?)
        }
    };
    let submission = Submission {
        maps,
        array,
        tasks,
        datasets,
    };
    let mut jobs = Jobs::read(dir)?;
    jobs.submissions.push(submission.clone());
    jobs.write(dir)?;
    Ok(submission)
}

/// How far an episode's stages are.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub enum Progress {
    /// Every stage current.
    #[serde(rename = "done")]
    Done,
    /// A stage failed (or is blocked by one that failed).
    #[serde(rename = "failed")]
    Failed,
    /// Some stage has not run or is stale.
    #[serde(rename = "not run")]
    NotRun,
}

impl Progress {
    /// `done`, `failed` or `not run`.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Done => "done",
            Self::Failed => "failed",
            Self::NotRun => "not run",
        }
    }
}

/// Where an episode stands.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct EpisodeState {
    /// The episode.
    pub episode: String,
    /// How far its stages are.
    pub state: Progress,
    /// Its verdict when done (`usable`, `suspect`, `unusable`).
    pub verdict: Option<String>,
    /// The failure (stage and reason) or what is missing.
    pub detail: String,
    /// Its latest job as the scheduler names it (`<array>_<index>` for a task).
    pub job: Option<String>,
    /// That job's queue state (`PENDING (Dependency)`, `RUNNING`, …; `None` when it has left
    /// the queue).
    pub queue: Option<String>,
}

/// Parse `squeue -h -o "%i|%T|%r"` output into job id → `STATE (reason)`; array tasks appear
/// as `<array>_<index>`, pending array ranges as `<array>_[a-b]` (expanded here).
pub fn parse_squeue(text: &str) -> BTreeMap<String, String> {
    let mut out = BTreeMap::new();
    for line in text.lines() {
        let mut parts = line.trim().split('|');
        let (Some(id), Some(state)) = (parts.next(), parts.next()) else {
            continue;
        };
        let reason = parts.next().unwrap_or("").trim();
        let state = if reason.is_empty() || reason == "None" {
            state.trim().to_string()
        } else {
            format!("{} ({reason})", state.trim())
        };
        match id.split_once("_[") {
            Some((array, range)) => {
                let range = range.trim_end_matches(']');
                let range = range.split('%').next().unwrap_or("");
                for part in range.split(',') {
                    let (a, b) = part.split_once('-').unwrap_or((part, part));
                    if let (Ok(a), Ok(b)) = (a.parse::<u32>(), b.parse::<u32>()) {
                        for i in a..=b {
                            out.insert(format!("{array}_{i}"), state.clone());
                        }
                    }
                }
            }
            None => {
                out.insert(id.trim().to_string(), state);
            }
        }
    }
    out
}

/// The scheduler's queue for the plan's jobs (empty when nothing was submitted).
fn queue(jobs: &Jobs) -> Result<BTreeMap<String, String>> {
    let ids: Vec<String> = jobs
        .submissions
        .iter()
        .flat_map(|s| [s.maps.clone(), s.array.clone(), s.datasets.clone()])
        .flatten()
        .collect();
    if ids.is_empty() {
        return Ok(BTreeMap::new());
    }
    let text = slurm(
        "squeue",
        &[
            "-h".into(),
            "-o".into(),
            "%i|%T|%r".into(),
            "-j".into(),
            ids.join(","),
        ],
    )?;
    Ok(parse_squeue(&text))
}

/// Every planned episode's state from its stage states (and, with `with_queue`, the
/// scheduler's queue).
pub fn episode_states(plan: &Plan, dir: &Path, with_queue: bool) -> Result<Vec<EpisodeState>> {
    let ctx = SessionContext::load(&plan.session)?;
    let jobs = Jobs::read(dir)?;
    let queue = if with_queue {
        queue(&jobs)?
    } else {
        BTreeMap::new()
    };
    let mut names: Vec<String> = plan.maps.episode.iter().cloned().collect();
    names.extend(plan.task_episodes());
    let rows = status(&ctx, Some(&names))?;
    let mut out = Vec::new();
    for name in names {
        // The map episode's run owns the session's maps; the datasets come after every task.
        let owns_session = plan.maps.episode.as_ref() == Some(&name);
        let own: Vec<_> = rows
            .iter()
            .filter(|r| {
                r.scope == name
                    || (owns_session
                        && r.scope == "session"
                        && !AFTER_EPISODE_FAMILIES
                            .contains(&r.stage.split('-').next().unwrap_or("")))
            })
            .collect();
        let failed = own
            .iter()
            .find(|r| r.state == "failed" || r.state == "blocked");
        let missing = own
            .iter()
            .find(|r| r.state == "not run" || r.state == "stale");
        let (state, detail) = match (failed, missing) {
            (Some(f), _) => (Progress::Failed, format!("{}: {}", f.stage, f.detail)),
            (None, Some(m)) => (Progress::NotRun, format!("{} is {}", m.stage, m.state)),
            (None, None) => (Progress::Done, String::new()),
        };
        let verdict = if state == Progress::Done {
            let q = ctx
                .session
                .episode_dir(&ctx.root, &name)
                .join("out")
                .join("quality.json");
            crate::outputs::read_quality(&q)
                .ok()
                .map(|q| q.verdict.as_str().to_string())
        } else {
            None
        };
        let job = jobs.latest_job_of(&name, plan);
        let queued = job.as_ref().and_then(|j| queue.get(j).cloned());
        out.push(EpisodeState {
            episode: name,
            state,
            verdict,
            detail,
            job,
            queue: queued,
        });
    }
    Ok(out)
}

/// The episodes a resubmission runs: those not done and not waiting or running in the queue.
pub fn to_resubmit(states: &[EpisodeState]) -> Vec<String> {
    states
        .iter()
        .filter(|s| s.state != Progress::Done && s.queue.is_none())
        .map(|s| s.episode.clone())
        .collect()
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use super::*;

    #[test]
    fn squeue_lines_and_pending_ranges_are_read() {
        let q = parse_squeue(
            "12|COMPLETING|None\n13_[2-4,7%2]|PENDING|Dependency\n13_0|RUNNING|None\n\n",
        );
        assert_eq!(q["12"], "COMPLETING");
        assert_eq!(q["13_0"], "RUNNING");
        for i in [2, 3, 4, 7] {
            assert_eq!(q[&format!("13_{i}")], "PENDING (Dependency)");
        }
        assert_eq!(q.len(), 6);
    }

    #[test]
    fn resources_grow_with_the_recording_and_never_drop_below_the_floor() {
        let small = resources(100, 0.1, 1.0, 2);
        assert_eq!(small.time_limit_s, MIN_TIME_LIMIT_S as u64);
        let big = resources(160_000, 0.92, 1.0, 2);
        assert!(big.time_limit_s > small.time_limit_s);
        assert_eq!(big.time_limit_s % 60, 0);
        assert!(big.memory_mb > small.memory_mb);
        assert_eq!(slurm_time(3725), "01:02:05");
    }

    #[test]
    fn resubmission_skips_done_and_queued_episodes() {
        let s = |e: &str, state: Progress, queue: Option<&str>| EpisodeState {
            episode: e.into(),
            state,
            verdict: None,
            detail: String::new(),
            job: None,
            queue: queue.map(str::to_string),
        };
        let states = [
            s("a", Progress::Done, None),
            s("b", Progress::Failed, None),
            s("c", Progress::NotRun, Some("RUNNING")),
            s("d", Progress::NotRun, None),
        ];
        assert_eq!(to_resubmit(&states), vec!["b".to_string(), "d".to_string()]);
    }
}
