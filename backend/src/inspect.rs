//! Check a session before reconstruction: `session.toml`, every unit calibration it names, and
//! every prepared episode's files: `meta.json`, the whole `imu.csv` (values and units), the
//! `audio.wav` header against the file's size, and every frame of every lens stream (present,
//! an image of the calibrated size; `--deep` decodes each one).
//!
//! One lens stream is checked by [`check_stream`], so other frame sources (video files) slot in
//! there. Problems are collected, not stopped at: the report lists every one.

use std::collections::BTreeMap;
use std::path::Path;

use kiwi_core::artifact::UnitCalibration;
use kiwi_core::layout::{EpisodeLayout, FrameRecord, Session};
use rayon::prelude::*;
use serde::Serialize;

use crate::error::{BackendError, Result};

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
    /// Every problem found (file, what was expected, what was found); empty when all is well.
    pub problems: Vec<String>,
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

/// What [`check_stream`] found in one lens stream.
#[derive(Debug, Clone, Serialize)]
pub struct StreamReport {
    /// Frames listed.
    pub frames: usize,
    /// Problems, each naming the file.
    pub problems: Vec<String>,
}

/// How thoroughly to check.
#[derive(Debug, Clone, Copy, Default)]
pub struct InspectOptions {
    /// Decode every frame and every audio sample instead of reading headers and sizes.
    pub deep: bool,
}

/// At most this many problems are listed per stream (a stream whose every frame is wrong
/// would otherwise print thousands of lines saying one thing).
const MAX_PROBLEMS_PER_STREAM: usize = 10;

/// Check one lens stream of a prepared episode: `frames.csv`, and for every frame that its
/// image exists and is an image of `expected_size` (`[w, h]`, the calibration's resolution).
/// Headers only, unless `deep` (then every image is decoded).
pub fn check_stream(
    layout: &EpisodeLayout,
    camera: &str,
    lens: &str,
    expected_size: Option<[u32; 2]>,
    deep: bool,
) -> StreamReport {
    let csv = layout.frames_csv(camera, lens);
    let frames = match kiwi_core::layout::read_frames_csv(&csv) {
        Ok(f) => f,
        Err(e) => {
            return StreamReport {
                frames: 0,
                problems: vec![e.to_string()],
            };
        }
    };
    if frames.is_empty() {
        return StreamReport {
            frames: 0,
            problems: vec![format!(
                "{}: lists no frames; expected the lens's frames (re-run ingest)",
                csv.display()
            )],
        };
    }
    let lens_dir = layout.lens_dir(camera, lens);
    match kiwi_core::layout::LensStorage::of(&lens_dir) {
        Err(e) => {
            return StreamReport {
                frames: frames.len(),
                problems: vec![e.to_string()],
            };
        }
        Ok(kiwi_core::layout::LensStorage::Video(video)) => {
            return StreamReport {
                frames: frames.len(),
                problems: check_video_stream(&lens_dir, &csv, &frames, &video, expected_size, deep),
            };
        }
        Ok(kiwi_core::layout::LensStorage::Images) => {}
    }
    let mut problems: Vec<String> = frames
        .par_iter()
        .filter_map(|f| check_frame(layout, camera, lens, f, expected_size, deep))
        .collect();
    let total = problems.len();
    if total > MAX_PROBLEMS_PER_STREAM {
        problems.truncate(MAX_PROBLEMS_PER_STREAM);
        problems.push(format!(
            "{}: {} more frames with problems",
            csv.display(),
            total - MAX_PROBLEMS_PER_STREAM
        ));
    }
    StreamReport {
        frames: frames.len(),
        problems,
    }
}

fn check_frame(
    layout: &EpisodeLayout,
    camera: &str,
    lens: &str,
    frame: &FrameRecord,
    expected_size: Option<[u32; 2]>,
    deep: bool,
) -> Option<String> {
    let path = layout.frame_path(camera, lens, frame);
    let size = if deep {
        image::open(&path).map(|i| [i.width(), i.height()])
    } else {
        image::ImageReader::open(&path)
            .and_then(image::ImageReader::with_guessed_format)
            .map_err(image::ImageError::IoError)
            .and_then(image::ImageReader::into_dimensions)
            .map(|(w, h)| [w, h])
    };
    match (size, expected_size) {
        (Err(e), _) => Some(format!(
            "{} (frame t = {} s): expected a readable image, found: {e}; re-run ingest for \
             this lens",
            path.display(),
            frame.t
        )),
        (Ok(found), Some(expected)) if found != expected => Some(format!(
            "{}: expected a {}×{} image (the calibration's resolution), found {}×{}; was the \
             recording made in another mode, or the frame resized?",
            path.display(),
            expected[0],
            expected[1],
            found[0],
            found[1]
        )),
        _ => None,
    }
}

/// Check a video-backed lens stream: `frames.csv` names the video's frames in order, the video
/// is there at the calibrated size, and (when `deep`) every frame decodes at the time
/// `frames.csv` gives it.
fn check_video_stream(
    lens_dir: &Path,
    csv: &Path,
    frames: &[FrameRecord],
    video: &kiwi_core::layout::VideoStream,
    expected_size: Option<[u32; 2]>,
    deep: bool,
) -> Vec<String> {
    let mut problems = Vec::new();
    if let Err(e) = video.check_frames(csv, frames) {
        problems.push(e.to_string());
    }
    let file = lens_dir.join(&video.file);
    if !file.is_file() {
        problems.push(format!(
            "{}: missing; video.json names it (re-run ingest for this lens)",
            file.display()
        ));
        return problems;
    }
    if let Some(expected) = expected_size
        && expected != [video.width, video.height]
    {
        problems.push(format!(
            "{}: expected {}×{} frames (the calibration's resolution), found {}×{}; was the \
             recording made in another mode, or ingested at another resolution?",
            file.display(),
            expected[0],
            expected[1],
            video.width,
            video.height
        ));
    }
    if deep && problems.is_empty() {
        let decoded = crate::frames::FrameSource::open(lens_dir)
            .and_then(|source| source.for_each_color(|_, _| Ok(())));
        if let Err(e) = decoded {
            problems.push(e.to_string());
        }
    }
    problems
}

/// Check a camera's own files: `meta.json`, the whole `imu.csv` (with the units check), and
/// `audio.wav` (header against size and meta's rate; decoded when `deep`). Returns the lenses
/// meta.json lists and the problems.
fn check_camera_files(
    layout: &EpisodeLayout,
    camera: &str,
    deep: bool,
) -> (Vec<String>, Vec<String>) {
    let mut problems = Vec::new();
    let meta = match layout.read_meta(camera) {
        Ok(m) => m,
        Err(e) => return (Vec::new(), vec![e.to_string()]),
    };
    let imu = layout.imu_csv(camera);
    if !imu.is_file() {
        problems.push(format!(
            "{}: missing; re-run ingest (or the simulator) for this camera",
            imu.display()
        ));
    } else if let Err(e) = kiwi_core::imu::ImuSeries::read_csv(&imu) {
        problems.push(e.to_string());
    }
    let wav = layout.audio_wav(camera);
    match check_wav(&wav, deep) {
        Ok(rate) if rate != meta.audio_rate_hz => problems.push(format!(
            "{}: expected audio at {} Hz (meta.json audio_rate_hz), found {rate} Hz; re-run \
             ingest",
            wav.display(),
            meta.audio_rate_hz
        )),
        Ok(_) => {}
        Err(e) => problems.push(e),
    }
    (meta.lenses, problems)
}

/// The sample rate of a WAV file after checking its header (or all of it when `deep`).
fn check_wav(path: &Path, deep: bool) -> std::result::Result<u32, String> {
    let file = std::fs::File::open(path).map_err(|e| {
        format!(
            "{}: {e}; expected the camera's audio.wav (re-run ingest)",
            path.display()
        )
    })?;
    let len = file.metadata().map_or(0, |m| m.len());
    let info = kiwi_core::audio::wav_info(std::io::BufReader::new(file), len, path)
        .map_err(|e| e.to_string())?;
    if deep {
        kiwi_core::audio::read_audio(path).map_err(|e| e.to_string())?;
    }
    Ok(info.rate_hz)
}

/// Load and check a session rooted at the folder of `session_toml`.
pub fn inspect_session(session_toml: &Path, options: InspectOptions) -> Result<SessionReport> {
    if session_toml.is_dir() {
        return Err(BackendError::Input {
            path: session_toml.to_path_buf(),
            message: format!(
                "is a folder; expected the session's session.toml (try {})",
                session_toml.join("session.toml").display()
            ),
        });
    }
    let root = session_toml.parent().unwrap_or(Path::new("."));
    let session = Session::load(session_toml)?;
    session.check_files(root)?;
    let mut cameras = Vec::new();
    let mut calibrations: BTreeMap<String, UnitCalibration> = BTreeMap::new();
    for (side, wrist) in &session.wrists {
        let cal = UnitCalibration::load(&root.join(&wrist.calibration).join("calibration.json"))?;
        cameras.push(CameraReport {
            camera: side.camera_name().into(),
            unit: wrist.unit.clone(),
            certified: cal.certification.as_ref().map(|c| c.passed),
        });
        calibrations.insert(side.camera_name().into(), cal);
    }
    if let Some(head) = &session.head {
        let cal = UnitCalibration::load(&root.join(&head.calibration).join("calibration.json"))?;
        cameras.push(CameraReport {
            camera: "head".into(),
            unit: head.unit.clone(),
            certified: cal.certification.as_ref().map(|c| c.passed),
        });
        calibrations.insert("head".into(), cal);
    }
    let mut episodes = Vec::new();
    let mut problems = Vec::new();
    for ep in &session.episodes {
        let layout = EpisodeLayout::new(session.episode_dir(root, &ep.name));
        let mut lenses = Vec::new();
        for camera in session.camera_names() {
            let (lens_names, mut found) = check_camera_files(&layout, camera, options.deep);
            problems.append(&mut found);
            if let (Ok(meta), Some(cal)) = (layout.read_meta(camera), calibrations.get(camera))
                && meta.unit_id != cal.unit_id
            {
                problems.push(format!(
                    "{}: recorded by unit {}, but session.toml calibrates camera {camera} with \
                     unit {}'s set; fix the unit in session.toml",
                    layout.meta_json(camera).display(),
                    meta.unit_id,
                    cal.unit_id
                ));
            }
            for lens in lens_names {
                let expected = calibrations
                    .get(camera)
                    .and_then(|c| c.lens(&lens))
                    .map(|l| l.resolution);
                let stream = check_stream(&layout, camera, &lens, expected, options.deep);
                problems.extend(stream.problems);
                lenses.push((camera.to_string(), lens, stream.frames));
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
        problems,
    })
}
