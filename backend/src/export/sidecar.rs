//! KIWI's full-detail sidecar: everything the pipeline knows about the exported episodes, at
//! full rate and without loss, so any other format can be rebuilt from it. The pipeline's own
//! files are copied byte for byte (they are documented field by field in docs/export.md);
//! the sidecar adds one `timestamps.csv` per lens with every frame's time on every clock, and
//! `sidecar.json`, the index of every file with its size and SHA-256.
//!
//! ```text
//! OUT/
//!   sidecar.json                    index: session, frame definitions, episodes, files
//!   session.toml
//!   calibration/<camera>/calibration.json     each unit's calibration (cam_from_imu, lenses, time shifts)
//!   session/work/<stage>/*.json     map metric recovery, front-map placement, tool geometry
//!   episodes/<ep>/out/              <wrist>.csv, TUM files, quality.json (verdict, sync evidence)
//!   episodes/<ep>/work/<stage>/     sync.json, localizations (poses.csv), observations (obs.csv),
//!                                   fused IMU states with full covariance (fused.csv), openings
//!   episodes/<ep>/<camera>/meta.json
//!   episodes/<ep>/<camera>/<lens>/frames.csv       frame times on the camera clock
//!   episodes/<ep>/<camera>/<lens>/timestamps.csv   frame,t_camera,t_session
//! ```

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use serde::Serialize;

use kiwi_core::layout::{EpisodeLayout, read_frames_csv};

use crate::error::{BackendError, Result};
use crate::export::{ExportReport, SessionExport, create_dir};
use crate::outputs::session_time;

/// `sidecar.json` schema version.
pub const SIDECAR_SCHEMA_VERSION: u32 = 1;
/// Extensions of stage files the sidecar carries (maps and images are left in the session).
const CARRIED_EXTENSIONS: [&str; 4] = ["csv", "json", "tum", "svg"];

/// One file of the sidecar.
#[derive(Debug, Clone, Serialize)]
pub struct SidecarFile {
    /// Path relative to the sidecar folder.
    pub path: String,
    /// Size (bytes).
    pub bytes: u64,
    /// SHA-256 of the content (hex).
    pub sha256: String,
}

/// `sidecar.json`.
#[derive(Debug, Clone, Serialize)]
pub struct SidecarIndex {
    /// [`SIDECAR_SCHEMA_VERSION`].
    pub schema_version: u32,
    /// Session name.
    pub session: String,
    /// The episode whose recordings built the maps.
    pub map_episode: String,
    /// Frame and time conventions, in words.
    pub conventions: Vec<String>,
    /// Exported episodes with their task text and verdict.
    pub episodes: Vec<SidecarEpisode>,
    /// Every file.
    pub files: Vec<SidecarFile>,
}

/// An episode of the sidecar.
#[derive(Debug, Clone, Serialize)]
pub struct SidecarEpisode {
    /// Name (folder under `episodes/`).
    pub name: String,
    /// Task text.
    pub task: String,
    /// `usable` or `suspect`.
    pub verdict: String,
}

/// The conventions written into `sidecar.json`.
const CONVENTIONS: [&str; 6] = [
    "a_from_b maps coordinates in frame b to frame a; positions in m, rotations as unit \
     quaternions (qx qy qz qw), times in s",
    "scene: the metric, gravity-aligned (z up) frame of the session's rear map",
    "tip: the tool tip frame of the wrist's tool; front_cam: the wrist unit's front lens; imu: \
     the unit's IMU (fused.csv states are scene_from_imu)",
    "t_camera: a camera's own clock (frame timestamp = exposure of its first row); t_session = \
     t_camera * (1 + drift_ppm * 1e-6) + offset_s with the camera's clock in sync.json",
    "the IMU clock of a lens: t_imu = t_camera + that lens's time_shift_s in calibration.json (fused.csv gives both)",
    "covariances in fused.csv are over the tangent [rotation, position] of scene_from_imu",
];

fn copy_file(from: &Path, to: &Path, files: &mut Vec<SidecarFile>, base: &Path) -> Result<()> {
    let bytes = std::fs::read(from).map_err(|e| BackendError::Input {
        path: from.to_path_buf(),
        message: format!("cannot read: {e}"),
    })?;
    write_file(to, &bytes, files, base)
}

fn write_file(to: &Path, bytes: &[u8], files: &mut Vec<SidecarFile>, base: &Path) -> Result<()> {
    if let Some(parent) = to.parent() {
        create_dir(parent)?;
    }
    kiwi_core::io::write_atomic(to, bytes)?;
    let rel = to
        .strip_prefix(base)
        .unwrap_or(to)
        .to_string_lossy()
        .replace('\\', "/");
    files.push(SidecarFile {
        path: rel,
        bytes: bytes.len() as u64,
        sha256: kiwi_core::io::sha256_bytes(bytes),
    });
    Ok(())
}

/// The entries of `dir` that `keep` accepts, sorted (none when it cannot be read).
fn sorted_entries(dir: &Path, keep: impl Fn(&Path) -> bool) -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(dir)
        .into_iter()
        .flatten()
        .flatten()
        .map(|e| e.path())
        .filter(|p| keep(p))
        .collect();
    v.sort();
    v
}

/// Files directly in `dir` with a carried extension, sorted.
fn carried_files(dir: &Path) -> Vec<PathBuf> {
    sorted_entries(dir, |p| {
        p.is_file()
            && p.extension()
                .and_then(|e| e.to_str())
                .is_some_and(|e| CARRIED_EXTENSIONS.contains(&e))
    })
}

/// The pipeline's stage folders under a `work/` folder (no temporary or old folders of an
/// interrupted run, none of the stages after the episodes: another export of the same run may
/// or may not have finished before this one).
fn stage_dirs(work: &Path) -> Vec<PathBuf> {
    sorted_entries(work, |p| {
        p.is_dir()
            && p.file_name().and_then(|n| n.to_str()).is_some_and(|n| {
                !n.starts_with('.')
                    && !crate::pipeline::graph::AFTER_EPISODE_FAMILIES
                        .contains(&n.split('-').next().unwrap_or(n))
            })
    })
}

/// Write the sidecar of `exp` into `dir`.
pub fn write(exp: &SessionExport, dir: &Path) -> Result<ExportReport> {
    let mut files = Vec::new();
    copy_file(
        &exp.root.join("session.toml"),
        &dir.join("session.toml"),
        &mut files,
        dir,
    )?;
    let mut calibrations: Vec<(String, PathBuf)> = exp
        .session
        .wrists
        .iter()
        .map(|(s, w)| (s.camera_name().to_string(), w.calibration.clone()))
        .collect();
    if let Some(h) = &exp.session.head {
        calibrations.push(("head".into(), h.calibration.clone()));
    }
    for (camera, set) in &calibrations {
        copy_file(
            &exp.root.join(set).join("calibration.json"),
            &dir.join("calibration")
                .join(camera)
                .join("calibration.json"),
            &mut files,
            dir,
        )?;
    }
    for stage in stage_dirs(&exp.root.join("work")) {
        let name = stage.file_name().unwrap_or_default();
        for f in carried_files(&stage) {
            if f.extension().is_some_and(|e| e == "json") {
                let to = dir
                    .join("session/work")
                    .join(name)
                    .join(f.file_name().unwrap_or_default());
                copy_file(&f, &to, &mut files, dir)?;
            }
        }
    }
    let mut report = ExportReport::default();
    for ep in &exp.episodes {
        let out = dir.join("episodes").join(&ep.name);
        for f in carried_files(&ep.dir.join("out")) {
            copy_file(
                &f,
                &out.join("out").join(f.file_name().unwrap_or_default()),
                &mut files,
                dir,
            )?;
        }
        for stage in stage_dirs(&ep.dir.join("work")) {
            let name = stage.file_name().unwrap_or_default();
            for f in carried_files(&stage) {
                copy_file(
                    &f,
                    &out.join("work")
                        .join(name)
                        .join(f.file_name().unwrap_or_default()),
                    &mut files,
                    dir,
                )?;
            }
        }
        let layout = EpisodeLayout::new(&ep.dir);
        for camera in exp.session.camera_names() {
            let Ok(meta) = layout.read_meta(camera) else {
                continue;
            };
            copy_file(
                &layout.meta_json(camera),
                &out.join(camera).join("meta.json"),
                &mut files,
                dir,
            )?;
            let clock = ep.clock(camera);
            for lens in &meta.lenses {
                let frames_csv = layout.frames_csv(camera, lens);
                if !frames_csv.is_file() {
                    continue;
                }
                copy_file(
                    &frames_csv,
                    &out.join(camera).join(lens).join("frames.csv"),
                    &mut files,
                    dir,
                )?;
                let frames = read_frames_csv(&frames_csv)?;
                let mut s = String::from("frame,t_camera,t_session\n");
                for (i, f) in frames.iter().enumerate() {
                    let _ = write!(s, "{i},{:.9},", f.t);
                    if let Some(t) = session_time(clock, f.t) {
                        let _ = write!(s, "{t:.9}");
                    }
                    s.push('\n');
                }
                write_file(
                    &out.join(camera).join(lens).join("timestamps.csv"),
                    s.as_bytes(),
                    &mut files,
                    dir,
                )?;
                report.frames += frames.len();
            }
        }
        report.exported.push(ep.name.clone());
    }
    let index = SidecarIndex {
        schema_version: SIDECAR_SCHEMA_VERSION,
        session: exp.session.name.clone(),
        map_episode: exp.session.map_episode.clone(),
        conventions: CONVENTIONS.iter().map(|c| (*c).to_string()).collect(),
        episodes: exp
            .episodes
            .iter()
            .map(|e| SidecarEpisode {
                name: e.name.clone(),
                task: e.task.clone(),
                verdict: e.quality.verdict.as_str().to_string(),
            })
            .collect(),
        files,
    };
    crate::formats::results::write_json(&dir.join("sidecar.json"), &index)?;
    Ok(report)
}
