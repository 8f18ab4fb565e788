//! Robust bundle adjustment on unit bearings.
//!
//! Unknowns: camera poses `cam_from_world` (6 DoF each, left-multiplied updates
//! `T ← exp(δ) T`, `δ = [ω; v]`) and world points (3 DoF). Each observation contributes the
//! 2-D tangent-plane residual of [`geometry::tangent_residual`], which equals the angular error
//! to first order and is valid for rays beyond 90° off-axis. A Huber loss (iteratively
//! reweighted) bounds the pull of outliers.
//!
//! Levenberg–Marquardt with the Schur complement: the point blocks are 3×3 and inverted in
//! place, the reduced camera system (dense, 6 per free camera; only its lower triangle is
//! formed, the part the factorization reads) is factored with faer's Cholesky, run sequentially
//! so the result is the same for any thread count. Every sum runs in observation order: the
//! same problem gives bit-identical results.
//!
//! Gauge: monocular BA leaves 7 DoF free (pose of the world and scale). Fix at least one camera;
//! the LM damping keeps the remaining scale direction bounded.

use faer::dyn_stack::{MemBuffer, MemStack};
use faer::{Mat, Par};
use nalgebra::{Matrix2x3, Matrix3, Matrix6, Matrix6x3, Vector3, Vector6};

use kiwi_core::geometry::{Pose, se3_exp};

use crate::error::{BackendError, Result};
use crate::vision::geometry::{
    huber_cost, huber_weight, point_jacobian_left_update, tangent_basis, tangent_residual,
};

/// One observation: camera `camera` sees point `point` along the unit `bearing`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BaObservation {
    /// Index into [`BaProblem::cam_from_world`].
    pub camera: usize,
    /// Index into [`BaProblem::points`].
    pub point: usize,
    /// Measured unit bearing in the camera frame.
    pub bearing: Vector3<f64>,
}

/// A bundle-adjustment problem; solved in place.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct BaProblem {
    /// Camera poses (world to camera).
    pub cam_from_world: Vec<Pose>,
    /// Per camera: held constant (gauge, or outside a local window).
    pub fixed_camera: Vec<bool>,
    /// World points.
    pub points: Vec<Vector3<f64>>,
    /// Per point: held constant.
    pub fixed_point: Vec<bool>,
    /// Observations.
    pub observations: Vec<BaObservation>,
}

/// Options of [`bundle_adjust`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BaOptions {
    /// Huber threshold on the residual norm (rad).
    pub huber_rad: f64,
    /// Largest number of LM iterations (accepted or rejected steps).
    pub max_iterations: usize,
    /// Initial LM damping (relative to the Hessian diagonal).
    pub initial_lambda: f64,
    /// Stop when an accepted step lowers the cost by less than this fraction.
    pub relative_tolerance: f64,
}

impl Default for BaOptions {
    fn default() -> Self {
        Self {
            // ~1.5 px at the X5 lens centre: inliers stay quadratic, outliers grow linearly.
            huber_rad: 0.005,
            max_iterations: 50,
            initial_lambda: 1e-4,
            relative_tolerance: 1e-10,
        }
    }
}

/// What a bundle adjustment did.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct BaReport {
    /// Robust cost before.
    pub initial_cost: f64,
    /// Robust cost after.
    pub final_cost: f64,
    /// RMS angular residual (rad) of all usable observations before.
    pub initial_rms_rad: f64,
    /// RMS angular residual (rad) after.
    pub final_rms_rad: f64,
    /// LM iterations run.
    pub iterations: usize,
    /// Steps accepted.
    pub accepted: usize,
    /// Whether the relative-decrease criterion was met (rather than the iteration cap).
    pub converged: bool,
}

/// Floor of the diagonal used for LM damping, so unconstrained directions are damped too.
const DAMPING_FLOOR: f64 = 1e-9;
/// Largest LM damping before giving up on further improvement.
const MAX_LAMBDA: f64 = 1e12;

fn invalid(message: String) -> BackendError {
    BackendError::Vision {
        context: "bundle adjustment".into(),
        message,
    }
}

impl BaProblem {
    /// Check indices, flags and finiteness.
    pub fn validate(&self) -> Result<()> {
        if self.fixed_camera.len() != self.cam_from_world.len() {
            return Err(invalid(format!(
                "expected one fixed flag per camera ({}), found {}",
                self.cam_from_world.len(),
                self.fixed_camera.len()
            )));
        }
        if self.fixed_point.len() != self.points.len() {
            return Err(invalid(format!(
                "expected one fixed flag per point ({}), found {}",
                self.points.len(),
                self.fixed_point.len()
            )));
        }
        for (i, o) in self.observations.iter().enumerate() {
            if o.camera >= self.cam_from_world.len() || o.point >= self.points.len() {
                return Err(invalid(format!(
                    "observation {i} refers to camera {} / point {} but there are {} cameras and {} points",
                    o.camera,
                    o.point,
                    self.cam_from_world.len(),
                    self.points.len()
                )));
            }
            if !o.bearing.iter().all(|v| v.is_finite()) || (o.bearing.norm() - 1.0).abs() > 1e-6 {
                return Err(invalid(format!(
                    "observation {i}: expected a finite unit bearing, found {:?}",
                    o.bearing
                )));
            }
        }
        if self.points.iter().any(|p| !p.iter().all(|v| v.is_finite())) {
            return Err(invalid("a point is not finite".into()));
        }
        Ok(())
    }
}

/// Robust cost and RMS angle-like residual of the current state.
fn evaluate(problem: &BaProblem, bases: &[Matrix2x3<f64>], huber: f64) -> (f64, f64) {
    let mut cost = 0.0;
    let mut sq = 0.0;
    let mut n = 0usize;
    for (o, basis) in problem.observations.iter().zip(bases) {
        let pc = (problem.cam_from_world[o.camera]
            * nalgebra::Point3::from(problem.points[o.point]))
        .coords;
        match tangent_residual(&o.bearing, basis, &pc) {
            Some((r, _)) => {
                let e = r.norm();
                cost += huber_cost(e, huber);
                sq += e * e;
                n += 1;
            }
            None => cost += huber_cost(std::f64::consts::PI, huber),
        }
    }
    (cost, if n > 0 { (sq / n as f64).sqrt() } else { 0.0 })
}

/// Solve `S x = b` in place for a symmetric positive definite `S` (sequential faer Cholesky;
/// `b` becomes `x`); false when the factorization fails or the solution is not finite.
pub(crate) fn solve_spd_system(s: &mut Mat<f64>, b: &mut Mat<f64>) -> bool {
    use faer::linalg::cholesky::llt::factor;
    let n = s.nrows();
    let mut mem = MemBuffer::new(factor::cholesky_in_place_scratch::<f64>(
        n,
        Par::Seq,
        Default::default(),
    ));
    let stack = MemStack::new(&mut mem);
    if factor::cholesky_in_place(
        s.as_mut(),
        Default::default(),
        Par::Seq,
        stack,
        Default::default(),
    )
    .is_err()
    {
        return false;
    }
    faer::linalg::triangular_solve::solve_lower_triangular_in_place(
        s.as_ref(),
        b.as_mut(),
        Par::Seq,
    );
    faer::linalg::triangular_solve::solve_upper_triangular_in_place(
        s.as_ref().transpose(),
        b.as_mut(),
        Par::Seq,
    );
    b.col(0).iter().all(|v| v.is_finite())
}

/// Run robust Levenberg–Marquardt bundle adjustment in place.
pub fn bundle_adjust(problem: &mut BaProblem, options: &BaOptions) -> Result<BaReport> {
    problem.validate()?;
    let bases: Vec<Matrix2x3<f64>> = problem
        .observations
        .iter()
        .map(|o| tangent_basis(&o.bearing))
        .collect();
    // Free-camera numbering and observations grouped by point.
    let mut cam_slot = vec![usize::MAX; problem.cam_from_world.len()];
    let mut free_cams = 0;
    for (i, fixed) in problem.fixed_camera.iter().enumerate() {
        if !fixed {
            cam_slot[i] = free_cams;
            free_cams += 1;
        }
    }
    let mut obs_of_point: Vec<Vec<usize>> = vec![Vec::new(); problem.points.len()];
    for (k, o) in problem.observations.iter().enumerate() {
        obs_of_point[o.point].push(k);
    }
    let huber = options.huber_rad;
    let (initial_cost, initial_rms) = evaluate(problem, &bases, huber);
    let mut cost = initial_cost;
    let mut lambda = options.initial_lambda;
    let mut report = BaReport {
        initial_cost,
        final_cost: initial_cost,
        initial_rms_rad: initial_rms,
        final_rms_rad: initial_rms,
        iterations: 0,
        accepted: 0,
        converged: false,
    };
    let nobs = problem.observations.len();
    let npts = problem.points.len();
    let dim = 6 * free_cams;
    let mut u = vec![Matrix6::<f64>::zeros(); free_cams];
    let mut gc = vec![Vector6::<f64>::zeros(); free_cams];
    let mut v = vec![Matrix3::<f64>::zeros(); npts];
    let mut gp = vec![Vector3::<f64>::zeros(); npts];
    let mut w = vec![Matrix6x3::<f64>::zeros(); nobs];
    let mut usable = vec![false; nobs];
    let mut relinearize = true;
    while report.iterations < options.max_iterations {
        report.iterations += 1;
        if relinearize {
            u.iter_mut().for_each(|m| *m = Matrix6::zeros());
            gc.iter_mut().for_each(|m| *m = Vector6::zeros());
            v.iter_mut().for_each(|m| *m = Matrix3::zeros());
            gp.iter_mut().for_each(|m| *m = Vector3::zeros());
            for (k, o) in problem.observations.iter().enumerate() {
                let pose = &problem.cam_from_world[o.camera];
                let pc = (pose * nalgebra::Point3::from(problem.points[o.point])).coords;
                usable[k] = false;
                let Some((r, j_p)) = tangent_residual(&o.bearing, &bases[k], &pc) else {
                    continue;
                };
                usable[k] = true;
                let wt = huber_weight(r.norm(), huber);
                let slot = cam_slot[o.camera];
                let j_pt = j_p * pose.rotation.to_rotation_matrix().matrix();
                if slot != usize::MAX {
                    let j_c = j_p * point_jacobian_left_update(&pc);
                    u[slot] += j_c.transpose() * j_c * wt;
                    gc[slot] += j_c.transpose() * r * wt;
                    w[k] = j_c.transpose() * j_pt * wt;
                }
                if !problem.fixed_point[o.point] {
                    v[o.point] += j_pt.transpose() * j_pt * wt;
                    gp[o.point] += j_pt.transpose() * r * wt;
                }
            }
            relinearize = false;
        }
        // Damped point blocks, inverted.
        let mut v_inv = vec![None; npts];
        for j in 0..npts {
            if problem.fixed_point[j] || obs_of_point[j].is_empty() {
                continue;
            }
            let mut vj = v[j];
            for d in 0..3 {
                vj[(d, d)] += lambda * vj[(d, d)].max(DAMPING_FLOOR) + DAMPING_FLOOR;
            }
            v_inv[j] = vj.try_inverse();
        }
        // Reduced camera system S δc = rhs.
        let mut s = Mat::<f64>::zeros(dim, dim);
        let mut rhs = Mat::<f64>::zeros(dim, 1);
        for c in 0..free_cams {
            for a in 0..6 {
                for b in 0..6 {
                    s[(6 * c + a, 6 * c + b)] = u[c][(a, b)];
                }
                s[(6 * c + a, 6 * c + a)] +=
                    lambda * u[c][(a, a)].max(DAMPING_FLOOR) + DAMPING_FLOOR;
                rhs[(6 * c + a, 0)] = -gc[c][a];
            }
        }
        for j in 0..npts {
            let Some(vi) = v_inv[j] else { continue };
            let vg = vi * gp[j];
            for &ka in &obs_of_point[j] {
                let ca = cam_slot[problem.observations[ka].camera];
                if ca == usize::MAX || !usable[ka] {
                    continue;
                }
                let wv = w[ka] * vi;
                let r_add = w[ka] * vg;
                for a in 0..6 {
                    rhs[(6 * ca + a, 0)] += r_add[a];
                }
                for &kb in &obs_of_point[j] {
                    let cb = cam_slot[problem.observations[kb].camera];
                    // The Cholesky factorization reads the lower triangle only: blocks above
                    // the diagonal are never formed (half the work of the reduction).
                    if cb == usize::MAX || cb > ca || !usable[kb] {
                        continue;
                    }
                    let block = wv * w[kb].transpose();
                    for a in 0..6 {
                        for b in 0..6 {
                            s[(6 * ca + a, 6 * cb + b)] -= block[(a, b)];
                        }
                    }
                }
            }
        }
        let solved = dim == 0 || solve_spd_system(&mut s, &mut rhs);
        if !solved {
            lambda *= 10.0;
            if lambda > MAX_LAMBDA {
                break;
            }
            continue;
        }
        // Back-substitute the points and try the step.
        let saved_cams = problem.cam_from_world.clone();
        let saved_pts = problem.points.clone();
        for (i, pose) in problem.cam_from_world.iter_mut().enumerate() {
            let slot = cam_slot[i];
            if slot == usize::MAX {
                continue;
            }
            let d = Vector6::from_fn(|a, _| rhs[(6 * slot + a, 0)]);
            *pose = se3_exp(&d) * *pose;
        }
        for j in 0..npts {
            let Some(vi) = v_inv[j] else { continue };
            let mut b = -gp[j];
            for &k in &obs_of_point[j] {
                let slot = cam_slot[problem.observations[k].camera];
                if slot == usize::MAX || !usable[k] {
                    continue;
                }
                let dc = Vector6::from_fn(|a, _| rhs[(6 * slot + a, 0)]);
                b -= w[k].transpose() * dc;
            }
            problem.points[j] += vi * b;
        }
        let (new_cost, _) = evaluate(problem, &bases, huber);
        if new_cost.is_finite() && new_cost < cost {
            let decrease = (cost - new_cost) / cost.max(f64::MIN_POSITIVE);
            cost = new_cost;
            report.accepted += 1;
            lambda = (lambda / 3.0).max(1e-12);
            relinearize = true;
            if decrease < options.relative_tolerance {
                report.converged = true;
                break;
            }
        } else {
            problem.cam_from_world = saved_cams;
            problem.points = saved_pts;
            lambda *= 4.0;
            if lambda > MAX_LAMBDA {
                report.converged = true;
                break;
            }
        }
    }
    let (final_cost, final_rms) = evaluate(problem, &bases, huber);
    report.final_cost = final_cost;
    report.final_rms_rad = final_rms;
    Ok(report)
}

/// Refine a two-view relative pose on its inlier bearing pairs by bundle adjustment: the
/// inliers are triangulated, camera 1 is held fixed, camera 2 and the points move, and the
/// translation is scaled back to unit length. Returns the refined `cam2_from_cam1` (or the
/// input when too few pairs triangulate).
pub fn refine_relative_pose(
    cam2_from_cam1: &Pose,
    b1: &[Vector3<f64>],
    b2: &[Vector3<f64>],
    inliers: &[bool],
    huber_rad: f64,
) -> Result<Pose> {
    use crate::vision::geometry::{RayObservation, TriangulationLimits, triangulate};
    /// Fewest triangulated pairs for a meaningful refinement (5 DoF, with redundancy).
    const MIN_PAIRS: usize = 8;
    let limits = TriangulationLimits {
        min_parallax_rad: 0.0,
        max_error_rad: std::f64::consts::FRAC_PI_2,
    };
    let mut problem = BaProblem {
        cam_from_world: vec![Pose::identity(), *cam2_from_cam1],
        fixed_camera: vec![true, false],
        ..BaProblem::default()
    };
    for ((x, y), &inl) in b1.iter().zip(b2).zip(inliers) {
        if !inl {
            continue;
        }
        let obs = [
            RayObservation {
                cam_from_world: Pose::identity(),
                bearing: *x,
            },
            RayObservation {
                cam_from_world: *cam2_from_cam1,
                bearing: *y,
            },
        ];
        let Some(t) = triangulate(&obs, &limits) else {
            continue;
        };
        let j = problem.points.len();
        problem.points.push(t.point);
        problem.fixed_point.push(false);
        problem.observations.push(BaObservation {
            camera: 0,
            point: j,
            bearing: *x,
        });
        problem.observations.push(BaObservation {
            camera: 1,
            point: j,
            bearing: *y,
        });
    }
    if problem.points.len() < MIN_PAIRS {
        return Ok(*cam2_from_cam1);
    }
    let options = BaOptions {
        huber_rad,
        ..BaOptions::default()
    };
    bundle_adjust(&mut problem, &options)?;
    let mut pose = problem.cam_from_world[1];
    let n = pose.translation.vector.norm();
    if !(n.is_finite() && n > 0.0) {
        return Ok(*cam2_from_cam1);
    }
    pose.translation.vector /= n;
    Ok(pose)
}
