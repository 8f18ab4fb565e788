//! Metric recovery of a visual map (paper §4.2): from a lens's camera trajectory in a map of
//! arbitrary scale and frame and the raw IMU of the same recording, estimate the map's scale,
//! the gravity direction in the map and the IMU biases, and return the similarity
//! `world_from_map` that makes the map metric and z-up.
//!
//! The estimate is the maximum-likelihood solution of one visual–inertial graph:
//! - one node per (valid) frame with the metric state `x = (R, p, v, b_a, b_g)` =
//!   `world_from_imu`, world velocity and biases, in a gravity-aligned world (`g = −9.81 ẑ`);
//! - GTSAM's `CombinedImuFactor` between consecutive nodes ([`crate::fusion::factors`]);
//! - three global unknowns: the scale `s` and the map's tilt `R_wm` (rotations about the
//!   world x and y axes; the heading is the gauge and stays at its initial value); the map origin
//!   is the world origin;
//! - a robust (Huber) visual factor per frame tying the node to its map pose,
//!   `e = [Log((R_wm R_mc)ᵀ R R_ic); p + R t_ic − s R_wm p_mc]`, with metric sigmas.
//!
//! Because node positions are free and the visual positions enter as noisy measurements, the
//! scale is not attenuated by the visual noise the way a linear regression of IMU displacements
//! on visual displacements is (errors in variables). The Gauss–Newton system is the chain's
//! block-tridiagonal matrix bordered by three global columns ("arrow"); it is solved by block
//! elimination along the chain with four right-hand sides and a 3×3 Schur complement, O(N).
//!
//! Initial values come from a linear visual–inertial alignment on keyframes (gyro bias from the
//! rotations, then scale, gravity and velocities by least squares, gravity magnitude enforced).
//! The global block of the inverse Hessian gives the scale and gravity uncertainties; a recording
//! whose scale is not determined to [`MetricConfig::max_scale_sigma`] is refused with an error
//! that says so rather than returning a scale.

use kiwi_core::geometry::{Pose, hat, so3_right_jacobian_inv};
use kiwi_core::imu::ImuSample;
use nalgebra::{Cholesky, DMatrix, DVector, Matrix3, SMatrix, SVector, UnitQuaternion, Vector3};

use crate::error::{BackendError, Result};
use crate::fusion::chain::{
    ImuNoiseModel, MAX_LAMBDA, MIN_DIAGONAL, accumulate_imu, cholesky_inverse, imu_cost,
    imu_information,
};
use crate::fusion::factors::{NavNode, huber_loss, huber_weight, rotation_log, rotation_matrix};
use crate::fusion::preint::{ImuBias, ImuParams, Matrix15, Preintegrated, Vector15};
use crate::fusion::preintegrate_nodes;
use crate::vision::align::Sim3;

/// Number of global unknowns: scale, tilt about world x, tilt about world y.
const G: usize = 3;
/// Right-hand sides of the chain solve: the gradient and the three global columns.
const RHS: usize = 1 + G;
type Matrix15xG = SMatrix<f64, 15, G>;
type Matrix15xR = SMatrix<f64, 15, RHS>;
type MatrixG = SMatrix<f64, G, G>;
type VectorG = SVector<f64, G>;

/// Fewest frames for a metric recovery (a few seconds of video).
pub const MIN_FRAMES: usize = 100;
/// Keyframe spacing of the linear initialisation (s): long enough that the IMU sees a
/// displacement well above the visual noise between keyframes, short enough for many equations.
const KEYFRAME_SPACING_S: f64 = 0.75;
/// Initial Marquardt damping: the scale's information is a small difference of large terms
/// (the Schur complement), so even 1e-6 of relative damping on the nodes stalls the scale step;
/// the problem is close to quadratic, so start almost undamped.
const INITIAL_LAMBDA: f64 = 1e-11;
/// Least-squares iterations before the robust loss is switched on.
const WARMUP_ITERATIONS: usize = 8;
/// Window for the excitation figure (s): accelerations are averaged over it.
const EXCITATION_WINDOW_S: f64 = 0.1;

/// One valid localization of the lens in the map.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MapFrame {
    /// Frame time on the camera clock (s).
    pub t: f64,
    /// `map_from_cam` in map units.
    pub map_from_cam: Pose,
}

/// Settings of the metric recovery.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MetricConfig {
    /// Visual position noise once metric (m).
    pub sigma_position_m: f64,
    /// Visual rotation noise (rad).
    pub sigma_rotation_rad: f64,
    /// Huber threshold on the whitened 6-dof visual residual norm.
    pub huber_k: f64,
    /// Largest acceptable 1-σ relative scale uncertainty; above it the recording has too little
    /// acceleration and no scale is returned.
    pub max_scale_sigma: f64,
    /// Largest acceptable 1-σ gravity-direction uncertainty (rad).
    pub max_gravity_sigma_rad: f64,
    /// Maximum Levenberg–Marquardt iterations.
    pub max_iterations: usize,
}

impl Default for MetricConfig {
    fn default() -> Self {
        Self {
            // Relocalizations in a map are good to a few mm and tenths of a degree.
            sigma_position_m: 2e-3,
            sigma_rotation_rad: 0.2f64.to_radians(),
            // √χ²₆(0.95): 95 % of inlier residuals stay quadratic.
            huber_k: 3.55,
            // A 0.25 % 1-σ scale keeps a 2-σ error within the 0.5 % KIWI promises.
            max_scale_sigma: 2.5e-3,
            // 0.05° 1-σ keeps a 2-σ tilt under 0.1°.
            max_gravity_sigma_rad: 0.05f64.to_radians(),
            max_iterations: 50,
        }
    }
}

/// How well the recording determines the metric quantities.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Conditioning {
    /// RMS world acceleration over the recording after removing its mean (m/s²), averaged over
    /// 0.1 s: the excitation that makes scale observable.
    pub excitation_rms_m_s2: f64,
    /// 1-σ relative scale uncertainty.
    pub scale_sigma: f64,
    /// 1-σ gravity-direction uncertainty (rad; largest axis).
    pub gravity_sigma_rad: f64,
    /// Posterior variance factor `χ²/dof` that the sigmas were inflated by (when above 1).
    pub variance_factor: f64,
}

/// The recovered metric quantities.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MetricResult {
    /// `world_from_map`: metric, z up (gravity along −z), heading and origin of the map kept.
    pub world_from_map: Sim3,
    /// Metres per map unit.
    pub scale: f64,
    /// Unit gravity direction in map coordinates.
    pub gravity_in_map: Vector3<f64>,
    /// Accelerometer bias at the middle of the recording (m/s²).
    pub accel_bias: Vector3<f64>,
    /// Its 1-σ per axis (m/s²).
    pub accel_bias_sigma: Vector3<f64>,
    /// Gyroscope bias at the middle of the recording (rad/s).
    pub gyro_bias: Vector3<f64>,
    /// Scale of the linear initialisation (for diagnostics).
    pub initial_scale: f64,
    /// How well it is determined.
    pub conditioning: Conditioning,
    /// Frames used as nodes.
    pub frames_used: usize,
    /// Visual factors down-weighted by the Huber loss.
    pub outliers_downweighted: usize,
    /// RMS visual position residual of the inliers (m).
    pub rms_position_m: f64,
    /// RMS visual rotation residual of the inliers (rad).
    pub rms_rotation_rad: f64,
    /// Solver iterations.
    pub iterations: usize,
    /// Final cost.
    pub final_cost: f64,
}

fn err(message: String) -> BackendError {
    BackendError::Estimation(message)
}

/// The global unknowns.
#[derive(Debug, Clone, Copy)]
struct Globals {
    scale: f64,
    world_from_map: Matrix3<f64>,
}

impl Globals {
    /// The scale step is additive (in units of `scale_ref`), not multiplicative: node positions
    /// are additive too, so the valley along which nodes and scale move together
    /// (`p ∝ s`) is a straight line and Gauss–Newton steps stay in it.
    fn retract(&self, d: &VectorG, scale_ref: f64) -> Self {
        Self {
            scale: self.scale + d[0] * scale_ref,
            world_from_map: rotation_matrix(&Vector3::new(d[1], d[2], 0.0)) * self.world_from_map,
        }
    }
}

/// A visual factor's data in the frames the residual needs.
#[derive(Debug, Clone, Copy)]
struct Visual {
    map_from_cam_rot: Matrix3<f64>,
    cam_in_map: Vector3<f64>,
}

/// Extrinsics shared by every visual factor.
#[derive(Debug, Clone, Copy)]
struct Lever {
    /// `R_ic` of `imu_from_cam`.
    imu_from_cam_rot: Matrix3<f64>,
    /// Camera origin in the IMU frame (m).
    cam_in_imu: Vector3<f64>,
}

type Matrix6x15 = SMatrix<f64, 6, 15>;
type Matrix6xG = SMatrix<f64, 6, G>;
type Vector6 = nalgebra::Vector6<f64>;

/// Residual `[rot; pos]` of a visual factor and its Jacobians (node tangent, globals).
///
/// The position residual is expressed in map units and converted to metres at the fixed
/// reference scale `scale_ref` (`e_pos · scale_ref / s`): the visual noise lives in the map, so
/// weighting the metric residual directly would reward shrinking the scale (the noise term of
/// the cost scales with `s²`) and bias the estimate low.
fn visual_linearize(
    v: &Visual,
    lever: &Lever,
    x: &NavNode,
    g: &Globals,
    scale_ref: f64,
    jacobians: bool,
) -> (Vector6, Matrix6x15, Matrix6xG) {
    let q = g.world_from_map * v.map_from_cam_rot;
    let r_pred = x.rotation * lever.imu_from_cam_rot;
    let e_rot = rotation_log(&(q.transpose() * r_pred));
    let w = g.world_from_map * v.cam_in_map * g.scale;
    let c = scale_ref / g.scale;
    let e_metric = x.position + x.rotation * lever.cam_in_imu - w;
    let e_pos = e_metric * c;
    let mut e = Vector6::zeros();
    e.fixed_rows_mut::<3>(0).copy_from(&e_rot);
    e.fixed_rows_mut::<3>(3).copy_from(&e_pos);
    let mut jn = Matrix6x15::zeros();
    let mut jg = Matrix6xG::zeros();
    if jacobians {
        let jr_inv = so3_right_jacobian_inv(&e_rot);
        jn.fixed_view_mut::<3, 3>(0, 0)
            .copy_from(&(jr_inv * lever.imu_from_cam_rot.transpose()));
        jn.fixed_view_mut::<3, 3>(3, 0)
            .copy_from(&(-x.rotation * hat(&lever.cam_in_imu) * c));
        jn.fixed_view_mut::<3, 3>(3, 3).copy_from(&(x.rotation * c));
        let d_rot_tilt = -jr_inv * r_pred.transpose();
        let d_pos_tilt = hat(&w) * c;
        // d(c e)/d(s / scale_ref) = −c (scale_ref / s) (e + w).
        let d_pos_scale = -(w + e_metric) * (c * c);
        for r in 0..3 {
            jg[(3 + r, 0)] = d_pos_scale[r];
            for c in 0..2 {
                jg[(r, 1 + c)] = d_rot_tilt[(r, c)];
                jg[(3 + r, 1 + c)] = d_pos_tilt[(r, c)];
            }
        }
    }
    (e, jn, jg)
}

/// The arrow-structured problem.
struct Problem<'a> {
    gravity: Vector3<f64>,
    imu: &'a [Preintegrated],
    imu_info: Vec<Matrix15>,
    visual: &'a [Visual],
    lever: Lever,
    /// Scale at which visual position residuals are expressed in metres (the initial scale).
    scale_ref: f64,
    /// Active Huber threshold (infinite in the least-squares warm-up).
    huber_k: f64,
    config: &'a MetricConfig,
    bias_prior: (f64, f64),
}

/// Working storage, allocated once.
struct System {
    diag: Vec<Matrix15>,
    off: Vec<Matrix15>,
    rhs: Vec<Matrix15xR>,
    coupling_gg: MatrixG,
    grad_g: VectorG,
    gain: Vec<Matrix15>,
    factor: Vec<Matrix15>,
    solved: Vec<Matrix15xR>,
    step: Vec<Vector15>,
    step_g: VectorG,
    schur: MatrixG,
}

impl Problem<'_> {
    fn whitened(&self, e: &Vector6) -> f64 {
        let r = e.fixed_rows::<3>(0).norm_squared() / self.config.sigma_rotation_rad.powi(2);
        let p = e.fixed_rows::<3>(3).norm_squared() / self.config.sigma_position_m.powi(2);
        (r + p).sqrt()
    }

    fn cost(&self, nodes: &[NavNode], g: &Globals) -> f64 {
        let mut cost = imu_cost(self.imu, &self.imu_info, &self.gravity, nodes);
        for (v, x) in self.visual.iter().zip(nodes) {
            let (e, _, _) = visual_linearize(v, &self.lever, x, g, self.scale_ref, false);
            cost += huber_loss(self.whitened(&e), self.huber_k);
        }
        let (sa, sg) = self.bias_prior;
        cost += 0.5 * (nodes[0].bias.acc / sa).norm_squared();
        cost += 0.5 * (nodes[0].bias.gyro / sg).norm_squared();
        cost
    }

    fn linearize(&self, nodes: &[NavNode], g: &Globals, sys: &mut System) {
        for m in sys.diag.iter_mut().chain(sys.off.iter_mut()) {
            m.fill(0.0);
        }
        for r in &mut sys.rhs {
            r.fill(0.0);
        }
        sys.coupling_gg.fill(0.0);
        sys.grad_g.fill(0.0);
        // `rhs[k]` column 0 holds the node gradient, columns 1.. the node–global coupling.
        for (k, pim) in self.imu.iter().enumerate() {
            let (gi, gj) = accumulate_imu(
                pim,
                &self.imu_info[k],
                &self.gravity,
                nodes,
                k,
                &mut sys.diag,
                &mut sys.off[k],
            );
            let mut c = sys.rhs[k].column_mut(0);
            c += gi;
            let mut c = sys.rhs[k + 1].column_mut(0);
            c += gj;
        }
        let wr = 1.0 / self.config.sigma_rotation_rad.powi(2);
        let wp = 1.0 / self.config.sigma_position_m.powi(2);
        for (k, (v, x)) in self.visual.iter().zip(nodes).enumerate() {
            let (e, jn, jg) = visual_linearize(v, &self.lever, x, g, self.scale_ref, true);
            let w = huber_weight(self.whitened(&e), self.huber_k);
            let info = Vector6::new(wr, wr, wr, wp, wp, wp) * w;
            let jn6 = jn.fixed_view::<6, 6>(0, 0).into_owned();
            let jnt_w = jn6.transpose() * nalgebra::Matrix6::from_diagonal(&info);
            let jgt_w = jg.transpose() * nalgebra::Matrix6::from_diagonal(&info);
            let mut d = sys.diag[k].fixed_view_mut::<6, 6>(0, 0);
            d += jnt_w * jn6;
            let mut gv = sys.rhs[k].fixed_view_mut::<6, 1>(0, 0);
            gv += jnt_w * e;
            let mut cv = sys.rhs[k].fixed_view_mut::<6, G>(0, 1);
            cv += jnt_w * jg;
            sys.coupling_gg += jgt_w * jg;
            sys.grad_g += jgt_w * e;
        }
        let (sa, sg) = self.bias_prior;
        for i in 0..3 {
            sys.diag[0][(9 + i, 9 + i)] += 1.0 / (sa * sa);
            sys.rhs[0][(9 + i, 0)] += nodes[0].bias.acc[i] / (sa * sa);
            sys.diag[0][(12 + i, 12 + i)] += 1.0 / (sg * sg);
            sys.rhs[0][(12 + i, 0)] += nodes[0].bias.gyro[i] / (sg * sg);
        }
    }

    /// Solve the damped arrow system; `false` if not positive definite.
    fn solve(sys: &mut System, lambda: f64) -> bool {
        let n = sys.diag.len();
        // Forward elimination along the chain on [−g_n, B] (B = node–global coupling).
        for k in 0..n {
            let mut s = sys.diag[k];
            for i in 0..15 {
                s[(i, i)] += lambda * sys.diag[k][(i, i)].max(MIN_DIAGONAL);
            }
            let mut y = sys.rhs[k];
            let mut g0 = y.column_mut(0);
            g0.neg_mut();
            if k > 0 {
                s -= sys.off[k - 1].transpose() * sys.gain[k - 1];
                y -= sys.gain[k - 1].transpose() * sys.solved[k - 1];
            }
            let Some(chol) = Cholesky::new(s) else {
                return false;
            };
            sys.factor[k] = chol.l();
            if k + 1 < n {
                sys.gain[k] = chol.solve(&sys.off[k]);
            }
            // Keep the forward-reduced right-hand side for the next row, the solve for back
            // substitution.
            sys.solved[k] = y;
        }
        // `solved[k]` holds the reduced RHS; finish: X_k = S_k⁻¹ y_k − gain_k X_{k+1}.
        let mut next: Option<Matrix15xR> = None;
        for k in (0..n).rev() {
            let l = sys.factor[k];
            let mut x = sys.solved[k];
            if !(l.solve_lower_triangular_mut(&mut x) && l.tr_solve_lower_triangular_mut(&mut x)) {
                return false;
            }
            if let Some(nx) = next {
                x -= sys.gain[k] * nx;
            }
            next = Some(x);
            sys.solved[k] = x;
        }
        // Schur complement on the globals: (C − Bᵀ A⁻¹ B) y = −g_g − Bᵀ A⁻¹ (−g_n).
        let mut schur = sys.coupling_gg;
        for i in 0..G {
            schur[(i, i)] += lambda * sys.coupling_gg[(i, i)].max(MIN_DIAGONAL);
        }
        let mut b = -sys.grad_g;
        for k in 0..n {
            let bk = sys.rhs[k].fixed_columns::<G>(1);
            let xb = sys.solved[k].fixed_columns::<G>(1);
            let xa = sys.solved[k].column(0);
            schur -= bk.transpose() * xb;
            b -= bk.transpose() * xa;
        }
        let Some(chol) = Cholesky::new(schur) else {
            return false;
        };
        sys.schur = schur;
        sys.step_g = chol.solve(&b);
        for k in 0..n {
            let xa: Vector15 = sys.solved[k].column(0).into_owned();
            let xb: Matrix15xG = sys.solved[k].fixed_columns::<G>(1).into_owned();
            sys.step[k] = xa - xb * sys.step_g;
        }
        true
    }
}

/// Least-squares gyro bias from visual rotations between keyframes.
fn gyro_bias_from_rotations(rotations: &[Matrix3<f64>], pims: &[Preintegrated]) -> Vector3<f64> {
    let mut h = Matrix3::zeros();
    let mut b = Vector3::zeros();
    for (k, pim) in pims.iter().enumerate() {
        let rel = rotations[k].transpose() * rotations[k + 1];
        let e = rotation_log(&(pim.delta_r().transpose() * rel));
        // Log(ΔR(b)ᵀ rel) ≈ e − J_θg δb_g.
        let j: Matrix3<f64> = pim.h_bias_gyro.fixed_view::<3, 3>(0, 0).into_owned();
        h += j.transpose() * j;
        b += j.transpose() * e;
    }
    Cholesky::new(h).map_or_else(Vector3::zeros, |c| c.solve(&b))
}

/// Linear alignment on keyframes: scale, gravity (map axes) and keyframe velocities (metric,
/// map axes), with the accelerometer bias taken as zero.
struct LinearInit {
    scale: f64,
    gravity_map: Vector3<f64>,
    velocities: Vec<Vector3<f64>>,
}

fn linear_alignment(
    frames: &[MapFrame],
    lever: &Lever,
    pims: &[Preintegrated],
    gyro_bias: &Vector3<f64>,
    gravity_norm: f64,
    sigma_p: f64,
) -> Result<LinearInit> {
    let n = frames.len();
    let bias = ImuBias {
        acc: Vector3::zeros(),
        gyro: *gyro_bias,
    };
    let rot_mi: Vec<Matrix3<f64>> = frames
        .iter()
        .map(|f| {
            f.map_from_cam.rotation.to_rotation_matrix().into_inner()
                * lever.imu_from_cam_rot.transpose()
        })
        .collect();
    // IMU origin in the metric map-aligned frame: s p_mc + R_mc · (IMU origin in the camera).
    let imu_in_cam = -(lever.imu_from_cam_rot.transpose() * lever.cam_in_imu);
    let lever_m: Vec<Vector3<f64>> = frames
        .iter()
        .map(|f| f.map_from_cam.rotation * imu_in_cam)
        .collect();
    let solve =
        |gravity_fixed: Option<Vector3<f64>>| -> Option<(f64, Vector3<f64>, Vec<Vector3<f64>>)> {
            // Unknowns: v_0..v_{n−1} (3n), s, and g (3) unless fixed.
            let dim = 3 * n + 1 + if gravity_fixed.is_some() { 0 } else { 3 };
            let mut h = DMatrix::<f64>::zeros(dim, dim);
            let mut rhs = DVector::<f64>::zeros(dim);
            let s_col = 3 * n;
            for (k, pim) in pims.iter().enumerate() {
                let d = pim.corrected(&bias);
                let dt = pim.dt;
                let ri = rot_mi[k];
                let wp = 1.0 / (pim.cov[(3, 3)] + 2.0 * sigma_p * sigma_p).max(1e-12);
                let wv = 1.0 / pim.cov[(6, 6)].max(1e-12);
                let dp_vis = frames[k + 1].map_from_cam.translation.vector
                    - frames[k].map_from_cam.translation.vector;
                for a in 0..3 {
                    // Position: s Δp_vis + Δlever − v_i dt − ½ g dt² = R_i Δp.
                    let mut row = Vec::with_capacity(5);
                    row.push((s_col, dp_vis[a]));
                    row.push((3 * k + a, -dt));
                    let mut y = (ri * d.delta_p)[a] - (lever_m[k + 1] - lever_m[k])[a];
                    match gravity_fixed {
                        Some(gv) => y += 0.5 * gv[a] * dt * dt,
                        None => row.push((3 * n + 1 + a, -0.5 * dt * dt)),
                    }
                    accumulate(&mut h, &mut rhs, &row, y, wp);
                    // Velocity: v_j − v_i − g dt = R_i Δv.
                    let mut row = vec![(3 * (k + 1) + a, 1.0), (3 * k + a, -1.0)];
                    let mut y = (ri * d.delta_v)[a];
                    match gravity_fixed {
                        Some(gv) => y += gv[a] * dt,
                        None => row.push((3 * n + 1 + a, -dt)),
                    }
                    accumulate(&mut h, &mut rhs, &row, y, wv);
                }
            }
            let x = Cholesky::new(h)?.solve(&rhs);
            let v = (0..n)
                .map(|k| Vector3::new(x[3 * k], x[3 * k + 1], x[3 * k + 2]))
                .collect();
            let g = gravity_fixed
                .unwrap_or_else(|| Vector3::new(x[3 * n + 1], x[3 * n + 2], x[3 * n + 3]));
            Some((x[s_col], g, v))
        };
    let fail = || {
        err(
            "the linear visual-inertial alignment is singular: the frames do not constrain \
             scale and gravity (too few or static frames)"
                .into(),
        )
    };
    let (_, g_free, _) = solve(None).ok_or_else(fail)?;
    if !(g_free.norm() > 0.0 && g_free.iter().all(|v| v.is_finite())) {
        return Err(fail());
    }
    // Enforce |g| and re-solve scale and velocities.
    let g = g_free.normalize() * gravity_norm;
    let (scale, g, velocities) = solve(Some(g)).ok_or_else(fail)?;
    if !(scale.is_finite() && scale > 0.0) {
        return Err(err(format!(
            "the linear visual-inertial alignment gives a non-positive scale ({scale:.3e}): the \
             recording has too little acceleration to observe scale, or the camera-IMU \
             calibration or time shift is wrong"
        )));
    }
    Ok(LinearInit {
        scale,
        gravity_map: g.normalize(),
        velocities,
    })
}

fn accumulate(h: &mut DMatrix<f64>, rhs: &mut DVector<f64>, row: &[(usize, f64)], y: f64, w: f64) {
    for &(i, a) in row {
        rhs[i] += w * a * y;
        for &(j, b) in row {
            h[(i, j)] += w * a * b;
        }
    }
}

fn check_frames(frames: &[MapFrame]) -> Result<()> {
    if frames.len() < MIN_FRAMES {
        return Err(err(format!(
            "metric recovery needs at least {MIN_FRAMES} valid localizations, found {}; map a \
             longer recording or relocalize more frames",
            frames.len()
        )));
    }
    for (k, f) in frames.iter().enumerate() {
        let finite = f.t.is_finite()
            && f.map_from_cam
                .translation
                .vector
                .iter()
                .all(|v| v.is_finite())
            && f.map_from_cam.rotation.coords.iter().all(|v| v.is_finite());
        if !finite {
            return Err(err(format!("localization {k} (t = {}) is not finite", f.t)));
        }
        if k > 0 && f.t <= frames[k - 1].t {
            return Err(err(format!(
                "localization times must increase: {} at index {k} follows {}; sort the rows \
                 and drop duplicates",
                f.t,
                frames[k - 1].t
            )));
        }
    }
    Ok(())
}

/// Recover scale, gravity and biases of a visual map.
///
/// `frames` are the valid localizations of one lens (camera clock), `imu` the raw IMU of the
/// recording, `cam_from_imu` and `time_shift_s` (`t_imu = t_cam + time_shift_s`) the lens's
/// camera–IMU calibration.
pub fn recover_metric(
    frames: &[MapFrame],
    imu: &[ImuSample],
    params: &ImuParams,
    cam_from_imu: &Pose,
    time_shift_s: f64,
    config: &MetricConfig,
) -> Result<MetricResult> {
    check_frames(frames)?;
    let (Some(first), Some(last)) = (imu.first(), imu.last()) else {
        return Err(err("the IMU log is empty".into()));
    };
    // Keep frames inside the IMU log.
    let frames: Vec<MapFrame> = frames
        .iter()
        .filter(|f| f.t + time_shift_s >= first.t && f.t + time_shift_s <= last.t)
        .copied()
        .collect();
    check_frames(&frames)?;
    let imu_from_cam = cam_from_imu.inverse();
    let lever = Lever {
        imu_from_cam_rot: imu_from_cam.rotation.to_rotation_matrix().into_inner(),
        cam_in_imu: imu_from_cam.translation.vector,
    };
    let gravity_norm = params.gravity.norm();

    // Linear initialisation on keyframes.
    let mut keys = vec![0usize];
    for (k, f) in frames.iter().enumerate() {
        if let Some(&last_key) = keys.last()
            && f.t - frames[last_key].t >= KEYFRAME_SPACING_S
        {
            keys.push(k);
        }
    }
    if keys.len() < 4 {
        return Err(err(format!(
            "the localizations span only {:.2} s; metric recovery needs several seconds of motion",
            frames[frames.len() - 1].t - frames[0].t
        )));
    }
    let key_frames: Vec<MapFrame> = keys.iter().map(|&k| frames[k]).collect();
    let key_times: Vec<f64> = key_frames.iter().map(|f| f.t + time_shift_s).collect();
    let key_pims = preintegrate_nodes(imu, params, &key_times, ImuBias::default())?;
    let key_rot_mi: Vec<Matrix3<f64>> = key_frames
        .iter()
        .map(|f| {
            f.map_from_cam.rotation.to_rotation_matrix().into_inner()
                * lever.imu_from_cam_rot.transpose()
        })
        .collect();
    let gyro_bias = gyro_bias_from_rotations(&key_rot_mi, &key_pims);
    let init = linear_alignment(
        &key_frames,
        &lever,
        &key_pims,
        &gyro_bias,
        gravity_norm,
        config.sigma_position_m,
    )?;

    // Initial nodes in the gravity-aligned world.
    let world_from_map = UnitQuaternion::rotation_between(&init.gravity_map, &-Vector3::z())
        .unwrap_or_else(|| {
            UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI)
        })
        .to_rotation_matrix()
        .into_inner();
    let globals = Globals {
        scale: init.scale,
        world_from_map,
    };
    let visual: Vec<Visual> = frames
        .iter()
        .map(|f| Visual {
            map_from_cam_rot: f.map_from_cam.rotation.to_rotation_matrix().into_inner(),
            cam_in_map: f.map_from_cam.translation.vector,
        })
        .collect();
    let nodes: Vec<NavNode> = frames
        .iter()
        .zip(&visual)
        .map(|(f, v)| {
            let r_wc = world_from_map * v.map_from_cam_rot;
            let r_wi = r_wc * lever.imu_from_cam_rot.transpose();
            let p_wc = world_from_map * v.cam_in_map * init.scale;
            let p_wi = p_wc - r_wi * lever.cam_in_imu;
            // Velocity: the keyframe velocities interpolated in time.
            let j = keys
                .partition_point(|&k| frames[k].t <= f.t)
                .clamp(1, keys.len() - 1);
            let (ta, tb) = (frames[keys[j - 1]].t, frames[keys[j]].t);
            let s = ((f.t - ta) / (tb - ta)).clamp(0.0, 1.0);
            let v_map = init.velocities[j - 1] * (1.0 - s) + init.velocities[j] * s;
            NavNode {
                rotation: r_wi,
                position: p_wi,
                velocity: world_from_map * v_map,
                bias: ImuBias {
                    acc: Vector3::zeros(),
                    gyro: gyro_bias,
                },
            }
        })
        .collect();

    let node_times: Vec<f64> = frames.iter().map(|f| f.t + time_shift_s).collect();
    let pims = preintegrate_nodes(imu, params, &node_times, ImuBias::default())?;
    let imu_info = pims
        .iter()
        .map(|p| imu_information(&p.residual_cov(), ImuNoiseModel::Full))
        .collect();
    let problem = Problem {
        gravity: params.gravity,
        imu: &pims,
        imu_info,
        visual: &visual,
        lever,
        scale_ref: init.scale,
        huber_k: f64::INFINITY,
        config,
        // Zero-centred bias priors as in fusion: loose next to any real IMU.
        bias_prior: (0.2, 0.02),
    };
    // Least squares first: from the linear initialisation (a few per cent off in scale) the
    // Huber loss would treat most frames as outliers and converge slowly; the quadratic problem
    // converges in a few steps, then the robust loss takes over from close to the optimum.
    let (nodes, globals, warmup, _, _) = solve_lm(&problem, nodes, globals, WARMUP_ITERATIONS);
    let problem = Problem {
        huber_k: config.huber_k,
        ..problem
    };
    let (nodes, globals, iterations, final_cost, sys) =
        solve_lm(&problem, nodes, globals, config.max_iterations);
    let iterations = iterations + warmup;
    summarize(
        &problem, &frames, &nodes, &globals, &sys, init.scale, iterations, final_cost,
    )
}

type LmOutput = (Vec<NavNode>, Globals, usize, f64, System);

fn solve_lm(
    problem: &Problem<'_>,
    mut nodes: Vec<NavNode>,
    mut globals: Globals,
    max_iterations: usize,
) -> LmOutput {
    let n = nodes.len();
    let mut sys = System {
        diag: vec![Matrix15::zeros(); n],
        off: vec![Matrix15::zeros(); n.saturating_sub(1)],
        rhs: vec![Matrix15xR::zeros(); n],
        coupling_gg: MatrixG::zeros(),
        grad_g: VectorG::zeros(),
        gain: vec![Matrix15::zeros(); n.saturating_sub(1)],
        factor: vec![Matrix15::zeros(); n],
        solved: vec![Matrix15xR::zeros(); n],
        step: vec![Vector15::zeros(); n],
        step_g: VectorG::zeros(),
        schur: MatrixG::zeros(),
    };
    let mut trial = nodes.clone();
    let mut cost = problem.cost(&nodes, &globals);
    let mut lambda = INITIAL_LAMBDA;
    let mut iterations = 0;
    while iterations < max_iterations {
        iterations += 1;
        problem.linearize(&nodes, &globals, &mut sys);
        let mut improved = false;
        let mut converged = false;
        while lambda < MAX_LAMBDA {
            if !Problem::solve(&mut sys, lambda) {
                lambda *= 10.0;
                continue;
            }
            for k in 0..n {
                trial[k] = nodes[k].retract(&sys.step[k]);
            }
            let trial_g = globals.retract(&sys.step_g, problem.scale_ref);
            let new_cost = problem.cost(&trial, &trial_g);
            if new_cost <= cost {
                converged = cost - new_cost <= 1e-10 * cost;
                std::mem::swap(&mut nodes, &mut trial);
                globals = trial_g;
                cost = new_cost;
                lambda = (lambda / 10.0).max(1e-12);
                improved = true;
                break;
            }
            lambda *= 10.0;
        }
        if !improved || converged {
            break;
        }
    }
    // Linearize and factor at the solution for the covariances.
    problem.linearize(&nodes, &globals, &mut sys);
    if !Problem::solve(&mut sys, 0.0) {
        sys.schur = MatrixG::zeros();
    }
    (nodes, globals, iterations, cost, sys)
}

/// Diagonal 15×15 block of `A⁻¹` at node `k` of the factored chain (backward selected
/// inversion from the end).
fn chain_marginal(sys: &System, k: usize) -> Matrix15 {
    let n = sys.factor.len();
    let mut sigma = cholesky_inverse(&sys.factor[n - 1]);
    for j in (k..n - 1).rev() {
        let g = &sys.gain[j];
        sigma = cholesky_inverse(&sys.factor[j]) + g * sigma * g.transpose();
    }
    sigma
}

#[allow(clippy::too_many_arguments)]
fn summarize(
    problem: &Problem<'_>,
    frames: &[MapFrame],
    nodes: &[NavNode],
    globals: &Globals,
    sys: &System,
    initial_scale: f64,
    iterations: usize,
    final_cost: f64,
) -> Result<MetricResult> {
    let n = nodes.len();
    // Residual statistics and the posterior variance factor.
    let mut downweighted = 0;
    let (mut sp, mut sr, mut inliers) = (0.0, 0.0, 0usize);
    for (v, x) in problem.visual.iter().zip(nodes) {
        let (e, _, _) = visual_linearize(v, &problem.lever, x, globals, problem.scale_ref, false);
        if problem.whitened(&e) > problem.config.huber_k {
            downweighted += 1;
        } else {
            inliers += 1;
            sr += e.fixed_rows::<3>(0).norm_squared();
            sp += e.fixed_rows::<3>(3).norm_squared();
        }
    }
    let residuals = 6 * n + 15 * (n - 1) + 6;
    let unknowns = 15 * n + G;
    let dof = residuals.saturating_sub(unknowns).max(1);
    let variance_factor = (2.0 * final_cost / dof as f64).max(1.0);
    let cov_g = Cholesky::new(sys.schur)
        .map(|c| c.inverse() * variance_factor)
        .ok_or_else(|| {
            err(
                "the metric problem is singular at the solution: scale and gravity are not \
                 observable from this recording"
                    .into(),
            )
        })?;
    let scale_sigma = cov_g[(0, 0)].max(0.0).sqrt() * problem.scale_ref / globals.scale;
    let tilt: nalgebra::Matrix2<f64> = cov_g.fixed_view::<2, 2>(1, 1).into_owned();
    let gravity_sigma_rad = tilt.symmetric_eigenvalues().max().max(0.0).sqrt();
    // Excitation: RMS of the de-meaned world acceleration averaged over a short window.
    let mut acc = Vec::new();
    let mut j = 0;
    for i in 0..n {
        while j < n && frames[j].t - frames[i].t < EXCITATION_WINDOW_S {
            j += 1;
        }
        if j >= n {
            break;
        }
        let dt = frames[j].t - frames[i].t;
        acc.push((nodes[j].velocity - nodes[i].velocity) / dt);
    }
    let excitation_rms_m_s2 = if acc.is_empty() {
        0.0
    } else {
        let mean = acc.iter().sum::<Vector3<f64>>() / acc.len() as f64;
        (acc.iter().map(|a| (a - mean).norm_squared()).sum::<f64>() / acc.len() as f64).sqrt()
    };
    let conditioning = Conditioning {
        excitation_rms_m_s2,
        scale_sigma,
        gravity_sigma_rad,
        variance_factor,
    };
    let config = problem.config;
    if scale_sigma > config.max_scale_sigma || gravity_sigma_rad > config.max_gravity_sigma_rad {
        return Err(err(format!(
            "too little acceleration to recover the map's scale: the recording determines it only \
             to {:.2} % (1 σ; limit {:.2} %) and gravity to {:.3}° (limit {:.3}°) with an RMS \
             acceleration of {:.3} m/s²; record the mapping episode with brisker motion (changes \
             of direction, a few tenths of m/s² or more) or a longer sweep",
            scale_sigma * 100.0,
            config.max_scale_sigma * 100.0,
            gravity_sigma_rad.to_degrees(),
            config.max_gravity_sigma_rad.to_degrees(),
            excitation_rms_m_s2
        )));
    }
    // Bias at the middle node with its marginal: A⁻¹ block + X_B S⁻¹ X_Bᵀ.
    let mid = n / 2;
    let xb: Matrix15xG = sys.solved[mid].fixed_columns::<G>(1).into_owned();
    let cov_mid = (chain_marginal(sys, mid) + xb * (cov_g / variance_factor) * xb.transpose())
        * variance_factor;
    let accel_bias_sigma = Vector3::new(cov_mid[(9, 9)], cov_mid[(10, 10)], cov_mid[(11, 11)])
        .map(|v| v.max(0.0).sqrt());
    let rotation = UnitQuaternion::from_matrix(&globals.world_from_map);
    let gravity_in_map = globals.world_from_map.transpose() * -Vector3::z();
    let denom = inliers.max(1) as f64;
    Ok(MetricResult {
        world_from_map: Sim3 {
            scale: globals.scale,
            rotation,
            translation: Vector3::zeros(),
        },
        scale: globals.scale,
        gravity_in_map,
        accel_bias: nodes[mid].bias.acc,
        accel_bias_sigma,
        gyro_bias: nodes[mid].bias.gyro,
        initial_scale,
        conditioning,
        frames_used: n,
        outliers_downweighted: downweighted,
        rms_position_m: (sp / denom).sqrt(),
        rms_rotation_rad: (sr / denom).sqrt(),
        iterations,
        final_cost,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn visual_jacobians_match_central_differences() {
        let lever = Lever {
            imu_from_cam_rot: rotation_matrix(&Vector3::new(0.3, -1.2, 0.4)),
            cam_in_imu: Vector3::new(0.02, -0.01, 0.03),
        };
        let v = Visual {
            map_from_cam_rot: rotation_matrix(&Vector3::new(-0.2, 0.5, 2.0)),
            cam_in_map: Vector3::new(1.3, -0.4, 2.2),
        };
        let g = Globals {
            scale: 0.7,
            world_from_map: rotation_matrix(&Vector3::new(0.1, 0.4, -0.8)),
        };
        let x = NavNode {
            rotation: rotation_matrix(&Vector3::new(0.6, 0.1, -0.3)),
            position: Vector3::new(0.8, -0.1, 1.4),
            velocity: Vector3::zeros(),
            bias: ImuBias::default(),
        };
        let (_, jn, jg) = visual_linearize(&v, &lever, &x, &g, 0.9, true);
        let h = 1e-6;
        for c in 0..6 {
            let mut d = Vector15::zeros();
            d[c] = h;
            let (ep, _, _) = visual_linearize(&v, &lever, &x.retract(&d), &g, 0.9, false);
            d[c] = -h;
            let (em, _, _) = visual_linearize(&v, &lever, &x.retract(&d), &g, 0.9, false);
            let num = (ep - em) / (2.0 * h);
            assert!(
                (num - jn.column(c)).norm() < 1e-7,
                "node column {c}: {num} vs {}",
                jn.column(c)
            );
        }
        for c in 0..G {
            let mut d = VectorG::zeros();
            d[c] = h;
            let (ep, _, _) = visual_linearize(&v, &lever, &x, &g.retract(&d, 0.9), 0.9, false);
            d[c] = -h;
            let (em, _, _) = visual_linearize(&v, &lever, &x, &g.retract(&d, 0.9), 0.9, false);
            let num = (ep - em) / (2.0 * h);
            assert!(
                (num - jg.column(c)).norm() < 1e-7,
                "global column {c}: {num} vs {}",
                jg.column(c)
            );
        }
    }
}
