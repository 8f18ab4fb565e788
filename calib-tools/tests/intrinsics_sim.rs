#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]
//! Acceptance of the intrinsics fit on simulator captures (960 × 960, ~190°, 40 views of the
//! recommended capture design, KB4 and Double Sphere): exact corners plus 0.3 px Gaussian noise
//! through the corners-file path, with and without 5 % corrupted detections.

mod common_intrinsics;

use std::collections::BTreeSet;
use std::path::Path;

use common_intrinsics::*;
use kiwi_calib::detect::CornerSet;
use kiwi_calib::intrinsics::{IntrinsicsOptions, calibrate, report::write_outputs};
use kiwi_calib::target::AprilGridTarget;
use kiwi_core::camera::{CameraModel, CameraModelKind};
use kiwi_fixtures::captures::IntrinsicsDesign;
use kiwi_fixtures::unit::LensModel;

const RESOLUTION: u32 = 960;
const VIEWS: usize = 40;
/// The capture design docs/intrinsics.md recommends: a 10 × 10 × 55 mm aprilgrid held at
/// 0.2–0.4 m, most views towards the edge of the image circle.
fn design() -> IntrinsicsDesign {
    IntrinsicsDesign::recommended()
}
/// The limit on how far the fitted lens projects from the true one (px RMS over the
/// field of view).
const PROJECTION_TOLERANCE_PX: f64 = 0.05;
/// Corner noise the issue assumes (px per axis).
const SIGMA: f64 = 0.3;

struct Check {
    camera: kiwi_core::camera::Camera,
    /// Standard deviations of cx, cy from the fit's own covariance (px).
    pp_std: [f64; 2],
    n_rejected: usize,
    fx_rel: f64,
    fy_rel: f64,
    cx_px: f64,
    cy_px: f64,
    projection_rms: f64,
    rms: f64,
    max_theta_deg: f64,
}

/// The lens's nominal field of view is 190°: its image circle ends 95° off-axis.
const LENS_HALF_FOV_DEG: f64 = 95.0;

fn check(
    dir: &Path,
    cap: &Path,
    kind: CameraModelKind,
    sigma: f64,
    corrupt: bool,
) -> (Check, Vec<String>) {
    let truth_cam = truth_camera(cap, "front");
    let truth = truth_corners(cap, "front");
    let target = design_target(&design());
    let mut set = noisy_corner_set(&truth, &target, RESOLUTION, sigma, 5);
    let mut corrupted = Vec::new();
    if corrupt {
        corrupted = corrupt_set(&mut set, &target, 0.05, 99);
    }
    let options = IntrinsicsOptions {
        model: kind,
        ..IntrinsicsOptions::default()
    };
    let t0 = std::time::Instant::now();
    let r = calibrate(&set, &options).unwrap();
    println!(
        "fit took {:.2} s, {} iterations: {:?} vs truth {:?}",
        t0.elapsed().as_secs_f64(),
        r.iterations,
        r.camera.params(),
        truth_cam.params()
    );
    let t = truth_cam.params();
    let p = r.camera.params();
    let max_theta = max_truth_theta(&truth_cam, &truth);
    let whole_image = projection_rms(&truth_cam, &r.camera, max_theta);
    let c = Check {
        camera: r.camera.clone(),
        pp_std: [r.param_std[2], r.param_std[3]],
        n_rejected: r.n_rejected,
        fx_rel: (p[0] - t[0]).abs() / t[0],
        fy_rel: (p[1] - t[1]).abs() / t[1],
        cx_px: (p[2] - t[2]).abs(),
        cy_px: (p[3] - t[3]).abs(),
        projection_rms: projection_rms(&truth_cam, &r.camera, LENS_HALF_FOV_DEG.to_radians()),
        rms: r.rms_px,
        max_theta_deg: max_theta.to_degrees(),
    };
    println!(
        "{kind} σ={sigma} corrupt={corrupt}: fx {:.4} % fy {:.4} % cx {:.3} px cy {:.3} px, projection \
         RMS {:.4} px within {LENS_HALF_FOV_DEG}° ({whole_image:.4} px over the whole image, \
         to {:.1}°), fit RMS {:.4} px ({} views, {} corners, {} rejected, max θ \
         {:.1}°), std {:?}",
        100.0 * c.fx_rel,
        100.0 * c.fy_rel,
        c.cx_px,
        c.cy_px,
        c.projection_rms,
        c.max_theta_deg,
        c.rms,
        r.n_views,
        r.n_corners,
        r.n_rejected,
        r.max_theta_deg,
        r.param_std
    );
    // Every corrupted corner the fit could notice must be listed as rejected.
    let rejected: BTreeSet<String> = r
        .rejected
        .iter()
        .map(|x| format!("{}/{}", x.image, x.id))
        .collect();
    let missed: Vec<String> = corrupted
        .iter()
        .filter(|k| !rejected.contains(*k))
        .cloned()
        .collect();
    let out = dir.join(format!("report-{kind}-{sigma}-{corrupt}"));
    let files = write_outputs(&r, "front", &out).unwrap();
    for f in &files.plots {
        assert!(std::fs::metadata(f).unwrap().len() > 1000);
    }
    if corrupt {
        let csv = std::fs::read_to_string(&files.rejected).unwrap();
        assert!(csv.lines().count() > corrupted.len());
        // Good corners must not be rejected along with the corrupted ones (an over-eager
        // rejection of peripheral corners would bias the fit): at most 0.5 % of them.
        assert!(
            r.n_rejected <= corrupted.len() + r.n_corners / 200,
            "{} corners rejected for {} corrupted",
            r.n_rejected,
            corrupted.len()
        );
    }
    (c, missed)
}

/// Corrupt a fraction of the corners: half moved by 3–25 px, half given the id (and board
/// position) of a target point the image does not contain. Returns `image/id` of each.
fn corrupt_set(
    set: &mut CornerSet,
    target: &AprilGridTarget,
    fraction: f64,
    seed: u64,
) -> Vec<String> {
    let mut noise = Noise::new(seed);
    let mut keys = Vec::new();
    for img in &mut set.images {
        let present: BTreeSet<u32> = img.corners.iter().map(|c| c.id).collect();
        for c in &mut img.corners {
            if noise.uniform() >= fraction {
                continue;
            }
            let full = present.len() >= target.point_count();
            if full || noise.uniform() < 0.5 {
                let r = 3.0 + 22.0 * noise.uniform();
                let a = std::f64::consts::TAU * noise.uniform();
                c.pixel[0] += r * a.cos();
                c.pixel[1] += r * a.sin();
            } else {
                let mut id;
                loop {
                    id = (noise.uniform() * target.point_count() as f64) as u32;
                    if !present.contains(&id) {
                        break;
                    }
                }
                // A wrong id is only wrong if it moves the board point noticeably.
                let b = target.point(id as usize);
                c.id = id;
                c.board = [b.x, b.y, b.z];
            }
            keys.push(format!("{}/{}", img.name, c.id));
        }
    }
    keys
}

/// The tolerances: fx, fy within 0.1 %, cx, cy within 0.3 px, the fitted lens
/// reproduces the true projections within 0.05 px RMS over the whole field of view, and the fit
/// RMS is within 15 % of the injected noise. The projection error is dominated by the principal
/// point's statistical uncertainty, which the capture design sets (docs/intrinsics.md, "Capture
/// design"): with the recommended design the fit's own principal-point std is ~0.017 px per
/// axis (KB4) and ~0.012 px (DS), so 0.05 px holds with margin; Kalibr's 6 × 6 board at
/// 0.35–0.9 m gives ~0.05 px per axis and cannot meet it reliably.
fn assert_inside(c: &Check) {
    assert!(c.fx_rel < 1e-3, "fx off by {:.4} %", 100.0 * c.fx_rel);
    assert!(c.fy_rel < 1e-3, "fy off by {:.4} %", 100.0 * c.fy_rel);
    assert!(c.cx_px < 0.3, "cx off by {:.3} px", c.cx_px);
    assert!(c.cy_px < 0.3, "cy off by {:.3} px", c.cy_px);
    assert!(
        c.projection_rms < PROJECTION_TOLERANCE_PX,
        "projections differ by {:.4} px RMS over the field of view (the issue: < \
         {PROJECTION_TOLERANCE_PX} px); principal point std {:?} px",
        c.projection_rms,
        c.pp_std
    );
    assert!(
        (c.rms - SIGMA).abs() < 0.15 * SIGMA,
        "fit RMS {:.4} px is not within 15 % of the injected {SIGMA} px",
        c.rms
    );
    assert!(c.max_theta_deg > 90.0, "the captures must reach past 90°");
}

/// The acceptance for one lens model: noise-free corners are reproduced exactly (the
/// fit has no bias, no wrong basin, no early stop: projection error < 0.001 px, far inside the
/// issue's 0.05 px); with 0.3 px noise the tolerances hold; with 5 % corrupted
/// detections every corrupted corner is rejected, hardly any good one is, and the result moves
/// by less than 0.05 px from the clean one.
fn accept(model: LensModel, kind: CameraModelKind, seed: u64) {
    let dir = tempfile::tempdir().unwrap();
    let cap = capture_with(dir.path(), model, VIEWS, RESOLUTION, seed, design());
    let (exact, _) = check(dir.path(), &cap, kind, 0.0, false);
    assert!(
        exact.projection_rms < 1e-3,
        "noise-free corners: projections differ by {:.5} px",
        exact.projection_rms
    );
    assert!(exact.fx_rel < 1e-6 && exact.cx_px < 1e-3 && exact.cy_px < 1e-3);
    let (clean, _) = check(dir.path(), &cap, kind, SIGMA, false);
    assert_inside(&clean);
    assert_eq!(clean.n_rejected, 0, "good corners were rejected");
    let (c, missed) = check(dir.path(), &cap, kind, SIGMA, true);
    assert_inside(&c);
    assert!(
        missed.is_empty(),
        "corrupted corners not rejected: {missed:?}"
    );
    let moved = projection_rms(&clean.camera, &c.camera, LENS_HALF_FOV_DEG.to_radians());
    println!("corruption moved the fit by {moved:.4} px RMS");
    assert!(
        moved < 0.05,
        "the corrupted fit differs from the clean one by {moved} px"
    );
}

/// KB4 lens: noise-free, clean and with 5 % corrupted detections.
#[test]
fn kb4_full_fov_clean_and_corrupted() {
    accept(LensModel::Kb4, CameraModelKind::Kb4, 11);
}

/// Double Sphere lens: noise-free, clean and with 5 % corrupted detections.
#[test]
fn ds_full_fov_clean_and_corrupted() {
    accept(LensModel::Ds, CameraModelKind::DoubleSphere, 11);
}
