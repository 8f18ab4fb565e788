#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]
//! Acceptance of `kiwi-calib certify` on simulated units.
//!
//! One simulated X5 unit (480 px lenses, 24 aprilgrid views per lens of the recommended capture
//! design — a 10 × 10 × 55 mm board at 0.2–0.4 m —, a 4 s camera–IMU excitation, a 4-h static
//! IMU log at 20 Hz, two 20 s QR-clock rig sessions in the 30 fps mode) certifies end to end
//! with every value inside the individual issues' tolerances (`common_certify`; the
//! intrinsics issue's 0.05 px projection figure is held even at this reduced size);
//! the same unit captured again (fresh noise and board poses) certifies into a second folder and
//! `--previous` reports no significant change; after a simulated firmware change (focal lengths
//! +0.4 %) `--previous` flags exactly its intrinsics. Three reduced captures fail with the named
//! check: too few views, a moving "static" IMU log, a rig recording without chirps.

use std::path::{Path, PathBuf};

use kiwi_calib::certify::policy::Policy;
use kiwi_calib::certify::{CertifyOptions, CertifyReport, certify, report};
use kiwi_core::artifact::UnitCalibration;
use kiwi_fixtures::captures::{UnitCaptureOptions, write_unit_captures};

mod common_certify;

const DATE: &str = "2026-11-22";
/// Projection error limit: the intrinsics issue's figure (stated for 960 px, 40 views), met by
/// the recommended design at 480 px and 24 views too (measured 0.008 / 0.010 px).
const PROJECTION_LIMIT_PX: f64 = common_certify::PROJECTION_PX;

fn sim(dir: &Path, name: &str, edit: impl FnOnce(&mut UnitCaptureOptions)) -> PathBuf {
    let out = dir.join(name);
    let mut o = UnitCaptureOptions::new(&out, "X5-CERT");
    o.seed = 7;
    o.resolution = 480;
    o.views = 24;
    o.cam_imu_duration_s = 4.0;
    o.static_duration_s = 4.0 * 3600.0;
    // 20 Hz keeps the 4-h log at 40 MB; the white-noise and random-walk regions are unchanged.
    o.static_rate_hz = Some(20.0);
    o.bench_duration_s = 0.0;
    o.rig_duration_s = 20.0;
    o.rig_repeats = 2;
    o.rig_modes = vec!["30fps".into()];
    // Half the default sensor noise: smaller PNGs on disk, same code paths.
    o.noise_sigma = 1.0;
    edit(&mut o);
    let started = std::time::Instant::now();
    write_unit_captures(&o).unwrap();
    println!(
        "{name}: simulated in {:.1} s",
        started.elapsed().as_secs_f64()
    );
    out
}

fn options(captures: &Path, units: &Path, previous: Option<&Path>) -> CertifyOptions {
    CertifyOptions {
        unit_id: "X5-CERT".into(),
        captures: captures.to_path_buf(),
        units_dir: units.to_path_buf(),
        policy: Policy::default(),
        previous: previous.map(Path::to_path_buf),
        date: Some(DATE.into()),
        progress: false,
    }
}

fn describe(r: &CertifyReport) -> String {
    let steps = r
        .steps
        .iter()
        .map(|s| format!("{} {} {:.1} s", s.step, s.status, s.seconds))
        .collect::<Vec<_>>()
        .join(", ");
    let checks = r
        .checks
        .iter()
        .map(|c| {
            format!(
                "{} {} ({} {}) {}{}",
                c.check.name,
                c.check.value,
                c.check.comparison,
                c.check.threshold,
                if c.check.passed { "ok" } else { "FAIL" },
                c.note
                    .as_ref()
                    .map_or_else(String::new, |n| format!(": {n}"))
            )
        })
        .collect::<Vec<_>>()
        .join("\n");
    format!("{checks}\nsteps: {steps} (total {:.1} s)", r.seconds)
}

/// Failed checks other than those naming missing captures or skipped dependants.
fn own_failures(r: &CertifyReport) -> Vec<String> {
    r.failed_checks
        .iter()
        .filter(|c| !c.ends_with(".captures") && *c != "cam_imu.intrinsics")
        .cloned()
        .collect()
}

#[test]
fn simulated_unit_certifies_recertifies_and_flags_a_firmware_change() {
    let tmp = tempfile::tempdir().unwrap();
    let cap = sim(tmp.path(), "captures", |_| {});
    let units = tmp.path().join("units");
    let a = certify(&options(&cap, &units, None)).unwrap();
    println!("{}", describe(&a));
    assert!(a.passed, "failed: {:?}\n{}", a.failed_checks, describe(&a));
    assert_eq!(a.folder, units.join("X5-CERT").join(DATE));

    // Every value inside the individual issues' tolerances.
    let truth = UnitCalibration::load(&cap.join("truth/calibration.json")).unwrap();
    let cal = UnitCalibration::load(&a.folder.join("calibration.json")).unwrap();
    assert!(cal.certification.as_ref().unwrap().passed);
    assert_eq!(cal.av_delays.len(), 1);
    assert!(cal.av_delays.iter().all(|d| d.repeats == 2));
    let checks = common_certify::compare_with_truth(&truth, &cal, PROJECTION_LIMIT_PX);
    println!("against the truth:\n{}", common_certify::describe(&checks));
    assert_eq!(checks.len(), 2 * 8 + 4 + 1);
    let failed: Vec<_> = checks.iter().filter(|c| !c.passed()).collect();
    assert!(
        failed.is_empty(),
        "outside the issues' tolerances: {failed:?}"
    );
    for f in [
        "calibration.json",
        "certification.json",
        "camchain-imucam.yaml",
        "imu.yaml",
        "basalt_calibration.json",
        "report/index.md",
        "report/policy.toml",
    ] {
        assert!(a.folder.join(f).is_file(), "{f} missing");
    }
    let page = std::fs::read_to_string(a.folder.join("report/index.md")).unwrap();
    assert!(page.starts_with("# Certification of unit X5-CERT"));
    assert!(page.lines().nth(2).unwrap().contains("CERTIFIED"));
    let images: Vec<&str> = page
        .lines()
        .filter_map(|l| l.strip_prefix("![").and_then(|r| r.split("](").nth(1)))
        .map(|r| r.trim_end_matches(')'))
        .collect();
    for step in [
        "intrinsics-front/",
        "intrinsics-rear/",
        "imu_noise/",
        "cam_imu/",
        "av_delay/",
    ] {
        assert!(
            images.iter().any(|i| i.starts_with(step)),
            "no {step} plot in the page"
        );
    }
    for i in &images {
        assert!(a.folder.join("report").join(i).is_file(), "{i} missing");
    }
    // The camera–IMU report names where its noise came from by a file the set keeps.
    let cam_imu_page = std::fs::read_to_string(a.folder.join("report/cam_imu/report.md")).unwrap();
    assert!(
        cam_imu_page.contains("imu block of this set's calibration.json"),
        "{cam_imu_page}"
    );
    let first_calibration = std::fs::read(a.folder.join("calibration.json")).unwrap();
    // The captures are no longer needed: free the disk before the next session.
    std::fs::remove_dir_all(&cap).unwrap();

    // The same unit (same lenses, IMU and delays) captured again with fresh noise and fresh
    // board poses: it certifies, gets a second folder, and `--previous` finds no parameter that
    // moved beyond its uncertainty.
    let again = sim(tmp.path(), "again", |o| {
        o.unit_seed = Some(7);
        o.seed = 8;
    });
    let b = certify(&options(&again, &units, Some(&a.folder))).unwrap();
    println!("{}", describe(&b));
    assert!(b.passed, "failed: {:?}\n{}", b.failed_checks, describe(&b));
    assert_eq!(b.folder, units.join("X5-CERT").join(format!("{DATE}-2")));
    let c = b.comparison.as_ref().unwrap();
    println!(
        "same unit again: {} parameters compared, significant {:?}",
        c.parameters.len(),
        c.significant
    );
    for group in [
        "intrinsics",
        "extrinsics",
        "time_shift",
        "imu_noise",
        "av_delay",
    ] {
        assert!(
            c.parameters.iter().any(|p| p.group == group),
            "{group} not compared"
        );
    }
    assert!(c.significant.is_empty(), "flagged {:?}", c.significant);
    assert!(c.changed_groups.is_empty());
    std::fs::remove_dir_all(&again).unwrap();

    // The same unit after a firmware change that scales its lens images by 0.4 %: its lenses
    // and static log (re-rendered; the excitation and rig are left out to keep the test short,
    // the benchmark certifies them too) are compared with the first set.
    let changed = sim(tmp.path(), "changed", |o| {
        o.focal_change = 0.004;
        o.firmware = "sim-1.1".into();
        o.cam_imu_duration_s = 0.0;
        o.rig_duration_s = 0.0;
    });
    let d = certify(&options(&changed, &units, Some(&a.folder))).unwrap();
    assert!(!d.passed);
    // Certifying the unit again writes a second folder and never touches the first.
    assert_eq!(d.folder, units.join("X5-CERT").join(format!("{DATE}-3")));
    assert_eq!(
        std::fs::read(a.folder.join("calibration.json")).unwrap(),
        first_calibration
    );
    let c = d.comparison.as_ref().unwrap();
    println!("firmware change flags {:?}", c.significant);
    assert_eq!(c.changed_groups, vec!["intrinsics".to_string()]);
    for lens in ["front", "rear"] {
        for p in ["fx", "fy"] {
            let name = format!("{lens}.intrinsics.{p}");
            assert!(c.significant.contains(&name), "{name} not flagged");
        }
    }
    assert!(
        c.parameters
            .iter()
            .any(|p| p.group == "imu_noise" && !p.significant)
    );
    let listed = report::list_text(&report::list_units(&units).unwrap());
    assert!(
        listed.contains(&format!("{DATE}-3")) && listed.contains("FAILED"),
        "{listed}"
    );
}

#[test]
fn too_few_views_fail_the_views_check() {
    let tmp = tempfile::tempdir().unwrap();
    let cap = sim(tmp.path(), "few", |o| {
        o.views = 5;
        o.resolution = 320;
        o.cam_imu_duration_s = 0.0;
        o.static_duration_s = 0.0;
        o.rig_duration_s = 0.0;
    });
    let r = certify(&options(&cap, &tmp.path().join("units"), None)).unwrap();
    assert!(!r.passed);
    assert_eq!(
        own_failures(&r),
        vec!["front.views", "rear.views"],
        "{}",
        describe(&r)
    );
    // Written all the same, marked failed.
    let record = std::fs::read_to_string(r.folder.join("certification.json")).unwrap();
    assert!(record.contains("\"passed\": false") && record.contains("front.views"));
    let page = std::fs::read_to_string(r.folder.join("report/index.md")).unwrap();
    assert!(page.contains("NOT CERTIFIED") && page.contains("`front.views`"));
}

#[test]
fn a_moving_static_log_fails_the_motion_check() {
    let tmp = tempfile::tempdir().unwrap();
    let cap = sim(tmp.path(), "moving", |o| {
        o.views = 0;
        o.cam_imu_duration_s = 0.0;
        o.static_duration_s = 3600.0;
        o.rig_duration_s = 0.0;
    });
    // Someone turns the unit at 0.2 rad/s for 3 s in the middle of the "static" log.
    let path = cap.join("imu_static/imu.csv");
    let text = std::fs::read_to_string(&path).unwrap();
    let mut out = String::with_capacity(text.len());
    for (i, line) in text.lines().enumerate() {
        let mut f: Vec<String> = line.split(',').map(str::to_string).collect();
        if i > 0 {
            let t: f64 = f[0].parse().unwrap();
            if (1800.0..1803.0).contains(&t) {
                f[3] = (f[3].parse::<f64>().unwrap() + 0.2).to_string();
            }
        }
        out.push_str(&f.join(","));
        out.push('\n');
    }
    std::fs::write(&path, out).unwrap();
    let r = certify(&options(&cap, &tmp.path().join("units"), None)).unwrap();
    assert!(!r.passed);
    assert_eq!(
        own_failures(&r),
        vec!["imu.static_gyro_motion_rad_s"],
        "{}",
        describe(&r)
    );
    let check = r
        .checks
        .iter()
        .find(|c| c.check.name == "imu.static_gyro_motion_rad_s")
        .unwrap();
    assert!(
        check.note.as_ref().unwrap().contains("t = 18"),
        "{:?}",
        check.note
    );
}

#[test]
fn a_rig_recording_without_chirps_fails_the_chirp_check() {
    let tmp = tempfile::tempdir().unwrap();
    let cap = sim(tmp.path(), "silent", |o| {
        o.views = 0;
        o.resolution = 320;
        o.cam_imu_duration_s = 0.0;
        o.static_duration_s = 0.0;
        o.rig_duration_s = 3.0;
        o.rig_repeats = 1;
        o.rig_chirps = false;
    });
    let r = certify(&options(&cap, &tmp.path().join("units"), None)).unwrap();
    assert!(!r.passed);
    assert_eq!(
        own_failures(&r),
        vec![
            "av_delay.x5-30fps.r1-30fps-cam0.chirps",
            "av_delay.x5-30fps.repeats"
        ],
        "{}",
        describe(&r)
    );
}
