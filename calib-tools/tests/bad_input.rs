#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]
//! `kiwi-calib` on bad input: every case fails (non-zero exit), its message names the file or
//! field and the fix, and no file is written or changed (every watched folder hashed before and
//! after). Plus the real-world files it must accept (Kalibr camchain variants).

use std::path::{Path, PathBuf};

use kiwi_core::geometry::Pose;
use kiwi_core::imu::{ImuSample, write_imu_csv};
use kiwi_core::layout::{CameraMeta, EpisodeLayout};
use kiwi_fixtures::check::{Case, run_all};
use kiwi_fixtures::imu::ImuSimulator;
use kiwi_fixtures::motion::Trajectory;
use kiwi_fixtures::scenario::{Scenario, episode_motion};
use kiwi_fixtures::unit::{LensModel, SimUnit};
use nalgebra::{Translation3, UnitQuaternion};

const CALIB: &str = env!("CARGO_BIN_EXE_kiwi-calib");
const UNIT: &str = "X5-BAD";
const DATE: &str = "2026-01-02";

fn unit() -> SimUnit {
    SimUnit::x5(UNIT, 3, 64, LensModel::Kb4).unwrap()
}

fn static_log(rate_hz: f64, seconds: f64) -> Vec<ImuSample> {
    let u = unit();
    let pose = Pose::from_parts(
        Translation3::new(0.0, 0.0, 0.8),
        UnitQuaternion::from_euler_angles(0.2, -0.1, 0.7),
    );
    let noise = kiwi_fixtures::unit::SimImuNoise { rate_hz, ..u.imu };
    ImuSimulator::new(
        &Trajectory::fixed(&pose),
        noise,
        0.0,
        seconds,
        true,
        5,
        "static",
    )
    .collect()
}

fn moving_log(seconds: f64) -> Vec<ImuSample> {
    let u = unit();
    let motion = episode_motion(Scenario::Tabletop, 4, 0, seconds);
    ImuSimulator::new(&motion.left, u.imu, 0.0, seconds, true, 5, "moving").collect()
}

fn map(samples: &[ImuSample], f: impl Fn(&mut ImuSample)) -> Vec<ImuSample> {
    samples
        .iter()
        .map(|s| {
            let mut s = *s;
            f(&mut s);
            s
        })
        .collect()
}

/// A camera–IMU capture folder `<root>/<name>/cam` with this IMU log (no frames are needed:
/// the log is checked first).
fn capture(root: &Path, name: &str, samples: &[ImuSample]) -> PathBuf {
    let layout = EpisodeLayout::new(root.join(name));
    layout
        .write_meta(&CameraMeta {
            camera: "cam".into(),
            unit_id: UNIT.into(),
            camera_model: "Insta360 X5".into(),
            mode: "119.88fps".into(),
            fps: 119.88,
            lenses: vec!["front".into(), "rear".into()],
            audio_rate_hz: 48_000,
            source: "bad-input test".into(),
            recording: None,
        })
        .unwrap();
    write_imu_csv(&layout.imu_csv("cam"), samples).unwrap();
    layout.camera_dir("cam")
}

fn s(p: &Path) -> String {
    p.display().to_string()
}

/// The calibration as JSON, changed by `edit`, written to `<root>/bad/<name>.json`.
fn edited(root: &Path, name: &str, edit: impl Fn(&mut serde_json::Value)) -> String {
    let cal = unit().true_calibration(DATE);
    let mut v: serde_json::Value = serde_json::from_str(&cal.to_json().unwrap()).unwrap();
    edit(&mut v);
    let path = root.join("bad").join(format!("{name}.json"));
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    std::fs::write(&path, serde_json::to_string_pretty(&v).unwrap()).unwrap();
    s(&path)
}

#[test]
fn kiwi_calib_refuses_bad_input_and_writes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    let calib = Path::new(CALIB);

    // A dated set, as certify leaves it.
    let units = root.join("units");
    let set = units.join(UNIT).join(DATE);
    std::fs::create_dir_all(&set).unwrap();
    let cal = unit().true_calibration(DATE);
    cal.save(&set.join("calibration.json")).unwrap();
    kiwi_calib::export::export_all(&cal, &set).unwrap();
    let cal_json = s(&set.join("calibration.json"));

    // An empty set folder left by a killed certification.
    let killed = units.join(UNIT).join("2026-01-03");
    std::fs::create_dir_all(&killed).unwrap();

    // IMU logs: static (imu-noise) and moving (cam-imu), each with a unit mistake.
    let logs = root.join("logs");
    std::fs::create_dir_all(&logs).unwrap();
    let still = static_log(100.0, 70.0);
    let write = |name: &str, samples: &[ImuSample]| {
        let p = logs.join(name);
        write_imu_csv(&p, samples).unwrap();
        s(&p)
    };
    let imu_g = write("g.csv", &map(&still, |x| x.accel /= 9.80665));
    let imu_ms = write("ms.csv", &map(&still, |x| x.t *= 1000.0));
    let imu_deg = write(
        "deg.csv",
        &map(&still, |x| x.gyro *= 180.0 / std::f64::consts::PI),
    );
    let good = write("good.csv", &still);
    let text = std::fs::read_to_string(&good).unwrap();
    let nan = logs.join("nan.csv");
    let mut lines: Vec<&str> = text.lines().collect();
    lines[500] = "4.99,0,0,NaN,0,0,9.81";
    std::fs::write(&nan, lines.join("\n")).unwrap();
    let backwards = logs.join("backwards.csv");
    let mut lines: Vec<String> = std::fs::read_to_string(&good)
        .unwrap()
        .lines()
        .map(str::to_string)
        .collect();
    lines.swap(300, 301);
    std::fs::write(&backwards, lines.join("\n")).unwrap();
    let header = logs.join("header.csv");
    std::fs::write(&header, "time,wx,wy,wz\n0,0,0,0\n").unwrap();
    let binary = logs.join("random.csv");
    std::fs::write(
        &binary,
        (0..4096u32)
            .map(|i| (i * 7919 % 128) as u8 + 128)
            .collect::<Vec<u8>>(),
    )
    .unwrap();

    let moving = moving_log(6.0);
    let cap_g = capture(root, "cap_g", &map(&moving, |x| x.accel /= 9.80665));
    let cap_deg = capture(
        root,
        "cap_deg",
        &map(&moving, |x| x.gyro *= 180.0 / std::f64::consts::PI),
    );
    let cap_ms = capture(root, "cap_ms", &map(&moving, |x| x.t *= 1000.0));
    let target = root.join("target.yaml");
    std::fs::write(
        &target,
        "target_type: 'aprilgrid'\ntagCols: 6\ntagRows: 6\ntagSize: 0.088\ntagSpacing: 0.3\n",
    )
    .unwrap();

    // Calibrations with one field wrong.
    let bad_lens = edited(root, "lens", |v| v["lenses"][0]["name"] = "left".into());
    let bad_cx = edited(root, "cx", |v| {
        v["lenses"][1]["intrinsics"]["cx"] = 900.0.into();
    });
    let bad_t = edited(root, "t", |v| {
        v["lenses"][0]["cam_from_imu"]["translation_m"] = serde_json::json!([1200.0, 0.0, 0.0]);
    });
    let no_imu = edited(root, "noimu", |v| {
        v.as_object_mut().unwrap().remove("imu");
    });
    let bad_date = edited(root, "date", |v| v["date"] = "2026-02-30".into());
    let bad_month = edited(root, "month", |v| v["date"] = "2026-13-01".into());
    let bad_fx = edited(root, "fx", |v| {
        v["lenses"][0]["intrinsics"]["fx"] = (-5.0).into();
    });
    let random_json = root.join("bad").join("random.json");
    std::fs::write(&random_json, [0xffu8, 0xfe, 0x00, 0x12, 0x80]).unwrap();
    let empty_json = root.join("bad").join("empty.json");
    std::fs::write(&empty_json, "").unwrap();

    // Kalibr files that cannot be imported.
    let kalibr = root.join("kalibr");
    std::fs::create_dir_all(&kalibr).unwrap();
    let cam = "  camera_model: pinhole\n  intrinsics: [30, 30, 31.5, 31.5]\n  distortion_model: equidistant\n  distortion_coeffs: [0.01, 0, 0, 0]\n  resolution: [64, 64]\n";
    let kfile = |name: &str, text: &str| {
        let p = kalibr.join(name);
        std::fs::write(&p, text).unwrap();
        s(&p)
    };
    let k_omni = kfile(
        "omni.yaml",
        "cam0:\n  camera_model: omni\n  intrinsics: [1, 2, 3, 4, 5]\n  distortion_model: radtan\n  distortion_coeffs: [0, 0, 0, 0]\n  resolution: [640, 480]\n",
    );
    let k_15 = kfile(
        "fifteen.yaml",
        &format!("cam0:\n{cam}  T_cam_imu: [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0]\n"),
    );
    let k_three = kfile(
        "three.yaml",
        &format!("cam0:\n{cam}cam1:\n{cam}cam2:\n{cam}"),
    );
    let k_garbage = kfile("garbage.yaml", "cam0: [unclosed\n  - :\n");
    let k_cx = kfile(
        "cx.yaml",
        "cam0:\n  camera_model: pinhole\n  intrinsics: [30, 30, 500, 31.5]\n  distortion_model: equidistant\n  distortion_coeffs: [0.01, 0, 0, 0]\n  resolution: [64, 64]\n",
    );

    let regular_file = root.join("not-a-port");
    std::fs::write(&regular_file, "x").unwrap();
    let out = |name: &str| s(&root.join("out").join(name));
    let bench = |name: &str| s(&root.join("bench").join(name));
    let set_s = s(&set);

    let mut cases = vec![
        // Item 3: dated sets are never written after they are created.
        Case::new(
            "export into a dated set",
            calib,
            &["export", "--calibration", &cal_json, "--out", &set_s],
        )
        .says(&["dated calibration set", "never changed"]),
        Case::new(
            "export into a folder inside a dated set",
            calib,
            &[
                "export",
                "--calibration",
                &cal_json,
                "--out",
                &s(&set.join("exports")),
            ],
        )
        .says(&["dated calibration set"]),
        Case::new(
            "export into a dated set through ..",
            calib,
            &[
                "export",
                "--calibration",
                &cal_json,
                "--out",
                &s(&set.join("report/../.")),
            ],
        )
        .says(&["dated calibration set"]),
        Case::new(
            "imu-noise into a dated set",
            calib,
            &["imu-noise", "--imu", &good, "--out", &set_s],
        )
        .says(&["dated calibration set"]),
        Case::new(
            "import-kalibr into a dated set",
            calib,
            &[
                "import-kalibr",
                "--camchain",
                &s(&set.join("camchain-imucam.yaml")),
                "--unit-id",
                UNIT,
                "--out",
                &s(&set.join("other.json")),
            ],
        )
        .says(&["dated calibration set"]),
        Case::new(
            "cam-imu into a dated set",
            calib,
            &[
                "cam-imu",
                "--capture",
                &s(&cap_g),
                "--intrinsics",
                &cal_json,
                "--target",
                &s(&target),
                "--out",
                &set_s,
            ],
        )
        .says(&["dated calibration set"]),
        Case::new(
            "intrinsics into a dated set",
            calib,
            &[
                "intrinsics",
                "--corners",
                &good,
                "--out",
                &s(&set.join("front")),
            ],
        )
        .says(&["dated calibration set"]),
        Case::new(
            "certify into a dated set",
            calib,
            &[
                "certify",
                "--unit",
                UNIT,
                "--captures",
                &s(root),
                "--out",
                &set_s,
            ],
        )
        .says(&["dated calibration set"]),
        // Item 2: unit mistakes in IMU logs.
        Case::new(
            "imu-noise, accelerometer in g",
            calib,
            &["imu-noise", "--imu", &imu_g, "--out", &out("n1")],
        )
        .says(&["g.csv", "ax, ay, az", "in g", "9.80665"]),
        Case::new(
            "imu-noise, timestamps in ms",
            calib,
            &["imu-noise", "--imu", &imu_ms, "--out", &out("n2")],
        )
        .says(&["ms.csv", "column t", "milliseconds", "divide t by"]),
        Case::new(
            "imu-noise, gyro in deg/s",
            calib,
            &["imu-noise", "--imu", &imu_deg, "--out", &out("n3")],
        )
        .says(&["deg.csv", "gx, gy, gz", "deg/s", "π/180"]),
        Case::new(
            "imu-noise, NaN",
            calib,
            &["imu-noise", "--imu", &s(&nan), "--out", &out("n4")],
        )
        .says(&["nan.csv", "line 501"]),
        Case::new(
            "imu-noise, times go backwards",
            calib,
            &["imu-noise", "--imu", &s(&backwards), "--out", &out("n5")],
        )
        .says(&["backwards.csv", "line 302"]),
        Case::new(
            "imu-noise, wrong header",
            calib,
            &["imu-noise", "--imu", &s(&header), "--out", &out("n6")],
        )
        .says(&["header.csv", "t,gx,gy,gz,ax,ay,az"]),
        Case::new(
            "imu-noise, binary file",
            calib,
            &["imu-noise", "--imu", &s(&binary), "--out", &out("n7")],
        )
        .says(&["random.csv", "UTF-8"]),
        Case::new(
            "imu-noise, a folder",
            calib,
            &["imu-noise", "--imu", &s(&logs), "--out", &out("n8")],
        )
        .says(&["logs", "folder"]),
        Case::new(
            "imu-noise, missing file",
            calib,
            &[
                "imu-noise",
                "--imu",
                &s(&logs.join("none.csv")),
                "--out",
                &out("n9"),
            ],
        )
        .says(&["none.csv", "no such file"]),
        Case::new(
            "cam-imu, accelerometer in g",
            calib,
            &[
                "cam-imu",
                "--capture",
                &s(&cap_g),
                "--intrinsics",
                &cal_json,
                "--target",
                &s(&target),
                "--out",
                &out("c1"),
            ],
        )
        .says(&["imu.csv", "in g", "9.80665"]),
        Case::new(
            "cam-imu, gyro in deg/s",
            calib,
            &[
                "cam-imu",
                "--capture",
                &s(&cap_deg),
                "--intrinsics",
                &cal_json,
                "--target",
                &s(&target),
                "--out",
                &out("c2"),
            ],
        )
        .says(&["imu.csv", "deg/s"]),
        Case::new(
            "cam-imu, timestamps in ms",
            calib,
            &[
                "cam-imu",
                "--capture",
                &s(&cap_ms),
                "--intrinsics",
                &cal_json,
                "--target",
                &s(&target),
                "--out",
                &out("c3"),
            ],
        )
        .says(&["imu.csv", "milliseconds"]),
        Case::new(
            "cam-imu, --gravity in g",
            calib,
            &[
                "cam-imu",
                "--capture",
                &s(&cap_g),
                "--intrinsics",
                &cal_json,
                "--target",
                &s(&target),
                "--out",
                &out("c4"),
                "--gravity",
                "1",
            ],
        )
        .says(&["--gravity", "m/s²"]),
        // Item 5: validate says no to bad calibrations.
        Case::new("validate, lens name", calib, &["validate", &bad_lens]).says(&[
            "lens.json",
            "lenses[0].name",
            "`left`",
        ]),
        Case::new("validate, principal point", calib, &["validate", &bad_cx]).says(&[
            "cx.json",
            "lenses[1].intrinsics.cx",
            "900",
        ]),
        Case::new("validate, 1.2 km camera-IMU", calib, &["validate", &bad_t]).says(&[
            "t.json",
            "lenses[0].cam_from_imu.translation_m",
            "metres",
        ]),
        Case::new("validate, no IMU block", calib, &["validate", &no_imu])
            .says(&["noimu.json", "incomplete", "imu"])
            .exit_codes(&[3]),
        Case::new("validate, 30 February", calib, &["validate", &bad_date]).says(&[
            "date.json",
            "date",
            "2026-02-30",
            "28 days",
        ]),
        Case::new("validate, month 13", calib, &["validate", &bad_month]).says(&[
            "month.json",
            "date",
            "no month 13",
        ]),
        Case::new(
            "validate, negative focal length",
            calib,
            &["validate", &bad_fx],
        )
        .says(&["fx.json", "intrinsics.fx"]),
        Case::new(
            "validate, binary file",
            calib,
            &["validate", &s(&random_json)],
        )
        .says(&["random.json"]),
        Case::new(
            "validate, empty file",
            calib,
            &["validate", &s(&empty_json)],
        )
        .says(&["empty.json"]),
        Case::new(
            "validate, folder without calibration.json",
            calib,
            &["validate", &s(&root.join("bad"))],
        )
        .says(&["calibration.json", "no such file"]),
        Case::new(
            "certify dated 30 February",
            calib,
            &[
                "certify",
                "--unit",
                UNIT,
                "--captures",
                &s(&root.join("captures")),
                "--out",
                &out("units"),
                "--date",
                "2026-02-30",
            ],
        )
        .says(&["2026-02-30"]),
        // Bench: a wrong port is an error, not an empty recording.
        Case::new(
            "bench servo, missing port",
            calib,
            &[
                "bench",
                "servo",
                "--port",
                "/dev/kiwi-nonexistent",
                "--duration",
                "20",
                "--out",
                &bench("b1"),
            ],
        )
        .says(&["/dev/kiwi-nonexistent", "does not exist"]),
        Case::new(
            "bench servo, a regular file",
            calib,
            &[
                "bench",
                "servo",
                "--port",
                &s(&regular_file),
                "--duration",
                "2",
                "--out",
                &bench("b2"),
            ],
        )
        .says(&["not-a-port", "regular file"]),
        Case::new(
            "bench servo, --duration 0",
            calib,
            &[
                "bench",
                "servo",
                "--port",
                "/dev/kiwi-nonexistent",
                "--duration",
                "0",
                "--out",
                &bench("b3"),
            ],
        )
        .says(&["duration"]),
        // Kalibr imports that must fail clearly.
        Case::new(
            "import-kalibr, omni model",
            calib,
            &[
                "import-kalibr",
                "--camchain",
                &k_omni,
                "--unit-id",
                UNIT,
                "--out",
                &out("k1.json"),
            ],
        )
        .says(&["omni.yaml", "cam0.camera_model"]),
        Case::new(
            "import-kalibr, 15 numbers",
            calib,
            &[
                "import-kalibr",
                "--camchain",
                &k_15,
                "--unit-id",
                UNIT,
                "--out",
                &out("k2.json"),
            ],
        )
        .says(&["fifteen.yaml", "cam0.T_cam_imu", "4×4"]),
        Case::new(
            "import-kalibr, three cameras",
            calib,
            &[
                "import-kalibr",
                "--camchain",
                &k_three,
                "--unit-id",
                UNIT,
                "--out",
                &out("k3.json"),
            ],
        )
        .says(&["three.yaml", "cam2", "--lenses"]),
        Case::new(
            "import-kalibr, not YAML",
            calib,
            &[
                "import-kalibr",
                "--camchain",
                &k_garbage,
                "--unit-id",
                UNIT,
                "--out",
                &out("k4.json"),
            ],
        )
        .says(&["garbage.yaml", "Kalibr YAML"]),
        Case::new(
            "import-kalibr, principal point",
            calib,
            &[
                "import-kalibr",
                "--camchain",
                &k_cx,
                "--unit-id",
                UNIT,
                "--out",
                &out("k5.json"),
            ],
        )
        .says(&["intrinsics.cx"]),
        Case::new(
            "import-kalibr, bad lens names",
            calib,
            &[
                "import-kalibr",
                "--camchain",
                &k_cx,
                "--unit-id",
                UNIT,
                "--lenses",
                "wrist",
                "--out",
                &out("k6.json"),
            ],
        )
        .says(&["name", "`wrist`"]),
        // Numbers on the command line.
        Case::new(
            "qr-clock --duration 0",
            calib,
            &["qr-clock", "--out", &out("q.mp4"), "--duration", "0"],
        )
        .says(&["--duration", "> 0"]),
        Case::new(
            "qr-clock --fps=-60",
            calib,
            &["qr-clock", "--out", &out("q.mp4"), "--fps=-60"],
        )
        .says(&["--fps", "> 0"]),
        Case::new(
            "target --tag-size 0",
            calib,
            &[
                "target",
                "aprilgrid",
                "--out",
                &out("t.svg"),
                "--tag-size",
                "0",
            ],
        )
        .says(&["--tag-size"]),
        Case::new(
            "av-delay, speaker distance in cm",
            calib,
            &[
                "av-delay",
                "--capture",
                &s(&cap_g),
                "--speaker-distance",
                "cam=150",
                "--out",
                &out("av"),
            ],
        )
        .says(&["--speaker-distance", "cm or mm"]),
        // Weak messages made clear.
        Case::new(
            "export, a folder as the calibration",
            calib,
            &["export", "--calibration", &s(&set), "--out", &out("e")],
        )
        .says(&[DATE, "folder", "expected a file"]),
        Case::new(
            "units show on an unfinished set",
            calib,
            &["units", "show", &s(&killed)],
        )
        .says(&["2026-01-03", "unfinished"]),
        Case::new(
            "units list on a missing folder",
            calib,
            &["units", "list", &s(&root.join("nowhere"))],
        )
        .says(&["nowhere", "units/"]),
    ];
    for c in &mut cases {
        c.watched = vec![
            units.clone(),
            root.join("out"),
            logs.clone(),
            kalibr.clone(),
        ];
        // A servo recording waits for its device before it gives up, in a folder of its own.
        if c.name.starts_with("bench servo")
            && let Some(i) = c.args.iter().position(|a| a == "--out")
        {
            c.watched.push(PathBuf::from(&c.args[i + 1]));
        }
    }
    let ran = run_all(&cases);
    assert!(ran >= 45, "{ran}");
}

#[test]
fn kalibr_variants_from_public_camchains_are_imported() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    // OpenCV FileStorage header, flat 16-number T_cam_imu, T_cn_cnm1 as an OpenCV matrix.
    let text = "%YAML:1.0\n---\ncam0:\n  camera_model: pinhole\n  intrinsics: [30.0, 30.0, 31.5, 31.5]\n  distortion_model: equidistant\n  distortion_coeffs: [0.01, 0.0, 0.0, 0.0]\n  resolution: [64, 64]\n  T_cam_imu: [1, 0, 0, 0.01, 0, 1, 0, 0.002, 0, 0, 1, -0.003, 0, 0, 0, 1]\n  timeshift_cam_imu: 0.001\ncam1:\n  camera_model: pinhole\n  intrinsics: [30.0, 30.0, 31.5, 31.5]\n  distortion_model: equidistant\n  distortion_coeffs: [0.01, 0.0, 0.0, 0.0]\n  resolution: [64, 64]\n  T_cn_cnm1: !!opencv-matrix\n    rows: 4\n    cols: 4\n    dt: d\n    data: [-1, 0, 0, 0, 0, 1, 0, 0, 0, 0, -1, -0.02, 0, 0, 0, 1]\n  timeshift_cam_imu: 0.001\n";
    let camchain = root.join("camchain-imucam.yaml");
    std::fs::write(&camchain, text).unwrap();
    let out = root.join("calibration.json");
    let output = std::process::Command::new(CALIB)
        .args([
            "import-kalibr",
            "--camchain",
            &s(&camchain),
            "--unit-id",
            UNIT,
            "--out",
            &s(&out),
        ])
        .output()
        .unwrap();
    let said = String::from_utf8_lossy(&output.stdout).into_owned()
        + &String::from_utf8_lossy(&output.stderr);
    assert!(output.status.success(), "{said}");
    assert!(
        said.contains("cam0 → front") && said.contains("cam1 → rear"),
        "{said}"
    );
    let cal = kiwi_core::artifact::UnitCalibration::load(&out).unwrap();
    let front = cal.lens("front").unwrap().cam_from_imu().unwrap();
    assert!((front.translation.vector.x - 0.01).abs() < 1e-12);
    // cam1 = T_cn_cnm1 · cam0_from_imu.
    let rear = cal.lens("rear").unwrap().cam_from_imu().unwrap();
    let expect = Pose::from_parts(
        Translation3::new(0.0, 0.0, -0.02),
        UnitQuaternion::from_euler_angles(0.0, std::f64::consts::PI, 0.0),
    ) * front;
    assert!((rear.translation.vector - expect.translation.vector).norm() < 1e-9);
    assert!(rear.rotation.angle_to(&expect.rotation) < 1e-9);

    // Rows of four, as Kalibr writes them, still work; --lenses names a GO 3's camera.
    let rows = "cam0:\n  camera_model: pinhole\n  intrinsics: [30.0, 30.0, 31.5, 31.5]\n  distortion_model: equidistant\n  distortion_coeffs: [0.01, 0.0, 0.0, 0.0]\n  resolution: [64, 64]\n  T_cam_imu:\n  - [1, 0, 0, 0]\n  - [0, 1, 0, 0]\n  - [0, 0, 1, 0]\n  - [0, 0, 0, 1]\n";
    std::fs::write(&camchain, rows).unwrap();
    let out2 = root.join("go3.json");
    let output = std::process::Command::new(CALIB)
        .args([
            "import-kalibr",
            "--camchain",
            &s(&camchain),
            "--unit-id",
            "GO3-1",
            "--lenses",
            "main",
            "--out",
            &s(&out2),
        ])
        .output()
        .unwrap();
    let said = String::from_utf8_lossy(&output.stdout).into_owned();
    assert!(
        output.status.success() && said.contains("cam0 → main"),
        "{said}"
    );
}

#[test]
fn units_list_reports_and_clean_removes_what_killed_runs_left() {
    let dir = tempfile::tempdir().unwrap();
    let units = dir.path().join("units");
    let unit_dir = units.join(UNIT);
    let set = unit_dir.join(DATE);
    std::fs::create_dir_all(&set).unwrap();
    unit()
        .true_calibration(DATE)
        .save(&set.join("calibration.json"))
        .unwrap();
    // A killed run: its claimed, empty set folder and its work folder (pid 4194304 is above
    // Linux's pid limit, so no process has it).
    let claimed = unit_dir.join("2026-01-05");
    let work = unit_dir.join(".certify-2026-01-05-4194304");
    std::fs::create_dir_all(work.join("report")).unwrap();
    std::fs::write(work.join("planted.txt"), "left by a killed run").unwrap();
    std::fs::create_dir_all(&claimed).unwrap();
    let before = kiwi_fixtures::check::snapshot(&set);

    let list = std::process::Command::new(CALIB)
        .args(["units", "list", &s(&units)])
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&list.stdout).into_owned();
    assert!(list.status.success(), "{text}");
    assert!(
        text.contains(".certify-2026-01-05-4194304") && text.contains("killed"),
        "{text}"
    );
    assert!(text.contains("2026-01-05 (empty set folder"), "{text}");
    assert!(text.contains("units clean"), "{text}");

    let clean = std::process::Command::new(CALIB)
        .args(["units", "clean", &s(&units)])
        .output()
        .unwrap();
    assert!(clean.status.success());
    assert!(!work.exists() && !claimed.exists());
    assert_eq!(
        kiwi_fixtures::check::snapshot(&set),
        before,
        "a finished set was touched"
    );
    let list = std::process::Command::new(CALIB)
        .args(["units", "list", &s(&units)])
        .output()
        .unwrap();
    assert!(!String::from_utf8_lossy(&list.stdout).contains("leftover"));

    // A new run never reuses a stale work folder: one with this process's id (a killed run
    // whose id came round again) is emptied first.
    let stale = unit_dir.join(format!(".certify-2026-01-06-{}", std::process::id()));
    std::fs::create_dir_all(&stale).unwrap();
    std::fs::write(stale.join("planted.txt"), "stale").unwrap();
    let fresh = kiwi_calib::certify::report::create_work_dir(&unit_dir, "2026-01-06").unwrap();
    assert_eq!(fresh, stale);
    assert_eq!(
        std::fs::read_dir(&fresh).unwrap().count(),
        0,
        "stale files survived"
    );
}
