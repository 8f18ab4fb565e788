#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]
//! Metric recovery acceptance on a simulated mapping episode: scale within 0.5 %, gravity
//! direction within 0.1°, accelerometer bias within 0.02 m/s², despite noisy localizations, lost
//! frames and a few wrong relocalizations; and a refusal (not a scale) when the recording has
//! too little acceleration.

use kiwi_backend::fusion::preint::ImuParams;
use kiwi_backend::metric::{MapFrame, MetricConfig, recover_metric};
use kiwi_core::geometry::{Pose, se3_exp};
use kiwi_core::imu::ImuSample;
use kiwi_fixtures::imu::{GRAVITY, ImuSimulator};
use kiwi_fixtures::motion::{Harmonic, Signal, Signal3, Trajectory};
use kiwi_fixtures::rng::{normal, stream, uniform};
use kiwi_fixtures::scenario::{Scenario, episode_motion};
use kiwi_fixtures::unit::{LensModel, SimUnit};
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3, Vector6};

const FPS: f64 = 119.88;
const DURATION_S: f64 = 60.0;
/// Map units per metre of the simulated map (monocular maps have an arbitrary scale).
const MAP_UNITS_PER_M: f64 = 0.37;
/// Visual noise (metric equivalent).
const SIGMA_P: f64 = 1e-3;
const SIGMA_R: f64 = 0.1 * std::f64::consts::PI / 180.0;
/// Frames whose relocalization failed (reported lost, so not passed in).
const LOST_FRACTION: f64 = 0.05;
/// Accepted relocalizations that are nevertheless wrong by centimetres and degrees.
const WRONG_FRACTION: f64 = 0.02;

struct Sim {
    frames: Vec<MapFrame>,
    imu: Vec<ImuSample>,
    params: ImuParams,
    cam_from_imu: Pose,
    time_shift_s: f64,
    map_rotation: UnitQuaternion<f64>,
    accel_bias_mid: Vector3<f64>,
}

fn simulate(traj: &Trajectory, seed: u64) -> Sim {
    let unit = SimUnit::x5("METRIC", seed, 96, LensModel::Kb4).unwrap();
    let lens = unit.lens("rear").unwrap();
    let cam_from_imu = lens.cam_from_imu;
    let time_shift_s = lens.time_shift_s;
    // IMU on the trajectory clock; the camera stamps frames at t_cam = t − time_shift.
    let mut sim = ImuSimulator::new(traj, unit.imu, 0.0, DURATION_S + 0.5, true, seed, "metric");
    let mut imu = Vec::new();
    let mid_index = (0.5 * DURATION_S * unit.imu.rate_hz) as usize;
    let mut accel_bias_mid = Vector3::zeros();
    while let Some(s) = sim.next() {
        imu.push(s);
        if imu.len() == mid_index {
            accel_bias_mid = sim.bias().accel;
        }
    }
    let map_rotation = UnitQuaternion::from_euler_angles(0.4, -0.3, 1.2);
    let map_from_world = |p: &Pose| -> Pose {
        Isometry3::from_parts(
            Translation3::from(
                map_rotation * p.translation.vector * MAP_UNITS_PER_M
                    + Vector3::new(0.5, -1.0, 2.0),
            ),
            map_rotation * p.rotation,
        )
    };
    let mut rng = stream(seed, "metric-test/frames");
    let mut frames = Vec::new();
    let n = ((DURATION_S - 0.2) * FPS) as usize;
    for k in 0..n {
        let t_true = 0.1 + k as f64 / FPS;
        let world_from_cam = traj.pose(t_true) * cam_from_imu.inverse();
        let noise = Vector6::from_fn(|i, _| {
            if i < 3 {
                normal(&mut rng, SIGMA_R)
            } else {
                normal(&mut rng, SIGMA_P)
            }
        });
        let lost = uniform(&mut rng, 0.0, 1.0) < LOST_FRACTION;
        let wrong = uniform(&mut rng, 0.0, 1.0) < WRONG_FRACTION;
        if lost {
            continue;
        }
        let mut xi = noise;
        if wrong {
            xi += Vector6::new(0.03, -0.02, 0.025, 0.05, -0.04, 0.03);
        }
        frames.push(MapFrame {
            t: t_true - time_shift_s,
            map_from_cam: map_from_world(&(world_from_cam * se3_exp(&xi))),
        });
    }
    let noise = &unit.imu;
    let params = ImuParams::from_densities(
        noise.gyro_noise_density,
        noise.gyro_random_walk,
        noise.accel_noise_density,
        noise.accel_random_walk,
        GRAVITY,
    );
    Sim {
        frames,
        imu,
        params,
        cam_from_imu,
        time_shift_s,
        map_rotation,
        accel_bias_mid,
    }
}

#[test]
fn metric_recovery_on_a_mapping_episode() {
    for seed in [11, 12] {
        let motion = episode_motion(Scenario::Mapping, seed, 0, DURATION_S + 1.0);
        let sim = simulate(&motion.left, seed);
        let t0 = std::time::Instant::now();
        let r = recover_metric(
            &sim.frames,
            &sim.imu,
            &sim.params,
            &sim.cam_from_imu,
            sim.time_shift_s,
            &MetricConfig::default(),
        )
        .unwrap();
        let scale_err = r.scale * MAP_UNITS_PER_M - 1.0;
        let gravity_true = sim.map_rotation * -Vector3::z();
        let gravity_err = r.gravity_in_map.angle(&gravity_true);
        let bias_err = (r.accel_bias - sim.accel_bias_mid).abs().max();
        eprintln!(
            "seed {seed}: {} frames, scale error {:+.3} % (linear init {:+.2} %, sigma {:.3} %), \
             gravity {:.4} deg (sigma {:.4}), accel bias error {:.4} m/s² (sigma {:.4?}), \
             excitation {:.3} m/s², {} downweighted, residuals {:.2} mm / {:.3} deg, \
             {} iterations, {:.2} s",
            r.frames_used,
            scale_err * 100.0,
            (r.initial_scale * MAP_UNITS_PER_M - 1.0) * 100.0,
            r.conditioning.scale_sigma * 100.0,
            gravity_err.to_degrees(),
            r.conditioning.gravity_sigma_rad.to_degrees(),
            bias_err,
            r.accel_bias_sigma.as_slice(),
            r.conditioning.excitation_rms_m_s2,
            r.outliers_downweighted,
            r.rms_position_m * 1e3,
            r.rms_rotation_rad.to_degrees(),
            r.iterations,
            t0.elapsed().as_secs_f64(),
        );
        assert!(scale_err.abs() < 5e-3, "scale error {scale_err}");
        assert!(gravity_err < 0.1f64.to_radians(), "gravity {gravity_err}");
        assert!(bias_err < 0.02, "accel bias error {bias_err}");
        // The world is z-up: the map's gravity maps to −z.
        let g_world = r.world_from_map.rotation * r.gravity_in_map;
        assert!((g_world + Vector3::z()).norm() < 1e-9);
        // The wrong relocalizations are recognised.
        let wrong = (WRONG_FRACTION * r.frames_used as f64) as usize;
        assert!(
            r.outliers_downweighted >= wrong / 2 && r.outliers_downweighted <= 3 * wrong,
            "{} downweighted for ~{wrong} wrong",
            r.outliers_downweighted
        );
    }
}

#[test]
fn too_little_acceleration_is_refused() {
    // The wrist barely moves: a slow turn in place with sub-millimetre drift.
    let base = Isometry3::from_parts(
        Translation3::new(0.2, 0.4, 1.1),
        UnitQuaternion::from_euler_angles(1.2, 0.1, 0.4),
    );
    let mut traj = Trajectory::fixed(&base);
    traj.rotation = Signal3([0.3, 0.2, 0.25].map(|amp| Signal {
        constant: 0.0,
        ramps: vec![],
        harmonics: vec![Harmonic {
            amplitude: amp,
            omega: 0.15,
            phase: amp,
        }],
    }));
    let sim = simulate(&traj, 5);
    let e = recover_metric(
        &sim.frames,
        &sim.imu,
        &sim.params,
        &sim.cam_from_imu,
        sim.time_shift_s,
        &MetricConfig::default(),
    )
    .unwrap_err()
    .to_string();
    eprintln!("{e}");
    assert!(e.contains("too little acceleration"), "{e}");
}

fn write_poses(path: &std::path::Path, frames: &[MapFrame], lost_every: usize) {
    use std::fmt::Write as _;
    let mut s = String::from("t,status,px,py,pz,qx,qy,qz,qw,inliers,reason\n");
    for (k, f) in frames.iter().enumerate() {
        if k % lost_every == lost_every - 1 {
            writeln!(s, "{:.9},lost,,,,,,,,0,too few inliers", f.t).unwrap();
            continue;
        }
        let (p, q) = (
            f.map_from_cam.translation.vector,
            f.map_from_cam.rotation.coords,
        );
        writeln!(
            s,
            "{:.9},tracked,{},{},{},{},{},{},{},120,",
            f.t, p.x, p.y, p.z, q.x, q.y, q.z, q.w
        )
        .unwrap();
    }
    std::fs::write(path, s).unwrap();
}

fn kiwi(args: &[&str]) -> std::process::Output {
    std::process::Command::new(env!("CARGO_BIN_EXE_kiwi"))
        .args(args)
        .output()
        .unwrap()
}

/// `kiwi metric` on both lenses' maps, then `kiwi place` with both metric files.
#[test]
fn metric_and_place_commands() {
    let dir = tempfile::tempdir().unwrap();
    let d = |n: &str| dir.path().join(n).to_str().unwrap().to_string();
    let seed = 21;
    let motion = episode_motion(Scenario::Mapping, seed, 0, DURATION_S + 1.0);
    let unit = SimUnit::x5("METRIC", seed, 96, LensModel::Kb4).unwrap();
    let sim = simulate(&motion.left, seed);
    kiwi_core::imu::write_imu_csv(std::path::Path::new(&d("imu.csv")), &sim.imu).unwrap();
    unit.true_calibration("2026-01-01")
        .save(std::path::Path::new(&d("calibration.json")))
        .unwrap();
    // The rear frames of `simulate`; the front map is another arbitrary similarity frame.
    write_poses(std::path::Path::new(&d("rear.csv")), &sim.frames, 50);
    let front = unit.lens("front").unwrap();
    let front_map_rotation = UnitQuaternion::from_euler_angles(-0.2, 0.5, -2.0);
    let mut rng = stream(seed, "metric-test/front");
    let front_frames: Vec<MapFrame> = sim
        .frames
        .iter()
        .map(|f| {
            let t = f.t + sim.time_shift_s - front.time_shift_s;
            let xi =
                Vector6::from_fn(|i, _| normal(&mut rng, if i < 3 { SIGMA_R } else { SIGMA_P }));
            let w = motion.left.pose(t + front.time_shift_s)
                * front.cam_from_imu.inverse()
                * se3_exp(&xi);
            MapFrame {
                t,
                map_from_cam: Isometry3::from_parts(
                    Translation3::from(
                        front_map_rotation * w.translation.vector * 1.9
                            + Vector3::new(-3.0, 0.2, 0.1),
                    ),
                    front_map_rotation * w.rotation,
                ),
            }
        })
        .collect();
    write_poses(std::path::Path::new(&d("front.csv")), &front_frames, 40);
    for (lens, poses) in [("rear", "rear.csv"), ("front", "front.csv")] {
        let out = kiwi(&[
            "metric",
            "--poses",
            &d(poses),
            "--imu",
            &d("imu.csv"),
            "--calibration",
            &d("calibration.json"),
            "--lens",
            lens,
            "--out",
            &d(&format!("{lens}-metric.json")),
            "--json",
        ]);
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
        let truth = if lens == "rear" {
            1.0 / MAP_UNITS_PER_M
        } else {
            1.0 / 1.9
        };
        let scale = v["scale_m_per_map_unit"].as_f64().unwrap();
        eprintln!(
            "{lens}: scale error {:+.3} %, {}",
            (scale / truth - 1.0) * 100.0,
            v["conditioning"]
        );
        assert!((scale / truth - 1.0).abs() < 5e-3);
        assert!(v["frames_lost"].as_u64().unwrap() > 0);
    }
    let out = kiwi(&[
        "place",
        "--front",
        &d("front.csv"),
        "--rear",
        &d("rear.csv"),
        "--calibration",
        &d("calibration.json"),
        "--front-metric",
        &d("front-metric.json"),
        "--rear-metric",
        &d("rear-metric.json"),
        "--out",
        &d("placement.json"),
        "--json",
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    eprintln!("placement: {v}");
    let (pairs, inliers) = (v["pairs"].as_u64().unwrap(), v["inliers"].as_u64().unwrap());
    assert!(pairs > 6000 && inliers as f64 > 0.9 * pairs as f64);
    assert!(v["rms_position_m"].as_f64().unwrap() < 6e-3);
    // The same front stream seen through a front map already placed (here its own, with the
    // placement just made) witnesses the same placement: pooled in, the fit stays put and counts
    // the witness's pairs; the witness without its map's metric and placement is refused.
    let place_with = |extra: &[&str]| {
        let mut a = vec![
            "place".to_string(),
            "--front".into(),
            d("front.csv"),
            "--rear".into(),
            d("rear.csv"),
            "--calibration".into(),
            d("calibration.json"),
            "--front-metric".into(),
            d("front-metric.json"),
            "--rear-metric".into(),
            d("rear-metric.json"),
            "--out".into(),
            d("pooled.json"),
            "--json".into(),
        ];
        a.extend(extra.iter().map(ToString::to_string));
        kiwi(&a.iter().map(String::as_str).collect::<Vec<_>>())
    };
    let out = place_with(&[
        "--witness",
        &d("front.csv"),
        "--witness-metric",
        &d("front-metric.json"),
        "--witness-placement",
        &d("placement.json"),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let w: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let translation = |v: &serde_json::Value| -> Vector3<f64> {
        let t = &v["scene_from_front_map"]["translation_m"];
        Vector3::from_fn(|i, _| t[i].as_f64().unwrap())
    };
    let moved = (translation(&w) - translation(&v)).norm();
    let witness_pairs = w["witness_pairs"].as_u64().unwrap();
    eprintln!(
        "pooled with the witness: moved {:.3} mm, {witness_pairs} witness pairs",
        moved * 1e3
    );
    assert!(moved < 1e-3, "{moved}");
    assert!(witness_pairs > 6000 && w["pairs"].as_u64().unwrap() == pairs + witness_pairs);
    let out = place_with(&["--witness", &d("front.csv")]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("--witness-metric"),
        "{err}"
    );
    // A poses file without the status column is refused with the column named.
    std::fs::write(d("bad.csv"), "t,px,py,pz,qx,qy,qz,qw\n0,0,0,0,0,0,0,1\n").unwrap();
    let out = kiwi(&[
        "metric",
        "--poses",
        &d("bad.csv"),
        "--imu",
        &d("imu.csv"),
        "--calibration",
        &d("calibration.json"),
        "--out",
        &d("m.json"),
    ]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("bad.csv") && err.contains("status"),
        "{err}"
    );

    // The rolling readout: with a camera meta.json beside the IMU log, the calibration's readout
    // of its recording mode is used, as if given with --readout, and poses are taken at their
    // exposure centre (the result differs from a global shutter's).
    let cal =
        kiwi_core::artifact::UnitCalibration::load(std::path::Path::new(&d("calibration.json")))
            .unwrap();
    let mode = cal
        .recording_modes
        .iter()
        .find(|m| m.readout_time_s.is_some_and(|r| r > 0.0))
        .unwrap();
    let meta = kiwi_core::layout::CameraMeta {
        camera: "left".into(),
        unit_id: cal.unit_id.clone(),
        camera_model: cal.camera_model.clone(),
        mode: mode.name.clone(),
        fps: mode.fps,
        lenses: vec!["front".into(), "rear".into()],
        audio_rate_hz: 48_000,
        source: "test".into(),
        recording: None,
    };
    std::fs::write(d("meta.json"), serde_json::to_string(&meta).unwrap()).unwrap();
    let metric = |extra: &[&str]| -> (bool, String, String) {
        let mut args = vec![
            "metric",
            "--poses",
            &d("rear.csv"),
            "--imu",
            &d("imu.csv"),
            "--calibration",
            &d("calibration.json"),
            "--out",
            &d("r.json"),
            "--json",
        ]
        .into_iter()
        .map(str::to_string)
        .collect::<Vec<_>>();
        args.extend(extra.iter().map(ToString::to_string));
        let refs: Vec<&str> = args.iter().map(String::as_str).collect();
        let out = kiwi(&refs);
        let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap_or_default();
        (
            out.status.success(),
            format!("{} {}", v["world_from_map"], v["scale_m_per_map_unit"]),
            String::from_utf8_lossy(&out.stderr).into_owned(),
        )
    };
    let readout = mode.readout_time_s.unwrap().to_string();
    let (ok, from_meta, err) = metric(&[]);
    assert!(ok, "{err}");
    let (ok, given, err) = metric(&["--readout", &readout]);
    assert!(ok, "{err}");
    assert_eq!(from_meta, given);
    let (ok, global, err) = metric(&["--readout", "0"]);
    assert!(ok, "{err}");
    assert_ne!(from_meta, global);
    let (ok, _, err) = metric(&["--readout=-0.01"]);
    assert!(!ok && err.contains("--readout"), "{err}");
}
