//! Property tests of the SO(3)/SE(3) maps: exp∘log identities (tiny angles and near π included)
//! and the Jacobian identities, checked numerically.

#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

use kiwi_core::geometry::*;
use nalgebra::{Matrix3, Matrix6, UnitQuaternion, Vector3};
use proptest::prelude::*;

fn vec3(max: f64) -> impl Strategy<Value = Vector3<f64>> {
    (-max..max, -max..max, -max..max).prop_map(|(x, y, z)| Vector3::new(x, y, z))
}

/// Rotation vectors with any angle in [0, π), including tiny ones and ones just below π.
fn rotation_vector() -> impl Strategy<Value = Vector3<f64>> {
    let axis = vec3(1.0)
        .prop_filter("non-zero axis", |v| v.norm() > 1e-3)
        .prop_map(|v| v.normalize());
    let angle = prop_oneof![
        0.0..1e-9f64,
        1e-9..1e-3f64,
        1e-3..3.0f64,
        (1e-12..1e-3f64).prop_map(|e| std::f64::consts::PI - e),
    ];
    (axis, angle).prop_map(|(a, t)| a * t)
}

fn tangent6() -> impl Strategy<Value = Tangent6> {
    (rotation_vector(), vec3(5.0)).prop_map(|(phi, rho)| tangent(&phi, &rho))
}

fn close3(a: &Matrix3<f64>, b: &Matrix3<f64>, tol: f64) -> bool {
    (a - b).norm() <= tol * (1.0 + b.norm())
}

fn close6(a: &Matrix6<f64>, b: &Matrix6<f64>, tol: f64) -> bool {
    (a - b).norm() <= tol * (1.0 + b.norm())
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(512))]

    #[test]
    fn so3_exp_log_round_trip(phi in rotation_vector()) {
        let q = so3_exp(&phi);
        let back = so3_exp(&so3_log(&q));
        prop_assert!(q.angle_to(&back) < 1e-12);
        // log(exp(phi)) = phi for angles below π (unique there).
        prop_assert!((so3_log(&q) - phi).norm() < 1e-12 * (1.0 + phi.norm()) + 1e-15);
    }

    #[test]
    fn se3_exp_log_round_trip(xi in tangent6()) {
        let pose = se3_exp(&xi);
        let back = se3_exp(&se3_log(&pose));
        prop_assert!(pose.rotation.angle_to(&back.rotation) < 1e-12);
        prop_assert!((pose.translation.vector - back.translation.vector).norm() < 1e-12 * (1.0 + xi.norm()));
    }

    #[test]
    fn so3_right_jacobian_first_order(phi in rotation_vector(), d in vec3(1.0)) {
        prop_assume!(phi.norm() < 3.0);
        let h = 1e-7;
        let delta = d.normalize() * h;
        // exp(phi + δ) ≈ exp(phi) exp(J_r δ)
        let lhs = so3_exp(&(phi + delta));
        let rhs = so3_exp(&phi) * so3_exp(&(so3_right_jacobian(&phi) * delta));
        prop_assert!(lhs.angle_to(&rhs) < 1e-6 * h * 10.0 + 1e-13);
        // and log(exp(phi) exp(δ)) ≈ phi + J_r⁻¹ δ
        let log = so3_log(&(so3_exp(&phi) * so3_exp(&delta)));
        prop_assert!((log - (phi + so3_right_jacobian_inv(&phi) * delta)).norm() < 1e-12 + 1e-5 * h);
    }

    #[test]
    fn so3_jacobian_inverses(phi in rotation_vector()) {
        prop_assume!(phi.norm() < 3.0);
        let i = Matrix3::identity();
        prop_assert!(close3(&(so3_right_jacobian(&phi) * so3_right_jacobian_inv(&phi)), &i, 1e-12));
        prop_assert!(close3(&(so3_left_jacobian(&phi) * so3_left_jacobian_inv(&phi)), &i, 1e-12));
        // J_l(φ) = R(φ) J_r(φ)
        let r = so3_exp(&phi).to_rotation_matrix().into_inner();
        prop_assert!(close3(&so3_left_jacobian(&phi), &(r * so3_right_jacobian(&phi)), 1e-12));
    }

    #[test]
    fn se3_jacobians_first_order(xi in tangent6(), d in (vec3(1.0), vec3(1.0))) {
        prop_assume!(xi.fixed_rows::<3>(0).norm() < 3.0);
        let h = 1e-7;
        let delta = tangent(&d.0, &d.1).normalize() * h;
        let lhs = se3_exp(&(xi + delta));
        let right = se3_exp(&xi) * se3_exp(&(se3_right_jacobian(&xi) * delta));
        let left = se3_exp(&(se3_left_jacobian(&xi) * delta)) * se3_exp(&xi);
        for rhs in [right, left] {
            let err = se3_log(&(lhs.inverse() * rhs)).norm();
            prop_assert!(err < 1e-5 * h * (1.0 + xi.norm()) + 1e-12, "err {err:e}");
        }
    }

    #[test]
    fn se3_jacobian_inverses(xi in tangent6()) {
        prop_assume!(xi.fixed_rows::<3>(0).norm() < 3.0);
        let i = Matrix6::identity();
        prop_assert!(close6(&(se3_left_jacobian(&xi) * se3_left_jacobian_inv(&xi)), &i, 1e-10));
        prop_assert!(close6(&(se3_right_jacobian(&xi) * se3_right_jacobian_inv(&xi)), &i, 1e-10));
        // J_l(ξ) = Ad(exp ξ) J_r(ξ)
        prop_assert!(close6(&se3_left_jacobian(&xi), &(se3_adjoint(&se3_exp(&xi)) * se3_right_jacobian(&xi)), 1e-10));
    }

    #[test]
    fn adjoint_moves_perturbations(xi in tangent6(), d in tangent6()) {
        let t = se3_exp(&xi);
        let small = d * 1e-3;
        let lhs = t * se3_exp(&small) * t.inverse();
        let rhs = se3_exp(&(se3_adjoint(&t) * small));
        prop_assert!(se3_log(&(lhs.inverse() * rhs)).norm() < 1e-10 * (1.0 + xi.norm()));
    }

    #[test]
    fn interpolation_stays_on_geodesic(a in tangent6(), b in tangent6(), s in 0.0..1.0f64) {
        let (pa, pb) = (se3_exp(&a), se3_exp(&b));
        let mid = interpolate_pose(&pa, &pb, s);
        let total = rotation_angle_between(&pa.rotation, &pb.rotation);
        prop_assume!(total < 3.0);
        let first = rotation_angle_between(&pa.rotation, &mid.rotation);
        prop_assert!((first - s * total).abs() < 1e-9);
    }

    #[test]
    fn rotation_average_of_identical_is_exact(phi in rotation_vector(), n in 1usize..8) {
        let q = so3_exp(&phi);
        let samples = vec![q; n];
        let mean = average_rotations(&samples, None).unwrap();
        prop_assert!(rotation_angle_between(&mean, &q) < 1e-9);
        let _unused: UnitQuaternion<f64> = mean;
    }
}
