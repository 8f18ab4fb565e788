//! Session and prepared-episode layouts: `session.toml`, and the folder structure ingest (or the
//! simulator) writes and every stage reads.
//!
//! ```text
//! session/
//!   session.toml                    units per wrist, tools, head camera, episodes, map episode
//!   units/<unit>/<date>/calibration.json
//!   episodes/<episode>/
//!     <camera>/                     left | right | head
//!       meta.json                   camera model, unit, recording mode, lenses
//!       imu.csv                     t,gx,gy,gz,ax,ay,az (s, rad/s, m/s²)
//!       audio.wav
//!       <lens>/                     front | rear (X5), main (GO 3)
//!         frames.csv                t,file  (t in s on the camera clock, file relative to the lens folder)
//!         frames/000000.png …       an image stream, or
//!         video.json + video.mkv    a video stream: frames.csv's file is `video.mkv#<index>`
//!     work/<stage>/                 stage outputs and their manifest
//!     truth/                        simulator ground truth; never read by algorithms
//! ```

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::error::{CoreError, Result};
use crate::io::{read_text, write_atomic, write_atomic_with};

/// The `session.toml` schema version this build reads.
pub const SESSION_SCHEMA_VERSION: u32 = 1;
/// The header of `frames.csv`.
pub const FRAMES_CSV_HEADER: &str = "t,file";
/// The descriptor file whose presence makes a lens folder a video stream.
pub const VIDEO_JSON: &str = "video.json";
/// The `video.json` schema version this build reads.
pub const VIDEO_SCHEMA_VERSION: u32 = 1;
/// Separates the video file from the frame index in a video stream's `frames.csv` (`video.mkv#12`).
pub const VIDEO_FRAME_SEPARATOR: char = '#';

/// Which wrist a camera is on.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Side {
    /// The operator's left wrist.
    Left,
    /// The operator's right wrist.
    Right,
}

impl Side {
    /// The camera folder name of this wrist in a prepared episode.
    pub fn camera_name(self) -> &'static str {
        match self {
            Self::Left => "left",
            Self::Right => "right",
        }
    }

    /// The operator's other wrist.
    pub fn other(self) -> Self {
        match self {
            Self::Left => Self::Right,
            Self::Right => Self::Left,
        }
    }
}

/// The tool a wrist carries.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ToolKind {
    /// The two-finger chopstick gripper (opening is an angle).
    Chopstick,
    /// The ALOHA-style parallel-jaw gripper (opening is a width).
    ParallelJaw,
    /// The bare-hand wrist cuff (no opening).
    BareHand,
}

/// One wrist's camera unit and tool.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WristConfig {
    /// Unit id of the X5 on this wrist.
    pub unit: String,
    /// Folder of the unit's calibration set, relative to the session root.
    pub calibration: PathBuf,
    /// The tool on this wrist.
    pub tool: ToolKind,
}

/// The optional head camera and the hat marker.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HeadConfig {
    /// Unit id of the head camera.
    pub unit: String,
    /// Folder of the unit's calibration set, relative to the session root.
    pub calibration: PathBuf,
    /// ArUco dictionary of the hat marker (OpenCV's name without `DICT_`, e.g. `4x4_50`).
    #[serde(default = "default_marker_dictionary")]
    pub marker_dictionary: String,
    /// ArUco id of the hat marker.
    pub marker_id: u32,
    /// Side length of the hat marker's black square (m).
    pub marker_size_m: f64,
    /// A measured head mount file (`marker_from_cam`), relative to the session folder; absent,
    /// the printed hat's CAD mount (`hardware/head/hat.toml`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mount: Option<PathBuf>,
}

/// The printed hat's ArUco dictionary.
fn default_marker_dictionary() -> String {
    "4x4_50".into()
}

/// One episode of the session.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EpisodeConfig {
    /// Episode name; its folder is `episodes/<name>`.
    pub name: String,
    /// Free-text description (the simulator writes its scenario name).
    #[serde(default)]
    pub description: String,
}

/// `session.toml`: one scene on one day.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Session {
    /// Always [`SESSION_SCHEMA_VERSION`].
    pub schema_version: u32,
    /// Session name.
    pub name: String,
    /// The episode whose recordings build the maps.
    pub map_episode: String,
    /// The wrist whose rear lens builds the shared rear (scene) map (default: left).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub map_wrist: Option<Side>,
    /// Wrist cameras by side (`left`, `right`).
    pub wrists: BTreeMap<Side, WristConfig>,
    /// The head camera, if worn.
    #[serde(default)]
    pub head: Option<HeadConfig>,
    /// Episodes in recording order.
    pub episodes: Vec<EpisodeConfig>,
    /// Datasets `kiwi run` exports after the episodes' outputs (none when absent).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub export: Option<ExportConfig>,
    /// How the floor reference is sought (defaults when absent).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub floor: Option<FloorConfig>,
}

/// `[floor]` of `session.toml`: the floor reference's settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FloorConfig {
    /// Heights of the wrists' front cameras above the floor the floor may be at, `[low, high]`
    /// (m) [default: 0.5 to 2.2, a standing operator]. The lowest supported horizontal surface
    /// this far below a camera is the floor: lower `low` for work near the floor, raise it when
    /// a worktop sits lower than 0.5 m under the wrists.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub camera_height_m: Option<[f64; 2]>,
}

/// The dataset formats an `[export]` table may name.
pub const EXPORT_FORMATS: [&str; 5] = ["lerobot", "umi", "sidecar", "colmap", "nerfstudio"];

/// `[export]` of `session.toml`: the datasets `kiwi run` writes into `exports/<format>/` once
/// every episode's outputs are current (the options of `kiwi export`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ExportConfig {
    /// Formats to write: any of [`EXPORT_FORMATS`].
    pub formats: Vec<String>,
    /// Output rate (Hz) of the resampled formats [default: the slowest source's rate].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fps: Option<f64>,
    /// Views as `camera.lens` [default: every wrist's front lens and the head camera's lenses].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub views: Option<Vec<String>>,
    /// Images per second and lens stream of the scene exports (`colmap`, `nerfstudio`)
    /// [default: 1 Hz].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rate: Option<f64>,
}

/// Parse `session.toml` text; an error names the field (`wrists.left.tool`) and its line.
pub fn parse_session(text: &str, path: &Path) -> Result<Session> {
    let parse_error = |field: String, e: &toml::de::Error| {
        let at = e.span().map(|s| s.start.min(text.len()));
        // A map keyed by an enum (`[wrists.left]`) shows as `?` in the path: name it from the
        // table header above the error and the key on its line.
        let field = match at {
            Some(at) if field.contains('?') => field_at(text, at).unwrap_or(field),
            _ => field,
        };
        let line = at.map(|at| {
            text.as_bytes()[..at]
                .iter()
                .filter(|&&b| b == b'\n')
                .count()
                + 1
        });
        CoreError::Parse {
            path: path.to_path_buf(),
            format: "TOML",
            field: match line {
                Some(line) if field.is_empty() || field == "." => format!("line {line}"),
                Some(line) => format!("{field} (line {line})"),
                None => field,
            },
            message: e.message().trim().to_string(),
            fix: "see docs/conventions.md for the session.toml fields".into(),
        }
    };
    let de = toml::Deserializer::parse(text).map_err(|e| parse_error(".".into(), &e))?;
    serde_path_to_error::deserialize(de).map_err(|e| parse_error(e.path().to_string(), e.inner()))
}

/// The dotted field name at byte `at` of TOML text: the nearest `[table]` header above it and
/// the key of its line (`wrists.left.tool`).
fn field_at(text: &str, at: usize) -> Option<String> {
    let before = text.get(..at)?;
    let line_start = before.rfind('\n').map_or(0, |i| i + 1);
    let line = text.get(line_start..)?.lines().next()?;
    let key = line
        .split_once('=')
        .map(|(k, _)| k.trim().trim_matches('"'));
    let header = before[..line_start].lines().rev().find_map(|l| {
        let l = l.trim();
        l.strip_prefix('[')
            .and_then(|r| r.split_once(']'))
            .map(|(h, _)| h.trim_matches(['[', ']']).trim().to_string())
    });
    match (header, key) {
        (Some(h), Some(k)) if !k.is_empty() => Some(format!("{h}.{k}")),
        (Some(h), _) => Some(h),
        (None, Some(k)) if !k.is_empty() => Some(k.to_string()),
        _ => None,
    }
}

impl Session {
    /// Parse and validate a `session.toml`.
    pub fn load(path: &Path) -> Result<Self> {
        let text = read_text(path)?;
        let session = parse_session(&text, path)?;
        session.validate().map_err(|e| e.at_path(path))?;
        Ok(session)
    }

    /// Validate and write atomically.
    pub fn save(&self, path: &Path) -> Result<()> {
        self.validate().map_err(|e| e.at_path(path))?;
        let text = toml::to_string_pretty(self).map_err(|e| {
            CoreError::invalid_value(
                "session",
                "serializable values",
                e.to_string(),
                "fix the session",
            )
        })?;
        write_atomic(path, text.as_bytes())
    }

    /// Check the fields' consistency (not the files: see [`Session::check_files`]).
    pub fn validate(&self) -> Result<()> {
        if self.schema_version != SESSION_SCHEMA_VERSION {
            return Err(CoreError::invalid_value(
                "schema_version",
                SESSION_SCHEMA_VERSION.to_string(),
                self.schema_version.to_string(),
                "write the current schema version",
            ));
        }
        if self.wrists.is_empty() {
            return Err(CoreError::invalid_value(
                "wrists",
                "at least one of wrists.left, wrists.right",
                "none",
                "add a [wrists.left] table",
            ));
        }
        for (i, ep) in self.episodes.iter().enumerate() {
            if ep.name.is_empty() || ep.name.contains(['/', '\\']) || ep.name.starts_with('.') {
                return Err(CoreError::invalid_value(
                    format!("episodes[{i}].name"),
                    "a folder name without path separators",
                    format!("`{}`", ep.name),
                    "rename the episode",
                ));
            }
            if self.episodes[..i].iter().any(|e| e.name == ep.name) {
                return Err(CoreError::invalid_value(
                    format!("episodes[{i}].name"),
                    "a unique episode name",
                    format!("`{}` twice", ep.name),
                    "rename one",
                ));
            }
        }
        if !self.episodes.iter().any(|e| e.name == self.map_episode) {
            return Err(CoreError::invalid_value(
                "map_episode",
                "the name of one of the episodes",
                format!("`{}`", self.map_episode),
                "name the episode whose recordings build the maps",
            ));
        }
        if let Some(side) = self.map_wrist
            && !self.wrists.contains_key(&side)
        {
            return Err(CoreError::invalid_value(
                "map_wrist",
                "a wrist of the session",
                side.camera_name(),
                format!(
                    "add [wrists.{}] or set map_wrist to a wrist the session has",
                    side.camera_name()
                ),
            ));
        }
        if let Some(h) = &self.head
            && !(h.marker_size_m.is_finite() && h.marker_size_m > 0.0 && h.marker_size_m < 1.0)
        {
            return Err(CoreError::invalid_value(
                "head.marker_size_m",
                "a side length in metres, in (0, 1)",
                h.marker_size_m.to_string(),
                "marker sizes are in metres (58 mm = 0.058)",
            ));
        }
        if let Some([low, high]) = self.floor.as_ref().and_then(|f| f.camera_height_m)
            && !(low.is_finite() && high.is_finite() && low > 0.0 && low < high && high < 10.0)
        {
            return Err(CoreError::invalid_value(
                "floor.camera_height_m",
                "[low, high] in metres with 0 < low < high < 10",
                format!("[{low}, {high}]"),
                "give the wrists' camera-to-floor heights in metres, e.g. [0.5, 2.2]",
            ));
        }
        if let Some(x) = &self.export {
            for (i, f) in x.formats.iter().enumerate() {
                if !EXPORT_FORMATS.contains(&f.as_str()) || x.formats[..i].contains(f) {
                    return Err(CoreError::invalid_value(
                        format!("export.formats[{i}]"),
                        format!("one of {} (each once)", EXPORT_FORMATS.join(", ")),
                        format!("`{f}`"),
                        "name each dataset format once, or remove the [export] table",
                    ));
                }
            }
            if let Some(fps) = x.fps
                && !(fps.is_finite() && fps > 0.0)
            {
                return Err(CoreError::invalid_value(
                    "export.fps",
                    "a rate in Hz above 0",
                    fps.to_string(),
                    "remove it to export at the recording's own rate",
                ));
            }
            if let Some(rate) = x.rate
                && !(rate.is_finite() && rate > 0.0)
            {
                return Err(CoreError::invalid_value(
                    "export.rate",
                    "images per second and lens stream, above 0",
                    rate.to_string(),
                    "remove it to export about one image per second",
                ));
            }
        }
        Ok(())
    }

    /// Check that every calibration set and episode folder named exists under `root`.
    pub fn check_files(&self, root: &Path) -> Result<()> {
        let mut calibrations: Vec<&Path> = self
            .wrists
            .values()
            .map(|w| w.calibration.as_path())
            .collect();
        if let Some(h) = &self.head {
            calibrations.push(&h.calibration);
        }
        for c in calibrations {
            let file = root.join(c).join("calibration.json");
            if !file.is_file() {
                return Err(CoreError::Missing { path: file, fix: "certify the unit with `kiwi-calib certify` or fix the calibration path in session.toml".into() });
            }
        }
        if let Some(mount) = self.head.as_ref().and_then(|h| h.mount.as_ref()) {
            let file = root.join(mount);
            if !file.is_file() {
                return Err(CoreError::Missing {
                    path: file,
                    fix: "fix [head] mount in session.toml, or remove it to use the printed hat's \
                          mount (hardware/head/hat.toml)"
                        .into(),
                });
            }
        }
        for ep in &self.episodes {
            let dir = self.episode_dir(root, &ep.name);
            if !dir.is_dir() {
                return Err(CoreError::Missing {
                    path: dir,
                    fix: "ingest the episode's recordings, or remove it from session.toml".into(),
                });
            }
        }
        Ok(())
    }

    /// The wrist whose rear lens builds the shared rear map: `map_wrist`, else the left wrist
    /// when the session has one, else the right.
    pub fn map_side(&self) -> Side {
        self.map_wrist
            .or_else(|| self.wrists.keys().next().copied())
            .unwrap_or(Side::Left)
    }

    /// The folder of an episode.
    pub fn episode_dir(&self, root: &Path, name: &str) -> PathBuf {
        root.join("episodes").join(name)
    }

    /// Camera folder names this session records: `left`, `right`, and `head` if worn.
    pub fn camera_names(&self) -> Vec<&'static str> {
        let mut names: Vec<&'static str> = self.wrists.keys().map(|s| s.camera_name()).collect();
        if self.head.is_some() {
            names.push("head");
        }
        names
    }
}

/// `meta.json` of one camera in a prepared episode.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraMeta {
    /// Camera folder name (`left`, `right`, `head`).
    pub camera: String,
    /// Unit id of the physical camera.
    pub unit_id: String,
    /// Camera product (`Insta360 X5`, `Insta360 GO 3`).
    pub camera_model: String,
    /// Recording mode name (matches the unit artifact's recording modes).
    pub mode: String,
    /// Nominal frame rate (Hz).
    pub fps: f64,
    /// Lens folders present (`front`, `rear` or `main`).
    pub lenses: Vec<String>,
    /// Audio sample rate (Hz).
    pub audio_rate_hz: u32,
    /// Where the recording came from (original file names, or `kiwi-sim`).
    #[serde(default)]
    pub source: String,
    /// What ingest read from the camera's files (absent for simulated recordings).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub recording: Option<RecordingInfo>,
}

impl CameraMeta {
    /// Read a `meta.json` (errors name the file and the field).
    pub fn load(path: &Path) -> Result<Self> {
        let text = read_text(path)?;
        serde_path_to_error::deserialize(&mut serde_json::Deserializer::from_str(&text)).map_err(
            |e| CoreError::Parse {
                path: path.to_path_buf(),
                format: "JSON",
                field: e.path().to_string(),
                message: e.inner().to_string(),
                fix: "see docs/conventions.md for meta.json".into(),
            },
        )
    }
}

/// What `kiwi ingest` read from a camera's own files, kept in `meta.json` for the record and
/// for the checks later stages make (the lens scale against a calibration's resolution).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RecordingInfo {
    /// How the files were read (`insta360` trailer, or `generic` video + IMU CSV).
    pub reader: String,
    /// The source files, in the order they were joined.
    pub files: Vec<String>,
    /// Camera firmware as the file states it (empty when it does not).
    #[serde(default)]
    pub firmware: String,
    /// Camera serial number as the file states it (empty when it does not).
    #[serde(default)]
    pub serial: String,
    /// Recording mode as the camera names it (empty when the file does not say).
    #[serde(default)]
    pub camera_mode: String,
    /// Frame rate measured from the container's frame times (Hz).
    pub measured_fps: f64,
    /// Per lens: source track, native and processing resolution, scale.
    pub lenses: Vec<LensRecording>,
    /// Where `imu.csv` came from and how it was converted.
    pub imu: ImuRecording,
    /// The camera's own lens calibration strings by name (e.g. `offset_v3`), verbatim.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub lens_calibration_strings: BTreeMap<String, String>,
    /// Frame readout time the camera states (s), if any.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub readout_time_s: Option<f64>,
}

/// One lens stream as ingested.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LensRecording {
    /// Lens folder name (`front`, `rear`, `main`).
    pub name: String,
    /// Source file and video track it came from (`VID_x_00_001.insv#v0`).
    pub source: String,
    /// Native image size in the file `[w, h]` (px).
    pub native_resolution: [u32; 2],
    /// Image size of the prepared stream `[w, h]` (px).
    pub resolution: [u32; 2],
    /// `resolution / native_resolution` (the same in both axes): a lens calibration made at
    /// another resolution is rejected unless scaled explicitly.
    pub scale: f64,
}

/// How `imu.csv` was made.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ImuRecording {
    /// Source (`insta360 trailer record 3`, or the CSV file).
    pub source: String,
    /// The axis map applied: KIWI IMU axes x, y, z as signed device axes (`-y,-z,+x`).
    pub axis_map: String,
    /// Device units converted at ingest (`g, deg/s, us`).
    pub device_units: String,
    /// Samples written.
    pub samples: usize,
    /// Mean sample rate (Hz).
    pub rate_hz: f64,
    /// Shift applied to the device time stamps to put them on the video clock (s).
    pub time_offset_s: f64,
}

/// One row of `frames.csv`.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameRecord {
    /// Exposure time (s) on the camera clock (middle of the exposure, first row for rolling shutter).
    pub t: f64,
    /// Image file, relative to the lens folder.
    pub file: String,
}

/// `video.json`: the descriptor of a video-backed lens stream. A lens folder that holds it is a
/// video stream, and its `frames.csv` rows name frames of the video (`video.mkv#<index>`, in
/// order from 0); a folder without it is an image stream.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VideoStream {
    /// Always [`VIDEO_SCHEMA_VERSION`].
    pub schema_version: u32,
    /// The video file, relative to the lens folder.
    pub file: String,
    /// Frames in the video (= rows of `frames.csv`).
    pub frames: usize,
    /// Image width (px).
    pub width: u32,
    /// Image height (px).
    pub height: u32,
    /// Codec as ffmpeg names it (`utvideo`, `ffv1`, `h264`).
    pub codec: String,
    /// Whether decoding gives back the encoded pixels exactly.
    pub lossless: bool,
    /// Frames between random-access points (1: every frame is one).
    pub keyframe_interval: u32,
    /// The encoder settings, for the record.
    #[serde(default)]
    pub encoder: String,
}

impl VideoStream {
    /// Read and validate a lens folder's `video.json`.
    pub fn load(path: &Path) -> Result<Self> {
        let text = read_text(path)?;
        let v: Self =
            serde_path_to_error::deserialize(&mut serde_json::Deserializer::from_str(&text))
                .map_err(|e| CoreError::Parse {
                    path: path.to_path_buf(),
                    format: "JSON",
                    field: e.path().to_string(),
                    message: e.inner().to_string(),
                    fix: "see docs/conventions.md for video.json".into(),
                })?;
        v.validate().map_err(|e| e.at_path(path))?;
        Ok(v)
    }

    /// Validate and write atomically.
    pub fn save(&self, path: &Path) -> Result<()> {
        self.validate().map_err(|e| e.at_path(path))?;
        let text = serde_json::to_string_pretty(self).map_err(|e| {
            CoreError::invalid_value("video", "serializable values", e.to_string(), "fix it")
        })?;
        write_atomic(path, text.as_bytes())
    }

    fn validate(&self) -> Result<()> {
        if self.schema_version != VIDEO_SCHEMA_VERSION {
            return Err(CoreError::invalid_value(
                "schema_version",
                VIDEO_SCHEMA_VERSION.to_string(),
                self.schema_version.to_string(),
                "re-write the stream with this version of KIWI",
            ));
        }
        let plain_name = !self.file.is_empty()
            && !self.file.contains(['/', '\\', VIDEO_FRAME_SEPARATOR])
            && !self.file.starts_with('.');
        if !plain_name {
            return Err(CoreError::invalid_value(
                "file",
                "a file name inside the lens folder, without '#'",
                format!("`{}`", self.file),
                "rename the video",
            ));
        }
        if self.width == 0 || self.height == 0 || self.frames == 0 || self.keyframe_interval == 0 {
            return Err(CoreError::invalid_value(
                "width, height, frames, keyframe_interval",
                "positive values",
                format!(
                    "{}x{}, {} frames, keyframe interval {}",
                    self.width, self.height, self.frames, self.keyframe_interval
                ),
                "re-write the stream",
            ));
        }
        Ok(())
    }

    /// The `frames.csv` file name of frame `index`.
    pub fn frame_ref(&self, index: usize) -> String {
        format!("{}{VIDEO_FRAME_SEPARATOR}{index}", self.file)
    }

    /// Check that `frames.csv` rows name this video's frames 0, 1, … in order, one per frame.
    pub fn check_frames(&self, frames_csv: &Path, frames: &[FrameRecord]) -> Result<()> {
        if frames.len() != self.frames {
            return Err(CoreError::Invalid {
                path: frames_csv.to_path_buf(),
                field: "rows".into(),
                expected: format!("{} rows, one per frame of {}", self.frames, self.file),
                found: format!("{} rows", frames.len()),
                fix: "re-write the stream (frames.csv and video.json disagree)".into(),
            });
        }
        for (i, f) in frames.iter().enumerate() {
            if f.file != self.frame_ref(i) {
                return Err(CoreError::Invalid {
                    path: frames_csv.to_path_buf(),
                    field: format!("line {}, column file", i + 2),
                    expected: format!("`{}` (this folder is a video stream)", self.frame_ref(i)),
                    found: format!("`{}`", f.file),
                    fix: "a video stream's frames.csv names the video's frames in order; \
                          re-write the stream"
                        .into(),
                });
            }
        }
        Ok(())
    }
}

/// How a lens folder stores its frames.
#[derive(Debug, Clone, PartialEq)]
pub enum LensStorage {
    /// One image file per frame (`frames/000000.png`, as `frames.csv` names them).
    Images,
    /// One video file and its descriptor (`video.json`).
    Video(VideoStream),
}

impl LensStorage {
    /// Tell a lens folder's kind: a video stream when it holds `video.json`, else images.
    pub fn of(lens_dir: &Path) -> Result<Self> {
        let descriptor = lens_dir.join(VIDEO_JSON);
        if descriptor.is_file() {
            Ok(Self::Video(VideoStream::load(&descriptor)?))
        } else {
            Ok(Self::Images)
        }
    }

    /// A short name for messages (`images`, `video (utvideo)`).
    pub fn describe(&self) -> String {
        match self {
            Self::Images => "images".into(),
            Self::Video(v) => format!("video ({})", v.codec),
        }
    }
}

/// Read and validate `frames.csv` (strictly increasing finite times, non-empty file names).
pub fn read_frames_csv(path: &Path) -> Result<Vec<FrameRecord>> {
    let file = std::fs::File::open(path).map_err(|source| CoreError::Io {
        action: "opening",
        path: path.to_path_buf(),
        source,
    })?;
    parse_frames_csv(std::io::BufReader::new(file), path)
}

/// [`read_frames_csv`] on content from any reader; `path` names it in errors.
pub fn parse_frames_csv<R: std::io::Read>(reader: R, path: &Path) -> Result<Vec<FrameRecord>> {
    let mut reader = csv::ReaderBuilder::new()
        .has_headers(true)
        .from_reader(reader);
    let headers = reader.headers().map_err(|e| csv_error(path, &e))?.clone();
    if headers.get(0) != Some("t") || headers.get(1) != Some("file") {
        return Err(CoreError::Invalid {
            path: path.to_path_buf(),
            field: "line 1 (header)".into(),
            expected: format!("`{FRAMES_CSV_HEADER}`"),
            found: format!("`{}`", headers.iter().collect::<Vec<_>>().join(",")),
            fix: "write frames.csv with columns t (s) and file".into(),
        });
    }
    let mut frames: Vec<FrameRecord> = Vec::new();
    for (i, row) in reader.records().enumerate() {
        let line = i + 2;
        let row = row.map_err(|e| csv_error(path, &e))?;
        let invalid = |expected: &str, found: String| CoreError::Invalid {
            path: path.to_path_buf(),
            field: format!("line {line}"),
            expected: expected.into(),
            found,
            fix: "repair the line".into(),
        };
        let t: f64 = row.get(0).unwrap_or("").trim().parse().map_err(|_| {
            invalid(
                "a time in seconds in column t",
                format!("`{}`", row.get(0).unwrap_or("")),
            )
        })?;
        let file = row.get(1).unwrap_or("").trim().to_string();
        if !t.is_finite() {
            return Err(invalid("a finite time", t.to_string()));
        }
        if file.is_empty() {
            return Err(invalid(
                "an image file name in column file",
                "an empty value".into(),
            ));
        }
        if let Some(prev) = frames.last()
            && t <= prev.t
        {
            return Err(CoreError::Invalid {
                path: path.to_path_buf(),
                field: format!("line {line}, column t"),
                expected: format!("a time after the previous {} s", prev.t),
                found: format!("{t} s"),
                fix:
                    "frames must be sorted with no repeated times (was the recording concatenated?)"
                        .into(),
            });
        }
        frames.push(FrameRecord { t, file });
    }
    Ok(frames)
}

/// Write `frames.csv` atomically.
pub fn write_frames_csv(path: &Path, frames: &[FrameRecord]) -> Result<()> {
    use std::io::Write;
    write_atomic_with(path, |f| {
        let mut w = std::io::BufWriter::new(f);
        writeln!(w, "{FRAMES_CSV_HEADER}")?;
        for fr in frames {
            writeln!(w, "{},{}", fr.t, fr.file)?;
        }
        w.flush()
    })
}

fn csv_error(path: &Path, e: &csv::Error) -> CoreError {
    if let csv::ErrorKind::Io(io) = e.kind() {
        return CoreError::Io {
            action: "reading",
            path: path.to_path_buf(),
            source: std::io::Error::new(io.kind(), io.to_string()),
        };
    }
    let field = e
        .position()
        .map_or_else(|| ".".into(), |p| format!("line {}", p.line()));
    CoreError::Parse {
        path: path.to_path_buf(),
        format: "CSV",
        field,
        message: e.to_string(),
        fix: "repair the file".into(),
    }
}

/// Paths inside one prepared episode.
#[derive(Debug, Clone)]
pub struct EpisodeLayout {
    root: PathBuf,
}

impl EpisodeLayout {
    /// The layout of the episode folder `root`.
    pub fn new(root: impl Into<PathBuf>) -> Self {
        Self { root: root.into() }
    }
    /// The episode folder.
    pub fn root(&self) -> &Path {
        &self.root
    }
    /// A camera's folder.
    pub fn camera_dir(&self, camera: &str) -> PathBuf {
        self.root.join(camera)
    }
    /// A camera's `meta.json`.
    pub fn meta_json(&self, camera: &str) -> PathBuf {
        self.camera_dir(camera).join("meta.json")
    }
    /// A camera's `imu.csv`.
    pub fn imu_csv(&self, camera: &str) -> PathBuf {
        self.camera_dir(camera).join("imu.csv")
    }
    /// A camera's `audio.wav`.
    pub fn audio_wav(&self, camera: &str) -> PathBuf {
        self.camera_dir(camera).join("audio.wav")
    }
    /// A lens folder.
    pub fn lens_dir(&self, camera: &str, lens: &str) -> PathBuf {
        self.camera_dir(camera).join(lens)
    }
    /// A lens's `frames.csv`.
    pub fn frames_csv(&self, camera: &str, lens: &str) -> PathBuf {
        self.lens_dir(camera, lens).join("frames.csv")
    }
    /// A lens's `video.json` (present only in a video stream).
    pub fn video_json(&self, camera: &str, lens: &str) -> PathBuf {
        self.lens_dir(camera, lens).join(VIDEO_JSON)
    }
    /// The image file of a frame record.
    pub fn frame_path(&self, camera: &str, lens: &str, frame: &FrameRecord) -> PathBuf {
        self.lens_dir(camera, lens).join(&frame.file)
    }
    /// Conventional image file name of frame `index` (relative to the lens folder).
    pub fn frame_file_name(index: usize) -> String {
        format!("frames/{index:06}.png")
    }
    /// A stage's work folder.
    pub fn work_dir(&self, stage: &str) -> PathBuf {
        self.root.join("work").join(stage)
    }
    /// The simulator's ground truth folder.
    pub fn truth_dir(&self) -> PathBuf {
        self.root.join("truth")
    }

    /// Read a camera's `meta.json`.
    pub fn read_meta(&self, camera: &str) -> Result<CameraMeta> {
        CameraMeta::load(&self.meta_json(camera))
    }

    /// Write a camera's `meta.json` atomically.
    pub fn write_meta(&self, meta: &CameraMeta) -> Result<()> {
        let text = serde_json::to_string_pretty(meta).map_err(|e| {
            CoreError::invalid_value(
                "meta",
                "serializable values",
                e.to_string(),
                "fix the metadata",
            )
        })?;
        write_atomic(&self.meta_json(&meta.camera), text.as_bytes())
    }

    /// Check that a camera's files are complete and consistent: `meta.json`, `imu.csv`,
    /// `audio.wav`, and per lens a valid `frames.csv` whose every image exists (an image
    /// stream; their content is checked by `kiwi inspect`) or whose rows match `video.json` and
    /// its video file (a video stream).
    /// Returns the number of frames per lens.
    pub fn validate_camera(&self, camera: &str) -> Result<Vec<(String, usize)>> {
        let meta = self.read_meta(camera)?;
        for file in [self.imu_csv(camera), self.audio_wav(camera)] {
            if !file.is_file() {
                return Err(CoreError::Missing {
                    path: file,
                    fix: "re-run ingest (or the simulator) for this camera".into(),
                });
            }
        }
        let mut counts = Vec::new();
        for lens in &meta.lenses {
            let csv = self.frames_csv(camera, lens);
            let frames = read_frames_csv(&csv)?;
            if let LensStorage::Video(video) = LensStorage::of(&self.lens_dir(camera, lens))? {
                video.check_frames(&csv, &frames)?;
                let file = self.lens_dir(camera, lens).join(&video.file);
                if !file.is_file() {
                    return Err(CoreError::Missing {
                        path: file,
                        fix: "video.json names a video that is not there; re-run ingest".into(),
                    });
                }
                counts.push((lens.clone(), frames.len()));
                continue;
            }
            for fr in &frames {
                let p = self.frame_path(camera, lens, fr);
                if !p.is_file() {
                    return Err(CoreError::Missing {
                        path: p,
                        fix: "frames.csv names an image that is not there; re-run ingest".into(),
                    });
                }
            }
            counts.push((lens.clone(), frames.len()));
        }
        Ok(counts)
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn video() -> VideoStream {
        VideoStream {
            schema_version: VIDEO_SCHEMA_VERSION,
            file: "video.mkv".into(),
            frames: 3,
            width: 320,
            height: 320,
            codec: "utvideo".into(),
            lossless: true,
            keyframe_interval: 1,
            encoder: String::new(),
        }
    }

    #[test]
    fn a_folder_with_video_json_is_a_video_stream_and_its_rows_must_name_its_frames() {
        let dir = tempfile::tempdir().unwrap();
        assert_eq!(LensStorage::of(dir.path()).unwrap(), LensStorage::Images);
        let v = video();
        v.save(&dir.path().join(VIDEO_JSON)).unwrap();
        assert_eq!(
            LensStorage::of(dir.path()).unwrap(),
            LensStorage::Video(v.clone())
        );
        let rows: Vec<FrameRecord> = (0..3)
            .map(|i| FrameRecord {
                t: i as f64 / 30.0,
                file: v.frame_ref(i),
            })
            .collect();
        let csv = dir.path().join("frames.csv");
        v.check_frames(&csv, &rows).unwrap();
        let mut png = rows.clone();
        png[1].file = "frames/000001.png".into();
        let e = v.check_frames(&csv, &png).unwrap_err().to_string();
        assert!(e.contains("line 3") && e.contains("video.mkv#1"), "{e}");
        let e = v.check_frames(&csv, &rows[..2]).unwrap_err().to_string();
        assert!(e.contains("3 rows"), "{e}");
    }

    #[test]
    fn a_video_descriptor_with_a_path_or_no_frames_is_rejected() {
        let dir = tempfile::tempdir().unwrap();
        let mut v = video();
        v.file = "../x.mkv".into();
        assert!(v.save(&dir.path().join(VIDEO_JSON)).is_err());
        let mut v = video();
        v.frames = 0;
        assert!(v.save(&dir.path().join(VIDEO_JSON)).is_err());
    }

    #[test]
    fn session_toml_errors_name_the_wrist() {
        let text = "name = \"s\"\nmap_episode = \"ep000\"\n\n[wrists.left]\nunit = \"X5-1\"\n\
                    calibration = \"units/X5-1/2026-01-01\"\ntool = \"spoon\"\n";
        let e = parse_session(text, Path::new("session.toml"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("wrists.left.tool (line 7)"), "{e}");
        assert!(e.contains("spoon"), "{e}");
        assert!(e.contains("session.toml"), "{e}");
        // Not TOML at all: the line, never a byte offset.
        let e = parse_session("name = \n", Path::new("session.toml"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("line 1"), "{e}");
    }
}
