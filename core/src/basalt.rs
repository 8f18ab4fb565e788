//! Basalt's `calibration.json` export.
//!
//! Basalt stores `T_imu_cam` (the inverse of our `cam_from_imu`) as `px, py, pz, qx, qy, qz, qw`,
//! intrinsics as `kb4` or `ds` objects, continuous-time noise densities as `*_noise_std` and
//! bias random walks as `*_bias_std`, and `cam_time_offset_ns` with `t_imu = t_cam + offset`.

use serde_json::{Value, json};

use crate::artifact::{Intrinsics, UnitCalibration};
use crate::error::{CoreError, Result};

/// Basalt `calibration.json` text for a unit. Every lens needs `cam_from_imu` and the unit
/// needs an IMU noise model, since Basalt's file has no way to leave them out.
pub fn calibration_json(calibration: &UnitCalibration) -> Result<String> {
    let imu = calibration.imu.as_ref().ok_or_else(|| {
        CoreError::invalid_value(
            "imu",
            "an IMU noise model",
            "none",
            "run `kiwi-calib imu-noise` before exporting to Basalt",
        )
    })?;
    let mut t_imu_cam = Vec::new();
    let mut intrinsics = Vec::new();
    let mut resolution = Vec::new();
    for (i, lens) in calibration.lenses.iter().enumerate() {
        let cam_from_imu = lens.cam_from_imu().ok_or_else(|| {
            CoreError::invalid_value(
                format!("lenses[{i}].cam_from_imu"),
                "a camera–IMU extrinsic",
                "none",
                "run `kiwi-calib cam-imu` before exporting to Basalt",
            )
        })?;
        let imu_from_cam = cam_from_imu.inverse();
        let q = imu_from_cam.rotation.quaternion();
        let p = imu_from_cam.translation.vector;
        t_imu_cam.push(
            json!({"px": p.x, "py": p.y, "pz": p.z, "qx": q.i, "qy": q.j, "qz": q.k, "qw": q.w}),
        );
        intrinsics.push(match lens.intrinsics {
            Intrinsics::Kb4 { fx, fy, cx, cy, k1, k2, k3, k4 } => json!({
                "camera_type": "kb4",
                "intrinsics": {"fx": fx, "fy": fy, "cx": cx, "cy": cy, "k1": k1, "k2": k2, "k3": k3, "k4": k4}
            }),
            Intrinsics::DoubleSphere { fx, fy, cx, cy, xi, alpha } => json!({
                "camera_type": "ds",
                "intrinsics": {"fx": fx, "fy": fy, "cx": cx, "cy": cy, "xi": xi, "alpha": alpha}
            }),
        });
        resolution.push(json!([lens.resolution[0], lens.resolution[1]]));
    }
    // Basalt has one camera time offset; use the first lens's (both lenses share the sensor clock).
    let offset_ns = calibration
        .lenses
        .first()
        .and_then(|l| l.time_shift_s)
        .unwrap_or(0.0)
        * 1e9;
    let triple = |v: f64| json!([v, v, v]);
    let value: Value = json!({
        "value0": {
            "T_imu_cam": t_imu_cam,
            "intrinsics": intrinsics,
            "resolution": resolution,
            "calib_accel_bias": [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
            "calib_gyro_bias": [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
            "imu_update_rate": imu.rate_hz,
            "accel_noise_std": triple(imu.accelerometer_noise_density),
            "gyro_noise_std": triple(imu.gyroscope_noise_density),
            "accel_bias_std": triple(imu.accelerometer_random_walk),
            "gyro_bias_std": triple(imu.gyroscope_random_walk),
            "cam_time_offset_ns": offset_ns.round() as i64,
            "vignette": []
        }
    });
    serde_json::to_string_pretty(&value).map_err(|e| {
        CoreError::invalid_value(
            "basalt",
            "serializable values",
            e.to_string(),
            "validate the calibration first",
        )
    })
}
