//! `kiwi ingest`: turn a camera's own files into a prepared episode (docs/conventions.md) —
//! per camera `meta.json`, `imu.csv` (SI units, KIWI's IMU axes, the video clock), `audio.wav`
//! (sample 0 at video time 0), `exposure.csv` when the camera records exposure times, and per
//! lens a stream resized to the processing resolution (a video, or PNGs on request) with its
//! frame times from the container.
//!
//! Two readers: Insta360 recordings ([`insv`]: X5/X4 `.insv` with both lenses as tracks of one
//! file or as `_00_`/`_10_` file pairs, split recordings joined, and GO 3 files), whose IMU,
//! exposure times and lens calibration strings come from the file's metadata trailer; and the
//! generic path, any video file ffmpeg reads plus an IMU CSV ([`imu`]). Known field failures
//! are named errors ([`BackendError::NoGyroRecord`], [`BackendError::MissingAudio`],
//! [`BackendError::VariableFrameRate`], [`BackendError::MissingLensTrack`]).
//!
//! The episode is written into a hidden folder and renamed into place when complete, so a
//! failed or killed ingest leaves no half-written episode; an existing episode is never
//! overwritten.

pub mod imu;
pub mod insv;
pub mod media;

use std::path::{Path, PathBuf};

use serde::Serialize;

use kiwi_core::artifact::UnitCalibration;
use kiwi_core::imu::{ImuSample, write_imu_csv};
use kiwi_core::layout::{
    CameraMeta, EpisodeConfig, EpisodeLayout, FrameRecord, ImuRecording, LensRecording,
    RecordingInfo, Session, write_frames_csv,
};
use kiwi_core::video::{VideoCodec, VideoStreamWriter};

use crate::error::{BackendError, Result};
use imu::{AxisMap, ImuCsvOptions, read_imu_csv};
use insv::Insta360Telemetry;
use media::{AudioTrack, MediaFile, VideoTrack};

/// A frame interval may differ from the nominal period by this fraction before the track counts
/// as variable-rate: container time bases round well below it, a dropped frame doubles it.
pub const VFR_TOLERANCE: f64 = 0.1;
/// Default processing resolution (px across a lens): the paper processes 960 × 960 frames.
pub const DEFAULT_RESOLUTION: u32 = 960;
/// A recording mode of the unit matches the recording when its frame rate is this close
/// (relative): 29.97 and 30 Hz modes differ by 0.1 %.
const MODE_FPS_TOLERANCE: f64 = 5e-4;
/// Successive segments of a split recording must continue within this fraction of a frame
/// period on the device clock.
const SEGMENT_GAP_TOLERANCE: f64 = 0.5;

/// One camera's files.
#[derive(Debug, Clone)]
pub struct CameraInput {
    /// Camera slot: `left`, `right` or `head`.
    pub camera: String,
    /// Its files: one multi-track file, `_00_`/`_10_` pairs, segments of a split recording, or
    /// (generic) one file per lens in lens order.
    pub files: Vec<PathBuf>,
    /// An IMU CSV (the generic path, or a camera whose file has no IMU record).
    pub imu_csv: Option<PathBuf>,
}

/// How lens frames are written.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LensOutput {
    /// One PNG per frame.
    Images,
    /// One video per lens.
    Video(VideoCodec),
}

/// Options of `kiwi ingest`.
#[derive(Debug, Clone)]
pub struct IngestOptions {
    /// Processing width of each lens (px; a lens at or below it keeps its native size).
    pub resolution: u32,
    /// How lens frames are written.
    pub output: LensOutput,
    /// Which source lens (0: first track or `_00_` file, 1: the other) is a wrist's `front`.
    pub front_lens: usize,
    /// Recording mode name (default: the unit calibration's mode with this frame rate).
    pub mode: Option<String>,
    /// How to read IMU CSVs.
    pub imu_csv: ImuCsvOptions,
    /// Axis map for a camera model the table does not know (or to override it).
    pub imu_axes: Option<AxisMap>,
}

impl Default for IngestOptions {
    fn default() -> Self {
        Self {
            resolution: DEFAULT_RESOLUTION,
            output: LensOutput::Video(VideoCodec::H264 { crf: 12 }),
            front_lens: 0,
            mode: None,
            imu_csv: ImuCsvOptions::default(),
            imu_axes: None,
        }
    }
}

/// What ingest wrote for one camera.
#[derive(Debug, Clone, Serialize)]
pub struct CameraReport {
    /// Camera slot.
    pub camera: String,
    /// Camera model.
    pub camera_model: String,
    /// Recording mode written into `meta.json`.
    pub mode: String,
    /// `(lens, frames)`.
    pub lenses: Vec<(String, usize)>,
    /// IMU samples written.
    pub imu_samples: usize,
    /// Audio samples written.
    pub audio_samples: usize,
    /// Measured frame rate (Hz).
    pub fps: f64,
}

/// What ingest wrote.
#[derive(Debug, Clone, Serialize)]
pub struct IngestReport {
    /// The episode folder.
    pub episode_dir: PathBuf,
    /// Per camera.
    pub cameras: Vec<CameraReport>,
}

fn input(path: &Path, message: String) -> BackendError {
    BackendError::Input {
        path: path.to_path_buf(),
        message,
    }
}

/// Ingest one episode's recordings into the session of `session_toml` (adding the episode to
/// `session.toml` if it is not listed).
pub fn ingest_episode(
    session_toml: &Path,
    episode: &str,
    inputs: &[CameraInput],
    o: &IngestOptions,
) -> Result<IngestReport> {
    let root = session_toml.parent().unwrap_or(Path::new("."));
    let mut session = Session::load(session_toml)?;
    if episode.is_empty() || episode.contains(['/', '\\']) || episode.starts_with('.') {
        return Err(input(
            session_toml,
            format!("episode name `{episode}`: expected a folder name without separators"),
        ));
    }
    let final_dir = session.episode_dir(root, episode);
    if final_dir.exists() {
        return Err(input(
            &final_dir,
            "exists: ingest never overwrites an episode; remove it or choose another --episode"
                .into(),
        ));
    }
    for needed in session.camera_names() {
        if !inputs.iter().any(|i| i.camera == needed) {
            return Err(input(
                session_toml,
                format!("the session records a `{needed}` camera: give its files (--{needed})"),
            ));
        }
    }
    let partial = root
        .join("episodes")
        .join(format!(".ingest-{episode}.partial"));
    if partial.exists() {
        std::fs::remove_dir_all(&partial).map_err(|e| {
            input(
                &partial,
                format!("cannot remove a stale partial ingest: {e}"),
            )
        })?;
    }
    std::fs::create_dir_all(&partial)
        .map_err(|e| input(&partial, format!("cannot create: {e}")))?;
    let layout = EpisodeLayout::new(&partial);
    let mut cameras = Vec::new();
    for camera in inputs {
        match ingest_camera(root, &session, &layout, camera, o) {
            Ok(r) => cameras.push(r),
            Err(e) => {
                let _ = std::fs::remove_dir_all(&partial);
                return Err(e);
            }
        }
    }
    std::fs::rename(&partial, &final_dir).map_err(|e| {
        input(
            &final_dir,
            format!("cannot move the ingested episode here: {e}"),
        )
    })?;
    if !session.episodes.iter().any(|e| e.name == episode) {
        session.episodes.push(EpisodeConfig {
            name: episode.to_string(),
            description: "ingested".into(),
        });
        session.save(session_toml)?;
    }
    Ok(IngestReport {
        episode_dir: final_dir,
        cameras,
    })
}

/// One segment of a recording: its lens tracks in source order, its audio, its trailer.
struct Segment {
    lenses: Vec<(PathBuf, VideoTrack, Vec<f64>)>,
    audio: Option<(PathBuf, AudioTrack)>,
    telemetry: Option<Insta360Telemetry>,
}

/// `(lens digit, sequence number)` of an Insta360 file name (`VID_20260814_132640_00_013`).
fn insta360_name(path: &Path) -> Option<(u32, u32)> {
    let stem = path.file_stem()?.to_str()?;
    let parts: Vec<&str> = stem.split('_').collect();
    let [.., code, seq] = parts.as_slice() else {
        return None;
    };
    let code = code.as_bytes();
    if code.len() != 2 || !code.iter().all(u8::is_ascii_digit) {
        return None;
    }
    Some((u32::from(code[0] - b'0'), seq.parse().ok()?))
}

/// Group Insta360 files into segments (by sequence number, lens files ordered by lens digit);
/// files whose names do not follow the camera's pattern are segments in the order given.
fn group_segments(files: &[PathBuf]) -> Vec<Vec<PathBuf>> {
    let named: Option<Vec<(u32, u32, &PathBuf)>> = files
        .iter()
        .map(|f| insta360_name(f).map(|(lens, seq)| (seq, lens, f)))
        .collect();
    match named {
        Some(mut v) => {
            v.sort_by_key(|(seq, lens, _)| (*seq, *lens));
            let mut groups: Vec<(u32, Vec<PathBuf>)> = Vec::new();
            for (seq, _, f) in v {
                match groups.last_mut() {
                    Some((s, g)) if *s == seq => g.push(f.clone()),
                    _ => groups.push((seq, vec![f.clone()])),
                }
            }
            groups.into_iter().map(|(_, g)| g).collect()
        }
        None => files.iter().map(|f| vec![f.clone()]).collect(),
    }
}

fn check_constant_rate(path: &Path, track: &VideoTrack, times: &[f64]) -> Result<()> {
    let period = 1.0 / track.fps;
    for (k, w) in times.windows(2).enumerate() {
        let dt = w[1] - w[0];
        if (dt - period).abs() > VFR_TOLERANCE * period {
            return Err(BackendError::VariableFrameRate {
                file: path.to_path_buf(),
                track: track.index,
                frame: k + 1,
                interval_s: dt,
                period_s: period,
            });
        }
    }
    Ok(())
}

fn read_segment(files: &[PathBuf], insta360: bool) -> Result<Segment> {
    let mut lenses = Vec::new();
    let mut audio = None;
    for f in files {
        let media: MediaFile = media::probe(f)?;
        for track in media.video {
            let times = media::frame_times(f, &track)?;
            if times.is_empty() {
                return Err(input(
                    f,
                    format!("video track {} has no frames", track.index),
                ));
            }
            check_constant_rate(f, &track, &times)?;
            lenses.push((f.clone(), track, times));
        }
        if audio.is_none()
            && let Some(a) = media.audio.first()
        {
            audio = Some((f.clone(), a.clone()));
        }
    }
    let telemetry = if insta360 {
        Some(insv::read_telemetry(&files[0])?)
    } else {
        None
    };
    Ok(Segment {
        lenses,
        audio,
        telemetry,
    })
}

fn lens_names(camera: &str) -> Vec<&'static str> {
    if camera == "head" {
        vec!["main"]
    } else {
        vec!["front", "rear"]
    }
}

fn ingest_camera(
    root: &Path,
    session: &Session,
    layout: &EpisodeLayout,
    input_files: &CameraInput,
    o: &IngestOptions,
) -> Result<CameraReport> {
    let camera = input_files.camera.as_str();
    let (unit_id, calibration_dir) = match camera {
        "left" | "right" => {
            let side = if camera == "left" {
                kiwi_core::layout::Side::Left
            } else {
                kiwi_core::layout::Side::Right
            };
            let w = session.wrists.get(&side).ok_or_else(|| {
                input(
                    &root.join("session.toml"),
                    format!("no [wrists.{camera}] in the session; add it before ingesting"),
                )
            })?;
            (w.unit.clone(), w.calibration.clone())
        }
        "head" => {
            let h = session.head.as_ref().ok_or_else(|| {
                input(
                    &root.join("session.toml"),
                    "no [head] in the session; add it before ingesting --head".into(),
                )
            })?;
            (h.unit.clone(), h.calibration.clone())
        }
        other => {
            return Err(input(
                &root.join("session.toml"),
                format!("camera `{other}`: expected left, right or head"),
            ));
        }
    };
    let Some(first) = input_files.files.first() else {
        return Err(input(
            &root.join("session.toml"),
            format!("no files given for the {camera} camera"),
        ));
    };
    let flags: Vec<bool> = input_files
        .files
        .iter()
        .map(|f| insv::has_trailer(f))
        .collect::<Result<_>>()?;
    let insta360 = flags[0];
    if flags.iter().any(|&f| f != insta360) {
        return Err(input(
            first,
            format!(
                "the {camera} camera's files mix Insta360 recordings and other videos; give one \
                 recording's files"
            ),
        ));
    }
    let groups = if insta360 {
        group_segments(&input_files.files)
    } else {
        vec![input_files.files.clone()]
    };
    let segments: Vec<Segment> = groups
        .iter()
        .map(|g| read_segment(g, insta360))
        .collect::<Result<_>>()?;
    let names = lens_names(camera);
    let files_text = input_files
        .files
        .iter()
        .map(|f| f.display().to_string())
        .collect::<Vec<_>>()
        .join(", ");
    for seg in &segments {
        if seg.lenses.len() != names.len() {
            return Err(BackendError::MissingLensTrack {
                files: files_text,
                camera: camera.into(),
                found: seg.lenses.len(),
                expected: names.len(),
                lenses: names.join(", "),
                fix: if seg.lenses.len() < names.len() {
                    "A dual-lens recording holds both lenses as tracks of one .insv, or as a \
                     _00_/_10_ file pair: give both files, and check the camera recorded in a \
                     360 (both-lens) mode"
                        .into()
                } else {
                    "Give only this camera's lens tracks (the head camera has one lens)".into()
                },
            });
        }
    }
    // Source lens order to KIWI lens names.
    let order: Vec<usize> = if names.len() == 2 {
        if o.front_lens > 1 {
            return Err(input(
                first,
                format!("--front-lens {}: expected 0 or 1", o.front_lens),
            ));
        }
        vec![o.front_lens, 1 - o.front_lens]
    } else {
        vec![0]
    };
    let audio_missing = segments.iter().position(|s| s.audio.is_none());
    if let Some(k) = audio_missing {
        return Err(BackendError::MissingAudio {
            file: groups[k][0].clone(),
        });
    }
    // Segment start times on the camera clock: the first segment's first frame keeps its
    // container time; each later segment follows its predecessor's last frame by one period.
    let lens0 = &segments[0].lenses[0];
    let period = 1.0 / lens0.1.fps;
    let mut seg_start = vec![lens0.2[0]];
    for k in 1..segments.len() {
        let prev = &segments[k - 1].lenses[0].2;
        let start = seg_start[k - 1] + prev.len() as f64 * period;
        if let (Some(a), Some(b)) = (&segments[k - 1].telemetry, &segments[k].telemetry)
            && let (Some(fa), Some(fb)) = (
                a.metadata.first_frame_timestamp,
                b.metadata.first_frame_timestamp,
            )
        {
            let device_gap = (fb - fa) as f64 * a.clock_unit_s;
            let expected = start - seg_start[k - 1];
            if (device_gap - expected).abs() > SEGMENT_GAP_TOLERANCE * period {
                return Err(input(
                    &groups[k][0],
                    format!(
                        "this segment starts {device_gap:.4} s after the previous one on the \
                         camera's clock, but the previous one holds {expected:.4} s of frames: \
                         the segments are not one continuous recording (give each recording's \
                         segments, all of them, in one --{camera})"
                    ),
                ));
            }
        }
        seg_start.push(start);
    }
    let dir = layout.camera_dir(camera);
    std::fs::create_dir_all(&dir).map_err(|e| input(&dir, format!("cannot create: {e}")))?;

    // Lens streams.
    let mut lens_records = Vec::new();
    let mut lens_counts = Vec::new();
    for (name_index, &src) in order.iter().enumerate() {
        let name = names[name_index];
        let (path0, track0, _) = &segments[0].lenses[src];
        let (nw, nh) = (track0.width, track0.height);
        let (w, h) = output_size(nw, nh, o.resolution);
        let lens_dir = layout.lens_dir(camera, name);
        let mut times = Vec::new();
        let mut sink = LensSink::create(&lens_dir, o.output, w, h, &track0.rate)?;
        for (k, seg) in segments.iter().enumerate() {
            let (path, track, seg_times) = &seg.lenses[src];
            if (track.width, track.height) != (nw, nh) {
                return Err(input(
                    path,
                    format!(
                        "lens track {}x{}, the first segment's is {nw}x{nh}: not segments of one \
                         recording",
                        track.width, track.height
                    ),
                ));
            }
            let mut reader = media::decode_video(path, track.index, w, h)?;
            let mut n = 0;
            while let Some(frame) = reader.next_frame()? {
                if n >= seg_times.len() {
                    return Err(input(
                        path,
                        format!(
                            "video track {} decodes to more frames than its {} packets",
                            track.index,
                            seg_times.len()
                        ),
                    ));
                }
                sink.push(&frame)?;
                times.push(seg_start[k] + seg_times[n] - seg_times[0]);
                n += 1;
            }
            let decoded = reader.finish()?;
            if decoded != seg_times.len() {
                return Err(input(
                    path,
                    format!(
                        "video track {} decoded to {decoded} frames, its container lists {}; the \
                         file is damaged",
                        track.index,
                        seg_times.len()
                    ),
                ));
            }
        }
        let count = times.len();
        sink.finish(&times)?;
        lens_counts.push((name.to_string(), count));
        lens_records.push(LensRecording {
            name: name.into(),
            source: format!(
                "{}#v{}",
                path0
                    .file_name()
                    .map_or_else(String::new, |n| n.to_string_lossy().into_owned()),
                track0.index
            ),
            native_resolution: [nw, nh],
            resolution: [w, h],
            scale: f64::from(w) / f64::from(nw),
        });
    }

    // IMU.
    let model = segments[0]
        .telemetry
        .as_ref()
        .map_or_else(|| "generic".to_string(), |t| t.metadata.camera_type.clone());
    let (samples, imu_record) = match &input_files.imu_csv {
        Some(csv) => {
            let s = read_imu_csv(csv, &o.imu_csv)?;
            let rec = ImuRecording {
                source: csv.display().to_string(),
                axis_map: o.imu_csv.axes.text(),
                device_units: format!(
                    "time x{} s, gyro {}, accel {}",
                    o.imu_csv.time_unit.0,
                    if o.imu_csv.gyro_deg_s {
                        "deg/s"
                    } else {
                        "rad/s"
                    },
                    if o.imu_csv.accel_g { "g" } else { "m/s2" }
                ),
                samples: s.len(),
                rate_hz: rate_of(&s),
                time_offset_s: o.imu_csv.time_offset_s,
            };
            (s, rec)
        }
        None if insta360 => insta360_imu(camera, &model, &segments, &seg_start, o)?,
        None => {
            return Err(input(
                first,
                format!(
                    "not an Insta360 recording, and no IMU log: give the camera's IMU CSV with \
                     --{camera}-imu FILE (see kiwi ingest --help for its units and axes)"
                ),
            ));
        }
    };
    // A log in other units than the flags said (or a misread record) stops here, naming the
    // input, rather than at the first stage that reads imu.csv.
    let imu_source = input_files.imu_csv.as_deref().unwrap_or(first);
    kiwi_core::imu::check_imu_samples(imu_source, &samples)?;
    write_imu_csv(&layout.imu_csv(camera), &samples)?;

    // Exposure times.
    if let Some(rows) = exposure_rows(&segments, &seg_start) {
        kiwi_core::io::write_atomic(&dir.join("exposure.csv"), rows.as_bytes())?;
    }

    // Audio: sample 0 at video time 0.
    let (audio, audio_rate) = assemble_audio(&segments, &seg_start)?;
    let floats: Vec<f32> = audio.iter().map(|&v| f32::from(v) / 32767.0).collect();
    kiwi_core::audio::write_wav(&layout.audio_wav(camera), &floats, audio_rate)?;

    // meta.json.
    let fps = measured_fps(&segments[0].lenses[0].2);
    let mode = match &o.mode {
        Some(m) => m.clone(),
        None => mode_from_calibration(&root.join(&calibration_dir), fps, camera)?,
    };
    let t = segments[0].telemetry.as_ref();
    let meta = CameraMeta {
        camera: camera.into(),
        unit_id,
        camera_model: if insta360 {
            model.clone()
        } else {
            "generic".into()
        },
        mode: mode.clone(),
        fps,
        lenses: names.iter().map(|n| (*n).to_string()).collect(),
        audio_rate_hz: audio_rate,
        source: files_text,
        recording: Some(RecordingInfo {
            reader: if insta360 { "insta360" } else { "generic" }.into(),
            files: input_files
                .files
                .iter()
                .map(|f| f.display().to_string())
                .collect(),
            firmware: t.map(|t| t.metadata.firmware.clone()).unwrap_or_default(),
            serial: t.map(|t| t.metadata.serial.clone()).unwrap_or_default(),
            camera_mode: t
                .and_then(|t| t.metadata.dimension)
                .map(|(w, h)| format!("{w}x{h}@{}", lens0.1.rate))
                .unwrap_or_default(),
            measured_fps: fps,
            lenses: lens_records,
            imu: imu_record.clone(),
            lens_calibration_strings: t
                .map(|t| t.metadata.lens_offsets.clone())
                .unwrap_or_default(),
            readout_time_s: t
                .and_then(|t| t.metadata.rolling_shutter_ms)
                .map(|ms| ms * 1e-3),
        }),
    };
    layout.write_meta(&meta)?;
    Ok(CameraReport {
        camera: camera.into(),
        camera_model: meta.camera_model,
        mode,
        lenses: lens_counts,
        imu_samples: imu_record.samples,
        audio_samples: audio.len(),
        fps,
    })
}

/// Output size of a lens: `resolution` across, the height in proportion (rounded to even for
/// the codecs); a lens no wider than `resolution` keeps its size.
fn output_size(w: u32, h: u32, resolution: u32) -> (u32, u32) {
    if resolution == 0 || w <= resolution {
        return (w, h);
    }
    let oh = (f64::from(h) * f64::from(resolution) / f64::from(w) / 2.0).round() as u32 * 2;
    (resolution, oh.max(2))
}

fn rate_of(s: &[ImuSample]) -> f64 {
    match (s.first(), s.last()) {
        (Some(a), Some(b)) if s.len() > 1 && b.t > a.t => (s.len() - 1) as f64 / (b.t - a.t),
        _ => 0.0,
    }
}

fn measured_fps(times: &[f64]) -> f64 {
    let mut d: Vec<f64> = times.windows(2).map(|w| w[1] - w[0]).collect();
    if d.is_empty() {
        return 0.0;
    }
    d.sort_by(f64::total_cmp);
    1.0 / d[d.len() / 2]
}

fn insta360_imu(
    camera: &str,
    model: &str,
    segments: &[Segment],
    seg_start: &[f64],
    o: &IngestOptions,
) -> Result<(Vec<ImuSample>, ImuRecording)> {
    let Some(axes) = o.imu_axes.or_else(|| AxisMap::for_model(model)) else {
        return Err(input(
            segments[0].lenses[0].0.as_path(),
            format!(
                "camera model `{model}` has no IMU axis map in KIWI's table (known: {}); give \
                     one with --imu-axes (KIWI x,y,z as signed device axes, e.g. -y,-z,+x)",
                imu::MODEL_AXES
                    .iter()
                    .map(|(m, _)| *m)
                    .collect::<Vec<_>>()
                    .join(", ")
            ),
        ));
    };
    let mut out: Vec<ImuSample> = Vec::new();
    let mut offset = 0.0;
    let mut units = String::new();
    for (k, seg) in segments.iter().enumerate() {
        let Some(t) = &seg.telemetry else { continue };
        let Some(samples) = &t.imu else {
            return Err(BackendError::NoGyroRecord {
                file: t.file.clone(),
                model: t.metadata.camera_type.clone(),
                firmware: t.metadata.firmware.clone(),
                camera: camera.into(),
            });
        };
        if t.metadata.first_frame_timestamp.is_none() {
            return Err(input(
                &t.file,
                "the trailer gives no first-frame time stamp (field 24): the IMU cannot be \
                 placed on the video clock"
                    .into(),
            ));
        }
        offset = t.gyro_offset_s();
        units = if t.metadata.is_raw_gyro {
            format!(
                "raw u16, ±{} g, ±{} deg/s, us",
                t.metadata.accel_range_g.unwrap_or(f64::NAN),
                t.metadata.gyro_range_dps.unwrap_or(f64::NAN)
            )
        } else {
            "g, rad/s, ms".into()
        };
        for s in samples {
            let Some(v) = t.video_time(s.timestamp) else {
                continue;
            };
            // Device times count from the segment's first frame.
            let time = seg_start[k] + v - offset;
            if out.last().is_some_and(|p| time <= p.t) {
                continue;
            }
            out.push(ImuSample::new(
                time,
                axes.apply(s.gyro),
                axes.apply(s.accel),
            ));
        }
    }
    let rec = ImuRecording {
        source: "insta360 trailer record 3".into(),
        axis_map: axes.text(),
        device_units: units,
        samples: out.len(),
        rate_hz: rate_of(&out),
        time_offset_s: -offset,
    };
    Ok((out, rec))
}

fn exposure_rows(segments: &[Segment], seg_start: &[f64]) -> Option<String> {
    let mut rows = String::from("t,exposure_s\n");
    let mut any = false;
    for (k, seg) in segments.iter().enumerate() {
        let Some(t) = &seg.telemetry else { continue };
        for e in &t.exposures {
            if let Some(v) = t.video_time(e.timestamp) {
                rows.push_str(&format!("{},{}\n", seg_start[k] + v, e.exposure_s));
                any = true;
            }
        }
    }
    any.then_some(rows)
}

fn assemble_audio(segments: &[Segment], seg_start: &[f64]) -> Result<(Vec<i16>, u32)> {
    let mut out: Vec<i16> = Vec::new();
    let mut rate = 0u32;
    for (k, seg) in segments.iter().enumerate() {
        let Some((path, track)) = &seg.audio else {
            continue;
        };
        if rate == 0 {
            rate = track.rate_hz;
        } else if rate != track.rate_hz {
            return Err(input(
                path,
                format!(
                    "audio at {} Hz, the first segment's at {rate} Hz",
                    track.rate_hz
                ),
            ));
        }
        let samples = media::decode_audio(path, track.index)?;
        // The audio track's start on the camera clock.
        let start_s = seg_start[k] + (track.start_s - seg.lenses[0].2[0]);
        let first = (start_s * f64::from(rate)).round() as i64;
        for (i, &v) in samples.iter().enumerate() {
            let at = first + i as i64;
            if at < 0 {
                continue;
            }
            let at = at as usize;
            if at >= out.len() {
                out.resize(at + 1, 0);
            }
            out[at] = v;
        }
    }
    if rate == 0 || out.is_empty() {
        return Err(BackendError::MissingAudio {
            file: segments
                .first()
                .and_then(|s| s.lenses.first())
                .map(|l| l.0.clone())
                .unwrap_or_default(),
        });
    }
    Ok((out, rate))
}

fn mode_from_calibration(cal_dir: &Path, fps: f64, camera: &str) -> Result<String> {
    let path = cal_dir.join("calibration.json");
    if !path.is_file() {
        return Err(input(
            &path,
            format!(
                "missing: the {camera} unit's calibration names its recording modes; certify the \
                 unit first, or name the mode with --mode"
            ),
        ));
    }
    let cal = UnitCalibration::load(&path)?;
    let matching: Vec<&str> = cal
        .recording_modes
        .iter()
        .filter(|m| (m.fps - fps).abs() <= MODE_FPS_TOLERANCE * fps)
        .map(|m| m.name.as_str())
        .collect();
    match matching.as_slice() {
        [one] => Ok((*one).to_string()),
        _ => Err(input(
            &path,
            format!(
                "{} of the unit's recording modes run at {fps:.3} Hz ({}); name the mode with \
                 --mode",
                matching.len(),
                cal.recording_modes
                    .iter()
                    .map(|m| format!("{} {} Hz", m.name, m.fps))
                    .collect::<Vec<_>>()
                    .join(", ")
            ),
        )),
    }
}

/// Where a lens's frames go: a video encoder or a folder of PNGs.
enum LensSink {
    Video(VideoStreamWriter),
    Images {
        dir: PathBuf,
        width: u32,
        height: u32,
        files: Vec<String>,
    },
}

impl LensSink {
    fn create(lens_dir: &Path, output: LensOutput, w: u32, h: u32, rate: &str) -> Result<Self> {
        Ok(match output {
            LensOutput::Video(codec) => {
                Self::Video(VideoStreamWriter::create(lens_dir, codec, w, h, rate)?)
            }
            LensOutput::Images => {
                let frames = lens_dir.join("frames");
                std::fs::create_dir_all(&frames)
                    .map_err(|e| input(&frames, format!("cannot create: {e}")))?;
                Self::Images {
                    dir: lens_dir.to_path_buf(),
                    width: w,
                    height: h,
                    files: Vec::new(),
                }
            }
        })
    }

    fn push(&mut self, rgb: &[u8]) -> Result<()> {
        match self {
            Self::Video(v) => Ok(v.push_rgb(rgb)?),
            Self::Images {
                dir,
                width,
                height,
                files,
            } => {
                let name = EpisodeLayout::frame_file_name(files.len());
                let path = dir.join(&name);
                image::save_buffer_with_format(
                    &path,
                    rgb,
                    *width,
                    *height,
                    image::ExtendedColorType::Rgb8,
                    image::ImageFormat::Png,
                )
                .map_err(|e| input(&path, format!("cannot write the frame: {e}")))?;
                files.push(name);
                Ok(())
            }
        }
    }

    fn finish(self, times: &[f64]) -> Result<()> {
        match self {
            Self::Video(v) => {
                v.finish(times)?;
                Ok(())
            }
            Self::Images { dir, files, .. } => {
                let rows: Vec<FrameRecord> = files
                    .into_iter()
                    .zip(times)
                    .map(|(file, &t)| FrameRecord { t, file })
                    .collect();
                Ok(write_frames_csv(&dir.join("frames.csv"), &rows)?)
            }
        }
    }
}
