//! IMU preintegration on the tangent space of SO(3) (Forster et al., TRO 2017, in GTSAM's
//! tangent formulation) with first-order bias correction, numerically identical to GTSAM 4.3's
//! `TangentPreintegration` + `PreintegratedCombinedMeasurements` (the PyPI 4.3 wheels are
//! built with `GTSAM_TANGENT_PREINTEGRATION`).
//!
//! Conventions (GTSAM's, checked by the golden test `estimate_golden`):
//! - a measurement `(acc, omega, dt)` is held constant over `dt` and corrected by the bias
//!   estimate `bias_hat` used for preintegration;
//! - the preintegrated vector `ζ = [θ, Δp, Δv]` (ΔR = Exp(θ); Δp, Δv in the frame at i, gravity
//!   excluded) is updated by `θ ← θ + J_r(θ)⁻¹ ω dt`, `Δp ← Δp + Δv dt + ½ Exp(θ) a dt²`,
//!   `Δv ← Δv + Exp(θ) a dt`;
//! - the 15×15 covariance is ordered `[rotation, position, velocity, bias_acc, bias_gyro]` and
//!   propagated as `Σ ← F Σ Fᵀ + G Q Gᵀ` with the exact Jacobians `A = ∂ζ'/∂ζ`,
//!   `B = ∂ζ'/∂a`, `C = ∂ζ'/∂ω`: `Q` adds `C Σ_g Cᵀ/dt`, `B Σ_a Bᵀ/dt`, the integration
//!   covariance `dt · Σ_int` on the position block and bias random walk `dt · Σ_b`; GTSAM 4.3
//!   has no bias-initialisation term;
//! - the factor's noise model is not `Σ` itself but `residualCovariance()`: `Σ` mapped by
//!   `diag(J_r(θ), ΔRᵀ, ΔRᵀ, −I₆)` into the coordinates of the residual (see
//!   [`Preintegrated::residual_cov`]);
//! - bias Jacobians `∂ζ/∂b_a`, `∂ζ/∂b_g` (9×3 each) follow `H ← A H − B` and `H ← A H − C`;
//!   bias correction is linear in ζ: `ζ̃ = ζ + ∂ζ/∂b_a δb_a + ∂ζ/∂b_g δb_g`, `ΔR̃ = Exp(θ̃)`.

use kiwi_core::geometry::{hat, so3_exp, so3_right_jacobian, so3_right_jacobian_inv};
use nalgebra::{Matrix3, SMatrix, Vector3, Vector6};

/// A 15×15 matrix over `[rotation, position, velocity, bias_acc, bias_gyro]`.
pub type Matrix15 = SMatrix<f64, 15, 15>;
/// A 15-vector over `[rotation, position, velocity, bias_acc, bias_gyro]`.
pub type Vector15 = SMatrix<f64, 15, 1>;
/// A 9×3 Jacobian of the preintegrated vector `[θ, Δp, Δv]`.
pub type Matrix9x3 = SMatrix<f64, 9, 3>;

/// IMU biases, GTSAM's `imuBias::ConstantBias` (vector order `[acc; gyro]`).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ImuBias {
    /// Accelerometer bias (m/s²).
    pub acc: Vector3<f64>,
    /// Gyroscope bias (rad/s).
    pub gyro: Vector3<f64>,
}

impl ImuBias {
    /// `[acc; gyro]`.
    pub fn vector(&self) -> Vector6<f64> {
        Vector6::new(
            self.acc.x,
            self.acc.y,
            self.acc.z,
            self.gyro.x,
            self.gyro.y,
            self.gyro.z,
        )
    }

    /// From `[acc; gyro]`.
    pub fn from_vector(v: &Vector6<f64>) -> Self {
        Self {
            acc: Vector3::new(v[0], v[1], v[2]),
            gyro: Vector3::new(v[3], v[4], v[5]),
        }
    }
}

/// Continuous-time IMU noise and the gravity vector: GTSAM's `PreintegrationCombinedParams`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ImuParams {
    /// Gravity in the navigation frame (m/s²), e.g. `(0, 0, −9.81)` for a z-up frame.
    pub gravity: Vector3<f64>,
    /// Gyro white-noise covariance (rad²/s² · s): noise density squared.
    pub gyro_cov: Matrix3<f64>,
    /// Accelerometer white-noise covariance (m²/s⁴ · s): noise density squared.
    pub acc_cov: Matrix3<f64>,
    /// Integration (position) covariance per second.
    pub integration_cov: Matrix3<f64>,
    /// Accelerometer bias random-walk covariance per second.
    pub bias_acc_cov: Matrix3<f64>,
    /// Gyro bias random-walk covariance per second.
    pub bias_gyro_cov: Matrix3<f64>,
}

/// Integration covariance used with densities from a calibration: small, as in GTSAM's examples.
pub const DEFAULT_INTEGRATION_SIGMA: f64 = 1e-4;

impl ImuParams {
    /// Parameters from continuous-time densities: gyro noise (rad/s/√Hz), gyro random walk
    /// (rad/s²/√Hz), accel noise (m/s²/√Hz), accel random walk (m/s³/√Hz), and gravity
    /// magnitude along −z of the navigation frame.
    pub fn from_densities(gn: f64, gw: f64, an: f64, aw: f64, gravity: f64) -> Self {
        let i = Matrix3::identity();
        Self {
            gravity: Vector3::new(0.0, 0.0, -gravity),
            gyro_cov: i * (gn * gn),
            acc_cov: i * (an * an),
            integration_cov: i * (DEFAULT_INTEGRATION_SIGMA * DEFAULT_INTEGRATION_SIGMA),
            bias_acc_cov: i * (aw * aw),
            bias_gyro_cov: i * (gw * gw),
        }
    }
}

/// Preintegrated IMU measurements between two instants.
#[derive(Debug, Clone, PartialEq)]
pub struct Preintegrated {
    /// Bias used while integrating (`biasHat`).
    pub bias_hat: ImuBias,
    /// Integrated time (s).
    pub dt: f64,
    /// θ with ΔR = Exp(θ) (body frame at i to body frame at the end).
    pub theta: Vector3<f64>,
    /// Δp in the frame at i (m), gravity excluded.
    pub delta_p: Vector3<f64>,
    /// Δv in the frame at i (m/s), gravity excluded.
    pub delta_v: Vector3<f64>,
    /// ∂[θ, Δp, Δv]/∂b_a.
    pub h_bias_acc: Matrix9x3,
    /// ∂[θ, Δp, Δv]/∂b_g.
    pub h_bias_gyro: Matrix9x3,
    /// Covariance of `[δθ, δp, δv, δb_a, δb_g]`.
    pub cov: Matrix15,
}

/// Below this angle the derivative of `J_r(θ) v` uses its Taylor series.
const SERIES_ANGLE: f64 = 1e-3;

/// `∂(J_r(θ) v)/∂θ`, with `J_r(θ) = I − a(t)[θ]× + b(t)[θ]×²`, `t = |θ|`.
fn right_jacobian_apply_derivative(theta: &Vector3<f64>, v: &Vector3<f64>) -> Matrix3<f64> {
    let t2 = theta.norm_squared();
    let t = t2.sqrt();
    // a = (1 − cos t)/t², b = (t − sin t)/t³, and a'(t)/t, b'(t)/t.
    let (a, b, da, db) = if t < SERIES_ANGLE {
        (
            0.5 - t2 / 24.0 + t2 * t2 / 720.0,
            1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0,
            -1.0 / 12.0 + t2 / 180.0 - t2 * t2 / 6720.0,
            -1.0 / 60.0 + t2 / 1260.0 - t2 * t2 / 60480.0,
        )
    } else {
        let (s, c) = t.sin_cos();
        let a = (1.0 - c) / t2;
        let b = (t - s) / (t2 * t);
        (
            a,
            b,
            (s / t2 - 2.0 * a / t) / t,
            ((1.0 - c) / (t2 * t) - 3.0 * b / t) / t,
        )
    };
    let hv = hat(v);
    let tv = theta.dot(v);
    // −a [θ]× v = a [v]× θ;  b [θ]×² v = b (θ (θ·v) − v t²).
    let first = hv * a + (hv * theta) * theta.transpose() * da;
    let inner = theta * tv - v * t2;
    let second = (Matrix3::identity() * tv + theta * v.transpose() - v * theta.transpose() * 2.0)
        * b
        + inner * theta.transpose() * db;
    first + second
}

impl Preintegrated {
    /// Start an empty preintegration with the bias estimate `bias_hat`.
    pub fn new(bias_hat: ImuBias) -> Self {
        Self {
            bias_hat,
            dt: 0.0,
            theta: Vector3::zeros(),
            delta_p: Vector3::zeros(),
            delta_v: Vector3::zeros(),
            h_bias_acc: Matrix9x3::zeros(),
            h_bias_gyro: Matrix9x3::zeros(),
            cov: Matrix15::zeros(),
        }
    }

    /// ΔR = Exp(θ).
    pub fn delta_r(&self) -> Matrix3<f64> {
        so3_exp(&self.theta).to_rotation_matrix().into_inner()
    }

    /// Add one measurement held constant for `dt > 0` seconds (non-positive `dt` is ignored).
    pub fn integrate(
        &mut self,
        params: &ImuParams,
        acc: &Vector3<f64>,
        omega: &Vector3<f64>,
        dt: f64,
    ) {
        if dt.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) {
            return;
        }
        let a = acc - self.bias_hat.acc;
        let w = omega - self.bias_hat.gyro;
        let dt22 = 0.5 * dt * dt;
        let theta = self.theta;
        let jr = so3_right_jacobian(&theta);
        let jr_inv = so3_right_jacobian_inv(&theta);
        let w_tangent = jr_inv * w;
        let rot = so3_exp(&theta).to_rotation_matrix().into_inner();
        let a_nav = rot * a;
        // ∂(J_r⁻¹ w)/∂θ = −J_r⁻¹ ∂(J_r c)/∂θ at c = J_r⁻¹ w.
        let w_tangent_h_theta = -jr_inv * right_jacobian_apply_derivative(&theta, &w_tangent);
        let a_nav_h_theta = rot * hat(&-a) * jr;

        self.theta += w_tangent * dt;
        self.delta_p += self.delta_v * dt + a_nav * dt22;
        self.delta_v += a_nav * dt;
        self.dt += dt;

        // A (9×9) inside F (15×15), B = ∂/∂acc, C = ∂/∂omega.
        let mut f = Matrix15::identity();
        {
            let mut b = f.fixed_view_mut::<3, 3>(0, 0);
            b += w_tangent_h_theta * dt;
        }
        f.fixed_view_mut::<3, 3>(3, 0)
            .copy_from(&(a_nav_h_theta * dt22));
        f.fixed_view_mut::<3, 3>(3, 6)
            .copy_from(&(Matrix3::identity() * dt));
        f.fixed_view_mut::<3, 3>(6, 0)
            .copy_from(&(a_nav_h_theta * dt));
        let theta_h_omega = jr_inv * dt;
        let pos_h_acc = rot * dt22;
        let vel_h_acc = rot * dt;
        f.fixed_view_mut::<3, 3>(0, 12).copy_from(&theta_h_omega);
        f.fixed_view_mut::<3, 3>(3, 9).copy_from(&pos_h_acc);
        f.fixed_view_mut::<3, 3>(6, 9).copy_from(&vel_h_acc);

        let mut cov = f * self.cov * f.transpose();
        let acc_over_dt = params.acc_cov / dt;
        add_block(
            &mut cov,
            0,
            0,
            &(theta_h_omega * (params.gyro_cov / dt) * theta_h_omega.transpose()),
        );
        add_block(
            &mut cov,
            3,
            3,
            &(pos_h_acc * acc_over_dt * pos_h_acc.transpose() + params.integration_cov * dt),
        );
        add_block(
            &mut cov,
            6,
            6,
            &(vel_h_acc * acc_over_dt * vel_h_acc.transpose()),
        );
        add_block(
            &mut cov,
            3,
            6,
            &(pos_h_acc * acc_over_dt * vel_h_acc.transpose()),
        );
        add_block(
            &mut cov,
            6,
            3,
            &(vel_h_acc * acc_over_dt * pos_h_acc.transpose()),
        );
        add_block(&mut cov, 9, 9, &(params.bias_acc_cov * dt));
        add_block(&mut cov, 12, 12, &(params.bias_gyro_cov * dt));
        self.cov = cov;

        // Bias Jacobians: H_a ← A H_a − B, H_g ← A H_g − C.
        let a9 = f.fixed_view::<9, 9>(0, 0).into_owned();
        let mut b9 = Matrix9x3::zeros();
        b9.fixed_view_mut::<3, 3>(3, 0).copy_from(&pos_h_acc);
        b9.fixed_view_mut::<3, 3>(6, 0).copy_from(&vel_h_acc);
        let mut c9 = Matrix9x3::zeros();
        c9.fixed_view_mut::<3, 3>(0, 0).copy_from(&theta_h_omega);
        self.h_bias_acc = a9 * self.h_bias_acc - b9;
        self.h_bias_gyro = a9 * self.h_bias_gyro - c9;
    }

    /// Covariance of the `CombinedImuFactor` residual (GTSAM 4.3 `residualCovariance`, the
    /// factor's noise model): the tangent covariance mapped into residual coordinates,
    /// `J Σ Jᵀ` with `J = diag(J_r(θ), ΔRᵀ, ΔRᵀ, −I₆)` (no Coriolis term).
    pub fn residual_cov(&self) -> Matrix15 {
        let dr_t = self.delta_r().transpose();
        let mut j = Matrix15::zeros();
        j.fixed_view_mut::<3, 3>(0, 0)
            .copy_from(&so3_right_jacobian(&self.theta));
        j.fixed_view_mut::<3, 3>(3, 3).copy_from(&dr_t);
        j.fixed_view_mut::<3, 3>(6, 6).copy_from(&dr_t);
        for k in 9..15 {
            j[(k, k)] = -1.0;
        }
        j * self.cov * j.transpose()
    }

    /// The bias-corrected deltas for the bias `bias` (first order in `bias − bias_hat`).
    pub fn corrected(&self, bias: &ImuBias) -> CorrectedDelta {
        let dba = bias.acc - self.bias_hat.acc;
        let dbg = bias.gyro - self.bias_hat.gyro;
        let z = self.h_bias_acc * dba + self.h_bias_gyro * dbg;
        let theta = self.theta + Vector3::new(z[0], z[1], z[2]);
        CorrectedDelta {
            delta_r: so3_exp(&theta).to_rotation_matrix().into_inner(),
            delta_p: self.delta_p + Vector3::new(z[3], z[4], z[5]),
            delta_v: self.delta_v + Vector3::new(z[6], z[7], z[8]),
            theta,
        }
    }
}

/// Bias-corrected preintegrated deltas.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CorrectedDelta {
    /// Corrected ΔR = Exp(θ̃).
    pub delta_r: Matrix3<f64>,
    /// Corrected Δp.
    pub delta_p: Vector3<f64>,
    /// Corrected Δv.
    pub delta_v: Vector3<f64>,
    /// Corrected θ̃.
    pub theta: Vector3<f64>,
}

fn add_block(m: &mut Matrix15, r: usize, c: usize, b: &Matrix3<f64>) {
    let mut v = m.fixed_view_mut::<3, 3>(r, c);
    v += b;
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn right_jacobian_derivative_matches_finite_differences() {
        let v = Vector3::new(0.3, -1.2, 0.7);
        for theta in [
            Vector3::new(0.4, -0.2, 0.9),
            Vector3::new(1e-4, 2e-4, -1e-4),
        ] {
            let d = right_jacobian_apply_derivative(&theta, &v);
            for c in 0..3 {
                let mut e = Vector3::zeros();
                e[c] = 1e-6;
                let num = (so3_right_jacobian(&(theta + e)) * v
                    - so3_right_jacobian(&(theta - e)) * v)
                    / 2e-6;
                assert!((num - d.column(c)).norm() < 1e-8, "{theta:?} column {c}");
            }
        }
    }
}
