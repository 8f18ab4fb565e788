//! Joint robust Levenberg–Marquardt over a lens's intrinsics and every view's board pose.
//!
//! Residuals are pixel differences `project(cam_from_board · P) − observed`. The camera models
//! project full 3-D directions (no division by z), so a corner 100° off-axis has a residual and
//! a Jacobian like any other. Poses are updated on the left: `R ← exp(δω)·R`, `t ← t + δt`.
//! The normal equations (intrinsics + 6 per view, a few hundred unknowns) are assembled per view
//! in parallel and solved densely by Cholesky.

use nalgebra::{
    DMatrix, DVector, Dyn, Matrix2xX, Matrix3, Matrix6, OMatrix, SMatrix, U6, Vector2, Vector3,
};
use rayon::prelude::*;

use kiwi_core::camera::{Camera, CameraModel};
use kiwi_core::geometry::{Pose, hat, so3_exp};

/// The observations of one view.
#[derive(Debug, Clone)]
pub(crate) struct ViewObs {
    /// Image name.
    pub name: String,
    /// Target point ids.
    pub ids: Vec<u32>,
    /// Board positions (m).
    pub board: Vec<Vector3<f64>>,
    /// Observed pixels.
    pub pixel: Vec<Vector2<f64>>,
    /// Whether each corner takes part.
    pub active: Vec<bool>,
    /// Whether each corner may take part at all (false: its id is repeated in the image);
    /// outlier rejection re-decides `active` among these every round.
    pub usable: Vec<bool>,
    /// Whether the view takes part.
    pub view_active: bool,
}

impl ViewObs {
    pub fn active_count(&self) -> usize {
        self.active.iter().filter(|a| **a).count()
    }
}

/// Largest number of LM iterations per solve; a good start converges in 10–30.
const MAX_ITERATIONS: usize = 200;
/// Relative cost decrease below which the solve has converged.
const COST_TOLERANCE: f64 = 1e-12;
/// Starting and limiting damping of the Levenberg–Marquardt step (relative to diag(H)).
const LAMBDA_START: f64 = 1e-4;
const LAMBDA_MAX: f64 = 1e12;

type Mat2x6 = SMatrix<f64, 2, 6>;

/// Huber cost and weight of a residual norm `s` with threshold `delta` (`None`: least squares).
fn huber(s: f64, delta: Option<f64>) -> (f64, f64) {
    match delta {
        Some(d) if s > d => (2.0 * d * s - d * d, d / s),
        _ => (s * s, 1.0),
    }
}

/// Residual of one corner, or `None` if it does not project.
pub(crate) fn residual(
    camera: &Camera,
    pose: &Pose,
    board: &Vector3<f64>,
    pixel: &Vector2<f64>,
) -> Option<Vector2<f64>> {
    let pc = pose * nalgebra::Point3::from(*board);
    camera.project(&pc.coords).map(|p| p.coords - pixel)
}

struct ViewSystem {
    hii: DMatrix<f64>,
    hip: OMatrix<f64, Dyn, U6>,
    hpp: Matrix6<f64>,
    gi: DVector<f64>,
    gp: SMatrix<f64, 6, 1>,
}

/// Total robust cost, or `None` if an active corner does not project. Per-view costs are
/// computed in parallel but summed in view order, so the result (and every LM decision built on
/// it) does not depend on the number of threads or on work stealing.
pub(crate) fn cost(
    camera: &Camera,
    poses: &[Pose],
    views: &[ViewObs],
    delta: Option<f64>,
) -> Option<f64> {
    let per_view: Vec<Option<f64>> = views
        .par_iter()
        .zip(poses.par_iter())
        .map(|(v, pose)| {
            if !v.view_active {
                return Some(0.0);
            }
            let mut c = 0.0;
            for i in 0..v.board.len() {
                if v.active[i] {
                    let r = residual(camera, pose, &v.board[i], &v.pixel[i])?;
                    c += huber(r.norm(), delta).0;
                }
            }
            Some(c)
        })
        .collect();
    per_view.into_iter().sum()
}

fn view_system(camera: &Camera, pose: &Pose, v: &ViewObs, delta: Option<f64>) -> ViewSystem {
    let ni = camera.params().len();
    let mut s = ViewSystem {
        hii: DMatrix::zeros(ni, ni),
        hip: OMatrix::<f64, Dyn, U6>::zeros(ni),
        hpp: Matrix6::zeros(),
        gi: DVector::zeros(ni),
        gp: SMatrix::zeros(),
    };
    let mut dp = Matrix2xX::zeros(ni);
    let rot: Matrix3<f64> = pose.rotation.to_rotation_matrix().into_inner();
    for i in 0..v.board.len() {
        if !v.active[i] {
            continue;
        }
        let rp = rot * v.board[i];
        let pc = rp + pose.translation.vector;
        let Some((px, jpt)) = camera.project_with_jacobians(&pc, Some(&mut dp)) else {
            continue;
        };
        let r = px.coords - v.pixel[i];
        let (_, w) = huber(r.norm(), delta);
        let jw = jpt * (-hat(&rp));
        let mut jp = Mat2x6::zeros();
        jp.fixed_view_mut::<2, 3>(0, 0).copy_from(&jw);
        jp.fixed_view_mut::<2, 3>(0, 3).copy_from(&jpt);
        s.hii += w * dp.transpose() * &dp;
        s.hip += w * dp.transpose() * jp;
        s.hpp += w * jp.transpose() * jp;
        s.gi += w * dp.transpose() * r;
        s.gp += w * jp.transpose() * r;
    }
    s
}

/// The full normal equations `H δ = −g` at the current state.
fn normal_equations(
    camera: &Camera,
    poses: &[Pose],
    views: &[ViewObs],
    delta: Option<f64>,
    offsets: &[Option<usize>],
    n: usize,
) -> (DMatrix<f64>, DVector<f64>) {
    let ni = camera.params().len();
    let systems: Vec<Option<ViewSystem>> = views
        .par_iter()
        .zip(poses.par_iter())
        .map(|(v, pose)| v.view_active.then(|| view_system(camera, pose, v, delta)))
        .collect();
    let mut h = DMatrix::zeros(n, n);
    let mut g = DVector::zeros(n);
    for (s, off) in systems.iter().zip(offsets) {
        let (Some(s), Some(o)) = (s, off) else {
            continue;
        };
        let o = *o;
        for r in 0..ni {
            for c in 0..ni {
                h[(r, c)] += s.hii[(r, c)];
            }
            for c in 0..6 {
                h[(r, o + c)] += s.hip[(r, c)];
                h[(o + c, r)] += s.hip[(r, c)];
            }
            g[r] += s.gi[r];
        }
        for r in 0..6 {
            for c in 0..6 {
                h[(o + r, o + c)] += s.hpp[(r, c)];
            }
            g[o + r] += s.gp[r];
        }
    }
    (h, g)
}

/// Block offsets of the active views' poses, and the number of unknowns.
fn layout(ni: usize, views: &[ViewObs]) -> (Vec<Option<usize>>, usize) {
    let mut n = ni;
    let offsets = views
        .iter()
        .map(|v| {
            v.view_active.then(|| {
                n += 6;
                n - 6
            })
        })
        .collect();
    (offsets, n)
}

/// What a solve did.
#[derive(Debug, Clone, Copy)]
pub(crate) struct SolveStats {
    /// Accepted iterations.
    pub iterations: usize,
}

/// Minimise the (Huber, threshold `delta` px; `None` = least squares) reprojection cost over
/// the intrinsics and the active views' poses. Active corners that do not project at the start
/// are deactivated first. Returns `None` if nothing could be evaluated.
pub(crate) fn optimize(
    camera: &mut Camera,
    poses: &mut [Pose],
    views: &mut [ViewObs],
    delta: Option<f64>,
) -> Option<SolveStats> {
    for (v, pose) in views.iter_mut().zip(poses.iter()) {
        for i in 0..v.board.len() {
            if v.active[i] && residual(camera, pose, &v.board[i], &v.pixel[i]).is_none() {
                v.active[i] = false;
            }
        }
    }
    let ni = camera.params().len();
    let (offsets, n) = layout(ni, views);
    let mut current = cost(camera, poses, views, delta)?;
    let mut lambda = LAMBDA_START;
    let mut iterations = 0;
    for _ in 0..MAX_ITERATIONS {
        let (h, g) = normal_equations(camera, poses, views, delta, &offsets, n);
        let mut improved = false;
        while lambda < LAMBDA_MAX {
            let mut a = h.clone();
            for d in 0..n {
                a[(d, d)] += lambda * h[(d, d)].max(1e-12) + 1e-15;
            }
            let Some(chol) = a.cholesky() else {
                lambda *= 10.0;
                continue;
            };
            let step = chol.solve(&(-&g));
            let mut trial_cam = camera.clone();
            let new_params: Vec<f64> = camera
                .params()
                .iter()
                .zip(step.iter())
                .map(|(p, d)| p + d)
                .collect();
            if trial_cam.set_params(&new_params).is_err() {
                lambda *= 10.0;
                continue;
            }
            let trial_poses: Vec<Pose> = poses
                .iter()
                .zip(&offsets)
                .map(|(pose, off)| match off {
                    Some(o) => {
                        let dw = Vector3::new(step[*o], step[o + 1], step[o + 2]);
                        let dt = Vector3::new(step[o + 3], step[o + 4], step[o + 5]);
                        Pose::from_parts(
                            (pose.translation.vector + dt).into(),
                            so3_exp(&dw) * pose.rotation,
                        )
                    }
                    None => *pose,
                })
                .collect();
            match cost(&trial_cam, &trial_poses, views, delta) {
                Some(c) if c < current => {
                    let rel = (current - c) / current.max(1e-300);
                    *camera = trial_cam;
                    poses.copy_from_slice(&trial_poses);
                    current = c;
                    lambda = (lambda * 0.3).max(1e-12);
                    improved = true;
                    iterations += 1;
                    if rel < COST_TOLERANCE {
                        return Some(SolveStats { iterations });
                    }
                    break;
                }
                _ => lambda *= 10.0,
            }
        }
        if !improved {
            break;
        }
    }
    Some(SolveStats { iterations })
}

/// Covariance of the intrinsics (marginal over the poses), scaled by `sigma2` (px²), from the
/// least-squares normal matrix at the current state; `None` if it is singular.
pub(crate) fn intrinsics_covariance(
    camera: &Camera,
    poses: &[Pose],
    views: &[ViewObs],
    sigma2: f64,
) -> Option<DMatrix<f64>> {
    let ni = camera.params().len();
    let (offsets, n) = layout(ni, views);
    let (h, _) = normal_equations(camera, poses, views, None, &offsets, n);
    let inv = h.cholesky()?.inverse();
    Some(inv.view((0, 0), (ni, ni)).into_owned() * sigma2)
}
