#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]
//! Simulator acceptance of the per-wrist fusion: 60 s bimanual tabletop at 119.88 Hz, pose
//! observations with 1 mm / 0.1° noise, 5 % outliers and a 2 s gap; ATE < 2 mm outside the gap,
//! < 2 cm inside; outliers move the solution by < 0.5 mm.

use kiwi_backend::fusion::preint::ImuParams;
use kiwi_backend::fusion::{FusionConfig, PoseObservation, Source, fuse};
use kiwi_core::geometry::{Pose, se3_exp};
use kiwi_fixtures::imu::{GRAVITY, ImuSimulator};
use kiwi_fixtures::motion::Trajectory;
use kiwi_fixtures::rng::{normal, stream, uniform};
use kiwi_fixtures::scenario::{Scenario, episode_motion};
use kiwi_fixtures::unit::{LensModel, SimUnit};
use nalgebra::Vector6;

const FPS: f64 = 119.88;
const DURATION_S: f64 = 60.0;
const GAP: (f64, f64) = (30.0, 32.0);
const SIGMA_P: f64 = 1e-3;
const SIGMA_R: f64 = 0.1 * std::f64::consts::PI / 180.0;
const OUTLIER_FRACTION: f64 = 0.05;
/// Outliers are off by up to ±0.1 rad (5.7°) per axis ...
const OUTLIER_ROT_RAD: f64 = 0.1;
/// ... and up to ±10 cm per axis.
const OUTLIER_POS_M: f64 = 0.1;

struct Run {
    positions: Vec<nalgebra::Vector3<f64>>,
    truth: Vec<Pose>,
    times: Vec<f64>,
    downweighted: usize,
    used: usize,
}

fn observations(
    traj: &Trajectory,
    times: &[f64],
    outliers: bool,
    seed: u64,
) -> Vec<PoseObservation> {
    let mut rng = stream(seed, "fusion-test/obs");
    let mut out = Vec::new();
    // Front at every node; rear on its own clock, half a frame later (interpolated).
    for (source, offset) in [(Source::Front, 0.0), (Source::Rear, 0.5 / FPS)] {
        for &t0 in times {
            let t = t0 + offset;
            let noise = Vector6::from_fn(|i, _| {
                if i < 3 {
                    normal(&mut rng, SIGMA_R)
                } else {
                    normal(&mut rng, SIGMA_P)
                }
            });
            // Draw the outlier decision and offset always, so runs with and without outliers
            // see the same noise.
            let is_outlier = uniform(&mut rng, 0.0, 1.0) < OUTLIER_FRACTION;
            let wild = Vector6::from_fn(|i, _| {
                let mag = if i < 3 {
                    OUTLIER_ROT_RAD
                } else {
                    OUTLIER_POS_M
                };
                uniform(&mut rng, -mag, mag)
            });
            if (GAP.0..GAP.1).contains(&t) || t > DURATION_S {
                continue;
            }
            let xi = if outliers && is_outlier {
                noise + wild
            } else {
                noise
            };
            out.push(PoseObservation {
                t,
                source,
                scene_from_imu: traj.pose(t) * se3_exp(&xi),
            });
        }
    }
    out
}

fn run(outliers: bool) -> Run {
    let motion = episode_motion(Scenario::Tabletop, 8, 0, DURATION_S + 1.0);
    let unit = SimUnit::x5("FUSE", 8, 96, LensModel::Kb4).unwrap();
    let traj = &motion.left;
    let imu: Vec<_> =
        ImuSimulator::new(traj, unit.imu, 0.0, DURATION_S + 0.5, true, 8, "fusion").collect();
    let n = (DURATION_S * FPS) as usize;
    let times: Vec<f64> = (0..n).map(|k| k as f64 / FPS).collect();
    let obs = observations(traj, &times, outliers, 8);
    let noise = &unit.imu;
    let params = ImuParams::from_densities(
        noise.gyro_noise_density,
        noise.gyro_random_walk,
        noise.accel_noise_density,
        noise.accel_random_walk,
        GRAVITY,
    );
    let mut config = FusionConfig::default();
    config.front_sigma.position_m = SIGMA_P;
    config.front_sigma.rotation_rad = SIGMA_R;
    config.rear_sigma = config.front_sigma;
    let t0 = std::time::Instant::now();
    let result = fuse(&imu, &params, &times, &obs, &config).unwrap();
    eprintln!(
        "fused {} nodes, {} factors ({} downweighted), {} iterations, cost {:.1} -> {:.1} in {:.2} s",
        result.nodes.len(),
        result.observations_used,
        result.outliers_downweighted,
        result.iterations,
        result.initial_cost,
        result.final_cost,
        t0.elapsed().as_secs_f64()
    );
    // Marginals are reported and larger inside the gap.
    let mid_gap = result.nodes.iter().find(|n| n.t > 31.0).unwrap();
    let before_gap = result.nodes.iter().find(|n| n.t > 20.0).unwrap();
    let (_, sp_gap, _) = mid_gap.camera_pose(&Pose::identity());
    let (_, sp_ok, _) = before_gap.camera_pose(&Pose::identity());
    eprintln!("sigma_p: {sp_ok:.2e} m with observations, {sp_gap:.2e} m mid-gap");
    assert!(sp_ok > 0.0 && sp_gap > 3.0 * sp_ok);
    assert_eq!(mid_gap.support.label(), "imu");
    Run {
        positions: result
            .nodes
            .iter()
            .map(|n| n.scene_from_imu.translation.vector)
            .collect(),
        truth: times.iter().map(|&t| traj.pose(t)).collect(),
        times,
        downweighted: result.outliers_downweighted,
        used: result.observations_used,
    }
}

fn rms(v: &[f64]) -> f64 {
    (v.iter().map(|x| x * x).sum::<f64>() / v.len() as f64).sqrt()
}

#[test]
fn fusion_meets_simulator_acceptance() {
    let with = run(true);
    let without = run(false);
    let (mut inside, mut outside) = (Vec::new(), Vec::new());
    let mut shift: f64 = 0.0;
    let mut shifts = Vec::new();
    for k in 0..with.times.len() {
        let e = (with.positions[k] - with.truth[k].translation.vector).norm();
        if (GAP.0..GAP.1).contains(&with.times[k]) {
            inside.push(e);
        } else {
            outside.push(e);
        }
        let d = (with.positions[k] - without.positions[k]).norm();
        shift = shift.max(d);
        shifts.push(d);
    }
    let (ate_out, ate_in) = (rms(&outside), rms(&inside));
    let max_in = inside.iter().copied().fold(0.0, f64::max);
    eprintln!(
        "ATE outside the gap {:.3} mm (max {:.3} mm), inside {:.3} mm (max {:.3} mm); outliers \
         shift the solution by {:.3} mm RMS, {:.3} mm max; {} of {} factors downweighted",
        ate_out * 1e3,
        outside.iter().copied().fold(0.0, f64::max) * 1e3,
        ate_in * 1e3,
        max_in * 1e3,
        rms(&shifts) * 1e3,
        shift * 1e3,
        with.downweighted,
        with.used
    );
    assert!(ate_out < 2e-3, "ATE outside the gap {ate_out}");
    assert!(ate_in < 2e-2, "ATE inside the gap {ate_in}");
    assert!(shift < 5e-4, "outliers move the solution by {shift} m");
    assert!(with.downweighted >= (OUTLIER_FRACTION * 0.8 * with.used as f64) as usize);
    assert!(without.used == with.used);
}
