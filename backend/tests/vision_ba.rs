//! Robust bundle adjustment and Sim(3) alignment against synthetic truth: a perturbed scene with
//! wide-angle rays (beyond 90° off-axis), noise and outliers converges back to the truth;
//! results are bit-identical across runs and thread counts.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

use kiwi_backend::vision::align::{align_and_measure, umeyama};
use kiwi_backend::vision::ba::{BaObservation, BaOptions, BaProblem, bundle_adjust};
use kiwi_core::geometry::{Pose, so3_exp};
use nalgebra::{Point3, Translation3, UnitQuaternion, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

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

fn jitter(rng: &mut ChaCha8Rng, b: &Vector3<f64>, sigma: f64) -> Vector3<f64> {
    (b + random_unit(rng) * sigma * rng.random_range(0.0..1.5)).normalize()
}

struct Scene {
    cams: Vec<Pose>,
    points: Vec<Vector3<f64>>,
    problem: BaProblem,
    outliers: usize,
    beyond_90: usize,
}

/// Cameras on a 2 m arc inside a cloud of points all around them.
fn scene(seed: u64, noise: f64, outlier_ratio: f64) -> Scene {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let cams: Vec<Pose> = (0..10)
        .map(|i| {
            let a = i as f64 * 0.2;
            let centre = Vector3::new(a.cos(), a.sin(), 0.1 * a);
            let rot = so3_exp(&(random_unit(&mut rng) * rng.random_range(0.0..3.0)));
            // cam_from_world = (world_from_cam)^-1 with world_from_cam = (centre, rot).
            Pose::from_parts(Translation3::from(centre), rot).inverse()
        })
        .collect();
    let points: Vec<Vector3<f64>> = (0..400)
        .map(|_| random_unit(&mut rng) * rng.random_range(2.0..5.0))
        .collect();
    let mut observations = Vec::new();
    let (mut outliers, mut beyond_90) = (0, 0);
    for (ci, c) in cams.iter().enumerate() {
        for (pi, p) in points.iter().enumerate() {
            let pc = (c * Point3::from(*p)).coords;
            let b = pc.normalize();
            if b.z.acos() > MAX_OFF_AXIS {
                continue;
            }
            if b.z < 0.0 {
                beyond_90 += 1;
            }
            let bearing = if rng.random_range(0.0..1.0) < outlier_ratio {
                outliers += 1;
                jitter(&mut rng, &b, 0.2)
            } else {
                jitter(&mut rng, &b, noise)
            };
            observations.push(BaObservation {
                camera: ci,
                point: pi,
                bearing,
            });
        }
    }
    let mut fixed_camera = vec![false; cams.len()];
    fixed_camera[0] = true;
    fixed_camera[1] = true;
    let problem = BaProblem {
        cam_from_world: cams.clone(),
        fixed_camera,
        points: points.clone(),
        fixed_point: vec![false; points.len()],
        observations,
    };
    Scene {
        cams,
        points,
        problem,
        outliers,
        beyond_90,
    }
}

fn perturb(problem: &mut BaProblem, seed: u64) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    for (pose, fixed) in problem.cam_from_world.iter_mut().zip(&problem.fixed_camera) {
        if !fixed {
            let d = Pose::from_parts(
                Translation3::from(random_unit(&mut rng) * 0.05),
                so3_exp(&(random_unit(&mut rng) * 0.02)),
            );
            *pose = d * *pose;
        }
    }
    for p in &mut problem.points {
        *p += random_unit(&mut rng) * 0.1;
    }
}

fn centre(p: &Pose) -> Vector3<f64> {
    p.inverse().translation.vector
}

#[test]
fn ba_recovers_a_perturbed_scene_with_outliers() {
    let mut s = scene(1, 0.0005, 0.05);
    assert!(s.beyond_90 > 200, "rays beyond 90°: {}", s.beyond_90);
    assert!(s.outliers > 50);
    // The robust cost at the truth (no iterations) is what the solver should reach.
    let mut at_truth = s.problem.clone();
    let zero = BaOptions {
        max_iterations: 0,
        ..BaOptions::default()
    };
    let truth_cost = bundle_adjust(&mut at_truth, &zero).unwrap().initial_cost;
    perturb(&mut s.problem, 2);
    let report = bundle_adjust(&mut s.problem, &BaOptions::default()).unwrap();
    assert!(
        report.final_cost <= truth_cost * 1.001,
        "{report:?} vs truth {truth_cost}"
    );
    let mut worst_c: f64 = 0.0;
    let mut worst_r: f64 = 0.0;
    for (est, truth) in s.problem.cam_from_world.iter().zip(&s.cams) {
        worst_c = worst_c.max((centre(est) - centre(truth)).norm());
        worst_r = worst_r.max(est.rotation.angle_to(&truth.rotation));
    }
    // Two fixed cameras 0.2 m apart fix the gauge; 0.5 mrad noise on ~350 rays per camera.
    assert!(
        worst_c < 0.005,
        "camera centre error {worst_c} m ({report:?})"
    );
    assert!(
        worst_r.to_degrees() < 0.05,
        "rotation error {}°",
        worst_r.to_degrees()
    );
    let mut errs: Vec<f64> = s
        .problem
        .points
        .iter()
        .zip(&s.points)
        .map(|(a, b)| (a - b).norm())
        .collect();
    errs.sort_by(f64::total_cmp);
    let median = errs[errs.len() / 2];
    // Points 2–5 m away seen with 0.5 mrad noise: depth noise of a few mm is physics.
    assert!(median < 0.015, "median point error {median} m");
}

#[test]
fn ba_noise_free_scene_converges_to_truth() {
    let mut s = scene(3, 0.0, 0.0);
    perturb(&mut s.problem, 4);
    let report = bundle_adjust(&mut s.problem, &BaOptions::default()).unwrap();
    assert!(report.final_rms_rad < 1e-7, "{report:?}");
    for (est, truth) in s.problem.cam_from_world.iter().zip(&s.cams) {
        assert!((centre(est) - centre(truth)).norm() < 1e-6);
    }
}

#[test]
fn ba_is_deterministic_across_runs_and_thread_counts() {
    let mut s = scene(5, 0.0005, 0.05);
    perturb(&mut s.problem, 6);
    let run = || {
        let mut p = s.problem.clone();
        let r = bundle_adjust(&mut p, &BaOptions::default()).unwrap();
        (p, r)
    };
    let first = run();
    let pool = |n| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(n)
            .build()
            .unwrap()
    };
    for other in [run(), pool(1).install(run), pool(2).install(run)] {
        assert_eq!(first.0, other.0);
        assert_eq!(first.1, other.1);
    }
}

#[test]
fn ba_rejects_bad_input_with_a_clear_error() {
    let mut s = scene(7, 0.0, 0.0);
    s.problem.observations[0].point = 10_000;
    let err = bundle_adjust(&mut s.problem, &BaOptions::default()).unwrap_err();
    assert!(err.to_string().contains("observation 0"), "{err}");
}

#[test]
fn umeyama_recovers_a_similarity_and_measures_ate() {
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let src: Vec<Vector3<f64>> = (0..50).map(|_| random_unit(&mut rng) * 3.0).collect();
    let rot = UnitQuaternion::from_scaled_axis(Vector3::new(0.3, -1.2, 2.0));
    let t = Vector3::new(1.0, -2.0, 0.5);
    let scale = 0.37;
    let dst: Vec<Vector3<f64>> = src.iter().map(|p| rot * p * scale + t).collect();
    let sim = umeyama(&src, &dst, true).unwrap();
    assert!((sim.scale - scale).abs() < 1e-12);
    assert!(sim.rotation.angle_to(&rot) < 1e-12);
    assert!((sim.translation - t).norm() < 1e-12);
    // With noise: ATE about the noise level, expressed against the extent.
    let noisy: Vec<Vector3<f64>> = dst
        .iter()
        .map(|p| p + random_unit(&mut rng) * 0.001)
        .collect();
    let (_, err) = align_and_measure(&src, &noisy).unwrap();
    assert!(err.rmse < 0.001 && err.rmse > 0.0002, "{err:?}");
    assert!(err.extent > 1.0);
    // Collinear or too few points cannot be aligned.
    let line: Vec<Vector3<f64>> = (0..5).map(|i| Vector3::x() * f64::from(i)).collect();
    assert!(umeyama(&line, &line, true).is_none());
    assert!(umeyama(&src[..2], &dst[..2], true).is_none());
    // SE(3) fit keeps the scale at one.
    let rigid: Vec<Vector3<f64>> = src.iter().map(|p| rot * p + t).collect();
    let se3 = umeyama(&src, &rigid, false).unwrap();
    assert_eq!(se3.scale, 1.0);
    assert!((se3.translation - t).norm() < 1e-12);
}
