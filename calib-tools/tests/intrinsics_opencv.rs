#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]
//! On corners restricted to less than 80° off-axis (where OpenCV's `cv::fisheye` works), KIWI's
//! KB4 fit must reach an RMS no worse than `cv::fisheye::calibrate` on the same corners.

mod common_intrinsics;

use common_intrinsics::*;
use kiwi_calib::detect::CornerSet;
use kiwi_calib::intrinsics::{IntrinsicsOptions, calibrate};
use kiwi_core::camera::{CameraModel, CameraModelKind};
use kiwi_fixtures::unit::LensModel;
use nalgebra::{Isometry3, Point2, Quaternion, Translation3, UnitQuaternion, Vector2, Vector3};
use opencv::core::{Mat, Point2f, Point3f, Size, TermCriteria, TermCriteria_Type, Vec3d, Vector};
use opencv::prelude::*;

const RESOLUTION: u32 = 960;
/// OpenCV's fisheye model is used within this angle only.
const MAX_THETA_DEG: f64 = 80.0;

/// Per-axis RMS of residuals (px).
fn rms(res: &[Vector2<f64>]) -> f64 {
    (res.iter().map(nalgebra::Matrix::norm_squared).sum::<f64>() / (2 * res.len()) as f64).sqrt()
}

fn opencv_rms(set: &CornerSet) -> (f64, [f64; 4]) {
    let mut obj: Vector<Vector<Point3f>> = Vector::new();
    let mut img: Vector<Vector<Point2f>> = Vector::new();
    for im in &set.images {
        obj.push(
            im.corners
                .iter()
                .map(|c| Point3f::new(c.board[0] as f32, c.board[1] as f32, 0.0))
                .collect(),
        );
        img.push(
            im.corners
                .iter()
                .map(|c| Point2f::new(c.pixel[0] as f32, c.pixel[1] as f32))
                .collect(),
        );
    }
    let mut k = Mat::default();
    let mut d = Mat::default();
    let mut rvecs: Vector<Vec3d> = Vector::new();
    let mut tvecs: Vector<Vec3d> = Vector::new();
    let flags = opencv::calib3d::Fisheye_CALIB_RECOMPUTE_EXTRINSIC
        | opencv::calib3d::Fisheye_CALIB_FIX_SKEW;
    let criteria = TermCriteria::new(
        TermCriteria_Type::COUNT as i32 + TermCriteria_Type::EPS as i32,
        200,
        1e-12,
    )
    .unwrap();
    let reported = opencv::calib3d::calibrate(
        &obj,
        &img,
        Size::new(RESOLUTION as i32, RESOLUTION as i32),
        &mut k,
        &mut d,
        &mut rvecs,
        &mut tvecs,
        flags,
        criteria,
    )
    .unwrap();
    // Reproject with OpenCV's own model and measure like KIWI does.
    let mut res = Vec::new();
    for (v, im) in set.images.iter().enumerate() {
        let mut projected: Vector<Point2f> = Vector::new();
        let rv = rvecs.get(v).unwrap();
        let tv = tvecs.get(v).unwrap();
        let (ra, ta) = ([rv[0], rv[1], rv[2]], [tv[0], tv[1], tv[2]]);
        let rvm = Mat::from_slice(&ra).unwrap();
        let tvm = Mat::from_slice(&ta).unwrap();
        let o = obj.get(v).unwrap();
        opencv::calib3d::fisheye_project_points_vec(
            &o,
            &mut projected,
            &rvm,
            &tvm,
            &k,
            &d,
            0.0,
            &mut opencv::core::no_array(),
        )
        .unwrap();
        for (p, c) in projected.iter().zip(&im.corners) {
            res.push(Vector2::new(
                f64::from(p.x) - c.pixel[0],
                f64::from(p.y) - c.pixel[1],
            ));
        }
    }
    let kf = |r: i32, c: i32| *k.at_2d::<f64>(r, c).unwrap();
    println!("OpenCV reported RMS {reported:.4}");
    (rms(&res), [kf(0, 0), kf(1, 1), kf(0, 2), kf(1, 2)])
}

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
    let mut res = Vec::new();
    for (im, v) in set.images.iter().zip(&r.views) {
        let p = v.cam_from_board.expect("every view is used");
        let pose = Isometry3::from_parts(
            Translation3::new(p[0], p[1], p[2]),
            UnitQuaternion::from_quaternion(Quaternion::new(p[6], p[3], p[4], p[5])),
        );
        for c in &im.corners {
            let pc = pose * nalgebra::Point3::from(Vector3::from(c.board));
            let q = r.camera.project(&pc.coords).unwrap();
            res.push(Vector2::new(q.x - c.pixel[0], q.y - c.pixel[1]));
        }
    }
    let kiwi = rms(&res);
    let (cv, k) = opencv_rms(&set);
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
