//! Check a session before reconstruction: `session.toml`, every unit calibration it names, and
//! every prepared episode's files (meta, IMU, audio, frames).

use std::path::Path;

use kiwi_core::artifact::UnitCalibration;
use kiwi_core::layout::{EpisodeLayout, Session};
use serde::Serialize;

use crate::error::Result;

/// What a session holds, for the user and for `--json`.
#[derive(Debug, Clone, Serialize)]
pub struct SessionReport {
    /// Session name.
    pub name: String,
    /// Episode that builds the maps.
    pub map_episode: String,
    /// Per camera: name, unit, whether its calibration is certified.
    pub cameras: Vec<CameraReport>,
    /// Per episode: per camera and lens, frame counts.
    pub episodes: Vec<EpisodeReport>,
}

/// One camera of the session.
#[derive(Debug, Clone, Serialize)]
pub struct CameraReport {
    /// Camera folder name (`left`, `right`, `head`).
    pub camera: String,
    /// Unit id.
    pub unit: String,
    /// Certification verdict of its calibration (`None` if uncertified).
    pub certified: Option<bool>,
}

/// One episode's content.
#[derive(Debug, Clone, Serialize)]
pub struct EpisodeReport {
    /// Episode name.
    pub name: String,
    /// `(camera, lens, frames)` for every lens found.
    pub lenses: Vec<(String, String, usize)>,
}

/// Load and check a session rooted at the folder of `session_toml`.
pub fn inspect_session(session_toml: &Path) -> Result<SessionReport> {
    let root = session_toml.parent().unwrap_or(Path::new("."));
    let session = Session::load(session_toml)?;
    session.check_files(root)?;
    let mut cameras = Vec::new();
    for (side, wrist) in &session.wrists {
        let cal = UnitCalibration::load(&root.join(&wrist.calibration).join("calibration.json"))?;
        cameras.push(CameraReport {
            camera: side.camera_name().into(),
            unit: wrist.unit.clone(),
            certified: cal.certification.map(|c| c.passed),
        });
    }
    if let Some(head) = &session.head {
        let cal = UnitCalibration::load(&root.join(&head.calibration).join("calibration.json"))?;
        cameras.push(CameraReport {
            camera: "head".into(),
            unit: head.unit.clone(),
            certified: cal.certification.map(|c| c.passed),
        });
    }
    let mut episodes = Vec::new();
    for ep in &session.episodes {
        let layout = EpisodeLayout::new(session.episode_dir(root, &ep.name));
        let mut lenses = Vec::new();
        for camera in session.camera_names() {
            for (lens, n) in layout.validate_camera(camera)? {
                check_video_stream(&layout.lens_dir(camera, &lens))?;
                lenses.push((camera.to_string(), lens, n));
            }
        }
        episodes.push(EpisodeReport {
            name: ep.name.clone(),
            lenses,
        });
    }
    Ok(SessionReport {
        name: session.name,
        map_episode: session.map_episode,
        cameras,
        episodes,
    })
}

/// Check a video-backed lens stream end to end: every frame decodes, at the time `frames.csv`
/// gives it, and the video holds exactly the frames listed. An image stream passes untouched
/// (its files are checked by [`EpisodeLayout::validate_camera`]).
pub fn check_video_stream(lens_dir: &Path) -> Result<()> {
    if !matches!(
        kiwi_core::layout::LensStorage::of(lens_dir)?,
        kiwi_core::layout::LensStorage::Video(_)
    ) {
        return Ok(());
    }
    let source = crate::frames::FrameSource::open(lens_dir)?;
    source.for_each_color(|_, _| Ok(()))
}
