//! Levenberg–Marquardt on a chain of 15-dimensional navigation states.
//!
//! The graph has one `CombinedImuFactor` between every pair of consecutive nodes plus unary
//! factors (robust pose observations, the initial velocity prior and the bias prior), so the
//! Gauss–Newton system is block-tridiagonal with 15×15 blocks. It is solved by block Cholesky
//! elimination along the chain (a Kalman/RTS-like sweep), O(N) in time and memory, on
//! stack-allocated fixed-size blocks: nothing is allocated inside the iterations. The same
//! elimination yields the diagonal blocks of the inverse Hessian (per-node marginal
//! covariances) by a backward selected-inversion sweep.

use nalgebra::{Cholesky, Matrix3, SMatrix, Vector3};

use kiwi_core::geometry::Pose;

use super::factors::{NavNode, Vector6, huber_loss, huber_weight, imu_linearize, pose_linearize};
use super::preint::{ImuBias, Matrix15, Preintegrated, Vector15};

/// A robust unary pose factor on one node: `Log_SE3(Z⁻¹ T)` with diagonal sigmas and Huber.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PoseFactor {
    /// The node it constrains.
    pub node: usize,
    /// The observed pose `Z` (same frames as the node pose).
    pub z: Pose,
    /// Rotation sigma (rad).
    pub sigma_rot: f64,
    /// Position sigma (m).
    pub sigma_pos: f64,
    /// Caller's tag (e.g. the observation source).
    pub tag: u8,
}

/// How the IMU factor's noise model is built from its residual covariance.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ImuNoiseModel {
    /// The full 15×15 covariance (correct; the default).
    #[default]
    Full,
    /// GTSAM's `noiseModel::Gaussian::Covariance(Σ, smart = true)`: when every off-diagonal
    /// entry is at most [`GTSAM_DIAGONAL_TOLERANCE`] in absolute value the covariance is replaced
    /// by its diagonal. At camera rates all entries are that small, so GTSAM silently drops the
    /// correlations; this mode reproduces it for like-for-like comparisons.
    GtsamSmart,
}

/// GTSAM's `checkIfDiagonal` threshold on off-diagonal covariance entries.
pub const GTSAM_DIAGONAL_TOLERANCE: f64 = 1e-9;

/// Information matrix of an IMU factor's residual covariance under `model`.
pub fn imu_information(cov: &Matrix15, model: ImuNoiseModel) -> Matrix15 {
    let diagonal = model == ImuNoiseModel::GtsamSmart
        && (0..15).all(|i| (i + 1..15).all(|j| cov[(i, j)].abs() <= GTSAM_DIAGONAL_TOLERANCE));
    if diagonal {
        Matrix15::from_diagonal(&cov.diagonal().map(|v| if v > 0.0 { 1.0 / v } else { 0.0 }))
    } else {
        Cholesky::new(*cov).map_or_else(Matrix15::zeros, |c| c.inverse())
    }
}

/// The whitened cost `½ Σ rᵀ Σ⁻¹ r` of the IMU factors between consecutive `nodes`.
pub(crate) fn imu_cost(
    imu: &[Preintegrated],
    imu_info: &[Matrix15],
    gravity: &Vector3<f64>,
    nodes: &[NavNode],
) -> f64 {
    imu.iter()
        .enumerate()
        .map(|(k, pim)| {
            let r = imu_linearize(pim, gravity, &nodes[k], &nodes[k + 1], false).residual;
            0.5 * (r.transpose() * imu_info[k] * r)[0]
        })
        .sum()
}

/// Add the IMU factor between nodes `k` and `k + 1` to the block-tridiagonal normal equations
/// (`diag`, `off`) and return its gradient contributions to the two nodes.
pub(crate) fn accumulate_imu(
    pim: &Preintegrated,
    info: &Matrix15,
    gravity: &Vector3<f64>,
    nodes: &[NavNode],
    k: usize,
    diag: &mut [Matrix15],
    off: &mut Matrix15,
) -> (Vector15, Vector15) {
    let lin = imu_linearize(pim, gravity, &nodes[k], &nodes[k + 1], true);
    let wi = lin.jac_i.transpose() * info;
    let wj = lin.jac_j.transpose() * info;
    diag[k] += wi * lin.jac_i;
    diag[k + 1] += wj * lin.jac_j;
    *off += wi * lin.jac_j;
    (wi * lin.residual, wj * lin.residual)
}

/// A chain problem: initial states, IMU factors between neighbours, unary factors.
#[derive(Debug, Clone)]
pub struct ChainProblem {
    /// Gravity in the world frame (m/s²).
    pub gravity: Vector3<f64>,
    /// Initial node states.
    pub nodes: Vec<NavNode>,
    /// Preintegrated IMU between node `k` and `k + 1` (length `nodes.len() − 1`).
    pub imu: Vec<Preintegrated>,
    /// Pose factors, sorted by node.
    pub pose_factors: Vec<PoseFactor>,
    /// Huber threshold on the whitened pose-residual norm (`None`: plain least squares).
    pub huber_k: Option<f64>,
    /// Noise model of the IMU factors.
    pub imu_noise: ImuNoiseModel,
    /// Prior `(mean, sigma)` on the first node's velocity.
    pub velocity_prior: Option<(Vector3<f64>, f64)>,
    /// Prior `(mean, sigma_acc, sigma_gyro)` on the first node's biases.
    pub bias_prior: Option<(ImuBias, f64, f64)>,
}

/// Stopping rules of the solver.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LmSettings {
    /// Maximum number of accepted-or-rejected linearizations.
    pub max_iterations: usize,
    /// Stop when the relative cost decrease falls below this.
    pub relative_tolerance: f64,
    /// Stop when the cost falls below this.
    pub absolute_tolerance: f64,
    /// Initial damping.
    pub lambda_initial: f64,
    /// Compute per-node marginal covariances at the solution.
    pub marginals: bool,
}

impl Default for LmSettings {
    fn default() -> Self {
        Self {
            max_iterations: 100,
            relative_tolerance: 1e-10,
            absolute_tolerance: 1e-12,
            lambda_initial: 1e-5,
            marginals: true,
        }
    }
}

/// The solution of a chain problem.
#[derive(Debug, Clone)]
pub struct ChainSolution {
    /// Optimised states.
    pub nodes: Vec<NavNode>,
    /// Marginal 15×15 covariance of each node (empty unless requested).
    pub marginals: Vec<Matrix15>,
    /// Final Huber weight of each pose factor (1 = fully trusted).
    pub pose_weights: Vec<f64>,
    /// Linearizations performed.
    pub iterations: usize,
    /// Cost at the initial values (GTSAM's `graph.error`).
    pub initial_cost: f64,
    /// Cost at the solution.
    pub final_cost: f64,
}

/// Damping floor relative to each diagonal entry (Marquardt scaling with a minimum).
pub(crate) const MIN_DIAGONAL: f64 = 1e-6;
/// Give up raising lambda past this (the step is then below numerical resolution).
pub(crate) const MAX_LAMBDA: f64 = 1e10;

/// Working storage of the block-tridiagonal system, allocated once per solve.
struct System {
    diag: Vec<Matrix15>,
    off: Vec<Matrix15>,
    grad: Vec<Vector15>,
    gain: Vec<Matrix15>,
    factor: Vec<Matrix15>,
    rhs: Vec<Vector15>,
    step: Vec<Vector15>,
    imu_info: Vec<Matrix15>,
}

impl ChainProblem {
    fn cost(&self, nodes: &[NavNode], imu_info: &[Matrix15]) -> f64 {
        let mut cost = imu_cost(&self.imu, imu_info, &self.gravity, nodes);
        for f in &self.pose_factors {
            let (e, _) = pose_linearize(&f.z, &nodes[f.node]);
            let s = whitened_norm(&e, f);
            cost += match self.huber_k {
                Some(k) => huber_loss(s, k),
                None => 0.5 * s * s,
            };
        }
        if let Some((mean, sigma)) = self.velocity_prior {
            cost += 0.5 * ((nodes[0].velocity - mean) / sigma).norm_squared();
        }
        if let Some((mean, sa, sg)) = self.bias_prior {
            cost += 0.5 * ((nodes[0].bias.acc - mean.acc) / sa).norm_squared();
            cost += 0.5 * ((nodes[0].bias.gyro - mean.gyro) / sg).norm_squared();
        }
        cost
    }

    fn linearize(&self, nodes: &[NavNode], sys: &mut System) {
        for m in sys.diag.iter_mut().chain(sys.off.iter_mut()) {
            m.fill(0.0);
        }
        for g in &mut sys.grad {
            g.fill(0.0);
        }
        for (k, pim) in self.imu.iter().enumerate() {
            let (gi, gj) = accumulate_imu(
                pim,
                &sys.imu_info[k],
                &self.gravity,
                nodes,
                k,
                &mut sys.diag,
                &mut sys.off[k],
            );
            sys.grad[k] += gi;
            sys.grad[k + 1] += gj;
        }
        for f in &self.pose_factors {
            let (e, jac) = pose_linearize(&f.z, &nodes[f.node]);
            let w = match self.huber_k {
                Some(k) => huber_weight(whitened_norm(&e, f), k),
                None => 1.0,
            };
            let mut info = Vector6::zeros();
            for i in 0..3 {
                info[i] = w / (f.sigma_rot * f.sigma_rot);
                info[3 + i] = w / (f.sigma_pos * f.sigma_pos);
            }
            // Only the leading 6×6 block of the Jacobian is non-zero.
            let j6 = jac.fixed_view::<6, 6>(0, 0).into_owned();
            let jt_w = j6.transpose() * nalgebra::Matrix6::from_diagonal(&info);
            let h = jt_w * j6;
            let g = jt_w * e;
            let n = f.node;
            let mut d = sys.diag[n].fixed_view_mut::<6, 6>(0, 0);
            d += h;
            let mut gv = sys.grad[n].fixed_view_mut::<6, 1>(0, 0);
            gv += g;
        }
        if let Some((mean, sigma)) = self.velocity_prior {
            let w = 1.0 / (sigma * sigma);
            let r = nodes[0].velocity - mean;
            for i in 0..3 {
                sys.diag[0][(6 + i, 6 + i)] += w;
                sys.grad[0][6 + i] += w * r[i];
            }
        }
        if let Some((mean, sa, sg)) = self.bias_prior {
            let ra = nodes[0].bias.acc - mean.acc;
            let rg = nodes[0].bias.gyro - mean.gyro;
            for i in 0..3 {
                sys.diag[0][(9 + i, 9 + i)] += 1.0 / (sa * sa);
                sys.grad[0][9 + i] += ra[i] / (sa * sa);
                sys.diag[0][(12 + i, 12 + i)] += 1.0 / (sg * sg);
                sys.grad[0][12 + i] += rg[i] / (sg * sg);
            }
        }
    }

    /// Solve `(H + λ diag(H)) δ = −g` by block elimination; `false` if not positive definite.
    fn solve(sys: &mut System, lambda: f64) -> bool {
        let n = sys.diag.len();
        for k in 0..n {
            let mut s = sys.diag[k];
            for i in 0..15 {
                s[(i, i)] += lambda * sys.diag[k][(i, i)].max(MIN_DIAGONAL);
            }
            let mut y = -sys.grad[k];
            if k > 0 {
                s -= sys.off[k - 1].transpose() * sys.gain[k - 1];
                y -= sys.gain[k - 1].transpose() * sys.rhs[k - 1];
            }
            let Some(chol) = Cholesky::new(s) else {
                return false;
            };
            sys.factor[k] = chol.l();
            sys.rhs[k] = y;
            if k + 1 < n {
                sys.gain[k] = chol.solve(&sys.off[k]);
            }
            sys.step[k] = chol.solve(&y);
        }
        for k in (0..n.saturating_sub(1)).rev() {
            let next = sys.step[k + 1];
            sys.step[k] -= sys.gain[k] * next;
        }
        true
    }

    /// Minimise the robust cost by Levenberg–Marquardt.
    pub fn solve_lm(&self, settings: &LmSettings) -> ChainSolution {
        let n = self.nodes.len();
        let imu_info: Vec<Matrix15> = self
            .imu
            .iter()
            .map(|p| imu_information(&p.residual_cov(), self.imu_noise))
            .collect();
        let mut sys = System {
            diag: vec![Matrix15::zeros(); n],
            off: vec![Matrix15::zeros(); n.saturating_sub(1)],
            grad: vec![Vector15::zeros(); n],
            gain: vec![Matrix15::zeros(); n.saturating_sub(1)],
            factor: vec![Matrix15::zeros(); n],
            rhs: vec![Vector15::zeros(); n],
            step: vec![Vector15::zeros(); n],
            imu_info,
        };
        let mut nodes = self.nodes.clone();
        let mut trial = nodes.clone();
        let initial_cost = self.cost(&nodes, &sys.imu_info);
        let mut cost = initial_cost;
        let mut lambda = settings.lambda_initial;
        let mut iterations = 0;
        while iterations < settings.max_iterations && cost > settings.absolute_tolerance {
            iterations += 1;
            self.linearize(&nodes, &mut sys);
            let mut improved = false;
            let mut converged = false;
            while lambda < MAX_LAMBDA {
                if !Self::solve(&mut sys, lambda) {
                    lambda *= 10.0;
                    continue;
                }
                for k in 0..n {
                    trial[k] = nodes[k].retract(&sys.step[k]);
                }
                let new_cost = self.cost(&trial, &sys.imu_info);
                if new_cost <= cost {
                    let decrease = cost - new_cost;
                    std::mem::swap(&mut nodes, &mut trial);
                    converged = decrease <= settings.relative_tolerance * cost;
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
        let mut marginals = Vec::new();
        if settings.marginals {
            self.linearize(&nodes, &mut sys);
            if Self::solve(&mut sys, 0.0) {
                marginals = Self::marginals(&sys);
            }
        }
        let pose_weights = self
            .pose_factors
            .iter()
            .map(|f| match self.huber_k {
                Some(k) => {
                    huber_weight(whitened_norm(&pose_linearize(&f.z, &nodes[f.node]).0, f), k)
                }
                None => 1.0,
            })
            .collect();
        ChainSolution {
            nodes,
            marginals,
            pose_weights,
            iterations,
            initial_cost,
            final_cost: cost,
        }
    }

    /// Diagonal blocks of `H⁻¹` from the factored system (selected inversion).
    fn marginals(sys: &System) -> Vec<Matrix15> {
        let n = sys.factor.len();
        let mut out = vec![Matrix15::zeros(); n];
        for k in (0..n).rev() {
            let l = &sys.factor[k];
            let s_inv = cholesky_inverse(l);
            out[k] = if k + 1 < n {
                let g = &sys.gain[k];
                s_inv + g * out[k + 1] * g.transpose()
            } else {
                s_inv
            };
        }
        out
    }
}

/// `(L Lᵀ)⁻¹` from a Cholesky factor `L` (zeros if `L` is singular).
pub(crate) fn cholesky_inverse(l: &Matrix15) -> Matrix15 {
    let mut inv = Matrix15::identity();
    if l.solve_lower_triangular_mut(&mut inv) {
        inv.transpose() * inv
    } else {
        Matrix15::zeros()
    }
}

fn whitened_norm(e: &Vector6, f: &PoseFactor) -> f64 {
    let r = Vector3::new(e[0], e[1], e[2]) / f.sigma_rot;
    let p = Vector3::new(e[3], e[4], e[5]) / f.sigma_pos;
    (r.norm_squared() + p.norm_squared()).sqrt()
}

/// Position (m) and rotation (rad) standard deviations from a node's marginal covariance, as the
/// square roots of the traces of the 3×3 blocks (the RMS error over the three axes × √3).
pub fn pose_sigmas(cov6: &SMatrix<f64, 6, 6>) -> (f64, f64) {
    let rot: Matrix3<f64> = cov6.fixed_view::<3, 3>(0, 0).into_owned();
    let pos: Matrix3<f64> = cov6.fixed_view::<3, 3>(3, 3).into_owned();
    (pos.trace().max(0.0).sqrt(), rot.trace().max(0.0).sqrt())
}
