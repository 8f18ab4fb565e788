//! Acceptance tests of the fisheye camera models: round trips over 0–95° off-axis, analytic
//! Jacobians against central differences, and KB4 against OpenCV's `cv::fisheye` golden vectors.

#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

use kiwi_core::camera::{CameraModel, DoubleSphere, Kb4, bearing_from_angles};
use nalgebra::{Matrix2xX, Point2, Vector3};

/// An X5-like 190° lens (KB4 fitted to an equidistant-ish profile).
fn kb4() -> Kb4 {
    Kb4::new(
        960,
        960,
        [281.3, 280.7, 479.6, 481.2, 0.031, -0.0042, 0.0011, -0.00013],
    )
    .unwrap()
}

/// A Double Sphere lens with a field of view above 190°.
fn ds() -> DoubleSphere {
    DoubleSphere::new(960, 960, [245.0, 244.2, 480.3, 479.1, -0.21, 0.61]).unwrap()
}

fn models() -> Vec<Box<dyn CameraModel>> {
    vec![Box::new(kb4()), Box::new(ds())]
}

/// Dense grid of directions from 0 to 95° off-axis.
fn grid() -> Vec<Vector3<f64>> {
    let mut dirs = Vec::new();
    for i in 0..=380 {
        let theta = (f64::from(i) * 0.25).to_radians();
        for j in 0..72 {
            let phi = (f64::from(j) * 5.0 + 0.37).to_radians();
            dirs.push(bearing_from_angles(theta, phi).into_inner());
        }
    }
    dirs
}

#[test]
fn fields_of_view_cover_190_degrees() {
    for m in models() {
        assert!(
            m.valid_fov().to_degrees() > 190.0,
            "{:?}: {}",
            m.kind(),
            m.valid_fov().to_degrees()
        );
    }
}

#[test]
fn project_unproject_round_trip_below_1e9_rad() {
    for m in models() {
        let mut worst: f64 = 0.0;
        for d in grid() {
            let pixel = m
                .project(&(d * 2.7))
                .unwrap_or_else(|| panic!("{:?} failed to project {d}", m.kind()));
            let back = m
                .unproject(&pixel)
                .unwrap_or_else(|| panic!("{:?} failed to unproject {pixel}", m.kind()));
            let angle = d.cross(&back).norm().atan2(d.dot(&back));
            worst = worst.max(angle);
        }
        assert!(
            worst < 1e-9,
            "{:?}: worst round-trip error {worst:e} rad",
            m.kind()
        );
    }
}

#[test]
fn unproject_project_round_trip_on_pixels() {
    for m in models() {
        for y in (0..960).step_by(37) {
            for x in (0..960).step_by(37) {
                let p = Point2::new(f64::from(x), f64::from(y));
                if let Some(b) = m.unproject(&p) {
                    let q = m.project(&b).unwrap();
                    assert!((q - p).norm() < 1e-7, "{:?}: {p} -> {q}", m.kind());
                }
            }
        }
    }
}

/// Within 1e-6 relative, with a floor of 1e-9 of the whole Jacobian's norm for entries that are
/// (near) zero, where central differences only see rounding noise.
fn relative_close(analytic: f64, numeric: f64, jacobian_norm: f64) -> bool {
    (analytic - numeric).abs() <= 1e-6 * analytic.abs().max(numeric.abs()) + 1e-9 * jacobian_norm
}

/// Parameters that enter the projection linearly (all but Double Sphere's xi and alpha) get a
/// large step: central differences are exact for them and rounding noise stays small.
fn param_step(kind: kiwi_core::camera::CameraModelKind, k: usize, value: f64) -> f64 {
    let linear = kind == kiwi_core::camera::CameraModelKind::Kb4 || k < 4;
    if linear {
        1e-3 * value.abs().max(1.0)
    } else {
        1e-4
    }
}

#[test]
fn analytic_jacobians_match_central_differences() {
    for m in models() {
        let n = m.params().len();
        let mut d_params = Matrix2xX::zeros(n);
        for d in grid().iter().step_by(41) {
            let point = d * 1.3;
            let (_, j_point) = m
                .project_with_jacobians(&point, Some(&mut d_params))
                .unwrap();
            let scale = j_point.norm();
            for k in 0..3 {
                let h = 1e-6;
                let mut plus = point;
                let mut minus = point;
                plus[k] += h;
                minus[k] -= h;
                let num = (m.project(&plus).unwrap() - m.project(&minus).unwrap()) / (2.0 * h);
                for r in 0..2 {
                    assert!(
                        relative_close(j_point[(r, k)], num[r], scale),
                        "{:?} d/dpoint[{r},{k}] {} vs {} at {point}",
                        m.kind(),
                        j_point[(r, k)],
                        num[r]
                    );
                }
            }
            let pscale = d_params.norm();
            for k in 0..n {
                let mut plus = m.params().to_vec();
                let mut minus = plus.clone();
                let h = param_step(m.kind(), k, plus[k]);
                plus[k] += h;
                minus[k] -= h;
                let (w, hgt) = m.resolution();
                let p_plus = build(m.kind(), w, hgt, &plus).project(&point).unwrap();
                let p_minus = build(m.kind(), w, hgt, &minus).project(&point).unwrap();
                let num = (p_plus - p_minus) / (2.0 * h);
                for r in 0..2 {
                    assert!(
                        relative_close(d_params[(r, k)], num[r], pscale),
                        "{:?} d/dparam[{r},{k}] {} vs {} at {point}",
                        m.kind(),
                        d_params[(r, k)],
                        num[r]
                    );
                }
            }
        }
    }
}

fn build(
    kind: kiwi_core::camera::CameraModelKind,
    w: u32,
    h: u32,
    p: &[f64],
) -> Box<dyn CameraModel> {
    match kind {
        kiwi_core::camera::CameraModelKind::Kb4 => {
            Box::new(Kb4::new(w, h, p.try_into().unwrap()).unwrap())
        }
        kiwi_core::camera::CameraModelKind::DoubleSphere => {
            Box::new(DoubleSphere::new(w, h, p.try_into().unwrap()).unwrap())
        }
    }
}

#[test]
fn on_axis_jacobians_are_finite_and_correct() {
    for m in models() {
        let point = Vector3::new(0.0, 0.0, 2.0);
        let (_, j) = m.project_with_jacobians(&point, None).unwrap();
        let h = 1e-6;
        let num_x = (m.project(&Vector3::new(h, 0.0, 2.0)).unwrap()
            - m.project(&Vector3::new(-h, 0.0, 2.0)).unwrap())
            / (2.0 * h);
        assert!(
            (j[(0, 0)] - num_x[0]).abs() < 1e-4 * j[(0, 0)].abs(),
            "{:?}",
            m.kind()
        );
    }
}

#[derive(serde::Deserialize)]
struct Golden {
    cameras: Vec<GoldenCamera>,
}

#[derive(serde::Deserialize)]
struct GoldenCamera {
    resolution: [u32; 2],
    params: [f64; 8],
    points: Vec<[f64; 3]>,
    pixels: Vec<[f64; 2]>,
}

#[test]
fn kb4_matches_opencv_fisheye_below_80_degrees() {
    let text = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/tests/golden/kb4_opencv.json"
    ))
    .unwrap();
    let golden: Golden = serde_json::from_str(&text).unwrap();
    let mut count = 0;
    for cam in &golden.cameras {
        let model = Kb4::new(cam.resolution[0], cam.resolution[1], cam.params).unwrap();
        for (p, px) in cam.points.iter().zip(&cam.pixels) {
            let ours = model.project(&Vector3::from(*p)).unwrap();
            let err = ((ours.x - px[0]).powi(2) + (ours.y - px[1]).powi(2)).sqrt();
            assert!(
                err < 1e-6,
                "OpenCV {px:?} vs KIWI {ours} for {p:?}: {err:e} px"
            );
            count += 1;
        }
    }
    assert!(count > 500);
}
