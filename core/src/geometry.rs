//! Lie-group geometry on SO(3) and SE(3), written for the `a_from_b` convention.
//!
//! Rigid transforms are [`Pose`]s (`nalgebra::Isometry3<f64>`) named `a_from_b`: they map
//! coordinates in frame `b` to frame `a` and compose right to left
//! (`a_from_c = a_from_b * b_from_c`).
//!
//! Tangent vectors of SE(3) are ordered **rotation first**, `xi = [phi; rho]`, as in GTSAM,
//! so covariances and Jacobians compare with GTSAM without reordering. Perturbations are
//! right-multiplied unless a function says otherwise:
//! `exp(xi + d) ≈ exp(xi) * exp(J_r(xi) d)`.
//!
//! Every closed form switches to a Taylor series near zero angle, and logarithms use
//! `atan2`, so the maps stay accurate for tiny rotations and rotations close to π.

use nalgebra::{Isometry3, Matrix3, Matrix6, Quaternion, Translation3, UnitQuaternion, Vector3};

/// A rigid transform `a_from_b` (maps coordinates in frame `b` to frame `a`).
pub type Pose = Isometry3<f64>;

/// A 6-vector in the tangent space of SE(3), ordered `[rotation (rad); translation]`.
pub type Tangent6 = nalgebra::Vector6<f64>;

/// Below this rotation angle (rad) the SO(3) coefficients use their Taylor series: at 1e-2 the
/// series truncation error is ~1e-18 while the closed forms would start losing digits.
const SERIES_ANGLE: f64 = 1e-2;

/// Tolerance on `RᵀR − I` (Frobenius norm) and on `det R − 1` for a matrix to count as a rotation;
/// tight enough to catch typos, loose enough for values printed with 9 significant digits.
pub const ROTATION_ORTHONORMALITY_TOLERANCE: f64 = 1e-6;

/// The skew-symmetric matrix `[v]×` with `[v]× w = v × w`.
pub fn hat(v: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(0.0, -v.z, v.y, v.z, 0.0, -v.x, -v.y, v.x, 0.0)
}

/// The vector of a skew-symmetric matrix (inverse of [`hat`]); ignores the symmetric part.
pub fn vee(m: &Matrix3<f64>) -> Vector3<f64> {
    Vector3::new(
        0.5 * (m[(2, 1)] - m[(1, 2)]),
        0.5 * (m[(0, 2)] - m[(2, 0)]),
        0.5 * (m[(1, 0)] - m[(0, 1)]),
    )
}

/// Exponential map of SO(3): the rotation by `|phi|` radians about `phi`.
pub fn so3_exp(phi: &Vector3<f64>) -> UnitQuaternion<f64> {
    let theta2 = phi.norm_squared();
    let theta = theta2.sqrt();
    let (w, s) = if theta < SERIES_ANGLE {
        // cos(θ/2) and sin(θ/2)/θ by series.
        (
            1.0 - theta2 / 8.0 + theta2 * theta2 / 384.0,
            0.5 - theta2 / 48.0 + theta2 * theta2 / 3840.0,
        )
    } else {
        ((0.5 * theta).cos(), (0.5 * theta).sin() / theta)
    };
    UnitQuaternion::new_normalize(Quaternion::new(w, s * phi.x, s * phi.y, s * phi.z))
}

/// Logarithm of SO(3): the rotation vector (axis × angle, angle in `[0, π]`).
pub fn so3_log(q: &UnitQuaternion<f64>) -> Vector3<f64> {
    let q = q.quaternion();
    // q and −q are the same rotation; pick w ≥ 0 so the angle is in [0, π].
    let (w, v) = if q.w < 0.0 {
        (-q.w, -q.imag())
    } else {
        (q.w, q.imag())
    };
    let n = v.norm();
    if n < 1e-8 {
        // θ = 2 atan(n/w) ≈ 2n/w (1 − n²/(3w²)); w ≈ 1 here.
        let scale = 2.0 / w * (1.0 - n * n / (3.0 * w * w));
        v * scale
    } else {
        let theta = 2.0 * n.atan2(w);
        v * (theta / n)
    }
}

/// `(1 − cos θ)/θ²`, `(θ − sin θ)/θ³` for SO(3) Jacobians.
fn so3_coefficients(theta: f64) -> (f64, f64) {
    if theta < SERIES_ANGLE {
        let t2 = theta * theta;
        (
            0.5 - t2 / 24.0 + t2 * t2 / 720.0,
            1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0,
        )
    } else {
        let half_sin = (0.5 * theta).sin();
        (
            2.0 * half_sin * half_sin / (theta * theta),
            (theta - theta.sin()) / (theta * theta * theta),
        )
    }
}

/// `1/θ² − cot(θ/2)/(2θ)`, the coefficient of `[φ]×²` in the inverse Jacobians.
fn so3_inverse_coefficient(theta: f64) -> f64 {
    if theta < SERIES_ANGLE {
        let t2 = theta * theta;
        1.0 / 12.0 + t2 / 720.0 + t2 * t2 / 30240.0
    } else {
        let half = 0.5 * theta;
        1.0 / (theta * theta) - half.cos() / (half.sin() * 2.0 * theta)
    }
}

/// Right Jacobian of SO(3): `exp(φ + δ) ≈ exp(φ) exp(J_r(φ) δ)`.
pub fn so3_right_jacobian(phi: &Vector3<f64>) -> Matrix3<f64> {
    let (a, b) = so3_coefficients(phi.norm());
    let k = hat(phi);
    Matrix3::identity() - k * a + k * k * b
}

/// Inverse of [`so3_right_jacobian`]: `log(exp(φ) exp(δ)) ≈ φ + J_r⁻¹(φ) δ`.
pub fn so3_right_jacobian_inv(phi: &Vector3<f64>) -> Matrix3<f64> {
    let c = so3_inverse_coefficient(phi.norm());
    let k = hat(phi);
    Matrix3::identity() + k * 0.5 + k * k * c
}

/// Left Jacobian of SO(3): `exp(φ + δ) ≈ exp(J_l(φ) δ) exp(φ)`; equals `J_r(−φ)`.
pub fn so3_left_jacobian(phi: &Vector3<f64>) -> Matrix3<f64> {
    so3_right_jacobian(&-phi)
}

/// Inverse of [`so3_left_jacobian`].
pub fn so3_left_jacobian_inv(phi: &Vector3<f64>) -> Matrix3<f64> {
    so3_right_jacobian_inv(&-phi)
}

/// Split a tangent vector into its rotation and translation parts.
fn split(xi: &Tangent6) -> (Vector3<f64>, Vector3<f64>) {
    (
        Vector3::new(xi[0], xi[1], xi[2]),
        Vector3::new(xi[3], xi[4], xi[5]),
    )
}

/// Join rotation and translation parts into a tangent vector.
pub fn tangent(phi: &Vector3<f64>, rho: &Vector3<f64>) -> Tangent6 {
    Tangent6::new(phi.x, phi.y, phi.z, rho.x, rho.y, rho.z)
}

/// Exponential map of SE(3) for `xi = [phi; rho]`.
pub fn se3_exp(xi: &Tangent6) -> Pose {
    let (phi, rho) = split(xi);
    let t = so3_left_jacobian(&phi) * rho;
    Isometry3::from_parts(Translation3::from(t), so3_exp(&phi))
}

/// Logarithm of SE(3), the inverse of [`se3_exp`].
pub fn se3_log(pose: &Pose) -> Tangent6 {
    let phi = so3_log(&pose.rotation);
    let rho = so3_left_jacobian_inv(&phi) * pose.translation.vector;
    tangent(&phi, &rho)
}

/// Barfoot's `Q(ρ, φ)` block of the SE(3) left Jacobian.
fn se3_q(phi: &Vector3<f64>, rho: &Vector3<f64>) -> Matrix3<f64> {
    let theta = phi.norm();
    let t2 = theta * theta;
    // Coefficients of the three bracketed terms, with series below the cancellation zone.
    let (c1, c2, c3) = if theta < 2.0 * SERIES_ANGLE {
        (
            1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0,
            1.0 / 24.0 - t2 / 720.0 + t2 * t2 / 40320.0,
            1.0 / 120.0 - t2 / 2520.0 + t2 * t2 / 120_960.0,
        )
    } else {
        let (s, c) = theta.sin_cos();
        (
            (theta - s) / (t2 * theta),
            (t2 + 2.0 * c - 2.0) / (2.0 * t2 * t2),
            (2.0 * theta - 3.0 * s + theta * c) / (2.0 * t2 * t2 * theta),
        )
    };
    let p = hat(phi);
    let r = hat(rho);
    let pr = p * r;
    let rp = r * p;
    let prp = pr * p;
    let ppr = p * pr;
    let rpp = rp * p;
    r * 0.5 + (pr + rp + prp) * c1 + (ppr + rpp - prp * 3.0) * c2 + (prp * p + ppr * p) * c3
}

/// Assemble a 6×6 matrix from 3×3 blocks `[[a, b], [c, d]]`.
fn blocks(a: &Matrix3<f64>, b: &Matrix3<f64>, c: &Matrix3<f64>, d: &Matrix3<f64>) -> Matrix6<f64> {
    let mut m = Matrix6::zeros();
    m.fixed_view_mut::<3, 3>(0, 0).copy_from(a);
    m.fixed_view_mut::<3, 3>(0, 3).copy_from(b);
    m.fixed_view_mut::<3, 3>(3, 0).copy_from(c);
    m.fixed_view_mut::<3, 3>(3, 3).copy_from(d);
    m
}

/// Left Jacobian of SE(3): `exp(ξ + δ) ≈ exp(J_l(ξ) δ) exp(ξ)`.
pub fn se3_left_jacobian(xi: &Tangent6) -> Matrix6<f64> {
    let (phi, rho) = split(xi);
    let j = so3_left_jacobian(&phi);
    blocks(&j, &Matrix3::zeros(), &se3_q(&phi, &rho), &j)
}

/// Inverse of [`se3_left_jacobian`].
pub fn se3_left_jacobian_inv(xi: &Tangent6) -> Matrix6<f64> {
    let (phi, rho) = split(xi);
    let j_inv = so3_left_jacobian_inv(&phi);
    let lower = -(j_inv * se3_q(&phi, &rho) * j_inv);
    blocks(&j_inv, &Matrix3::zeros(), &lower, &j_inv)
}

/// Right Jacobian of SE(3): `exp(ξ + δ) ≈ exp(ξ) exp(J_r(ξ) δ)`; equals `J_l(−ξ)`.
pub fn se3_right_jacobian(xi: &Tangent6) -> Matrix6<f64> {
    se3_left_jacobian(&-xi)
}

/// Inverse of [`se3_right_jacobian`].
pub fn se3_right_jacobian_inv(xi: &Tangent6) -> Matrix6<f64> {
    se3_left_jacobian_inv(&-xi)
}

/// Adjoint of a pose in the `[phi; rho]` ordering: `T exp(ξ) T⁻¹ = exp(Ad_T ξ)`.
pub fn se3_adjoint(pose: &Pose) -> Matrix6<f64> {
    let r = pose.rotation.to_rotation_matrix().into_inner();
    let t = hat(&pose.translation.vector) * r;
    blocks(&r, &Matrix3::zeros(), &t, &r)
}

/// Interpolate between two poses of the same frames: rotation along the SO(3) geodesic,
/// translation linearly (the SO(3)×R³ interpolation used for trajectories sampled in time).
///
/// `s = 0` gives `a_from_b0`, `s = 1` gives `a_from_b1`; values outside `[0, 1]` extrapolate.
pub fn interpolate_pose(a_from_b0: &Pose, a_from_b1: &Pose, s: f64) -> Pose {
    let delta = so3_log(&(a_from_b0.rotation.inverse() * a_from_b1.rotation));
    let rotation = a_from_b0.rotation * so3_exp(&(delta * s));
    let translation = a_from_b0
        .translation
        .vector
        .lerp(&a_from_b1.translation.vector, s);
    Isometry3::from_parts(Translation3::from(translation), rotation)
}

/// Geodesic angle (rad) between two rotations.
pub fn rotation_angle_between(a: &UnitQuaternion<f64>, b: &UnitQuaternion<f64>) -> f64 {
    so3_log(&(a.inverse() * b)).norm()
}

/// Convergence threshold (rad) of the Weiszfeld iteration in [`average_rotations`].
const AVERAGING_TOLERANCE: f64 = 1e-13;
/// Iteration cap for [`average_rotations`]; Weiszfeld converges in a few tens from the chordal start.
const AVERAGING_MAX_ITERATIONS: usize = 200;
/// Residual below which a sample counts as coincident with the estimate (avoids 1/0 in Weiszfeld).
const AVERAGING_COINCIDENT: f64 = 1e-15;

/// Robust mean of rotations: the weighted geodesic L1 median (Weiszfeld iterations in the
/// tangent space), started from the chordal L2 mean.
///
/// The L1 median ignores a minority of outliers that would drag a least-squares mean.
/// Returns `None` for an empty set, mismatched weights, or non-positive total weight.
pub fn average_rotations(
    rotations: &[UnitQuaternion<f64>],
    weights: Option<&[f64]>,
) -> Option<UnitQuaternion<f64>> {
    if rotations.is_empty() {
        return None;
    }
    if let Some(w) = weights
        && (w.len() != rotations.len() || w.iter().any(|x| !x.is_finite() || *x < 0.0))
    {
        return None;
    }
    let weight = |i: usize| weights.map_or(1.0, |w| w[i]);
    if (0..rotations.len()).map(weight).sum::<f64>() <= 0.0 {
        return None;
    }
    // Chordal mean: project the weighted sum of matrices onto SO(3).
    let mut sum = Matrix3::zeros();
    for (i, q) in rotations.iter().enumerate() {
        sum += q.to_rotation_matrix().into_inner() * weight(i);
    }
    let mut estimate = project_to_rotation(&sum).unwrap_or(rotations[0]);
    for _ in 0..AVERAGING_MAX_ITERATIONS {
        let mut numerator = Vector3::zeros();
        let mut denominator = 0.0;
        for (i, q) in rotations.iter().enumerate() {
            let r = so3_log(&(estimate.inverse() * q));
            let d = r.norm();
            if d < AVERAGING_COINCIDENT {
                continue;
            }
            numerator += r * (weight(i) / d);
            denominator += weight(i) / d;
        }
        if denominator <= 0.0 {
            break;
        }
        let step = numerator / denominator;
        estimate *= so3_exp(&step);
        if step.norm() < AVERAGING_TOLERANCE {
            break;
        }
    }
    Some(estimate)
}

/// The rotation nearest (Frobenius) to a 3×3 matrix, or `None` if it is degenerate.
pub fn project_to_rotation(m: &Matrix3<f64>) -> Option<UnitQuaternion<f64>> {
    let svd = m.svd(true, true);
    let u = svd.u?;
    let v_t = svd.v_t?;
    let mut d = Matrix3::identity();
    if (u * v_t).determinant() < 0.0 {
        d[(2, 2)] = -1.0;
    }
    let r = u * d * v_t;
    if !r.iter().all(|x| x.is_finite()) {
        return None;
    }
    // Shepperd's method on the orthonormal `r`: `UnitQuaternion::from_matrix` iterates from the
    // identity, which is a fixed point for a half turn (diag(-1, 1, -1) came back unchanged as
    // the identity).
    Some(UnitQuaternion::from_rotation_matrix(
        &nalgebra::Rotation3::from_matrix_unchecked(r),
    ))
}

/// Check that a matrix is a proper rotation (orthonormal, determinant +1) within
/// [`ROTATION_ORTHONORMALITY_TOLERANCE`]; on failure, say how far off it is.
pub fn rotation_from_matrix(m: &Matrix3<f64>) -> Result<UnitQuaternion<f64>, String> {
    if !m.iter().all(|x| x.is_finite()) {
        return Err("a matrix with non-finite entries".into());
    }
    let orthonormality = (m.transpose() * m - Matrix3::identity()).norm();
    let det = m.determinant();
    if orthonormality > ROTATION_ORTHONORMALITY_TOLERANCE
        || (det - 1.0).abs() > ROTATION_ORTHONORMALITY_TOLERANCE
    {
        return Err(format!(
            "a matrix with |RᵀR − I| = {orthonormality:.3e} and det = {det:.6}"
        ));
    }
    project_to_rotation(m).ok_or_else(|| "a degenerate matrix".into())
}

#[cfg(test)]
mod tests {
    use super::*;
    use approx::assert_relative_eq;

    #[test]
    fn half_turns_are_kept() {
        for axis in [Vector3::x_axis(), Vector3::y_axis(), Vector3::z_axis()] {
            let half = UnitQuaternion::from_axis_angle(&axis, std::f64::consts::PI);
            let m = half.to_rotation_matrix().into_inner();
            let back = rotation_from_matrix(&m).unwrap();
            assert!(back.angle_to(&half) < 1e-12, "{axis:?}: {back:?}");
        }
    }

    #[test]
    fn hat_vee_are_inverse() {
        let v = Vector3::new(0.3, -1.2, 2.5);
        assert_eq!(vee(&hat(&v)), v);
        let w = Vector3::new(-0.7, 0.1, 0.4);
        assert_relative_eq!(hat(&v) * w, v.cross(&w), epsilon = 1e-15);
    }

    #[test]
    fn exp_matches_nalgebra_for_moderate_angles() {
        let phi = Vector3::new(0.3, -0.4, 1.1);
        let ours = so3_exp(&phi);
        let theirs = UnitQuaternion::from_scaled_axis(phi);
        assert!(ours.angle_to(&theirs) < 1e-14);
    }

    #[test]
    fn log_near_pi_is_accurate() {
        for &eps in &[0.0, 1e-15, 1e-12, 1e-9, 1e-6, 1e-3] {
            let axis = Vector3::new(1.0, 2.0, -0.5).normalize();
            let phi = axis * (std::f64::consts::PI - eps);
            let back = so3_log(&so3_exp(&phi));
            // At exactly π the axis sign is ambiguous: ±phi are the same rotation.
            let same = (back - phi).norm() < 1e-12 || (eps == 0.0 && (back + phi).norm() < 1e-12);
            assert!(same, "eps {eps}: {back} vs {phi}");
        }
    }

    #[test]
    fn average_rejects_outliers() {
        let truth = so3_exp(&Vector3::new(0.2, 0.1, -0.3));
        let mut samples: Vec<_> = (0..20)
            .map(|i| {
                let f = f64::from(i);
                truth
                    * so3_exp(&Vector3::new(
                        1e-3 * (f * 0.7).sin(),
                        1e-3 * (f * 1.3).cos(),
                        0.0,
                    ))
            })
            .collect();
        samples.push(so3_exp(&Vector3::new(2.0, 0.0, 0.0)));
        samples.push(so3_exp(&Vector3::new(0.0, -2.5, 0.0)));
        let mean = average_rotations(&samples, None).unwrap();
        assert!(rotation_angle_between(&mean, &truth) < 2e-3);
        assert!(average_rotations(&[], None).is_none());
        assert!(average_rotations(&samples, Some(&[1.0])).is_none());
    }

    #[test]
    fn interpolation_hits_endpoints_and_midpoint() {
        let a = se3_exp(&Tangent6::new(0.1, 0.2, 0.3, 1.0, 2.0, 3.0));
        let b = se3_exp(&Tangent6::new(0.5, -0.2, 0.1, -1.0, 0.0, 1.0));
        assert_relative_eq!(interpolate_pose(&a, &b, 0.0), a, epsilon = 1e-14);
        assert_relative_eq!(interpolate_pose(&a, &b, 1.0), b, epsilon = 1e-12);
        let mid = interpolate_pose(&a, &b, 0.5);
        let angle_a = rotation_angle_between(&a.rotation, &mid.rotation);
        let angle_b = rotation_angle_between(&mid.rotation, &b.rotation);
        assert_relative_eq!(angle_a, angle_b, epsilon = 1e-12);
    }

    #[test]
    fn rotation_check_rejects_non_orthonormal() {
        let mut m = Matrix3::identity();
        assert!(rotation_from_matrix(&m).is_ok());
        m[(0, 1)] = 0.01;
        assert!(rotation_from_matrix(&m).is_err());
        let reflection = Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, -1.0));
        assert!(rotation_from_matrix(&reflection).is_err());
    }
}
