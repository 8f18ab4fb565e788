//! Lens intrinsics throughput: aprilgrid detection + KB4 fit of 100 simulator images at
//! 960 × 960 (target < 30 s on the 2-core machine). Prints wall times and the fit's accuracy.

#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use std::time::Instant;

use kiwi_calib::detect::{DetectOptions, detect_folder};
use kiwi_calib::intrinsics::{IntrinsicsOptions, calibrate};
use kiwi_calib::target::AprilGridTarget;
use kiwi_core::artifact::UnitCalibration;
use kiwi_core::camera::CameraModel;
use kiwi_fixtures::captures::{UnitCaptureOptions, write_unit_captures};

fn main() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("unit");
    let mut o = UnitCaptureOptions::new(&out, "X5-BENCH");
    o.views = 100;
    o.resolution = 960;
    o.cam_imu_duration_s = 0.0;
    o.static_duration_s = 0.0;
    o.bench_duration_s = 0.0;
    o.rig_duration_s = 0.0;
    let t = Instant::now();
    write_unit_captures(&o).unwrap();
    println!(
        "rendered 2 × 100 views in {:.1} s (not timed below)",
        t.elapsed().as_secs_f64()
    );
    let target = AprilGridTarget::load(&out.join("target.yaml")).unwrap();
    let images = out.join("intrinsics/front/frames");
    let t0 = Instant::now();
    let set = detect_folder(&images, &target, &DetectOptions::default()).unwrap();
    let detect_s = t0.elapsed().as_secs_f64();
    let t1 = Instant::now();
    let r = calibrate(&set, &IntrinsicsOptions::default()).unwrap();
    let fit_s = t1.elapsed().as_secs_f64();
    let truth = UnitCalibration::load(&out.join("truth/calibration.json")).unwrap();
    let tp = truth
        .lens("front")
        .unwrap()
        .camera()
        .unwrap()
        .params()
        .to_vec();
    println!(
        "intrinsics bench: 100 images 960x960 on {} threads: detection {detect_s:.2} s ({} \
         images with the target, {} corners), fit {fit_s:.2} s ({} iterations, {} rejected), \
         total {:.2} s (target < 30 s)",
        rayon::current_num_threads(),
        set.images.len(),
        set.total_corners(),
        r.iterations,
        r.n_rejected,
        detect_s + fit_s
    );
    println!(
        "fit: rms {:.3} px, fx {:.3} (truth {:.3}), cx {:.3} (truth {:.3}), max θ {:.1}°",
        r.rms_px, r.params[0], tp[0], r.params[2], tp[2], r.max_theta_deg
    );
}
