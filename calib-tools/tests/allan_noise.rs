//! `kiwi-calib imu-noise`: overlapping ADEV against allantools, and noise densities recovered
//! from simulated static logs.

#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

use std::path::Path;

use kiwi_calib::allan::{
    AllanOptions, StaticLog, Term, analyse, averaging_factors, oadev_axes, read_static_log,
    write_outputs,
};
use kiwi_fixtures::imu::ImuSimulator;
use kiwi_fixtures::motion::Trajectory;
use kiwi_fixtures::unit::SimImuNoise;
use nalgebra::{Isometry3, Translation3, UnitQuaternion};

/// The golden input, regenerated bit for bit as `make_allan_golden.py` does.
fn golden_series(axis: u64, n: usize) -> Vec<f64> {
    let mut x: u64 = 0x9E37_79B9_7F4A_7C15u64.wrapping_add(axis);
    let mut uniform = || {
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        (x >> 11) as f64 * (1.0 / 9_007_199_254_740_992.0)
    };
    let mut rw = 0.0;
    (0..n)
        .map(|_| {
            let (a, b, c, d, e) = (uniform(), uniform(), uniform(), uniform(), uniform());
            rw += 1e-6 * (e - 0.5);
            1e-3 * (((a + b) + (c + d)) - 2.0) + rw + 0.05 * axis as f64
        })
        .collect()
}

#[test]
fn oadev_matches_allantools_golden_values() {
    let text = std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/golden/allan_oadev.json"),
    )
    .unwrap();
    let golden: serde_json::Value = serde_json::from_str(&text).unwrap();
    let n = golden["n"].as_u64().unwrap() as usize;
    let rate = golden["rate"].as_f64().unwrap();
    let m: Vec<usize> = golden["m"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_u64().unwrap() as usize)
        .collect();
    // Our averaging-time grid is the script's.
    assert_eq!(averaging_factors(n, 20, 0.3), m);
    let axes = golden["axes"].as_array().unwrap();
    let data: Vec<Vec<f64>> = (0..axes.len())
        .map(|a| golden_series(a as u64, n))
        .collect();
    let curves = oadev_axes(data, rate, &m);
    let mut worst = 0.0f64;
    for (curve, g) in curves.iter().zip(axes) {
        let adev: Vec<f64> = g["adev"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_f64().unwrap())
            .collect();
        let counts: Vec<usize> = g["n"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_u64().unwrap() as usize)
            .collect();
        assert_eq!(curve.adev.len(), adev.len());
        for (j, (&ours, &theirs)) in curve.adev.iter().zip(&adev).enumerate() {
            let rel = (ours / theirs - 1.0).abs();
            worst = worst.max(rel);
            assert!(rel < 1e-9, "m = {}: {ours} vs allantools {theirs}", m[j]);
            assert_eq!(curve.n_terms[j], counts[j]);
        }
    }
    println!("worst relative difference to allantools: {worst:.2e}");
}

/// A simulated static log held in memory.
fn static_log(noise: SimImuNoise, duration_s: f64, seed: u64) -> StaticLog {
    let rest = Isometry3::from_parts(
        Translation3::new(0.0, 0.0, 0.8),
        UnitQuaternion::from_euler_angles(0.02, -0.015, 0.7),
    );
    let trajectory = Trajectory::fixed(&rest);
    let sim = ImuSimulator::new(&trajectory, noise, 0.0, duration_s, true, seed, "static");
    let mut times = Vec::new();
    let mut axes: [Vec<f64>; 6] = Default::default();
    for s in sim {
        times.push(s.t);
        for k in 0..3 {
            axes[k].push(s.gyro[k]);
            axes[k + 3].push(s.accel[k]);
        }
    }
    StaticLog::from_samples(Path::new("sim/imu_static/imu.csv"), &times, axes).unwrap()
}

/// Densities whose random-walk region spans more than a decade of averaging times in a
/// 4-hour log: crossover τ = 3N²/K² = 75 s, longest τ = 1440 s.
fn noise() -> SimImuNoise {
    SimImuNoise {
        rate_hz: 100.0,
        gyro_noise_density: 1.5e-3,
        gyro_random_walk: 3e-4,
        accel_noise_density: 1.5e-2,
        accel_random_walk: 3e-3,
        gyro_turn_on_bias: [0.01, -0.02, 0.005],
        accel_turn_on_bias: [0.05, 0.02, -0.08],
    }
}

#[test]
fn simulated_static_logs_give_the_true_densities() {
    let truth = noise();
    let mut worst_n = 0.0f64;
    let mut worst_k = 0.0f64;
    for seed in [1u64, 2, 3] {
        let log = static_log(truth, 4.0 * 3600.0, seed);
        let report = analyse(log, &AllanOptions::default()).unwrap();
        for (a, axis) in report.axes.iter().enumerate() {
            let (n_true, k_true) = if a < 3 {
                (truth.gyro_noise_density, truth.gyro_random_walk)
            } else {
                (truth.accel_noise_density, truth.accel_random_walk)
            };
            let n_err = axis.fit.white_noise.value / n_true - 1.0;
            let k_err = axis.fit.random_walk.value / k_true - 1.0;
            println!(
                "seed {seed} {}: N {:+.2} % (±{:.2} %), K {:+.1} % (±{:.1} %), B {:.2e}, rms {:.2}",
                axis.axis,
                100.0 * n_err,
                100.0 * axis.fit.white_noise.std / n_true,
                100.0 * k_err,
                100.0 * axis.fit.random_walk.std / k_true,
                axis.fit.bias_instability.value,
                axis.fit.weighted_rms
            );
            assert!(
                n_err.abs() < 0.03,
                "seed {seed} {}: N off by {n_err}",
                axis.axis
            );
            assert!(
                k_err.abs() < 0.15,
                "seed {seed} {}: K off by {k_err}",
                axis.axis
            );
            assert!(axis.fit.random_walk.determined);
            worst_n = worst_n.max(n_err.abs());
            worst_k = worst_k.max(k_err.abs());
        }
        assert!(report.warnings.iter().all(|w| !w.contains("random-walk")));
    }
    println!(
        "worst: N {:.2} %, K {:.1} %",
        100.0 * worst_n,
        100.0 * worst_k
    );
}

#[test]
fn a_short_log_says_the_random_walk_is_poorly_determined() {
    let log = static_log(noise(), 600.0, 5);
    // Required (the default): an error that says how long a log is needed.
    let err = analyse(log.clone(), &AllanOptions::default())
        .unwrap_err()
        .to_string();
    assert!(err.contains("random-walk"), "{err}");
    assert!(err.contains("poorly determined"), "{err}");
    assert!(err.contains("at least"), "{err}");
    // Not required: a result with a warning, and the white noise still right.
    let options = AllanOptions {
        require: vec![Term::White],
        ..AllanOptions::default()
    };
    let report = analyse(log, &options).unwrap();
    assert!(
        report
            .warnings
            .iter()
            .any(|w| w.contains("random-walk") && w.contains("poorly determined")),
        "{:?}",
        report.warnings
    );
    for a in &report.axes[..3] {
        assert!((a.fit.white_noise.value / 1.5e-3 - 1.0).abs() < 0.05);
    }
}

fn write_csv(path: &Path, times: &[f64], axes: &[Vec<f64>; 6]) {
    let mut s = String::from("t,gx,gy,gz,ax,ay,az\n");
    for (i, t) in times.iter().enumerate() {
        s.push_str(&format!(
            "{t},{},{},{},{},{},{}\n",
            axes[0][i], axes[1][i], axes[2][i], axes[3][i], axes[4][i], axes[5][i]
        ));
    }
    std::fs::write(path, s).unwrap();
}

fn small_log() -> (Vec<f64>, [Vec<f64>; 6]) {
    let log = static_log(noise(), 300.0, 9);
    let times: Vec<f64> = (0..log.len()).map(|i| i as f64 / 100.0).collect();
    (times, log.axes)
}

#[test]
fn the_file_reader_matches_memory_and_rejects_bad_logs() {
    let dir = tempfile::tempdir().unwrap();
    let (times, axes) = small_log();
    let good = dir.path().join("imu.csv");
    write_csv(&good, &times, &axes);
    let read = read_static_log(&good, None).unwrap();
    assert_eq!(read.len(), times.len());
    assert!((read.rate_hz - 100.0).abs() < 1e-6);
    for a in 0..6 {
        for i in [0, 1234, times.len() - 1] {
            assert_eq!(read.axes[a][i], axes[a][i]);
        }
    }
    let options = AllanOptions {
        require: vec![Term::White],
        ..AllanOptions::default()
    };
    assert!(analyse(read, &options).is_ok());

    // A gap.
    let mut t_gap = times.clone();
    for t in t_gap.iter_mut().skip(5000) {
        *t += 0.5;
    }
    let p = dir.path().join("gap.csv");
    write_csv(&p, &t_gap, &axes);
    let err = read_static_log(&p, None).unwrap_err().to_string();
    assert!(err.contains("gap") && err.contains("line 5002"), "{err}");

    // Time going backwards.
    let mut t_back = times.clone();
    t_back[700] = t_back[698];
    let p = dir.path().join("back.csv");
    write_csv(&p, &t_back, &axes);
    let err = read_static_log(&p, None).unwrap_err().to_string();
    assert!(
        err.contains("does not increase") && err.contains("line 702"),
        "{err}"
    );

    // A broken number.
    let p = dir.path().join("broken.csv");
    let text = std::fs::read_to_string(&good)
        .unwrap()
        .replacen("\n1,", "\n1,x", 1);
    std::fs::write(&p, text).unwrap();
    let err = read_static_log(&p, None).unwrap_err().to_string();
    assert!(err.contains("line 102") && err.contains("gx"), "{err}");

    // Accelerometer in g.
    let mut in_g = axes.clone();
    for a in 3..6 {
        for v in &mut in_g[a] {
            *v /= 9.80665;
        }
    }
    let p = dir.path().join("g.csv");
    write_csv(&p, &times, &in_g);
    // The shared IMU plausibility check names the unit mistake as the file is read.
    let err = read_static_log(&p, None).unwrap_err().to_string();
    assert!(err.contains("in g") && err.contains("9.80665"), "{err}");

    // Somebody picked the IMU up for two seconds.
    let mut moved = axes.clone();
    for i in 15_000..15_200 {
        moved[2][i] += 0.8;
        moved[3][i] += 1.5;
    }
    let p = dir.path().join("moved.csv");
    write_csv(&p, &times, &moved);
    let log = read_static_log(&p, None).unwrap();
    let err = analyse(log, &options).unwrap_err().to_string();
    assert!(
        err.contains("not static") && err.contains("t = 15"),
        "{err}"
    );
}

#[test]
fn outputs_hold_the_result_the_kalibr_file_and_a_plot() {
    let dir = tempfile::tempdir().unwrap();
    let log = static_log(noise(), 1800.0, 4);
    let options = AllanOptions {
        require: vec![Term::White],
        ..AllanOptions::default()
    };
    let report = analyse(log, &options).unwrap();
    let written = write_outputs(&report, dir.path(), None, None).unwrap();
    let yaml = std::fs::read_to_string(&written.kalibr_imu).unwrap();
    let imu = kiwi_core::kalibr::imu_from_yaml(&yaml, &written.kalibr_imu).unwrap();
    assert!((imu.gyroscope_noise_density / 1.5e-3 - 1.0).abs() < 0.05);
    let svg = std::fs::read_to_string(&written.plot).unwrap();
    assert!(
        svg.starts_with("<svg") && svg.contains("height=\"1240\""),
        "{svg:.300}"
    );
    assert!(svg.contains("Gyroscope Allan deviation") && svg.contains("Accelerometer"));
    let md = std::fs::read_to_string(&written.report).unwrap();
    assert!(md.contains("allan.svg") && md.contains("0.664"));
    let json = kiwi_calib::allan::summary_json(&report);
    for axis in ["gx", "gy", "gz", "ax", "ay", "az"] {
        let a = &json["axes"][axis];
        assert_eq!(
            a["taus"].as_array().unwrap().len(),
            a["adev"].as_array().unwrap().len()
        );
        assert!(a["white_noise"].as_f64().unwrap() > 0.0);
    }
    assert!(json["rate_hz"].as_f64().unwrap() > 99.0);
}
