//! A certified calibration compared with the simulator's truth, value by value, against the
//! tolerances of the individual issues (intrinsics, IMU noise, camera–IMU, A/V delay). Shared
//! by the certification test (480 px) and the certification benchmark (960 px, 40 views: the
//! conditions the intrinsics issue states its figures for).

#![allow(dead_code, clippy::unwrap_used, clippy::expect_used)]

use kiwi_core::artifact::UnitCalibration;

#[allow(clippy::panic)]
#[path = "../common_intrinsics/mod.rs"]
mod common_intrinsics;
use common_intrinsics::projection_rms;

/// Intrinsics issue: focal lengths within 0.1 %.
pub const FOCAL_REL: f64 = 1e-3;
/// Intrinsics issue: principal point within 0.3 px.
pub const PRINCIPAL_POINT_PX: f64 = 0.3;
/// Intrinsics issue: projection error over the whole field < 0.05 px RMS (960 px, 40 views,
/// 0.3 px corner noise).
pub const PROJECTION_PX: f64 = 0.05;
/// Field over which the projection error is measured (rad off-axis): the lens's ~190°.
pub const PROJECTION_FIELD_RAD: f64 = 95.0 * std::f64::consts::PI / 180.0;
/// Camera–IMU issue: extrinsic rotation within 0.1°.
pub const ROTATION_DEG: f64 = 0.1;
/// Camera–IMU issue: extrinsic translation within 2 mm.
pub const TRANSLATION_M: f64 = 0.002;
/// Camera–IMU issue: time shift within 0.2 ms.
pub const TIME_SHIFT_S: f64 = 2e-4;
/// IMU-noise issue: white-noise densities within 3 %.
pub const NOISE_DENSITY_REL: f64 = 0.03;
/// IMU-noise issue: random walks within 15 %.
pub const RANDOM_WALK_REL: f64 = 0.15;
/// A/V-delay issue: delay within 1 ms.
pub const AV_DELAY_S: f64 = 1e-3;

/// One value of a certified calibration against the truth.
#[derive(Debug, Clone)]
pub struct TruthCheck {
    /// What is compared, e.g. `front.projection`.
    pub name: String,
    /// The error against the truth, in `unit`.
    pub error: f64,
    /// The tolerance, in `unit`.
    pub limit: f64,
    /// Unit of `error` and `limit`.
    pub unit: &'static str,
}

impl TruthCheck {
    /// Whether the error is inside the tolerance.
    pub fn passed(&self) -> bool {
        self.error < self.limit
    }
}

/// Every compared value of `cal` against `truth`, with the issues' tolerances; the projection
/// error is held to `projection_limit_px` (the figure is for 960 px).
pub fn compare_with_truth(
    truth: &UnitCalibration,
    cal: &UnitCalibration,
    projection_limit_px: f64,
) -> Vec<TruthCheck> {
    let mut out = Vec::new();
    let mut push = |name: String, error: f64, limit: f64, unit: &'static str| {
        out.push(TruthCheck {
            name,
            error,
            limit,
            unit,
        });
    };
    for t in &truth.lenses {
        let l = cal.lens(&t.name).unwrap();
        let (tp, lp) = (t.intrinsics.params(), l.intrinsics.params());
        let n = &t.name;
        push(
            format!("{n}.fx"),
            (lp[0] / tp[0] - 1.0).abs() * 100.0,
            FOCAL_REL * 100.0,
            "%",
        );
        push(
            format!("{n}.fy"),
            (lp[1] / tp[1] - 1.0).abs() * 100.0,
            FOCAL_REL * 100.0,
            "%",
        );
        push(
            format!("{n}.cx"),
            (lp[2] - tp[2]).abs(),
            PRINCIPAL_POINT_PX,
            "px",
        );
        push(
            format!("{n}.cy"),
            (lp[3] - tp[3]).abs(),
            PRINCIPAL_POINT_PX,
            "px",
        );
        let proj = projection_rms(
            &t.camera().unwrap(),
            &l.camera().unwrap(),
            PROJECTION_FIELD_RAD,
        );
        push(format!("{n}.projection"), proj, projection_limit_px, "px");
        let (xt, xl) = (t.cam_from_imu().unwrap(), l.cam_from_imu().unwrap());
        push(
            format!("{n}.cam_from_imu.rotation"),
            (xt.rotation.inverse() * xl.rotation).angle().to_degrees(),
            ROTATION_DEG,
            "deg",
        );
        push(
            format!("{n}.cam_from_imu.translation"),
            (xt.translation.vector - xl.translation.vector).norm() * 1e3,
            TRANSLATION_M * 1e3,
            "mm",
        );
        push(
            format!("{n}.time_shift"),
            (t.time_shift_s.unwrap() - l.time_shift_s.unwrap()).abs() * 1e3,
            TIME_SHIFT_S * 1e3,
            "ms",
        );
    }
    let (ti, ci) = (truth.imu.as_ref().unwrap(), cal.imu.as_ref().unwrap());
    for (name, t, c, tol) in [
        (
            "imu.gyroscope_noise_density",
            ti.gyroscope_noise_density,
            ci.gyroscope_noise_density,
            NOISE_DENSITY_REL,
        ),
        (
            "imu.accelerometer_noise_density",
            ti.accelerometer_noise_density,
            ci.accelerometer_noise_density,
            NOISE_DENSITY_REL,
        ),
        (
            "imu.gyroscope_random_walk",
            ti.gyroscope_random_walk,
            ci.gyroscope_random_walk,
            RANDOM_WALK_REL,
        ),
        (
            "imu.accelerometer_random_walk",
            ti.accelerometer_random_walk,
            ci.accelerometer_random_walk,
            RANDOM_WALK_REL,
        ),
    ] {
        push(name.into(), (c / t - 1.0).abs() * 100.0, tol * 100.0, "%");
    }
    for d in &cal.av_delays {
        let t = truth.av_delays.iter().find(|t| t.mode == d.mode).unwrap();
        push(
            format!("av_delay.{}", d.mode),
            (d.delay_s - t.delay_s).abs() * 1e3,
            AV_DELAY_S * 1e3,
            "ms",
        );
    }
    out
}

/// The checks as aligned text lines, `ok` or `FAIL` each.
pub fn describe(checks: &[TruthCheck]) -> String {
    checks
        .iter()
        .map(|c| {
            format!(
                "  {:<32} {:>9.4} {:<3} (limit {} {}) {}",
                c.name,
                c.error,
                c.unit,
                c.limit,
                c.unit,
                if c.passed() { "ok" } else { "FAIL" }
            )
        })
        .collect::<Vec<_>>()
        .join("\n")
}
