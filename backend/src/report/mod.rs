//! The session report (`kiwi report`, and the `report` stage that ends `kiwi run`): one
//! self-contained HTML page per session, for a lab to check a session by looking at it.
//!
//! Per episode: a top view of both tool tips' paths (and the head camera's, from the head
//! stage's `out/head.tum`) over the scene map's landmarks, coloured by support class; a support
//! timeline per stream (each wrist's support class, each lens localized or lost with the
//! reason); the sync graph (cameras, pair lags and drifts, triangle closures); the gripper
//! openings over time; the quality verdict with its reasons; and the stage timings from the
//! stage manifests. The SVG charts are inline (drawn with `kiwi-plot`); the page needs no
//! network and no script.
//!
//! [`gather`] reads what the stages left into typed values — anything missing (an episode whose
//! stages failed, a map that could not be built) becomes a note on the page, never an error —
//! and [`page::render`] draws them. The page is not a stage result other stages read: it holds
//! wall times, so it is published beside the stage folders (`report/index.html`) rather than
//! kept in them.

pub mod page;

use std::path::Path;

use kiwi_core::layout::ToolKind;

use crate::error::Result;
use crate::formats::tables::{LensFrame, read_lens_frames};
use crate::outputs::{QualityRecord, SupportClass, read_quality, session_time};
use crate::pipeline::SessionContext;
use crate::pipeline::graph::{Lens, MapName, StageKind, build, id_of};
use crate::pipeline::stage::{Manifest, RunStatus};
use crate::pipeline::stages::{POSES_FILE, PUBLISHED_DIR, SYNC_FILE, map_in_scene, read_json_file};
use crate::quality::Verdict;
use crate::sync::SyncResult;

/// The session sub-folder the report stage publishes (`report/`).
pub const REPORT_DIR: &str = "report";
/// The page inside it.
pub const PAGE_FILE: &str = "index.html";
/// The head camera's path in an episode's `out/` (TUM: `t x y z qx qy qz qw`), drawn when the
/// session has a head camera.
pub const HEAD_PATH_FILE: &str = "head.tum";
/// The floor stage's figure in an episode's `out/`.
pub const FLOOR_FIGURE_FILE: &str = "floor.svg";

/// One wrist of the session.
#[derive(Debug, Clone, PartialEq)]
pub struct WristSetup {
    /// `left` or `right`.
    pub camera: String,
    /// The camera unit's id.
    pub unit: String,
    /// The tool on it.
    pub tool: ToolKind,
}

/// A frame of a wrist's output trajectory, as the report draws it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackSample {
    /// Session time (s), or camera time when the camera is not on the session timeline.
    pub t: f64,
    /// Tool-tip position in the scene (m).
    pub tip: [f64; 3],
    /// What supported the frame.
    pub support: SupportClass,
    /// Gripper opening (rad for an angle, m for a width), when measured.
    pub opening: Option<f64>,
}

/// A wrist's output trajectory in an episode.
#[derive(Debug, Clone, PartialEq)]
pub struct WristTrack {
    /// `left` or `right`.
    pub camera: String,
    /// The tool (what the opening measures).
    pub tool: ToolKind,
    /// Whether the times are on the session timeline (else on the camera's clock).
    pub session_clock: bool,
    /// One per front frame.
    pub samples: Vec<TrackSample>,
}

/// One lens stream's localization outcome per frame.
#[derive(Debug, Clone, PartialEq)]
pub struct LensTrack {
    /// `left` or `right`.
    pub camera: String,
    /// `front` or `rear`.
    pub lens: String,
    /// Whether the times are on the session timeline (else on the camera's clock).
    pub session_clock: bool,
    /// One per frame.
    pub frames: Vec<LensFrame>,
}

/// How a stage last ended, from its manifest.
#[derive(Debug, Clone, PartialEq)]
pub struct StageTiming {
    /// The stage's name (`localize-left-front`).
    pub stage: String,
    /// `ok`, `failed` or `not run`.
    pub status: String,
    /// Wall time of its last run (s).
    pub seconds: Option<f64>,
    /// Why it failed.
    pub reason: Option<String>,
}

/// Everything the page shows of one episode.
#[derive(Debug, Clone)]
pub struct EpisodeReport {
    /// Episode name.
    pub name: String,
    /// Its description in `session.toml`.
    pub description: String,
    /// The verdict of its `quality.json` (`None`: not processed yet).
    pub verdict: Option<Verdict>,
    /// The reasons behind it.
    pub reasons: Vec<String>,
    /// The quality record, when the outputs were made.
    pub quality: Option<QualityRecord>,
    /// Both wrists' trajectories (empty when the outputs failed).
    pub wrists: Vec<WristTrack>,
    /// The head camera's path (session time, position), when the session has a head camera.
    pub head: Option<Vec<(f64, [f64; 3])>>,
    /// The floor stage's figure (SVG text of `out/floor.svg`), when published.
    pub floor_figure: Option<String>,
    /// Every wrist lens's localizations.
    pub lenses: Vec<LensTrack>,
    /// The sync result, when the sync stage ran.
    pub sync: Option<SyncResult>,
    /// The episode's stages.
    pub stages: Vec<StageTiming>,
    /// What could not be read, and why.
    pub notes: Vec<String>,
}

/// Everything the page shows of a session.
#[derive(Debug, Clone)]
pub struct SessionReport {
    /// The session's name.
    pub name: String,
    /// The episode whose recordings built the maps.
    pub map_episode: String,
    /// The wrists.
    pub wrists: Vec<WristSetup>,
    /// The scene map's landmarks in the scene frame (m).
    pub landmarks: Vec<[f64; 3]>,
    /// Why there are none, when there are none.
    pub landmarks_note: Option<String>,
    /// The episodes, in `session.toml` order.
    pub episodes: Vec<EpisodeReport>,
    /// The session stages (maps, tools, metric recovery, placements, exports).
    pub session_stages: Vec<StageTiming>,
    /// The map-sharing ablation (`kiwi evaluate ablation`), when it was run.
    pub ablation: Option<crate::evaluate::ablation::AblationReport>,
    /// The marker-referenced evaluations (`kiwi evaluate markers`) of the episodes they were
    /// run on, in episode order.
    pub markers: Vec<MarkerResult>,
}

/// One episode's marker-referenced evaluation with its scored frames.
#[derive(Debug, Clone, PartialEq)]
pub struct MarkerResult {
    /// The record.
    pub evaluation: crate::evaluate::markers::MarkerEvaluation,
    /// Its scored frames (empty when their file is missing or unreadable).
    pub frames: Vec<crate::evaluate::markers::ScoredFrame>,
}

/// What [`write_report`] wrote.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ReportSummary {
    /// Size of the page (bytes).
    pub bytes: usize,
    /// Charts on it.
    pub plots: usize,
    /// Episodes on it.
    pub episodes: usize,
}

/// Gather the session's results and write its report page to `path`, atomically.
pub fn write_report(ctx: &SessionContext, path: &Path) -> Result<ReportSummary> {
    let report = gather(ctx);
    let page = page::render(&report)?;
    kiwi_core::io::write_atomic(path, page.html.as_bytes())?;
    Ok(ReportSummary {
        bytes: page.html.len(),
        plots: page.plots,
        episodes: report.episodes.len(),
    })
}

/// Read what the stages of the session left (never failing: what is missing becomes a note).
pub fn gather(ctx: &SessionContext) -> SessionReport {
    let episodes_all = ctx.episode_names();
    let graph = build(ctx, &episodes_all);
    let timing = |kind: &StageKind| -> StageTiming {
        let id = id_of(kind);
        match Manifest::read(&id.dir(&ctx.root)) {
            Some(m) => StageTiming {
                stage: id.name.clone(),
                status: match m.status {
                    RunStatus::Ok => "ok".into(),
                    RunStatus::Failed => "failed".into(),
                },
                seconds: Some(m.seconds),
                reason: m.reason,
            },
            None => StageTiming {
                stage: id.name.clone(),
                status: "not run".into(),
                seconds: None,
                reason: None,
            },
        }
    };
    let session_stages = graph
        .iter()
        .filter(|n| n.id.scope == crate::pipeline::stage::Scope::Session)
        .filter(|n| n.kind != StageKind::Report)
        .map(|n| timing(&n.kind))
        .collect();
    let (landmarks, landmarks_note) = match scene_landmarks(ctx) {
        Ok(points) => (points, None),
        Err(why) => (Vec::new(), Some(why)),
    };
    let episodes = ctx
        .session
        .episodes
        .iter()
        .map(|e| {
            let mut report = episode_report(ctx, &e.name, &e.description);
            report.stages = graph
                .iter()
                .filter(|n| n.id.scope == crate::pipeline::stage::Scope::Episode(e.name.clone()))
                .map(|n| timing(&n.kind))
                .collect();
            report
        })
        .collect();
    let ablation_path = ctx
        .root
        .join(crate::evaluate::EVALUATION_DIR)
        .join(crate::evaluate::ablation::ABLATION_FILE);
    let ablation = ablation_path
        .is_file()
        .then(|| read_json_file(&ablation_path, "ablation record").ok())
        .flatten();
    let evaluation_dir = ctx.root.join(crate::evaluate::EVALUATION_DIR);
    let markers = episodes_all
        .iter()
        .filter_map(|e| {
            let (json, csv) = crate::evaluate::markers::evaluation_files(e);
            let evaluation =
                read_json_file(&evaluation_dir.join(json), "marker evaluation").ok()?;
            Some(MarkerResult {
                evaluation,
                frames: crate::evaluate::markers::read_errors_csv(&evaluation_dir.join(csv))
                    .unwrap_or_default(),
            })
        })
        .collect();
    SessionReport {
        ablation,
        markers,
        name: ctx.session.name.clone(),
        map_episode: ctx.session.map_episode.clone(),
        wrists: ctx
            .wrists
            .values()
            .map(|w| WristSetup {
                camera: w.camera.to_string(),
                unit: w.calibration.unit_id.clone(),
                tool: w.tool_kind,
            })
            .collect(),
        landmarks,
        landmarks_note,
        episodes,
        session_stages,
    }
}

/// The scene map's landmarks in the scene frame: the rear map made metric and z-up by its
/// metric recovery.
fn scene_landmarks(ctx: &SessionContext) -> std::result::Result<Vec<[f64; 3]>, String> {
    let (_, points) =
        map_in_scene(&ctx.root, MapName::Rear).map_err(|e| format!("no scene map to draw: {e}"))?;
    Ok(points.iter().map(|p| [p.x, p.y, p.z]).collect())
}

fn episode_report(ctx: &SessionContext, name: &str, description: &str) -> EpisodeReport {
    let layout = ctx.episode(name);
    let out = layout.root().join(PUBLISHED_DIR);
    let mut notes = Vec::new();
    let quality_path = out.join("quality.json");
    let quality = if quality_path.is_file() {
        read_quality(&quality_path)
            .map_err(|e| notes.push(e.to_string()))
            .ok()
    } else {
        None
    };
    let sync_path = id_of(&StageKind::Sync {
        episode: name.to_string(),
    })
    .dir(&ctx.root)
    .join(SYNC_FILE);
    let sync: Option<SyncResult> = quality.as_ref().and_then(|q| q.sync.clone()).or_else(|| {
        if !sync_path.is_file() {
            return None;
        }
        read_json_file(&sync_path, "sync result")
            .map_err(|e| notes.push(e.to_string()))
            .ok()
    });
    let clock = |camera: &str| {
        sync.as_ref()
            .and_then(|s| s.cameras.iter().find(|c| c.name == camera))
    };

    let mut wrists = Vec::new();
    let mut lenses = Vec::new();
    for (&side, w) in &ctx.wrists {
        let camera = w.camera;
        let csv = out.join(format!("{camera}.csv"));
        if csv.is_file() {
            match crate::export::read_trajectory(&csv) {
                Ok(rows) => {
                    let session_clock = rows.iter().all(|r| r.t_session.is_some());
                    wrists.push(WristTrack {
                        camera: camera.to_string(),
                        tool: w.tool_kind,
                        session_clock,
                        samples: rows
                            .iter()
                            .map(|r| {
                                let p = r.scene_from_tip.translation.vector;
                                TrackSample {
                                    t: if session_clock {
                                        r.t_session.unwrap_or(r.t_camera)
                                    } else {
                                        r.t_camera
                                    },
                                    tip: [p.x, p.y, p.z],
                                    support: r.support,
                                    opening: r.opening,
                                }
                            })
                            .collect(),
                    });
                }
                Err(e) => notes.push(e.to_string()),
            }
        }
        for lens in [Lens::Front, Lens::Rear] {
            let poses = id_of(&StageKind::Localize {
                episode: name.to_string(),
                side,
                lens,
            })
            .dir(&ctx.root)
            .join(POSES_FILE);
            if !poses.is_file() {
                continue;
            }
            match read_lens_frames(&poses) {
                Ok(mut frames) => {
                    // A camera is on the session timeline or not, whatever the time.
                    let c = clock(camera);
                    let session_clock = session_time(c, 0.0).is_some();
                    if session_clock {
                        for f in &mut frames {
                            f.t = session_time(c, f.t).unwrap_or(f.t);
                        }
                    }
                    lenses.push(LensTrack {
                        camera: camera.to_string(),
                        lens: lens.name().to_string(),
                        session_clock,
                        frames,
                    });
                }
                Err(e) => notes.push(e.to_string()),
            }
        }
    }
    let head_path = out.join(HEAD_PATH_FILE);
    let head = if head_path.is_file() {
        read_head_path(&head_path)
            .map_err(|e| notes.push(e.to_string()))
            .ok()
    } else {
        None
    };
    let floor_path = out.join(FLOOR_FIGURE_FILE);
    let floor_figure = if floor_path.is_file() {
        kiwi_core::io::read_text(&floor_path)
            .map_err(|e| notes.push(e.to_string()))
            .ok()
            // The page inlines the drawing: an XML declaration may not stand inside HTML.
            .map(|svg| match svg.find("<svg") {
                Some(at) => svg[at..].to_string(),
                None => svg,
            })
    } else {
        None
    };
    let (verdict, reasons) = match &quality {
        Some(q) => (Some(q.verdict), q.reasons.clone()),
        None => (
            None,
            vec!["not processed: run `kiwi run` on the session".to_string()],
        ),
    };
    EpisodeReport {
        name: name.to_string(),
        description: description.to_string(),
        verdict,
        reasons,
        quality,
        wrists,
        head,
        floor_figure,
        lenses,
        sync,
        stages: Vec::new(),
        notes,
    }
}

/// Read a TUM path (`t x y z qx qy qz qw` per line, `#` comments).
fn read_head_path(path: &Path) -> Result<Vec<(f64, [f64; 3])>> {
    let text = kiwi_core::io::read_text(path)?;
    let mut out = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let v: Vec<f64> = line
            .split_whitespace()
            .map(str::parse)
            .collect::<std::result::Result<_, _>>()
            .map_err(|e| crate::error::BackendError::Input {
                path: path.to_path_buf(),
                message: format!(
                    "line {}: not a TUM row ({e}): expected t x y z qx qy qz qw",
                    i + 1
                ),
            })?;
        if v.len() != 8 || v.iter().any(|x| !x.is_finite()) {
            return Err(crate::error::BackendError::Input {
                path: path.to_path_buf(),
                message: format!(
                    "line {}: expected 8 finite numbers (t x y z qx qy qz qw), found {}",
                    i + 1,
                    v.len()
                ),
            });
        }
        out.push((v[0], [v[1], v[2], v[3]]));
    }
    Ok(out)
}
