//! From images to what the batch estimator needs: aprilgrid corners per frame (parallel), each
//! frame's board pose from bearing vectors with a robust pixel refinement, camera angular rates
//! from consecutive poses, the coarse time shift by cross-correlating angular-rate magnitudes
//! with the gyro, and the camera-from-IMU rotation by aligning the angular rates.

use std::path::Path;

use indicatif::{ProgressBar, ProgressStyle};
use nalgebra::{Matrix6, Point2, Vector2, Vector3, Vector6};
use rayon::prelude::*;

use kiwi_core::camera::{Camera, CameraModel};
use kiwi_core::geometry::{Pose, hat, se3_exp, so3_log};
use kiwi_core::imu::ImuSample;
use kiwi_core::layout::FrameRecord;

use crate::detect::Detector;
use crate::error::{CalibError, Result};
use crate::target::AprilGridTarget;

/// Fewest corners for a frame to count: below this a board pose is poorly determined.
pub const MIN_CORNERS_PER_FRAME: usize = 12;
/// Corners farther than this many robust standard deviations from the pose are dropped.
const CORNER_OUTLIER_SIGMAS: f64 = 4.0;
/// Floor (px) of the corner outlier threshold, so a perfect frame does not lose good corners.
const CORNER_OUTLIER_FLOOR_PX: f64 = 1.0;
/// A frame whose RMS reprojection error after refinement exceeds this (px) is rejected
/// (misdetection, heavy blur).
pub const MAX_FRAME_RMS_PX: f64 = 2.5;
/// Gauss–Newton iterations of a frame's pose refinement.
const POSE_ITERATIONS: usize = 8;
/// Two frames further apart than this many frame periods give no angular rate (a gap).
const MAX_RATE_GAP_PERIODS: f64 = 2.5;
/// Step (s) of the coarse time-shift search grid.
const SEARCH_STEP_S: f64 = 0.0005;
/// A time-shift correlation peak below this normalised correlation is not trusted.
pub const MIN_CORRELATION: f64 = 0.7;
/// RMS camera rotation rate (rad/s) below which the rotation is too weak to calibrate.
pub const MIN_ROTATION_RATE: f64 = 0.3;
/// The weakest rotation axis must carry at least this share of the strongest one's energy.
pub const MIN_AXIS_SHARE: f64 = 0.02;

/// One detected corner.
#[derive(Debug, Clone, Copy)]
pub struct CornerObs {
    /// Board point (m, board frame).
    pub board: Vector3<f64>,
    /// Detected pixel.
    pub pixel: Vector2<f64>,
    /// Rolling-shutter delay of its row after the frame stamp (s).
    pub row_delay_s: f64,
}

/// One frame with enough corners.
#[derive(Debug, Clone)]
pub struct FrameObs {
    /// Index in frames.csv.
    pub index: usize,
    /// Frame stamp (s, camera clock).
    pub t: f64,
    /// Mean rolling-shutter delay of its corners (s).
    pub row_delay_s: f64,
    /// Inlier corners.
    pub corners: Vec<CornerObs>,
    /// Corners dropped as outliers.
    pub outliers: usize,
    /// `cam_from_board` from this frame alone.
    pub cam_from_board: Pose,
    /// RMS reprojection error of that pose (px).
    pub rms_px: f64,
}

/// What detection found for one lens.
#[derive(Debug, Clone)]
pub struct LensObservations {
    /// Lens name.
    pub name: String,
    /// Its camera model.
    pub camera: Camera,
    /// Frames in frames.csv.
    pub frames_total: usize,
    /// Frames looked at (after `--frame-step`).
    pub frames_used: usize,
    /// Frames rejected (too few corners or too large an error).
    pub frames_rejected: usize,
    /// Accepted frames, in time order.
    pub frames: Vec<FrameObs>,
}

/// Input of one lens for detection.
pub struct LensInput<'a> {
    /// Lens name.
    pub name: &'a str,
    /// Lens folder (frames.csv's files are relative to it).
    pub dir: &'a Path,
    /// Frames.
    pub frames: &'a [FrameRecord],
    /// Camera model.
    pub camera: &'a Camera,
}

/// Detect the board in every `step`-th frame of each lens (in parallel) and estimate each
/// frame's pose; `readout_s` is the rolling-shutter readout of a full frame.
pub fn observe(
    lenses: &[LensInput<'_>],
    target: &AprilGridTarget,
    step: usize,
    readout_s: f64,
    progress: bool,
) -> Result<Vec<LensObservations>> {
    let detector = Detector::new(*target);
    let jobs: Vec<(usize, usize)> = lenses
        .iter()
        .enumerate()
        .flat_map(|(l, lens)| {
            (0..lens.frames.len())
                .step_by(step.max(1))
                .map(move |k| (l, k))
        })
        .collect();
    let bar = if progress {
        let b = ProgressBar::new(jobs.len() as u64);
        if let Ok(style) =
            ProgressStyle::with_template("detecting {bar:40} {pos}/{len} frames ({eta} left)")
        {
            b.set_style(style);
        }
        b
    } else {
        ProgressBar::hidden()
    };
    let found: Vec<Result<Option<FrameObs>>> = jobs
        .par_iter()
        .map(|&(l, k)| {
            let lens = &lenses[l];
            let record = &lens.frames[k];
            let gray = load_gray(&lens.dir.join(&record.file))?;
            let (_, height) = lens.camera.resolution();
            if (gray.width(), gray.height()) != lens.camera.resolution() {
                return Err(CalibError::Input {
                    path: lens.dir.join(&record.file),
                    message: format!(
                        "image is {}x{} but the {} lens's intrinsics are for {}x{}; pass the \
                         calibration.json of this unit and recording resolution",
                        gray.width(),
                        gray.height(),
                        lens.name,
                        lens.camera.resolution().0,
                        height
                    ),
                });
            }
            let detection = detector.detect(&gray)?;
            bar.inc(1);
            Ok(frame_pose(
                lens.camera,
                k,
                record.t,
                detected_corners(&detection, lens.camera, readout_s),
                None,
            ))
        })
        .collect();
    bar.finish_and_clear();
    let mut out: Vec<LensObservations> = lenses
        .iter()
        .map(|lens| LensObservations {
            name: lens.name.to_owned(),
            camera: lens.camera.clone(),
            frames_total: lens.frames.len(),
            frames_used: 0,
            frames_rejected: 0,
            frames: Vec::new(),
        })
        .collect();
    for (&(l, _), r) in jobs.iter().zip(found) {
        out[l].frames_used += 1;
        match r? {
            Some(f) => out[l].frames.push(f),
            None => out[l].frames_rejected += 1,
        }
    }
    Ok(out)
}

/// A frame's pose from its corners: bearings → planar homography pose → robust pixel
/// refinement with outlier removal. `None` when the frame cannot be trusted.
pub fn frame_pose(
    camera: &Camera,
    index: usize,
    t: f64,
    mut corners: Vec<CornerObs>,
    start: Option<&Pose>,
) -> Option<FrameObs> {
    if corners.len() < MIN_CORNERS_PER_FRAME {
        return None;
    }
    let mut pose = match start {
        Some(p) => *p,
        None => {
            let (bearings, board): (Vec<Vector3<f64>>, Vec<Vector3<f64>>) = corners
                .iter()
                .filter_map(|c| {
                    camera
                        .unproject(&Point2::new(c.pixel.x, c.pixel.y))
                        .map(|b| (b.into_inner(), c.board))
                })
                .unzip();
            crate::intrinsics::init::pose_from_bearings(&bearings, &board)?.0
        }
    };
    let total = corners.len();
    for _ in 0..2 {
        pose = refine_pose(camera, &pose, &corners)?;
        let errors: Vec<f64> = corners
            .iter()
            .map(|c| pixel_error(camera, &pose, c).unwrap_or(f64::INFINITY))
            .collect();
        let mut sorted: Vec<f64> = errors.iter().copied().filter(|e| e.is_finite()).collect();
        if sorted.len() < MIN_CORNERS_PER_FRAME {
            return None;
        }
        sorted.sort_by(f64::total_cmp);
        let sigma = 1.4826 * sorted[sorted.len() / 2];
        let limit = (CORNER_OUTLIER_SIGMAS * sigma).max(CORNER_OUTLIER_FLOOR_PX);
        let kept: Vec<CornerObs> = corners
            .iter()
            .zip(&errors)
            .filter(|(_, e)| **e <= limit)
            .map(|(c, _)| *c)
            .collect();
        if kept.len() == corners.len() {
            break;
        }
        corners = kept;
        if corners.len() < MIN_CORNERS_PER_FRAME {
            return None;
        }
    }
    let sq: f64 = corners
        .iter()
        .map(|c| pixel_error(camera, &pose, c).map_or(f64::INFINITY, |e| e * e))
        .sum();
    let rms_px = (sq / corners.len() as f64).sqrt();
    if rms_px.is_nan() || rms_px > MAX_FRAME_RMS_PX {
        return None;
    }
    let row_delay_s = corners.iter().map(|c| c.row_delay_s).sum::<f64>() / corners.len() as f64;
    Some(FrameObs {
        index,
        t,
        row_delay_s,
        outliers: total - corners.len(),
        corners,
        cam_from_board: pose,
        rms_px,
    })
}

fn pixel_error(camera: &Camera, pose: &Pose, c: &CornerObs) -> Option<f64> {
    let p = camera.project(&(pose * nalgebra::Point3::from(c.board)).coords)?;
    Some((p.coords - c.pixel).norm())
}

/// Gauss–Newton on pixel residuals of one frame's pose (left perturbation).
fn refine_pose(camera: &Camera, pose: &Pose, corners: &[CornerObs]) -> Option<Pose> {
    let mut pose = *pose;
    for _ in 0..POSE_ITERATIONS {
        let mut h = Matrix6::<f64>::zeros();
        let mut g = Vector6::<f64>::zeros();
        for c in corners {
            let pc = (pose * nalgebra::Point3::from(c.board)).coords;
            let Some((px, dp)) = camera.project_with_jacobians(&pc, None) else {
                continue;
            };
            let r = px.coords - c.pixel;
            let mut dxi = nalgebra::Matrix3x6::<f64>::zeros();
            dxi.fixed_view_mut::<3, 3>(0, 0).copy_from(&(-hat(&pc)));
            dxi.fixed_view_mut::<3, 3>(0, 3)
                .copy_from(&nalgebra::Matrix3::identity());
            let a = dp * dxi;
            h += a.transpose() * a;
            g += a.transpose() * r;
        }
        let step = h.cholesky()?.solve(&(-g));
        pose = se3_exp(&step) * pose;
        if step.norm() < 1e-10 {
            break;
        }
    }
    Some(pose)
}

/// A camera angular-rate sample from two consecutive frames.
#[derive(Debug, Clone, Copy)]
pub struct RateSample {
    /// Start of the interval (s, camera clock, rolling-shutter mean row).
    pub t0: f64,
    /// End of the interval.
    pub t1: f64,
    /// Mean body angular rate over the interval (rad/s, camera frame).
    pub omega: Vector3<f64>,
}

/// Camera angular rates between consecutive accepted frames.
pub fn camera_rates(frames: &[FrameObs], fps: f64) -> Vec<RateSample> {
    frames
        .windows(2)
        .filter_map(|w| {
            let (a, b) = (&w[0], &w[1]);
            let t0 = a.t + a.row_delay_s;
            let t1 = b.t + b.row_delay_s;
            let dt = t1 - t0;
            if !(dt > 0.0 && dt <= MAX_RATE_GAP_PERIODS * (b.index - a.index) as f64 / fps) {
                return None;
            }
            // board_from_cam(t1) = board_from_cam(t0) · exp(ω dt), ω in the camera frame.
            let ra = a.cam_from_board.rotation;
            let rb = b.cam_from_board.rotation;
            let omega = so3_log(&(ra * rb.inverse())) / dt;
            Some(RateSample { t0, t1, omega })
        })
        .collect()
}

/// Running integrals of the gyro (vector and magnitude) for interval means at any time.
pub struct GyroIntegral {
    t: Vec<f64>,
    vector: Vec<Vector3<f64>>,
    magnitude: Vec<f64>,
}

impl GyroIntegral {
    /// Trapezoidal integrals over the samples.
    pub fn new(samples: &[ImuSample]) -> Self {
        let mut t = Vec::with_capacity(samples.len());
        let mut vector = Vec::with_capacity(samples.len());
        let mut magnitude = Vec::with_capacity(samples.len());
        let (mut v, mut m) = (Vector3::zeros(), 0.0);
        for (i, s) in samples.iter().enumerate() {
            if i > 0 {
                let p = &samples[i - 1];
                let dt = s.t - p.t;
                v += (s.gyro + p.gyro) * (0.5 * dt);
                m += (s.gyro.norm() + p.gyro.norm()) * 0.5 * dt;
            }
            t.push(s.t);
            vector.push(v);
            magnitude.push(m);
        }
        Self {
            t,
            vector,
            magnitude,
        }
    }

    fn at(&self, time: f64) -> Option<(Vector3<f64>, f64)> {
        let n = self.t.len();
        if n < 2 || time < self.t[0] || time > self.t[n - 1] {
            return None;
        }
        let i = self.t.partition_point(|&x| x <= time).clamp(1, n - 1);
        let (a, b) = (self.t[i - 1], self.t[i]);
        let s = (time - a) / (b - a);
        Some((
            self.vector[i - 1] * (1.0 - s) + self.vector[i] * s,
            self.magnitude[i - 1] * (1.0 - s) + self.magnitude[i] * s,
        ))
    }

    /// Mean gyro vector and mean magnitude over `[t0, t1]` (IMU clock).
    pub fn mean(&self, t0: f64, t1: f64) -> Option<(Vector3<f64>, f64)> {
        let (v0, m0) = self.at(t0)?;
        let (v1, m1) = self.at(t1)?;
        let dt = t1 - t0;
        Some(((v1 - v0) / dt, (m1 - m0) / dt))
    }
}

/// Result of the coarse time-shift search.
#[derive(Debug, Clone, Copy)]
pub struct CoarseShift {
    /// Time shift (s): `t_imu = t_cam + shift`.
    pub shift_s: f64,
    /// Normalised correlation at the peak.
    pub correlation: f64,
}

/// Cross-correlate the camera's angular-rate magnitude with the gyro's over shifts
/// `guess ± window`; the peak, refined by a parabola, is the coarse time shift.
pub fn coarse_time_shift(
    rates: &[RateSample],
    gyro: &GyroIntegral,
    guess: f64,
    window: f64,
) -> Option<CoarseShift> {
    let steps = (window / SEARCH_STEP_S).ceil() as i64;
    let cam: Vec<f64> = rates.iter().map(|r| r.omega.norm()).collect();
    let score = |shift: f64| -> Option<f64> {
        let mut pairs = Vec::with_capacity(rates.len());
        for (r, &c) in rates.iter().zip(&cam) {
            if let Some((_, m)) = gyro.mean(r.t0 + shift, r.t1 + shift) {
                pairs.push((c, m));
            }
        }
        // Demand most of the frames overlap the IMU log, else a shift off the end scores on a
        // handful of pairs.
        if pairs.len() < rates.len() / 2 || pairs.len() < 10 {
            return None;
        }
        let n = pairs.len() as f64;
        let (ma, mb) = pairs
            .iter()
            .fold((0.0, 0.0), |(a, b), (x, y)| (a + x / n, b + y / n));
        let (mut sab, mut saa, mut sbb) = (0.0, 0.0, 0.0);
        for (x, y) in &pairs {
            sab += (x - ma) * (y - mb);
            saa += (x - ma) * (x - ma);
            sbb += (y - mb) * (y - mb);
        }
        let d = (saa * sbb).sqrt();
        (d > 0.0).then(|| sab / d)
    };
    let scores: Vec<(f64, Option<f64>)> = (-steps..=steps)
        .into_par_iter()
        .map(|k| {
            let s = guess + k as f64 * SEARCH_STEP_S;
            (s, score(s))
        })
        .collect();
    let (best, _) = scores
        .iter()
        .enumerate()
        .filter_map(|(i, (_, c))| c.map(|c| (i, c)))
        .max_by(|a, b| a.1.total_cmp(&b.1))?;
    let c = scores[best].1?;
    let mut shift = scores[best].0;
    if best > 0
        && best + 1 < scores.len()
        && let (Some(l), Some(r)) = (scores[best - 1].1, scores[best + 1].1)
    {
        let denom = l - 2.0 * c + r;
        if denom < 0.0 {
            shift += 0.5 * (l - r) / denom * SEARCH_STEP_S;
        }
    }
    Some(CoarseShift {
        shift_s: shift,
        correlation: c,
    })
}

/// Rotation `cam_from_imu` and gyro bias from paired angular rates (`ω_cam = R (ω_imu − b)`),
/// by alternating an SVD alignment and the bias mean.
pub fn align_rates(
    rates: &[RateSample],
    gyro: &GyroIntegral,
    shift: f64,
) -> Option<(nalgebra::UnitQuaternion<f64>, Vector3<f64>)> {
    let pairs: Vec<(Vector3<f64>, Vector3<f64>)> = rates
        .iter()
        .filter_map(|r| {
            gyro.mean(r.t0 + shift, r.t1 + shift)
                .map(|(v, _)| (r.omega, v))
        })
        .collect();
    if pairs.len() < 10 {
        return None;
    }
    let mut bias = Vector3::zeros();
    let mut rot = nalgebra::UnitQuaternion::identity();
    for _ in 0..4 {
        let mut h = nalgebra::Matrix3::<f64>::zeros();
        for (c, i) in &pairs {
            h += (i - bias) * c.transpose();
        }
        let svd = h.svd(true, true);
        let (u, v_t) = (svd.u?, svd.v_t?);
        let mut d = nalgebra::Matrix3::identity();
        if (v_t.transpose() * u.transpose()).determinant() < 0.0 {
            d[(2, 2)] = -1.0;
        }
        let r = v_t.transpose() * d * u.transpose();
        rot = nalgebra::UnitQuaternion::from_matrix(&r);
        bias = pairs
            .iter()
            .fold(Vector3::zeros(), |a, (c, i)| a + (i - rot.inverse() * c))
            / pairs.len() as f64;
    }
    Some((rot, bias))
}

/// RMS camera rotation rate and the weakest axis's share of the rotation energy.
pub fn excitation(rates: &[RateSample]) -> (f64, f64) {
    if rates.is_empty() {
        return (0.0, 0.0);
    }
    let mut m = nalgebra::Matrix3::<f64>::zeros();
    for r in rates {
        m += r.omega * r.omega.transpose();
    }
    m /= rates.len() as f64;
    let rms = m.trace().sqrt();
    let eig = m.symmetric_eigenvalues();
    let (lo, hi) = (eig.min(), eig.max());
    (rms, if hi > 0.0 { lo / hi } else { 0.0 })
}

/// A tracked tag is dropped if refinement moves any of its corners further than this from the
/// prediction (px): the prediction (gyro rotation, constant-velocity translation) is good to a
/// few tenths of a pixel, so a larger move means the refinement locked onto another edge.
const MAX_TRACK_DISPLACEMENT_PX: f64 = 1.5;
/// Predicted corners closer than this to the image edge are not tracked (px).
const TRACK_BORDER_PX: f64 = 6.0;
/// Tags seen more obliquely than this (cosine of the angle between the board normal and the
/// ray) are not tracked: foreshortened tags refine poorly.
const MIN_TRACK_COSINE: f64 = 0.26;

/// Gyro-aided prediction of frames between keyframes: what tracking needs.
pub struct TrackModel<'a> {
    /// Gyro integrals.
    pub gyro: &'a GyroIntegral,
    /// `cam_from_imu` rotation of the lens.
    pub cam_from_imu: nalgebra::UnitQuaternion<f64>,
    /// Time shift (s).
    pub shift_s: f64,
    /// Gyro bias (rad/s).
    pub gyro_bias: Vector3<f64>,
}

/// Fill in the frames between accepted keyframes by tracking: each frame's board pose is
/// predicted from the previous one (rotation from the gyro through `cam_from_imu`, translation
/// at constant velocity), every visible tag's corners are projected and refined with
/// `cornerSubPix` in the image, and the frame goes through the same robust pose check as a
/// detected one. A frame whose tracking fails is detected from scratch.
pub fn track(
    lens: &LensInput<'_>,
    keyframes: &LensObservations,
    target: &AprilGridTarget,
    model: &TrackModel<'_>,
    step: usize,
    keyframe_step: usize,
    readout_s: f64,
    progress: &ProgressBar,
) -> Result<LensObservations> {
    let detector = Detector::new(*target);
    let segments: Vec<&FrameObs> = keyframes.frames.iter().collect();
    let tracked: Vec<Result<(Vec<FrameObs>, usize)>> = segments
        .par_iter()
        .map(|key| {
            let mut out = vec![(*key).clone()];
            let mut rejected = 0;
            let end = (key.index + keyframe_step * step).min(lens.frames.len());
            for k in (key.index + step..end).step_by(step) {
                let record = &lens.frames[k];
                let gray = load_gray(&lens.dir.join(&record.file))?;
                let n = out.len();
                let prev = &out[n - 1];
                // Only a frame right before the previous one gives a usable velocity.
                let prev2 = (n >= 2 && out[n - 2].index + step == prev.index).then(|| &out[n - 2]);
                let predicted = predict(prev, prev2, record.t, model);
                let corners = track_corners(&gray, lens.camera, target, &predicted, readout_s)?;
                let mut frame = frame_pose(lens.camera, k, record.t, corners, Some(&predicted));
                if frame.is_none() {
                    let d = detector.detect(&gray)?;
                    frame = frame_pose(
                        lens.camera,
                        k,
                        record.t,
                        detected_corners(&d, lens.camera, readout_s),
                        None,
                    );
                }
                progress.inc(1);
                match frame {
                    Some(f) => out.push(f),
                    None => rejected += 1,
                }
            }
            Ok((out, rejected))
        })
        .collect();
    let mut result = LensObservations {
        frames: Vec::new(),
        frames_used: keyframes.frames_used,
        frames_rejected: keyframes.frames_rejected,
        ..keyframes.clone()
    };
    result.frames.clear();
    for r in tracked {
        let (frames, rejected) = r?;
        result.frames_used += frames.len() + rejected - 1;
        result.frames_rejected += rejected;
        result.frames.extend(frames);
    }
    result.frames.sort_by_key(|f| f.index);
    Ok(result)
}

fn detected_corners(
    d: &crate::detect::Detection,
    camera: &Camera,
    readout_s: f64,
) -> Vec<CornerObs> {
    let (_, height) = camera.resolution();
    d.corners
        .iter()
        .map(|c| CornerObs {
            board: c.board_point(),
            pixel: Vector2::new(c.pixel[0], c.pixel[1]),
            row_delay_s: readout_s * (c.pixel[1] + 0.5) / f64::from(height),
        })
        .collect()
}

/// `cam_from_board` at `t`: the previous frame's pose advanced by the gyro's rotation and, with
/// two previous frames, by their velocity.
fn predict(prev: &FrameObs, prev2: Option<&FrameObs>, t: f64, m: &TrackModel<'_>) -> Pose {
    let t0 = prev.t + prev.row_delay_s;
    let t1 = t + prev.row_delay_s;
    let dt = t1 - t0;
    let omega_imu = m
        .gyro
        .mean(t0 + m.shift_s, t1 + m.shift_s)
        .map_or(Vector3::zeros(), |(v, _)| v - m.gyro_bias);
    // board_from_cam(t1) = board_from_cam(t0) · exp(ω_cam dt).
    let step = kiwi_core::geometry::so3_exp(&(m.cam_from_imu * omega_imu * dt));
    let board_from_cam0 = prev.cam_from_board.inverse();
    let mut position = board_from_cam0.translation.vector;
    if let Some(p2) = prev2 {
        let b2 = p2.cam_from_board.inverse();
        let dt2 = t0 - (p2.t + p2.row_delay_s);
        if dt2 > 0.0 {
            position += (position - b2.translation.vector) * (dt / dt2);
        }
    }
    let board_from_cam = Pose::from_parts(
        nalgebra::Translation3::from(position),
        board_from_cam0.rotation * step,
    );
    board_from_cam.inverse()
}

/// Project every tag the predicted pose shows well and refine its corners in the image.
fn track_corners(
    gray: &image::GrayImage,
    camera: &Camera,
    target: &AprilGridTarget,
    cam_from_board: &Pose,
    readout_s: f64,
) -> Result<Vec<CornerObs>> {
    let (w, h) = camera.resolution();
    let (w, h) = (f64::from(w), f64::from(h));
    let normal = cam_from_board.rotation * Vector3::z();
    let mut tags: Vec<(u32, [Point2<f64>; 4])> = Vec::new();
    let mut boards: Vec<[Vector3<f64>; 4]> = Vec::new();
    'tags: for tag in 0..target.tag_count() {
        let mut px = [Point2::origin(); 4];
        let mut bp = [Vector3::zeros(); 4];
        for k in 0..4 {
            let b = target.point(target.corner_point_id(tag, k));
            let pc = (cam_from_board * nalgebra::Point3::from(b)).coords;
            // Facing the camera, not too oblique.
            if -normal.dot(&pc) < MIN_TRACK_COSINE * pc.norm() {
                continue 'tags;
            }
            let Some(p) = camera.project(&pc) else {
                continue 'tags;
            };
            if p.x < TRACK_BORDER_PX
                || p.y < TRACK_BORDER_PX
                || p.x > w - 1.0 - TRACK_BORDER_PX
                || p.y > h - 1.0 - TRACK_BORDER_PX
            {
                continue 'tags;
            }
            px[k] = p;
            bp[k] = b;
        }
        tags.push((tag as u32, px));
        boards.push(bp);
    }
    if tags.is_empty() {
        return Ok(Vec::new());
    }
    let refined = crate::detect::refine_corners(gray, &tags)?;
    let mut out = Vec::with_capacity(4 * tags.len());
    for (((_, pred), bp), new) in tags.iter().zip(&boards).zip(refined.chunks(4)) {
        if pred
            .iter()
            .zip(new)
            .any(|(a, b)| (a - b).norm() > MAX_TRACK_DISPLACEMENT_PX)
        {
            continue;
        }
        for (b, p) in bp.iter().zip(new) {
            out.push(CornerObs {
                board: *b,
                pixel: Vector2::new(p.x, p.y),
                row_delay_s: readout_s * (p.y + 0.5) / h,
            });
        }
    }
    Ok(out)
}

/// Load a frame as 8-bit grey. 8-bit RGB frames (what cameras and the simulator write) are
/// converted with integer Rec. 601 weights, several times faster than the generic colour
/// pipeline; other formats go through [`crate::detect::load_gray`].
pub fn load_gray(path: &Path) -> Result<image::GrayImage> {
    let reader = image::ImageReader::open(path)
        .and_then(image::ImageReader::with_guessed_format)
        .map_err(|e| CalibError::Input {
            path: path.to_path_buf(),
            message: format!("cannot read the frame ({e}); check the file or frames.csv"),
        })?;
    match reader.decode() {
        Ok(image::DynamicImage::ImageRgb8(rgb)) => {
            let (w, h) = rgb.dimensions();
            let data: Vec<u8> = rgb
                .as_raw()
                .chunks_exact(3)
                .map(|p| {
                    ((77 * u32::from(p[0]) + 150 * u32::from(p[1]) + 29 * u32::from(p[2]) + 128)
                        >> 8) as u8
                })
                .collect();
            image::GrayImage::from_raw(w, h, data).ok_or_else(|| {
                CalibError::Internal(format!("{}: grey buffer size", path.display()))
            })
        }
        Ok(image::DynamicImage::ImageLuma8(g)) => Ok(g),
        _ => crate::detect::load_gray(path),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn omega(t: f64) -> Vector3<f64> {
        Vector3::new(
            1.5 * (2.1 * t).sin() + 0.4 * (7.3 * t).cos(),
            0.8 * (3.7 * t + 1.0).sin(),
            1.1 * (5.2 * t + 0.3).sin() * (0.9 * t).cos(),
        )
    }

    #[test]
    fn coarse_shift_and_rotation_recovered_from_rates() {
        // t_imu = t_cam + shift: the camera sees at t what the gyro logs at t + shift.
        let shift = 0.037;
        let cam_from_imu = kiwi_core::geometry::so3_exp(&Vector3::new(0.3, -1.2, 2.0));
        let bias = Vector3::new(0.01, -0.02, 0.005);
        let gyro: Vec<ImuSample> = (0..20_000)
            .map(|i| {
                let t = i as f64 * 1e-3;
                ImuSample::new(t, omega(t - shift) + bias, Vector3::zeros())
            })
            .collect();
        let integral = GyroIntegral::new(&gyro);
        let rates: Vec<RateSample> = (0..1000)
            .map(|k| {
                let (t0, t1) = (1.0 + k as f64 / 60.0, 1.0 + (k + 1) as f64 / 60.0);
                RateSample {
                    t0,
                    t1,
                    omega: cam_from_imu * omega(0.5 * (t0 + t1)),
                }
            })
            .collect();
        let c = coarse_time_shift(&rates, &integral, 0.0, 0.2).unwrap();
        assert!((c.shift_s - shift).abs() < 5e-4, "{c:?}");
        assert!(c.correlation > 0.99);
        let (r, b) = align_rates(&rates, &integral, c.shift_s).unwrap();
        assert!(
            r.angle_to(&cam_from_imu) < 2e-3,
            "{}",
            r.angle_to(&cam_from_imu)
        );
        assert!((b - bias).norm() < 2e-3, "{b}");
        let (rms, share) = excitation(&rates);
        assert!(rms > 1.0 && share > 0.05);
        // Rotation about one axis only is not enough.
        let flat: Vec<RateSample> = rates
            .iter()
            .map(|r| RateSample {
                omega: Vector3::new(r.omega.norm(), 0.0, 0.0),
                ..*r
            })
            .collect();
        assert!(excitation(&flat).1 < MIN_AXIS_SHARE);
    }
}
