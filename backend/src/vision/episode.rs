//! Prepared-episode drivers of `kiwi map` and `kiwi localize`: read a lens stream
//! (`<episode>/<camera>/<lens>/`: `frames.csv` and its images or video, through
//! [`crate::frames::FrameSource`]) with its calibration, build a map from it, localize it
//! against a frozen map, and write `poses.csv`.
//!
//! The calibration comes from `--calibration` or, by default, from the session the episode
//! belongs to (`<session>/episodes/<episode>`): the unit named in the camera's `meta.json` is
//! looked up in `session.toml` and its `calibration.json` read. Images are decoded ahead in
//! parallel batches (decoding is independent per frame, so results do not depend on the
//! thread count); the vision itself runs sequentially in frame order.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::time::Instant;

use serde::Serialize;

use kiwi_core::artifact::UnitCalibration;
use kiwi_core::camera::{Camera, CameraModel};
use kiwi_core::geometry::Pose;
use kiwi_core::layout::{EpisodeLayout, FrameRecord, Session};

use crate::error::{BackendError, Result};
use crate::frames::FrameSource;
use crate::vision::features::{
    FOV_MASK_MARGIN_RAD, GrayImage, Mask, OrbExtractor, OrbOptions, fov_mask, intersect_masks,
};
use crate::vision::frontend::{FrameTracker, TrackerOptions};
use crate::vision::localize::{
    FrameLocalization, LocalizationStatus, Localizer, LocalizerOptions, RelocalizationSource,
    pixel_angle,
};
use crate::vision::loop_closure::{LoopOptions, LoopReport, close_loops};
use crate::vision::map::VisualMap;
use crate::vision::mapping::{MapperOptions, global_adjustment, reconstruct};
use crate::vision::quality::{MapQuality, assess};
use crate::vision::runs::{
    Conflict, RunBook, WitnessJudgement, conflict_reason, conflicts, judge_runs,
    runs_joining_withdrawn, runs_to_withdraw, withdraw, witness_agrees, witness_reason,
};

/// Angle of one pixel at the centre of the 960 px X5 lens the mapper's defaults are tuned for.
const REFERENCE_PIXEL_ANGLE_RAD: f64 = 1.0 / 290.0;

/// One lens's frames in a prepared episode, with the lens model to read them.
pub struct LensStream {
    /// The episode folder.
    pub episode: PathBuf,
    /// Camera folder name (`left`, `right`, `head`).
    pub camera_name: String,
    /// Lens name (`front`, `rear`, `main`).
    pub lens: String,
    /// The lens's calibrated model.
    pub camera: Camera,
    /// The frames this stream processes: `frames.csv`'s rows, or the part [`LensStream::select`]
    /// kept.
    pub frames: Vec<FrameRecord>,
    /// The frames themselves (images or video).
    pub source: FrameSource,
    /// Index in `source` of each of `frames`.
    source_index: Vec<usize>,
    /// Features allowed where non-zero: the lens's field of view, intersected with a static
    /// mask if one was given.
    pub mask: Mask,
}

fn input_err(path: &Path, message: String) -> BackendError {
    BackendError::Input {
        path: path.to_path_buf(),
        message,
    }
}

/// Find the unit calibration of a camera from the session the episode belongs to.
fn session_calibration(layout: &EpisodeLayout, camera: &str) -> Result<PathBuf> {
    let meta = layout.read_meta(camera)?;
    let root = layout
        .root()
        .parent()
        .and_then(Path::parent)
        .ok_or_else(|| {
            input_err(
                layout.root(),
                "expected the episode inside <session>/episodes/; pass --calibration".into(),
            )
        })?;
    let toml = root.join("session.toml");
    if !toml.is_file() {
        return Err(input_err(
            &toml,
            "no session.toml two folders above the episode to find the lens calibration; pass \
             --calibration FILE"
                .into(),
        ));
    }
    let session = Session::load(&toml)?;
    let mut dirs: Vec<(&str, &Path)> = session
        .wrists
        .values()
        .map(|w| (w.unit.as_str(), w.calibration.as_path()))
        .collect();
    if let Some(h) = &session.head {
        dirs.push((h.unit.as_str(), h.calibration.as_path()));
    }
    dirs.iter()
        .find(|(unit, _)| *unit == meta.unit_id)
        .map(|(_, dir)| root.join(dir).join("calibration.json"))
        .ok_or_else(|| {
            input_err(
                &toml,
                format!(
                    "unit `{}` of camera `{camera}` is not in the session; pass --calibration",
                    meta.unit_id
                ),
            )
        })
}

impl LensStream {
    /// Open `<episode>/<camera>/<lens>`; `calibration` is a unit `calibration.json` (default:
    /// found through the session), `static_mask` an optional image (non-zero = usable).
    pub fn open(
        episode: &Path,
        camera_name: &str,
        lens: &str,
        calibration: Option<&Path>,
        static_mask: Option<&Path>,
    ) -> Result<Self> {
        let layout = EpisodeLayout::new(episode);
        let frames_csv = layout.frames_csv(camera_name, lens);
        if !frames_csv.is_file() {
            return Err(input_err(
                &frames_csv,
                format!(
                    "missing: expected lens `{lens}` of camera `{camera_name}` in the episode \
                     (check --camera and --lens)"
                ),
            ));
        }
        let source = FrameSource::open(&layout.lens_dir(camera_name, lens))?;
        let frames = source.frames().to_vec();
        let cal_path = match calibration {
            Some(p) => p.to_path_buf(),
            None => session_calibration(&layout, camera_name)?,
        };
        let cal = UnitCalibration::load(&cal_path)?;
        let lens_cal = cal.lens(lens).ok_or_else(|| {
            input_err(
                &cal_path,
                format!("field `lenses`: no lens named `{lens}`; check --lens"),
            )
        })?;
        let camera = lens_cal.camera()?;
        let meta = layout.read_meta(camera_name).ok();
        source.check_calibration_size(&camera, &cal_path, meta.as_ref())?;
        let mut mask = fov_mask(&camera, FOV_MASK_MARGIN_RAD);
        if let Some(m) = static_mask {
            let image = GrayImage::load(m)?;
            mask = intersect_masks(&mask, &image).map_err(|e| input_err(m, e.to_string()))?;
        }
        Ok(Self {
            episode: episode.to_path_buf(),
            camera_name: camera_name.into(),
            lens: lens.into(),
            camera,
            source_index: (0..frames.len()).collect(),
            frames,
            source,
            mask,
        })
    }

    /// Keep only the frames `keep` (positions in the current [`LensStream::frames`], strictly
    /// increasing): a window or a subsampling of the stream.
    pub fn select(&mut self, keep: &[usize]) -> Result<()> {
        crate::frames::check_increasing_below(self.source.lens_dir(), keep, self.frames.len())?;
        self.frames = keep.iter().map(|&k| self.frames[k].clone()).collect();
        self.source_index = keep.iter().map(|&k| self.source_index[k]).collect();
        Ok(())
    }

    /// The episode's folder name.
    pub fn episode_name(&self) -> String {
        self.episode
            .file_name()
            .map_or_else(String::new, |n| n.to_string_lossy().into_owned())
    }

    /// Check that frame `i` has the calibrated lens's size.
    fn check_size(&self, i: usize, image: &GrayImage) -> Result<()> {
        let (w, h) = self.camera.resolution();
        if (image.width, image.height) == (w, h) {
            return Ok(());
        }
        let file = self
            .frames
            .get(i)
            .map_or_else(String::new, |f| f.file.clone());
        Err(input_err(
            &self.source.lens_dir().join(file),
            format!(
                "frame {i} (t = {} s) is {}×{}, but the lens is calibrated at {w}×{h}; was \
                 the frame resized, or is the calibration for another recording mode?",
                self.frames.get(i).map_or(f64::NAN, |f| f.t),
                image.width,
                image.height
            ),
        ))
    }

    /// Decode frame `i`, checking it has the calibrated lens's size.
    pub fn load(&self, i: usize) -> Result<GrayImage> {
        let Some(&j) = self.source_index.get(i) else {
            return Err(input_err(
                self.source.lens_dir(),
                format!("frame {i} asked for, the stream has {}", self.frames.len()),
            ));
        };
        let image = self.source.load_gray(j)?;
        self.check_size(i, &image)?;
        Ok(image)
    }

    /// Call `f(index, image)` for every frame in order. Images are decoded ahead on another
    /// thread while `f` runs ([`FrameSource::for_each_gray`]), so decoding overlaps the vision;
    /// `f` still sees every frame in order, so results do not depend on the thread count. Stops
    /// at the first error (decoding or `f`).
    pub fn for_each_frame(&self, mut f: impl FnMut(usize, GrayImage) -> Result<()>) -> Result<()> {
        self.source
            .for_each_gray_at(&self.source_index, |i, image| {
                self.check_size(i, &image)?;
                f(i, image)
            })
    }
}

/// Mapper thresholds scaled from the 960 px defaults to this lens's pixel size.
pub fn mapper_options_for(camera: &dyn CameraModel) -> MapperOptions {
    let s = (pixel_angle(camera) / REFERENCE_PIXEL_ANGLE_RAD).max(1.0);
    let mut o = MapperOptions::default();
    o.ransac.threshold_rad *= s;
    o.triangulation.max_error_rad *= s;
    o.ba.huber_rad *= s;
    o.max_error_rad *= s;
    o
}

/// What `kiwi map` did.
#[derive(Debug, Clone, Serialize)]
pub struct MapSummary {
    /// Frames in the stream.
    pub frames: usize,
    /// Frames whose pose the mapper estimated.
    pub frames_tracked: usize,
    /// First frame the mapper could not track (mapping stopped there), if any.
    pub lost_at: Option<u32>,
    /// Keyframes in the map.
    pub keyframes: usize,
    /// Described landmarks in the map.
    pub landmarks: usize,
    /// Words in the place-recognition vocabulary.
    pub vocabulary_words: usize,
    /// Loop-closure places verified geometrically.
    pub loops_verified: usize,
    /// Loops used for the pose-graph correction (verified and mutually consistent).
    pub loops_closed: usize,
    /// Landmarks fused into an older landmark by loop closure.
    pub landmarks_merged: usize,
    /// The mapper's own consistency check (forward against reversed mapping) and verdict: a map
    /// that is not trustworthy serves no poses.
    pub quality: MapQuality,
    /// Wall time (s).
    pub seconds: f64,
}

/// Build a map from a lens stream: KLT/ORB tracks, incremental mapping with local and global
/// bundle adjustment, loop closure, ORB features at the keyframes, the place-recognition
/// vocabulary. `progress(done, total)` is called after each frame is tracked.
pub fn build_map(
    stream: &LensStream,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<(VisualMap, MapSummary)> {
    build_map_with(stream, true, progress)
}

/// [`build_map`], with loop closure (`vision::loop_closure`) before the map is exported only
/// when `loop_closure` is set. On in [`build_map`]: on the 960 px 60 s survey it halves the
/// shared rear map's keyframe ATE (0.069 -> 0.036 %) and the tabletop's rear errors
/// (medians 5.7 -> 2.0 / 3.1 mm) for little extra mapping time (docs/vision.md).
pub fn build_map_with(
    stream: &LensStream,
    loop_closure: bool,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<(VisualMap, MapSummary)> {
    build_map_with_orb(stream, loop_closure, &OrbOptions::default(), progress)
}

/// [`build_map_with`] with the ORB settings of the front end and the keyframes (e.g. raw-image
/// descriptors, `OrbOptions::rectified` off, to compare with the default; a map's query must
/// use the same setting).
pub fn build_map_with_orb(
    stream: &LensStream,
    loop_closure: bool,
    orb_options: &OrbOptions,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<(VisualMap, MapSummary)> {
    let start = Instant::now();
    let tracker_options = TrackerOptions {
        orb: *orb_options,
        ..TrackerOptions::default()
    };
    let mut tracker = FrameTracker::new(tracker_options, stream.mask.clone())?;
    let n = stream.frames.len();
    let mut frames = Vec::with_capacity(n);
    stream.for_each_frame(|i, img| {
        frames.push(tracker.process(i as u32, stream.frames[i].t, img, &stream.camera)?);
        progress(i + 1, n);
        Ok(())
    })?;
    let mapper_options = mapper_options_for(&stream.camera);
    let mut recon = reconstruct(&frames, &mapper_options)?;
    let mut orb = OrbExtractor::new(orb_options)?;
    let mut features = Vec::with_capacity(recon.keyframes.len());
    for kf in &recon.keyframes {
        let img = stream.load(kf.frame as usize)?;
        features.push(orb.extract(&img, Some(&stream.mask), &stream.camera)?);
    }
    let loops = if !loop_closure {
        LoopReport::default()
    } else {
        close_loops(
            &mut recon,
            &features,
            tracker.track_descriptors(),
            &mapper_options.ransac,
            &LoopOptions::default(),
        )
    };
    if !loops.closed.is_empty() {
        global_adjustment(&mut recon, &mapper_options)?;
    }
    tracing::info!(
        verified = loops.verified,
        closed = loops.closed.len(),
        merged = loops.merged_landmarks,
        added = loops.added_observations,
        "loop closure"
    );
    let quality = assess(&frames, &recon, &mapper_options);
    if !quality.trustworthy {
        tracing::warn!(reason = %quality.reason, "the map is not trustworthy");
    }
    let mut map = VisualMap::from_reconstruction_described(
        &recon,
        &features,
        tracker.track_descriptors(),
        &stream.camera_name,
        &stream.lens,
        &stream.episode_name(),
        &stream.camera,
    )?;
    // Each keyframe's image around its landmarks, for tracking to find them again by
    // correlation where descriptors do not survive a change of view.
    let keyframe_frames: Vec<u32> = map.keyframes.iter().map(|k| k.frame).collect();
    map.sample_patches(&stream.camera, f64::from(orb_options.scale_factor), |k| {
        match keyframe_frames.get(k) {
            Some(&frame) => stream.load(frame as usize),
            None => Err(BackendError::Vision {
                context: "map patches".into(),
                message: format!("keyframe {k} is not in the map"),
            }),
        }
    })?;
    let summary = MapSummary {
        frames: n,
        frames_tracked: recon.frame_poses.len(),
        lost_at: recon.lost_at,
        keyframes: map.keyframes.len(),
        landmarks: map.landmarks.len(),
        vocabulary_words: map
            .vocabulary
            .as_ref()
            .map_or(0, crate::vision::place::Vocabulary::num_words),
        loops_verified: loops.verified,
        loops_closed: loops.closed.len(),
        landmarks_merged: loops.merged_landmarks,
        quality: quality.clone(),
        seconds: start.elapsed().as_secs_f64(),
    };
    map.quality = Some(quality);
    Ok((map, summary))
}

/// What `kiwi localize` did.
#[derive(Debug, Clone, Serialize)]
pub struct LocalizeSummary {
    /// Frames in the stream.
    pub frames: usize,
    /// Frames with an accepted pose.
    pub localized: usize,
    /// `localized / frames`.
    pub localized_fraction: f64,
    /// Frames localized by tracking.
    pub tracked: usize,
    /// Frames localized by relocalization.
    pub relocalized: usize,
    /// Frames lost.
    pub lost: usize,
    /// Median inlier count of the localized frames.
    pub median_inliers: usize,
    /// Wall time (s), image decoding included.
    pub seconds: f64,
    /// Frames per second of wall time.
    pub frames_per_second: f64,
    /// Relocalization attempts (forward and backward passes).
    pub relocalization_attempts: usize,
    /// Mean wall time of one relocalization attempt (ms; ORB included).
    pub relocalization_ms_per_attempt: f64,
    /// Relocalization attempts per second of stream time lost (0 without lost frames).
    pub relocalization_attempts_per_lost_second: f64,
    /// Time from the stream's first frame to the first frame localized in the forward pass
    /// (s; `None` if none was): how long a stream that starts lost takes to find the map.
    pub first_pose_after_s: Option<f64>,
    /// Frames localized only once the pose of the wrist's other lens was given (runs begun by
    /// guided matching around it, and what tracking carried from there); 0 without that pose.
    #[serde(default)]
    pub from_other_lens: usize,
    /// Frames kept in runs that met a run they do not join because an independent witness
    /// (the other wrist's front map) placed them where they stand; 0 without a witness.
    #[serde(default)]
    pub kept_by_witness: usize,
    /// Frames localized, after the runs check, around where that witness places the lens
    /// (runs begun by guided matching there, and what tracking carried from there).
    #[serde(default)]
    pub found_around_witness: usize,
    /// Why the witness, asked, could not be computed (the runs were judged without it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub witness_unavailable: Option<String>,
}

/// Summarize per-frame results.
pub fn summarize(results: &[FrameLocalization], seconds: f64) -> LocalizeSummary {
    let count = |s: LocalizationStatus| results.iter().filter(|r| r.status == s).count();
    let (tracked, relocalized, lost) = (
        count(LocalizationStatus::Tracked),
        count(LocalizationStatus::Relocalized),
        count(LocalizationStatus::Lost),
    );
    let mut inliers: Vec<usize> = results
        .iter()
        .filter(|r| r.status != LocalizationStatus::Lost)
        .map(|r| r.inliers)
        .collect();
    inliers.sort_unstable();
    let localized = tracked + relocalized;
    LocalizeSummary {
        frames: results.len(),
        localized,
        localized_fraction: localized as f64 / results.len().max(1) as f64,
        tracked,
        relocalized,
        lost,
        median_inliers: inliers.get(inliers.len() / 2).copied().unwrap_or(0),
        seconds,
        frames_per_second: results.len() as f64 / seconds.max(1e-9),
        relocalization_attempts: 0,
        relocalization_ms_per_attempt: 0.0,
        relocalization_attempts_per_lost_second: 0.0,
        first_pose_after_s: None,
        from_other_lens: 0,
        kept_by_witness: 0,
        found_around_witness: 0,
        witness_unavailable: None,
    }
}

/// Seconds of stream time the lost frames of `results` stand for (each frame counts one mean
/// frame interval).
fn lost_seconds(results: &[FrameLocalization]) -> f64 {
    let (Some(first), Some(last)) = (results.first(), results.last()) else {
        return 0.0;
    };
    let n = results.len();
    if n < 2 || last.t <= first.t {
        return 0.0;
    }
    let interval = (last.t - first.t) / (n - 1) as f64;
    interval
        * results
            .iter()
            .filter(|r| r.status == LocalizationStatus::Lost)
            .count() as f64
}

/// Localize every frame of a stream against a frozen map (which must match the lens), then
/// retry lost runs backwards from the frame after them ([`backfill`]).
pub fn localize_stream(
    map: &VisualMap,
    stream: &LensStream,
    options: &LocalizerOptions,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<(Vec<FrameLocalization>, LocalizeSummary)> {
    localize_stream_with_other_lens(map, stream, options, &[], progress)
}

/// [`localize_stream`], with the pose the wrist's other lens gives at each frame
/// (`other_lens[i]`: this lens's `map_from_cam` at frame `i` predicted from the other lens's
/// localization, `None` where it has none; an empty slice for none at all). Frames still lost
/// after the stream's own passes are tried from that pose ([`from_other_lens`]) before runs
/// that do not join are withdrawn.
pub fn localize_stream_with_other_lens(
    map: &VisualMap,
    stream: &LensStream,
    options: &LocalizerOptions,
    other_lens: &[Option<Pose>],
    progress: &mut dyn FnMut(usize, usize),
) -> Result<(Vec<FrameLocalization>, LocalizeSummary)> {
    localize_stream_with_witness(map, stream, options, other_lens, None, progress)
}

/// Where a witness independent of the stream's map places the lens: per frame `map_from_cam`
/// (`None` where it has none), computed only when asked — when two of the stream's runs cannot
/// both be right ([`crate::vision::runs`]). The pipeline's witness for the other wrist's rear
/// lens in the mapping episode is that wrist's front lens localized in the map wrist's front
/// map, carried into the rear map through that map's metric recovery and placement.
pub type Witness<'a> = &'a mut dyn FnMut() -> Result<Vec<Option<Pose>>>;

/// [`localize_stream_with_other_lens`], with a [`Witness`] that decides between runs that do
/// not join: of two such runs, one the witness places where it stands is kept and the other
/// withdrawn ([`runs_to_withdraw`]).
pub fn localize_stream_with_witness(
    map: &VisualMap,
    stream: &LensStream,
    options: &LocalizerOptions,
    other_lens: &[Option<Pose>],
    witness: Option<Witness<'_>>,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<(Vec<FrameLocalization>, LocalizeSummary)> {
    let start = Instant::now();
    let mut localizer = stream_localizer(map, stream, options)?;
    let n = stream.frames.len();
    if let Some(why) = localizer.refusal() {
        // A refused map serves no pose: the frames need not be decoded.
        let results: Vec<FrameLocalization> = (stream.frames.iter().enumerate())
            .map(|(i, f)| FrameLocalization::lost(i as u32, f.t, 0, why.to_string()))
            .collect();
        progress(n, n);
        let summary = summarize(&results, start.elapsed().as_secs_f64());
        return Ok((results, summary));
    }
    let mut results = Vec::with_capacity(n);
    let mut book = RunBook::new(n);
    let mut run = None;
    stream.for_each_frame(|i, img| {
        let r = localizer.process(i as u32, stream.frames[i].t, &img)?;
        run = book.follow(i, &r, localizer.relocalization_source(), run);
        if r.map_from_cam.is_some() {
            book.frame_run[i] = run;
        }
        results.push(r);
        progress(i + 1, n);
        Ok(())
    })?;
    let lost_forward = lost_seconds(&results);
    let first_pose_after_s = results
        .iter()
        .find(|r| r.status != LocalizationStatus::Lost)
        .zip(results.first())
        .map(|(r, f)| r.t - f.t);
    let (mut attempts, mut attempt_s) = localizer.relocalization_cost();
    let (back_attempts, back_s) =
        backfill(map, stream, options, &mut results, &mut book, |_| true)?;
    attempts += back_attempts;
    attempt_s += back_s;
    let lost_before: Vec<bool> = results
        .iter()
        .map(|r| r.status == LocalizationStatus::Lost)
        .collect();
    let (other_attempts, other_s) =
        from_other_lens(map, stream, options, other_lens, &mut results, &mut book)?;
    attempts += other_attempts;
    attempt_s += other_s;
    let found_by_other: Vec<bool> = (results.iter().zip(&lost_before))
        .map(|(r, &lost)| lost && r.status != LocalizationStatus::Lost)
        .collect();
    let depth = localizer.map_depth();
    let look = withdraw_look_alikes(
        map,
        stream,
        options,
        depth,
        witness,
        &mut results,
        &mut book,
    )?;
    attempts += look.attempts;
    attempt_s += look.seconds;
    let mut found_around_witness = 0;
    if let Some(witnessed) = &look.witnessed {
        let (a, s, found) = around_witness(
            map,
            stream,
            options,
            depth,
            witnessed,
            &mut results,
            &mut book,
        )?;
        attempts += a;
        attempt_s += s;
        found_around_witness = found;
    }
    let mut summary = summarize(&results, start.elapsed().as_secs_f64());
    summary.relocalization_attempts = attempts;
    summary.first_pose_after_s = first_pose_after_s;
    // Counted after the runs check: a frame it withdrew again is not among them.
    summary.from_other_lens = (results.iter().zip(&found_by_other))
        .filter(|(r, found)| **found && r.status != LocalizationStatus::Lost)
        .count();
    summary.kept_by_witness = look.kept_by_witness;
    summary.found_around_witness = found_around_witness;
    summary.witness_unavailable = look.witness_unavailable;
    summary.relocalization_ms_per_attempt = 1e3 * attempt_s / attempts.max(1) as f64;
    summary.relocalization_attempts_per_lost_second = if lost_forward > 0.0 {
        attempts as f64 / lost_forward
    } else {
        0.0
    };
    Ok((results, summary))
}

/// Frames skipped after a lost frame that did not localize around the other lens's pose before
/// the next is tried: a view that fails there usually fails a frame later too (≈ 0.1 s at
/// 30 Hz), and each try costs a guided match over the whole frame.
const OTHER_LENS_RETRY_FRAMES: usize = 3;

/// How far (rad, in the direction a landmark is seen) the other lens's prediction of this lens's
/// pose may be off: over simulated 8 s walks the prediction lay 8-36 mm (median; 95th
/// percentile up to 56 mm) and 0.1-0.6° from the front's own poses (the two maps' metric
/// recovery and the placement over several metres), which at the front lens's 0.4-1 m is 2-6°.
pub const OTHER_LENS_RADIUS_RAD: f64 = 0.1;

/// Why a frame of [`localize_around`] has no pose to search around.
const NOTHING_TO_SEARCH_AROUND: &str = "not tried: no pose to search around";

/// Localize the frames of `stream` only around the poses `around` gives (per frame
/// `map_from_cam`; `None` leaves the frame lost), as around the other lens's pose
/// ([`from_other_lens`]: guided matching, then tracking), without place recognition of its own:
/// whether the lens's view fits the place another source puts it. Frames are tried in order;
/// the result is deterministic.
pub fn localize_around(
    map: &VisualMap,
    stream: &LensStream,
    options: &LocalizerOptions,
    around: &[Option<Pose>],
) -> Result<Vec<FrameLocalization>> {
    let localizer = stream_localizer(map, stream, options)?;
    let why = localizer
        .refusal()
        .unwrap_or(NOTHING_TO_SEARCH_AROUND)
        .to_string();
    let mut results: Vec<FrameLocalization> = (stream.frames.iter().enumerate())
        .map(|(i, f)| FrameLocalization::lost(i as u32, f.t, 0, why.clone()))
        .collect();
    if localizer.refusal().is_some() {
        return Ok(results);
    }
    let mut book = RunBook::new(results.len());
    from_other_lens(map, stream, options, around, &mut results, &mut book)?;
    Ok(results)
}

/// Added to the reason of a lost frame that was tried around the other lens's pose in vain.
const OTHER_LENS_NOT_FOUND: &str = "; around the other lens's pose: not found either";

/// Localize lost frames around the pose the wrist's other lens gives (`other_lens`, per frame
/// `map_from_cam`): a fresh localizer matches the frame around that pose
/// ([`Localizer::process_around`] within [`OTHER_LENS_RADIUS_RAD`], judged by the tracking
/// rules); an accepted pose opens a run
/// ([`RelocalizationSource::OtherLens`]) that tracking carries forward while the frames are
/// lost, and the frames before it in its lost stretch are filled backwards ([`backfill`]).
/// The other lens is localized in another map on other walls, so a view that place
/// recognition cannot find, or finds at a look-alike place, is found where the wrist truly
/// is. Returns the attempts and their wall time (s).
fn from_other_lens(
    map: &VisualMap,
    stream: &LensStream,
    options: &LocalizerOptions,
    other_lens: &[Option<Pose>],
    results: &mut [FrameLocalization],
    book: &mut RunBook,
) -> Result<(usize, f64)> {
    let n = results.len();
    let (mut attempts, mut seconds) = (0, 0.0);
    let mut seeded = vec![false; n];
    let mut i = 0;
    while i < n {
        let prior = other_lens.get(i).copied().flatten();
        let Some(map_from_cam) = prior.filter(|_| results[i].status == LocalizationStatus::Lost)
        else {
            i += 1;
            continue;
        };
        let mut localizer = stream_localizer(map, stream, options)?;
        let started = Instant::now();
        let seed = localizer.process_around(
            i as u32,
            stream.frames[i].t,
            &stream.load(i)?,
            &map_from_cam.inverse(),
            OTHER_LENS_RADIUS_RAD,
        )?;
        attempts += 1;
        seconds += started.elapsed().as_secs_f64();
        let Some(mut first) = seed else {
            results[i].reason.push_str(OTHER_LENS_NOT_FOUND);
            i += OTHER_LENS_RETRY_FRAMES;
            continue;
        };
        first.status = LocalizationStatus::Relocalized;
        let run = book.open(i, RelocalizationSource::OtherLens);
        results[i] = first;
        book.frame_run[i] = Some(run);
        let mut k = i;
        while k > 0 && results[k - 1].status == LocalizationStatus::Lost {
            k -= 1;
            seeded[k] = true;
        }
        // Carried forward by tracking alone: a relocalization here would rest on place
        // recognition again, which already failed on these frames.
        i += 1;
        while i < n && results[i].status == LocalizationStatus::Lost {
            let r = localizer.process(i as u32, stream.frames[i].t, &stream.load(i)?)?;
            if r.status != LocalizationStatus::Tracked {
                break;
            }
            results[i] = r;
            book.frame_run[i] = Some(run);
            i += 1;
        }
    }
    let (a, s) = backfill(map, stream, options, results, book, |k| seeded[k])?;
    Ok((attempts + a, seconds + s))
}

/// Withdraw the runs that no hand-held motion joins ([`crate::vision::runs`]): the one whose
/// start rests on less, then fill the withdrawn frames again backwards from the runs that stay
/// (without whole-map matches once one has fooled the stream), withdraw refilled runs that join
/// a withdrawn pose (the same look-alike), and whatever still does not join. `depth` is the
/// map's median keyframe-to-landmark depth. With a `witness`, asked once the stream holds runs
/// that do not join, a run the witness places where it stands is kept against one it does not
/// ([`runs_to_withdraw`]) and is not withdrawn for joining a withdrawn pose.
fn withdraw_look_alikes(
    map: &VisualMap,
    stream: &LensStream,
    options: &LocalizerOptions,
    depth: f64,
    witness: Option<Witness<'_>>,
    results: &mut [FrameLocalization],
    book: &mut RunBook,
) -> Result<LookAlikes> {
    let found = conflicts(results, book, depth);
    if found.is_empty() {
        return Ok(LookAlikes::default());
    }
    // A witness that cannot be computed leaves the runs to be judged as without one: it is
    // evidence the stream can do without, not an input it needs.
    let mut unavailable = None;
    let witnessed = match witness.map(|ask| ask()) {
        Some(Ok(poses)) => Some(poses),
        Some(Err(e)) => {
            tracing::warn!(
                "{}/{}: the other wrist's witness could not be computed ({e}); runs that do \
                 not join are judged without it",
                stream.camera_name,
                stream.lens
            );
            unavailable = Some(e.to_string());
            None
        }
        None => None,
    };
    let witness_poses = witnessed.as_deref().unwrap_or_default();
    let judge = |r: &[FrameLocalization], b: &RunBook| judge_runs(r, b, witness_poses, depth);
    let judged = judge(results, book);
    // The runs that meet a run they do not join and agree with the witness.
    let placed = |conflicts: &[Conflict], b: &RunBook, judged: &[Option<WitnessJudgement>]| {
        (conflicts.iter())
            .flat_map(|c| [b.frame_run[c.before], b.frame_run[c.after]])
            .flatten()
            .filter(|&run| witness_agrees(judged, run) == Some(true))
            .collect::<BTreeSet<usize>>()
    };
    let mut met = placed(&found, book, &judged);
    let mut gone = vec![None; results.len()];
    let runs = runs_to_withdraw(&found, book, &judged);
    let why = |r: &[FrameLocalization], b: &RunBook, run| {
        witness_reason(b, &judged, run).unwrap_or_else(|| conflict_reason(r, b, &found, run))
    };
    let mut withdrawn = withdraw(results, book, &runs, why, &mut gone);
    let fooled_whole_map = runs
        .iter()
        .any(|&r| book.runs[r].source == RelocalizationSource::WholeMap);
    let refill = LocalizerOptions {
        relocalization_map_candidates: if fooled_whole_map {
            0
        } else {
            options.relocalization_map_candidates
        },
        ..*options
    };
    // Only the stretches that hold withdrawn frames: the others were tried already.
    let cost = backfill(map, stream, &refill, results, book, |i| gone[i].is_some())?;
    // Withdrawing a run can show the next one that joins it; each round withdraws at least one
    // run, so this ends.
    loop {
        let judged = judge(results, book);
        let again = runs_joining_withdrawn(results, book, &gone, depth, &judged);
        if again.is_empty() {
            break;
        }
        let why_again = |_: &[FrameLocalization], b: &RunBook, run: usize| {
            format!(
                "withdrawn: the run that began at frame {} ({}) joins poses withdrawn as a \
                 look-alike place",
                b.runs[run].start,
                b.runs[run].source.describe()
            )
        };
        withdrawn += withdraw(results, book, &again, why_again, &mut gone);
    }
    let left = conflicts(results, book, depth);
    let judged = judge(results, book);
    let runs = runs_to_withdraw(&left, book, &judged);
    let why = |r: &[FrameLocalization], b: &RunBook, run| {
        witness_reason(b, &judged, run).unwrap_or_else(|| conflict_reason(r, b, &left, run))
    };
    met.extend(placed(&left, book, &judged));
    withdrawn += withdraw(results, book, &runs, why, &mut gone);
    let kept = (book.frame_run.iter().flatten())
        .filter(|run| met.contains(run))
        .count();
    tracing::info!(
        "{}/{}: {withdrawn} frames withdrawn from runs that do not join the stream; {kept} \
         kept in runs the other wrist's witness placed",
        stream.camera_name,
        stream.lens
    );
    Ok(LookAlikes {
        attempts: cost.0,
        seconds: cost.1,
        kept_by_witness: kept,
        witnessed,
        witness_unavailable: unavailable,
    })
}

/// What [`withdraw_look_alikes`] did.
#[derive(Default)]
struct LookAlikes {
    /// The refill's relocalization attempts.
    attempts: usize,
    /// Their wall time (s).
    seconds: f64,
    /// Frames kept in runs that met a conflict because the witness placed them.
    kept_by_witness: usize,
    /// The witness's poses, when it was asked.
    witnessed: Option<Vec<Option<Pose>>>,
    /// Why the witness, asked, could not be computed.
    witness_unavailable: Option<String>,
}

/// Localize the frames still lost around where the witness places the lens (as
/// [`from_other_lens`] does around the other lens's pose), then withdraw the runs begun there
/// that the witness does not place where they end up, and any run that does not join another
/// which the witness does place ([`runs_to_withdraw`]). Returns the relocalization attempts,
/// their wall time (s), and the frames found this way that stay.
fn around_witness(
    map: &VisualMap,
    stream: &LensStream,
    options: &LocalizerOptions,
    depth: f64,
    witnessed: &[Option<Pose>],
    results: &mut [FrameLocalization],
    book: &mut RunBook,
) -> Result<(usize, f64, usize)> {
    let lost_before: Vec<bool> = results
        .iter()
        .map(|r| r.status == LocalizationStatus::Lost)
        .collect();
    let runs_before = book.runs.len();
    let (attempts, seconds) = from_other_lens(map, stream, options, witnessed, results, book)?;
    let judged = judge_runs(results, book, witnessed, depth);
    let left = conflicts(results, book, depth);
    let mut runs = runs_to_withdraw(&left, book, &judged);
    runs.extend(
        (runs_before..book.runs.len()).filter(|&r| witness_agrees(&judged, r) == Some(false)),
    );
    let why = |r: &[FrameLocalization], b: &RunBook, run| {
        witness_reason(b, &judged, run).unwrap_or_else(|| conflict_reason(r, b, &left, run))
    };
    let mut gone = vec![None; results.len()];
    withdraw(results, book, &runs, why, &mut gone);
    let found = (results.iter().zip(&lost_before))
        .filter(|(r, lost)| **lost && r.status != LocalizationStatus::Lost)
        .count();
    tracing::info!(
        "{}/{}: {found} frames found around where the other wrist's witness places the lens",
        stream.camera_name,
        stream.lens
    );
    Ok((attempts, seconds, found))
}

/// A fresh localizer for a stream's lens, camera and mask.
fn stream_localizer(
    map: &VisualMap,
    stream: &LensStream,
    options: &LocalizerOptions,
) -> Result<Localizer> {
    Localizer::new(
        map,
        &stream.lens,
        stream.camera.clone(),
        stream.mask.clone(),
        *options,
    )
}

/// Frames after a lost run that the backward pass starts from when the frame after the run
/// cannot be localized from its own pose again: relocalizing a frame or two after the run gives
/// the backward tracking its motion prior.
const BACKFILL_LEAD: usize = 2;

/// Retry lost frames backwards from the localized frame that follows them: a fresh localizer
/// starts from that frame's pose ([`Localizer::process_from`]; or relocalizes just after the
/// run when the frame does not localize from it again) and tracks back into the run with the
/// motion prior (a stream that starts, or resumes, where relocalization alone fails is often
/// trackable from the other side). A frame lost again keeps its forward result and the pass
/// goes on (the localizer relocalizes, at its own reduced rate after repeated failures); the
/// same acceptance rules apply, so a filled frame is as trustworthy as any other. Only lost
/// stretches holding a frame `retry` accepts are tried. Sequential and seeded by frame index,
/// so the result stays deterministic. Returns its relocalization attempts and their wall time
/// (s).
fn backfill(
    map: &VisualMap,
    stream: &LensStream,
    options: &LocalizerOptions,
    results: &mut [FrameLocalization],
    book: &mut RunBook,
    retry: impl Fn(usize) -> bool,
) -> Result<(usize, f64)> {
    let n = results.len();
    let (mut attempts, mut seconds) = (0, 0.0);
    for b in 0..n {
        if results[b].status == LocalizationStatus::Lost {
            continue;
        }
        let mut a = b;
        while a > 0 && results[a - 1].status == LocalizationStatus::Lost {
            a -= 1;
        }
        if a == b || !(a..b).any(&retry) {
            continue;
        }
        let mut localizer = stream_localizer(map, stream, options)?;
        // From frame b's own pose when the frame localizes from it again; else relocalize a
        // little after it.
        let seeded = match results[b].map_from_cam {
            Some(p) => localizer
                .process_from(b as u32, results[b].t, &stream.load(b)?, &p.inverse())?
                .is_some(),
            None => false,
        };
        let top = if seeded {
            b - 1
        } else {
            (b + BACKFILL_LEAD).min(n - 1)
        };
        // Filled frames join the run they were tracked from: frame b's when seeded from it.
        let mut run = if seeded { book.frame_run[b] } else { None };
        for j in (a..=top).rev() {
            let image = stream.load(j)?;
            let r = localizer.process(j as u32, stream.frames[j].t, &image)?;
            run = book.follow(j, &r, localizer.relocalization_source(), run);
            if j < b && r.status != LocalizationStatus::Lost {
                results[j] = r;
                book.frame_run[j] = run;
            }
        }
        let (a, s) = localizer.relocalization_cost();
        attempts += a;
        seconds += s;
    }
    Ok((attempts, seconds))
}

/// Header of `poses.csv`.
pub const POSES_CSV_HEADER: &str = "t,status,px,py,pz,qx,qy,qz,qw,inliers,reason";

/// Write `poses.csv` atomically: one row per frame, `map_from_cam` of localized frames, empty
/// pose fields for lost frames (with the reason).
pub fn write_poses_csv(path: &Path, results: &[FrameLocalization]) -> Result<()> {
    use std::fmt::Write as _;
    let mut text = String::with_capacity(96 * (results.len() + 1));
    text.push_str(POSES_CSV_HEADER);
    text.push('\n');
    for r in results {
        let _ = write!(text, "{},{},", r.t, r.status.name());
        match &r.map_from_cam {
            Some(p) => {
                let (t, q) = (p.translation.vector, p.rotation);
                let _ = write!(
                    text,
                    "{},{},{},{},{},{},{}",
                    t.x, t.y, t.z, q.i, q.j, q.k, q.w
                );
            }
            None => text.push_str(",,,,,,"),
        }
        // Reasons never contain quotes; commas are replaced so the row stays 11 fields.
        let _ = writeln!(text, ",{},{}", r.inliers, r.reason.replace(',', ";"));
    }
    kiwi_core::io::write_atomic(path, text.as_bytes())?;
    Ok(())
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic)]

    use super::*;
    use crate::frames::DECODE_BATCH;
    use std::sync::mpsc;
    use std::time::Duration;

    /// A stream that hangs fails the test after this long instead of blocking the test run.
    const HANG_TIMEOUT: Duration = Duration::from_secs(30);

    /// A lens stream of `n` 32×32 frames on disk; frame `bad` (if any) has the wrong size.
    fn stream(dir: &Path, n: usize, bad: Option<usize>) -> LensStream {
        let lens_dir = dir.join("left").join("front");
        std::fs::create_dir_all(lens_dir.join("frames")).unwrap();
        let mut frames = Vec::new();
        for i in 0..n {
            let file = EpisodeLayout::frame_file_name(i);
            let size = if Some(i) == bad { 48 } else { 32 };
            image::GrayImage::from_pixel(size, size, image::Luma([i as u8]))
                .save(lens_dir.join(&file))
                .unwrap();
            frames.push(FrameRecord {
                t: i as f64 * 0.01,
                file,
            });
        }
        let camera = Camera::Kb4(
            kiwi_core::camera::Kb4::new(32, 32, [10.0, 10.0, 15.5, 15.5, 0.0, 0.0, 0.0, 0.0])
                .unwrap(),
        );
        kiwi_core::layout::write_frames_csv(&lens_dir.join("frames.csv"), &frames).unwrap();
        let source = FrameSource::open(&lens_dir).unwrap();
        let mask = fov_mask(&camera, FOV_MASK_MARGIN_RAD);
        LensStream {
            episode: dir.to_path_buf(),
            camera_name: "left".into(),
            lens: "front".into(),
            camera,
            source_index: (0..frames.len()).collect(),
            frames,
            source,
            mask,
        }
    }

    fn frame_path(s: &LensStream, i: usize) -> PathBuf {
        s.source.lens_dir().join(&s.frames[i].file)
    }

    /// Run `f` on another thread; fail if it does not return within [`HANG_TIMEOUT`].
    fn within_timeout<T: Send + 'static>(f: impl FnOnce() -> T + Send + 'static) -> T {
        let (tx, rx) = mpsc::channel();
        std::thread::spawn(move || {
            let _ = tx.send(f());
        });
        rx.recv_timeout(HANG_TIMEOUT)
            .expect("the frame stream hung: a thread waits on one that failed")
    }

    #[test]
    fn consumer_failing_mid_stream_stops_the_decoder() {
        // Many more frames than the channel holds, so the decoder is blocked on a full channel
        // when the consumer fails.
        let dir = tempfile::tempdir().unwrap();
        let s = stream(dir.path(), 6 * DECODE_BATCH, None);
        let (seen, result) = within_timeout(move || {
            let mut seen = 0;
            let r = s.for_each_frame(|i, _| {
                seen += 1;
                if i == 3 {
                    Err(BackendError::Vision {
                        context: "test".into(),
                        message: "consumer failed".into(),
                    })
                } else {
                    Ok(())
                }
            });
            (seen, r)
        });
        assert_eq!(seen, 4);
        assert!(result.unwrap_err().to_string().contains("consumer failed"));
    }

    #[test]
    fn producer_failing_mid_stream_reports_the_frame() {
        let dir = tempfile::tempdir().unwrap();
        let bad = 2 * DECODE_BATCH + 3;
        let s = stream(dir.path(), 6 * DECODE_BATCH, Some(bad));
        let (seen, result) = within_timeout(move || {
            let mut seen = 0;
            let r = s.for_each_frame(|_, _| {
                seen += 1;
                Ok(())
            });
            (seen, r)
        });
        assert_eq!(
            seen, bad,
            "every frame before the bad one reaches the consumer"
        );
        let e = result.unwrap_err().to_string();
        assert!(
            e.contains("000035.png") && e.contains("48×48") && e.contains("32×32"),
            "{e}"
        );
    }

    #[test]
    fn missing_frame_mid_stream_and_slow_consumer_do_not_hang() {
        let dir = tempfile::tempdir().unwrap();
        let s = stream(dir.path(), 4 * DECODE_BATCH, None);
        std::fs::remove_file(frame_path(&s, DECODE_BATCH + 1)).unwrap();
        let result = within_timeout(move || {
            s.for_each_frame(|_, _| {
                std::thread::sleep(Duration::from_millis(1));
                Ok(())
            })
        });
        let e = result.unwrap_err().to_string();
        assert!(e.contains("000017.png"), "{e}");
    }
}
