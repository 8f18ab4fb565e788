//! `kiwi run`: execute the stage graph of a session.
//!
//! Workers (as many as `--threads`) take the next stage whose dependencies are decided, in graph
//! order, so the three maps build side by side and the episodes' streams localize in parallel
//! once the maps exist; inside a stage, data parallelism uses the same rayon pool. A stage whose
//! inputs are unchanged is skipped; a failed stage blocks only the stages that read it, so one
//! bad episode never stops the others. Results do not depend on the number of threads.

use std::collections::{BTreeMap, BTreeSet};
use std::path::PathBuf;
use std::sync::{Condvar, Mutex, PoisonError};
use std::time::Instant;

use serde::Serialize;

use super::context::SessionContext;
use super::graph::{FAMILIES, StageKind, StageNode, build};
use super::stage::{Fingerprint, InputDigest, Manifest, StageId, StageState, StageWork, state_of};
use super::stages::{PUBLISHED_DIR, StageEnv, inputs, parameters, run as run_stage, version};
use crate::error::{BackendError, Result};
use crate::outputs::{QualityRecord, failed_record, read_quality};
use crate::quality::Verdict;

/// What `kiwi run` should do.
#[derive(Debug, Clone, Default)]
pub struct RunOptions {
    /// Episodes to process (default: all of the session's).
    pub episodes: Option<Vec<String>>,
    /// Re-run this stage family and every stage after it.
    pub from: Option<String>,
    /// Re-run these stage families (`all` for every stage).
    pub force: Vec<String>,
    /// Run only these stage families (and nothing after them).
    pub only: Option<Vec<String>>,
    /// Worker threads (default: the machine's cores).
    pub threads: Option<usize>,
}

/// How a stage ended in this run.
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(tag = "outcome", rename_all = "lowercase")]
pub enum Outcome {
    /// Ran and wrote its outputs.
    Ran {
        /// Wall time (s).
        seconds: f64,
    },
    /// Its inputs were unchanged: the earlier result stands.
    Current,
    /// It failed.
    Failed {
        /// Why.
        reason: String,
    },
    /// A stage it reads failed (or was blocked).
    Blocked {
        /// Which stage and why.
        reason: String,
    },
    /// Not requested in this run.
    Skipped,
}

/// One stage's line in the run report.
#[derive(Debug, Clone, Serialize)]
pub struct StageReport {
    /// `ep001/localize-left-front`.
    pub stage: String,
    /// How it ended.
    #[serde(flatten)]
    pub outcome: Outcome,
}

/// One episode's result.
#[derive(Debug, Clone, Serialize)]
pub struct EpisodeReport {
    /// Episode name.
    pub episode: String,
    /// Verdict (`unusable` when a stage failed).
    pub verdict: Verdict,
    /// Reasons for the verdict.
    pub reasons: Vec<String>,
    /// The episode's `out/` folder.
    pub out: PathBuf,
}

/// What `kiwi run` did.
#[derive(Debug, Clone, Serialize)]
pub struct RunReport {
    /// Every stage of the graph.
    pub stages: Vec<StageReport>,
    /// Every requested episode.
    pub episodes: Vec<EpisodeReport>,
    /// Stages run, current (skipped), failed and blocked.
    pub counts: BTreeMap<String, usize>,
    /// Wall time (s).
    pub seconds: f64,
}

impl RunReport {
    /// Episodes whose verdict is `unusable`.
    pub fn failed_episodes(&self) -> usize {
        self.episodes
            .iter()
            .filter(|e| e.verdict == Verdict::Unusable)
            .count()
    }
}

/// Progress of the running stages, shown by the caller (a terminal display or nothing).
pub trait Progress: Sync {
    /// A stage starts; `total` may be 0 when unknown.
    fn start(&self, stage: &StageId);
    /// A stage has done `done` of `total` units.
    fn update(&self, stage: &StageId, done: usize, total: usize);
    /// A stage ended.
    fn finish(&self, stage: &StageId, outcome: &Outcome);
}

/// A progress display that shows nothing.
pub struct NoProgress;

impl Progress for NoProgress {
    fn start(&self, _: &StageId) {}
    fn update(&self, _: &StageId, _: usize, _: usize) {}
    fn finish(&self, _: &StageId, _: &Outcome) {}
}

fn option_err(ctx: &SessionContext, message: String) -> BackendError {
    BackendError::Input {
        path: ctx.toml.clone(),
        message,
    }
}

/// Whether a stage named on the command line selects `id`: a family (`localize`: every
/// stream's localization in every episode), one stage as `kiwi status` lists it
/// (`localize-left-front`: that stream in every episode) or one episode's stage
/// (`ep001/localize-left-front`, `session/map-rear`).
fn selects(selector: &str, id: &StageId) -> bool {
    selector == id.family() || selector == id.name || selector == id.label()
}

/// Check a stage named on the command line against the run's stage graph.
fn check_selector(ctx: &SessionContext, graph: &[StageNode], flag: &str, name: &str) -> Result<()> {
    if FAMILIES.contains(&name)
        || (flag == "--force" && name == "all")
        || graph.iter().any(|n| selects(name, &n.id))
    {
        Ok(())
    } else {
        Err(option_err(
            ctx,
            format!(
                "{flag} {name}: unknown stage; name a stage family ({}{}), a stage as `kiwi \
                 status` lists it (localize-left-front) or one episode's stage \
                 (ep001/localize-left-front)",
                FAMILIES.join(", "),
                if flag == "--force" { ", or all" } else { "" }
            ),
        ))
    }
}

/// The episodes a run covers, checked against the session.
pub fn selected_episodes(
    ctx: &SessionContext,
    requested: Option<&[String]>,
) -> Result<Vec<String>> {
    let all = ctx.episode_names();
    match requested {
        None => Ok(all),
        Some(list) => {
            for e in list {
                if !all.contains(e) {
                    return Err(option_err(
                        ctx,
                        format!(
                            "--episodes: no episode `{e}` in the session (episodes: {})",
                            all.join(", ")
                        ),
                    ));
                }
            }
            Ok(all.into_iter().filter(|e| list.contains(e)).collect())
        }
    }
}

/// Every stage that reads, directly or not, one of `roots`.
fn dependents(graph: &[StageNode], roots: &BTreeSet<StageId>) -> BTreeSet<StageId> {
    let mut set = roots.clone();
    for node in graph {
        if node.deps.iter().any(|d| set.contains(d)) {
            set.insert(node.id.clone());
        }
    }
    set
}

/// The fingerprint of a stage now, given its dependencies' output digests.
pub fn fingerprint_of(
    ctx: &SessionContext,
    node: &StageNode,
    dep_digests: &BTreeMap<StageId, String>,
) -> Result<Fingerprint> {
    let mut all = inputs(ctx, &node.kind)?;
    for dep in &node.deps {
        all.push(InputDigest {
            name: format!("stage {}", dep.label()),
            path: ctx.relative(&dep.dir(&ctx.root)),
            digest: dep_digests.get(dep).cloned().unwrap_or_default(),
        });
    }
    Ok(Fingerprint::new(
        version(&node.kind),
        parameters(&node.kind),
        all,
    ))
}

/// What the scheduler knows of a stage.
#[derive(Debug, Clone)]
enum Decided {
    /// Outputs available with this digest.
    Done(String),
    /// Failed or blocked: the reason.
    Broken(String),
}

struct Shared {
    decided: BTreeMap<StageId, Decided>,
    running: BTreeSet<StageId>,
    reports: BTreeMap<StageId, Outcome>,
}

/// Run the graph of `ctx` for the options; `progress` shows what runs.
pub fn run(
    ctx: &SessionContext,
    options: &RunOptions,
    progress: &dyn Progress,
) -> Result<RunReport> {
    let started = Instant::now();
    let episodes = selected_episodes(ctx, options.episodes.as_deref())?;
    let graph = build(ctx, &episodes);
    for f in &options.force {
        check_selector(ctx, &graph, "--force", f)?;
    }
    if let Some(f) = &options.from {
        check_selector(ctx, &graph, "--from", f)?;
    }
    for f in options.only.iter().flatten() {
        check_selector(ctx, &graph, "--only", f)?;
    }
    let forced: BTreeSet<StageId> = {
        let named: BTreeSet<StageId> = graph
            .iter()
            .filter(|n| {
                options
                    .force
                    .iter()
                    .any(|f| f == "all" || selects(f, &n.id))
            })
            .map(|n| n.id.clone())
            .collect();
        let from: BTreeSet<StageId> = match &options.from {
            Some(f) => dependents(
                &graph,
                &graph
                    .iter()
                    .filter(|n| selects(f, &n.id))
                    .map(|n| n.id.clone())
                    .collect(),
            ),
            None => BTreeSet::new(),
        };
        named.union(&from).cloned().collect()
    };
    // Stages the run may execute: with --only, those families; their dependencies must then be
    // current already.
    let runnable = |id: &StageId| {
        options
            .only
            .as_ref()
            .is_none_or(|only| only.iter().any(|f| selects(f, id)))
    };
    let wanted: BTreeSet<StageId> = match &options.only {
        None => graph.iter().map(|n| n.id.clone()).collect(),
        Some(_) => {
            // The selected stages and what they read.
            let mut set: BTreeSet<StageId> = graph
                .iter()
                .filter(|n| runnable(&n.id))
                .map(|n| n.id.clone())
                .collect();
            for node in graph.iter().rev() {
                if set.contains(&node.id) {
                    set.extend(node.deps.iter().cloned());
                }
            }
            set
        }
    };
    let nodes: Vec<&StageNode> = graph.iter().filter(|n| wanted.contains(&n.id)).collect();
    for scope_root in nodes
        .iter()
        .map(|n| n.id.work_root(&ctx.root))
        .collect::<BTreeSet<_>>()
    {
        let names: Vec<&str> = nodes
            .iter()
            .filter(|n| n.id.work_root(&ctx.root) == scope_root)
            .map(|n| n.id.name.as_str())
            .collect();
        super::stage::clean_leftovers(&scope_root, &names);
    }

    let threads = options
        .threads
        .unwrap_or_else(|| std::thread::available_parallelism().map_or(2, usize::from))
        .max(1);
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .map_err(|e| option_err(ctx, format!("--threads {threads}: cannot start: {e}")))?;
    let shared = Mutex::new(Shared {
        decided: BTreeMap::new(),
        running: BTreeSet::new(),
        reports: BTreeMap::new(),
    });
    let wake = Condvar::new();

    let worker = || {
        loop {
            let next = {
                // A poisoned lock still holds consistent state (nothing panics while holding
                // it); going on keeps every waiting worker's wake-up.
                let mut s = shared.lock().unwrap_or_else(PoisonError::into_inner);
                loop {
                    let ready = nodes.iter().find(|n| {
                        !s.decided.contains_key(&n.id)
                            && !s.running.contains(&n.id)
                            && n.deps.iter().all(|d| s.decided.contains_key(d))
                    });
                    match ready {
                        Some(n) => {
                            s.running.insert(n.id.clone());
                            let deps: Vec<(StageId, Decided)> = n
                                .deps
                                .iter()
                                .filter_map(|d| s.decided.get(d).map(|v| (d.clone(), v.clone())))
                                .collect();
                            break Some((*n, deps));
                        }
                        None if s.running.is_empty() => break None,
                        None => {
                            s = wake.wait(s).unwrap_or_else(PoisonError::into_inner);
                        }
                    }
                }
            };
            let Some((node, deps)) = next else {
                wake.notify_all();
                return;
            };
            let (decided, outcome) = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                execute(
                    ctx,
                    node,
                    &deps,
                    forced.contains(&node.id),
                    runnable(&node.id),
                    &pool,
                    progress,
                )
            }))
            .unwrap_or_else(|_| {
                let reason = "internal error (a panic) in the stage; please report it".to_string();
                (Decided::Broken(reason.clone()), Outcome::Failed { reason })
            });
            {
                let mut s = shared.lock().unwrap_or_else(PoisonError::into_inner);
                s.running.remove(&node.id);
                s.decided.insert(node.id.clone(), decided);
                s.reports.insert(node.id.clone(), outcome);
            }
            wake.notify_all();
        }
    };
    std::thread::scope(|scope| {
        for _ in 0..threads {
            scope.spawn(worker);
        }
    });
    let shared = shared.into_inner().unwrap_or_else(PoisonError::into_inner);

    let mut stages = Vec::new();
    let mut counts: BTreeMap<String, usize> = BTreeMap::new();
    for node in &graph {
        let outcome = shared
            .reports
            .get(&node.id)
            .cloned()
            .unwrap_or(Outcome::Skipped);
        let key = match &outcome {
            Outcome::Ran { .. } => "ran",
            Outcome::Current => "current",
            Outcome::Failed { .. } => "failed",
            Outcome::Blocked { .. } => "blocked",
            Outcome::Skipped => "not requested",
        };
        *counts.entry(key.to_string()).or_insert(0) += 1;
        stages.push(StageReport {
            stage: node.id.label(),
            outcome,
        });
    }
    let mut reports = Vec::new();
    for episode in &episodes {
        let outputs = StageId::episode(episode, "outputs");
        let out = ctx.episode(episode).root().join(PUBLISHED_DIR);
        let record: Option<QualityRecord> = match shared.decided.get(&outputs) {
            Some(Decided::Done(_)) => read_quality(&out.join("quality.json")).ok(),
            _ => None,
        };
        let (verdict, reasons) = match (record, shared.decided.get(&outputs)) {
            (Some(r), _) => (r.verdict, r.reasons),
            (None, Some(Decided::Broken(reason))) => (Verdict::Unusable, vec![reason.clone()]),
            (None, _) => (
                Verdict::Unusable,
                vec!["not processed in this run (see the stages requested)".into()],
            ),
        };
        reports.push(EpisodeReport {
            episode: episode.clone(),
            verdict,
            reasons,
            out,
        });
    }
    ctx.digests.save();
    Ok(RunReport {
        stages,
        episodes: reports,
        counts,
        seconds: started.elapsed().as_secs_f64(),
    })
}

/// Decide one stage: block it, skip it as current, or run it.
fn execute(
    ctx: &SessionContext,
    node: &StageNode,
    deps: &[(StageId, Decided)],
    forced: bool,
    runnable: bool,
    pool: &rayon::ThreadPool,
    progress: &dyn Progress,
) -> (Decided, Outcome) {
    // An export leaves a failed episode out (its published quality.json says why) rather than
    // fail with it; the report shows the failure.
    let tolerates_broken = matches!(node.kind, StageKind::Export { .. } | StageKind::Report);
    // A stage this run may not execute (outside --only) keeps what it last published.
    let publish = |reason: &str| {
        if runnable {
            publish_failure(ctx, node, reason);
        }
    };
    let blocked = !tolerates_broken
        && deps
            .iter()
            .any(|(id, d)| matches!(d, Decided::Broken(_)) && !node.optional.contains(id));
    if blocked {
        // Every cause, the required inputs' first: a stage that could do without one failed
        // input still names it when another stops it.
        let mut causes: Vec<String> = Vec::new();
        let required_first = (deps.iter().filter(|(id, _)| !node.optional.contains(id)))
            .chain(deps.iter().filter(|(id, _)| node.optional.contains(id)));
        for (dep, d) in required_first {
            let Decided::Broken(reason) = d else {
                continue;
            };
            // A blocked input's reason is already its causes, joined.
            let found: Vec<String> = if reason.starts_with("needs ") {
                (reason.split("; needs "))
                    .enumerate()
                    .map(|(k, c)| {
                        if k == 0 {
                            c.to_string()
                        } else {
                            format!("needs {c}")
                        }
                    })
                    .collect()
            } else {
                vec![format!("needs {}, which failed: {reason}", dep.label())]
            };
            for cause in found {
                if !causes.contains(&cause) {
                    causes.push(cause);
                }
            }
        }
        let reason = causes.join("; ");
        publish(&reason);
        return (Decided::Broken(reason.clone()), Outcome::Blocked { reason });
    }
    let digests: BTreeMap<StageId, String> = deps
        .iter()
        .filter_map(|(id, d)| match d {
            Decided::Done(digest) => Some((id.clone(), digest.clone())),
            Decided::Broken(_) => None,
        })
        .collect();
    let fingerprint = match fingerprint_of(ctx, node, &digests) {
        Ok(f) => f,
        Err(e) => {
            let reason = e.to_string();
            publish(&reason);
            return (Decided::Broken(reason.clone()), Outcome::Failed { reason });
        }
    };
    let dir = node.id.dir(&ctx.root);
    let state = state_of(&dir, &fingerprint);
    if state == StageState::Current
        && !forced
        && let Some(m) = Manifest::read(&dir)
    {
        return (Decided::Done(m.output_digest), Outcome::Current);
    }
    if !runnable {
        let reason = format!(
            "{} is {}; run it first (without --only)",
            node.id.label(),
            state.describe()
        );
        return (Decided::Broken(reason.clone()), Outcome::Blocked { reason });
    }
    progress.start(&node.id);
    let started = Instant::now();
    let result = (|| -> Result<Manifest> {
        let work = StageWork::begin(&ctx.root, &node.id)?;
        let id = node.id.clone();
        let report = |done: usize, total: usize| progress.update(&id, done, total);
        let unavailable: Vec<(StageId, String)> = (deps.iter())
            .filter_map(|(id, d)| match d {
                Decided::Broken(reason) => Some((id.clone(), reason.clone())),
                Decided::Done(_) => None,
            })
            .collect();
        let env = StageEnv {
            ctx,
            out: work.dir(),
            progress: &report,
            unavailable: &unavailable,
        };
        let body = pool.install(|| run_stage(&env, &node.kind));
        let seconds = started.elapsed().as_secs_f64();
        match body {
            Ok(()) => {
                let publish = published_target(ctx, node);
                work.commit_ok(&fingerprint, seconds, publish.as_deref())
            }
            Err(e) => {
                let reason = e.to_string();
                let _ = work.commit_failed(&fingerprint, &reason, seconds);
                Err(e)
            }
        }
    })();
    let (decided, outcome) = match result {
        Ok(m) => (
            Decided::Done(m.output_digest),
            Outcome::Ran {
                seconds: started.elapsed().as_secs_f64(),
            },
        ),
        Err(e) => {
            let reason = e.to_string();
            publish_failure(ctx, node, &reason);
            (Decided::Broken(reason.clone()), Outcome::Failed { reason })
        }
    };
    progress.finish(&node.id, &outcome);
    (decided, outcome)
}

/// The session sub-folder the export stages publish their datasets in (`exports/<format>/`).
pub const EXPORTS_DIR: &str = "exports";

/// Where a stage's published sub-folder goes: the outputs stage's `out/` becomes the episode's
/// `out/`, an export stage's `out/` becomes `exports/<format>/`, the report's `report/`.
fn published_target(ctx: &SessionContext, node: &StageNode) -> Option<PathBuf> {
    match &node.kind {
        StageKind::Outputs { episode } => Some(ctx.episode(episode).root().join(PUBLISHED_DIR)),
        StageKind::Export { format } => Some(ctx.root.join(EXPORTS_DIR).join(format.name())),
        StageKind::Report => Some(ctx.root.join(crate::report::REPORT_DIR)),
        _ => None,
    }
}

/// When an episode's outputs cannot be made, its `out/` holds only a `quality.json` that says
/// `unusable` and why (never the trajectories of an earlier run with other inputs).
fn publish_failure(ctx: &SessionContext, node: &StageNode, reason: &str) {
    let StageKind::Outputs { episode } = &node.kind else {
        return;
    };
    let out = ctx.episode(episode).root().join(PUBLISHED_DIR);
    let record = failed_record(episode, &ctx.session.map_episode, vec![reason.to_string()]);
    let tmp = ctx
        .episode(episode)
        .root()
        .join(format!(".tmp-out-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&tmp);
    let written = std::fs::create_dir_all(&tmp).is_ok()
        && crate::formats::results::write_json(&tmp.join("quality.json"), &record).is_ok();
    if written {
        let _ = super::stage::replace_dir(&tmp, &out);
    }
    let _ = std::fs::remove_dir_all(&tmp);
}
