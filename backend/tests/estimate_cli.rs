#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]
//! `kiwi fuse` end to end on simulated files: formats, calibration handling (cam_from_imu, time
//! shift, IMU noise), accuracy of the written `scene_from_front_cam`, `--json`, input errors.

use std::fmt::Write as _;
use std::process::Command;

use kiwi_core::geometry::se3_exp;
use kiwi_fixtures::imu::ImuSimulator;
use kiwi_fixtures::rng::{normal, stream};
use kiwi_fixtures::scenario::{Scenario, episode_motion};
use kiwi_fixtures::unit::{LensModel, SimUnit};
use nalgebra::{Quaternion, UnitQuaternion, Vector3, Vector6};

const FPS: f64 = 119.88;

fn kiwi(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_kiwi"))
        .args(args)
        .output()
        .unwrap()
}

#[test]
fn fuse_command_writes_camera_trajectory() {
    let dir = tempfile::tempdir().unwrap();
    let d = |n: &str| dir.path().join(n);
    let motion = episode_motion(Scenario::Tabletop, 5, 0, 12.0);
    let unit = SimUnit::x5("CLI", 5, 96, LensModel::Kb4).unwrap();
    let traj = &motion.right;
    let imu: Vec<_> = ImuSimulator::new(traj, unit.imu, 0.0, 11.0, true, 5, "cli").collect();
    kiwi_core::imu::write_imu_csv(&d("imu.csv"), &imu).unwrap();
    let cal = unit.true_calibration("2026-01-01");
    cal.save(&d("calibration.json")).unwrap();
    let lens = cal.lens("front").unwrap();
    let cam_from_imu = lens.cam_from_imu().unwrap();
    let shift = lens.time_shift_s.unwrap_or(0.0);

    let mut frames = String::from("t,index\n");
    let mut obs = String::from("t,source,px,py,pz,qx,qy,qz,qw\n");
    let mut rng = stream(5, "cli/obs");
    let cam_times: Vec<f64> = (0..1000).map(|k| 0.2 + k as f64 / FPS).collect();
    for (k, t) in cam_times.iter().enumerate() {
        writeln!(frames, "{t:.9},{k}").unwrap();
        let t_imu = t + shift;
        let xi = Vector6::from_fn(|i, _| normal(&mut rng, if i < 3 { 1.7e-3 } else { 1e-3 }));
        let z = traj.pose(t_imu) * se3_exp(&xi);
        let (p, q) = (z.translation.vector, z.rotation.coords);
        writeln!(
            obs,
            "{t_imu:.9},front,{},{},{},{},{},{},{}",
            p.x, p.y, p.z, q.x, q.y, q.z, q.w
        )
        .unwrap();
    }
    std::fs::write(d("frames.csv"), &frames).unwrap();
    std::fs::write(d("obs.csv"), &obs).unwrap();
    let s = |p: &std::path::Path| p.to_str().unwrap().to_string();
    let (imu_p, frames_p, obs_p, cal_p, out_p) = (
        s(&d("imu.csv")),
        s(&d("frames.csv")),
        s(&d("obs.csv")),
        s(&d("calibration.json")),
        s(&d("traj.csv")),
    );
    let out = kiwi(&[
        "fuse",
        "--imu",
        &imu_p,
        "--frames",
        &frames_p,
        "--observations",
        &obs_p,
        "--calibration",
        &cal_p,
        "--lens",
        "front",
        "--out",
        &out_p,
        "--json",
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let summary: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    for key in [
        "nodes",
        "observations_used",
        "outliers_downweighted",
        "iterations",
        "final_cost",
        "seconds",
    ] {
        assert!(summary.get(key).is_some(), "missing {key} in {summary}");
    }
    assert_eq!(summary["nodes"], 1000);
    let text = std::fs::read_to_string(d("traj.csv")).unwrap();
    let mut lines = text.lines();
    assert_eq!(
        lines.next().unwrap(),
        "t,px,py,pz,qx,qy,qz,qw,sigma_p,sigma_r,support"
    );
    let mut worst: f64 = 0.0;
    let mut rows = 0;
    for (line, t) in lines.zip(&cam_times) {
        let f: Vec<&str> = line.split(',').collect();
        let v: Vec<f64> = f[..10].iter().map(|x| x.parse().unwrap()).collect();
        assert!((v[0] - t).abs() < 1e-8, "frame clock kept");
        let truth = traj.pose(t + shift) * cam_from_imu.inverse();
        worst = worst.max((Vector3::new(v[1], v[2], v[3]) - truth.translation.vector).norm());
        let q = UnitQuaternion::from_quaternion(Quaternion::new(v[7], v[4], v[5], v[6]));
        assert!(q.angle_to(&truth.rotation) < 0.01);
        assert!(v[8] > 0.0 && v[8] < 0.01 && v[9] > 0.0);
        assert!(f[10].starts_with("front"));
        rows += 1;
    }
    assert_eq!(rows, 1000);
    eprintln!(
        "kiwi fuse: worst camera position error {:.3} mm; {summary}",
        worst * 1e3
    );
    assert!(worst < 2e-3);

    // Without a calibration the IMU noise is required ...
    let out = kiwi(&[
        "fuse",
        "--imu",
        &imu_p,
        "--frames",
        &frames_p,
        "--observations",
        &obs_p,
        "--out",
        &out_p,
    ]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("--imu-noise"));
    // ... and with it the output is scene_from_imu.
    let out = kiwi(&[
        "fuse",
        "--imu",
        &imu_p,
        "--frames",
        &frames_p,
        "--observations",
        &obs_p,
        "--out",
        &out_p,
        "--imu-noise",
        "1.5e-4,2e-5,1.5e-3,3e-4",
        "--pose-sigma",
        "front=0.001,0.0017",
        "--huber",
        "4",
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );

    // A wrong header names the file and the expected header.
    std::fs::write(d("bad.csv"), "time,src\n1,front\n").unwrap();
    let bad = s(&d("bad.csv"));
    let out = kiwi(&[
        "fuse",
        "--imu",
        &imu_p,
        "--frames",
        &frames_p,
        "--observations",
        &bad,
        "--calibration",
        &cal_p,
        "--out",
        &out_p,
    ]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        err.contains("bad.csv") && err.contains("t,source,px,py,pz,qx,qy,qz,qw"),
        "{err}"
    );
}
