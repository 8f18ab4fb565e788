#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]
//! Real data: the fit converges without a focal-length hint on real corner sets of a strongly
//! distorted lens. The corners are OpenCV's own fisheye test set (`opencv_extra`,
//! `testdata/cv/cameracalibration/fisheye/calib-3_stereo_from_JY`: a stereo pair of fisheye
//! lenses, 1280 × 800, 34 views of an 8 × 6 chessboard with 24.4 mm squares, copied unchanged
//! under `fixtures/data/opencv_fisheye_jy/`), imported with `kiwi-calib corners import`'s
//! converter. KIWI's fit must reach OpenCV's `cv::fisheye::calibrate` RMS on the same corners
//! and agree with its focal length and principal point. `calibrate` takes no focal length: it
//! starts from its own focal-length scan.

mod common_opencv;

use std::path::PathBuf;

use common_opencv::{kiwi_rms_all, opencv_fisheye};

use kiwi_calib::detect::CornerSet;
use kiwi_calib::import::import_opencv;
use kiwi_calib::intrinsics::{IntrinsicsOptions, IntrinsicsResult, calibrate};
use kiwi_core::camera::CameraModelKind;

const WIDTH: u32 = 1280;
const HEIGHT: u32 = 800;
/// KIWI's RMS over all corners may exceed OpenCV's by this fraction: OpenCV's least squares
/// over every corner is the minimum of that RMS for the same KB4 model, and KIWI's robust fit
/// (Huber, 8 corners rejected per lens) sits a little above it (measured +0.2 % / +0.3 %).
const RMS_MARGIN: f64 = 0.01;
/// Focal lengths must agree with OpenCV's within this fraction (measured ≤ 0.08 %).
const FOCAL_TOL: f64 = 0.002;
/// Principal point must agree with OpenCV's within this (px; measured ≤ 0.13 px).
const CENTRE_TOL_PX: f64 = 0.5;
/// The Double Sphere fit's RMS may exceed the KB4 fit's by this fraction (measured +0.1 %).
const DS_RMS_MARGIN: f64 = 0.02;

fn data(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../fixtures/data/opencv_fisheye_jy")
        .join(name)
}

fn corners(lens: &str) -> CornerSet {
    import_opencv(
        &data(&format!("{lens}.xml")),
        &data("object.xml"),
        WIDTH,
        HEIGHT,
    )
    .unwrap()
}

fn fit(set: &CornerSet, model: CameraModelKind) -> IntrinsicsResult {
    let options = IntrinsicsOptions {
        model,
        ..IntrinsicsOptions::default()
    };
    calibrate(set, &options).unwrap()
}

fn check_lens(lens: &str) {
    let set = corners(lens);
    assert_eq!(set.images.len(), 34);
    assert_eq!(set.total_corners(), 34 * 48);
    let (cv_rms, cv_k) = opencv_fisheye(&set, WIDTH, HEIGHT);
    println!(
        "{lens}: OpenCV fisheye RMS {cv_rms:.4} px, fx {:.3} fy {:.3} cx {:.3} cy {:.3}",
        cv_k[0], cv_k[1], cv_k[2], cv_k[3]
    );
    let mut kb4_rms = f64::NAN;
    for model in [CameraModelKind::Kb4, CameraModelKind::DoubleSphere] {
        let r = fit(&set, model);
        let all = kiwi_rms_all(&set, &r);
        let p = r.pinhole();
        // Focal length at the image centre: fx for KB4, fx / (1 + xi) for Double Sphere.
        let centre_scale = match model {
            CameraModelKind::DoubleSphere => 1.0 / (1.0 + r.params[4]),
            _ => 1.0,
        };
        let (fx, fy) = (p[0] * centre_scale, p[1] * centre_scale);
        println!(
            "{lens} {:?}: KIWI RMS {:.4} px used / {all:.4} px all corners, {} views, {} \
             rejected, centre focal fx {:.3} fy {:.3} cx {:.3} cy {:.3}, max theta {:.1} deg, \
             params {:?}",
            model, r.rms_px, r.n_views, r.n_rejected, fx, fy, p[2], p[3], r.max_theta_deg, r.params
        );
        assert_eq!(r.n_views, 34, "{lens} {model:?}: every view is used");
        assert!(
            r.n_rejected <= set.total_corners() / 100,
            "{lens} {model:?}: {} corners rejected",
            r.n_rejected
        );
        for (name, kiwi, cv) in [("fx", fx, cv_k[0]), ("fy", fy, cv_k[1])] {
            assert!(
                (kiwi / cv - 1.0).abs() < FOCAL_TOL,
                "{lens} {model:?}: {name} {kiwi:.3} vs OpenCV {cv:.3}"
            );
        }
        for (name, kiwi, cv) in [("cx", p[2], cv_k[2]), ("cy", p[3], cv_k[3])] {
            assert!(
                (kiwi - cv).abs() < CENTRE_TOL_PX,
                "{lens} {model:?}: {name} {kiwi:.3} vs OpenCV {cv:.3}"
            );
        }
        match model {
            CameraModelKind::Kb4 => {
                assert!(
                    all <= cv_rms * (1.0 + RMS_MARGIN),
                    "{lens}: KIWI KB4 RMS {all:.4} px over all corners vs OpenCV {cv_rms:.4} px"
                );
                assert!(
                    r.rms_px <= cv_rms,
                    "{lens}: KIWI KB4 RMS {:.4} px over its used corners vs OpenCV {cv_rms:.4} px",
                    r.rms_px
                );
                kb4_rms = r.rms_px;
            }
            _ => assert!(
                r.rms_px <= kb4_rms * (1.0 + DS_RMS_MARGIN),
                "{lens}: Double Sphere RMS {:.4} px vs KB4 {kb4_rms:.4} px",
                r.rms_px
            ),
        }
    }
}

#[test]
fn real_fisheye_left_lens_converges_without_a_focal_hint() {
    check_lens("left");
}

#[test]
fn real_fisheye_right_lens_converges_without_a_focal_hint() {
    check_lens("right");
}

#[test]
fn corners_import_command_writes_the_same_corners() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("corners.json");
    let status = std::process::Command::new(env!("CARGO_BIN_EXE_kiwi-calib"))
        .args(["corners", "import", "--opencv"])
        .arg(data("right.xml"))
        .arg("--object")
        .arg(data("object.xml"))
        .args(["--size", "1280x800", "--out"])
        .arg(&out)
        .status()
        .unwrap();
    assert!(status.success());
    assert_eq!(CornerSet::load(&out).unwrap(), corners("right"));
    let bad = std::process::Command::new(env!("CARGO_BIN_EXE_kiwi-calib"))
        .args(["corners", "import", "--opencv"])
        .arg(data("right.xml"))
        .arg("--object")
        .arg(data("object.xml"))
        .args(["--size", "1280", "--out"])
        .arg(dir.path().join("bad.json"))
        .output()
        .unwrap();
    assert!(!bad.status.success());
    let stderr = String::from_utf8_lossy(&bad.stderr);
    assert!(stderr.contains("WIDTHxHEIGHT"), "{stderr}");
}
