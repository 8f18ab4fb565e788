//! The marker-referenced pose accuracy protocol (paper §5): two fixed fiducial markers in the
//! workspace give each wrist's front lens reference poses that share nothing with KIWI's maps,
//! and KIWI's published camera trajectory is scored against them.
//!
//! Per wrist, on the front lens's frames where both markers are found:
//! 1. the markers' planar arrangement (`a_from_b`: the second marker in the first's plane, an
//!    offset and a turn) is fitted on the first 40 % of the sequence only, then held fixed;
//! 2. every such frame gets an eight-corner reference pose `marker_from_cam` (both markers'
//!    corners, on bearings, so no pinhole approximation of the 190° lens enters);
//! 3. a fixed-scale rigid alignment `scene_from_marker` is fitted on the first 40 %;
//! 4. after a 10 % gap, the median translation error (ATE) over the last 50 % is the score.
//!
//! Each hand is scored with its own alignment, and both with the left-fitted one (which keeps
//! their estimated relative placement). The sequence is the wrist's published trajectory's time
//! span; a reference is timed at its markers' rows on the rolling shutter and the published
//! trajectory is interpolated to that time.

use std::fmt::Write as _;

use nalgebra::{Point3, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

use kiwi_core::camera::Camera;
use kiwi_core::geometry::{Pose, interpolate_pose};
use kiwi_core::layout::Side;

use crate::error::{BackendError, Result};
use crate::export::{TrajectoryRow, read_trajectory};
use crate::frames::FrameSource;
use crate::head::marker::{
    MarkerFinder, Resolved, SquarePoses, marker_corners, resolve, square_poses,
};
use crate::pipeline::SessionContext;
use crate::pipeline::stages::PUBLISHED_DIR;
use crate::vision::align::{Sim3, umeyama};
use crate::vision::geometry::{refine_absolute_pose, rms_angular_error};

/// Share of the sequence whose observations fit the arrangement and the alignment.
pub const FIT_FRACTION: f64 = 0.4;
/// Where scoring starts: after a gap of 10 % of the sequence, so the fit's frames and the
/// scored ones are not neighbours.
pub const SCORE_FROM_FRACTION: f64 = 0.5;
/// The paper's printed markers' black-square side (m).
pub const PAPER_MARKER_SIZE_M: f64 = 0.058;
/// Smallest marker (px, square root of its area on the fisheye image) whose corners enter a
/// reference: below this the detector's corners err by a good part of a pixel.
pub const MIN_PAIR_MARKER_SIZE_PX: f64 = 15.0;
/// Fewest frames of the first 40 % with both markers clearly posed that fit the arrangement.
pub const MIN_ARRANGEMENT_FRAMES: usize = 5;
/// Fewest reference frames of the first 40 % that fit the alignment (three fix it; more keep a
/// few poor references from tilting it).
pub const MIN_ALIGNMENT_FRAMES: usize = 10;
/// Largest RMS angle (rad) between the eight corners' bearings and a reference pose's: about a
/// pixel at 960 px on a 190° lens. A worse fit is a misdetection or a blurred frame and is no
/// reference.
pub const MAX_REFERENCE_RMS_RAD: f64 = 0.004;
/// Huber scale of the eight-corner pose (rad): a third of a pixel at 960 px.
const REFERENCE_HUBER_RAD: f64 = 1e-3;
/// Rounds of the arrangement fit (poses given the arrangement, then the arrangement given the
/// poses); the arrangement settles in two or three.
const ARRANGEMENT_ROUNDS: usize = 4;
/// Gauss-Newton iterations of each arrangement update.
const ARRANGEMENT_ITERATIONS: usize = 6;
/// A previous reference newer than this (s) seeds the next frame's pose.
const PREVIOUS_REFERENCE_MAX_AGE_S: f64 = 0.25;
/// Neighbouring references at most this far apart (s) give the camera's velocity for the
/// rolling-shutter correction: three frames at 30 Hz.
const MAX_VELOCITY_GAP_S: f64 = 0.1;
/// The published trajectory is interpolated between rows at most this far apart (s): three
/// frames at 30 Hz.
const MAX_ROW_GAP_S: f64 = 0.1;

/// The two fixed markers.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MarkerPair {
    /// ArUco dictionary (`4x4_50`, ...).
    pub dictionary: String,
    /// The markers' ids; the first is the reference marker whose frame the references are in.
    pub ids: [usize; 2],
    /// Black-square side of both (m).
    pub size_m: f64,
}

/// One front frame where both markers were found.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PairSighting {
    /// Frame index in the stream.
    pub frame: usize,
    /// When the markers' rows were exposed, on the camera's clock (s): the frame's timestamp
    /// plus the readout up to the mean of the two markers' centre rows.
    pub t_camera: f64,
    /// Each marker's corners as bearings (lens frame, OpenCV's corner order).
    pub corners: [[Vector3<f64>; 4]; 2],
    /// When each corner was exposed, relative to `t_camera` (s): its row on the rolling shutter.
    pub corner_dt: [[f64; 4]; 2],
    /// Each marker's two IPPE poses (`cam_from_marker`), when the corners form a square's image.
    pub poses: [Option<SquarePoses>; 2],
}

/// What became of a front stream's frames.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct PairCounts {
    /// Frames searched.
    pub frames: usize,
    /// Frames where the first marker was found.
    pub first_found: usize,
    /// Frames where the second marker was found.
    pub second_found: usize,
    /// Frames where both were found, large enough to use.
    pub both: usize,
}

/// The markers' planar arrangement: the second marker in the first's frame, in its plane.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Arrangement {
    /// The second marker's centre along the first's x (m).
    pub x_m: f64,
    /// ... along its y (m).
    pub y_m: f64,
    /// The second marker's turn about the first's normal (rad).
    pub yaw_rad: f64,
    /// Frames it was fitted on.
    pub frames: usize,
    /// Median distance of the second marker's single-marker poses from the first's plane (m):
    /// a figure of centimetres says the markers do not lie in one plane.
    pub out_of_plane_m: f64,
    /// RMS angle of all eight corners over the fitted frames after the fit (rad).
    pub rms_rad: f64,
}

/// The pose of a marker lying in another's plane at `(x, y)` turned by `yaw` about its normal.
fn planar_pose(x: f64, y: f64, yaw: f64) -> Pose {
    Pose::from_parts(
        Translation3::new(x, y, 0.0),
        UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw),
    )
}

impl Arrangement {
    /// `a_from_b`.
    pub fn a_from_b(&self) -> Pose {
        planar_pose(self.x_m, self.y_m, self.yaw_rad)
    }

    fn with(&self, p: &Vector3<f64>) -> Self {
        Self {
            x_m: p.x,
            y_m: p.y,
            yaw_rad: p.z,
            ..*self
        }
    }
}

/// Which part of the sequence a frame falls in.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Phase {
    /// The first 40 %: fits the arrangement and the alignment.
    Fit,
    /// The 10 % between: used for nothing.
    Gap,
    /// The last 50 %: scored.
    Score,
}

impl Phase {
    /// Name in files.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Fit => "fit",
            Self::Gap => "gap",
            Self::Score => "score",
        }
    }
}

/// The sequence a wrist is scored over (camera clock, s).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Span {
    /// First published frame.
    pub t0: f64,
    /// Last published frame.
    pub t1: f64,
}

impl Span {
    /// The phase of time `t`.
    pub fn phase(&self, t: f64) -> Phase {
        let f = (t - self.t0) / (self.t1 - self.t0).max(f64::EPSILON);
        if f < FIT_FRACTION {
            Phase::Fit
        } else if f < SCORE_FROM_FRACTION {
            Phase::Gap
        } else {
            Phase::Score
        }
    }
}

/// One frame's reference pose.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Reference {
    /// Index of its sighting.
    pub sighting: usize,
    /// Exposure time on the camera's clock (s).
    pub t_camera: f64,
    /// `marker_from_cam` (the first marker's frame).
    pub marker_from_cam: Pose,
    /// RMS angle of the eight corners (rad).
    pub rms_rad: f64,
}

/// Translation and rotation errors over the scored frames.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Ate {
    /// Scored frames.
    pub frames: usize,
    /// Median translation error (m): the protocol's figure.
    pub median_m: f64,
    /// Mean translation error (m).
    pub mean_m: f64,
    /// RMS translation error (m).
    pub rmse_m: f64,
    /// 90th percentile (m).
    pub p90_m: f64,
    /// Largest (m).
    pub max_m: f64,
    /// Median rotation error (deg).
    pub median_rotation_deg: f64,
}

/// One scored frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FrameError {
    /// Exposure time on the camera's clock (s).
    pub t_camera: f64,
    /// Its phase.
    pub phase: Phase,
    /// The reference camera position in the scene through the wrist's own alignment (m).
    pub reference_scene: Vector3<f64>,
    /// KIWI's camera position (m).
    pub estimate_scene: Vector3<f64>,
    /// The reference pose itself, `marker_from_cam`.
    pub marker_from_cam: Pose,
    /// Translation error with the wrist's own alignment (m).
    pub error_m: f64,
    /// ... with the left-fitted alignment (m), when there is one.
    pub shared_error_m: Option<f64>,
    /// Rotation error with the wrist's own alignment (rad).
    pub rotation_error_rad: f64,
}

/// One wrist's result.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct WristMarkers {
    /// Camera folder name (`left`, `right`).
    pub camera: String,
    /// The sequence.
    pub span: Span,
    /// Detection counts.
    pub counts: PairCounts,
    /// The fitted arrangement.
    pub arrangement: Arrangement,
    /// Frames with a reference pose.
    pub references: usize,
    /// References with a published pose to compare (the others fall outside the trajectory).
    pub compared: usize,
    /// Of those, in the first 40 % (the alignment's frames).
    pub fit_frames: usize,
    /// `scene_from_marker` fitted on them: translation (m) and rotation (xyzw).
    pub scene_from_marker_p: [f64; 3],
    /// Its rotation, as a quaternion `[x, y, z, w]`.
    pub scene_from_marker_q: [f64; 4],
    /// Errors with this wrist's own alignment.
    pub independent: Ate,
    /// Errors with the left-fitted alignment.
    pub shared: Option<Ate>,
    /// Every frame with a reference and a published pose, each with its phase (the figures
    /// count the scored ones).
    #[serde(skip)]
    pub errors: Vec<FrameError>,
}

/// The evaluation of one episode.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MarkerEvaluation {
    /// Episode name.
    pub episode: String,
    /// The markers.
    pub markers: MarkerPair,
    /// How the alignments were fitted.
    pub alignment: AlignmentKind,
    /// Each wrist's result, left first.
    pub wrists: Vec<WristMarkers>,
    /// Wrists left out, each with the reason.
    pub skipped: std::collections::BTreeMap<String, String>,
}

fn estimation(message: String) -> BackendError {
    BackendError::Estimation(message)
}

/// Find both markers in every frame of a front stream (frames in parallel). `readout_s` is the
/// recording mode's rolling readout (0 for a global shutter); `tick` is called once per frame.
pub fn find_pairs(
    source: &FrameSource,
    camera: &Camera,
    pair: &MarkerPair,
    readout_s: f64,
    tick: &(dyn Fn() + Sync),
) -> Result<(Vec<PairSighting>, PairCounts)> {
    let finders = [
        MarkerFinder::new(camera.clone(), &pair.dictionary, pair.ids[0])?,
        MarkerFinder::new(camera.clone(), &pair.dictionary, pair.ids[1])?,
    ];
    let indices: Vec<usize> = (0..source.len()).collect();
    type Found = [Option<([Vector3<f64>; 4], [f64; 4])>; 2];
    let per_frame: Vec<Result<Found>> = source.map_color(&indices, |_, image| {
        let result = (|| {
            let image = image?;
            let mut found: Found = [None, None];
            for (slot, finder) in found.iter_mut().zip(&finders) {
                if let Some(corners) = finder.find(&image)?
                    && finder.size_px(&corners).unwrap_or(0.0) >= MIN_PAIR_MARKER_SIZE_PX
                {
                    *slot = Some((
                        corners,
                        finder.corner_row_fractions(&corners).unwrap_or([0.5; 4]),
                    ));
                }
            }
            Ok(found)
        })();
        tick();
        result
    });
    let mut counts = PairCounts {
        frames: indices.len(),
        ..PairCounts::default()
    };
    let mut sightings = Vec::new();
    for (frame, (record, found)) in source.frames().iter().zip(per_frame).enumerate() {
        let found = found?;
        counts.first_found += usize::from(found[0].is_some());
        counts.second_found += usize::from(found[1].is_some());
        let [Some((a, rows_a)), Some((b, rows_b))] = found else {
            continue;
        };
        counts.both += 1;
        let mean_row = (rows_a.iter().sum::<f64>() + rows_b.iter().sum::<f64>()) / 8.0;
        sightings.push(PairSighting {
            frame,
            t_camera: record.t + readout_s * mean_row,
            corners: [a, b],
            corner_dt: [
                rows_a.map(|r| readout_s * (r - mean_row)),
                rows_b.map(|r| readout_s * (r - mean_row)),
            ],
            poses: [
                square_poses(&a, pair.size_m)?,
                square_poses(&b, pair.size_m)?,
            ],
        });
    }
    Ok((sightings, counts))
}

/// The eight corners' bearings and their points in the first marker's frame.
fn eight_corners(
    s: &PairSighting,
    a_from_b: &Pose,
    size_m: f64,
) -> ([Vector3<f64>; 8], [Vector3<f64>; 8]) {
    let square = marker_corners(size_m);
    let mut bearings = [Vector3::zeros(); 8];
    let mut points = [Vector3::zeros(); 8];
    for k in 0..4 {
        bearings[k] = s.corners[0][k];
        bearings[k + 4] = s.corners[1][k];
        points[k] = square[k];
        points[k + 4] = (a_from_b * Point3::from(square[k])).coords;
    }
    (bearings, points)
}

/// A frame's eight-corner `cam_from_a` and its RMS angle: refined from every start there is
/// (both IPPE branches of each marker, the previous reference) and the best kept, so neither
/// marker's planar ambiguity decides the pose.
fn eight_corner_pose(
    s: &PairSighting,
    a_from_b: &Pose,
    size_m: f64,
    previous: Option<&Pose>,
) -> Option<(Pose, f64)> {
    let (bearings, points) = eight_corners(s, a_from_b, size_m);
    let b_from_a = a_from_b.inverse();
    let mut starts: Vec<Pose> = Vec::with_capacity(5);
    if let Some(p) = &s.poses[0] {
        starts.extend([p.best.cam_from_marker, p.other.cam_from_marker]);
    }
    if let Some(p) = &s.poses[1] {
        starts.extend([
            p.best.cam_from_marker * b_from_a,
            p.other.cam_from_marker * b_from_a,
        ]);
    }
    starts.extend(previous.copied());
    starts
        .iter()
        .map(|start| {
            let pose = refine_absolute_pose(start, &bearings, &points, REFERENCE_HUBER_RAD);
            (pose, rms_angular_error(&pose, &bearings, &points))
        })
        .filter(|(pose, rms)| {
            rms.is_finite() && pose.translation.vector.iter().all(|v| v.is_finite())
        })
        .min_by(|a, b| a.1.total_cmp(&b.1))
}

/// The second marker's corner residuals (cross products of observed and predicted bearings)
/// over the frames, given each frame's `cam_from_a` and the arrangement `(x, y, yaw)`.
fn arrangement_residuals(
    frames: &[(&PairSighting, Pose)],
    p: &Vector3<f64>,
    size_m: f64,
    out: &mut Vec<f64>,
) {
    out.clear();
    let a_from_b = planar_pose(p.x, p.y, p.z);
    let square = marker_corners(size_m);
    for (s, cam_from_a) in frames {
        for (b, corner) in s.corners[1].iter().zip(&square) {
            let x = (cam_from_a * a_from_b * Point3::from(*corner)).coords;
            let r = b.normalize().cross(&x.normalize());
            out.extend(r.iter());
        }
    }
}

/// Gauss-Newton on `(x, y, yaw)` with each frame's pose held.
fn refine_arrangement(
    frames: &[(&PairSighting, Pose)],
    start: &Vector3<f64>,
    size_m: f64,
) -> Vector3<f64> {
    const STEP: f64 = 1e-6;
    let mut p = *start;
    let (mut r0, mut r_plus, mut r_minus) = (Vec::new(), Vec::new(), Vec::new());
    for _ in 0..ARRANGEMENT_ITERATIONS {
        arrangement_residuals(frames, &p, size_m, &mut r0);
        let mut jtj = nalgebra::Matrix3::<f64>::zeros();
        let mut jtr = Vector3::<f64>::zeros();
        let mut columns = [Vec::new(), Vec::new(), Vec::new()];
        for (k, column) in columns.iter_mut().enumerate() {
            let mut d = Vector3::zeros();
            d[k] = STEP;
            arrangement_residuals(frames, &(p + d), size_m, &mut r_plus);
            arrangement_residuals(frames, &(p - d), size_m, &mut r_minus);
            *column = r_plus
                .iter()
                .zip(&r_minus)
                .map(|(a, b)| (a - b) / (2.0 * STEP))
                .collect();
        }
        for i in 0..r0.len() {
            let j = Vector3::new(columns[0][i], columns[1][i], columns[2][i]);
            jtj += j * j.transpose();
            jtr += j * r0[i];
        }
        let Some(delta) = jtj.try_inverse().map(|inv| -(inv * jtr)) else {
            break;
        };
        p += delta;
        if delta.norm() < 1e-9 {
            break;
        }
    }
    p
}

/// Median of `values` (sorted in place); `None` when empty.
fn median(values: &mut [f64]) -> Option<f64> {
    if values.is_empty() {
        return None;
    }
    values.sort_by(f64::total_cmp);
    let n = values.len();
    Some(if n % 2 == 1 {
        values[n / 2]
    } else {
        0.5 * (values[n / 2 - 1] + values[n / 2])
    })
}

/// Fit the markers' planar arrangement on the sightings of the first 40 % of `span`: a start
/// from the frames where both markers' single-marker poses are clear, then rounds of
/// eight-corner poses and a Gauss-Newton update of the arrangement.
pub fn fit_arrangement(
    sightings: &[PairSighting],
    span: &Span,
    size_m: f64,
) -> Result<Arrangement> {
    let fit: Vec<&PairSighting> = sightings
        .iter()
        .filter(|s| span.phase(s.t_camera) == Phase::Fit)
        .collect();
    let (mut xs, mut ys, mut zs, mut yaws) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    for s in &fit {
        let (Some(a), Some(b)) = (&s.poses[0], &s.poses[1]) else {
            continue;
        };
        let (Resolved::Clear(a), Resolved::Clear(b)) = (resolve(a, None), resolve(b, None)) else {
            continue;
        };
        let a_from_b = a.cam_from_marker.inverse() * b.cam_from_marker;
        let t = a_from_b.translation.vector;
        let m = a_from_b.rotation.to_rotation_matrix();
        xs.push(t.x);
        ys.push(t.y);
        zs.push(t.z.abs());
        yaws.push(m[(1, 0)].atan2(m[(0, 0)]));
    }
    if xs.len() < MIN_ARRANGEMENT_FRAMES {
        return Err(estimation(format!(
            "both markers were clearly posed together in {} frames of the first {:.0} % of the \
             sequence ({} frames saw both); the arrangement needs {MIN_ARRANGEMENT_FRAMES}: keep \
             both markers in the front lens's view early in the episode, closer or larger",
            xs.len(),
            100.0 * FIT_FRACTION,
            fit.len()
        )));
    }
    let frames = xs.len();
    let (x, y, yaw, out_of_plane) = (
        median(&mut xs).unwrap_or(0.0),
        median(&mut ys).unwrap_or(0.0),
        median(&mut yaws).unwrap_or(0.0),
        median(&mut zs).unwrap_or(0.0),
    );
    let mut arrangement = Arrangement {
        x_m: x,
        y_m: y,
        yaw_rad: yaw,
        frames,
        out_of_plane_m: out_of_plane,
        rms_rad: f64::NAN,
    };
    for _ in 0..ARRANGEMENT_ROUNDS {
        let a_from_b = arrangement.a_from_b();
        let posed: Vec<(&PairSighting, Pose)> = fit
            .iter()
            .filter_map(|s| {
                eight_corner_pose(s, &a_from_b, size_m, None)
                    .filter(|(_, rms)| *rms <= MAX_REFERENCE_RMS_RAD)
                    .map(|(pose, _)| (*s, pose))
            })
            .collect();
        if posed.len() < MIN_ARRANGEMENT_FRAMES {
            break;
        }
        let start = Vector3::new(arrangement.x_m, arrangement.y_m, arrangement.yaw_rad);
        arrangement = arrangement.with(&refine_arrangement(&posed, &start, size_m));
        arrangement.frames = posed.len();
    }
    let a_from_b = arrangement.a_from_b();
    let mut rms: Vec<f64> = fit
        .iter()
        .filter_map(|s| eight_corner_pose(s, &a_from_b, size_m, None).map(|(_, r)| r))
        .collect();
    arrangement.rms_rad = median(&mut rms).unwrap_or(f64::NAN);
    Ok(arrangement)
}

/// Every sighting's eight-corner reference pose through the held arrangement; those whose
/// corners the pose does not explain ([`MAX_REFERENCE_RMS_RAD`]) are left out.
///
/// On a rolling shutter each corner is exposed at its own row's time: after a first pass, the
/// camera's motion between neighbouring references moves every corner's observation to the
/// reference's time (at the depth the first pass gives it) and the pose is solved again.
pub fn reference_poses(
    sightings: &[PairSighting],
    arrangement: &Arrangement,
    size_m: f64,
) -> Vec<Reference> {
    let a_from_b = arrangement.a_from_b();
    let first = solve_references(sightings, &a_from_b, size_m);
    let rolling = sightings
        .iter()
        .any(|s| s.corner_dt.iter().flatten().any(|dt| *dt != 0.0));
    if !rolling {
        return first;
    }
    // Each first-pass reference's camera velocity (a body twist per second), from its nearest
    // neighbours in time.
    let twist_at = |i: usize| -> Option<kiwi_core::geometry::Tangent6> {
        let lo = if i > 0 { i - 1 } else { i };
        let hi = if i + 1 < first.len() { i + 1 } else { i };
        let (a, b) = (&first[lo], &first[hi]);
        let dt = b.t_camera - a.t_camera;
        (hi > lo && dt > 0.0 && dt <= MAX_VELOCITY_GAP_S).then(|| {
            kiwi_core::geometry::se3_log(&(a.marker_from_cam.inverse() * b.marker_from_cam)) / dt
        })
    };
    let mut corrected: Vec<PairSighting> = Vec::with_capacity(first.len());
    // Index in `sightings` of each corrected sighting.
    let mut origin = Vec::with_capacity(first.len());
    for (i, r) in first.iter().enumerate() {
        let Some(xi) = twist_at(i) else {
            continue;
        };
        let s = &sightings[r.sighting];
        let cam_from_a = r.marker_from_cam.inverse();
        let (_, points) = eight_corners(s, &a_from_b, size_m);
        let mut moved = *s;
        for m in 0..2 {
            for k in 0..4 {
                // `cam(t_ref)_from_cam(t_ref + dt)`.
                let ref_from_corner = kiwi_core::geometry::se3_exp(&(xi * s.corner_dt[m][k]));
                let depth = (ref_from_corner.inverse()
                    * (cam_from_a * Point3::from(points[4 * m + k])))
                .coords
                .norm();
                moved.corners[m][k] = (ref_from_corner
                    * Point3::from(s.corners[m][k].normalize() * depth))
                .coords
                .normalize();
            }
        }
        corrected.push(moved);
        origin.push(r.sighting);
    }
    let mut second = solve_references(&corrected, &a_from_b, size_m);
    for r in &mut second {
        r.sighting = origin[r.sighting];
    }
    second
}

/// Eight-corner poses of `sightings` (each seeded by the previous reference), kept when they
/// explain the corners.
fn solve_references(sightings: &[PairSighting], a_from_b: &Pose, size_m: f64) -> Vec<Reference> {
    let mut out: Vec<Reference> = Vec::with_capacity(sightings.len());
    for (k, s) in sightings.iter().enumerate() {
        let previous = out
            .last()
            .filter(|r| (s.t_camera - r.t_camera).abs() <= PREVIOUS_REFERENCE_MAX_AGE_S)
            .map(|r| r.marker_from_cam.inverse());
        let Some((cam_from_a, rms)) = eight_corner_pose(s, a_from_b, size_m, previous.as_ref())
        else {
            continue;
        };
        if rms <= MAX_REFERENCE_RMS_RAD {
            out.push(Reference {
                sighting: k,
                t_camera: s.t_camera,
                marker_from_cam: cam_from_a.inverse(),
                rms_rad: rms,
            });
        }
    }
    out
}

/// The published `scene_from_front_cam` at camera time `t`, interpolated between the two rows
/// around it (`None` outside the trajectory or across a gap).
pub fn estimate_at(rows: &[TrajectoryRow], t: f64) -> Option<Pose> {
    let k = rows.partition_point(|r| r.t_camera <= t);
    if k == 0 {
        return None;
    }
    let a = &rows[k - 1];
    if k == rows.len() {
        return ((t - a.t_camera).abs() < 1e-9).then_some(a.scene_from_front_cam);
    }
    let b = &rows[k];
    let dt = b.t_camera - a.t_camera;
    if !(dt > 0.0 && dt <= MAX_ROW_GAP_S) {
        return None;
    }
    Some(interpolate_pose(
        &a.scene_from_front_cam,
        &b.scene_from_front_cam,
        (t - a.t_camera) / dt,
    ))
}

/// A reference paired with KIWI's pose at its time.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Paired {
    /// Exposure time on the camera's clock (s).
    pub t_camera: f64,
    /// Its phase.
    pub phase: Phase,
    /// `marker_from_cam` of the reference.
    pub marker_from_cam: Pose,
    /// KIWI's `scene_from_front_cam`.
    pub scene_from_cam: Pose,
}

/// Pair each reference with the published pose at its time.
pub fn pair_with_estimates(
    references: &[Reference],
    rows: &[TrajectoryRow],
    span: &Span,
) -> Vec<Paired> {
    references
        .iter()
        .filter_map(|r| {
            estimate_at(rows, r.t_camera).map(|scene_from_cam| Paired {
                t_camera: r.t_camera,
                phase: span.phase(r.t_camera),
                marker_from_cam: r.marker_from_cam,
                scene_from_cam,
            })
        })
        .collect()
}

/// How the fixed-scale rigid alignment is fitted.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum AlignmentKind {
    /// On the camera positions alone (Umeyama without scale), as trajectory ATE is usually
    /// aligned: the rotation rests on how far the positions spread.
    #[default]
    Positions,
    /// On whole poses: the rotation from the frames' orientations (the mean of KIWI's
    /// orientation times the reference's inverse), the translation from the positions given it.
    /// Holds the rotation when the fitted stretch of trajectory spans little space.
    Poses,
}

/// The fixed-scale rigid `scene_from_marker` that best maps the references of the first 40 %
/// onto KIWI's poses.
pub fn fit_alignment(paired: &[Paired], kind: AlignmentKind) -> Option<Sim3> {
    let fit: Vec<&Paired> = paired.iter().filter(|p| p.phase == Phase::Fit).collect();
    if fit.len() < MIN_ALIGNMENT_FRAMES {
        return None;
    }
    match kind {
        AlignmentKind::Positions => {
            let (source, target): (Vec<Vector3<f64>>, Vec<Vector3<f64>>) = fit
                .iter()
                .map(|p| {
                    (
                        p.marker_from_cam.translation.vector,
                        p.scene_from_cam.translation.vector,
                    )
                })
                .unzip();
            umeyama(&source, &target, false)
        }
        AlignmentKind::Poses => {
            let rotations: Vec<UnitQuaternion<f64>> = fit
                .iter()
                .map(|p| p.scene_from_cam.rotation * p.marker_from_cam.rotation.inverse())
                .collect();
            let rotation = kiwi_core::geometry::average_rotations(&rotations, None)?;
            let translation = fit
                .iter()
                .map(|p| {
                    p.scene_from_cam.translation.vector
                        - rotation * p.marker_from_cam.translation.vector
                })
                .sum::<Vector3<f64>>()
                / fit.len() as f64;
            Some(Sim3 {
                scale: 1.0,
                rotation,
                translation,
            })
        }
    }
}

/// Every paired frame's error through `scene_from_marker` (the fitted ones' are the fit's
/// residuals; only the scored ones count in the figures).
pub fn frame_errors(paired: &[Paired], scene_from_marker: &Sim3) -> Vec<FrameError> {
    paired
        .iter()
        .map(|p| {
            let reference =
                scene_from_marker.transform_point(&p.marker_from_cam.translation.vector);
            let estimate = p.scene_from_cam.translation.vector;
            let reference_rotation = scene_from_marker.rotation * p.marker_from_cam.rotation;
            FrameError {
                t_camera: p.t_camera,
                phase: p.phase,
                reference_scene: reference,
                estimate_scene: estimate,
                marker_from_cam: p.marker_from_cam,
                error_m: (estimate - reference).norm(),
                shared_error_m: None,
                rotation_error_rad: reference_rotation.angle_to(&p.scene_from_cam.rotation),
            }
        })
        .collect()
}

/// The summary of translation errors (m) and rotation errors (rad).
pub fn ate(errors: &[f64], rotation_errors: &[f64]) -> Option<Ate> {
    if errors.is_empty() {
        return None;
    }
    let mut e = errors.to_vec();
    let n = e.len() as f64;
    let mean = e.iter().sum::<f64>() / n;
    let rmse = (e.iter().map(|v| v * v).sum::<f64>() / n).sqrt();
    let med = median(&mut e)?;
    let p90 = e[((0.9 * (e.len() - 1) as f64).round() as usize).min(e.len() - 1)];
    let max = e[e.len() - 1];
    let mut r = rotation_errors.to_vec();
    Some(Ate {
        frames: errors.len(),
        median_m: med,
        mean_m: mean,
        rmse_m: rmse,
        p90_m: p90,
        max_m: max,
        median_rotation_deg: median(&mut r).unwrap_or(f64::NAN).to_degrees(),
    })
}

/// The figures over the scored frames of `errors`; `None` when none is scored.
fn scored_ate(errors: &[FrameError]) -> Option<Ate> {
    let scored = || errors.iter().filter(|e| e.phase == Phase::Score);
    let translation: Vec<f64> = scored().map(|e| e.error_m).collect();
    let rotation: Vec<f64> = scored().map(|e| e.rotation_error_rad).collect();
    ate(&translation, &rotation)
}

/// One wrist's sightings, arrangement, references and pairs with its published trajectory.
struct WristRun {
    camera: String,
    span: Span,
    counts: PairCounts,
    arrangement: Arrangement,
    references: usize,
    paired: Vec<Paired>,
}

fn wrist_run(
    ctx: &SessionContext,
    episode: &str,
    w: &crate::pipeline::context::WristContext,
    pair: &MarkerPair,
    progress: &(dyn Fn(&str, usize, usize) + Sync),
) -> Result<WristRun> {
    let layout = ctx.episode(episode);
    let published = layout
        .root()
        .join(PUBLISHED_DIR)
        .join(format!("{}.csv", w.camera));
    // A wrist without a published trajectory is left out, not the whole evaluation.
    if !published.is_file() {
        return Err(estimation(format!(
            "{} is missing: the wrist's trajectory is published by `kiwi run`; run it on the \
             session first (or see the episode's quality.json for why it has none)",
            published.display()
        )));
    }
    let rows = read_trajectory(&published)?;
    let (Some(first), Some(last)) = (rows.first(), rows.last()) else {
        return Err(estimation(format!(
            "{} has no rows: the wrist was not reconstructed; see quality.json",
            published.display()
        )));
    };
    let span = Span {
        t0: first.t_camera,
        t1: last.t_camera,
    };
    let camera = w
        .calibration
        .lens("front")
        .ok_or_else(|| BackendError::Input {
            path: w.calibration_path.clone(),
            message: "field `lenses`: no lens named `front`".into(),
        })?
        .camera()?;
    let source = FrameSource::open(&layout.lens_dir(w.camera, "front"))?;
    let readout = 2.0 * crate::pipeline::stages::exposure_centre_delay(ctx, episode, w)?;
    let total = source.len();
    let done = std::sync::atomic::AtomicUsize::new(0);
    let tick = || {
        let d = done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
        progress(w.camera, d, total);
    };
    let (sightings, counts) = find_pairs(&source, &camera, pair, readout, &tick)?;
    let arrangement = fit_arrangement(&sightings, &span, pair.size_m)
        .map_err(|e| estimation(format!("{} front: {e}", w.camera)))?;
    let references = reference_poses(&sightings, &arrangement, pair.size_m);
    let paired = pair_with_estimates(&references, &rows, &span);
    Ok(WristRun {
        camera: w.camera.to_string(),
        span,
        counts,
        arrangement,
        references: references.len(),
        paired,
    })
}

/// Score one wrist with its own alignment and, when given, the left-fitted one.
fn score(
    run: WristRun,
    shared: Option<&Sim3>,
    kind: AlignmentKind,
) -> Result<(WristMarkers, Sim3)> {
    let fit_frames = run.paired.iter().filter(|p| p.phase == Phase::Fit).count();
    let Some(alignment) = fit_alignment(&run.paired, kind) else {
        return Err(estimation(format!(
            "{} front: {fit_frames} reference poses with a published pose in the first {:.0} % \
             of the sequence; the alignment needs {MIN_ALIGNMENT_FRAMES}",
            run.camera,
            100.0 * FIT_FRACTION
        )));
    };
    let mut errors = frame_errors(&run.paired, &alignment);
    let shared_errors = shared.map(|s| frame_errors(&run.paired, s));
    if let Some(shared_errors) = &shared_errors {
        for (e, s) in errors.iter_mut().zip(shared_errors) {
            e.shared_error_m = Some(s.error_m);
        }
    }
    let Some(independent) = scored_ate(&errors) else {
        return Err(estimation(format!(
            "{} front: no reference pose with a published pose in the last {:.0} % of the \
             sequence: nothing to score",
            run.camera,
            100.0 * (1.0 - SCORE_FROM_FRACTION)
        )));
    };
    let shared_ate = shared_errors.as_deref().and_then(scored_ate);
    let q = alignment.rotation.coords;
    Ok((
        WristMarkers {
            camera: run.camera,
            span: run.span,
            counts: run.counts,
            arrangement: run.arrangement,
            references: run.references,
            compared: run.paired.len(),
            fit_frames,
            scene_from_marker_p: alignment.translation.into(),
            scene_from_marker_q: [q.x, q.y, q.z, q.w],
            independent,
            shared: shared_ate,
            errors,
        },
        alignment,
    ))
}

/// Run the protocol on one episode of the session (its outputs from `kiwi run` must exist);
/// `progress(camera, done, total)` reports the marker search.
pub fn evaluate_markers(
    ctx: &SessionContext,
    episode: &str,
    pair: &MarkerPair,
    alignment: AlignmentKind,
    progress: &(dyn Fn(&str, usize, usize) + Sync),
) -> Result<MarkerEvaluation> {
    if !(pair.size_m.is_finite() && pair.size_m > 0.0) || pair.ids[0] == pair.ids[1] {
        return Err(BackendError::Input {
            path: ctx.toml.clone(),
            message: format!(
                "the markers are two distinct ids of a positive size; got ids {:?}, size {} m",
                pair.ids, pair.size_m
            ),
        });
    }
    let Some(size) = crate::gripper::aruco::dictionary_size(&pair.dictionary) else {
        return Err(BackendError::Input {
            path: ctx.toml.clone(),
            message: format!(
                "the markers' dictionary `{}` is not one KIWI reads: use {}",
                pair.dictionary,
                crate::gripper::aruco::DICTIONARY_NAMES
            ),
        });
    };
    if let Some(id) = pair.ids.iter().find(|&&id| id >= size) {
        return Err(BackendError::Input {
            path: ctx.toml.clone(),
            message: format!(
                "marker id {id} is not in dictionary {} (ids 0 to {}): check the printed \
                 markers' ids",
                pair.dictionary,
                size - 1
            ),
        });
    }
    let mut evaluation = MarkerEvaluation {
        episode: episode.to_string(),
        markers: pair.clone(),
        alignment,
        wrists: Vec::new(),
        skipped: std::collections::BTreeMap::new(),
    };
    let mut left_alignment: Option<Sim3> = None;
    for side in [Side::Left, Side::Right] {
        let Some(w) = ctx.wrists.get(&side) else {
            continue;
        };
        let scored = wrist_run(ctx, episode, w, pair, progress).and_then(|run| {
            let shared = if side == Side::Right {
                left_alignment.as_ref()
            } else {
                None
            };
            score(run, shared, alignment)
        });
        match scored {
            Ok((mut result, alignment)) => {
                if side == Side::Left {
                    // The left hand's shared alignment is its own.
                    result.shared = Some(result.independent);
                    for e in &mut result.errors {
                        e.shared_error_m = Some(e.error_m);
                    }
                    left_alignment = Some(alignment);
                }
                evaluation.wrists.push(result);
            }
            Err(e @ BackendError::Input { .. }) => return Err(e),
            Err(e) => {
                evaluation
                    .skipped
                    .insert(w.camera.to_string(), e.to_string());
            }
        }
    }
    Ok(evaluation)
}

/// Every compared frame as CSV: camera, time, phase (`fit`, `gap`, `score`), both positions
/// (m), errors (m, deg).
pub fn errors_csv(evaluation: &MarkerEvaluation) -> String {
    let mut s = String::from(
        "camera,t_camera,phase,ref_x,ref_y,ref_z,est_x,est_y,est_z,error_m,shared_error_m,\
         rotation_error_deg\n",
    );
    for w in &evaluation.wrists {
        for e in &w.errors {
            let (r, p) = (e.reference_scene, e.estimate_scene);
            let _ = writeln!(
                s,
                "{},{:.6},{},{:.6},{:.6},{:.6},{:.6},{:.6},{:.6},{:.6},{},{:.4}",
                w.camera,
                e.t_camera,
                e.phase.as_str(),
                r.x,
                r.y,
                r.z,
                p.x,
                p.y,
                p.z,
                e.error_m,
                e.shared_error_m
                    .map_or(String::new(), |v| format!("{v:.6}")),
                e.rotation_error_rad.to_degrees()
            );
        }
    }
    s
}

/// File names of an episode's record and scored frames in the session's `evaluation/`.
pub fn evaluation_files(episode: &str) -> (String, String) {
    (
        format!("markers-{episode}.json"),
        format!("markers-{episode}.csv"),
    )
}

/// A row of the compared frames' CSV ([`errors_csv`]).
#[derive(Debug, Clone, PartialEq, Deserialize)]
pub struct ScoredFrame {
    /// Camera folder name.
    pub camera: String,
    /// Exposure time on the camera's clock (s).
    pub t_camera: f64,
    /// Its part of the sequence.
    pub phase: Phase,
    /// Error with the wrist's own alignment (m).
    pub error_m: f64,
    /// Error with the left-fitted alignment (m).
    pub shared_error_m: Option<f64>,
}

/// Read the compared frames' CSV.
pub fn read_errors_csv(path: &std::path::Path) -> Result<Vec<ScoredFrame>> {
    let bad = |message: String| BackendError::Input {
        path: path.to_path_buf(),
        message,
    };
    let mut reader = csv::Reader::from_path(path).map_err(|e| {
        bad(format!(
            "cannot open: {e}; run `kiwi evaluate markers` again"
        ))
    })?;
    reader
        .deserialize::<ScoredFrame>()
        .enumerate()
        .map(|(i, row)| {
            row.map_err(|e| {
                bad(format!(
                    "line {}: not a scored frame ({e}); run `kiwi evaluate markers` again",
                    i + 2
                ))
            })
        })
        .collect()
}

/// The result as text: per hand, frames and median errors with both alignments.
pub fn table(evaluation: &MarkerEvaluation) -> String {
    let mut s = format!(
        "{}: marker-referenced accuracy (markers {} and {}, {} mm, {}), median translation ATE \
         on the last {:.0} %\n{:<8} {:>8} {:>10} {:>12} {:>12} {:>10} {:>10}\n",
        evaluation.episode,
        evaluation.markers.ids[0],
        evaluation.markers.ids[1],
        evaluation.markers.size_m * 1e3,
        evaluation.markers.dictionary,
        100.0 * (1.0 - SCORE_FROM_FRACTION),
        "hand",
        "frames",
        "refs",
        "own (mm)",
        "left (mm)",
        "p90 (mm)",
        "rot (deg)"
    );
    for w in &evaluation.wrists {
        let _ = writeln!(
            s,
            "{:<8} {:>8} {:>10} {:>12.2} {:>12} {:>10.2} {:>10.2}",
            w.camera,
            w.counts.frames,
            w.references,
            w.independent.median_m * 1e3,
            w.shared
                .map_or("-".into(), |a| format!("{:.2}", a.median_m * 1e3)),
            w.independent.p90_m * 1e3,
            w.independent.median_rotation_deg
        );
    }
    for w in &evaluation.wrists {
        let a = &w.arrangement;
        let _ = writeln!(
            s,
            "{} arrangement: second marker at ({:.1}, {:.1}) mm, turned {:.2} deg, from {} \
             frames; off the plane {:.1} mm",
            w.camera,
            a.x_m * 1e3,
            a.y_m * 1e3,
            a.yaw_rad.to_degrees(),
            a.frames,
            a.out_of_plane_m * 1e3
        );
    }
    for (camera, why) in &evaluation.skipped {
        let _ = writeln!(s, "{camera}: left out: {why}");
    }
    if evaluation.alignment == AlignmentKind::Positions
        && evaluation
            .wrists
            .iter()
            .filter(|w| w.shared.is_some())
            .count()
            > 1
    {
        let _ = writeln!(
            s,
            "note: the left-fitted figure's rotation rests on how far the left's positions spread \
             over the first 40 %; a fraction of a millimetre of reference error then turns the \
             other hand by up to a millimetre. --align poses holds it by the orientations \
             (docs/evaluate.md)."
        );
    }
    s
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use super::*;

    #[test]
    fn phases_split_the_sequence_at_forty_and_fifty_percent() {
        let span = Span { t0: 10.0, t1: 20.0 };
        assert_eq!(span.phase(10.0), Phase::Fit);
        assert_eq!(span.phase(13.99), Phase::Fit);
        assert_eq!(span.phase(14.0), Phase::Gap);
        assert_eq!(span.phase(14.99), Phase::Gap);
        assert_eq!(span.phase(15.0), Phase::Score);
        assert_eq!(span.phase(20.0), Phase::Score);
    }

    #[test]
    fn the_median_of_an_even_count_is_the_mean_of_the_middle_two() {
        assert_eq!(median(&mut [4.0, 1.0, 3.0, 2.0]), Some(2.5));
        assert_eq!(median(&mut [5.0, 1.0, 3.0]), Some(3.0));
        assert_eq!(median(&mut []), None);
    }

    /// Bearings of the eight corners seen from `cam_from_a`.
    fn sighting(cam_from_a: &Pose, a_from_b: &Pose, size_m: f64) -> PairSighting {
        let square = marker_corners(size_m);
        let see = |p: &Pose| square.map(|c| (cam_from_a * p * Point3::from(c)).coords.normalize());
        let a = see(&Pose::identity());
        let b = see(a_from_b);
        PairSighting {
            frame: 0,
            t_camera: 0.0,
            corners: [a, b],
            corner_dt: [[0.0; 4]; 2],
            poses: [
                square_poses(&a, size_m).unwrap(),
                square_poses(&b, size_m).unwrap(),
            ],
        }
    }

    #[test]
    fn the_arrangement_and_the_eight_corner_pose_are_recovered_from_exact_corners() {
        let size = PAPER_MARKER_SIZE_M;
        let truth = Arrangement {
            x_m: 0.2,
            y_m: -0.05,
            yaw_rad: 0.35,
            frames: 0,
            out_of_plane_m: 0.0,
            rms_rad: 0.0,
        };
        let span = Span { t0: 0.0, t1: 10.0 };
        // A camera 0.3-0.4 m above the markers, looking down at them from varied places.
        let sightings: Vec<PairSighting> = (0..12)
            .map(|k| {
                let t = f64::from(k);
                let eye = Vector3::new(
                    0.1 + 0.05 * (t * 0.7).sin(),
                    -0.25 + 0.02 * t,
                    0.3 + 0.01 * t,
                );
                let target = Vector3::new(0.1, 0.0, 0.0);
                // Camera z towards the markers, x roughly along the markers' x.
                let z = (target - eye).normalize();
                let x = Vector3::y().cross(&z).normalize();
                let y = z.cross(&x);
                let r =
                    nalgebra::Rotation3::from_matrix_unchecked(nalgebra::Matrix3::from_columns(&[
                        x, y, z,
                    ]));
                let a_from_cam = Pose::from_parts(
                    Translation3::from(eye),
                    UnitQuaternion::from_rotation_matrix(&r),
                );
                let mut s = sighting(&a_from_cam.inverse(), &truth.a_from_b(), size);
                s.frame = k as usize;
                s.t_camera = 0.3 * t;
                s
            })
            .collect();
        let fitted = fit_arrangement(&sightings, &span, size).unwrap();
        assert!((fitted.x_m - truth.x_m).abs() < 1e-6, "{fitted:?}");
        assert!((fitted.y_m - truth.y_m).abs() < 1e-6, "{fitted:?}");
        assert!((fitted.yaw_rad - truth.yaw_rad).abs() < 1e-6, "{fitted:?}");
        let refs = reference_poses(&sightings, &fitted, size);
        assert_eq!(refs.len(), sightings.len());
        for r in &refs {
            assert!(r.rms_rad < 1e-6, "{r:?}");
        }
    }
}
