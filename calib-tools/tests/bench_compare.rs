#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]
//! `bench compare` on a simulated encoder (50 Hz, quantized counts, host clock with its own
//! origin and jitter) and a simulated vision estimate (119.88 fps, noisy, with missing frames):
//! the clock offset is recovered within 2 ms and the RMSE within 10 % of the truth-computed RMSE.

use std::fmt::Write as _;
use std::path::Path;

use kiwi_calib::bench::compare::{EncoderMap, OpeningUnit, run};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

/// The jaw's true opening (rad) at camera time `t`: open–close cycles of two speeds.
fn opening(t: f64) -> f64 {
    0.4 + 0.3 * (2.1 * t).sin() + 0.05 * (5.7 * t + 1.0).sin()
}

const ZERO_COUNT: f64 = 1024.0;

fn write_encoder(path: &Path, offset: f64, rng: &mut ChaCha8Rng) {
    let jitter = Normal::new(0.0, 0.0005).unwrap();
    let mut s = String::from("t,raw,angle_rad\n");
    for k in 0..(20 * 50) {
        let t_cam = f64::from(k) / 50.0;
        let raw = (ZERO_COUNT + opening(t_cam) / std::f64::consts::TAU * 4096.0).round();
        let angle = (raw - ZERO_COUNT) / 4096.0 * std::f64::consts::TAU;
        let t_host = t_cam + offset + jitter.sample(rng);
        writeln!(s, "{t_host:.6},{raw},{angle:.6}").unwrap();
    }
    std::fs::write(path, s).unwrap();
}

/// Vision rows from 1 s to 19 s of camera time; returns the truth-computed RMSE.
fn write_vision(
    path: &Path,
    unit: &str,
    to_unit: impl Fn(f64) -> f64,
    sigma: f64,
    rng: &mut ChaCha8Rng,
) -> f64 {
    let noise = Normal::new(0.0, sigma).unwrap();
    let mut s = String::from("t,opening,unit,confidence,status\n");
    let (mut sum, mut n) = (0.0, 0usize);
    let fps = 119.88;
    for k in (fps as usize)..(19.0 * fps) as usize {
        let t = k as f64 / fps;
        if rng.random::<f64>() < 0.05 {
            writeln!(s, "{t:.6},,{unit},0,missing: jaws out of view").unwrap();
            continue;
        }
        let truth = to_unit(opening(t));
        let v = truth + noise.sample(rng);
        sum += (v - truth).powi(2);
        n += 1;
        writeln!(s, "{t:.6},{v:.6},{unit},0.9,ok").unwrap();
    }
    std::fs::write(path, s).unwrap();
    (sum / n as f64).sqrt()
}

#[test]
fn chopstick_offset_and_rmse_are_recovered() {
    let dir = tempfile::tempdir().unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let offset = 5.432_1;
    write_encoder(&dir.path().join("encoder.csv"), offset, &mut rng);
    let truth_rmse = write_vision(
        &dir.path().join("opening.csv"),
        "deg",
        f64::to_degrees,
        0.17,
        &mut rng,
    );
    let (c, out) = run(
        &dir.path().join("encoder.csv"),
        &dir.path().join("opening.csv"),
        &EncoderMap::default(),
        &dir.path().join("cmp"),
    )
    .unwrap();
    eprintln!("{c:?} truth rmse {truth_rmse}");
    assert_eq!(c.unit, OpeningUnit::Deg);
    assert!(
        (c.offset_s - offset).abs() < 0.002,
        "offset {} vs {offset}",
        c.offset_s
    );
    assert!(
        (c.rmse - truth_rmse).abs() < 0.1 * truth_rmse,
        "rmse {} vs truth {truth_rmse}",
        c.rmse
    );
    assert!(c.bias.abs() < 0.05);
    assert!(c.n > 1900);
    assert!(out.plot.exists() && out.aligned.exists());
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&out.json).unwrap()).unwrap();
    assert_eq!(json["unit"], "deg");
    // The dominant cycle of 0.3·sin(2.1 t) is ≈ 3 s.
    assert!(
        (c.cycle_s - std::f64::consts::TAU / 2.1).abs() < 0.3,
        "{}",
        c.cycle_s
    );
}

#[test]
fn parallel_jaw_pixels_are_mapped_and_compared() {
    let dir = tempfile::tempdir().unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(10);
    let offset = -1.234_5;
    write_encoder(&dir.path().join("encoder.csv"), offset, &mut rng);
    let truth_rmse = write_vision(
        &dir.path().join("opening.csv"),
        "px",
        |a| 40.0 + 250.0 * a,
        1.9,
        &mut rng,
    );
    let (c, _) = run(
        &dir.path().join("encoder.csv"),
        &dir.path().join("opening.csv"),
        &EncoderMap::default(),
        &dir.path().join("cmp"),
    )
    .unwrap();
    assert_eq!(c.unit, OpeningUnit::Px);
    assert!((c.offset_s - offset).abs() < 0.002, "{}", c.offset_s);
    assert!(
        (c.rmse - truth_rmse).abs() < 0.1 * truth_rmse,
        "{c:?} {truth_rmse}"
    );
    assert!((c.gain - 250.0).abs() < 2.0, "{}", c.gain);
}

#[test]
fn bad_inputs_name_the_file_line_and_field() {
    let dir = tempfile::tempdir().unwrap();
    let enc = dir.path().join("encoder.csv");
    std::fs::write(&enc, "t,raw,angle_rad\n0.0,1,0.1\n0.01,x,0.2\n").unwrap();
    let vis = dir.path().join("opening.csv");
    std::fs::write(&vis, "t,opening,unit,confidence,status\n").unwrap();
    let err = run(&enc, &vis, &EncoderMap::default(), dir.path())
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("encoder.csv") && err.contains("line 3") && err.contains("raw"),
        "{err}"
    );
    std::fs::write(&enc, "t,raw,angle_rad\n1.0,1,0.1\n0.5,2,0.2\n").unwrap();
    let err = run(&enc, &vis, &EncoderMap::default(), dir.path())
        .unwrap_err()
        .to_string();
    assert!(err.contains("does not increase"), "{err}");
}
