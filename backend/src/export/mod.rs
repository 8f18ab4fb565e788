//! Dataset exports (`kiwi export`): an episode's outputs (`episodes/<ep>/out/`) turned into the
//! files robot-learning tools load as they are — a LeRobot v3.0 dataset ([`lerobot`]), UMI's
//! zipped zarr replay buffer ([`umi`]), KIWI's full-detail sidecar ([`sidecar`]) — or into the
//! posed images, cameras and points that Gaussian-splatting trainers read ([`splat`]: a COLMAP
//! text model or a nerfstudio `transforms.json`).
//!
//! This module holds what the formats share: which episodes are exported (an episode whose
//! verdict is `unusable`, or that has no outputs, is left out with the reason logged), reading
//! `<wrist>.csv` back, the fixed-rate time grid on the session timeline with the poses resampled
//! onto it, and the views (lens streams) with the frame chosen for every row.

pub mod lerobot;
pub mod mask;
mod parquet;
pub mod sidecar;
pub mod splat;
pub mod stats;
pub mod umi;
mod video;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use nalgebra::UnitQuaternion;
use serde::Deserialize;

use kiwi_core::geometry::{Pose, interpolate_pose};
use kiwi_core::layout::{EpisodeLayout, Session, Side, ToolKind};

use crate::error::{BackendError, Result};
use crate::frames::FrameSource;
use crate::outputs::{QualityRecord, SupportClass, read_quality, session_time};
use crate::quality::Verdict;
use crate::sync::CameraClock;

/// A requested rate may exceed the slowest source by this fraction (clock drift between
/// cameras is tens of ppm; a user typing 29.97 for 30000/1001 is 1e-6 off).
const RATE_SLACK: f64 = 1e-3;
/// Rates within this relative distance of `N·1000/1001` are taken as that NTSC rate.
const NTSC_MATCH: f64 = 1e-4;
/// A grid time this far past a trajectory's last frame is that frame (rounding of `k/fps`).
const GRID_SLACK_S: f64 = 1e-6;
/// Frames whose gripper opening was not measured are bridged linearly between measured frames
/// at most this far from the row (s): a few missed detections, not a hand closing unseen.
const MAX_OPENING_GAP_S: f64 = 0.5;
/// The rates an export may be asked for (Hz).
const MAX_EXPORT_FPS: f64 = 1000.0;

/// The dataset formats `kiwi export` writes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum ExportFormat {
    /// LeRobot v3.0 (parquet + mp4).
    LeRobot,
    /// UMI's replay buffer (`dataset.zarr.zip`).
    Umi,
    /// KIWI's full-detail sidecar.
    Sidecar,
    /// A COLMAP text model with posed images and points (3DGUT, gsplat).
    Colmap,
    /// A nerfstudio `transforms.json` with posed images and points (nerfstudio, brush).
    Nerfstudio,
}

impl ExportFormat {
    /// `lerobot`, `umi`, `sidecar`, `colmap` or `nerfstudio`: the name on the command line and
    /// in `session.toml`.
    pub fn name(self) -> &'static str {
        match self {
            Self::LeRobot => "lerobot",
            Self::Umi => "umi",
            Self::Sidecar => "sidecar",
            Self::Colmap => "colmap",
            Self::Nerfstudio => "nerfstudio",
        }
    }
}

impl std::str::FromStr for ExportFormat {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s {
            "lerobot" => Ok(Self::LeRobot),
            "umi" => Ok(Self::Umi),
            "sidecar" => Ok(Self::Sidecar),
            "colmap" => Ok(Self::Colmap),
            "nerfstudio" => Ok(Self::Nerfstudio),
            other => Err(format!(
                "unknown export format `{other}`: expected lerobot, umi, sidecar, colmap or \
                 nerfstudio"
            )),
        }
    }
}

/// What to export.
#[derive(Debug, Clone, Default)]
pub struct ExportOptions {
    /// Output rate (Hz) [default: the slowest source the export needs].
    pub fps: Option<f64>,
    /// Views as `camera.lens` (`left.front`, `head.front`) [default: every wrist's front lens
    /// and the head camera's lenses].
    pub views: Option<Vec<String>>,
    /// Episodes by name [default: every episode of the session].
    pub episodes: Option<Vec<String>>,
    /// Images per second and lens stream of the scene exports (`colmap`, `nerfstudio`)
    /// [default: [`splat::DEFAULT_RATE_HZ`]].
    pub rate: Option<f64>,
}

/// What an export wrote and what it left out.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct ExportReport {
    /// Episodes written, in order.
    pub exported: Vec<String>,
    /// Episodes left out, with the reason.
    pub skipped: Vec<(String, String)>,
    /// Rows (frames) written over all episodes.
    pub frames: usize,
    /// The output rate (Hz), when the format resamples.
    pub fps: Option<f64>,
    /// Largest distance (s) between a row's timestamp and the capture time of the video frame
    /// chosen for it, over all views.
    pub max_frame_offset_s: f64,
    /// What a user of the export should know (a lens model refitted for the format, and how
    /// well), one sentence each.
    pub notes: Vec<String>,
}

fn export_err(message: String) -> BackendError {
    BackendError::Export(message)
}

/// An output rate as an exact fraction `num/den` (video containers store it so).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Rate {
    /// Numerator.
    pub num: u32,
    /// Denominator.
    pub den: u32,
}

impl Rate {
    /// The rate for a number of frames per second: NTSC rates (29.97 → 30000/1001) exactly,
    /// integer rates exactly, anything else to the millihertz.
    pub fn from_hz(fps: f64) -> Result<Self> {
        if !fps.is_finite() || fps <= 0.0 || fps > MAX_EXPORT_FPS {
            return Err(export_err(format!(
                "--fps {fps}: expected a rate above 0 and at most {MAX_EXPORT_FPS} Hz"
            )));
        }
        // Integer rates `N/1`, then NTSC rates `N·1000/1001`: N whole in both.
        for (den, unit) in [(1u32, 1.0), (1001, 1000.0)] {
            let n = (fps * f64::from(den) / unit).round();
            let num = n * unit;
            if n >= 1.0 && ((num / f64::from(den)) - fps).abs() <= NTSC_MATCH * fps {
                return Ok(Self {
                    num: num as u32,
                    den,
                });
            }
        }
        Ok(Self {
            num: (fps * 1000.0).round() as u32,
            den: 1000,
        })
    }

    /// Frames per second.
    pub fn hz(self) -> f64 {
        f64::from(self.num) / f64::from(self.den)
    }

    /// Time of row `k` after the first (s), exact to the fraction.
    pub fn time(self, k: usize) -> f64 {
        (k as f64 * f64::from(self.den)) / f64::from(self.num)
    }
}

/// One row of `<wrist>.csv` read back.
#[derive(Debug, Clone, PartialEq)]
pub struct TrajectoryRow {
    /// Session time (s), `None` when the camera is not on the session timeline.
    pub t_session: Option<f64>,
    /// Camera-clock time (s).
    pub t_camera: f64,
    /// `scene_from_tip`.
    pub scene_from_tip: Pose,
    /// `scene_from_front_cam`.
    pub scene_from_front_cam: Pose,
    /// Tool-tip position sigma (m).
    pub tip_sigma_p_m: f64,
    /// Tool-tip rotation sigma (rad).
    pub tip_sigma_r_rad: f64,
    /// Front-camera position sigma (m).
    pub cam_sigma_p_m: f64,
    /// Front-camera rotation sigma (rad).
    pub cam_sigma_r_rad: f64,
    /// Support class.
    pub support: SupportClass,
    /// Visual factors at the frame.
    pub factors: String,
    /// Gripper opening (rad or m) when measured.
    pub opening: Option<f64>,
    /// Its confidence (0 when not measured).
    pub opening_confidence: f64,
}

#[derive(Deserialize)]
struct RawRow {
    t_session: Option<f64>,
    t_camera: f64,
    tip_px: f64,
    tip_py: f64,
    tip_pz: f64,
    tip_qx: f64,
    tip_qy: f64,
    tip_qz: f64,
    tip_qw: f64,
    cam_px: f64,
    cam_py: f64,
    cam_pz: f64,
    cam_qx: f64,
    cam_qy: f64,
    cam_qz: f64,
    cam_qw: f64,
    tip_sigma_p_m: f64,
    tip_sigma_r_rad: f64,
    cam_sigma_p_m: f64,
    cam_sigma_r_rad: f64,
    support: SupportClass,
    factors: String,
    opening: Option<f64>,
    #[allow(dead_code)]
    opening_unit: Option<String>,
    opening_confidence: Option<f64>,
}

fn pose_of(p: [f64; 3], q: [f64; 4], path: &Path, line: usize) -> Result<Pose> {
    crate::formats::tables::pose_from_row(p, q).map_err(|m| BackendError::Input {
        path: path.to_path_buf(),
        message: format!("line {line}: {m}; re-run `kiwi run --force outputs`"),
    })
}

/// Read an episode's `<wrist>.csv` (written by [`crate::outputs`]).
pub fn read_trajectory(path: &Path) -> Result<Vec<TrajectoryRow>> {
    let input = |message: String| BackendError::Input {
        path: path.to_path_buf(),
        message,
    };
    let mut reader = csv::Reader::from_path(path).map_err(|e| {
        input(format!(
            "cannot open: {e}; run `kiwi run` on the session first"
        ))
    })?;
    let mut rows: Vec<TrajectoryRow> = Vec::new();
    for (i, rec) in reader.deserialize::<RawRow>().enumerate() {
        let line = i + 2;
        let r = rec.map_err(|e| {
            input(format!(
                "line {line}: not a KIWI trajectory row ({e}); expected the columns {}",
                crate::outputs::TRAJECTORY_HEADER
            ))
        })?;
        if let (Some(prev), Some(t)) = (rows.last().and_then(|p| p.t_session), r.t_session)
            && t.partial_cmp(&prev) != Some(std::cmp::Ordering::Greater)
        {
            return Err(input(format!(
                "line {line}: t_session {t} does not come after the previous row's {prev}"
            )));
        }
        rows.push(TrajectoryRow {
            t_session: r.t_session,
            t_camera: r.t_camera,
            scene_from_tip: pose_of(
                [r.tip_px, r.tip_py, r.tip_pz],
                [r.tip_qx, r.tip_qy, r.tip_qz, r.tip_qw],
                path,
                line,
            )?,
            scene_from_front_cam: pose_of(
                [r.cam_px, r.cam_py, r.cam_pz],
                [r.cam_qx, r.cam_qy, r.cam_qz, r.cam_qw],
                path,
                line,
            )?,
            tip_sigma_p_m: r.tip_sigma_p_m,
            tip_sigma_r_rad: r.tip_sigma_r_rad,
            cam_sigma_p_m: r.cam_sigma_p_m,
            cam_sigma_r_rad: r.cam_sigma_r_rad,
            support: r.support,
            factors: r.factors,
            opening: r.opening,
            opening_confidence: r.opening_confidence.unwrap_or(0.0),
        });
    }
    Ok(rows)
}

/// One wrist's trajectory of an episode.
#[derive(Debug, Clone)]
pub struct WristTrajectory {
    /// The wrist.
    pub side: Side,
    /// Its tool.
    pub tool: ToolKind,
    /// Rows at every front frame.
    pub rows: Vec<TrajectoryRow>,
}

/// One wrist's state at a row of the output grid.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WristSample {
    /// `scene_from_tip`, interpolated on the SO(3)×R³ geodesic.
    pub scene_from_tip: Pose,
    /// `scene_from_front_cam`, interpolated in the same way.
    pub scene_from_front_cam: Pose,
    /// The larger tool-tip position sigma of the two frames around the row (m).
    pub tip_sigma_p_m: f64,
    /// The larger tool-tip rotation sigma (rad).
    pub tip_sigma_r_rad: f64,
    /// The weaker support class of the two frames around the row.
    pub support: SupportClass,
    /// Gripper opening (rad or m): linear between the nearest measured frames around the row
    /// (within [`MAX_OPENING_GAP_S`]), else the one measured frame near it, else `None`.
    pub opening: Option<f64>,
    /// Its confidence: the smaller of the two frames' around the row (0 when either was not
    /// measured, so a bridged value is marked).
    pub opening_confidence: f64,
}

fn support_rank(s: SupportClass) -> u8 {
    match s {
        SupportClass::Front => 0,
        SupportClass::Rear => 1,
        SupportClass::RearInterpolated => 2,
        SupportClass::ImuOnly => 3,
    }
}

/// The code of a support class in exported integer columns: 0 front, 1 rear, 2
/// rear-interpolated, 3 IMU only.
pub fn support_code(s: SupportClass) -> i64 {
    i64::from(support_rank(s))
}

impl WristTrajectory {
    /// First and last session time.
    pub fn span(&self) -> Option<(f64, f64)> {
        Some((self.rows.first()?.t_session?, self.rows.last()?.t_session?))
    }

    /// [`Self::sample`] for a row of `episode`'s output grid: a time without a pose is an error
    /// naming the episode, the wrist and the time.
    pub fn sample_row(&self, episode: &str, t: f64) -> Result<WristSample> {
        self.sample(t).ok_or_else(|| {
            export_err(format!(
                "episode {episode}: the {} trajectory has no pose at session time {t:.6}",
                self.side.camera_name()
            ))
        })
    }

    /// The wrist's state at session time `t` (inside [`Self::span`]).
    pub fn sample(&self, t: f64) -> Option<WristSample> {
        let k = self
            .rows
            .partition_point(|r| r.t_session.is_some_and(|ts| ts <= t));
        let (ia, ib) = match (k.checked_sub(1), self.rows.get(k)) {
            (Some(i), _) if self.rows[i].t_session == Some(t) => (i, i),
            (Some(i), Some(_)) => (i, k),
            // The grid's last row may sit a rounding error after the last frame.
            (Some(i), None)
                if self.rows[i]
                    .t_session
                    .is_some_and(|ts| t - ts <= GRID_SLACK_S) =>
            {
                (i, i)
            }
            _ => return None,
        };
        let (a, b) = (&self.rows[ia], &self.rows[ib]);
        let (ta, tb) = (a.t_session?, b.t_session?);
        let s = if tb > ta { (t - ta) / (tb - ta) } else { 0.0 };
        let support = if support_rank(a.support) >= support_rank(b.support) {
            a.support
        } else {
            b.support
        };
        let opening = self.opening_at(ia, ib, t);
        Some(WristSample {
            scene_from_tip: interpolate_pose(&a.scene_from_tip, &b.scene_from_tip, s),
            scene_from_front_cam: interpolate_pose(
                &a.scene_from_front_cam,
                &b.scene_from_front_cam,
                s,
            ),
            tip_sigma_p_m: a.tip_sigma_p_m.max(b.tip_sigma_p_m),
            tip_sigma_r_rad: a.tip_sigma_r_rad.max(b.tip_sigma_r_rad),
            support,
            opening,
            opening_confidence: if opening.is_some() {
                a.opening_confidence.min(b.opening_confidence)
            } else {
                0.0
            },
        })
    }

    /// The gripper opening at session time `t` between rows `ia` and `ib`: linear between the
    /// nearest measured frames at or before `ia` and at or after `ib` (bridging frames whose
    /// opening was not measured), the one there is near an end, `None` when no frame within
    /// [`MAX_OPENING_GAP_S`] has one.
    fn opening_at(&self, ia: usize, ib: usize, t: f64) -> Option<f64> {
        let measured = |r: &TrajectoryRow| Some((r.t_session?, r.opening?));
        let near = |r: &&TrajectoryRow| {
            r.t_session
                .is_some_and(|ts| (ts - t).abs() <= MAX_OPENING_GAP_S)
        };
        let before = self.rows[..=ia]
            .iter()
            .rev()
            .take_while(near)
            .find_map(measured);
        let after = self.rows[ib..].iter().take_while(near).find_map(measured);
        match (before, after) {
            (Some((t0, x)), Some((t1, y))) if t1 > t0 => Some(x + (y - x) * (t - t0) / (t1 - t0)),
            (before, after) => before.or(after).map(|(_, v)| v),
        }
    }

    /// Median interval between frames on the session timeline (s).
    pub fn period(&self) -> Option<f64> {
        let t: Vec<f64> = self.rows.iter().filter_map(|r| r.t_session).collect();
        median_period(&t)
    }
}

/// Median interval between consecutive times (s).
pub(crate) fn median_period(t: &[f64]) -> Option<f64> {
    let mut d: Vec<f64> = t.windows(2).map(|w| w[1] - w[0]).collect();
    if d.is_empty() {
        return None;
    }
    d.sort_by(f64::total_cmp);
    Some(d[d.len() / 2])
}

/// An episode ready to export: its outputs read back.
#[derive(Debug, Clone)]
pub struct EpisodeOutputs {
    /// Episode name.
    pub name: String,
    /// Task text: the episode's description in `session.toml`, else its name.
    pub task: String,
    /// The episode folder.
    pub dir: PathBuf,
    /// Its `quality.json`.
    pub quality: QualityRecord,
    /// Per wrist, in session order (left, right).
    pub wrists: Vec<WristTrajectory>,
    /// The head camera's poses (`out/head.csv`), when the session has a head camera.
    pub head: Option<crate::head::episode::CameraTrack>,
}

impl EpisodeOutputs {
    /// The clock of a camera on the session timeline (`None` when it is not on it).
    pub fn clock(&self, camera: &str) -> Option<&CameraClock> {
        self.quality
            .sync
            .as_ref()
            .and_then(|s| s.cameras.iter().find(|c| c.name == camera))
    }
}

/// A session opened for export.
#[derive(Debug, Clone)]
pub struct SessionExport {
    /// `session.toml`.
    pub session: Session,
    /// The session folder.
    pub root: PathBuf,
    /// Episodes to export.
    pub episodes: Vec<EpisodeOutputs>,
    /// Episodes left out, with the reason (each also logged).
    pub skipped: Vec<(String, String)>,
}

/// Open a session and read the outputs of the episodes to export. An unknown episode name is
/// an error; an episode without outputs or with the verdict `unusable` is left out with the
/// reason logged.
pub fn open_session(session_toml: &Path, episodes: Option<&[String]>) -> Result<SessionExport> {
    let session = Session::load(session_toml)?;
    let root = session_toml
        .parent()
        .map_or_else(|| PathBuf::from("."), Path::to_path_buf);
    let names: Vec<String> = match episodes {
        Some(list) => {
            for name in list {
                if !session.episodes.iter().any(|e| &e.name == name) {
                    let known: Vec<&str> =
                        session.episodes.iter().map(|e| e.name.as_str()).collect();
                    return Err(export_err(format!(
                        "--episodes: no episode `{name}` in {} (it has: {})",
                        session_toml.display(),
                        known.join(", ")
                    )));
                }
            }
            list.to_vec()
        }
        None => session.episodes.iter().map(|e| e.name.clone()).collect(),
    };
    let mut out = Vec::new();
    let mut skipped = Vec::new();
    for name in names {
        let dir = session.episode_dir(&root, &name);
        let quality_path = dir.join("out").join("quality.json");
        let skip = |skipped: &mut Vec<(String, String)>, reason: String| {
            tracing::warn!("export: episode {name} left out: {reason}");
            skipped.push((name.clone(), reason));
        };
        if !quality_path.is_file() {
            skip(
                &mut skipped,
                format!(
                    "no outputs ({} is missing): run `kiwi run` on the session",
                    quality_path.display()
                ),
            );
            continue;
        }
        let quality = read_quality(&quality_path)?;
        if quality.verdict == Verdict::Unusable {
            skip(
                &mut skipped,
                format!("verdict unusable: {}", quality.reasons.join("; ")),
            );
            continue;
        }
        let mut wrists = Vec::new();
        for (side, cfg) in &session.wrists {
            let rows =
                read_trajectory(&dir.join("out").join(format!("{}.csv", side.camera_name())))?;
            wrists.push(WristTrajectory {
                side: *side,
                tool: cfg.tool,
                rows,
            });
        }
        if let Some(w) = wrists.iter().find(|w| w.span().is_none()) {
            skip(
                &mut skipped,
                format!(
                    "the {} wrist has no frame on the session timeline",
                    w.side.camera_name()
                ),
            );
            continue;
        }
        let task = session
            .episodes
            .iter()
            .find(|e| e.name == name)
            .map(|e| e.description.trim().to_string())
            .filter(|d| !d.is_empty())
            .unwrap_or_else(|| name.clone());
        let head_csv = dir.join("out").join("head.csv");
        let head = if head_csv.is_file() {
            Some(crate::head::episode::CameraTrack::read_csv(&head_csv)?)
        } else {
            None
        };
        out.push(EpisodeOutputs {
            name,
            task,
            dir,
            quality,
            wrists,
            head,
        });
    }
    Ok(SessionExport {
        session,
        root,
        episodes: out,
        skipped,
    })
}

/// A lens stream exported as a video view.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord)]
pub struct View {
    /// Camera folder (`left`, `right`, `head`).
    pub camera: String,
    /// Lens folder (`front`, `rear`, …).
    pub lens: String,
}

impl View {
    /// `left_front`: the name in dataset keys.
    pub fn key(&self) -> String {
        format!("{}_{}", self.camera, self.lens)
    }
}

/// The views to export: those named (`camera.lens`), else every wrist's front lens and every
/// lens of the head camera. A view no episode has is an error naming the ones there are.
pub fn resolve_views(exp: &SessionExport, requested: Option<&[String]>) -> Result<Vec<View>> {
    let available = |ep: &EpisodeOutputs| -> Vec<View> {
        let mut v = Vec::new();
        for camera in exp.session.camera_names() {
            let layout = EpisodeLayout::new(&ep.dir);
            if let Ok(meta) = layout.read_meta(camera) {
                for lens in meta.lenses {
                    if layout.lens_dir(camera, &lens).join("frames.csv").is_file() {
                        v.push(View {
                            camera: camera.to_string(),
                            lens,
                        });
                    }
                }
            }
        }
        v
    };
    let Some(first) = exp.episodes.first() else {
        return Ok(Vec::new());
    };
    let have = available(first);
    let views: Vec<View> = match requested {
        Some(list) => {
            let mut views = Vec::new();
            for name in list {
                let view = name
                    .split_once('.')
                    .map(|(c, l)| View {
                        camera: c.to_string(),
                        lens: l.to_string(),
                    })
                    .filter(|v| have.contains(v))
                    .ok_or_else(|| {
                        let names: Vec<String> = have
                            .iter()
                            .map(|v| format!("{}.{}", v.camera, v.lens))
                            .collect();
                        export_err(format!(
                            "--views: unknown view `{name}`: expected camera.lens, one of {}",
                            names.join(", ")
                        ))
                    })?;
                if !views.contains(&view) {
                    views.push(view);
                }
            }
            views
        }
        None => have
            .into_iter()
            .filter(|v| v.camera == "head" || v.lens == "front")
            .collect(),
    };
    for ep in &exp.episodes[1..] {
        let have = available(ep);
        if let Some(v) = views.iter().find(|v| !have.contains(v)) {
            return Err(export_err(format!(
                "view {}.{} is missing from episode {} ({}); export the episodes separately or \
                 leave the view out with --views",
                v.camera,
                v.lens,
                ep.name,
                ep.dir.display()
            )));
        }
    }
    Ok(views)
}

/// A view's stream of one episode on the session timeline.
pub struct ViewStream {
    /// The view.
    pub view: View,
    /// Its frames.
    pub source: FrameSource,
    /// Every frame's session time (s).
    pub session_times: Vec<f64>,
}

impl ViewStream {
    /// Open a view of an episode; its camera must be on the session timeline.
    pub fn open(ep: &EpisodeOutputs, view: &View) -> Result<Self> {
        let layout = EpisodeLayout::new(&ep.dir);
        let source = FrameSource::open(&layout.lens_dir(&view.camera, &view.lens))?;
        let clock = ep.clock(&view.camera);
        let session_times = source
            .frames()
            .iter()
            .map(|f| session_time(clock, f.t))
            .collect::<Option<Vec<f64>>>()
            .ok_or_else(|| {
                export_err(format!(
                    "episode {}: camera {} is not on the session timeline (see sync in \
                     quality.json); leave view {}.{} out with --views",
                    ep.name, view.camera, view.camera, view.lens
                ))
            })?;
        Ok(Self {
            view: view.clone(),
            source,
            session_times,
        })
    }

    /// Median frame interval (s).
    pub fn period(&self) -> Option<f64> {
        median_period(&self.session_times)
    }

    /// The frame nearest each time, and the largest distance to it (s).
    pub fn nearest_frames(&self, times: &[f64]) -> (Vec<usize>, f64) {
        let st = &self.session_times;
        let mut worst = 0.0f64;
        let picks = times
            .iter()
            .map(|&t| {
                let k = st.partition_point(|&s| s < t);
                let best = [k.checked_sub(1), (k < st.len()).then_some(k)]
                    .into_iter()
                    .flatten()
                    .min_by(|&a, &b| (st[a] - t).abs().total_cmp(&(st[b] - t).abs()))
                    .unwrap_or(0);
                worst = worst.max((st.get(best).copied().unwrap_or(t) - t).abs());
                best
            })
            .collect();
        (picks, worst)
    }
}

/// The fixed-rate rows of one episode on the session timeline.
#[derive(Debug, Clone)]
pub struct TimeGrid {
    /// Session time of the first row (s).
    pub t0: f64,
    /// The rate.
    pub rate: Rate,
    /// Rows.
    pub len: usize,
}

impl TimeGrid {
    /// Session time of row `k`.
    pub fn time(&self, k: usize) -> f64 {
        self.t0 + self.rate.time(k)
    }

    /// Every row's session time.
    pub fn times(&self) -> Vec<f64> {
        (0..self.len).map(|k| self.time(k)).collect()
    }
}

/// The rate of an export: the one asked for (an error when a source cannot supply it), else
/// the slowest source's.
pub fn choose_rate(
    requested: Option<f64>,
    sources: &[(String, f64)],
    episode: &str,
) -> Result<Rate> {
    let slowest = sources
        .iter()
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .ok_or_else(|| export_err(format!("episode {episode}: nothing to export")))?;
    match requested {
        Some(fps) => {
            let rate = Rate::from_hz(fps)?;
            if rate.hz() > slowest.1 * (1.0 + RATE_SLACK) {
                return Err(export_err(format!(
                    "--fps {fps}: episode {episode}'s {} runs at {:.3} Hz, so it cannot supply \
                     {fps} distinct frames per second; ask for at most {:.3}",
                    slowest.0, slowest.1, slowest.1
                )));
            }
            Ok(rate)
        }
        None => Rate::from_hz(slowest.1),
    }
}

/// The grid of an episode: from the latest first sample to the earliest last sample of the
/// wrists and views, at `rate`.
pub fn episode_grid(ep: &EpisodeOutputs, views: &[ViewStream], rate: Rate) -> Result<TimeGrid> {
    let mut start = f64::NEG_INFINITY;
    let mut end = f64::INFINITY;
    for w in &ep.wrists {
        if let Some((a, b)) = w.span() {
            start = start.max(a);
            end = end.min(b);
        }
    }
    for v in views {
        if let (Some(a), Some(b)) = (v.session_times.first(), v.session_times.last()) {
            start = start.max(*a);
            end = end.min(*b);
        }
    }
    if end
        .partial_cmp(&start)
        .is_none_or(|o| o == std::cmp::Ordering::Less)
    {
        return Err(export_err(format!(
            "episode {}: the wrists' trajectories and the views do not overlap in time",
            ep.name
        )));
    }
    let len = ((end - start) * rate.hz() + 1e-9).floor() as usize + 1;
    Ok(TimeGrid {
        t0: start,
        rate,
        len,
    })
}

/// The source rates an export of `ep` needs: every wrist's trajectory and every view.
pub fn source_rates(ep: &EpisodeOutputs, views: &[ViewStream]) -> Vec<(String, f64)> {
    let mut rates = Vec::new();
    for w in &ep.wrists {
        if let Some(p) = w.period() {
            rates.push((format!("{} trajectory", w.side.camera_name()), 1.0 / p));
        }
    }
    for v in views {
        if let Some(p) = v.period() {
            rates.push((format!("view {}.{}", v.view.camera, v.view.lens), 1.0 / p));
        }
    }
    rates
}

/// Unit quaternion components `[x, y, z, w]` kept in the hemisphere of the previous one, so a
/// series has no sign flips.
pub fn continuous_quaternion(q: &UnitQuaternion<f64>, previous: Option<[f64; 4]>) -> [f64; 4] {
    let c = q.coords;
    let mut v = [c.x, c.y, c.z, c.w];
    if let Some(p) = previous
        && p.iter().zip(&v).map(|(a, b)| a * b).sum::<f64>() < 0.0
    {
        v.iter_mut().for_each(|x| *x = -*x);
    }
    v
}

/// Per-episode summary of the frames chosen for each view.
pub type FrameChoice = BTreeMap<String, Vec<usize>>;

/// Make `dir` fresh for an export: it must not exist yet or be empty.
pub fn prepare_out_dir(out: &Path) -> Result<PathBuf> {
    if out.exists() && std::fs::read_dir(out).map_or(true, |mut d| d.next().is_some()) {
        return Err(export_err(format!(
            "{}: exists and is not empty; remove it or choose another --out",
            out.display()
        )));
    }
    let name = out
        .file_name()
        .map_or_else(|| "export".into(), |n| n.to_string_lossy().to_string());
    let partial = out.with_file_name(format!(".{name}.partial"));
    if partial.exists() {
        std::fs::remove_dir_all(&partial).map_err(|e| BackendError::Input {
            path: partial.clone(),
            message: format!("cannot remove a stale partial export: {e}"),
        })?;
    }
    std::fs::create_dir_all(&partial).map_err(|e| BackendError::Input {
        path: partial.clone(),
        message: format!("cannot create: {e}"),
    })?;
    Ok(partial)
}

/// Move a finished export from its partial folder into place.
pub fn finish_out_dir(partial: &Path, out: &Path) -> Result<()> {
    if out.exists() {
        let _ = std::fs::remove_dir(out);
    }
    std::fs::rename(partial, out).map_err(|e| BackendError::Input {
        path: out.to_path_buf(),
        message: format!(
            "cannot move the finished export from {}: {e}",
            partial.display()
        ),
    })
}

/// Create a folder (and its parents), naming it in the error.
pub(crate) fn create_dir(dir: &Path) -> Result<()> {
    std::fs::create_dir_all(dir).map_err(|e| BackendError::Input {
        path: dir.to_path_buf(),
        message: format!("cannot create: {e}"),
    })
}

/// Run an export of a session in `format` into `out`.
pub fn export(
    session_toml: &Path,
    format: ExportFormat,
    options: &ExportOptions,
    out: &Path,
) -> Result<ExportReport> {
    let exp = open_session(session_toml, options.episodes.as_deref())?;
    if exp.episodes.is_empty() {
        let reasons: Vec<String> = exp
            .skipped
            .iter()
            .map(|(n, r)| format!("{n}: {r}"))
            .collect();
        return Err(export_err(format!(
            "no episode of {} can be exported ({})",
            session_toml.display(),
            reasons.join("; ")
        )));
    }
    let partial = prepare_out_dir(out)?;
    let result = match format {
        ExportFormat::LeRobot => lerobot::write(&exp, options, &partial),
        ExportFormat::Umi => umi::write(&exp, options, &partial),
        ExportFormat::Sidecar => sidecar::write(&exp, &partial),
        ExportFormat::Colmap => splat::write(&exp, options, splat::SceneFormat::Colmap, &partial),
        ExportFormat::Nerfstudio => {
            splat::write(&exp, options, splat::SceneFormat::Nerfstudio, &partial)
        }
    };
    match result {
        Ok(mut report) => {
            report.skipped.clone_from(&exp.skipped);
            finish_out_dir(&partial, out)?;
            Ok(report)
        }
        Err(e) => {
            let _ = std::fs::remove_dir_all(&partial);
            Err(e)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::Rate;

    #[test]
    fn rates_snap_to_integer_and_ntsc_fractions() {
        let r = |hz: f64| {
            let r = Rate::from_hz(hz).unwrap();
            (r.num, r.den)
        };
        assert_eq!(r(30.0), (30, 1));
        assert_eq!(r(15.0), (15, 1));
        assert_eq!(r(29.97), (30000, 1001));
        assert_eq!(r(30000.0 / 1001.0), (30000, 1001));
        // A camera 40 ppm slow on the session timeline still records 30000/1001.
        assert_eq!(r(30000.0 / 1001.0 / (1.0 + 40e-6)), (30000, 1001));
        assert_eq!(r(59.94), (60000, 1001));
        assert_eq!(r(119.88), (120000, 1001));
        // Neither: to the millihertz.
        assert_eq!(r(12.345), (12345, 1000));
        assert_eq!(r(29.9), (29900, 1000));
        assert!(Rate::from_hz(0.0).is_err());
        assert!(Rate::from_hz(f64::NAN).is_err());
        assert!(Rate::from_hz(5000.0).is_err());
    }
}
