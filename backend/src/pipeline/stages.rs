//! What each stage reads, its version and parameters, and its body: read the typed outputs of
//! the stages before it, call the stage's module (`sync`, `vision`, `metric`, `placement`,
//! `observations`, `fusion`, `gripper`, `outputs`), write its outputs into the stage's folder.
//!
//! Outputs are deterministic (no wall times, no dates): the same inputs give byte-identical
//! files whatever the thread count, so an interrupted and resumed run ends exactly where an
//! uninterrupted one does. Wall times go to the manifests.

use std::path::{Path, PathBuf};

use kiwi_core::geometry::Pose;
use kiwi_core::imu::ImuSeries;
use kiwi_core::io::{sha256_bytes, write_atomic};
use kiwi_core::layout::{EpisodeLayout, Side};
use kiwi_core::tool::ToolCalibration;

use super::context::{SessionContext, WristContext};
use super::graph::{Lens, MapName, StageKind, id_of, wrist_output_deps};
use super::stage::{InputDigest, Manifest, StageId};
use crate::error::{BackendError, Result};
use crate::export::ExportFormat;
use crate::formats::results::{
    FrontWitness, MetricFile, PlacementFile, metric_from_localizations,
    placement_from_localizations, read_metric, read_placement, write_json,
};
use crate::formats::tables::{
    Localization, read_fused, read_localizations, read_observations, write_fused,
    write_observations,
};
use crate::fusion::{FusionConfig, PoseObservation, Source, fuse, visual_sigma_from_disagreement};
use crate::metric::MetricConfig;
use crate::observations::{
    RunArbiter, SceneReference, body_observations, body_observations_arbitrated,
    front_poses_from_rear, lens_poses_at, observations_in_other_front_map,
    rear_poses_from_other_front_map,
};
use crate::placement::PlacementConfig;
use crate::vision::episode::{
    LensStream, Witness, build_map_with, localize_around, localize_stream,
    localize_stream_with_witness, write_poses_csv,
};
use crate::vision::localize::{FrameLocalization, LocalizerOptions};
use crate::vision::map::VisualMap;

/// Called by a stage as it progresses: `(done, total)` in the stage's own units (frames).
pub type ProgressFn<'a> = &'a (dyn Fn(usize, usize) + Sync);

/// The map file inside a map stage's folder.
pub const MAP_FILE: &str = "map.kmap";
/// The localizations inside a localize stage's folder (the `kiwi localize` format).
pub const POSES_FILE: &str = "poses.csv";
/// The observations inside an observations stage's folder (the `kiwi fuse` format).
pub const OBSERVATIONS_FILE: &str = "obs.csv";
/// The fused trajectory inside a fusion stage's folder.
pub const FUSED_FILE: &str = "fused.csv";
/// The placement stage's record (`scene_from_front_map` and its residuals).
pub const PLACEMENT_FILE: &str = "placement.json";
/// The sync result inside the sync stage's folder.
pub const SYNC_FILE: &str = "sync.json";
/// The tool calibration (or why there is none) inside a tool stage's folder.
pub const TOOL_FILE: &str = "tool.json";
/// A stage's deterministic summary.
pub const SUMMARY_FILE: &str = "summary.json";

fn input(path: &Path, message: String) -> BackendError {
    BackendError::Input {
        path: path.to_path_buf(),
        message,
    }
}

/// The version of a stage's algorithm and output format: a change re-runs the stage.
pub fn version(kind: &StageKind) -> &'static str {
    match kind {
        StageKind::Sync { .. } => "sync-3",
        StageKind::Map { .. } => "map-5",
        StageKind::Tool { .. } => "tool-1",
        StageKind::Localize { .. } => "localize-12",
        StageKind::Metric { .. } => "metric-2",
        StageKind::Placement { .. } => "placement-3",
        StageKind::Observations { .. } => "observations-4",
        StageKind::Fusion { .. } => "fusion-4",
        StageKind::Gripper { .. } => "gripper-1",
        StageKind::Head { .. } => "head-2",
        StageKind::Floor { .. } => "floor-2",
        StageKind::Outputs { .. } => "outputs-5",
        StageKind::Export { .. } => "export-1",
        StageKind::Report => "report-1",
    }
}

/// The parameters a stage runs with (recorded in its manifest).
pub fn parameters(kind: &StageKind) -> serde_json::Value {
    match kind {
        StageKind::Map { .. } => serde_json::json!({ "loop_closure": true }),
        StageKind::Fusion { .. } => {
            let c = FusionConfig::default();
            serde_json::json!({
                "visual_sigma": "placement RMS / sqrt(2), both lenses",
                "min_visual_sigma": [
                    crate::fusion::MIN_VISUAL_SIGMA_POSITION_M,
                    crate::fusion::MIN_VISUAL_SIGMA_ROTATION_RAD
                ],
                "huber_k": c.huber_k,
                "max_interpolation_gap_s": c.max_interpolation_gap_s,
                "match_tolerance_s": c.match_tolerance_s,
            })
        }
        StageKind::Metric { .. } => {
            let c = MetricConfig::default();
            serde_json::json!({
                "sigma_position_m": c.sigma_position_m,
                "sigma_rotation_rad": c.sigma_rotation_rad,
                "huber_k": c.huber_k,
                "max_scale_sigma": c.max_scale_sigma,
            })
        }
        StageKind::Head { .. } => {
            let o = crate::head::track::TrackOptions::default();
            serde_json::json!({
                "rate_hz": o.rate_hz,
                "half_window_s": o.half_window_s,
                "outlier_spreads": o.outlier_spreads,
                "min_spread": [o.min_spread_m, o.min_spread_rad],
                "min_observations": o.min_observations,
                "min_ambiguity_ratio": crate::head::marker::MIN_AMBIGUITY_RATIO,
                "max_corner_error_rad": crate::head::marker::MAX_CORNER_ERROR_RAD,
                "min_marker_size_px": crate::head::marker::MIN_MARKER_SIZE_PX,
                "previous_sighting_max_age_s": crate::head::episode::PREVIOUS_SIGHTING_MAX_AGE_S,
                "max_node_gap_s": crate::head::episode::MAX_NODE_GAP_S,
            })
        }
        // The band is an input (from session.toml); the rest are the algorithm's settings.
        StageKind::Floor { .. } => {
            let o = crate::floor::FloorOptions::default();
            serde_json::json!({
                "window_s": o.window_s,
                "max_windows": o.max_windows,
                "sweep": o.sweep,
                "stereo": o.stereo,
            })
        }
        _ => serde_json::Value::Null,
    }
}

/// Digest of a file's content, named for the manifest.
fn file_input(ctx: &SessionContext, name: String, path: &Path) -> Result<InputDigest> {
    if !path.is_file() {
        return Err(input(
            path,
            format!(
                "missing: the stage needs it ({name}); re-ingest the episode or fix the session"
            ),
        ));
    }
    Ok(InputDigest {
        name,
        path: ctx.relative(path),
        digest: ctx.digests.sha256(path)?,
    })
}

/// Digest of a lens stream. An image stream: its `frames.csv` and every frame file's name and
/// size (the images are not read: hashing hundreds of gigabytes of frames per check would cost
/// more than the check saves; a frame replaced by one of the same size is not noticed). A video
/// stream: its `frames.csv`, `video.json` and the video's content (one sequential read,
/// remembered while the file keeps its size and time: [`super::digests`]).
pub fn stream_input(
    ctx: &SessionContext,
    layout: &EpisodeLayout,
    camera: &str,
    lens: &str,
) -> Result<InputDigest> {
    let csv = layout.frames_csv(camera, lens);
    if !csv.is_file() {
        return Err(input(
            &csv,
            format!(
                "missing: expected lens `{lens}` of camera `{camera}` in episode {} (every wrist \
                 records both lenses); re-ingest the episode",
                layout
                    .root()
                    .file_name()
                    .map_or_else(String::new, |n| n.to_string_lossy().into_owned())
            ),
        ));
    }
    let frames = kiwi_core::layout::read_frames_csv(&csv)?;
    let mut text = ctx.digests.sha256(&csv)?;
    text.push('\n');
    match kiwi_core::layout::LensStorage::of(&layout.lens_dir(camera, lens))? {
        kiwi_core::layout::LensStorage::Video(video) => {
            video.check_frames(&csv, &frames)?;
            text.push_str(&ctx.digests.sha256(&layout.video_json(camera, lens))?);
            text.push('\n');
            let file = layout.lens_dir(camera, lens).join(&video.file);
            text.push_str(&format!("{}={}\n", video.file, ctx.digests.sha256(&file)?));
        }
        kiwi_core::layout::LensStorage::Images => {
            for f in &frames {
                let path = layout.frame_path(camera, lens, f);
                let size = std::fs::metadata(&path).map(|m| m.len()).map_err(|e| {
                    input(
                        &path,
                        format!("frame listed in {} cannot be read: {e}", csv.display()),
                    )
                })?;
                text.push_str(&format!("{}={size}\n", f.file));
            }
        }
    }
    Ok(InputDigest {
        name: format!("stream {camera}/{lens}"),
        path: ctx.relative(&layout.lens_dir(camera, lens)),
        digest: sha256_bytes(text.as_bytes()),
    })
}

fn calibration_input(ctx: &SessionContext, wrist: &WristContext) -> Result<InputDigest> {
    file_input(
        ctx,
        format!("calibration {}", wrist.camera),
        &wrist.calibration_path,
    )
}

/// Every camera's calibration: both wrists' units and the head camera's, when there is one.
fn calibration_inputs(ctx: &SessionContext) -> Result<Vec<InputDigest>> {
    let mut v = Vec::new();
    for w in ctx.wrists.values() {
        v.push(calibration_input(ctx, w)?);
    }
    if let Some(h) = &ctx.session.head {
        v.push(file_input(
            ctx,
            "calibration head".into(),
            &ctx.root.join(&h.calibration).join("calibration.json"),
        )?);
    }
    Ok(v)
}

fn wrist(ctx: &SessionContext, side: Side) -> Result<&WristContext> {
    ctx.wrists.get(&side).ok_or_else(|| {
        input(
            &ctx.toml,
            format!("no [wrists.{}] in the session", side.camera_name()),
        )
    })
}

/// The stage's own inputs (files and streams); the outputs of the stages it depends on are
/// added by the runner.
pub fn inputs(ctx: &SessionContext, kind: &StageKind) -> Result<Vec<InputDigest>> {
    let map_ep = ctx.episode(&ctx.session.map_episode);
    Ok(match kind {
        StageKind::Sync { episode } => {
            let layout = ctx.episode(episode);
            let mut v = Vec::new();
            for camera in ctx.session.camera_names() {
                v.push(file_input(
                    ctx,
                    format!("audio {camera}"),
                    &layout.audio_wav(camera),
                )?);
                v.push(file_input(
                    ctx,
                    format!("meta {camera}"),
                    &layout.meta_json(camera),
                )?);
            }
            v.extend(calibration_inputs(ctx)?);
            v
        }
        StageKind::Map { map } => {
            let (side, lens) = map_source(ctx, *map);
            let w = wrist(ctx, side)?;
            vec![
                stream_input(ctx, &map_ep, w.camera, lens.name())?,
                calibration_input(ctx, w)?,
            ]
        }
        StageKind::Tool { side } => {
            let w = wrist(ctx, *side)?;
            let mut v = vec![
                stream_input(ctx, &map_ep, w.camera, "front")?,
                calibration_input(ctx, w)?,
            ];
            if let Some(def) = &w.tool {
                v.push(InputDigest {
                    name: "tool definition".into(),
                    path: format!("hardware/tools/{}.toml", def.name),
                    digest: sha256_bytes(serde_json::to_string(def).unwrap_or_default().as_bytes()),
                });
            }
            v
        }
        StageKind::Localize {
            episode,
            side,
            lens,
        } => {
            let w = wrist(ctx, *side)?;
            let mut v = vec![
                stream_input(ctx, &ctx.episode(episode), w.camera, lens.name())?,
                calibration_input(ctx, w)?,
            ];
            if rear_witnessed(ctx, episode, *side, *lens) {
                // The witness reads this wrist's front stream of the mapping episode.
                v.push(stream_input(ctx, &map_ep, w.camera, Lens::Front.name())?);
            }
            v
        }
        StageKind::Metric { map } => {
            let (side, _) = map_source(ctx, *map);
            let w = wrist(ctx, side)?;
            vec![
                file_input(ctx, format!("imu {}", w.camera), &map_ep.imu_csv(w.camera))?,
                calibration_input(ctx, w)?,
            ]
        }
        StageKind::Placement { side } => vec![calibration_input(ctx, wrist(ctx, *side)?)?],
        StageKind::Observations { episode, side } => {
            let w = wrist(ctx, *side)?;
            vec![
                calibration_input(ctx, w)?,
                file_input(
                    ctx,
                    format!("meta {}", w.camera),
                    &ctx.episode(episode).meta_json(w.camera),
                )?,
            ]
        }
        StageKind::Fusion { episode, side } => {
            let w = wrist(ctx, *side)?;
            let layout = ctx.episode(episode);
            vec![
                file_input(ctx, format!("imu {}", w.camera), &layout.imu_csv(w.camera))?,
                file_input(
                    ctx,
                    format!("meta {}", w.camera),
                    &layout.meta_json(w.camera),
                )?,
                file_input(
                    ctx,
                    format!("frames {}/front", w.camera),
                    &layout.frames_csv(w.camera, "front"),
                )?,
                calibration_input(ctx, w)?,
            ]
        }
        StageKind::Gripper { episode, side } => {
            let w = wrist(ctx, *side)?;
            vec![
                stream_input(ctx, &ctx.episode(episode), w.camera, "front")?,
                calibration_input(ctx, w)?,
            ]
        }
        StageKind::Head { episode } => {
            let layout = ctx.episode(episode);
            let mut v = calibration_inputs(ctx)?;
            for w in ctx.wrists.values() {
                v.push(stream_input(ctx, &layout, w.camera, "rear")?);
                v.push(file_input(
                    ctx,
                    format!("frames {}/front", w.camera),
                    &layout.frames_csv(w.camera, "front"),
                )?);
                v.push(file_input(
                    ctx,
                    format!("meta {}", w.camera),
                    &layout.meta_json(w.camera),
                )?);
            }
            if let Some(h) = &ctx.session.head {
                let lens = head_lens(ctx, episode)?;
                v.push(file_input(
                    ctx,
                    format!("frames head/{lens}"),
                    &layout.frames_csv("head", &lens),
                )?);
                v.push(InputDigest {
                    name: "head marker".into(),
                    path: ctx.relative(&ctx.toml),
                    digest: sha256_bytes(
                        format!(
                            "{} {} {}",
                            h.marker_dictionary, h.marker_id, h.marker_size_m
                        )
                        .as_bytes(),
                    ),
                });
                let (mount, _) = head_mount(ctx)?;
                v.push(InputDigest {
                    name: "head mount".into(),
                    path: h.mount.as_ref().map_or_else(
                        || kiwi_core::head::BUILTIN_HEAD_MOUNT_PATH.to_string(),
                        |m| ctx.relative(&ctx.root.join(m)),
                    ),
                    digest: sha256_bytes(
                        serde_json::to_string(&mount).unwrap_or_default().as_bytes(),
                    ),
                });
            }
            v
        }
        StageKind::Floor { episode } => {
            let layout = ctx.episode(episode);
            let mut v = Vec::new();
            for w in ctx.wrists.values() {
                v.push(calibration_input(ctx, w)?);
                v.push(stream_input(ctx, &layout, w.camera, "front")?);
                v.push(file_input(
                    ctx,
                    format!("meta {}", w.camera),
                    &layout.meta_json(w.camera),
                )?);
            }
            v.push(InputDigest {
                name: "floor band".into(),
                path: ctx.relative(&ctx.toml),
                digest: sha256_bytes(format!("{:?}", floor_band(ctx)).as_bytes()),
            });
            v
        }
        StageKind::Outputs { .. } => {
            let mut v = Vec::new();
            for w in ctx.wrists.values() {
                v.push(calibration_input(ctx, w)?);
                if let Some(def) = &w.tool {
                    v.push(InputDigest {
                        name: format!("tool {}", w.camera),
                        path: format!("hardware/tools/{}.toml", def.name),
                        digest: sha256_bytes(
                            serde_json::to_string(def).unwrap_or_default().as_bytes(),
                        ),
                    });
                }
            }
            v
        }
        StageKind::Export { format } => export_inputs(ctx, *format)?,
        // The episodes' names and descriptions and the wrists' tools come from session.toml;
        // the rest is the outputs of the stages it reads.
        StageKind::Report => vec![file_input(ctx, "session".into(), &ctx.toml)?],
    })
}

/// What an export reads besides the episodes' outputs: the `[export]` settings,
/// `session.toml`, the calibrations, and in every episode each camera's `meta.json` and the
/// lens streams that are views of the dataset (the named views, else every wrist's front lens
/// and the head camera's lenses; for the scene formats every wrist lens, and the maps with
/// their metric and placement files, whose landmarks are the scene points).
fn export_inputs(ctx: &SessionContext, format: ExportFormat) -> Result<Vec<InputDigest>> {
    let scene = matches!(format, ExportFormat::Colmap | ExportFormat::Nerfstudio);
    let settings = serde_json::to_string(&ctx.session.export).unwrap_or_default();
    let mut v = vec![
        InputDigest {
            name: "export settings".into(),
            path: "session.toml [export]".into(),
            digest: sha256_bytes(settings.as_bytes()),
        },
        file_input(ctx, "session".into(), &ctx.toml)?,
    ];
    v.extend(calibration_inputs(ctx)?);
    let named = ctx.session.export.as_ref().and_then(|x| x.views.clone());
    for episode in ctx.episode_names() {
        let layout = ctx.episode(&episode);
        for camera in ctx.session.camera_names() {
            let meta = layout.meta_json(camera);
            if !meta.is_file() {
                // A camera an episode lacks: the export names it when it matters.
                continue;
            }
            v.push(file_input(ctx, format!("{episode} meta {camera}"), &meta)?);
            let lenses: Vec<String> = match &named {
                Some(views) => views
                    .iter()
                    .filter_map(|n| n.split_once('.'))
                    .filter(|(c, _)| *c == camera)
                    .map(|(_, l)| l.to_string())
                    .collect(),
                None if scene && camera == "head" => Vec::new(),
                None if camera == "head" || scene => layout.read_meta(camera)?.lenses,
                None => vec!["front".into()],
            };
            for lens in lenses {
                if layout.frames_csv(camera, &lens).is_file() {
                    let mut d = stream_input(ctx, &layout, camera, &lens)?;
                    d.name = format!("{episode} {}", d.name);
                    v.push(d);
                }
            }
        }
    }
    if scene {
        let mut maps = vec![MapName::Rear];
        maps.extend(ctx.wrists.keys().map(|s| MapName::Front(*s)));
        for map in maps {
            let stage = |kind: StageKind| id_of(&kind).dir(&ctx.root);
            let mut files = vec![
                stage(StageKind::Map { map }).join(MAP_FILE),
                stage(StageKind::Metric { map }).join("metric.json"),
            ];
            if let MapName::Front(side) = map {
                files.push(stage(StageKind::Placement { side }).join(PLACEMENT_FILE));
            }
            for f in files {
                v.push(file_input(
                    ctx,
                    format!("{} {}", map.label(), f.display()),
                    &f,
                )?);
            }
        }
    }
    Ok(v)
}

/// The wrist and lens a map is built from.
pub fn map_source(ctx: &SessionContext, map: MapName) -> (Side, Lens) {
    match map {
        MapName::Rear => (ctx.map_side(), Lens::Rear),
        MapName::Front(side) => (side, Lens::Front),
    }
}

/// Everything a stage body needs.
pub struct StageEnv<'a> {
    /// The session.
    pub ctx: &'a SessionContext,
    /// Where to write the outputs.
    pub out: &'a Path,
    /// Progress callback.
    pub progress: ProgressFn<'a>,
    /// Stages it reads that failed or were blocked this run, with the reason (only those it can
    /// do without: [`super::graph::StageNode::optional`]); their folders hold nothing to read.
    pub unavailable: &'a [(StageId, String)],
}

impl StageEnv<'_> {
    fn dep_dir(&self, kind: &StageKind) -> PathBuf {
        id_of(kind).dir(&self.ctx.root)
    }

    /// Whether every one of `stages` gave its outputs this run.
    fn available(&self, stages: &[StageId]) -> bool {
        self.missing(stages).is_none()
    }

    /// The first of `stages` that gave no outputs this run, with why.
    fn missing(&self, stages: &[StageId]) -> Option<&(StageId, String)> {
        self.unavailable.iter().find(|(id, _)| stages.contains(id))
    }
}

/// A JSON value with wall-time fields removed, so that the written summary is deterministic.
fn without_timings(value: serde_json::Value) -> serde_json::Value {
    match value {
        serde_json::Value::Object(mut m) => {
            // Wall-clock figures depend on the machine and its load: results must not.
            for key in [
                "seconds",
                "frames_per_second",
                "frames_per_s",
                "relocalization_ms_per_attempt",
            ] {
                m.remove(key);
            }
            serde_json::Value::Object(m)
        }
        other => other,
    }
}

fn write_summary<T: serde::Serialize>(dir: &Path, value: &T) -> Result<()> {
    let v = serde_json::to_value(value).map_err(|e| BackendError::Input {
        path: dir.join(SUMMARY_FILE),
        message: e.to_string(),
    })?;
    write_json(&dir.join(SUMMARY_FILE), &without_timings(v))
}

/// Run a stage's body.
pub fn run(env: &StageEnv<'_>, kind: &StageKind) -> Result<()> {
    match kind {
        StageKind::Sync { episode } => run_sync(env, episode),
        StageKind::Map { map } => run_map(env, *map),
        StageKind::Tool { side } => run_tool(env, *side),
        StageKind::Localize {
            episode,
            side,
            lens,
        } => run_localize(env, episode, *side, *lens),
        StageKind::Metric { map } => run_metric(env, *map),
        StageKind::Placement { side } => run_placement(env, *side),
        StageKind::Observations { episode, side } => run_observations(env, episode, *side),
        StageKind::Fusion { episode, side } => run_fusion(env, episode, *side),
        StageKind::Gripper { episode, side } => run_gripper(env, episode, *side),
        StageKind::Head { episode } => run_head(env, episode),
        StageKind::Floor { episode } => run_floor(env, episode),
        StageKind::Outputs { episode } => run_outputs(env, episode),
        StageKind::Export { format } => run_export(env, *format),
        StageKind::Report => {
            crate::report::write_report(
                env.ctx,
                &env.out.join(PUBLISHED_DIR).join(crate::report::PAGE_FILE),
            )?;
            Ok(())
        }
    }
}

/// A dataset of every usable episode, written into the stage's `out/` (published as
/// `exports/<format>/`); episodes whose outputs failed or are unusable are left out, each with
/// its reason in the summary.
fn run_export(env: &StageEnv<'_>, format: ExportFormat) -> Result<()> {
    let config = env.ctx.session.export.clone();
    let options = crate::export::ExportOptions {
        fps: config.as_ref().and_then(|x| x.fps),
        rate: config.as_ref().and_then(|x| x.rate),
        views: config.and_then(|x| x.views),
        episodes: None,
    };
    let report = crate::export::export(
        &env.ctx.toml,
        format,
        &options,
        &env.out.join(PUBLISHED_DIR),
    )?;
    write_summary(env.out, &report)
}

fn run_sync(env: &StageEnv<'_>, episode: &str) -> Result<()> {
    let layout = env.ctx.episode(episode);
    let mut cameras: Vec<(String, PathBuf)> = env
        .ctx
        .wrists
        .values()
        .map(|w| (w.camera.to_string(), w.calibration_path.clone()))
        .collect();
    if let Some(h) = &env.ctx.session.head {
        cameras.push((
            "head".into(),
            env.ctx.root.join(&h.calibration).join("calibration.json"),
        ));
    }
    let mut inputs = Vec::new();
    for (k, (camera, calibration_path)) in cameras.iter().enumerate() {
        let meta = layout.read_meta(camera)?;
        let calibration = kiwi_core::artifact::UnitCalibration::load(calibration_path)?;
        inputs.push(crate::sync::SyncInput {
            name: camera.clone(),
            audio: crate::sync::audio::read_audio(&layout.audio_wav(camera))?,
            av_delay_s: crate::sync::av_delay_for(
                &calibration,
                Some(&meta.mode),
                calibration_path,
            )?,
        });
        (env.progress)(k + 1, cameras.len() + 1);
    }
    let result = crate::sync::synchronise(&inputs);
    write_json(&env.out.join(SYNC_FILE), &result)
}

fn open_stream(ctx: &SessionContext, episode: &str, side: Side, lens: Lens) -> Result<LensStream> {
    let w = wrist(ctx, side)?;
    LensStream::open(
        ctx.episode(episode).root(),
        w.camera,
        lens.name(),
        Some(&w.calibration_path),
        None,
    )
}

fn run_map(env: &StageEnv<'_>, map: MapName) -> Result<()> {
    let (side, lens) = map_source(env.ctx, map);
    let stream = open_stream(env.ctx, &env.ctx.session.map_episode, side, lens)?;
    let context = format!(
        "map {} from {}",
        map.label(),
        env.ctx.relative(
            &env.ctx
                .episode(&env.ctx.session.map_episode)
                .lens_dir(wrist(env.ctx, side)?.camera, lens.name())
        )
    );
    let (vmap, summary) = build_map_with(&stream, true, &mut |done, total| {
        (env.progress)(done, total);
    })
    .map_err(|e| match e {
        // Name the stream the map was built from: the mapper's own errors do not know it.
        BackendError::Vision { message, .. } => BackendError::Vision {
            context: context.clone(),
            message,
        },
        other => other,
    })?;
    if summary.keyframes < 2 || summary.landmarks == 0 {
        return Err(BackendError::Vision {
            context,
            message: format!(
                "the stream gave {} keyframes and {} landmarks: not a map; record the mapping \
                 episode with slower, wider motion over textured surroundings",
                summary.keyframes, summary.landmarks
            ),
        });
    }
    vmap.save(&env.out.join(MAP_FILE))?;
    write_summary(env.out, &summary)
}

fn run_tool(env: &StageEnv<'_>, side: Side) -> Result<()> {
    let w = wrist(env.ctx, side)?;
    let Some(def) = &w.tool else {
        return Ok(());
    };
    let layout = env.ctx.episode(&env.ctx.session.map_episode);
    let lens_dir = layout.lens_dir(w.camera, "front");
    let frames = kiwi_core::layout::read_frames_csv(&layout.frames_csv(w.camera, "front"))?;
    let lens = w.calibration.lens("front").ok_or_else(|| {
        input(
            &w.calibration_path,
            "field `lenses`: no lens named `front`".into(),
        )
    })?;
    let camera = lens.camera()?;
    let options = crate::gripper::calibrate::CalibrateOptions {
        max_frames: TOOL_CALIBRATION_FRAMES,
        unit_id: w.calibration.unit_id.clone(),
        lens: "front".into(),
        unit_calibration_date: w.calibration.date.clone(),
    };
    let done = std::sync::atomic::AtomicUsize::new(0);
    let total = TOOL_CALIBRATION_FRAMES.min(frames.len());
    let record = match crate::gripper::calibrate::calibrate_tool(
        &camera,
        def,
        &lens_dir,
        &frames,
        &options,
        &|| {
            let d = done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
            (env.progress)(d, total);
        },
    ) {
        Ok(tc) => ToolRecord {
            calibrated: true,
            reason: None,
            calibration: Some(tc),
        },
        Err(e) => ToolRecord {
            calibrated: false,
            reason: Some(format!(
                "{e}; the opening is measured with the tool definition's CAD geometry"
            )),
            calibration: None,
        },
    };
    write_json(&env.out.join(TOOL_FILE), &record)
}

/// `summary.json` of a fusion stage.
#[derive(Debug, Clone, Copy, serde::Serialize, serde::Deserialize)]
pub struct FusionSummary {
    /// Solver and residual statistics.
    #[serde(flatten)]
    pub statistics: crate::fusion::FusionStatistics,
    /// Front frames outside the IMU log (not fused, not in the outputs).
    pub frames_outside_imu: usize,
}

/// Frames of the map episode searched for the tool's body tag.
const TOOL_CALIBRATION_FRAMES: usize = 60;

/// `tool.json` of a tool stage: the calibration, or why the CAD geometry is used.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct ToolRecord {
    /// Whether the body tag gave a calibration.
    pub calibrated: bool,
    /// Why not.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reason: Option<String>,
    /// The calibration.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub calibration: Option<ToolCalibration>,
}

/// Whether a localization stage has a witness of where its lens stands
/// ([`super::graph::rear_witness_deps`]): the mapping episode's rear stream of a wrist that did
/// not build the rear map.
pub fn rear_witnessed(ctx: &SessionContext, episode: &str, side: Side, lens: Lens) -> bool {
    lens == Lens::Rear
        && episode == ctx.session.map_episode
        && !super::graph::rear_witness_deps(ctx, side).is_empty()
}

/// The witness of where the rear lens of `side` stands in the mapping episode (`rear_times`,
/// its frames): this wrist's front stream localized in the map wrist's front map, carried into
/// the rear map through that map's metric recovery and placement
/// ([`rear_poses_from_other_front_map`]).
fn rear_witness(env: &StageEnv<'_>, side: Side, rear_times: &[f64]) -> Result<Vec<Option<Pose>>> {
    let map_ep = env.ctx.session.map_episode.clone();
    let results =
        front_in_other_front_map(env, &map_ep, side, "the witness of the rear lens's runs")?;
    // Kept for the placement, which pools the same witness.
    write_poses_csv(&env.out.join(WITNESS_FILE), &results)?;
    let rows = valid_rows(&results);
    let w = wrist(env.ctx, side)?;
    let other = scene_reference(env.ctx, side.other())?;
    Ok(rear_poses_from_other_front_map(
        rear_times, &rows, &other, &w.front, &w.rear,
    ))
}

/// The front stream of `side` in `episode` localized in the other wrist's front map (`why`
/// says what for, in the log).
fn front_in_other_front_map(
    env: &StageEnv<'_>,
    episode: &str,
    side: Side,
    why: &str,
) -> Result<Vec<FrameLocalization>> {
    let other = side.other();
    let map = VisualMap::load(
        &env.dep_dir(&StageKind::Map {
            map: MapName::Front(other),
        })
        .join(MAP_FILE),
    )?;
    let front = open_stream(env.ctx, episode, side, Lens::Front)?;
    let (results, summary) =
        localize_stream(&map, &front, &LocalizerOptions::default(), &mut |_, _| {})?;
    tracing::info!(
        "{episode}/{}: the front lens has a pose at {} of {} frames in the {} front map ({why})",
        side.camera_name(),
        summary.localized,
        summary.frames,
        other.camera_name()
    );
    Ok(results)
}

/// Per-frame localizations as the rows the estimation stages read.
fn valid_rows(results: &[FrameLocalization]) -> Vec<Localization> {
    (results.iter())
        .map(|r| Localization {
            t: r.t,
            valid: r.map_from_cam.is_some(),
            map_from_cam: r.map_from_cam.unwrap_or_else(Pose::identity),
        })
        .collect()
}

/// `witness.csv` of the mapping episode's rear stage of a wrist that did not build the rear
/// map, when it asked the witness: the wrist's front stream in the other wrist's front map
/// (the `poses.csv` format).
pub const WITNESS_FILE: &str = "witness.csv";

/// The front stream of `side` in `episode` in the other wrist's front map (`why` says what
/// for, in the log): in the mapping episode as that episode's rear stage kept it when it asked
/// ([`WITNESS_FILE`]), else localized now.
fn witness_rows(
    env: &StageEnv<'_>,
    episode: &str,
    side: Side,
    why: &str,
) -> Result<Vec<Localization>> {
    let kept = env
        .dep_dir(&StageKind::Localize {
            episode: episode.to_string(),
            side,
            lens: Lens::Rear,
        })
        .join(WITNESS_FILE);
    if episode == env.ctx.session.map_episode && kept.is_file() {
        return read_localizations(&kept);
    }
    Ok(valid_rows(&front_in_other_front_map(
        env, episode, side, why,
    )?))
}

/// The pipeline's [`RunArbiter`] for one wrist in one episode: its lenses' frames localized
/// around where the other lens places the wrist, and its front lens seen in the other wrist's
/// front map. Evidence that cannot be made is logged and counts as none.
struct StageArbiter<'a, 'e> {
    env: &'a StageEnv<'e>,
    episode: &'a str,
    side: Side,
    reference: SceneReference,
    exposure_centre_s: f64,
    /// Whether the other wrist's front map, metric recovery and placement are there.
    witnessed: bool,
}

impl StageArbiter<'_, '_> {
    fn try_localize_at(&self, lens: Lens, at: &[PoseObservation]) -> Result<Vec<PoseObservation>> {
        let (ctx, side) = (self.env.ctx, self.side);
        let w = wrist(ctx, side)?;
        let (source, calibration) = match lens {
            Lens::Front => (Source::Front, &w.front),
            Lens::Rear => (Source::Rear, &w.rear),
        };
        let map = VisualMap::load(
            &(self.env)
                .dep_dir(&StageKind::Map {
                    map: MapName::for_lens(side, lens),
                })
                .join(MAP_FILE),
        )?;
        let mut stream = open_stream(ctx, self.episode, side, lens)?;
        let times: Vec<f64> = stream.frames.iter().map(|f| f.t).collect();
        let around = lens_poses_at(
            &times,
            at,
            source,
            &self.reference,
            calibration,
            self.exposure_centre_s,
        );
        let keep: Vec<usize> = (0..around.len()).filter(|&i| around[i].is_some()).collect();
        if keep.is_empty() {
            return Ok(Vec::new());
        }
        let around: Vec<Option<Pose>> = keep.iter().map(|&i| around[i]).collect();
        stream.select(&keep)?;
        let results = localize_around(&map, &stream, &LocalizerOptions::default(), &around)?;
        let rows = valid_rows(&results);
        let (front, rear) = match lens {
            Lens::Front => (rows.as_slice(), &[][..]),
            Lens::Rear => (&[][..], rows.as_slice()),
        };
        let (obs, _) = body_observations(
            front,
            rear,
            &self.reference,
            &w.front,
            &w.rear,
            self.exposure_centre_s,
        );
        tracing::info!(
            "{}/{}: the {} lens localized at {} of {} moments around where the other lens \
             places the wrist",
            self.episode,
            side.camera_name(),
            lens.name(),
            obs.len(),
            keep.len()
        );
        Ok(obs)
    }
}

impl RunArbiter for StageArbiter<'_, '_> {
    fn localize_at(&mut self, lens: Source, at: &[PoseObservation]) -> Vec<PoseObservation> {
        let lens = match lens {
            Source::Front => Lens::Front,
            Source::Rear => Lens::Rear,
        };
        self.try_localize_at(lens, at)
            .map_err(|e| {
                tracing::warn!(
                    "{}/{}: the {} lens could not be tried where the other lens places the \
                     wrist ({e})",
                    self.episode,
                    self.side.camera_name(),
                    lens.name()
                );
            })
            .unwrap_or_default()
    }

    fn witness(&mut self) -> Option<Vec<PoseObservation>> {
        if !self.witnessed {
            return None;
        }
        observation_witness(self.env, self.episode, self.side, self.exposure_centre_s)
    }
}

/// The third vote where the two lenses of `side` disagree in `episode`: its front lens seen in
/// the other wrist's front map, as body observations through that wrist's placement; `None`
/// (with a warning) when it cannot be computed.
fn observation_witness(
    env: &StageEnv<'_>,
    episode: &str,
    side: Side,
    exposure_centre_s: f64,
) -> Option<Vec<PoseObservation>> {
    let make = || -> Result<Vec<PoseObservation>> {
        let rows = witness_rows(
            env,
            episode,
            side,
            "the third vote where its front and rear lenses disagree",
        )?;
        let w = wrist(env.ctx, side)?;
        let other = scene_reference(env.ctx, side.other())?;
        Ok(observations_in_other_front_map(
            &rows,
            &other,
            &w.front,
            exposure_centre_s,
        ))
    };
    make()
        .map_err(|e| {
            tracing::warn!(
                "{episode}/{}: the other wrist's front map could not witness where the wrist \
                 is ({e}); disagreeing runs are judged without it",
                side.camera_name()
            );
        })
        .ok()
}

fn run_localize(env: &StageEnv<'_>, episode: &str, side: Side, lens: Lens) -> Result<()> {
    let map_dir = env.dep_dir(&StageKind::Map {
        map: MapName::for_lens(side, lens),
    });
    let map = VisualMap::load(&map_dir.join(MAP_FILE))?;
    let stream = open_stream(env.ctx, episode, side, lens)?;
    let reference = if lens == Lens::Front && episode != env.ctx.session.map_episode {
        Some(scene_reference(env.ctx, side)?)
    } else {
        None
    };
    let other_lens = match &reference {
        Some(reference) => {
            let w = wrist(env.ctx, side)?;
            let rear = localizations_of(env, episode, side, Lens::Rear)?;
            let times: Vec<f64> = stream.frames.iter().map(|f| f.t).collect();
            front_poses_from_rear(&times, &rear, reference, &w.front, &w.rear)
        }
        None => Vec::new(),
    };
    let witnessed = rear_witnessed(env.ctx, episode, side, lens)
        && env.available(&super::graph::rear_witness_deps(env.ctx, side));
    let rear_times: Vec<f64> = stream.frames.iter().map(|f| f.t).collect();
    let mut ask = || rear_witness(env, side, &rear_times);
    let (results, summary) = localize_stream_with_witness(
        &map,
        &stream,
        &LocalizerOptions::default(),
        &other_lens,
        witnessed.then_some(&mut ask as Witness<'_>),
        &mut |done, total| (env.progress)(done, total),
    )?;
    if let (Some(reference), Some(agreement)) =
        (&reference, other_lens_agreement(&results, &other_lens))
    {
        let scale = reference.front_metric.scale;
        tracing::info!(
            "{episode}/{}: the rear lens's prediction of the front pose is {:.1} mm and {:.2}° \
             off the front's own pose (median over {} frames; 95th percentile {:.1} mm)",
            side.camera_name(),
            1e3 * scale * agreement.median_distance,
            agreement.median_angle_deg,
            agreement.frames,
            1e3 * scale * agreement.p95_distance,
        );
    }
    write_poses_csv(&env.out.join(POSES_FILE), &results)?;
    write_summary(env.out, &summary)
}

/// How far the other lens's predictions lie from the poses a stream found itself.
struct LensAgreement {
    /// Frames with both.
    frames: usize,
    /// Median position difference (map units).
    median_distance: f64,
    /// 95th percentile of the position difference (map units).
    p95_distance: f64,
    /// Median rotation difference (degrees).
    median_angle_deg: f64,
}

/// [`LensAgreement`] of `results` with `predicted` (`map_from_cam` per frame); `None` without
/// a frame that has both.
fn other_lens_agreement(
    results: &[FrameLocalization],
    predicted: &[Option<Pose>],
) -> Option<LensAgreement> {
    let (mut distances, mut angles): (Vec<f64>, Vec<f64>) = results
        .iter()
        .zip(predicted)
        .filter_map(|(r, p)| {
            let d = r.map_from_cam?.inverse() * (*p)?;
            Some((d.translation.vector.norm(), d.rotation.angle().to_degrees()))
        })
        .unzip();
    distances.sort_by(f64::total_cmp);
    angles.sort_by(f64::total_cmp);
    let n = distances.len();
    (n > 0).then(|| LensAgreement {
        frames: n,
        median_distance: distances[n / 2],
        p95_distance: distances[(n * 95 / 100).min(n - 1)],
        median_angle_deg: angles[n / 2],
    })
}

fn localizations_of(
    env: &StageEnv<'_>,
    episode: &str,
    side: Side,
    lens: Lens,
) -> Result<Vec<Localization>> {
    let dir = env.dep_dir(&StageKind::Localize {
        episode: episode.to_string(),
        side,
        lens,
    });
    read_localizations(&dir.join(POSES_FILE))
}

fn run_metric(env: &StageEnv<'_>, map: MapName) -> Result<()> {
    let (side, lens) = map_source(env.ctx, map);
    let w = wrist(env.ctx, side)?;
    let map_ep = env.ctx.session.map_episode.clone();
    let rows = localizations_of(env, &map_ep, side, lens)?;
    let imu_path = env.ctx.episode(&map_ep).imu_csv(w.camera);
    let imu = ImuSeries::read_csv(&imu_path)?;
    let cal = match lens {
        Lens::Front => &w.front,
        Lens::Rear => &w.rear,
    };
    let centre = exposure_centre_delay(env.ctx, &map_ep, w)?;
    let mut file = metric_from_localizations(
        &rows,
        &imu,
        lens.name(),
        cal,
        &w.imu,
        centre,
        &MetricConfig::default(),
        std::time::Instant::now(),
    )
    .map_err(|e| {
        BackendError::Estimation(format!(
            "metric recovery of the {} map: {e}; {}",
            map.label(),
            lens_outcome(env, &map_ep, side, lens)
        ))
    })?;
    file.seconds = None;
    write_json(&env.out.join("metric.json"), &file)
}

fn metric_of_map(env: &StageEnv<'_>, map: MapName) -> Result<MetricFile> {
    read_metric(&env.dep_dir(&StageKind::Metric { map }).join("metric.json"))
}

fn run_placement(env: &StageEnv<'_>, side: Side) -> Result<()> {
    let w = wrist(env.ctx, side)?;
    let map_ep = env.ctx.session.map_episode.clone();
    let front = localizations_of(env, &map_ep, side, Lens::Front)?;
    let rear = localizations_of(env, &map_ep, side, Lens::Rear)?;
    let front_metric = metric_of_map(env, MapName::Front(side))?;
    let rear_metric = metric_of_map(env, MapName::Rear)?;
    let path = env.dep_dir(&StageKind::Metric {
        map: MapName::Front(side),
    });
    // The wrist that did not build the rear map also has its front lens seen in the other
    // wrist's front map: pooled in, when that map and its placement are there.
    let witness_deps = super::graph::rear_witness_deps(env.ctx, side);
    let witness = if !witness_deps.is_empty() && env.available(&witness_deps) {
        match (
            witness_rows(
                env,
                &env.ctx.session.map_episode,
                side,
                "pooled into its placement",
            ),
            scene_reference(env.ctx, side.other()),
        ) {
            (Ok(rows), Ok(other)) => Some((rows, other)),
            (Err(e), _) | (_, Err(e)) => {
                tracing::warn!(
                    "placement of the {} front map: the other wrist's front map could not \
                     witness it ({e}); placed from the rear lens alone",
                    side.camera_name()
                );
                None
            }
        }
    } else {
        None
    };
    let file = placement_from_localizations(
        &front,
        &rear,
        &w.front,
        &w.rear,
        &front_metric.world_from_map.to_sim3(&path)?,
        &rear_metric.world_from_map.to_sim3(&path)?,
        witness.as_ref().map(|(rows, other)| FrontWitness {
            rows,
            other_front_sim: other.front_metric,
            scene_from_other_front_map: other.scene_from_front_map,
        }),
        &PlacementConfig::default(),
    )
    .map_err(|e| {
        BackendError::Estimation(format!(
            "placement of the {} front map: {e}; {}; {}",
            side.camera_name(),
            lens_outcome(env, &map_ep, side, Lens::Front),
            lens_outcome(env, &map_ep, side, Lens::Rear)
        ))
    })?;
    write_json(&env.out.join(PLACEMENT_FILE), &file)
}

/// What a lens's localization gave, for an error that must say why a stage had too little to
/// work with: how many frames have a pose, and the commonest reason the others were lost.
fn lens_outcome(env: &StageEnv<'_>, episode: &str, side: Side, lens: Lens) -> String {
    let dir = env.dep_dir(&StageKind::Localize {
        episode: episode.to_string(),
        side,
        lens,
    });
    let name = format!("the {} {} lens", side.camera_name(), lens.name());
    match localization_record(&dir) {
        Ok(record) => crate::quality::describe_outcome(&name, &record),
        Err(e) => format!("{name}'s localizations could not be read ({e})"),
    }
}

/// Time from a frame's timestamp (its first row) to its exposure centre (s): half the rolling
/// readout of the recording mode the camera recorded the episode in (`meta.json`), as the unit's
/// calibration gives it; 0 for a global shutter or a mode without a known readout.
pub(crate) fn exposure_centre_delay(
    ctx: &SessionContext,
    episode: &str,
    w: &WristContext,
) -> Result<f64> {
    let meta = ctx.episode(episode).read_meta(w.camera)?;
    let delay =
        crate::formats::calibration::exposure_centre_delay(&w.calibration, &meta.mode, meta.fps);
    if delay.is_none() {
        tracing::warn!(
            "{}: no readout time for recording mode {} ({} fps): frames are treated as \
             global-shutter exposures",
            w.calibration_path.display(),
            meta.mode,
            meta.fps
        );
    }
    Ok(delay.unwrap_or(0.0))
}

/// The frozen scene reference of a wrist, from the session's metric and placement stages.
pub fn scene_reference(ctx: &SessionContext, side: Side) -> Result<SceneReference> {
    let dir = |kind: StageKind| id_of(&kind).dir(&ctx.root);
    let front_path = dir(StageKind::Metric {
        map: MapName::Front(side),
    })
    .join("metric.json");
    let rear_path = dir(StageKind::Metric { map: MapName::Rear }).join("metric.json");
    let placement_path = dir(StageKind::Placement { side }).join(PLACEMENT_FILE);
    let front = read_metric(&front_path)?;
    let rear = read_metric(&rear_path)?;
    let placement: PlacementFile = read_placement(&placement_path)?;
    let g = placement.scene_from_front_map.to_sim3(&placement_path)?;
    Ok(SceneReference {
        front_metric: front.world_from_map.to_sim3(&front_path)?,
        rear_metric: rear.world_from_map.to_sim3(&rear_path)?,
        scene_from_front_map: nalgebra::Isometry3::from_parts(
            nalgebra::Translation3::from(g.translation),
            g.rotation,
        ),
    })
}

fn run_observations(env: &StageEnv<'_>, episode: &str, side: Side) -> Result<()> {
    let w = wrist(env.ctx, side)?;
    let front = localizations_of(env, episode, side, Lens::Front)?;
    let rear = localizations_of(env, episode, side, Lens::Rear)?;
    let reference = scene_reference(env.ctx, side)?;
    let centre = exposure_centre_delay(env.ctx, episode, w)?;
    let witness_deps = super::graph::other_front_map_deps(env.ctx, side);
    let mut arbiter = StageArbiter {
        env,
        episode,
        side,
        reference,
        exposure_centre_s: centre,
        witnessed: !witness_deps.is_empty() && env.available(&witness_deps),
    };
    let (obs, counts) = body_observations_arbitrated(
        &front,
        &rear,
        &reference,
        &w.front,
        &w.rear,
        centre,
        Some(&mut arbiter),
    );
    if obs.is_empty() && !counts.withdrawn_runs.is_empty() {
        let why: Vec<String> = counts
            .withdrawn_runs
            .iter()
            .map(|r| {
                format!(
                    "{} run {:.2}-{:.2} s ({} frames): {}",
                    r.lens, r.start_s, r.end_s, r.observations, r.reason
                )
            })
            .collect();
        return Err(BackendError::Estimation(format!(
            "the {} wrist keeps no observation: {}; record the episode again starting from a \
             view both lenses share with the mapping episode",
            side.camera_name(),
            why.join("; ")
        )));
    }
    write_observations(&env.out.join(OBSERVATIONS_FILE), &obs)?;
    write_json(&env.out.join(SUMMARY_FILE), &counts)
}

fn run_fusion(env: &StageEnv<'_>, episode: &str, side: Side) -> Result<()> {
    let w = wrist(env.ctx, side)?;
    let layout = env.ctx.episode(episode);
    let obs_path = env
        .dep_dir(&StageKind::Observations {
            episode: episode.to_string(),
            side,
        })
        .join(OBSERVATIONS_FILE);
    let observations = read_observations(&obs_path).map_err(|e| {
        BackendError::Estimation(format!(
            "the {} wrist has no visual observation in this episode ({e}): neither lens \
             localized in its map",
            side.camera_name()
        ))
    })?;
    let imu = ImuSeries::read_csv(&layout.imu_csv(w.camera))?;
    let frames = kiwi_core::layout::read_frames_csv(&layout.frames_csv(w.camera, "front"))?;
    // Frames exposed before the IMU log starts or after it ends (a camera starts its IMU a
    // moment after its first frame) cannot be states of the graph: they are left out and
    // counted.
    // The graph's states sit at each frame's exposure centre, where its visual observations are
    // exact; each is then carried back along the IMU to the frame's timestamp (its first row),
    // the time the outputs give it.
    let centre = exposure_centre_delay(env.ctx, episode, w)?;
    let (first, last) = imu.time_range();
    let (camera_times, node_times): (Vec<f64>, Vec<f64>) = frames
        .iter()
        .map(|f| (f.t, f.t + w.front.time_shift_s + centre))
        .filter(|(_, t)| (first..=last).contains(t) && (first..=last).contains(&(t - centre)))
        .unzip();
    let placement_path = env
        .dep_dir(&StageKind::Placement { side })
        .join(PLACEMENT_FILE);
    let placement = read_placement(&placement_path)?;
    let sigma = visual_sigma_from_disagreement(
        placement.rms_position_m,
        placement.rms_rotation_deg.to_radians(),
    );
    let config = FusionConfig {
        front_sigma: sigma,
        rear_sigma: sigma,
        ..FusionConfig::default()
    };
    let mut result = fuse(imu.samples(), &w.imu, &node_times, &observations, &config)?;
    let statistics = crate::fusion::residual_statistics(&result, &observations, &config);
    if centre > 0.0 {
        for node in &mut result.nodes {
            if let Some(sample) = imu.interpolate(node.t) {
                *node = node.carried(&sample, &w.imu.gravity, -centre);
            }
        }
    }
    write_fused(&env.out.join(FUSED_FILE), &camera_times, &result.nodes)?;
    let summary = FusionSummary {
        statistics,
        frames_outside_imu: frames.len() - node_times.len(),
    };
    write_json(&env.out.join(SUMMARY_FILE), &summary)?;
    // Read back once: the file is what later stages use, so it must parse.
    read_fused(&env.out.join(FUSED_FILE))?;
    Ok(())
}

fn run_gripper(env: &StageEnv<'_>, episode: &str, side: Side) -> Result<()> {
    let w = wrist(env.ctx, side)?;
    let Some(def) = &w.tool else {
        return Ok(());
    };
    let tool_path = env.dep_dir(&StageKind::Tool { side }).join(TOOL_FILE);
    let text = kiwi_core::io::read_text(&tool_path)?;
    let record: ToolRecord = serde_json::from_str(&text)
        .map_err(|e| input(&tool_path, format!("not a tool stage record: {e}; re-run")))?;
    let lens = w.calibration.lens("front").ok_or_else(|| {
        input(
            &w.calibration_path,
            "field `lenses`: no lens named `front`".into(),
        )
    })?;
    let camera = lens.camera()?;
    let lens_dir = env.ctx.episode(episode).lens_dir(w.camera, "front");
    let total = kiwi_core::layout::read_frames_csv(&lens_dir.join("frames.csv"))?.len();
    let done = std::sync::atomic::AtomicUsize::new(0);
    let tick = || {
        let d = done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
        (env.progress)(d, total);
    };
    let (_, files) = match &record.calibration {
        Some(tc) => crate::gripper::run_calibrated(&camera, tc, &lens_dir, env.out, &tick)?,
        None => crate::gripper::run(&camera, def, &lens_dir, env.out, &tick)?,
    };
    // The summary's speed is a wall time: keep it out so the stage's files are deterministic.
    let summary: serde_json::Value =
        serde_json::from_str(&kiwi_core::io::read_text(&files.summary)?)
            .map_err(|e| input(&files.summary, format!("cannot read back: {e}")))?;
    write_json(&files.summary, &without_timings(summary))
}

/// The files of the head stage, published by `outputs` in the episode's `out/`.
pub const HEAD_FILES: [&str; 3] = ["head.csv", "head.tum", "head_camera.csv"];
/// The head stage's record (also `quality.json`'s `head` section).
pub const HEAD_SUMMARY_FILE: &str = "head.json";

/// The head camera's lens: the first lens its `meta.json` lists.
pub fn head_lens(ctx: &SessionContext, episode: &str) -> Result<String> {
    let layout = ctx.episode(episode);
    let meta = layout.read_meta("head")?;
    meta.lenses.first().cloned().ok_or_else(|| {
        input(
            &layout.meta_json("head"),
            "field `lenses` is empty: expected the head camera's lens (e.g. [\"main\"]); \
             re-ingest the head camera's recording"
                .into(),
        )
    })
}

/// The session's head mount and where it came from: `[head] mount`, else the printed hat.
pub fn head_mount(ctx: &SessionContext) -> Result<(kiwi_core::head::HeadMount, String)> {
    match ctx.session.head.as_ref().and_then(|h| h.mount.as_ref()) {
        Some(path) => {
            let file = ctx.root.join(path);
            Ok((
                kiwi_core::head::HeadMount::load(&file)?,
                ctx.relative(&file),
            ))
        }
        None => Ok((
            kiwi_core::head::HeadMount::builtin()?,
            format!(
                "{} (the printed hat's CAD mount)",
                kiwi_core::head::BUILTIN_HEAD_MOUNT_PATH
            ),
        )),
    }
}

fn run_head(env: &StageEnv<'_>, episode: &str) -> Result<()> {
    use crate::head::episode::{
        HeadSummary, HeadTrack, WristPlacement, camera_frames_file, find_sightings, observations,
        track_files,
    };
    let ctx = env.ctx;
    let Some(head) = &ctx.session.head else {
        return Err(input(
            &ctx.toml,
            "has no [head]: the head stage needs the head camera and its hat marker".into(),
        ));
    };
    let sync = sync_of(env, episode)?;
    let clock_of = |name: &str| sync.cameras.iter().find(|c| c.name == name);
    let layout = ctx.episode(episode);
    let (mount, mount_source) = head_mount(ctx)?;
    let mut sources = Vec::new();
    for w in ctx.wrists.values() {
        sources.push(crate::frames::FrameSource::open(
            &layout.lens_dir(w.camera, "rear"),
        )?);
    }
    let total: usize = sources.iter().map(crate::frames::FrameSource::len).sum();
    let done = std::sync::atomic::AtomicUsize::new(0);
    let tick = || {
        let d = done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
        (env.progress)(d, total);
    };
    let mut all = Vec::new();
    let mut wrists = std::collections::BTreeMap::new();
    let (mut t0, mut t1) = (f64::INFINITY, f64::NEG_INFINITY);
    for ((&side, w), source) in ctx.wrists.iter().zip(&sources) {
        let fused = fused_of(env, episode, side)?;
        let clock = clock_of(w.camera);
        for row in &fused {
            if let Some(t) = crate::outputs::session_time(clock, row.t_camera) {
                t0 = t0.min(t);
                t1 = t1.max(t);
            }
        }
        let nodes: Vec<crate::fusion::FusedNode> = fused.into_iter().map(|r| r.node).collect();
        let camera = w
            .calibration
            .lens("rear")
            .ok_or_else(|| {
                input(
                    &w.calibration_path,
                    "field `lenses`: no lens named `rear`".into(),
                )
            })?
            .camera()?;
        let finder = crate::head::marker::MarkerFinder::new(
            camera,
            &head.marker_dictionary,
            head.marker_id as usize,
        )?;
        let readout = 2.0 * exposure_centre_delay(ctx, episode, w)?;
        let (sightings, mut counts) =
            find_sightings(source, &finder, head.marker_size_m, readout, &tick)?;
        let placement = WristPlacement {
            side,
            nodes: &nodes,
            rear_cam_from_imu: w.rear.cam_from_imu,
            rear_time_shift_s: w.rear.time_shift_s,
            front_time_shift_s: w.front.time_shift_s,
            clock,
        };
        let (obs, unplaced) = observations(&placement, &sightings);
        counts.unplaced = unplaced;
        all.extend(obs);
        wrists.insert(w.camera.to_string(), counts);
    }
    let options = crate::head::track::TrackOptions::default();
    let samples = if t1 >= t0 {
        crate::head::track::fuse(&all, t0, t1, &options)
    } else {
        Vec::new()
    };
    let track = HeadTrack {
        samples,
        marker_from_cam: mount.marker_from_cam(),
    };
    let lens = head_lens(ctx, episode)?;
    let frame_times: Vec<f64> =
        kiwi_core::layout::read_frames_csv(&layout.frames_csv("head", &lens))?
            .iter()
            .map(|f| f.t)
            .collect();
    let (track_csv, track_tum) = track_files(&track);
    let (camera_csv, camera_frames_posed) =
        camera_frames_file(&track, &frame_times, clock_of("head"));
    let [track_name, tum_name, camera_name] = HEAD_FILES;
    write_atomic(&env.out.join(track_name), track_csv.as_bytes())?;
    write_atomic(&env.out.join(tum_name), track_tum.as_bytes())?;
    write_atomic(&env.out.join(camera_name), camera_csv.as_bytes())?;
    let sigmas = track.median_sigmas();
    let summary = HeadSummary {
        mount: mount_source,
        wrists,
        observations: all.len(),
        samples: track.samples.len(),
        rate_hz: options.rate_hz,
        posed_fraction: track.posed_fraction(),
        longest_gap_s: track.longest_gap_s(),
        median_sigma_p_m: sigmas.map(|s| s.0),
        median_sigma_r_rad: sigmas.map(|s| s.1),
        camera_frames: frame_times.len(),
        camera_frames_posed,
    };
    write_json(&env.out.join(HEAD_SUMMARY_FILE), &summary)
}

/// The floor stage's record (also `quality.json`'s `floor` section).
pub const FLOOR_SUMMARY_FILE: &str = "floor.json";
/// The floor stage's files published by `outputs` beside its record: every window's result and
/// the plane-support figure.
pub const FLOOR_FILES: [&str; 2] = ["floor_windows.csv", "floor.svg"];

/// The camera-to-floor band of the session: `[floor] camera_height_m`, else the default.
pub fn floor_band(ctx: &SessionContext) -> [f64; 2] {
    ctx.session
        .floor
        .as_ref()
        .and_then(|f| f.camera_height_m)
        .unwrap_or(crate::floor::DEFAULT_CAMERA_HEIGHT_M)
}

fn run_floor(env: &StageEnv<'_>, episode: &str) -> Result<()> {
    use crate::floor::{FloorOptions, FloorSummary, FrontLens, pool, surfaces_above};
    let ctx = env.ctx;
    let sync = sync_of(env, episode)?;
    let clock_of = |name: &str| sync.cameras.iter().find(|c| c.name == name);
    let layout = ctx.episode(episode);
    let options = FloorOptions {
        camera_height_m: floor_band(ctx),
        ..FloorOptions::default()
    };
    let wrists = ctx.wrists.len();
    let mut windows = Vec::new();
    let mut counts = std::collections::BTreeMap::new();
    for (k, (&side, w)) in ctx.wrists.iter().enumerate() {
        let nodes: Vec<crate::fusion::FusedNode> = fused_of(env, episode, side)?
            .into_iter()
            .map(|r| r.node)
            .collect();
        let camera = w
            .calibration
            .lens("front")
            .ok_or_else(|| {
                input(
                    &w.calibration_path,
                    "field `lenses`: no lens named `front`".into(),
                )
            })?
            .camera()?;
        let lens = FrontLens {
            side,
            nodes: &nodes,
            cam_from_imu: w.front.cam_from_imu,
            time_shift_s: w.front.time_shift_s,
            readout_s: 2.0 * exposure_centre_delay(ctx, episode, w)?,
            camera: &camera,
            clock: clock_of(w.camera),
        };
        let source = crate::frames::FrameSource::open(&layout.lens_dir(w.camera, "front"))?;
        // Progress in hundredths of a wrist.
        let tick = |done: usize, total: usize| {
            (env.progress)(k * 100 + done * 100 / total.max(1), wrists * 100);
        };
        let (mine, c) = crate::floor::wrist_windows(&source, &lens, &options, &tick)?;
        windows.extend(mine);
        counts.insert(w.camera.to_string(), c);
    }
    let all_counts: Vec<_> = counts.values().copied().collect();
    let floor = pool(&mut windows, &all_counts, options.camera_height_m);
    let surfaces = surfaces_above(&windows, &floor);
    let [windows_name, figure_name] = FLOOR_FILES;
    write_atomic(
        &env.out.join(windows_name),
        crate::floor::windows_csv(&windows, options.camera_height_m).as_bytes(),
    )?;
    let charts = crate::floor::figure::charts(&windows, &floor, &surfaces);
    let svg = kiwi_plot::Chart::stack_to_svg(&charts).map_err(|e| {
        input(
            &env.out.join(figure_name),
            format!("cannot draw the floor figure: {e}"),
        )
    })?;
    write_atomic(&env.out.join(figure_name), svg.as_bytes())?;
    let summary = FloorSummary::new(floor, surfaces, options.camera_height_m, counts, &windows);
    write_json(&env.out.join(FLOOR_SUMMARY_FILE), &summary)
}

/// A session map and its landmarks in the scene frame: the map's metric recovery, and for a
/// front map its placement into the scene (eq. 2). `root` is the session folder.
pub fn map_in_scene(root: &Path, map: MapName) -> Result<(VisualMap, Vec<nalgebra::Vector3<f64>>)> {
    let dir = |kind: StageKind| id_of(&kind).dir(root);
    let map_path = dir(StageKind::Map { map }).join(MAP_FILE);
    if !map_path.is_file() {
        return Err(input(
            &map_path,
            "missing: run `kiwi run` on the session first (it builds the maps)".into(),
        ));
    }
    let visual = VisualMap::load(&map_path)?;
    let metric_path = dir(StageKind::Metric { map }).join("metric.json");
    let metric = read_metric(&metric_path)?
        .world_from_map
        .to_sim3(&metric_path)?;
    let placement = match map {
        MapName::Rear => None,
        MapName::Front(side) => {
            let path = dir(StageKind::Placement { side }).join(PLACEMENT_FILE);
            Some(read_placement(&path)?.scene_from_front_map.to_sim3(&path)?)
        }
    };
    let points = visual
        .landmarks
        .iter()
        .map(|l| {
            let p = metric.transform_point(&nalgebra::Vector3::from(l.position));
            placement.as_ref().map_or(p, |g| g.transform_point(&p))
        })
        .collect();
    Ok((visual, points))
}

/// Read a stage's manifest, for summaries.
pub fn manifest_of(ctx: &SessionContext, id: &StageId) -> Option<Manifest> {
    Manifest::read(&id.dir(&ctx.root))
}

/// Write bytes atomically (re-exported for the outputs module).
pub fn write_file(path: &Path, bytes: &[u8]) -> Result<()> {
    Ok(write_atomic(path, bytes)?)
}

/// Sub-folder of the outputs stage's folder that is published as the episode's `out/`.
pub const PUBLISHED_DIR: &str = "out";

/// A lens's localization outcome from its stage folder (`poses.csv`, `summary.json`).
fn localization_record(dir: &Path) -> Result<crate::outputs::LocalizationRecord> {
    let summary: serde_json::Value =
        read_json_file(&dir.join(SUMMARY_FILE), "localization summary")?;
    let path = dir.join(POSES_FILE);
    let mut record = crate::outputs::LocalizationRecord {
        from_other_lens: summary
            .get("from_other_lens")
            .and_then(serde_json::Value::as_u64)
            .map_or(0, |n| n as usize),
        ..Default::default()
    };
    for frame in crate::formats::tables::read_lens_frames(&path)? {
        record.frames += 1;
        match frame.lost {
            Some(why) => {
                *record
                    .lost_reasons
                    .entry(crate::quality::reason_class(&why))
                    .or_insert(0) += 1;
            }
            None => record.localized += 1,
        }
    }
    Ok(record)
}

/// Read a JSON file a stage wrote (`what` names it in the error).
pub(crate) fn read_json_file<T: serde::de::DeserializeOwned>(path: &Path, what: &str) -> Result<T> {
    let text = kiwi_core::io::read_text(path)?;
    serde_json::from_str(&text).map_err(|e| {
        input(
            path,
            format!("not a {what}: {e}; re-run the stage that writes it"),
        )
    })
}

fn opening_series(dir: &Path) -> Result<Option<crate::outputs::OpeningSeries>> {
    let csv = dir.join("opening.csv");
    if !csv.is_file() {
        return Ok(None);
    }
    let summary: serde_json::Value = read_json_file(&dir.join("opening.json"), "gripper summary")?;
    let px_per_m = summary
        .get("px_per_m")
        .and_then(serde_json::Value::as_f64)
        .unwrap_or(0.0);
    let text = kiwi_core::io::read_text(&csv)?;
    let mut rows = Vec::new();
    let mut unit_out = "rad";
    for (i, line) in text
        .lines()
        .enumerate()
        .skip(1)
        .filter(|(_, l)| !l.trim().is_empty())
    {
        let f: Vec<&str> = line.splitn(5, ',').collect();
        if f.len() < 4 {
            return Err(input(
                &csv,
                format!("line {}: expected t,opening,unit,confidence,status", i + 1),
            ));
        }
        let t: f64 = f[0]
            .parse()
            .map_err(|_| input(&csv, format!("line {}: bad time `{}`", i + 1, f[0])))?;
        let raw: Option<f64> = f[1].parse().ok().filter(|v: &f64| v.is_finite());
        let (value, unit) = match f[2] {
            "deg" => (raw.map(f64::to_radians), "rad"),
            "px" if px_per_m > 0.0 => (raw.map(|v| v / px_per_m), "m"),
            other => {
                return Err(input(
                    &csv,
                    format!(
                        "line {}: opening unit `{other}` cannot be converted to SI (px needs px_per_m in opening.json)",
                        i + 1
                    ),
                ));
            }
        };
        unit_out = unit;
        rows.push(crate::outputs::Opening {
            t,
            value,
            confidence: f[3].parse().unwrap_or(0.0),
        });
    }
    Ok(Some(crate::outputs::OpeningSeries {
        unit: unit_out,
        rows,
    }))
}

/// A wrist's fused trajectory in an episode, from its `fusion` stage.
fn fused_of(
    env: &StageEnv<'_>,
    episode: &str,
    side: Side,
) -> Result<Vec<crate::formats::tables::FusedRow>> {
    read_fused(
        &env.dep_dir(&StageKind::Fusion {
            episode: episode.to_string(),
            side,
        })
        .join(FUSED_FILE),
    )
}

/// The episode's sync result, from its `sync` stage.
fn sync_of(env: &StageEnv<'_>, episode: &str) -> Result<crate::sync::SyncResult> {
    read_json_file(
        &env.dep_dir(&StageKind::Sync {
            episode: episode.to_string(),
        })
        .join(SYNC_FILE),
        "sync result",
    )
}

/// The files `names` of a stage's folder `dir` as `(name, bytes)`, for `outputs` to publish.
fn stage_files(dir: &Path, names: &[&str], stage: &str) -> Result<Vec<(String, Vec<u8>)>> {
    names
        .iter()
        .map(|name| {
            let path = dir.join(name);
            let bytes = std::fs::read(&path).map_err(|e| {
                input(
                    &path,
                    format!("cannot read the {stage} stage's file: {e}; re-run"),
                )
            })?;
            Ok((name.to_string(), bytes))
        })
        .collect()
}

fn run_outputs(env: &StageEnv<'_>, episode: &str) -> Result<()> {
    let ctx = env.ctx;
    let sync = sync_of(env, episode)?;
    let mut metric = std::collections::BTreeMap::new();
    metric.insert(MapName::Rear.label(), metric_of_map(env, MapName::Rear)?);
    let mut wrists = Vec::new();
    let mut missing_wrists = Vec::new();
    for (&side, w) in &ctx.wrists {
        // A wrist whose stages failed is left out; the other is published.
        if let Some((stage, why)) = env.missing(&wrist_output_deps(ctx, episode, side)) {
            let why = if why.starts_with("needs ") {
                why.clone()
            } else {
                format!("needs {}, which failed: {why}", stage.label())
            };
            missing_wrists.push((w.camera.to_string(), why));
            continue;
        }
        let front_map = MapName::Front(side);
        metric.insert(front_map.label(), metric_of_map(env, front_map)?);
        let fused = fused_of(env, episode, side)?;
        let loc = |lens: Lens| {
            localization_record(&env.dep_dir(&StageKind::Localize {
                episode: episode.to_string(),
                side,
                lens,
            }))
        };
        let observations = read_json_file(
            &env.dep_dir(&StageKind::Observations {
                episode: episode.to_string(),
                side,
            })
            .join(SUMMARY_FILE),
            "observation summary",
        )?;
        let fusion: FusionSummary = read_json_file(
            &env.dep_dir(&StageKind::Fusion {
                episode: episode.to_string(),
                side,
            })
            .join(SUMMARY_FILE),
            "fusion summary",
        )?;
        let placement = read_placement(
            &env.dep_dir(&StageKind::Placement { side })
                .join(PLACEMENT_FILE),
        )?;
        let (opening, tool_calibrated) = if w.tool.is_some() {
            let record: ToolRecord = read_json_file(
                &env.dep_dir(&StageKind::Tool { side }).join(TOOL_FILE),
                "tool record",
            )?;
            (
                opening_series(&env.dep_dir(&StageKind::Gripper {
                    episode: episode.to_string(),
                    side,
                }))?,
                Some(record.calibrated),
            )
        } else {
            (None, None)
        };
        wrists.push(crate::outputs::WristInputs {
            camera: w.camera.to_string(),
            unit: w.calibration.unit_id.clone(),
            calibration_date: w.calibration.date.clone(),
            certified: w.certified(),
            fused,
            front_cam_from_imu: w.front.cam_from_imu,
            cam_from_tip: w.cam_from_tip,
            opening,
            front: loc(Lens::Front)?,
            rear: loc(Lens::Rear)?,
            observations,
            fusion: fusion.statistics,
            frames_outside_imu: fusion.frames_outside_imu,
            placement,
            tool_calibrated,
        });
    }
    if wrists.is_empty() {
        let reasons: Vec<String> = (missing_wrists.iter())
            .map(|(camera, why)| format!("{camera}: {why}"))
            .collect();
        return Err(BackendError::Estimation(format!(
            "no wrist has a trajectory: {}",
            reasons.join("; ")
        )));
    }
    let head_stage = StageId::episode(episode, "head");
    let floor_stage = StageId::episode(episode, "floor");
    // The head and the floor read both wrists: with a wrist missing, its reason says it all.
    let mut missing_parts = Vec::new();
    if missing_wrists.is_empty() {
        if ctx.session.head.is_some()
            && let Some((_, why)) = env.missing(std::slice::from_ref(&head_stage))
        {
            missing_parts.push(format!("head: no track published: {why}"));
        }
        if let Some((_, why)) = env.missing(std::slice::from_ref(&floor_stage)) {
            missing_parts.push(format!(
                "floor: no floor published (no heights above it): {why}"
            ));
        }
    }
    let head = match &ctx.session.head {
        None => None,
        Some(_) if !env.available(std::slice::from_ref(&head_stage)) => None,
        Some(_) => {
            let dir = env.dep_dir(&StageKind::Head {
                episode: episode.to_string(),
            });
            Some(crate::outputs::HeadOutputs {
                files: stage_files(&dir, &HEAD_FILES, "head")?,
                summary: read_json_file(&dir.join(HEAD_SUMMARY_FILE), "head stage record")?,
            })
        }
    };
    let floor = if env.available(std::slice::from_ref(&floor_stage)) {
        let floor_dir = env.dep_dir(&StageKind::Floor {
            episode: episode.to_string(),
        });
        let summary_path = floor_dir.join(FLOOR_SUMMARY_FILE);
        let mut floor_files = stage_files(&floor_dir, &FLOOR_FILES, "floor")?;
        let summary_bytes = stage_files(&floor_dir, &[FLOOR_SUMMARY_FILE], "floor")?;
        let summary = serde_json::from_slice(&summary_bytes[0].1).map_err(|e| {
            input(
                &summary_path,
                format!("not a floor stage record: {e}; re-run `kiwi run --force floor`"),
            )
        })?;
        floor_files.extend(summary_bytes);
        Some(crate::outputs::FloorOutputs {
            files: floor_files,
            summary,
        })
    } else {
        None
    };
    let inputs = crate::outputs::EpisodeInputs {
        episode: episode.to_string(),
        map_episode: ctx.session.map_episode.clone(),
        wrists,
        missing_wrists,
        missing_parts,
        sync,
        metric,
        head,
        floor,
    };
    crate::outputs::write_outputs(&inputs, &env.out.join(PUBLISHED_DIR))?;
    Ok(())
}
