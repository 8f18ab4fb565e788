//! Shared helpers of the tests that compare KIWI's fit with OpenCV's `cv::fisheye::calibrate`
//! on the same corners.
#![allow(dead_code)]

use kiwi_calib::detect::CornerSet;
use kiwi_calib::intrinsics::IntrinsicsResult;
use kiwi_core::camera::CameraModel;
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion, Vector2, Vector3};
use opencv::core::{Mat, Point2f, Point3f, Size, TermCriteria, TermCriteria_Type, Vec3d, Vector};
use opencv::prelude::*;

/// Per-axis RMS of residuals (px).
pub fn rms(res: &[Vector2<f64>]) -> f64 {
    (res.iter().map(nalgebra::Matrix::norm_squared).sum::<f64>() / (2 * res.len()) as f64).sqrt()
}

/// KIWI's per-axis RMS over every corner of every image, rejected ones included (the same
/// definition as for OpenCV below).
pub fn kiwi_rms_all(set: &CornerSet, r: &IntrinsicsResult) -> f64 {
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
    rms(&res)
}

/// OpenCV's fisheye calibration of the same corners: (per-axis RMS over all corners, [fx, fy,
/// cx, cy]).
pub fn opencv_fisheye(set: &CornerSet, width: u32, height: u32) -> (f64, [f64; 4]) {
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
    // The flags of OpenCV's own test on this data (fisheye.calibration), without
    // CALIB_CHECK_COND (it throws on an ill-conditioned view instead of fitting).
    let flags = opencv::calib3d::Fisheye_CALIB_RECOMPUTE_EXTRINSIC
        | opencv::calib3d::Fisheye_CALIB_FIX_SKEW;
    let criteria = TermCriteria::new(
        TermCriteria_Type::COUNT as i32 + TermCriteria_Type::EPS as i32,
        200,
        1e-12,
    )
    .unwrap();
    opencv::calib3d::calibrate(
        &obj,
        &img,
        Size::new(width as i32, height as i32),
        &mut k,
        &mut d,
        &mut rvecs,
        &mut tvecs,
        flags,
        criteria,
    )
    .unwrap();
    let mut res = Vec::new();
    for (v, im) in set.images.iter().enumerate() {
        let mut projected: Vector<Point2f> = Vector::new();
        let rv = rvecs.get(v).unwrap();
        let tv = tvecs.get(v).unwrap();
        let (ra, ta) = ([rv[0], rv[1], rv[2]], [tv[0], tv[1], tv[2]]);
        let rvm = Mat::from_slice(&ra).unwrap();
        let tvm = Mat::from_slice(&ta).unwrap();
        opencv::calib3d::fisheye_project_points_vec(
            &obj.get(v).unwrap(),
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
    (rms(&res), [kf(0, 0), kf(1, 1), kf(0, 2), kf(1, 2)])
}
