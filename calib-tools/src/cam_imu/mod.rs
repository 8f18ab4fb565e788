//! Camera–IMU calibration of a unit (`kiwi-calib cam-imu`): `cam_from_imu` and the time shift of
//! every lens from one excitation recording in front of aprilgrid boards (both lenses of an X5
//! share the IMU, so they are estimated jointly and the lens-to-lens extrinsic follows).
//!
//! Pipeline (docs/cam-imu.md):
//! 1. aprilgrid corners in every frame (parallel), each frame's board pose from bearing vectors
//!    with a robust pixel refinement; frames with too few corners or a large error are dropped;
//! 2. camera angular rates from consecutive poses; coarse time shift per lens by
//!    cross-correlating rate magnitudes with the gyro over `guess ± window`;
//! 3. `cam_from_imu` rotation and gyro bias by aligning the angular rates;
//! 4. joint batch Levenberg–Marquardt over a cubic B-spline trajectory (SO(3)×R³) fitted to every
//!    IMU sample and every corner at its rolling-shutter time, with each lens's extrinsic and time
//!    shift, the rear board's pose, gravity and drifting biases; Huber loss, outlier rejection,
//!    a second solve; standard deviations from the inverse Hessian scaled by the residual variance.

pub mod observe;
pub mod report;
pub mod solve;
pub mod spline;

use std::path::{Path, PathBuf};
use std::time::Instant;

use nalgebra::{Matrix6, UnitQuaternion, Vector3};
use serde::Serialize;

use kiwi_core::artifact::UnitCalibration;
use kiwi_core::camera::CameraModel;
use kiwi_core::geometry::{Pose, average_rotations, se3_adjoint, so3_log};
use kiwi_core::imu::{ImuSample, ImuSeries};
use kiwi_core::layout::{EpisodeLayout, read_frames_csv};

use crate::error::{CalibError, Result};
use crate::target::AprilGridTarget;
use observe::{GyroIntegral, LensInput, LensObservations};
use solve::{LensState, Problem, State, Weights};
use spline::{TrajectorySpline, VectorSpline};

/// Fewest accepted frames per lens: fewer cannot separate the extrinsic from the trajectory.
pub const MIN_FRAMES: usize = 40;
/// Default keyframe interval (s): 5 Hz keyframes give the coarse alignment dozens of
/// angular-rate samples per ten seconds while full detection runs on a twenty-fourth of the
/// frames of a 120 Hz video.
pub const DEFAULT_KEYFRAME_INTERVAL_S: f64 = 0.2;
/// Fewest accepted keyframes before tracking: enough angular-rate samples for the coarse shift.
const MIN_KEYFRAMES: usize = 15;
/// Default gravity magnitude (m/s²); the simulator's and a mid-latitude sea-level value.
pub const DEFAULT_GRAVITY: f64 = 9.81;
/// IMU noise used when the calibration has no `imu` block (typical MEMS IMU of an action camera;
/// run `kiwi-calib imu-noise` for the unit's own values).
const DEFAULT_GYRO_NOISE: f64 = 2.0e-4;
const DEFAULT_GYRO_RANDOM_WALK: f64 = 2.0e-5;
const DEFAULT_ACCEL_NOISE: f64 = 2.0e-3;
const DEFAULT_ACCEL_RANDOM_WALK: f64 = 3.0e-4;
/// Frames this close (s) to either end of the IMU log are left out, so a refined time shift
/// never moves a corner off the trajectory.
const END_MARGIN_S: f64 = 0.1;
/// Huber threshold in units of the corner noise.
const HUBER_SIGMAS: f64 = 3.0;
/// After the first solve, corners beyond this many noise sigmas are rejected as outliers.
const OUTLIER_SIGMAS: f64 = 5.0;
/// Floor of the corner noise (px): detections are never trusted below this.
const MIN_PIXEL_SIGMA: f64 = 0.05;
/// IMU residual samples kept for the plot (a line of a few thousand points shows the shape).
const MAX_PLOTTED_IMU_RESIDUALS: usize = 4000;

/// Options of `kiwi-calib cam-imu`.
#[derive(Debug, Clone)]
pub struct CamImuOptions {
    /// The camera folder of the excitation (meta.json, imu.csv, <lens>/frames.csv).
    pub capture: PathBuf,
    /// The unit's calibration.json with the lenses' intrinsics.
    pub intrinsics: PathBuf,
    /// How the outputs name the calibration the IMU noise came from (default: `intrinsics`'
    /// path); a caller that reads a staged copy names the file the user keeps.
    pub intrinsics_label: Option<String>,
    /// Kalibr aprilgrid yaml.
    pub target: PathBuf,
    /// Use every n-th frame.
    pub frame_step: usize,
    /// Detect the board from scratch in a keyframe this often (s) and track it (gyro-aided
    /// prediction + sub-pixel refinement) in the frames between; 0 detects in every frame.
    pub keyframe_interval_s: f64,
    /// Starting time shift (s).
    pub time_shift_guess_s: f64,
    /// Half-width (s) of the coarse time-shift search.
    pub search_window_s: f64,
    /// Knot spacing of the trajectory spline (s).
    pub knot_spacing_s: f64,
    /// Knot spacing of the bias splines (s).
    pub bias_knot_spacing_s: f64,
    /// Rolling-shutter readout override (s); otherwise from the calibration's recording mode.
    pub readout_s: Option<f64>,
    /// Gravity magnitude (m/s²).
    pub gravity_m_s2: f64,
    /// Levenberg–Marquardt iterations per solve.
    pub max_iterations: usize,
    /// Progress bars on stderr.
    pub progress: bool,
}

impl CamImuOptions {
    /// Defaults for a capture.
    pub fn new(capture: &Path, intrinsics: &Path, target: &Path) -> Self {
        Self {
            capture: capture.to_path_buf(),
            intrinsics: intrinsics.to_path_buf(),
            intrinsics_label: None,
            target: target.to_path_buf(),
            frame_step: 1,
            keyframe_interval_s: DEFAULT_KEYFRAME_INTERVAL_S,
            time_shift_guess_s: 0.0,
            search_window_s: 0.25,
            knot_spacing_s: 0.02,
            bias_knot_spacing_s: 5.0,
            readout_s: None,
            gravity_m_s2: DEFAULT_GRAVITY,
            max_iterations: 30,
            progress: false,
        }
    }
}

/// One lens's result.
#[derive(Debug, Clone, Serialize)]
pub struct LensResult {
    /// Lens name.
    pub name: String,
    /// `cam_from_imu` rotation as an axis-angle vector (deg).
    pub rotation_deg: [f64; 3],
    /// `cam_from_imu` translation (m).
    pub translation_m: [f64; 3],
    /// Kalibr time shift (s): `t_imu = t_cam + time_shift_s`.
    pub time_shift_s: f64,
    /// RMS reprojection error of the inlier corners (px).
    pub rms_px: f64,
    /// Standard deviation of the rotation (deg, about the camera axes).
    pub rotation_std_deg: [f64; 3],
    /// Standard deviation of the translation (m).
    pub translation_std_m: [f64; 3],
    /// Standard deviation of the time shift (s).
    pub time_shift_std_s: f64,
    /// Coarse time shift from the rate cross-correlation (s).
    pub coarse_time_shift_s: f64,
    /// Normalised correlation at the coarse peak.
    pub correlation: f64,
    /// Frames in frames.csv / looked at / accepted.
    pub frames_total: usize,
    /// Frames looked at.
    pub frames_used: usize,
    /// Frames accepted.
    pub frames_accepted: usize,
    /// Corners used in the final solve.
    pub corners: usize,
    /// Corners rejected (per-frame check and after the first solve).
    pub corners_rejected: usize,
    /// RMS camera rotation rate (rad/s).
    pub rotation_rate_rms: f64,
    /// `cam_from_imu` as a pose.
    #[serde(skip)]
    pub cam_from_imu: Pose,
}

/// Lens-to-lens extrinsic composed through the IMU.
#[derive(Debug, Clone, Serialize)]
pub struct LensPair {
    /// `a_from_b` names.
    pub name: String,
    /// Rotation (axis-angle, deg).
    pub rotation_deg: [f64; 3],
    /// Translation (m).
    pub translation_m: [f64; 3],
    /// Rotation standard deviation (deg).
    pub rotation_std_deg: [f64; 3],
    /// Translation standard deviation (m).
    pub translation_std_m: [f64; 3],
    /// Difference of the time shifts (s): second lens minus first.
    pub time_shift_difference_s: f64,
}

/// The whole result.
#[derive(Debug, Clone, Serialize)]
pub struct CamImuResult {
    /// Unit id.
    pub unit_id: String,
    /// Per lens.
    pub lenses: Vec<LensResult>,
    /// Lens-to-lens extrinsics (second lens from first, ...).
    pub lens_pairs: Vec<LensPair>,
    /// Gravity in the first board's frame (m/s²).
    pub gravity: [f64; 3],
    /// Mean gyro bias (rad/s).
    pub gyro_bias: [f64; 3],
    /// Mean accelerometer bias (m/s²).
    pub accel_bias: [f64; 3],
    /// RMS gyro residual (rad/s) and accelerometer residual (m/s²).
    pub gyro_rms: f64,
    /// RMS accelerometer residual (m/s²).
    pub accel_rms: f64,
    /// Corner noise used for the weights (px).
    pub pixel_sigma: f64,
    /// Rolling-shutter readout used (s) and where it came from.
    pub readout_s: f64,
    /// Where the readout came from.
    pub readout_source: String,
    /// Where the IMU noise came from.
    pub imu_noise_source: String,
    /// Residual variance factor (χ²/dof) the covariances were scaled by.
    pub variance_factor: f64,
    /// Levenberg–Marquardt iterations (both solves).
    pub iterations: usize,
    /// Wall times (s): detection, initialisation, batch.
    pub seconds: Timing,
    /// Samples of the plots.
    #[serde(skip)]
    pub plots: PlotData,
    /// Inputs (for provenance).
    #[serde(skip)]
    pub inputs: Vec<PathBuf>,
    /// The calibration with the new extrinsics.
    #[serde(skip)]
    pub calibration: UnitCalibration,
}

/// Wall times of the stages (s).
#[derive(Debug, Clone, Copy, Serialize, Default)]
pub struct Timing {
    /// Detection and per-frame poses.
    pub detection: f64,
    /// Coarse time shift, rotation and trajectory initialisation.
    pub initialisation: f64,
    /// Both batch solves.
    pub batch: f64,
}

/// Residual series for the report plots.
#[derive(Debug, Clone, Default)]
pub struct PlotData {
    /// Per lens: `(t, |residual| px)` per corner.
    pub corner_residuals: Vec<Vec<(f64, f64)>>,
    /// Per lens: `(du, dv)` per corner.
    pub corner_vectors: Vec<Vec<(f64, f64)>>,
    /// `(t, |gyro residual|, |accel residual|)`.
    pub imu_residuals: Vec<(f64, f64, f64)>,
    /// Per lens: `(t, camera rate magnitude, gyro magnitude at the estimated shift)`.
    pub rates: Vec<Vec<(f64, f64, f64)>>,
}

fn input(path: &Path, message: String) -> CalibError {
    CalibError::Input {
        path: path.to_path_buf(),
        message,
    }
}

/// Everything read from disk.
struct Inputs {
    calibration: UnitCalibration,
    target: AprilGridTarget,
    imu: Vec<ImuSample>,
    fps: f64,
    lens_names: Vec<String>,
    frames: Vec<Vec<kiwi_core::layout::FrameRecord>>,
    readout_s: f64,
    readout_source: String,
    files: Vec<PathBuf>,
}

fn load_inputs(o: &CamImuOptions) -> Result<Inputs> {
    let capture = &o.capture;
    let camera_name = capture
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .ok_or_else(|| input(capture, "expected a camera folder (with meta.json)".into()))?;
    let root = capture.parent().map(Path::to_path_buf).unwrap_or_default();
    let layout = EpisodeLayout::new(root);
    let meta = layout.read_meta(&camera_name)?;
    let calibration = UnitCalibration::load(&o.intrinsics)?;
    let target = AprilGridTarget::load(&o.target)?;
    let imu_path = layout.imu_csv(&camera_name);
    let imu = ImuSeries::read_csv(&imu_path)?;
    if !imu.gaps().is_empty() {
        tracing::warn!(
            "{}: {} gaps in the IMU log; the trajectory bridges them",
            imu_path.display(),
            imu.gaps().len()
        );
    }
    let mut files = vec![o.intrinsics.clone(), o.target.clone(), imu_path.clone()];
    let mut frames = Vec::new();
    for name in &meta.lenses {
        if calibration.lens(name).is_none() {
            return Err(input(
                &o.intrinsics,
                format!(
                    "lenses[]: no lens named {name:?} (the capture's meta.json lists {:?}); pass \
                     the calibration.json of unit {} with intrinsics for every lens",
                    meta.lenses, meta.unit_id
                ),
            ));
        }
        let path = layout.frames_csv(&camera_name, name);
        frames.push(read_frames_csv(&path)?);
        files.push(path);
    }
    if meta.lenses.is_empty() {
        return Err(input(
            &layout.meta_json(&camera_name),
            "lenses: empty; list the lens folders of the capture".into(),
        ));
    }
    if calibration.unit_id != meta.unit_id {
        tracing::warn!(
            "the capture is from unit {} but the calibration is for unit {}",
            meta.unit_id,
            calibration.unit_id
        );
    }
    let (readout_s, readout_source) = match o.readout_s {
        Some(r) => (r, "--readout".to_owned()),
        None => {
            let mode = calibration
                .recording_modes
                .iter()
                .find(|m| m.name == meta.mode)
                .or_else(|| {
                    calibration
                        .recording_modes
                        .iter()
                        .find(|m| (m.fps - meta.fps).abs() < 0.01 && m.readout_time_s.is_some())
                });
            match mode.and_then(|m| m.readout_time_s.map(|r| (r, m.name.clone()))) {
                Some((r, name)) => (r, format!("recording mode {name} of the calibration")),
                None => {
                    tracing::warn!(
                        "no readout time for mode {} ({} fps) in {}: assuming a global shutter; \
                         pass --readout SECONDS for a rolling-shutter camera",
                        meta.mode,
                        meta.fps,
                        o.intrinsics.display()
                    );
                    (0.0, "none known: global shutter assumed".to_owned())
                }
            }
        }
    };
    if !(0.0..0.1).contains(&readout_s) {
        return Err(input(
            &o.intrinsics,
            format!(
                "recording_modes[].readout_time_s: expected 0–0.1 s, found {readout_s}; the \
                 readout is in seconds"
            ),
        ));
    }
    Ok(Inputs {
        calibration,
        target,
        imu: imu.samples().to_vec(),
        fps: meta.fps,
        lens_names: meta.lenses,
        frames,
        readout_s,
        readout_source,
        files,
    })
}

/// Run the calibration.
pub fn calibrate(o: &CamImuOptions) -> Result<CamImuResult> {
    let inputs = load_inputs(o)?;
    let capture = &o.capture;
    let t_start = Instant::now();
    let cameras: Vec<kiwi_core::camera::Camera> = inputs
        .lens_names
        .iter()
        .map(|n| {
            inputs
                .calibration
                .lens(n)
                .ok_or_else(|| input(&o.intrinsics, format!("no lens {n}")))
                .and_then(|l| l.camera().map_err(CalibError::from))
        })
        .collect::<Result<_>>()?;
    let dirs: Vec<PathBuf> = inputs.lens_names.iter().map(|n| capture.join(n)).collect();
    let lens_inputs: Vec<LensInput<'_>> = inputs
        .lens_names
        .iter()
        .enumerate()
        .map(|(i, n)| LensInput {
            name: n,
            dir: &dirs[i],
            frames: &inputs.frames[i],
            camera: &cameras[i],
        })
        .collect();
    let gyro = GyroIntegral::new(&inputs.imu);
    let keyframe_step = if o.keyframe_interval_s > 0.0 {
        ((o.keyframe_interval_s * inputs.fps / o.frame_step.max(1) as f64).round() as usize).max(1)
    } else {
        1
    };
    let mut lenses = observe::observe(
        &lens_inputs,
        &inputs.target,
        o.frame_step * keyframe_step,
        inputs.readout_s,
        o.progress,
    )?;
    if keyframe_step > 1 {
        check_detections(
            &lenses,
            (MIN_FRAMES / keyframe_step).max(MIN_KEYFRAMES),
            capture,
            &inputs.target,
        )?;
        let total: usize = inputs.frames.iter().map(Vec::len).sum::<usize>() / o.frame_step.max(1);
        let bar = if o.progress {
            let b = indicatif::ProgressBar::new(total as u64);
            if let Ok(style) = indicatif::ProgressStyle::with_template(
                "tracking {bar:40} {pos}/{len} frames ({eta} left)",
            ) {
                b.set_style(style);
            }
            b
        } else {
            indicatif::ProgressBar::hidden()
        };
        for (l, lens) in lens_inputs.iter().enumerate() {
            let (shift, rotation, bias, _) = coarse_align(&lenses[l], &gyro, o, inputs.fps)?;
            let model = observe::TrackModel {
                gyro: &gyro,
                cam_from_imu: rotation,
                shift_s: shift.shift_s,
                gyro_bias: bias,
            };
            lenses[l] = observe::track(
                lens,
                &lenses[l],
                &inputs.target,
                &model,
                o.frame_step.max(1),
                keyframe_step,
                inputs.readout_s,
                &bar,
            )?;
        }
        bar.finish_and_clear();
    }
    let detection_s = t_start.elapsed().as_secs_f64();
    check_detections(&lenses, MIN_FRAMES, capture, &inputs.target)?;
    // Coarse alignment per lens.
    let t_init = Instant::now();
    let mut coarse = Vec::new();
    for l in &lenses {
        coarse.push(coarse_align(l, &gyro, o, inputs.fps)?);
    }

    let imu_t0 = inputs.imu.first().map_or(0.0, |s| s.t);
    let imu_t1 = inputs.imu.last().map_or(0.0, |s| s.t);
    let count = ((imu_t1 - imu_t0) / o.knot_spacing_s).floor().max(0.0) as usize + 4;
    let mut spline = TrajectorySpline {
        t0: imu_t0,
        h: o.knot_spacing_s,
        rotations: vec![UnitQuaternion::identity(); count],
        positions: vec![Vector3::zeros(); count],
    };
    let t_end = spline.t_end();
    // Keep frames whose every corner lies well inside the trajectory.
    for (l, obs) in lenses.iter_mut().enumerate() {
        let d = coarse[l].0.shift_s;
        obs.frames.retain(|f| {
            f.t + d >= imu_t0 + END_MARGIN_S && f.t + d + inputs.readout_s <= t_end - END_MARGIN_S
        });
        if obs.frames.len() < MIN_FRAMES {
            return Err(input(
                &capture.join("imu.csv"),
                format!(
                    "only {} frames of the {} lens fall inside the IMU log (need {MIN_FRAMES}); \
                     record the IMU for the whole video",
                    obs.frames.len(),
                    obs.name
                ),
            ));
        }
    }
    let lens_states: Vec<LensState> = coarse
        .iter()
        .map(|(s, r, _, _)| LensState {
            cam_from_imu: Pose::from_parts(nalgebra::Translation3::identity(), *r),
            time_shift_s: s.shift_s,
        })
        .collect();
    // World = the first lens's board: world_from_imu = board_from_cam · cam_from_imu.
    let x0 = lens_states[0].cam_from_imu;
    let samples: Vec<(f64, Pose)> = lenses[0]
        .frames
        .iter()
        .map(|f| {
            (
                f.t + lens_states[0].time_shift_s + f.row_delay_s,
                f.cam_from_board.inverse() * x0,
            )
        })
        .collect();
    for j in 0..count {
        let tau = spline.t0 + (j as f64 - 1.0) * spline.h;
        let pose = interpolate_samples(&samples, tau);
        spline.rotations[j] = pose.rotation;
        spline.positions[j] = pose.translation.vector;
    }
    // Smooth the start: make consecutive control rotations take the short way.
    let mut world_from_board = vec![Pose::identity(); lenses.len()];
    for l in 1..lenses.len() {
        let x = lens_states[l].cam_from_imu;
        let mut rots = Vec::new();
        let mut trans: Vec<Vector3<f64>> = Vec::new();
        for f in &lenses[l].frames {
            if let Some((r, p)) = spline.pose(f.t + lens_states[l].time_shift_s + f.row_delay_s) {
                let w = Pose::from_parts(nalgebra::Translation3::from(p), r)
                    * x.inverse()
                    * f.cam_from_board;
                rots.push(w.rotation);
                trans.push(w.translation.vector);
            }
        }
        let r = average_rotations(&rots, None)
            .ok_or_else(|| input(capture, format!("no usable frames of lens {l}")))?;
        let t = Vector3::from_fn(|i, _| {
            let mut v: Vec<f64> = trans.iter().map(|p| p[i]).collect();
            v.sort_by(f64::total_cmp);
            v.get(v.len() / 2).copied().unwrap_or(0.0)
        });
        world_from_board[l] = Pose::from_parts(nalgebra::Translation3::from(t), r);
    }
    let imu_in: Vec<ImuSample> = inputs
        .imu
        .iter()
        .filter(|s| spline.locate(s.t).is_some())
        .copied()
        .collect();
    // Gravity: g = a − R·f on average (the board frame is not level).
    let mut gsum = Vector3::zeros();
    let mut gn = 0.0;
    for s in imu_in.iter().step_by(10) {
        if let Some(st) = spline.state(s.t) {
            gsum += st.acceleration - st.rotation * s.accel;
            gn += 1.0;
        }
    }
    let gravity = if gn > 0.0 && gsum.norm() > 0.0 {
        gsum.normalize() * o.gravity_m_s2
    } else {
        Vector3::new(0.0, 0.0, -o.gravity_m_s2)
    };
    let noise = inputs.calibration.imu.clone();
    let imu_noise_source = if noise.is_some() {
        let label = o
            .intrinsics_label
            .clone()
            .unwrap_or_else(|| o.intrinsics.display().to_string());
        format!("imu block of {label}")
    } else {
        "defaults (no imu block in the calibration; run kiwi-calib imu-noise)".to_owned()
    };
    let rate = inputs.imu.len() as f64 / (imu_t1 - imu_t0).max(1e-9);
    let (ng, kg, na, ka) = noise.as_ref().map_or(
        (
            DEFAULT_GYRO_NOISE,
            DEFAULT_GYRO_RANDOM_WALK,
            DEFAULT_ACCEL_NOISE,
            DEFAULT_ACCEL_RANDOM_WALK,
        ),
        |n| {
            (
                n.gyroscope_noise_density,
                n.gyroscope_random_walk,
                n.accelerometer_noise_density,
                n.accelerometer_random_walk,
            )
        },
    );
    let mut frame_rms: Vec<f64> = lenses
        .iter()
        .flat_map(|l| l.frames.iter().map(|f| f.rms_px))
        .collect();
    frame_rms.sort_by(f64::total_cmp);
    let pixel_sigma =
        (frame_rms[frame_rms.len() / 2] / std::f64::consts::SQRT_2).max(MIN_PIXEL_SIGMA);
    let mut weights = Weights {
        pixel_sigma,
        huber_px: HUBER_SIGMAS * pixel_sigma,
        gyro_sigma: ng * rate.sqrt(),
        accel_sigma: na * rate.sqrt(),
        gyro_random_walk: kg,
        accel_random_walk: ka,
    };
    let mut state = State {
        spline,
        lenses: lens_states.clone(),
        world_from_board,
        gravity,
        gyro_bias: VectorSpline::constant(imu_t0, imu_t1, o.bias_knot_spacing_s, coarse[0].2),
        accel_bias: VectorSpline::constant(imu_t0, imu_t1, o.bias_knot_spacing_s, Vector3::zeros()),
    };
    let initialisation_s = t_init.elapsed().as_secs_f64();

    // Batch: solve, reject outlier corners, re-weight, solve again.
    let t_batch = Instant::now();
    let progress = |stage: &'static str| {
        move |it: usize, c: f64| tracing::info!("{stage}: iteration {it}, cost {c:.6e}")
    };
    let (s1, sum1) = {
        let problem = Problem {
            lenses: &lenses,
            imu: &imu_in,
            weights,
        };
        solve::optimize(
            &problem,
            state,
            o.max_iterations,
            false,
            &progress("batch 1"),
        )
    };
    state = s1;
    let mut rejected = vec![0usize; lenses.len()];
    {
        let problem = Problem {
            lenses: &lenses,
            imu: &imu_in,
            weights,
        };
        let res = solve::corner_residuals(&problem, &state);
        let mut comps: Vec<f64> = res
            .iter()
            .flat_map(|(_, _, _, r)| [r.x.abs(), r.y.abs()])
            .collect();
        comps.sort_by(f64::total_cmp);
        let sigma =
            (1.4826 * comps.get(comps.len() / 2).copied().unwrap_or(1.0)).max(MIN_PIXEL_SIGMA);
        weights.pixel_sigma = sigma;
        weights.huber_px = HUBER_SIGMAS * sigma;
        let limit = OUTLIER_SIGMAS * sigma;
        for (l, obs) in lenses.iter_mut().enumerate() {
            let lens = state.lenses[l];
            let wfb = state.world_from_board[l];
            for f in &mut obs.frames {
                let before = f.corners.len();
                let t0 = f.t + lens.time_shift_s;
                f.corners.retain(|c| {
                    state
                        .spline
                        .pose(t0 + c.row_delay_s)
                        .and_then(|(r, p)| {
                            let pw = wfb * nalgebra::Point3::from(c.board);
                            let pc = lens.cam_from_imu
                                * nalgebra::Point3::from(r.inverse() * (pw.coords - p));
                            obs.camera.project(&pc.coords)
                        })
                        .is_some_and(|px| (px.coords - c.pixel).norm() <= limit)
                });
                rejected[l] += before - f.corners.len();
            }
            obs.frames
                .retain(|f| f.corners.len() >= observe::MIN_CORNERS_PER_FRAME);
        }
    }
    let problem = Problem {
        lenses: &lenses,
        imu: &imu_in,
        weights,
    };
    let (state, sum2) = solve::optimize(
        &problem,
        state,
        o.max_iterations,
        true,
        &progress("batch 2"),
    );
    let batch_s = t_batch.elapsed().as_secs_f64();

    // Uncertainties: inverse Hessian scaled by the residual variance factor.
    let n_corners: usize = lenses
        .iter()
        .map(|l| l.frames.iter().map(|f| f.corners.len()).sum::<usize>())
        .sum();
    let n_res = 2 * n_corners + 6 * imu_in.len();
    let n_par = 6 * state.spline.len()
        + 7 * lenses.len()
        + 6 * (lenses.len() - 1)
        + 2
        + 6 * state.gyro_bias.values.len();
    let variance_factor = sum2.final_cost / (n_res.saturating_sub(n_par)).max(1) as f64;
    let residuals = solve::corner_residuals(&problem, &state);
    let imu_res = solve::imu_residuals(&problem, &state, 1);
    let mut results = Vec::new();
    for (l, obs) in lenses.iter().enumerate() {
        let lens = state.lenses[l];
        let sq: Vec<f64> = residuals
            .iter()
            .filter(|r| r.0 == l)
            .map(|r| r.3.norm_squared())
            .collect();
        let rms_px = (sq.iter().sum::<f64>() / sq.len().max(1) as f64).sqrt();
        let cov = lens_covariance(&sum2, l, l, variance_factor);
        let sd = |i: usize| cov.map_or(f64::NAN, |c| c[(i, i)].max(0.0).sqrt());
        let time_std = sum2.covariance.as_ref().map_or(f64::NAN, |c| {
            let b = sum2.lens_offsets[l] + 6;
            (c[(b, b)] * variance_factor).max(0.0).sqrt()
        });
        let x = lens.cam_from_imu;
        let rv = so3_log(&x.rotation);
        results.push(LensResult {
            name: obs.name.clone(),
            rotation_deg: [rv.x.to_degrees(), rv.y.to_degrees(), rv.z.to_degrees()],
            translation_m: [x.translation.x, x.translation.y, x.translation.z],
            time_shift_s: lens.time_shift_s,
            rms_px,
            rotation_std_deg: [sd(0).to_degrees(), sd(1).to_degrees(), sd(2).to_degrees()],
            translation_std_m: translation_std(&x, cov),
            time_shift_std_s: time_std,
            coarse_time_shift_s: coarse[l].0.shift_s,
            correlation: coarse[l].0.correlation,
            frames_total: obs.frames_total,
            frames_used: obs.frames_used,
            frames_accepted: obs.frames.len(),
            corners: sq.len(),
            corners_rejected: rejected[l] + obs.frames.iter().map(|f| f.outliers).sum::<usize>(),
            rotation_rate_rms: coarse[l].3,
            cam_from_imu: x,
        });
    }
    let mut lens_pairs = Vec::new();
    for l in 1..results.len() {
        let (a, b) = (&results[l - 1], &results[l]);
        let e = b.cam_from_imu * a.cam_from_imu.inverse();
        let rv = so3_log(&e.rotation);
        // Left perturbations: ξ_E = ξ_b − Ad_E ξ_a.
        let (std_r, std_t) = match (
            lens_covariance(&sum2, l - 1, l - 1, variance_factor),
            lens_covariance(&sum2, l, l, variance_factor),
            lens_covariance(&sum2, l, l - 1, variance_factor),
        ) {
            (Some(caa), Some(cbb), Some(cba)) => {
                let ad = se3_adjoint(&e);
                let c =
                    cbb + ad * caa * ad.transpose() - cba * ad.transpose() - ad * cba.transpose();
                let sd = |i: usize| c[(i, i)].max(0.0).sqrt();
                (
                    [sd(0).to_degrees(), sd(1).to_degrees(), sd(2).to_degrees()],
                    translation_std(&e, Some(c)),
                )
            }
            _ => ([f64::NAN; 3], [f64::NAN; 3]),
        };
        lens_pairs.push(LensPair {
            name: format!("{}_from_{}", b.name, a.name),
            rotation_deg: [rv.x.to_degrees(), rv.y.to_degrees(), rv.z.to_degrees()],
            translation_m: [e.translation.x, e.translation.y, e.translation.z],
            rotation_std_deg: std_r,
            translation_std_m: std_t,
            time_shift_difference_s: b.time_shift_s - a.time_shift_s,
        });
    }
    let mut calibration = inputs.calibration.clone();
    for r in &results {
        if let Some(lc) = calibration.lenses.iter_mut().find(|c| c.name == r.name) {
            lc.cam_from_imu = Some(kiwi_core::artifact::RigidTransform::from_pose(
                &r.cam_from_imu,
            ));
            lc.time_shift_s = Some(r.time_shift_s);
        }
    }
    let mean_bias = |s: &VectorSpline| {
        let v = s.values.iter().fold(Vector3::zeros(), |a, b| a + b) / s.values.len() as f64;
        [v.x, v.y, v.z]
    };
    let rms = |f: &dyn Fn(&ImuResidual) -> f64| {
        (imu_res.iter().map(|r| f(r).powi(2)).sum::<f64>() / imu_res.len().max(1) as f64).sqrt()
            / 3f64.sqrt()
    };
    let plots = plot_data(&lenses, &state, &residuals, &imu_res, &gyro, inputs.fps);
    Ok(CamImuResult {
        unit_id: calibration.unit_id.clone(),
        lenses: results,
        lens_pairs,
        gravity: [state.gravity.x, state.gravity.y, state.gravity.z],
        gyro_bias: mean_bias(&state.gyro_bias),
        accel_bias: mean_bias(&state.accel_bias),
        gyro_rms: rms(&|r| r.1.norm()),
        accel_rms: rms(&|r| r.2.norm()),
        pixel_sigma: weights.pixel_sigma,
        readout_s: inputs.readout_s,
        readout_source: inputs.readout_source,
        imu_noise_source,
        variance_factor,
        iterations: sum1.iterations + sum2.iterations,
        seconds: Timing {
            detection: detection_s,
            initialisation: initialisation_s,
            batch: batch_s,
        },
        plots,
        inputs: inputs.files,
        calibration,
    })
}

/// Fail with a useful message when a lens has fewer than `min` accepted frames.
fn check_detections(
    lenses: &[LensObservations],
    min: usize,
    capture: &Path,
    target: &AprilGridTarget,
) -> Result<()> {
    for l in lenses {
        if l.frames.len() < min {
            return Err(input(
                &capture.join(&l.name),
                format!(
                    "too few detections: the board was found in {} of {} frames of the {} lens \
                     (need at least {min}); film the aprilgrid from closer and keep it in \
                     view, check the target yaml matches the board ({}x{} tags of {} m)",
                    l.frames.len(),
                    l.frames_used,
                    l.name,
                    target.cols,
                    target.rows,
                    target.tag_size_m
                ),
            ));
        }
    }
    Ok(())
}

/// Coarse time shift, `cam_from_imu` rotation, gyro bias and RMS rotation rate of one lens.
fn coarse_align(
    l: &LensObservations,
    gyro: &GyroIntegral,
    o: &CamImuOptions,
    fps: f64,
) -> Result<(observe::CoarseShift, UnitQuaternion<f64>, Vector3<f64>, f64)> {
    let capture = &o.capture;
    let rates = observe::camera_rates(&l.frames, fps);
    let (rms, share) = observe::excitation(&rates);
    if rms < observe::MIN_ROTATION_RATE || share < observe::MIN_AXIS_SHARE {
        return Err(input(
            capture,
            format!(
                "too little rotation excitation for the {} lens: RMS rate {rms:.2} rad/s \
                 (need ≥ {}), weakest axis {:.1} % of the strongest (need ≥ {:.0} %); rotate \
                 the camera about all three axes (roll, pitch, yaw) while filming the board",
                l.name,
                observe::MIN_ROTATION_RATE,
                100.0 * share,
                100.0 * observe::MIN_AXIS_SHARE
            ),
        ));
    }
    let shift = observe::coarse_time_shift(&rates, gyro, o.time_shift_guess_s, o.search_window_s)
        .ok_or_else(|| {
        input(
            &capture.join("imu.csv"),
            format!(
                "the IMU log does not overlap the {} lens's frames for any time shift within \
                 {} ± {} s; check imu.csv is on the camera clock (t in s)",
                l.name, o.time_shift_guess_s, o.search_window_s
            ),
        )
    })?;
    if shift.correlation < observe::MIN_CORRELATION {
        return Err(input(
            &capture.join("imu.csv"),
            format!(
                "gyro/camera angular-rate correlation too weak for a time shift for the {} \
                 lens: peak {:.2} at {:.1} ms (need ≥ {}); the gyro may not belong to this \
                 camera, the shift may lie outside {} ± {} s (widen --search-window), or the \
                 motion is too smooth — vary the rotation speed",
                l.name,
                shift.correlation,
                shift.shift_s * 1e3,
                observe::MIN_CORRELATION,
                o.time_shift_guess_s,
                o.search_window_s
            ),
        ));
    }
    let (rotation, bias) = observe::align_rates(&rates, gyro, shift.shift_s)
        .ok_or_else(|| input(capture, "too few angular-rate pairs to align".into()))?;
    tracing::info!(
        "{}: coarse time shift {:.2} ms (correlation {:.3}), rotation {:.2} deg",
        l.name,
        shift.shift_s * 1e3,
        shift.correlation,
        rotation.angle().to_degrees()
    );
    Ok((shift, rotation, bias, rms))
}

/// One IMU residual: time, gyro (rad/s) and accelerometer (m/s²) residual.
type ImuResidual = (f64, Vector3<f64>, Vector3<f64>);

/// The 6 × 6 covariance block between lens `a`'s and lens `b`'s `cam_from_imu`, scaled.
fn lens_covariance(
    summary: &solve::SolveSummary,
    a: usize,
    b: usize,
    scale: f64,
) -> Option<Matrix6<f64>> {
    let c = summary.covariance.as_ref()?;
    let (oa, ob) = (summary.lens_offsets[a], summary.lens_offsets[b]);
    Some(Matrix6::from_fn(|i, j| c[(oa + i, ob + j)] * scale))
}

/// Standard deviation of a pose's translation under a left-perturbation covariance:
/// `t' = exp(φ)t + ρ` ⇒ `δt = −[t]× φ + ρ`.
fn translation_std(pose: &Pose, cov: Option<Matrix6<f64>>) -> [f64; 3] {
    let Some(c) = cov else {
        return [f64::NAN; 3];
    };
    let mut j = nalgebra::Matrix3x6::<f64>::zeros();
    j.fixed_view_mut::<3, 3>(0, 0)
        .copy_from(&(-kiwi_core::geometry::hat(&pose.translation.vector)));
    j.fixed_view_mut::<3, 3>(0, 3)
        .copy_from(&nalgebra::Matrix3::identity());
    let ct = j * c * j.transpose();
    [
        ct[(0, 0)].max(0.0).sqrt(),
        ct[(1, 1)].max(0.0).sqrt(),
        ct[(2, 2)].max(0.0).sqrt(),
    ]
}

/// Pose at `t` from time-sorted samples: geodesic interpolation, clamped at the ends.
fn interpolate_samples(samples: &[(f64, Pose)], t: f64) -> Pose {
    let n = samples.len();
    if n == 0 {
        return Pose::identity();
    }
    let i = samples.partition_point(|s| s.0 <= t);
    if i == 0 {
        return samples[0].1;
    }
    if i >= n {
        return samples[n - 1].1;
    }
    let (a, b) = (&samples[i - 1], &samples[i]);
    let s = (t - a.0) / (b.0 - a.0);
    kiwi_core::geometry::interpolate_pose(&a.1, &b.1, s)
}

fn plot_data(
    lenses: &[LensObservations],
    state: &State,
    residuals: &[(usize, usize, f64, nalgebra::Vector2<f64>)],
    imu_res: &[(f64, Vector3<f64>, Vector3<f64>)],
    gyro: &GyroIntegral,
    fps: f64,
) -> PlotData {
    let mut p = PlotData {
        corner_residuals: vec![Vec::new(); lenses.len()],
        corner_vectors: vec![Vec::new(); lenses.len()],
        ..PlotData::default()
    };
    for (l, _, t, r) in residuals {
        p.corner_residuals[*l].push((*t, r.norm()));
        p.corner_vectors[*l].push((r.x, r.y));
    }
    p.imu_residuals = kiwi_plot::decimate(imu_res, MAX_PLOTTED_IMU_RESIDUALS)
        .iter()
        .map(|(t, g, a)| (*t, g.norm(), a.norm()))
        .collect();
    for (l, obs) in lenses.iter().enumerate() {
        let d = state.lenses[l].time_shift_s;
        p.rates.push(
            observe::camera_rates(&obs.frames, fps)
                .iter()
                .filter_map(|r| {
                    gyro.mean(r.t0 + d, r.t1 + d)
                        .map(|(_, m)| (0.5 * (r.t0 + r.t1), r.omega.norm(), m))
                })
                .collect(),
        );
    }
    p
}
