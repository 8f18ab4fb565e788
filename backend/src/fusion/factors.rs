//! Factors of the per-wrist graph: GTSAM's `CombinedImuFactor` between consecutive nodes and a
//! unary pose factor (`PriorFactor<Pose3>`) per visual observation, plus the Huber weight.
//!
//! A node's state is `x = (R, p, v, b_a, b_g)` with tangent `[δθ, δp, δv, δb_a, δb_g]`
//! (15-dimensional) and retraction `R Exp(δθ)`, `p + R δp`, `v + δv`, `b + δb`: the first-order
//! `Pose3` chart, whose Jacobians at zero equal GTSAM's `Pose3::Expmap` ones, so residuals,
//! Jacobians and optima are those of GTSAM.
//!
//! - IMU residual (GTSAM 4.3 `CombinedImuFactor::evaluateError`), order `[rot, pos, vel,
//!   bias_acc, bias_gyro]`: the navigation part is the SE_2(3) logarithm
//!   `Log(X_j⁻¹ X̂_j)` of the predicted state `X̂_j = (R_i ΔR̃, p_i + v_i Δt + ½ g Δt² + R_i Δp̃,
//!   v_i + g Δt + R_i Δṽ)` relative to `X_j`, i.e. `φ = Log(R_jᵀ R̂)`, `ρ = J_l(φ)⁻¹ R_jᵀ(p̂ − p_j)`,
//!   `ν = J_l(φ)⁻¹ R_jᵀ(v̂ − v_j)`; the bias part is `b_i − b_j`. `~` marks deltas corrected for
//!   `b_i`; the noise model is [`Preintegrated::residual_cov`](super::preint::Preintegrated::residual_cov).
//! - Pose residual: `e = Log_SE3(Z⁻¹ T)` (`[rot; trans]`), diagonal sigmas, Huber on the whitened
//!   norm (GTSAM `noiseModel::Robust` with `mEstimator::Huber`, block reweighting).

use kiwi_core::geometry::{
    Pose, hat, se3_log, se3_right_jacobian_inv, so3_left_jacobian_inv, so3_log, so3_right_jacobian,
    tangent,
};
use nalgebra::{Isometry3, Matrix3, Rotation3, SMatrix, Translation3, UnitQuaternion, Vector3};

use super::preint::{ImuBias, Matrix15, Preintegrated, Vector15};

/// A 6-vector `[rot; trans]`.
pub type Vector6 = nalgebra::Vector6<f64>;
/// A 6×15 pose-factor Jacobian.
pub type Matrix6x15 = SMatrix<f64, 6, 15>;

/// A navigation state: `world_from_body` attitude and position, world velocity and biases.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NavNode {
    /// Attitude `world_from_body` as a rotation matrix.
    pub rotation: Matrix3<f64>,
    /// Position in the world (m).
    pub position: Vector3<f64>,
    /// Velocity in the world (m/s).
    pub velocity: Vector3<f64>,
    /// IMU biases.
    pub bias: ImuBias,
}

impl NavNode {
    /// A node at `pose` with velocity `velocity` and zero biases.
    pub fn from_pose(pose: &Pose, velocity: Vector3<f64>) -> Self {
        Self {
            rotation: pose.rotation.to_rotation_matrix().into_inner(),
            position: pose.translation.vector,
            velocity,
            bias: ImuBias::default(),
        }
    }

    /// The pose `world_from_body`.
    pub fn pose(&self) -> Pose {
        let q =
            UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(self.rotation));
        Isometry3::from_parts(Translation3::from(self.position), q)
    }

    /// Apply a tangent step.
    pub fn retract(&self, d: &Vector15) -> Self {
        let dth = Vector3::new(d[0], d[1], d[2]);
        let dp = Vector3::new(d[3], d[4], d[5]);
        let dv = Vector3::new(d[6], d[7], d[8]);
        let rot = self.rotation * rotation_matrix(&dth);
        Self {
            // Re-orthonormalise through the quaternion to stop drift over many iterations.
            rotation: orthonormalize(&rot),
            position: self.position + self.rotation * dp,
            velocity: self.velocity + dv,
            bias: ImuBias {
                acc: self.bias.acc + Vector3::new(d[9], d[10], d[11]),
                gyro: self.bias.gyro + Vector3::new(d[12], d[13], d[14]),
            },
        }
    }
}

/// `Exp(φ)` as a matrix.
pub fn rotation_matrix(phi: &Vector3<f64>) -> Matrix3<f64> {
    kiwi_core::geometry::so3_exp(phi)
        .to_rotation_matrix()
        .into_inner()
}

/// `Log(R)` of a rotation matrix.
pub fn rotation_log(r: &Matrix3<f64>) -> Vector3<f64> {
    so3_log(&UnitQuaternion::from_rotation_matrix(
        &Rotation3::from_matrix_unchecked(*r),
    ))
}

fn orthonormalize(r: &Matrix3<f64>) -> Matrix3<f64> {
    UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(*r))
        .to_rotation_matrix()
        .into_inner()
}

/// Residual and Jacobians of one `CombinedImuFactor`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ImuLinearization {
    /// Unwhitened residual `[rot, pos, vel, bias_acc, bias_gyro]`.
    pub residual: Vector15,
    /// ∂r/∂x_i.
    pub jac_i: Matrix15,
    /// ∂r/∂x_j.
    pub jac_j: Matrix15,
}

/// The unwhitened `CombinedImuFactor` residual between `xi` and `xj`.
pub fn imu_residual(
    pim: &Preintegrated,
    gravity: &Vector3<f64>,
    xi: &NavNode,
    xj: &NavNode,
) -> Vector15 {
    imu_linearize(pim, gravity, xi, xj, false).residual
}

/// Residual and (if `jacobians`) Jacobians of the `CombinedImuFactor` between `xi` and `xj`.
pub fn imu_linearize(
    pim: &Preintegrated,
    gravity: &Vector3<f64>,
    xi: &NavNode,
    xj: &NavNode,
    jacobians: bool,
) -> ImuLinearization {
    let c = pim.corrected(&xi.bias);
    let dt = pim.dt;
    let ri = &xi.rotation;
    let rj_t = xj.rotation.transpose();
    let r_pred = ri * c.delta_r;
    let e = rj_t * r_pred;
    let phi = rotation_log(&e);
    let p_pred = xi.position + xi.velocity * dt + gravity * (0.5 * dt * dt) + ri * c.delta_p;
    let v_pred = xi.velocity + gravity * dt + ri * c.delta_v;
    // Y = X_j⁻¹ X_pred as an SE_2(3) element (E, a, b); residual = Log_SE23(Y).
    let a = rj_t * (p_pred - xj.position);
    let b = rj_t * (v_pred - xj.velocity);
    let jl_inv = so3_left_jacobian_inv(&phi);
    let rho = jl_inv * a;
    let nu = jl_inv * b;
    let mut residual = Vector15::zeros();
    residual.fixed_view_mut::<3, 1>(0, 0).copy_from(&phi);
    residual.fixed_view_mut::<3, 1>(3, 0).copy_from(&rho);
    residual.fixed_view_mut::<3, 1>(6, 0).copy_from(&nu);
    residual
        .fixed_view_mut::<3, 1>(9, 0)
        .copy_from(&(xi.bias.acc - xj.bias.acc));
    residual
        .fixed_view_mut::<3, 1>(12, 0)
        .copy_from(&(xi.bias.gyro - xj.bias.gyro));
    let mut jac_i = Matrix15::zeros();
    let mut jac_j = Matrix15::zeros();
    if jacobians {
        // Right perturbation of X_pred in its body tangent, per variable of node i.
        let dr_t = c.delta_r.transpose();
        let rp_t = r_pred.transpose();
        let mut d_pred = SMatrix::<f64, 9, 15>::zeros();
        d_pred.fixed_view_mut::<3, 3>(0, 0).copy_from(&dr_t);
        d_pred
            .fixed_view_mut::<3, 3>(3, 0)
            .copy_from(&(-dr_t * hat(&c.delta_p)));
        d_pred
            .fixed_view_mut::<3, 3>(6, 0)
            .copy_from(&(-dr_t * hat(&c.delta_v)));
        d_pred.fixed_view_mut::<3, 3>(3, 3).copy_from(&dr_t);
        d_pred.fixed_view_mut::<3, 3>(3, 6).copy_from(&(rp_t * dt));
        d_pred.fixed_view_mut::<3, 3>(6, 6).copy_from(&rp_t);
        let jr_theta = so3_right_jacobian(&c.theta);
        for (col, h) in [(9, &pim.h_bias_acc), (12, &pim.h_bias_gyro)] {
            d_pred
                .fixed_view_mut::<3, 3>(0, col)
                .copy_from(&(jr_theta * h.fixed_view::<3, 3>(0, 0)));
            d_pred
                .fixed_view_mut::<3, 3>(3, col)
                .copy_from(&(dr_t * h.fixed_view::<3, 3>(3, 0)));
            d_pred
                .fixed_view_mut::<3, 3>(6, col)
                .copy_from(&(dr_t * h.fixed_view::<3, 3>(6, 0)));
        }
        let xi_res = [phi, rho, nu];
        let top_i = se23_right_jacobian_inv(&xi_res) * d_pred;
        // X_j enters as Y = X_j⁻¹ …: a left perturbation −δ_j of Y, J_l⁻¹(ξ) = J_r⁻¹(−ξ).
        let mut d_j = SMatrix::<f64, 9, 15>::zeros();
        for k in 0..6 {
            d_j[(k, k)] = 1.0;
        }
        d_j.fixed_view_mut::<3, 3>(6, 6).copy_from(&rj_t);
        let top_j = -se23_right_jacobian_inv(&[-phi, -rho, -nu]) * d_j;
        jac_i.fixed_view_mut::<9, 15>(0, 0).copy_from(&top_i);
        jac_j.fixed_view_mut::<9, 15>(0, 0).copy_from(&top_j);
        // Bias random walk.
        for k in 9..15 {
            jac_i[(k, k)] = 1.0;
            jac_j[(k, k)] = -1.0;
        }
    }
    ImuLinearization {
        residual,
        jac_i,
        jac_j,
    }
}

/// Inverse right Jacobian of SE_2(3) at `[φ, ρ, ν]`: the SE(3) one applied to `ρ` and `ν`
/// separately (the two translation-like parts do not couple).
pub fn se23_right_jacobian_inv(xi: &[Vector3<f64>; 3]) -> SMatrix<f64, 9, 9> {
    let a = se3_right_jacobian_inv(&tangent(&xi[0], &xi[1]));
    let b = se3_right_jacobian_inv(&tangent(&xi[0], &xi[2]));
    let mut m = SMatrix::<f64, 9, 9>::zeros();
    m.fixed_view_mut::<6, 6>(0, 0).copy_from(&a);
    m.fixed_view_mut::<3, 3>(6, 0)
        .copy_from(&b.fixed_view::<3, 3>(3, 0));
    m.fixed_view_mut::<3, 3>(6, 6)
        .copy_from(&b.fixed_view::<3, 3>(3, 3));
    m
}

/// Residual `Log_SE3(Z⁻¹ T)` of a pose observation `z` of the node pose and its Jacobian with
/// respect to the node's 15-dim tangent (zero outside the pose block).
pub fn pose_linearize(z: &Pose, x: &NavNode) -> (Vector6, Matrix6x15) {
    let err = se3_log(&(z.inverse() * x.pose()));
    let mut jac = Matrix6x15::zeros();
    jac.fixed_view_mut::<6, 6>(0, 0)
        .copy_from(&se3_right_jacobian_inv(&err));
    (err, jac)
}

/// Huber's square-root weight for a whitened residual norm `s` and threshold `k`
/// (GTSAM `mEstimator::Huber::weight`, applied to rows as `√w`).
pub fn huber_weight(s: f64, k: f64) -> f64 {
    if s <= k { 1.0 } else { k / s }
}

/// Huber loss `ρ(s)`: `s²/2` inside the threshold, `k s − k²/2` outside.
pub fn huber_loss(s: f64, k: f64) -> f64 {
    if s <= k {
        0.5 * s * s
    } else {
        k * s - 0.5 * k * k
    }
}
