//! `sync` as a pipeline stage over a prepared episode: reads every camera's `audio.wav`, its
//! recording mode from `meta.json` and the A/V delay of that mode from its unit's calibration,
//! and writes `work/sync/sync.json` with a manifest of input hashes, so a re-run with unchanged
//! inputs is skipped.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use kiwi_core::artifact::UnitCalibration;
use kiwi_core::io::{sha256_file, write_atomic};
use kiwi_core::layout::{EpisodeLayout, Session};

use super::audio::read_audio;
use super::{SyncInput, SyncResult, synchronise};
use crate::error::{BackendError, Result};

/// Version of the stage's algorithm and output format; a change re-runs the stage.
pub const STAGE_VERSION: &str = "sync-1";

/// The manifest written next to a stage's output.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    /// Stage version.
    pub version: String,
    /// Input files and their SHA-256.
    pub inputs: Vec<(String, String)>,
}

/// What the stage did.
#[derive(Debug)]
pub enum StageOutcome {
    /// Inputs unchanged since the last run: nothing done.
    UpToDate(PathBuf),
    /// Ran and wrote the result.
    Written(PathBuf, Box<SyncResult>),
}

/// The A/V delay of `mode` in a calibration, or an error saying how to get it.
pub fn av_delay_for(calibration: &UnitCalibration, mode: Option<&str>, path: &Path) -> Result<f64> {
    let found = match mode {
        Some(m) => calibration.av_delays.iter().find(|d| d.mode == m),
        None if calibration.av_delays.len() == 1 => calibration.av_delays.first(),
        None => None,
    };
    found.map(|d| d.delay_s).ok_or_else(|| BackendError::Input {
        path: path.to_path_buf(),
        message: format!(
            "no A/V delay for recording mode {}; the unit has delays for [{}]: certify it with `kiwi-calib av-delay`, or name the mode",
            mode.unwrap_or("(unspecified)"),
            calibration.av_delays.iter().map(|d| d.mode.as_str()).collect::<Vec<_>>().join(", ")
        ),
    })
}

/// Run the sync stage on episode `episode` of the session at `session_toml`.
pub fn run(session_toml: &Path, episode: &str, force: bool) -> Result<StageOutcome> {
    let root = session_toml.parent().unwrap_or(Path::new("."));
    let session = Session::load(session_toml)?;
    if !session.episodes.iter().any(|e| e.name == episode) {
        return Err(BackendError::Input {
            path: session_toml.to_path_buf(),
            message: format!("no episode `{episode}` in the session"),
        });
    }
    let layout = EpisodeLayout::new(session.episode_dir(root, episode));
    let mut cameras = Vec::new();
    for (side, wrist) in &session.wrists {
        cameras.push((
            side.camera_name().to_string(),
            root.join(&wrist.calibration).join("calibration.json"),
        ));
    }
    if let Some(head) = &session.head {
        cameras.push((
            "head".into(),
            root.join(&head.calibration).join("calibration.json"),
        ));
    }
    let mut inputs_hashes = Vec::new();
    for (camera, calibration) in &cameras {
        for p in [
            layout.audio_wav(camera),
            layout.meta_json(camera),
            calibration.clone(),
        ] {
            inputs_hashes.push((p.display().to_string(), sha256_file(&p)?));
        }
    }
    let manifest = Manifest {
        version: STAGE_VERSION.into(),
        inputs: inputs_hashes,
    };
    let out_dir = layout.work_dir("sync");
    let out = out_dir.join("sync.json");
    let manifest_path = out_dir.join("manifest.json");
    if !force
        && out.is_file()
        && std::fs::read_to_string(&manifest_path)
            .ok()
            .and_then(|t| serde_json::from_str::<Manifest>(&t).ok())
            .as_ref()
            == Some(&manifest)
    {
        return Ok(StageOutcome::UpToDate(out));
    }
    let mut inputs = Vec::new();
    for (camera, calibration_path) in &cameras {
        let meta = layout.read_meta(camera)?;
        let calibration = UnitCalibration::load(calibration_path)?;
        inputs.push(SyncInput {
            name: camera.clone(),
            audio: read_audio(&layout.audio_wav(camera))?,
            av_delay_s: av_delay_for(&calibration, Some(&meta.mode), calibration_path)?,
        });
    }
    let result = synchronise(&inputs);
    let text = serde_json::to_string_pretty(&result).map_err(|e| BackendError::Input {
        path: out.clone(),
        message: e.to_string(),
    })?;
    write_atomic(&out, text.as_bytes())?;
    let mtext = serde_json::to_string_pretty(&manifest).map_err(|e| BackendError::Input {
        path: manifest_path.clone(),
        message: e.to_string(),
    })?;
    write_atomic(&manifest_path, mtext.as_bytes())?;
    Ok(StageOutcome::Written(out, Box::new(result)))
}
