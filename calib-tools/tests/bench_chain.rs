#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]
//! The whole simulated servo bench, at reduced cost (320 px, 4 s at 119.88 fps): `kiwi-sim
//! unit` renders the front lens filming the chopstick and writes the encoder log on the host
//! clock → `kiwi gripper` measures every frame → `bench compare` with the tool's encoder map
//! (from the `tool.json` beside `opening.csv`). Issue acceptance: the clock offset within 2 ms
//! of the truth (host offset + lens time shift) and the RMSE within 10 % of the RMSE computed
//! against the simulator's true opening.

use std::path::Path;

use kiwi_calib::bench::compare::{self, EncoderMap, OpeningUnit};
use kiwi_core::artifact::UnitCalibration;
use kiwi_core::tool::ToolDefinition;
use kiwi_fixtures::captures::{UnitCaptureOptions, write_unit_captures};

/// Truth opening (rad) per camera frame time, from `truth/servo_bench/opening.csv`.
fn truth_openings(path: &Path) -> Vec<(f64, f64)> {
    std::fs::read_to_string(path)
        .unwrap()
        .lines()
        .skip(1)
        .map(|l| {
            let mut f = l.split(',');
            (
                f.next().unwrap().parse().unwrap(),
                f.next().unwrap().parse().unwrap(),
            )
        })
        .collect()
}

#[test]
fn simulated_bench_recovers_offset_and_rmse() {
    let dir = tempfile::tempdir().unwrap();
    let sim = dir.path().join("unit");
    let mut o = UnitCaptureOptions::new(&sim, "X5-CHAIN");
    o.seed = 11;
    o.resolution = 320;
    o.views = 0;
    o.cam_imu_duration_s = 0.0;
    o.static_duration_s = 0.0;
    o.rig_duration_s = 0.0;
    o.bench_duration_s = 4.0;
    let summary = write_unit_captures(&o).unwrap();
    assert!(summary.bench_frames > 400, "{summary:?}");

    // kiwi gripper on the front lens, with the unit's calibration.
    let cal = UnitCalibration::load(&summary.truth_calibration).unwrap();
    let lens = cal.lens("front").unwrap();
    let camera = lens.camera().unwrap();
    let def = ToolDefinition::builtin(kiwi_core::layout::ToolKind::Chopstick).unwrap();
    let out = dir.path().join("gripper");
    let (opening, files) = kiwi_backend::gripper::run(
        &camera,
        &def,
        &sim.join("servo_bench").join("front"),
        &out,
        &|| {},
    )
    .unwrap();
    eprintln!(
        "gripper: {} of {} frames measured, {:.0} frames/s",
        opening.measured, opening.frames, opening.frames_per_s
    );
    assert!(opening.measured * 10 >= opening.frames * 9, "{opening:?}");

    // RMSE of vision against the simulator's true opening at the same frames.
    let truth = truth_openings(&sim.join("truth/servo_bench/opening.csv"));
    let (vision, unit, _) = compare::read_vision(&files.csv).unwrap();
    assert_eq!(unit, OpeningUnit::Deg);
    let (mut sum, mut n) = (0.0, 0);
    for v in &vision {
        // The nearest truth row (opening.csv rounds times to 1 µs).
        let i = truth.partition_point(|(t, _)| *t < v.t);
        let k = [i.saturating_sub(1), i.min(truth.len() - 1)]
            .into_iter()
            .min_by(|a, b| {
                (truth[*a].0 - v.t)
                    .abs()
                    .total_cmp(&(truth[*b].0 - v.t).abs())
            })
            .unwrap();
        assert!((truth[k].0 - v.t).abs() < 1e-5, "frame time {}", v.t);
        sum += (v.opening - truth[k].1.to_degrees()).powi(2);
        n += 1;
    }
    let truth_rmse = (sum / f64::from(n)).sqrt();

    // bench compare, the encoder map read from the tool.json beside opening.csv.
    let (tool, px_per_m) = compare::load_tool(files.tool.to_str().unwrap()).unwrap();
    let map = EncoderMap::from_tool(&tool, px_per_m, "tool.json");
    assert_eq!(map.zero_count, Some(1024.0), "{map:?}");
    let encoder = sim.join("servo_bench").join("encoder.csv");
    let (cmp, _) = compare::run(&encoder, &files.csv, &map, &dir.path().join("cmp")).unwrap();
    let meta: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(sim.join("truth/servo_bench/encoder.json")).unwrap(),
    )
    .unwrap();
    let true_offset = meta["host_offset_s"].as_f64().unwrap() + lens.time_shift_s.unwrap_or(0.0);
    let offset_err = cmp.offset_s - true_offset;
    let rmse_rel = cmp.rmse / truth_rmse - 1.0;
    eprintln!(
        "compare: offset {:.5} s vs {true_offset:.5} s true ({:+.2} ms); RMSE {:.4} deg vs \
         {truth_rmse:.4} deg truth-computed ({:+.1} %) over {} samples",
        cmp.offset_s,
        offset_err * 1e3,
        cmp.rmse,
        100.0 * rmse_rel,
        cmp.n
    );
    assert!(offset_err.abs() < 0.002, "offset off by {offset_err} s");
    assert!(rmse_rel.abs() < 0.10, "RMSE {} vs {truth_rmse}", cmp.rmse);
}
