//! Bearing-vector geometry against synthetic truth: relative pose, P3P, absolute pose RANSAC,
//! triangulation and the tangent-plane residual, over many random scenes with rays beyond 90°
//! off-axis, noise and outliers; determinism across runs and thread counts.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

use kiwi_backend::vision::geometry::{
    RansacOptions, RayObservation, TriangulationLimits, absolute_pose_position_std,
    absolute_pose_ransac, angular_error, dominant_plane, p3p, refine_absolute_pose,
    relative_pose_ransac, tangent_basis, tangent_residual, triangulate,
};
use kiwi_core::geometry::{Pose, so3_exp};
use nalgebra::{Point3, Translation3, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Largest off-axis angle of synthetic rays: beyond 90°, as the X5 lenses see.
const MAX_OFF_AXIS: f64 = 100.0 * std::f64::consts::PI / 180.0;

fn random_unit(rng: &mut ChaCha8Rng) -> Vector3<f64> {
    loop {
        let v = Vector3::new(
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
        );
        let n = v.norm();
        if n > 0.1 && n <= 1.0 {
            return v / n;
        }
    }
}

/// A direction within `MAX_OFF_AXIS` of +z.
fn random_fov_direction(rng: &mut ChaCha8Rng) -> Vector3<f64> {
    loop {
        let v = random_unit(rng);
        if v.z.clamp(-1.0, 1.0).acos() <= MAX_OFF_AXIS {
            return v;
        }
    }
}

fn random_pose(rng: &mut ChaCha8Rng, rot: f64, trans: f64) -> Pose {
    let phi = random_unit(rng) * rng.random_range(0.0..rot);
    let t = random_unit(rng) * trans;
    Pose::from_parts(Translation3::from(t), so3_exp(&phi))
}

/// Perturb a unit bearing by a Gaussian-ish angular noise of scale `sigma` (rad).
fn noisy(rng: &mut ChaCha8Rng, b: &Vector3<f64>, sigma: f64) -> Vector3<f64> {
    if sigma == 0.0 {
        return *b;
    }
    let basis = tangent_basis(b);
    let g = |rng: &mut ChaCha8Rng| {
        // Sum of uniforms: cheap, bounded, close to Gaussian.
        (0..6).map(|_| rng.random_range(-1.0..1.0)).sum::<f64>() / 2.0_f64.sqrt()
    };
    let d =
        basis.row(0).transpose() * (g(rng) * sigma) + basis.row(1).transpose() * (g(rng) * sigma);
    (b + d).normalize()
}

fn rotation_error(a: &Pose, b: &Pose) -> f64 {
    a.rotation.angle_to(&b.rotation)
}

struct TwoView {
    truth: Pose,
    b1: Vec<Vector3<f64>>,
    b2: Vec<Vector3<f64>>,
    outlier: Vec<bool>,
}

/// Points seen by both cameras (within the field of view of each), `outlier_ratio` of the
/// pairs replaced by random bearings.
fn two_view(seed: u64, n: usize, noise: f64, outlier_ratio: f64) -> TwoView {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let truth = random_pose(&mut rng, 0.5, 0.3);
    let (mut b1, mut b2, mut outlier) = (Vec::new(), Vec::new(), Vec::new());
    while b1.len() < n {
        let d = random_fov_direction(&mut rng);
        let p1 = d * rng.random_range(1.0..5.0);
        let p2 = (truth * Point3::from(p1)).coords;
        if p2.normalize().z.acos() > MAX_OFF_AXIS {
            continue;
        }
        let is_out = rng.random_range(0.0..1.0) < outlier_ratio;
        b1.push(noisy(&mut rng, &d, noise));
        b2.push(if is_out {
            random_fov_direction(&mut rng)
        } else {
            noisy(&mut rng, &p2.normalize(), noise)
        });
        outlier.push(is_out);
    }
    TwoView {
        truth,
        b1,
        b2,
        outlier,
    }
}

#[test]
fn relative_pose_recovers_truth_with_noise_outliers_and_wide_rays() {
    let options = RansacOptions::default();
    let mut beyond_90 = 0;
    for seed in 0..20 {
        let s = two_view(seed, 300, 0.001, 0.3);
        beyond_90 += s.b1.iter().filter(|b| b.z < 0.0).count();
        let est = relative_pose_ransac(&s.b1, &s.b2, &options).expect("a model");
        let rot = rotation_error(&est.cam2_from_cam1, &s.truth).to_degrees();
        let t_est = est.cam2_from_cam1.translation.vector;
        let t_true = s.truth.translation.vector.normalize();
        let dir = angular_error(&t_est, &t_true).to_degrees();
        assert!(rot < 0.2, "seed {seed}: rotation error {rot}°");
        assert!(dir < 2.0, "seed {seed}: translation direction error {dir}°");
        // Outliers are rejected: no more than a handful accepted by chance.
        let false_inliers = est
            .inliers
            .iter()
            .zip(&s.outlier)
            .filter(|&(&i, &o)| i && o)
            .count();
        let true_inliers = est
            .inliers
            .iter()
            .zip(&s.outlier)
            .filter(|&(&i, &o)| i && !o)
            .count();
        let n_good = s.outlier.iter().filter(|&&o| !o).count();
        assert!(
            false_inliers <= 10,
            "seed {seed}: {false_inliers} outliers accepted"
        );
        assert!(
            true_inliers as f64 >= 0.9 * n_good as f64,
            "seed {seed}: only {true_inliers}/{n_good} inliers kept"
        );
    }
    assert!(
        beyond_90 > 100,
        "the test must use rays beyond 90° ({beyond_90})"
    );
}

#[test]
fn relative_pose_is_exact_without_noise() {
    for seed in 100..110 {
        let s = two_view(seed, 50, 0.0, 0.0);
        let est = relative_pose_ransac(&s.b1, &s.b2, &RansacOptions::default()).unwrap();
        assert!(rotation_error(&est.cam2_from_cam1, &s.truth) < 1e-8);
        let dir = angular_error(
            &est.cam2_from_cam1.translation.vector,
            &s.truth.translation.vector,
        );
        assert!(dir < 1e-7, "seed {seed}: {dir}");
        assert_eq!(est.num_inliers, 50);
    }
}

struct Absolute {
    truth: Pose,
    bearings: Vec<Vector3<f64>>,
    points: Vec<Vector3<f64>>,
    outlier: Vec<bool>,
}

fn absolute(seed: u64, n: usize, noise: f64, outlier_ratio: f64) -> Absolute {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let truth = random_pose(&mut rng, 3.0, 2.0);
    let world_from_cam = truth.inverse();
    let (mut bearings, mut points, mut outlier) = (Vec::new(), Vec::new(), Vec::new());
    for _ in 0..n {
        let d = random_fov_direction(&mut rng);
        let pc = d * rng.random_range(0.5..6.0);
        let pw = (world_from_cam * Point3::from(pc)).coords;
        let is_out = rng.random_range(0.0..1.0) < outlier_ratio;
        bearings.push(if is_out {
            random_fov_direction(&mut rng)
        } else {
            noisy(&mut rng, &d, noise)
        });
        points.push(pw);
        outlier.push(is_out);
    }
    Absolute {
        truth,
        bearings,
        points,
        outlier,
    }
}

#[test]
fn p3p_finds_the_true_pose_among_its_solutions() {
    let mut worst: f64 = 0.0;
    for seed in 0..500 {
        let s = absolute(1000 + seed, 3, 0.0, 0.0);
        let sols = p3p(
            &[s.bearings[0], s.bearings[1], s.bearings[2]],
            &[s.points[0], s.points[1], s.points[2]],
        );
        assert!(sols.len() <= 4);
        let best = sols
            .iter()
            .map(|p| {
                rotation_error(p, &s.truth)
                    + (p.translation.vector - s.truth.translation.vector).norm()
            })
            .fold(f64::INFINITY, f64::min);
        worst = worst.max(best);
    }
    // Near-degenerate random triangles cost a little precision; typical errors are ~1e-12.
    assert!(worst < 1e-5, "worst P3P error {worst}");
}

#[test]
fn absolute_pose_ransac_recovers_truth_with_noise_and_outliers() {
    let options = RansacOptions::default();
    for seed in 0..20 {
        let s = absolute(seed, 200, 0.001, 0.4);
        let est = absolute_pose_ransac(&s.bearings, &s.points, &options).expect("a pose");
        let rot = rotation_error(&est.cam_from_world, &s.truth).to_degrees();
        let centre_err = (est.cam_from_world.inverse().translation.vector
            - s.truth.inverse().translation.vector)
            .norm();
        assert!(rot < 0.1, "seed {seed}: rotation error {rot}°");
        assert!(centre_err < 0.01, "seed {seed}: centre error {centre_err}");
        let false_inliers = est
            .inliers
            .iter()
            .zip(&s.outlier)
            .filter(|&(&i, &o)| i && o)
            .count();
        assert!(false_inliers <= 5, "seed {seed}: {false_inliers}");
    }
}

#[test]
fn absolute_pose_ransac_refuses_pure_outliers() {
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let bearings: Vec<Vector3<f64>> = (0..100).map(|_| random_fov_direction(&mut rng)).collect();
    let points: Vec<Vector3<f64>> = (0..100).map(|_| random_unit(&mut rng) * 3.0).collect();
    let options = RansacOptions {
        min_inliers: 20,
        ..RansacOptions::default()
    };
    assert!(absolute_pose_ransac(&bearings, &points, &options).is_none());
}

#[test]
fn ransac_is_deterministic_across_runs_and_thread_counts() {
    let s = two_view(42, 300, 0.001, 0.3);
    let a = absolute(43, 300, 0.001, 0.3);
    let run = || {
        (
            relative_pose_ransac(&s.b1, &s.b2, &RansacOptions::default()).unwrap(),
            absolute_pose_ransac(&a.bearings, &a.points, &RansacOptions::default()).unwrap(),
        )
    };
    let first = run();
    let pool = |n| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(n)
            .build()
            .unwrap()
    };
    let one = pool(1).install(run);
    let two = pool(2).install(run);
    for other in [&one, &two, &run()] {
        assert_eq!(first.0, other.0);
        assert_eq!(first.1, other.1);
    }
    // A different seed explores different samples but reaches the same answer.
    let other_seed = RansacOptions {
        seed: 99,
        ..RansacOptions::default()
    };
    let b = relative_pose_ransac(&s.b1, &s.b2, &other_seed).unwrap();
    assert!(rotation_error(&b.cam2_from_cam1, &first.0.cam2_from_cam1) < 0.003);
}

#[test]
fn triangulation_is_exact_and_checks_parallax_and_cheirality() {
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let limits = TriangulationLimits::default();
    for _ in 0..200 {
        let cams: Vec<Pose> = (0..3).map(|_| random_pose(&mut rng, 3.0, 0.5)).collect();
        let x = random_unit(&mut rng) * rng.random_range(1.5..4.0);
        let obs: Vec<RayObservation> = cams
            .iter()
            .map(|c| RayObservation {
                cam_from_world: *c,
                bearing: (c * Point3::from(x)).coords.normalize(),
            })
            .collect();
        let t = triangulate(&obs, &limits).expect("triangulated");
        assert!((t.point - x).norm() < 1e-8 * (1.0 + x.norm()));
        assert!(t.max_error_rad < 1e-8);
    }
    // A point behind one camera (its bearing flipped) is refused.
    let c1 = Pose::identity();
    let c2 = Pose::from_parts(
        Translation3::new(-0.5, 0.0, 0.0),
        so3_exp(&Vector3::zeros()),
    );
    let x = Vector3::new(0.2, 0.1, 2.0);
    let b1 = x.normalize();
    let b2 = (c2 * Point3::from(x)).coords.normalize();
    let ok = [
        RayObservation {
            cam_from_world: c1,
            bearing: b1,
        },
        RayObservation {
            cam_from_world: c2,
            bearing: b2,
        },
    ];
    assert!(triangulate(&ok, &limits).is_some());
    let behind = [
        ok[0],
        RayObservation {
            bearing: -b2,
            ..ok[1]
        },
    ];
    assert!(triangulate(&behind, &limits).is_none());
    // A far point seen with tiny parallax is refused.
    let far = Vector3::new(0.0, 0.0, 200.0);
    let tiny = [
        RayObservation {
            cam_from_world: c1,
            bearing: far.normalize(),
        },
        RayObservation {
            cam_from_world: c2,
            bearing: (c2 * Point3::from(far)).coords.normalize(),
        },
    ];
    assert!(triangulate(&tiny, &limits).is_none());
    // A point 120° off-axis in both cameras triangulates.
    let wide = Vector3::new(2.0, 0.0, -1.2);
    let obs = [c1, c2].map(|c| RayObservation {
        cam_from_world: c,
        bearing: (c * Point3::from(wide)).coords.normalize(),
    });
    assert!(obs[0].bearing.z < 0.0);
    let t = triangulate(&obs, &limits).unwrap();
    assert!((t.point - wide).norm() < 1e-9);
}

#[test]
fn tangent_residual_matches_angle_and_finite_differences() {
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    for _ in 0..200 {
        let b = random_unit(&mut rng);
        let basis = tangent_basis(&b);
        let p = (b + random_unit(&mut rng) * 0.3) * rng.random_range(0.5..5.0);
        let (r, j) = tangent_residual(&b, &basis, &p).unwrap();
        // |r| = 2 tan(α/2).
        let alpha = angular_error(&b, &p);
        assert!((r.norm() - 2.0 * (alpha / 2.0).tan()).abs() < 1e-12);
        let h = 1e-6;
        for k in 0..3 {
            let mut dp = Vector3::zeros();
            dp[k] = h;
            let (rp, _) = tangent_residual(&b, &basis, &(p + dp)).unwrap();
            let (rm, _) = tangent_residual(&b, &basis, &(p - dp)).unwrap();
            let fd = (rp - rm) / (2.0 * h);
            assert!((fd - j.column(k)).norm() < 1e-6, "{fd} vs {}", j.column(k));
        }
    }
}

/// The predicted position uncertainty of an absolute pose matches the scatter of poses refined
/// from noisy bearings (Monte Carlo, largest eigenvalue of the centres' covariance within 25 %),
/// grows linearly with the scene's distance, and is refused for fewer than three points.
#[test]
fn absolute_pose_position_std_matches_monte_carlo_scatter() {
    let mut rng = ChaCha8Rng::seed_from_u64(41);
    let cam_from_world = random_pose(&mut rng, 1.0, 0.5);
    let world_from_cam = cam_from_world.inverse();
    let sigma = 2e-3;
    // A one-sided scene: 30 points within 60° of the axis at 2-4 m (position weakly fixed
    // along the axis).
    let mut points = Vec::new();
    while points.len() < 30 {
        let d = random_fov_direction(&mut rng);
        if d.z < 0.5 {
            continue;
        }
        let depth = rng.random_range(2.0..4.0);
        points.push((world_from_cam * Point3::from(d * depth)).coords);
    }
    let bearings: Vec<Vector3<f64>> = points
        .iter()
        .map(|p| (cam_from_world * Point3::from(*p)).coords.normalize())
        .collect();
    let predicted = absolute_pose_position_std(
        &cam_from_world,
        bearings.iter().copied().zip(points.iter().copied()),
        sigma,
    )
    .unwrap();
    let centre = world_from_cam.translation.vector;
    let trials = 400;
    let mut cov = nalgebra::Matrix3::<f64>::zeros();
    for _ in 0..trials {
        let b: Vec<Vector3<f64>> = bearings.iter().map(|b| noisy(&mut rng, b, sigma)).collect();
        // Huber threshold far above the noise: plain least squares.
        let pose = refine_absolute_pose(&cam_from_world, &b, &points, 1.0);
        let d = pose.inverse().translation.vector - centre;
        cov += d * d.transpose();
    }
    cov /= f64::from(trials);
    let largest = cov
        .symmetric_eigenvalues()
        .iter()
        .copied()
        .fold(0.0_f64, f64::max)
        .sqrt();
    let ratio = largest / predicted;
    assert!(
        (0.75..1.25).contains(&ratio),
        "Monte Carlo σ {largest:.5} vs predicted {predicted:.5} (ratio {ratio:.3})"
    );
    // The same bearings on points four times as far: four times the uncertainty.
    let far: Vec<Vector3<f64>> = points.iter().map(|p| centre + (p - centre) * 4.0).collect();
    let predicted_far = absolute_pose_position_std(
        &cam_from_world,
        bearings.iter().copied().zip(far.iter().copied()),
        sigma,
    )
    .unwrap();
    assert!(
        (predicted_far / predicted - 4.0).abs() < 1e-6,
        "far/near {}",
        predicted_far / predicted
    );
    assert!(
        absolute_pose_position_std(
            &cam_from_world,
            bearings[..2]
                .iter()
                .copied()
                .zip(points[..2].iter().copied()),
            sigma
        )
        .is_none()
    );
}

#[test]
fn dominant_plane_finds_the_floor_among_walls_and_clutter() {
    // 60 points on a tilted floor with 5 mm noise, 30 on a wall, 30 scattered in the room:
    // the floor is the dominant plane and holds exactly its own points at 2 cm.
    let mut rng = ChaCha8Rng::seed_from_u64(41);
    let normal = Vector3::new(0.1, -0.05, 1.0).normalize();
    let offset = 0.3;
    let mut points = Vec::new();
    for _ in 0..60 {
        let p = Vector3::new(
            rng.random_range(-2.0..2.0),
            rng.random_range(-2.0..2.0),
            0.0,
        );
        let on = p - normal * (normal.dot(&p) - offset);
        points.push(on + normal * rng.random_range(-0.005..0.005));
    }
    for _ in 0..30 {
        points.push(Vector3::new(
            2.5,
            rng.random_range(-2.0..2.0),
            rng.random_range(0.5..2.5),
        ));
    }
    for _ in 0..30 {
        points.push(Vector3::new(
            rng.random_range(-2.0..2.0),
            rng.random_range(-2.0..2.0),
            rng.random_range(1.0..2.5),
        ));
    }
    let (n, d, count) = dominant_plane(&points, 0.02).unwrap();
    assert_eq!(count, 60, "floor points held");
    let sign = n.dot(&normal).signum();
    assert!((n * sign - normal).norm() < 0.02, "normal {n:?}");
    assert!((d * sign - offset).abs() < 0.02, "offset {d}");
    assert!(dominant_plane(&points[..2], 0.02).is_none());
    assert_eq!(dominant_plane(&points, 0.02), dominant_plane(&points, 0.02));
}
