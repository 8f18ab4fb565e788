//! Per-tool calibration (run once per tool and unit): the pose of the dot plane in the
//! front-lens frame from the body ArUco tag, and the hinge and jaw direction from the jaw dots.
//!
//! 1. **Tag.** In every searched frame the tag is detected on a virtual perspective view aimed
//!    at it ([`super::aruco`]); its corners are bearing vectors. One `front_from_tag` is fitted
//!    to all frames' corners at once (Gauss–Newton on the angle between each observed bearing
//!    and the predicted corner direction; the tool is rigid on the camera), starting from the
//!    definition's CAD pose. Per-frame fits give the scatter reported in the artifact.
//! 2. **Plane.** The tag is printed in the jaw plane, `face_offset_m` in front of it, top edge
//!    along the jaws; so the tag gives the plane's normal and depth, the jaw direction and,
//!    through `behind_hinge_m`, a first hinge.
//! 3. **Hinge.** With that plane, the per-frame dots are fitted with one free line per jaw.
//!    Chopstick: the hinge is the least-squares intersection of all jaw lines over all frames
//!    (openings differ, so the lines fan out from the pivot) and the jaw direction is their
//!    mean bisector. Parallel jaw: the direction is the mean plate direction, the rail centre
//!    lies midway between the plates, and the dots' offsets from their slots place it along
//!    the jaws. Repeated twice, as the dot-to-slot assignment depends on the hinge.

use std::path::Path;

use kiwi_core::camera::{Camera, CameraModel};
use kiwi_core::layout::{FrameRecord, ToolKind};
use kiwi_core::tool::{
    TOOL_CALIBRATION_SCHEMA_VERSION, ToolCalibration, ToolCalibrationQuality, ToolDefinition,
    TransformDef, body_frame,
};
use nalgebra::{
    Isometry3, Matrix2, Matrix3, Matrix6, Rotation3, Translation3, UnitQuaternion, Vector2,
    Vector3, Vector6,
};
use rayon::prelude::*;

use super::aruco::{TagDetector, TagView, project_bearing};
use super::estimate::{GripperEstimator, ImageView, JawDots, JawLine, fit_line};
use crate::error::{BackendError, Result};
use crate::frames::FrameSource;

/// The virtual tag view covers this many tag half-diagonals around the nominal tag centre:
/// room for a tool mounted several millimetres and degrees off its CAD pose.
const VIEW_MARGIN: f64 = 3.0;
/// Virtual-view pixels per source pixel at the tag: the detector's corner refinement works
/// better with a few more pixels per tag cell than a 190° lens gives.
const VIEW_UPSAMPLE: f64 = 2.0;
/// Gauss–Newton iterations of the tag pose (it converges in 3–5 from the CAD pose).
const POSE_ITERATIONS: usize = 15;
/// A frame whose own tag fit leaves corners this far off (source px, RMS) is a misdetection.
const MAX_FRAME_RMS_PX: f64 = 2.0;
/// Fewest frames with the tag for a calibration.
const MIN_TAG_FRAMES: usize = 3;
/// Fewest jaw lines (one per jaw and frame) for the hinge refinement.
const MIN_JAW_LINES: usize = 6;
/// Fewest dots on a jaw for its line to enter the hinge refinement: short lines point poorly.
const MIN_LINE_DOTS: usize = 4;
/// The chopstick's hinge from line intersections needs lines at least this far from parallel
/// (smallest eigenvalue of the normal equations per line, i.e. sin² of their spread).
const MIN_INTERSECTION_SPREAD: f64 = 1e-3;
/// Hinge refinement passes (the dot-to-slot assignment depends on the hinge).
const HINGE_PASSES: usize = 2;
/// A refined hinge further than this from the tag's (m) means the dots were misread.
const MAX_HINGE_SHIFT_M: f64 = 0.01;

/// Tag corners of one frame as bearings.
type Corners = [Vector3<f64>; 4];
/// A decoded frame: width, height, BGR bytes.
type Frame = (usize, usize, Vec<u8>);

/// Options of a tool calibration.
#[derive(Debug, Clone)]
pub struct CalibrateOptions {
    /// Frames searched for the tag and dots, spread evenly over the recording.
    pub max_frames: usize,
    /// Unit id written into the artifact.
    pub unit_id: String,
    /// Lens name written into the artifact.
    pub lens: String,
    /// Date of the unit calibration used.
    pub unit_calibration_date: String,
}

/// The tag's corners in its own frame (x along the printed rows, y printed up, z out of the
/// face), in OpenCV's corner order: top-left, top-right, bottom-right, bottom-left.
fn tag_corners(size: f64) -> [Vector3<f64>; 4] {
    let h = size / 2.0;
    [
        Vector3::new(-h, h, 0.0),
        Vector3::new(h, h, 0.0),
        Vector3::new(h, -h, 0.0),
        Vector3::new(-h, -h, 0.0),
    ]
}

/// The definition's (CAD) `front_from_tag`: face centre, y along the jaws, z towards the camera.
pub fn nominal_front_from_tag(def: &ToolDefinition) -> Isometry3<f64> {
    let d0 = def.jaw_direction();
    let n = def.plane_normal();
    let centre = def.hinge() - d0 * def.marker.behind_hinge_m - n * def.marker.face_offset_m;
    let z = -n;
    let y = d0;
    let x = y.cross(&z);
    Isometry3::from_parts(
        Translation3::from(centre),
        UnitQuaternion::from_matrix(&Matrix3::from_columns(&[x, y, z])),
    )
}

/// Two unit vectors spanning the plane perpendicular to `b`.
fn tangent_basis(b: &Vector3<f64>) -> (Vector3<f64>, Vector3<f64>) {
    let helper = if b.x.abs() < 0.9 {
        Vector3::x()
    } else {
        Vector3::y()
    };
    let t1 = b.cross(&helper).normalize();
    (t1, b.cross(&t1))
}

/// Angular residuals of corners (tag frame) seen along bearings, for a pose.
fn residuals(
    pose: &Isometry3<f64>,
    corners: &[Vector3<f64>; 4],
    obs: &[[Vector3<f64>; 4]],
    out: &mut Vec<f64>,
) {
    out.clear();
    for frame in obs {
        for (x, b) in corners.iter().zip(frame) {
            let p = (pose * nalgebra::Point3::from(*x)).coords.normalize();
            let (t1, t2) = tangent_basis(b);
            out.push(t1.dot(&p));
            out.push(t2.dot(&p));
        }
    }
}

fn perturb(pose: &Isometry3<f64>, d: &Vector6<f64>) -> Isometry3<f64> {
    let rot = UnitQuaternion::from_scaled_axis(Vector3::new(d[0], d[1], d[2])) * pose.rotation;
    Isometry3::from_parts(
        Translation3::from(pose.translation.vector + Vector3::new(d[3], d[4], d[5])),
        rot,
    )
}

/// Gauss–Newton fit of `front_from_tag` to corner bearings of one or more frames.
pub fn fit_tag_pose(
    start: &Isometry3<f64>,
    size: f64,
    obs: &[[Vector3<f64>; 4]],
) -> Option<Isometry3<f64>> {
    if obs.is_empty() {
        return None;
    }
    let corners = tag_corners(size);
    let mut pose = *start;
    let (mut r0, mut r1) = (Vec::new(), Vec::new());
    let eps = [1e-7, 1e-7, 1e-7, 1e-8, 1e-8, 1e-8];
    for _ in 0..POSE_ITERATIONS {
        residuals(&pose, &corners, obs, &mut r0);
        let mut jac = vec![[0.0; 6]; r0.len()];
        for (k, e) in eps.iter().enumerate() {
            let mut d = Vector6::zeros();
            d[k] = *e;
            residuals(&perturb(&pose, &d), &corners, obs, &mut r1);
            for (row, (a, b)) in jac.iter_mut().zip(r1.iter().zip(&r0)) {
                row[k] = (a - b) / e;
            }
        }
        let mut jtj = Matrix6::zeros();
        let mut jtr = Vector6::zeros();
        for (row, r) in jac.iter().zip(&r0) {
            let j = Vector6::from_row_slice(row);
            jtj += j * j.transpose();
            jtr += j * *r;
        }
        // A little damping keeps the first step sane from a rough start.
        for k in 0..6 {
            jtj[(k, k)] *= 1.0 + 1e-6;
        }
        let step = jtj.cholesky()?.solve(&(-jtr));
        pose = perturb(&pose, &step);
        if step.norm() < 1e-12 {
            break;
        }
    }
    pose.translation
        .vector
        .iter()
        .all(|v| v.is_finite())
        .then_some(pose)
}

/// RMS distance (source px) between observed and predicted tag corners.
fn reprojection_rms(
    camera: &Camera,
    pose: &Isometry3<f64>,
    size: f64,
    obs: &[[Vector3<f64>; 4]],
) -> f64 {
    let corners = tag_corners(size);
    let (mut sum, mut n) = (0.0, 0usize);
    for frame in obs {
        for (x, b) in corners.iter().zip(frame) {
            let p = (pose * nalgebra::Point3::from(*x)).coords;
            if let (Some(a), Some(o)) = (camera.project(&p), project_bearing(camera, b)) {
                sum += (a - o).norm_squared();
                n += 1;
            }
        }
    }
    if n == 0 {
        f64::NAN
    } else {
        (sum / n as f64).sqrt()
    }
}

/// Frames spread evenly over the recording, at most `max`.
/// Indices of at most `max` frames spread evenly over `n`.
fn spread(n: usize, max: usize) -> Vec<usize> {
    let m = max.max(1).min(n);
    (0..m).map(|k| k * n / m).collect()
}

/// A definition whose plane, jaw direction and hinge come from a body frame.
fn with_body(
    def: &ToolDefinition,
    hinge: Vector3<f64>,
    d0: Vector3<f64>,
    n: Vector3<f64>,
) -> ToolDefinition {
    let mut d = def.clone();
    let f = body_frame(hinge, d0, n);
    let x = f.rotation * Vector3::x();
    let y = f.rotation * Vector3::y();
    d.hinge.in_front_m = hinge.into();
    d.hinge.jaw_direction = x.into();
    d.hinge.plane_normal = y.into();
    d
}

/// Result of one hinge-refinement pass, in the pass's plane coordinates (m, rad).
struct HingeStep {
    du: f64,
    dv: f64,
    rotation: f64,
    lines: usize,
    rms: f64,
}

/// Angle of a jaw line from the plane's u axis (rad).
fn line_angle(l: &JawLine) -> f64 {
    l.direction[1].atan2(l.direction[0])
}

/// Hinge and jaw-direction correction from the dots of many frames (plane coordinates of the
/// estimator's current plane).
fn hinge_step(est: &GripperEstimator, kind: ToolKind, obs: &[JawDots]) -> Option<HingeStep> {
    let mut lines = Vec::new();
    let mut slot_offsets = Vec::new();
    let mut bisectors = Vec::new();
    for o in obs {
        let mut pair = Vec::new();
        for jaw in &o.jaws {
            if jaw.len() < MIN_LINE_DOTS {
                continue;
            }
            let pts: Vec<[f64; 2]> = jaw.iter().map(|(_, p)| *p).collect();
            if let Some(l) = fit_line(&pts, None) {
                pair.push(l);
            }
            for (k, p) in jaw {
                if let Some(s) = est.slots().get(*k) {
                    slot_offsets.push(p[0] - s);
                }
            }
        }
        if let [a, b] = pair[..] {
            bisectors.push((line_angle(&a) + line_angle(&b)) / 2.0);
        }
        lines.extend(pair.iter().copied());
    }
    if lines.len() < MIN_JAW_LINES {
        return None;
    }
    let rms = (lines.iter().map(|l| l.rms * l.rms).sum::<f64>() / lines.len() as f64).sqrt();
    let mean_angle = lines.iter().map(line_angle).sum::<f64>() / lines.len() as f64;
    match kind {
        ToolKind::Chopstick => {
            // Least-squares point closest to all lines: Σ (I − d dᵀ)(h − p) = 0.
            let mut a = Matrix2::zeros();
            let mut b = Vector2::zeros();
            for l in &lines {
                let d = Vector2::from(l.direction);
                let m = Matrix2::identity() - d * d.transpose();
                a += m;
                b += m * Vector2::from(l.point);
            }
            let eig = a.symmetric_eigenvalues();
            if eig.min() / lines.len() as f64 <= MIN_INTERSECTION_SPREAD {
                return None;
            }
            let h = a.try_inverse()? * b;
            // The jaws open symmetrically about the closed direction: their bisector.
            if bisectors.is_empty() {
                return None;
            }
            Some(HingeStep {
                du: h.x,
                dv: h.y,
                rotation: bisectors.iter().sum::<f64>() / bisectors.len() as f64,
                lines: lines.len(),
                rms,
            })
        }
        _ => {
            // The plates run along the jaw direction; the rail centre is midway between them at
            // the plates' middle, and the dot row's offset from its slots places it along u.
            let u_mid = (est.slots().first().copied().unwrap_or(0.0)
                + est.slots().last().copied().unwrap_or(0.0))
                / 2.0;
            let v_at = |l: &JawLine| {
                l.point[1] + (u_mid - l.point[0]) * l.direction[1] / l.direction[0].max(1e-9)
            };
            let mut mids = Vec::new();
            for o in obs {
                let fitted: Vec<_> = o
                    .jaws
                    .iter()
                    .filter(|j| j.len() >= MIN_LINE_DOTS)
                    .filter_map(|j| fit_line(&j.iter().map(|(_, p)| *p).collect::<Vec<_>>(), None))
                    .collect();
                if fitted.len() == 2 {
                    mids.push((v_at(&fitted[0]) + v_at(&fitted[1])) / 2.0);
                }
            }
            if mids.is_empty() || slot_offsets.is_empty() {
                return None;
            }
            Some(HingeStep {
                du: slot_offsets.iter().sum::<f64>() / slot_offsets.len() as f64,
                dv: mids.iter().sum::<f64>() / mids.len() as f64,
                rotation: mean_angle,
                lines: lines.len(),
                rms,
            })
        }
    }
}

/// One jaw's dots in one frame, for the plane fit: each dot's distance from the hinge along the
/// jaw (its slot) and its bearing in the lens frame.
struct JawObs {
    slots: Vec<f64>,
    bearings: Vec<Vector3<f64>>,
    /// Starting value of the jaw's own parameter (chopstick: angle from `e_u`, rad; parallel
    /// jaw: the plate's dot-line offset along `e_v`, m).
    start: f64,
    /// Frame index (pairs the two jaws of a frame).
    frame: usize,
}

/// The dot plane as a body frame: origin on the dotted face under the hinge, axes `e_u`
/// (closed jaws), `e_v`, `n` (right-handed, `n` away from the camera).
#[derive(Debug, Clone, Copy)]
struct PlaneBody {
    origin: Vector3<f64>,
    rotation: Rotation3<f64>,
}

impl PlaneBody {
    /// The body moved by `d` = (rotation in its own axes, translation in its own axes).
    fn moved(&self, d: &Vector6<f64>) -> Self {
        let r = Rotation3::from_scaled_axis(Vector3::new(d[0], d[1], d[2]));
        Self {
            origin: self.origin + self.rotation * Vector3::new(d[3], d[4], d[5]),
            rotation: self.rotation * r,
        }
    }
}

/// A dot's position in the plane body frame: `s` along its jaw, with the jaw's parameter `p`.
fn body_dot(kind: ToolKind, s: f64, p: f64) -> Vector3<f64> {
    match kind {
        ToolKind::Chopstick => Vector3::new(s * p.cos(), s * p.sin(), 0.0),
        _ => Vector3::new(s, p, 0.0),
    }
}

/// Pose components of the plane fit left free. The chopstick's per-jaw angles absorb a turn
/// about the normal, the parallel jaw's per-plate offsets a shift across the jaws: those are
/// fixed afterwards from the jaws' mean (bisector, midline).
fn free_pose(kind: ToolKind) -> [usize; 5] {
    match kind {
        ToolKind::Chopstick => [0, 1, 3, 4, 5],
        _ => [0, 1, 2, 3, 5],
    }
}

/// Angular residual (2 components) of a body point against an observed bearing.
fn bearing_residual(body: &PlaneBody, x: &Vector3<f64>, b: &Vector3<f64>) -> [f64; 2] {
    let p = (body.origin + body.rotation * x).normalize();
    let (t1, t2) = tangent_basis(b);
    [t1.dot(&p), t2.dot(&p)]
}

/// Plane-fit iterations (Gauss–Newton with a little damping; converges in 3–6).
const PLANE_ITERATIONS: usize = 20;
/// A dot whose residual exceeds this many times the fit's RMS is dropped and the fit rerun
/// (a misread or half-occluded dot).
const PLANE_OUTLIER_RMS: f64 = 4.0;

/// Result of the joint dot-plane fit.
struct PlaneFit {
    body: PlaneBody,
    /// Per-jaw parameters, aligned with the observations.
    params: Vec<f64>,
    /// RMS of the dots' distance from their modelled position, across the ray (m).
    rms_m: f64,
}

/// Joint fit of the dot plane's pose (tilt, depth, in-plane position) and every jaw's own
/// parameter to the dots' bearings over all frames: the dots sit at known distances along
/// each jaw (their slots), so their spacing fixes the depth and foreshortening the tilt,
/// independently of the body tag (whose corners carry a small systematic bias).
fn fit_plane(kind: ToolKind, start: PlaneBody, jaws: &[JawObs]) -> Option<PlaneFit> {
    let free = free_pose(kind);
    let m = jaws.len();
    let np = free.len() + m;
    let mut body = start;
    let mut params: Vec<f64> = jaws.iter().map(|j| j.start).collect();
    let mut keep: Vec<Vec<bool>> = jaws.iter().map(|j| vec![true; j.slots.len()]).collect();
    let eps = 1e-7;
    let mut rms_angle = f64::NAN;
    for round in 0..2 {
        for _ in 0..PLANE_ITERATIONS {
            let mut jtj = nalgebra::DMatrix::<f64>::zeros(np, np);
            let mut jtr = nalgebra::DVector::<f64>::zeros(np);
            let mut cols = [0usize; 6];
            for (jl, jaw) in jaws.iter().enumerate() {
                for (k, (s, b)) in jaw.slots.iter().zip(&jaw.bearings).enumerate() {
                    if !keep[jl][k] {
                        continue;
                    }
                    let x = body_dot(kind, *s, params[jl]);
                    let r0 = bearing_residual(&body, &x, b);
                    let mut jac = [[0.0; 6]; 2];
                    for (c, &q) in free.iter().enumerate() {
                        let mut d = Vector6::zeros();
                        d[q] = eps;
                        let r1 = bearing_residual(&body.moved(&d), &x, b);
                        jac[0][c] = (r1[0] - r0[0]) / eps;
                        jac[1][c] = (r1[1] - r0[1]) / eps;
                        cols[c] = c;
                    }
                    let x1 = body_dot(kind, *s, params[jl] + eps);
                    let r1 = bearing_residual(&body, &x1, b);
                    jac[0][5] = (r1[0] - r0[0]) / eps;
                    jac[1][5] = (r1[1] - r0[1]) / eps;
                    cols[5] = free.len() + jl;
                    for (row, r) in jac.iter().zip(r0) {
                        for (&ca, &ja) in cols.iter().zip(row) {
                            jtr[ca] += ja * r;
                            for (&cc, &jc) in cols.iter().zip(row) {
                                jtj[(ca, cc)] += ja * jc;
                            }
                        }
                    }
                }
            }
            for k in 0..np {
                jtj[(k, k)] *= 1.0 + 1e-6;
            }
            let step = jtj.cholesky()?.solve(&(-jtr));
            let mut d = Vector6::zeros();
            for (c, &q) in free.iter().enumerate() {
                d[q] = step[c];
            }
            body = body.moved(&d);
            for (p, st) in params.iter_mut().zip(step.iter().skip(free.len())) {
                *p += st;
            }
            if step.norm() < 1e-12 {
                break;
            }
        }
        // Residuals: RMS angle, then drop outliers once.
        let mut res = Vec::new();
        for (jl, jaw) in jaws.iter().enumerate() {
            for (k, (s, b)) in jaw.slots.iter().zip(&jaw.bearings).enumerate() {
                let r = bearing_residual(&body, &body_dot(kind, *s, params[jl]), b);
                res.push((jl, k, r[0].hypot(r[1])));
            }
        }
        let used: Vec<f64> = res
            .iter()
            .filter(|(j, k, _)| keep[*j][*k])
            .map(|r| r.2)
            .collect();
        rms_angle = (used.iter().map(|r| r * r).sum::<f64>() / used.len().max(1) as f64).sqrt();
        if round == 0 {
            for (j, k, r) in res {
                keep[j][k] = r <= PLANE_OUTLIER_RMS * rms_angle;
            }
        }
    }
    let depth = jaws
        .iter()
        .flat_map(|j| j.slots.iter().zip(&j.bearings).map(|(s, _)| *s))
        .map(|s| (body.origin + body.rotation * Vector3::new(s, 0.0, 0.0)).norm())
        .sum::<f64>()
        / jaws.iter().map(|j| j.slots.len()).sum::<usize>().max(1) as f64;
    (body.origin.iter().all(|v| v.is_finite()) && params.iter().all(|v| v.is_finite())).then_some(
        PlaneFit {
            body,
            params,
            rms_m: rms_angle * depth,
        },
    )
}

/// The plane body of the estimator's current dot plane.
fn plane_body(est: &GripperEstimator) -> PlaneBody {
    let plane = est.rectifier().plane();
    let (e_u, e_v) = (Vector3::from(plane.e_u), Vector3::from(plane.e_v));
    PlaneBody {
        origin: Vector3::from(plane.origin),
        rotation: Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[
            e_u,
            e_v,
            e_u.cross(&e_v),
        ])),
    }
}

/// Jaw observations for the plane fit from per-frame dots (plane coordinates of `est`).
fn jaw_observations(est: &GripperEstimator, kind: ToolKind, obs: &[JawDots]) -> Vec<JawObs> {
    let plane = est.rectifier().plane();
    let mut out = Vec::new();
    for (frame, o) in obs.iter().enumerate() {
        for jaw in &o.jaws {
            if jaw.len() < MIN_LINE_DOTS {
                continue;
            }
            let slots: Vec<f64> = jaw
                .iter()
                .filter_map(|(k, _)| est.slots().get(*k).copied())
                .collect();
            if slots.len() != jaw.len() {
                continue;
            }
            let bearings = jaw
                .iter()
                .map(|(_, p)| plane.point(p[0], p[1]).normalize())
                .collect();
            let start = match kind {
                ToolKind::Chopstick => {
                    let pts: Vec<[f64; 2]> = jaw.iter().map(|(_, p)| *p).collect();
                    match fit_line(&pts, Some([0.0, 0.0])) {
                        Some(l) => line_angle(&l),
                        None => continue,
                    }
                }
                _ => jaw.iter().map(|(_, p)| p[1]).sum::<f64>() / jaw.len() as f64,
            };
            out.push(JawObs {
                slots,
                bearings,
                start,
                frame,
            });
        }
    }
    out
}

/// Hinge, jaw direction and plane normal from a plane fit: the chopstick's closed direction
/// is the jaws' mean bisector, the parallel jaw's rail centre their mean midline.
fn geometry_from_fit(
    kind: ToolKind,
    fit: &PlaneFit,
    jaws: &[JawObs],
    half_thickness: f64,
) -> Option<(Vector3<f64>, Vector3<f64>, Vector3<f64>)> {
    let mut mids = Vec::new();
    for (a, ja) in jaws.iter().enumerate() {
        for (b, jb) in jaws.iter().enumerate().skip(a + 1) {
            if ja.frame == jb.frame {
                mids.push((fit.params[a] + fit.params[b]) / 2.0);
            }
        }
    }
    if mids.is_empty() {
        return None;
    }
    let mid = mids.iter().sum::<f64>() / mids.len() as f64;
    let r = fit.body.rotation;
    let n = r * Vector3::z();
    let (origin, d0) = match kind {
        ToolKind::Chopstick => (fit.body.origin, r * Vector3::new(mid.cos(), mid.sin(), 0.0)),
        _ => (
            fit.body.origin + r * Vector3::new(0.0, mid, 0.0),
            r * Vector3::x(),
        ),
    };
    Some((origin + n * half_thickness, d0, n))
}

/// Plane-fit passes (each re-rectifies with the refined plane and re-reads the dots).
const PLANE_PASSES: usize = 2;

/// Every loaded frame's dots, assigned to jaws and slots.
fn dots_of(est: &GripperEstimator, loaded: &[(Option<Corners>, Option<Frame>)]) -> Vec<JawDots> {
    loaded
        .par_iter()
        .filter_map(|(_, img)| img.as_ref())
        .map(|(w, h, data)| {
            est.jaw_dots(&ImageView {
                width: *w,
                height: *h,
                data,
                order: super::ChannelOrder::Bgr,
            })
        })
        .collect()
}

/// Calibrate a tool on one lens from a folder of its frames (`frames.csv` + images or video).
pub fn calibrate_tool(
    camera: &Camera,
    def: &ToolDefinition,
    lens_dir: &Path,
    frames: &[FrameRecord],
    options: &CalibrateOptions,
    progress: &(dyn Fn() + Sync),
) -> Result<ToolCalibration> {
    let input = |message: String| BackendError::Input {
        path: lens_dir.to_path_buf(),
        message,
    };
    if def.kind == ToolKind::BareHand {
        return Err(input(
            "the bare-hand cuff has no jaws or dot plane to calibrate".into(),
        ));
    }
    let nominal = nominal_front_from_tag(def);
    let size = def.marker.size_m;
    // Aim the virtual view at the CAD tag with the source's pixel density there.
    let centre = nominal.translation.vector;
    let dist = centre.norm();
    let half_angle = (VIEW_MARGIN * size * std::f64::consts::FRAC_1_SQRT_2 / dist).atan();
    let step = 1e-3;
    let side_dir = (nominal.rotation * Vector3::x()) * step;
    let density = match (
        camera.project(&centre),
        camera.project(&(centre + side_dir)),
    ) {
        (Some(a), Some(b)) => (b - a).norm() / (step / dist),
        _ => {
            return Err(input(
                "the tool's body tag is not in the lens's field of view: check hinge.in_front_m \
                 and marker.behind_hinge_m in the tool definition"
                    .into(),
            ));
        }
    };
    let view = TagView::new(camera, &centre, half_angle, density * VIEW_UPSAMPLE)?;
    let detector = TagDetector::new(&def.marker.dictionary, def.marker.id)?;
    let source = FrameSource::open(lens_dir)?;
    if source.len() != frames.len() {
        return Err(input(format!(
            "{} frames given, the lens folder holds {}; pass the folder's own frames.csv rows",
            frames.len(),
            source.len()
        )));
    }
    let chosen = spread(frames.len(), options.max_frames);
    // Load each chosen frame once: tag corners and the pixels for the dot passes.
    let loaded: Vec<(Option<Corners>, Option<Frame>)> = source.map_color(&chosen, |_, img| {
        let img = img.ok().map(|c| (c.width, c.height, c.bgr));
        let tag = img.as_ref().and_then(|(w, h, data)| {
            detector
                .detect(
                    &view,
                    &ImageView {
                        width: *w,
                        height: *h,
                        data,
                        order: super::ChannelOrder::Bgr,
                    },
                )
                .ok()
                .flatten()
        });
        progress();
        (tag, img)
    });
    // Per-frame fits screen misdetections and give the scatter.
    let mut good: Vec<[Vector3<f64>; 4]> = Vec::new();
    let mut per_frame: Vec<Isometry3<f64>> = Vec::new();
    for obs in loaded.iter().filter_map(|(t, _)| t.as_ref()) {
        let one = std::slice::from_ref(obs);
        if let Some(p) = fit_tag_pose(&nominal, size, one)
            && reprojection_rms(camera, &p, size, one) <= MAX_FRAME_RMS_PX
        {
            good.push(*obs);
            per_frame.push(p);
        }
    }
    if good.len() < MIN_TAG_FRAMES {
        return Err(input(format!(
            "the body tag ({} id {}) was found in {} of {} frames searched, need {MIN_TAG_FRAMES}: \
             record the tool with its tag unobstructed and lit, or check marker.dictionary, \
             marker.id and marker.size_m",
            def.marker.dictionary,
            def.marker.id,
            good.len(),
            chosen.len()
        )));
    }
    let tag = fit_tag_pose(&nominal, size, &good)
        .ok_or_else(|| input("the tag pose fit did not converge".into()))?;
    let tag_rms_px = reprojection_rms(camera, &tag, size, &good);
    let z = tag.rotation * Vector3::z();
    let normal_spread = (per_frame
        .iter()
        .map(|p| (p.rotation * Vector3::z()).angle(&z).powi(2))
        .sum::<f64>()
        / per_frame.len() as f64)
        .sqrt()
        .to_degrees();
    let pos_spread = (per_frame
        .iter()
        .map(|p| (p.translation.vector - tag.translation.vector).norm_squared())
        .sum::<f64>()
        / per_frame.len() as f64)
        .sqrt();

    // The plane and a first hinge from the tag.
    let n = -z;
    let mut d0 = tag.rotation * Vector3::y();
    let mut hinge =
        tag.translation.vector + n * def.marker.face_offset_m + d0 * def.marker.behind_hinge_m;
    let tag_hinge = hinge;
    let (mut jaw_lines, mut dot_rms) = (0usize, None);
    for _ in 0..HINGE_PASSES {
        let current = with_body(def, hinge, d0, n);
        let est = GripperEstimator::new(camera, &current)?;
        let obs = dots_of(&est, &loaded);
        let Some(s) = hinge_step(&est, def.kind, &obs) else {
            break;
        };
        let plane = est.rectifier().plane();
        let (e_u, e_v) = (Vector3::from(plane.e_u), Vector3::from(plane.e_v));
        let moved = hinge + e_u * s.du + e_v * s.dv;
        if (moved - tag_hinge).norm() > MAX_HINGE_SHIFT_M {
            break;
        }
        hinge = moved;
        d0 =
            Rotation3::from_axis_angle(&nalgebra::Unit::new_normalize(e_u.cross(&e_v)), s.rotation)
                * d0;
        jaw_lines = s.lines;
        dot_rms = Some(s.rms);
    }
    // The plane itself from the dots' known spacing over all frames.
    let mut n = n;
    for _ in 0..PLANE_PASSES {
        let current = with_body(def, hinge, d0, n);
        let est = GripperEstimator::new(camera, &current)?;
        let obs = dots_of(&est, &loaded);
        let jaws = jaw_observations(&est, def.kind, &obs);
        if jaws.len() < MIN_JAW_LINES {
            break;
        }
        let Some(fit) = fit_plane(def.kind, plane_body(&est), &jaws) else {
            break;
        };
        let Some((h, d, nn)) = geometry_from_fit(def.kind, &fit, &jaws, def.jaws.half_thickness_m)
        else {
            break;
        };
        if (h - tag_hinge).norm() > MAX_HINGE_SHIFT_M {
            break;
        }
        (hinge, d0, n) = (h, d, nn);
        jaw_lines = jaws.len();
        dot_rms = Some(fit.rms_m);
    }
    let calibrated = with_body(def, hinge, d0, n);
    let body = calibrated.front_from_body();
    let tip = body * def.front_from_body().inverse() * def.cam_from_tip();
    Ok(ToolCalibration {
        schema_version: TOOL_CALIBRATION_SCHEMA_VERSION,
        unit_id: options.unit_id.clone(),
        lens: options.lens.clone(),
        unit_calibration_date: options.unit_calibration_date.clone(),
        definition: def.clone(),
        hinge_in_front_m: calibrated.hinge.in_front_m,
        jaw_direction: calibrated.hinge.jaw_direction,
        plane_normal: calibrated.hinge.plane_normal,
        front_from_tag: TransformDef::from_pose(&tag),
        cam_from_tip: TransformDef::from_pose(&tip),
        quality: ToolCalibrationQuality {
            frames_searched: chosen.len(),
            frames_with_tag: good.len(),
            tag_rms_px,
            tag_normal_spread_deg: normal_spread,
            tag_position_spread_m: pos_spread,
            jaw_lines,
            dot_line_rms_m: dot_rms,
            plane_tilt_from_definition_deg: calibrated
                .plane_normal()
                .angle(&def.plane_normal())
                .to_degrees(),
            jaw_direction_from_definition_deg: calibrated
                .jaw_direction()
                .angle(&def.jaw_direction())
                .to_degrees(),
            hinge_shift_from_definition_m: (calibrated.hinge() - def.hinge()).norm(),
        },
    })
}
