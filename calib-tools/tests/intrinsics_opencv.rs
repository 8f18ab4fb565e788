#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]
//! On corners restricted to less than 80° off-axis (where OpenCV's `cv::fisheye` works), KIWI's
//! KB4 fit must reach an RMS no worse than `cv::fisheye::calibrate` on the same corners.

mod common_intrinsics;
mod common_opencv;

use common_intrinsics::*;
use common_opencv::{kiwi_rms_all, opencv_fisheye};
use kiwi_calib::intrinsics::{IntrinsicsOptions, calibrate};
use kiwi_core::camera::{CameraModel, CameraModelKind};
use kiwi_fixtures::unit::LensModel;
use nalgebra::Point2;

const RESOLUTION: u32 = 960;
/// OpenCV's fisheye model is used within this angle only.
const MAX_THETA_DEG: f64 = 80.0;

#[test]
fn kiwi_kb4_no_worse_than_opencv_fisheye_below_80_degrees() {
    let dir = tempfile::tempdir().unwrap();
    let cap = capture(dir.path(), LensModel::Kb4, 40, RESOLUTION, 21);
    let truth_cam = truth_camera(&cap, "front");
    let mut truth = truth_corners(&cap, "front");
    for corners in truth.values_mut() {
        corners.retain(|&(_, u, v)| {
            truth_cam
                .unproject(&Point2::new(u, v))
                .is_some_and(|b| b.z.acos().to_degrees() < MAX_THETA_DEG)
        });
    }
    truth.retain(|_, c| c.len() >= 12);
    let set = noisy_corner_set(&truth, &sim_target(), RESOLUTION, 0.3, 8);
    let options = IntrinsicsOptions {
        model: CameraModelKind::Kb4,
        // Corners end at 80°: the periphery is empty on purpose.
        check_coverage: false,
        ..IntrinsicsOptions::default()
    };
    let r = calibrate(&set, &options).unwrap();
    // KIWI's RMS over every corner of every image (rejected ones included), same definition.
    let kiwi = kiwi_rms_all(&set, &r);
    let (cv, k) = opencv_fisheye(&set, RESOLUTION, RESOLUTION);
    let t = truth_cam.params();
    println!(
        "{} views, {} corners < {MAX_THETA_DEG}°: KIWI KB4 RMS {kiwi:.5} px (fx {:.3}), OpenCV \
         fisheye RMS {cv:.5} px (fx {:.3}); truth fx {:.3}",
        set.images.len(),
        set.total_corners(),
        r.params[0],
        k[0],
        t[0]
    );
    assert!(kiwi <= cv + 1e-6, "KIWI {kiwi} px vs OpenCV {cv} px");
}
