//! The joint batch estimate: a continuous-time IMU trajectory (cubic B-spline on SO(3)×R³) fitted
//! to every gyro and accelerometer sample and to every detected corner at its own
//! rolling-shutter time, together with each lens's `cam_from_imu` and time shift, the boards'
//! poses, gravity and slowly drifting gyro and accelerometer biases (a coarse B-spline with a
//! random-walk prior). Robust (Huber) loss on pixel residuals; Levenberg–Marquardt.
//!
//! The normal equations are an arrowhead: the spline block is banded (a residual touches four
//! consecutive control points, so 24 consecutive parameters), bordered by the few dozen global
//! parameters. The band is factored by a banded Cholesky, the globals by a Schur complement
//! factored with faer; the inverse of that Schur complement is the globals' covariance.

use faer::dyn_stack::{MemBuffer, MemStack};
use faer::{Mat, Par};
use nalgebra::{Matrix3, Matrix6, SMatrix, Vector3, Vector6};
use rayon::prelude::*;

use kiwi_core::camera::CameraModel;
use kiwi_core::geometry::{Pose, se3_adjoint, se3_exp, so3_exp};
use kiwi_core::imu::ImuSample;

use super::observe::LensObservations;
use super::spline::{TrajectorySpline, VectorSpline, basis_d2, skew};

/// Parameters of one trajectory control point (rotation 3, position 3).
const CTRL_DIM: usize = 6;
/// Spline parameters one residual touches (four control points): the band width.
const BAND: usize = 4 * CTRL_DIM;
/// Parameters per lens in the global block: `cam_from_imu` (6) and the time shift (1).
const LENS_DIM: usize = 7;
/// Parameters per bias knot: gyro (3) and accelerometer (3).
const BIAS_DIM: usize = 6;
/// Relative cost decrease below which Levenberg–Marquardt stops.
const COST_TOLERANCE: f64 = 1e-6;
/// Damping above which a step is hopeless: the estimate has converged.
const MAX_LAMBDA: f64 = 1e8;
/// Damping increases tried per iteration: near the minimum a rejected Gauss–Newton step means
/// the cost is flat to round-off, and more trials only cost time.
const MAX_TRIALS: usize = 3;
/// Pieces the normal equations and the Schur complement are accumulated in: a fixed split
/// (not one per thread) sums in the same order on any machine and thread count.
const ACCUMULATION_PIECES: usize = 8;
/// IMU samples per cost term summed as one piece (fixed for the same reason).
const IMU_COST_CHUNK: usize = 4096;

/// Noise model of the residuals.
#[derive(Debug, Clone, Copy)]
pub struct Weights {
    /// Corner detection noise (px, per axis).
    pub pixel_sigma: f64,
    /// Huber threshold on a corner's residual norm (px).
    pub huber_px: f64,
    /// Gyro noise per sample (rad/s).
    pub gyro_sigma: f64,
    /// Accelerometer noise per sample (m/s²).
    pub accel_sigma: f64,
    /// Gyro bias random walk (rad/s²/√Hz).
    pub gyro_random_walk: f64,
    /// Accelerometer bias random walk (m/s³/√Hz).
    pub accel_random_walk: f64,
}

/// One lens's extrinsic state.
#[derive(Debug, Clone, Copy)]
pub struct LensState {
    /// `cam_from_imu`.
    pub cam_from_imu: Pose,
    /// Kalibr time shift (s): `t_imu = t_cam + time_shift_s`.
    pub time_shift_s: f64,
}

/// Everything the batch estimates.
#[derive(Debug, Clone)]
pub struct State {
    /// `world_from_imu(t)`; the world is the first lens's board.
    pub spline: TrajectorySpline,
    /// Per lens.
    pub lenses: Vec<LensState>,
    /// `world_from_board` per lens (the first is the identity and fixed).
    pub world_from_board: Vec<Pose>,
    /// Gravity in the world frame (m/s², magnitude fixed).
    pub gravity: Vector3<f64>,
    /// Gyro bias (rad/s) over time.
    pub gyro_bias: VectorSpline,
    /// Accelerometer bias (m/s²) over time.
    pub accel_bias: VectorSpline,
}

/// Residual data: every lens's frames and the IMU samples inside the spline.
pub struct Problem<'a> {
    /// Lenses (frames and corners); frames outside the spline are skipped.
    pub lenses: &'a [LensObservations],
    /// IMU samples inside the spline.
    pub imu: &'a [ImuSample],
    /// Noise model.
    pub weights: Weights,
}

/// Where each global parameter lives.
#[derive(Debug, Clone)]
struct Layout {
    ns: usize,
    ng: usize,
    lens: Vec<usize>,
    board: Vec<Option<usize>>,
    gravity: usize,
    bias: usize,
}

impl Layout {
    fn new(state: &State) -> Self {
        let n_lens = state.lenses.len();
        let lens: Vec<usize> = (0..n_lens).map(|l| l * LENS_DIM).collect();
        let mut next = n_lens * LENS_DIM;
        let board = (0..n_lens)
            .map(|l| {
                (l > 0).then(|| {
                    next += 6;
                    next - 6
                })
            })
            .collect();
        let gravity = next;
        let bias = gravity + 2;
        let ng = bias + BIAS_DIM * state.gyro_bias.values.len();
        Self {
            ns: CTRL_DIM * state.spline.len(),
            ng,
            lens,
            board,
            gravity,
            bias,
        }
    }
}

/// Two unit vectors orthogonal to gravity: its 2-dof tangent basis.
fn gravity_basis(g: &Vector3<f64>) -> SMatrix<f64, 3, 2> {
    let n = g.normalize();
    let a = if n.x.abs() < 0.9 {
        Vector3::x()
    } else {
        Vector3::y()
    };
    let e1 = n.cross(&a).normalize();
    let e2 = n.cross(&e1);
    SMatrix::<f64, 3, 2>::from_columns(&[e1, e2])
}

/// Huber weight and cost of a residual norm `e` with threshold `k` (cost `e²` inside).
fn huber(e: f64, k: f64) -> (f64, f64) {
    if e <= k {
        (1.0, e * e)
    } else {
        (k / e, 2.0 * k * e - k * k)
    }
}

/// The normal equations `H δ = −g` in arrowhead form.
#[derive(Clone)]
struct Normal {
    ns: usize,
    ng: usize,
    /// Lower band of the spline block: `band[i·BAND + (i − j)] = H[i][j]`.
    band: Vec<f64>,
    /// Spline × global block, row-major `ns × ng`.
    cross: Vec<f64>,
    /// Global block, row-major `ng × ng` (lower triangle accumulated).
    dense: Vec<f64>,
    gs: Vec<f64>,
    gg: Vec<f64>,
    cost: f64,
}

impl Normal {
    fn new(ns: usize, ng: usize) -> Self {
        Self {
            ns,
            ng,
            band: vec![0.0; ns * BAND],
            cross: vec![0.0; ns * ng],
            dense: vec![0.0; ng * ng],
            gs: vec![0.0; ns],
            gg: vec![0.0; ng],
            cost: 0.0,
        }
    }

    fn merge(mut self, other: &Self) -> Self {
        for (a, b) in [
            (&mut self.band, &other.band),
            (&mut self.cross, &other.cross),
            (&mut self.dense, &other.dense),
            (&mut self.gs, &other.gs),
            (&mut self.gg, &other.gg),
        ] {
            for (x, y) in a.iter_mut().zip(b.iter()) {
                *x += y;
            }
        }
        self.cost += other.cost;
        self
    }

    /// Add `Jᵀ M J` and `Jᵀ g` for a block of `m` residuals whose Jacobian has `BAND` spline
    /// columns from `s0` followed by global columns `gidx` (row-major `m × (BAND + k)`).
    fn add(
        &mut self,
        m: usize,
        s0: usize,
        gidx: &[usize],
        jac: &[f64],
        info: &[f64],
        grad: &[f64],
    ) {
        let n = BAND + gidx.len();
        // JᵀM, n × m.
        let mut jtm = [0.0f64; 64 * 6];
        for p in 0..n {
            for a in 0..m {
                let mut s = 0.0;
                for b in 0..m {
                    s += jac[b * n + p] * info[b * m + a];
                }
                jtm[p * m + a] = s;
            }
        }
        let global = |p: usize| -> Option<usize> { (p >= BAND).then(|| gidx[p - BAND]) };
        for p in 0..n {
            let row = &jtm[p * m..p * m + m];
            let gp: f64 = (0..m).map(|a| jac[a * n + p] * grad[a]).sum();
            match global(p) {
                None => self.gs[s0 + p] += gp,
                Some(i) => self.gg[i] += gp,
            }
            for q in 0..=p {
                let v: f64 = (0..m).map(|a| row[a] * jac[a * n + q]).sum();
                if v == 0.0 {
                    continue;
                }
                match (global(p), global(q)) {
                    (None, None) => {
                        let (i, j) = (s0 + p, s0 + q);
                        self.band[i * BAND + (i - j)] += v;
                    }
                    (Some(gi), None) => self.cross[(s0 + q) * self.ng + gi] += v,
                    (None, Some(gj)) => self.cross[(s0 + p) * self.ng + gj] += v,
                    (Some(gi), Some(gj)) => {
                        let (a, b) = if gi >= gj { (gi, gj) } else { (gj, gi) };
                        self.dense[a * self.ng + b] += v;
                        if gi == gj && p != q {
                            // The (p, q) and (q, p) terms land on the same diagonal entry.
                            self.dense[a * self.ng + b] += v;
                        }
                    }
                }
            }
        }
    }
}

/// Cost and, with `normal`, the normal equations of one frame's corners.
fn frame_terms(
    state: &State,
    layout: &Layout,
    lens_index: usize,
    obs: &LensObservations,
    frame: &super::observe::FrameObs,
    weights: &Weights,
    normal: Option<&mut Normal>,
) -> f64 {
    let lens = &state.lenses[lens_index];
    let camera = &obs.camera;
    let t_ref = frame.t + lens.time_shift_s + frame.row_delay_s;
    let Some(st) = state.spline.state(t_ref) else {
        return 0.0;
    };
    let x = &lens.cam_from_imu;
    let world_from_board = &state.world_from_board[lens_index];
    let inv_var = 1.0 / (weights.pixel_sigma * weights.pixel_sigma);
    let mut m6 = Matrix6::<f64>::zeros();
    let mut g6 = Vector6::<f64>::zeros();
    let mut cost = 0.0;
    let motion = FrameMotion::new(&state.spline, &st, t_ref);
    for c in &frame.corners {
        let (r, p) = motion.at(c.row_delay_s - frame.row_delay_s);
        let pw = world_from_board * nalgebra::Point3::from(c.board);
        let pi = r.inverse() * (pw.coords - p);
        let pc = x * nalgebra::Point3::from(pi);
        let Some((px, dp)) = camera.project_with_jacobians(&pc.coords, None) else {
            // Behind the lens: a gross outlier at the Huber slope.
            cost += inv_var * 2.0 * weights.huber_px * 1e3;
            continue;
        };
        let res = px.coords - c.pixel;
        let (w, rho) = huber(res.norm(), weights.huber_px);
        cost += inv_var * rho;
        let mut dxi = nalgebra::Matrix3x6::<f64>::zeros();
        dxi.fixed_view_mut::<3, 3>(0, 0)
            .copy_from(&(-skew(&pc.coords)));
        dxi.fixed_view_mut::<3, 3>(0, 3)
            .copy_from(&Matrix3::identity());
        let a = dp * dxi;
        m6 += a.transpose() * a * (w * inv_var);
        g6 += a.transpose() * res * (w * inv_var);
    }
    let Some(normal) = normal else {
        return cost;
    };
    // Jacobian of the left perturbation of cam_from_board at the frame's reference time.
    let (jr, _) = state.spline.rotation_jacobians(st.knot);
    let rx = x.rotation.to_rotation_matrix().into_inner();
    let tx = skew(&x.translation.vector);
    let rwi_t = st.rotation.to_rotation_matrix().into_inner().transpose();
    let mut g_rot = SMatrix::<f64, 6, 3>::zeros();
    g_rot.fixed_view_mut::<3, 3>(0, 0).copy_from(&(-rx));
    g_rot.fixed_view_mut::<3, 3>(3, 0).copy_from(&(-tx * rx));
    let mut g_pos = SMatrix::<f64, 6, 3>::zeros();
    g_pos.fixed_view_mut::<3, 3>(3, 0).copy_from(&(-rx * rwi_t));
    let b = super::spline::basis(st.knot.u);
    let lens_base = layout.lens[lens_index];
    let mut gidx: Vec<usize> = (lens_base..lens_base + LENS_DIM).collect();
    if let Some(bb) = layout.board[lens_index] {
        gidx.extend(bb..bb + 6);
    }
    let n = BAND + gidx.len();
    let mut jac = [0.0f64; 6 * (BAND + 13)];
    let mut put = |row: usize, col: usize, v: f64| jac[row * n + col] = v;
    for k in 0..4 {
        let jrk = g_rot * jr.fixed_view::<3, 3>(0, 3 * k);
        let jpk = g_pos * b[k];
        for i in 0..6 {
            for a in 0..3 {
                put(i, CTRL_DIM * k + a, jrk[(i, a)]);
                put(i, CTRL_DIM * k + 3 + a, jpk[(i, a)]);
            }
        }
    }
    let d_shift = g_rot * st.omega + g_pos * st.velocity;
    let cam_from_board = x * st_pose(&st).inverse() * world_from_board;
    let ad = se3_adjoint(&cam_from_board);
    for i in 0..6 {
        put(i, BAND + i, 1.0);
        put(i, BAND + 6, d_shift[i]);
        if layout.board[lens_index].is_some() {
            for a in 0..6 {
                put(i, BAND + 7 + a, ad[(i, a)]);
            }
        }
    }
    let info: Vec<f64> = (0..36).map(|k| m6[(k / 6, k % 6)]).collect();
    normal.add(
        6,
        CTRL_DIM * st.knot.segment,
        &gidx,
        &jac[..6 * n],
        &info,
        g6.as_slice(),
    );
    normal.cost += cost;
    cost
}

/// The trajectory around a frame's reference time to second order, for the corners' rolling-
/// shutter times (rows are read within a few milliseconds, where the third-order term is far
/// below a hundredth of a pixel): `R(t+δ) = R exp(ωδ + ω̇δ²/2)`, `p(t+δ) = p + vδ + aδ²/2`.
struct FrameMotion {
    rotation: nalgebra::UnitQuaternion<f64>,
    position: Vector3<f64>,
    omega: Vector3<f64>,
    omega_dot: Vector3<f64>,
    velocity: Vector3<f64>,
    acceleration: Vector3<f64>,
}

/// Step (s) of the angular-acceleration finite difference.
const OMEGA_DOT_STEP_S: f64 = 1e-3;

impl FrameMotion {
    fn new(spline: &TrajectorySpline, st: &super::spline::TrajectoryState, t: f64) -> Self {
        let omega_dot = match (
            spline.state(t + OMEGA_DOT_STEP_S),
            spline.state(t - OMEGA_DOT_STEP_S),
        ) {
            (Some(a), Some(b)) => (a.omega - b.omega) / (2.0 * OMEGA_DOT_STEP_S),
            _ => Vector3::zeros(),
        };
        Self {
            rotation: st.rotation,
            position: st.position,
            omega: st.omega,
            omega_dot,
            velocity: st.velocity,
            acceleration: st.acceleration,
        }
    }

    fn at(&self, d: f64) -> (nalgebra::UnitQuaternion<f64>, Vector3<f64>) {
        (
            self.rotation * so3_exp(&(self.omega * d + self.omega_dot * (0.5 * d * d))),
            self.position + self.velocity * d + self.acceleration * (0.5 * d * d),
        )
    }
}

fn st_pose(st: &super::spline::TrajectoryState) -> Pose {
    Pose::from_parts(nalgebra::Translation3::from(st.position), st.rotation)
}

/// Cost and, with `normal`, the normal equations of one IMU sample.
fn imu_terms(
    state: &State,
    layout: &Layout,
    s: &ImuSample,
    weights: &Weights,
    normal: Option<&mut Normal>,
) -> f64 {
    let Some(st) = state.spline.state(s.t) else {
        return 0.0;
    };
    let (bi, bw) = state.gyro_bias.weights(s.t);
    let bg = (0..4).fold(Vector3::zeros(), |a, j| {
        a + state.gyro_bias.values[bi + j] * bw[j]
    });
    let ba = (0..4).fold(Vector3::zeros(), |a, j| {
        a + state.accel_bias.values[bi + j] * bw[j]
    });
    let rt = st.rotation.inverse();
    let f = rt * (st.acceleration - state.gravity);
    let rg = st.omega + bg - s.gyro;
    let ra = f + ba - s.accel;
    let (wg, wa) = (
        1.0 / (weights.gyro_sigma * weights.gyro_sigma),
        1.0 / (weights.accel_sigma * weights.accel_sigma),
    );
    let cost = wg * rg.norm_squared() + wa * ra.norm_squared();
    let Some(normal) = normal else {
        return cost;
    };
    let (jr, jw) = state.spline.rotation_jacobians(st.knot);
    let rt_m = rt.to_rotation_matrix().into_inner();
    let fx = skew(&f);
    let d2 = basis_d2(st.knot.u);
    let h2 = state.spline.h * state.spline.h;
    let mut gidx = [0usize; 4 * BIAS_DIM + 2];
    for j in 0..4 {
        for a in 0..BIAS_DIM {
            gidx[j * BIAS_DIM + a] = layout.bias + BIAS_DIM * (bi + j) + a;
        }
    }
    gidx[4 * BIAS_DIM] = layout.gravity;
    gidx[4 * BIAS_DIM + 1] = layout.gravity + 1;
    let n = BAND + gidx.len();
    let mut jac = [0.0f64; 6 * (BAND + 4 * BIAS_DIM + 2)];
    let dg = rt_m * skew(&state.gravity) * gravity_basis(&state.gravity);
    for k in 0..4 {
        let jwk = jw.fixed_view::<3, 3>(0, 3 * k);
        let jak = fx * jr.fixed_view::<3, 3>(0, 3 * k);
        let jp = rt_m * (d2[k] / h2);
        for i in 0..3 {
            for a in 0..3 {
                jac[i * n + CTRL_DIM * k + a] = jwk[(i, a)];
                jac[(3 + i) * n + CTRL_DIM * k + a] = jak[(i, a)];
                jac[(3 + i) * n + CTRL_DIM * k + 3 + a] = jp[(i, a)];
            }
        }
    }
    for j in 0..4 {
        for i in 0..3 {
            jac[i * n + BAND + j * BIAS_DIM + i] = bw[j];
            jac[(3 + i) * n + BAND + j * BIAS_DIM + 3 + i] = bw[j];
        }
    }
    for i in 0..3 {
        for a in 0..2 {
            jac[(3 + i) * n + BAND + 4 * BIAS_DIM + a] = dg[(i, a)];
        }
    }
    let mut info = [0.0f64; 36];
    for i in 0..3 {
        info[i * 6 + i] = wg;
        info[(3 + i) * 6 + 3 + i] = wa;
    }
    let grad = [
        wg * rg.x,
        wg * rg.y,
        wg * rg.z,
        wa * ra.x,
        wa * ra.y,
        wa * ra.z,
    ];
    normal.add(
        6,
        CTRL_DIM * st.knot.segment,
        &gidx,
        &jac[..6 * n],
        &info,
        &grad,
    );
    normal.cost += cost;
    cost
}

/// Random-walk prior between consecutive bias knots.
fn bias_prior(
    state: &State,
    layout: &Layout,
    weights: &Weights,
    normal: Option<&mut Normal>,
) -> f64 {
    let h = state.gyro_bias.h;
    let wg = 1.0 / (weights.gyro_random_walk * weights.gyro_random_walk * h);
    let wa = 1.0 / (weights.accel_random_walk * weights.accel_random_walk * h);
    let mut cost = 0.0;
    let mut terms = Vec::new();
    for j in 1..state.gyro_bias.values.len() {
        let dg = state.gyro_bias.values[j] - state.gyro_bias.values[j - 1];
        let da = state.accel_bias.values[j] - state.accel_bias.values[j - 1];
        cost += wg * dg.norm_squared() + wa * da.norm_squared();
        terms.push((j, dg, da));
    }
    if let Some(normal) = normal {
        let ng = layout.ng;
        for (j, dg, da) in terms {
            for a in 0..BIAS_DIM {
                let (w, r) = if a < 3 { (wg, dg[a]) } else { (wa, da[a - 3]) };
                let i1 = layout.bias + BIAS_DIM * j + a;
                let i0 = layout.bias + BIAS_DIM * (j - 1) + a;
                normal.dense[i1 * ng + i1] += w;
                normal.dense[i0 * ng + i0] += w;
                normal.dense[i1 * ng + i0] -= w;
                normal.gg[i1] += w * r;
                normal.gg[i0] -= w * r;
            }
        }
        normal.cost += cost;
    }
    cost
}

/// Total cost of a state. Terms are evaluated in parallel and summed in a fixed order, so the
/// same state always gives the same bits (Levenberg–Marquardt's accept/reject decisions rest
/// on it).
pub fn cost(problem: &Problem<'_>, state: &State) -> f64 {
    let layout = Layout::new(state);
    let w = &problem.weights;
    let frames: Vec<(usize, usize)> = frame_items(problem);
    let frame_costs: Vec<f64> = frames
        .par_iter()
        .map(|&(l, k)| {
            let obs = &problem.lenses[l];
            frame_terms(state, &layout, l, obs, &obs.frames[k], w, None)
        })
        .collect();
    let imu_costs: Vec<f64> = problem
        .imu
        .par_chunks(IMU_COST_CHUNK)
        .map(|c| {
            c.iter()
                .map(|s| imu_terms(state, &layout, s, w, None))
                .sum::<f64>()
        })
        .collect();
    frame_costs.iter().sum::<f64>()
        + imu_costs.iter().sum::<f64>()
        + bias_prior(state, &layout, w, None)
}

/// Every (lens, frame) pair of the problem, in order.
fn frame_items(problem: &Problem<'_>) -> Vec<(usize, usize)> {
    problem
        .lenses
        .iter()
        .enumerate()
        .flat_map(|(l, o)| (0..o.frames.len()).map(move |k| (l, k)))
        .collect()
}

fn build(problem: &Problem<'_>, state: &State, layout: &Layout) -> Normal {
    let w = &problem.weights;
    // Work items: (lens, frame) pairs and IMU sample ranges, split into a fixed number of
    // pieces, each filling one accumulator; the accumulators are merged in piece order.
    let frames = frame_items(problem);
    let frame_piece = frames.len().div_ceil(ACCUMULATION_PIECES).max(1);
    let imu_piece = problem.imu.len().div_ceil(ACCUMULATION_PIECES).max(1);
    let pieces: Vec<Normal> = (0..ACCUMULATION_PIECES)
        .into_par_iter()
        .map(|c| {
            let mut n = Normal::new(layout.ns, layout.ng);
            for &(l, k) in frames.iter().skip(c * frame_piece).take(frame_piece) {
                let obs = &problem.lenses[l];
                frame_terms(state, layout, l, obs, &obs.frames[k], w, Some(&mut n));
            }
            for s in problem.imu.iter().skip(c * imu_piece).take(imu_piece) {
                imu_terms(state, layout, s, w, Some(&mut n));
            }
            n
        })
        .collect();
    let mut pieces = pieces.into_iter();
    let mut normal = pieces
        .next()
        .unwrap_or_else(|| Normal::new(layout.ns, layout.ng));
    for piece in pieces {
        normal = normal.merge(&piece);
    }
    bias_prior(state, layout, w, Some(&mut normal));
    normal
}

/// In-place banded Cholesky of the lower band (`band[i·BAND + (i − j)]`); false if not SPD.
fn band_cholesky(band: &mut [f64], n: usize) -> bool {
    for i in 0..n {
        let j0 = i.saturating_sub(BAND - 1);
        for j in j0..=i {
            let mut s = band[i * BAND + (i - j)];
            let k0 = j0.max(j.saturating_sub(BAND - 1));
            for k in k0..j {
                s -= band[i * BAND + (i - k)] * band[j * BAND + (j - k)];
            }
            if i == j {
                if s.is_nan() || s <= 0.0 {
                    return false;
                }
                band[i * BAND] = s.sqrt();
            } else {
                band[i * BAND + (i - j)] = s / band[j * BAND];
            }
        }
    }
    true
}

/// Solve `L Lᵀ X = B` in place for a row-major `n × cols` right-hand side.
fn band_solve(l: &[f64], n: usize, x: &mut [f64], cols: usize) {
    let mut acc = vec![0.0; cols];
    for i in 0..n {
        acc.copy_from_slice(&x[i * cols..(i + 1) * cols]);
        for k in i.saturating_sub(BAND - 1)..i {
            let lik = l[i * BAND + (i - k)];
            if lik != 0.0 {
                for c in 0..cols {
                    acc[c] -= lik * x[k * cols + c];
                }
            }
        }
        let d = l[i * BAND];
        for c in 0..cols {
            x[i * cols + c] = acc[c] / d;
        }
    }
    for i in (0..n).rev() {
        acc.copy_from_slice(&x[i * cols..(i + 1) * cols]);
        for k in i + 1..(i + BAND).min(n) {
            let lki = l[k * BAND + (k - i)];
            if lki != 0.0 {
                for c in 0..cols {
                    acc[c] -= lki * x[k * cols + c];
                }
            }
        }
        let d = l[i * BAND];
        for c in 0..cols {
            x[i * cols + c] = acc[c] / d;
        }
    }
}

/// Cholesky-factor a dense SPD matrix with faer and solve for `rhs` in place.
fn dense_solve(s: &mut Mat<f64>, rhs: &mut Mat<f64>) -> bool {
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
        rhs.as_mut(),
        Par::Seq,
    );
    faer::linalg::triangular_solve::solve_upper_triangular_in_place(
        s.as_ref().transpose(),
        rhs.as_mut(),
        Par::Seq,
    );
    (0..rhs.ncols()).all(|c| rhs.col(c).iter().all(|v| v.is_finite()))
}

/// The Schur complement of the spline block, `S = C − Bᵀ A⁻¹ B`, and `A⁻¹ B`, with damping.
struct Reduced {
    band: Vec<f64>,
    ainv_b: Vec<f64>,
    schur: Mat<f64>,
}

fn reduce(normal: &Normal, lambda: f64) -> Option<Reduced> {
    let (ns, ng) = (normal.ns, normal.ng);
    let mut band = normal.band.clone();
    for i in 0..ns {
        band[i * BAND] = band[i * BAND] * (1.0 + lambda) + 1e-9;
    }
    if !band_cholesky(&mut band, ns) {
        return None;
    }
    let mut ainv_b = normal.cross.clone();
    band_solve(&band, ns, &mut ainv_b, ng);
    let mut schur = Mat::<f64>::zeros(ng, ng);
    // Bᵀ A⁻¹ B, accumulated in parallel over a fixed number of row blocks of the spline and
    // summed in block order.
    let rows = ns.div_ceil(ACCUMULATION_PIECES).max(1);
    let parts: Vec<Vec<f64>> = (0..ns)
        .step_by(rows)
        .collect::<Vec<_>>()
        .par_iter()
        .map(|&r0| {
            let mut acc = vec![0.0; ng * ng];
            for i in r0..(r0 + rows).min(ns) {
                let b = &normal.cross[i * ng..(i + 1) * ng];
                let y = &ainv_b[i * ng..(i + 1) * ng];
                for p in 0..ng {
                    if b[p] == 0.0 {
                        continue;
                    }
                    for q in 0..ng {
                        acc[p * ng + q] += b[p] * y[q];
                    }
                }
            }
            acc
        })
        .collect();
    for p in 0..ng {
        for q in 0..ng {
            let (a, b) = if p >= q { (p, q) } else { (q, p) };
            let mut v = normal.dense[a * ng + b];
            if p == q {
                v = v * (1.0 + lambda) + 1e-12;
            }
            schur[(p, q)] = v - parts.iter().map(|acc| acc[p * ng + q]).sum::<f64>();
        }
    }
    Some(Reduced {
        band,
        ainv_b,
        schur,
    })
}

/// Solve the damped normal equations for the step `(δ_spline, δ_global)`.
fn solve_step(normal: &Normal, lambda: f64) -> Option<(Vec<f64>, Vec<f64>)> {
    let (ns, ng) = (normal.ns, normal.ng);
    let red = reduce(normal, lambda)?;
    // A⁻¹ g_s.
    let mut ainv_g = normal.gs.clone();
    band_solve(&red.band, ns, &mut ainv_g, 1);
    let mut rhs = Mat::<f64>::zeros(ng, 1);
    for p in 0..ng {
        let mut v = normal.gg[p];
        for i in 0..ns {
            v -= normal.cross[i * ng + p] * ainv_g[i];
        }
        rhs[(p, 0)] = -v;
    }
    let mut schur = red.schur;
    if !dense_solve(&mut schur, &mut rhs) {
        return None;
    }
    let dg: Vec<f64> = (0..ng).map(|p| rhs[(p, 0)]).collect();
    // δ_s = −A⁻¹ g_s − A⁻¹ B δ_g.
    let ds: Vec<f64> = (0..ns)
        .map(|i| {
            let y = &red.ainv_b[i * ng..(i + 1) * ng];
            -ainv_g[i] - y.iter().zip(&dg).map(|(a, b)| a * b).sum::<f64>()
        })
        .collect();
    Some((ds, dg))
}

/// The state moved by a step.
fn apply(state: &State, layout: &Layout, ds: &[f64], dg: &[f64]) -> State {
    let mut s = state.clone();
    for j in 0..s.spline.len() {
        let d = &ds[CTRL_DIM * j..CTRL_DIM * j + CTRL_DIM];
        s.spline.rotations[j] *= so3_exp(&Vector3::new(d[0], d[1], d[2]));
        s.spline.positions[j] += Vector3::new(d[3], d[4], d[5]);
    }
    for (l, lens) in s.lenses.iter_mut().enumerate() {
        let b = layout.lens[l];
        let xi = Vector6::from_column_slice(&dg[b..b + 6]);
        lens.cam_from_imu = se3_exp(&xi) * lens.cam_from_imu;
        lens.time_shift_s += dg[b + 6];
    }
    for (l, board) in s.world_from_board.iter_mut().enumerate() {
        if let Some(b) = layout.board[l] {
            *board *= se3_exp(&Vector6::from_column_slice(&dg[b..b + 6]));
        }
    }
    let e = gravity_basis(&state.gravity);
    let dgrav = e * nalgebra::Vector2::new(dg[layout.gravity], dg[layout.gravity + 1]);
    s.gravity = so3_exp(&dgrav) * state.gravity;
    for j in 0..s.gyro_bias.values.len() {
        let b = layout.bias + BIAS_DIM * j;
        s.gyro_bias.values[j] += Vector3::new(dg[b], dg[b + 1], dg[b + 2]);
        s.accel_bias.values[j] += Vector3::new(dg[b + 3], dg[b + 4], dg[b + 5]);
    }
    s
}

/// How the optimisation went.
#[derive(Debug, Clone)]
pub struct SolveSummary {
    /// Levenberg–Marquardt iterations.
    pub iterations: usize,
    /// Cost before and after.
    pub initial_cost: f64,
    /// Final cost.
    pub final_cost: f64,
    /// Covariance of the global parameters (unscaled inverse of the Schur complement), and the
    /// index of each lens's block in it.
    pub covariance: Option<Mat<f64>>,
    /// Offsets of each lens's 7 parameters (`cam_from_imu` left perturbation, time shift).
    pub lens_offsets: Vec<usize>,
}

/// Levenberg–Marquardt from `state`; returns the refined state.
pub fn optimize(
    problem: &Problem<'_>,
    mut state: State,
    max_iterations: usize,
    with_covariance: bool,
    on_iteration: &dyn Fn(usize, f64),
) -> (State, SolveSummary) {
    let mut current = cost(problem, &state);
    let initial_cost = current;
    let mut lambda = 1e-6;
    let mut iterations = 0;
    for it in 0..max_iterations {
        iterations = it + 1;
        let layout = Layout::new(&state);
        let normal = build(problem, &state, &layout);
        let mut improved = false;
        let mut trials = 0;
        while lambda < MAX_LAMBDA && trials < MAX_TRIALS {
            trials += 1;
            let Some((ds, dg)) = solve_step(&normal, lambda) else {
                lambda *= 10.0;
                continue;
            };
            let candidate = apply(&state, &layout, &ds, &dg);
            let c = cost(problem, &candidate);
            if c.is_finite() && c < current {
                let decrease = (current - c) / current.max(f64::MIN_POSITIVE);
                state = candidate;
                current = c;
                lambda = (lambda / 10.0).max(1e-9);
                improved = decrease > COST_TOLERANCE;
                break;
            }
            lambda *= 10.0;
        }
        on_iteration(iterations, current);
        if !improved {
            break;
        }
    }
    let layout = Layout::new(&state);
    let covariance = with_covariance.then(|| build(problem, &state, &layout));
    let covariance = covariance
        .as_ref()
        .and_then(|normal| reduce(normal, 0.0))
        .and_then(|red| {
            let ng = layout.ng;
            let mut s = red.schur;
            let mut id = Mat::<f64>::identity(ng, ng);
            dense_solve(&mut s, &mut id).then_some(id)
        });
    (
        state,
        SolveSummary {
            iterations,
            initial_cost,
            final_cost: current,
            covariance,
            lens_offsets: layout.lens.clone(),
        },
    )
}

/// Per-corner pixel residuals of a state: `(lens, frame index in frames.csv, time, residual)`.
pub fn corner_residuals(
    problem: &Problem<'_>,
    state: &State,
) -> Vec<(usize, usize, f64, nalgebra::Vector2<f64>)> {
    let mut out = Vec::new();
    for (l, obs) in problem.lenses.iter().enumerate() {
        let lens = &state.lenses[l];
        for f in &obs.frames {
            let t_ref = f.t + lens.time_shift_s + f.row_delay_s;
            let Some(st) = state.spline.state(t_ref) else {
                continue;
            };
            let motion = FrameMotion::new(&state.spline, &st, t_ref);
            for c in &f.corners {
                let (r, p) = motion.at(c.row_delay_s - f.row_delay_s);
                let pw = state.world_from_board[l] * nalgebra::Point3::from(c.board);
                let pi = r.inverse() * (pw.coords - p);
                let pc = lens.cam_from_imu * nalgebra::Point3::from(pi);
                if let Some(px) = obs.camera.project(&pc.coords) {
                    out.push((l, f.index, f.t, px.coords - c.pixel));
                }
            }
        }
    }
    out
}

/// Gyro and accelerometer residuals at every `stride`-th sample: `(t, gyro, accel)`.
pub fn imu_residuals(
    problem: &Problem<'_>,
    state: &State,
    stride: usize,
) -> Vec<(f64, Vector3<f64>, Vector3<f64>)> {
    problem
        .imu
        .iter()
        .step_by(stride.max(1))
        .filter_map(|s| {
            let st = state.spline.state(s.t)?;
            let bg = state.gyro_bias.value(s.t);
            let ba = state.accel_bias.value(s.t);
            let f = st.rotation.inverse() * (st.acceleration - state.gravity);
            Some((s.t, st.omega + bg - s.gyro, f + ba - s.accel))
        })
        .collect()
}
