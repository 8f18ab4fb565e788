//! Wall time of a full `kiwi-calib certify` run on simulated captures, and the firmware-change
//! case end to end: the unit certified from a second capture session (`--previous` must report
//! no change) and after a firmware change that scales its focal lengths by 0.4 % (`--previous`
//! must flag exactly the intrinsics). Target: < 5 min per certification on the 2-core machine.
//!
//! Sizes (environment variables): `KIWI_CERTIFY_RES` (per-lens px, default 480),
//! `KIWI_CERTIFY_VIEWS` (default 30), `KIWI_CERTIFY_CAM_IMU_S` (default 8),
//! `KIWI_CERTIFY_STATIC_H` (default 4, at 100 Hz), `KIWI_CERTIFY_RIG_S` (default 20, both modes,
//! two sessions), `KIWI_CERTIFY_FIRMWARE` (1 = also run the two extra certifications).
//! Run: `cargo bench -p kiwi-calib --bench certify`.
//!
//! After the first certification every certified value is compared with the simulator's
//! truth against the individual issues' tolerances (the intrinsics issue's 0.05 px projection
//! figure is stated for 960 px and 40 views: `KIWI_CERTIFY_RES=960 KIWI_CERTIFY_VIEWS=40`) and
//! the bench prints each value and a verdict.

#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use std::path::{Path, PathBuf};
use std::time::Instant;

use kiwi_calib::certify::policy::Policy;
use kiwi_calib::certify::{CertifyOptions, CertifyReport, certify};
use kiwi_core::artifact::UnitCalibration;
use kiwi_fixtures::captures::{UnitCaptureOptions, write_unit_captures};

#[path = "../tests/common_certify/mod.rs"]
mod common_certify;

fn env<T: std::str::FromStr>(name: &str, default: T) -> T {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

fn simulate(dir: &Path, name: &str, seed: u64, focal_change: f64) -> (PathBuf, f64) {
    let out = dir.join(name);
    let mut o = UnitCaptureOptions::new(&out, "X5-BENCH");
    o.seed = seed;
    o.unit_seed = Some(7);
    o.resolution = env("KIWI_CERTIFY_RES", 480);
    o.views = env("KIWI_CERTIFY_VIEWS", 30);
    o.cam_imu_duration_s = env("KIWI_CERTIFY_CAM_IMU_S", 8.0);
    o.static_duration_s = env("KIWI_CERTIFY_STATIC_H", 4.0) * 3600.0;
    o.static_rate_hz = Some(100.0);
    o.bench_duration_s = 0.0;
    o.rig_duration_s = env("KIWI_CERTIFY_RIG_S", 20.0);
    o.focal_change = focal_change;
    if focal_change != 0.0 {
        o.firmware = "sim-1.1".into();
    }
    let t = Instant::now();
    write_unit_captures(&o).unwrap();
    (out, t.elapsed().as_secs_f64())
}

fn run(captures: &Path, units: &Path, previous: Option<&Path>) -> (CertifyReport, f64) {
    let t = Instant::now();
    let report = certify(&CertifyOptions {
        unit_id: "X5-BENCH".into(),
        captures: captures.to_path_buf(),
        units_dir: units.to_path_buf(),
        policy: Policy::default(),
        previous: previous.map(Path::to_path_buf),
        date: None,
        progress: false,
    })
    .unwrap();
    (report, t.elapsed().as_secs_f64())
}

fn print(label: &str, r: &CertifyReport, seconds: f64) {
    println!(
        "{label}: {} in {seconds:.1} s wall ({}); steps: {}",
        if r.passed {
            "CERTIFIED"
        } else {
            "NOT CERTIFIED"
        },
        r.folder.display(),
        r.steps
            .iter()
            .map(|s| format!("{} {:.1} s", s.step, s.seconds))
            .collect::<Vec<_>>()
            .join(", ")
    );
    if !r.passed {
        println!("  failed: {:?}", r.failed_checks);
    }
    if let Some(c) = &r.comparison {
        println!(
            "  --previous: {} parameters compared, significant: {:?} (groups {:?})",
            c.parameters.len(),
            c.significant,
            c.changed_groups
        );
    }
}

fn main() {
    let tmp = tempfile::tempdir().unwrap();
    let units = tmp.path().join("units");
    println!(
        "certify benchmark on {} threads (captures: {} px, {} views/lens, {} s excitation, {} h \
         static log, {} s rig recordings)",
        rayon::current_num_threads(),
        env("KIWI_CERTIFY_RES", 480),
        env("KIWI_CERTIFY_VIEWS", 30),
        env("KIWI_CERTIFY_CAM_IMU_S", 8.0),
        env("KIWI_CERTIFY_STATIC_H", 4.0),
        env("KIWI_CERTIFY_RIG_S", 20.0)
    );
    let (cap, sim_s) = simulate(tmp.path(), "session1", 7, 0.0);
    println!("simulated the captures in {sim_s:.1} s");
    let (a, a_s) = run(&cap, &units, None);
    print("full certification", &a, a_s);
    let truth = UnitCalibration::load(&cap.join("truth/calibration.json")).unwrap();
    let cal = UnitCalibration::load(&a.folder.join("calibration.json")).unwrap();
    // The projection figure (stated for 960 px lenses, 40 views), at every size.
    let checks = common_certify::compare_with_truth(&truth, &cal, common_certify::PROJECTION_PX);
    let failed = checks.iter().filter(|c| !c.passed()).count();
    println!(
        "against the truth ({} values):\n{}",
        checks.len(),
        common_certify::describe(&checks)
    );
    println!(
        "every value inside the issues' tolerances: {}",
        if failed == 0 {
            "yes".to_string()
        } else {
            format!("NO ({failed} outside)")
        }
    );
    if env("KIWI_CERTIFY_FIRMWARE", 0) == 1 {
        let (cap2, _) = simulate(tmp.path(), "session2", 8, 0.0);
        let (b, b_s) = run(&cap2, &units, Some(&a.folder));
        print("second capture session, --previous", &b, b_s);
        let (cap3, _) = simulate(tmp.path(), "firmware", 8, 0.004);
        let (c, c_s) = run(&cap3, &units, Some(&b.folder));
        print(
            "after a firmware change (+0.4 % focal), --previous",
            &c,
            c_s,
        );
    }
}
