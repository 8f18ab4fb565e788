//! Acceptance tests of the unit artifact: lossless JSON round trip, Kalibr export re-import,
//! Basalt export, and one test per malformed input asserting the error names the field.

#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

use std::path::Path;

use kiwi_core::artifact::*;
use kiwi_core::geometry::{Tangent6, se3_exp};
use kiwi_core::{basalt, kalibr};

fn sample() -> UnitCalibration {
    let front_from_imu = se3_exp(&Tangent6::new(1.2, -1.1, 1.3, 0.011, -0.004, 0.021));
    let rear_from_imu = se3_exp(&Tangent6::new(-1.2, 1.1, 1.25, -0.012, 0.003, -0.019));
    UnitCalibration {
        schema_version: SCHEMA_VERSION,
        unit_id: "X5-0042".into(),
        camera_model: "Insta360 X5".into(),
        firmware: "1.2.3".into(),
        date: "2026-11-22".into(),
        recording_modes: vec![RecordingMode {
            name: "x5-960-119.88".into(),
            width: 960,
            height: 960,
            fps: 119.88,
            readout_time_s: Some(0.0081),
        }],
        lenses: vec![
            LensCalibration {
                name: "front".into(),
                intrinsics: Intrinsics::Kb4 {
                    fx: 281.312345678,
                    fy: 280.7,
                    cx: 479.6,
                    cy: 481.2,
                    k1: 0.031,
                    k2: -0.0042,
                    k3: 0.0011,
                    k4: -0.00013,
                },
                resolution: [960, 960],
                valid_fov_rad: 190f64.to_radians(),
                rms_px: Some(0.31),
                param_std: Some(vec![0.1, 0.1, 0.05, 0.05, 1e-4, 1e-4, 1e-5, 1e-6]),
                cam_from_imu: Some(RigidTransform::from_pose(&front_from_imu)),
                time_shift_s: Some(0.00312),
            },
            LensCalibration {
                name: "rear".into(),
                intrinsics: Intrinsics::DoubleSphere {
                    fx: 245.0,
                    fy: 244.2,
                    cx: 480.3,
                    cy: 479.1,
                    xi: -0.21,
                    alpha: 0.61,
                },
                resolution: [960, 960],
                valid_fov_rad: 192f64.to_radians(),
                rms_px: Some(0.29),
                param_std: None,
                cam_from_imu: Some(RigidTransform::from_pose(&rear_from_imu)),
                time_shift_s: Some(-0.0021),
            },
        ],
        imu: Some(ImuNoise {
            rate_hz: 1000.0,
            gyroscope_noise_density: 1.7e-4,
            gyroscope_random_walk: 1.9e-5,
            accelerometer_noise_density: 2.0e-3,
            accelerometer_random_walk: 3.0e-3,
            gyroscope_bias_instability: Some(2e-5),
            accelerometer_bias_instability: None,
            axis_convention: "x5-imu".into(),
        }),
        av_delays: vec![AvDelay {
            mode: "x5-960-119.88".into(),
            delay_s: 0.0213,
            std_s: 0.0004,
            repeats: 3,
        }],
        provenance: Provenance {
            tool: "test".into(),
            tool_version: "0".into(),
            created_utc: "2026-11-22T00:00:00Z".into(),
            inputs: vec![],
        },
        certification: Some(Certification {
            passed: true,
            checks: vec![Check {
                name: "front.rms_px".into(),
                value: 0.31,
                threshold: 0.5,
                comparison: "at_most".into(),
                passed: true,
            }],
        }),
    }
}

#[test]
fn json_round_trip_is_lossless() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("calibration.json");
    let cal = sample();
    cal.save(&path).unwrap();
    let back = UnitCalibration::load(&path).unwrap();
    assert_eq!(back, cal);
}

#[test]
fn kalibr_export_reimports_to_the_same_values() {
    let cal = sample();
    let text = kalibr::camchain_yaml(&cal);
    let lenses = kalibr::lenses_from_camchain(&text, Path::new("camchain-imucam.yaml")).unwrap();
    assert_eq!(lenses.len(), 2);
    for (a, b) in lenses.iter().zip(&cal.lenses) {
        assert_eq!(a.name, b.name);
        assert_eq!(a.intrinsics, b.intrinsics);
        assert_eq!(a.resolution, b.resolution);
        assert_eq!(a.cam_from_imu, b.cam_from_imu);
        assert_eq!(a.time_shift_s, b.time_shift_s);
    }
    assert!(text.contains("camera_model: ds") && text.contains("distortion_model: equidistant"));
    let imu = kalibr::imu_from_yaml(
        &kalibr::imu_yaml(cal.imu.as_ref().unwrap()),
        Path::new("imu.yaml"),
    )
    .unwrap();
    let orig = cal.imu.as_ref().unwrap();
    assert_eq!(imu.gyroscope_noise_density, orig.gyroscope_noise_density);
    assert_eq!(
        imu.accelerometer_random_walk,
        orig.accelerometer_random_walk
    );
    assert_eq!(imu.rate_hz, orig.rate_hz);
}

#[test]
fn kalibr_import_reads_nested_imu_and_rejects_unknown_models() {
    let nested = "imu0:\n  update_rate: 200.0\n  accelerometer_noise_density: 0.002\n  accelerometer_random_walk: 0.003\n  gyroscope_noise_density: 0.00017\n  gyroscope_random_walk: 0.000019\n";
    let imu = kalibr::imu_from_yaml(nested, Path::new("imu.yaml")).unwrap();
    assert_eq!(imu.rate_hz, 200.0);
    let bad = "cam0:\n  camera_model: omni\n  intrinsics: [1, 2, 3, 4, 5]\n  distortion_model: radtan\n  distortion_coeffs: [0, 0, 0, 0]\n  resolution: [640, 480]\n";
    let err = kalibr::lenses_from_camchain(bad, Path::new("c.yaml")).unwrap_err();
    assert_eq!(err.field(), Some("cam0.camera_model"), "{err}");
}

#[test]
fn basalt_export_has_inverse_extrinsics() {
    let cal = sample();
    let text = basalt::calibration_json(&cal).unwrap();
    let v: serde_json::Value = serde_json::from_str(&text).unwrap();
    let t = &v["value0"]["T_imu_cam"][0];
    let imu_from_cam = cal.lenses[0].cam_from_imu().unwrap().inverse();
    assert!((t["px"].as_f64().unwrap() - imu_from_cam.translation.x).abs() < 1e-15);
    assert_eq!(v["value0"]["intrinsics"][1]["camera_type"], "ds");
    assert_eq!(v["value0"]["cam_time_offset_ns"], 3_120_000);
}

fn load_modified(edit: impl FnOnce(&mut serde_json::Value)) -> kiwi_core::CoreError {
    let mut v: serde_json::Value = serde_json::from_str(&sample().to_json().unwrap()).unwrap();
    edit(&mut v);
    UnitCalibration::from_json(
        &v.to_string(),
        Path::new("units/X5-0042/2026-11-22/calibration.json"),
    )
    .unwrap_err()
}

#[test]
fn missing_field_is_named() {
    let err = load_modified(|v| {
        v["lenses"][0]["intrinsics"]
            .as_object_mut()
            .unwrap()
            .remove("fy");
    });
    assert_eq!(err.field(), Some("lenses[0].intrinsics.fy"), "{err}");
    assert!(err.to_string().contains("calibration.json"), "{err}");
}

#[test]
fn nan_is_named() {
    // JSON has no NaN: a writer that emits null or the bare token must be caught at the field.
    let err = load_modified(|v| v["lenses"][1]["intrinsics"]["xi"] = serde_json::Value::Null);
    assert_eq!(err.field(), Some("lenses[1].intrinsics.xi"), "{err}");
    let mut cal = sample();
    cal.lenses[0].time_shift_s = Some(f64::NAN);
    let err = cal.validate().unwrap_err();
    assert_eq!(err.field(), Some("lenses[0].time_shift_s"), "{err}");
    let text = sample().to_json().unwrap().replace("0.00312", "NaN");
    let err = UnitCalibration::from_json(&text, Path::new("calibration.json")).unwrap_err();
    assert!(err.to_string().contains("NaN"), "{err}");
}

#[test]
fn negative_focal_length_is_named() {
    let err = load_modified(|v| v["lenses"][0]["intrinsics"]["fx"] = serde_json::json!(-281.3));
    assert_eq!(err.field(), Some("lenses[0].intrinsics.fx"), "{err}");
    assert!(err.to_string().contains("positive focal length"), "{err}");
}

#[test]
fn non_orthonormal_rotation_is_named() {
    let err = load_modified(|v| {
        v["lenses"][1]["cam_from_imu"]["rotation"][0][1] = serde_json::json!(0.3);
    });
    assert_eq!(
        err.field(),
        Some("lenses[1].cam_from_imu.rotation"),
        "{err}"
    );
}

#[test]
fn unknown_schema_version_is_named() {
    let err = load_modified(|v| v["schema_version"] = serde_json::json!(7));
    assert_eq!(err.field(), Some("schema_version"), "{err}");
    assert!(err.to_string().contains("newer KIWI"), "{err}");
    let err = load_modified(|v| {
        v.as_object_mut().unwrap().remove("schema_version");
    });
    assert_eq!(err.field(), Some("schema_version"), "{err}");
}

#[test]
fn unknown_field_and_bad_units_are_named() {
    let err = load_modified(|v| v["lenses"][0]["focal"] = serde_json::json!(1.0));
    assert!(err.to_string().contains("focal"), "{err}");
    let err = load_modified(|v| v["lenses"][0]["time_shift_s"] = serde_json::json!(3120.0));
    assert_eq!(err.field(), Some("lenses[0].time_shift_s"), "{err}");
    let err = load_modified(|v| v["lenses"][0]["valid_fov_rad"] = serde_json::json!(190.0));
    assert_eq!(err.field(), Some("lenses[0].valid_fov_rad"), "{err}");
}
