//! What the estimators read of a unit calibration (`calibration.json`): a lens's `cam_from_imu`
//! and time shift, and the IMU noise densities.

use std::path::Path;

use kiwi_core::artifact::UnitCalibration;
use kiwi_core::geometry::Pose;

use crate::error::{BackendError, Result};
use crate::fusion::preint::ImuParams;

/// Standard gravity used for fusion in a z-up scene (m/s²).
pub const GRAVITY_M_S2: f64 = 9.81;

fn input(path: &Path, message: String) -> BackendError {
    BackendError::Input {
        path: path.to_path_buf(),
        message,
    }
}

/// What the estimators need of one lens of a unit artifact.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LensImuCalibration {
    /// The lens's `cam_from_imu`.
    pub cam_from_imu: Pose,
    /// Kalibr time shift: `t_imu = t_cam + time_shift_s`.
    pub time_shift_s: f64,
    /// IMU noise densities `[gn, gw, an, aw]`, when the artifact has an `imu` block.
    pub imu_noise: Option<[f64; 4]>,
}

/// Load `lens`'s camera–IMU calibration and the IMU noise from a unit `calibration.json`.
pub fn load_lens_calibration(path: &Path, lens: &str) -> Result<LensImuCalibration> {
    lens_calibration(&UnitCalibration::load(path)?, path, lens)
}

/// `lens`'s camera–IMU calibration and the IMU noise from a loaded unit calibration (`path`,
/// where it was read, for the errors).
pub fn lens_calibration(
    cal: &UnitCalibration,
    path: &Path,
    lens: &str,
) -> Result<LensImuCalibration> {
    let entry = cal.lens(lens).ok_or_else(|| {
        let names: Vec<&str> = cal.lenses.iter().map(|l| l.name.as_str()).collect();
        input(
            path,
            format!("no lens `{lens}`; the unit has {names:?}; pass --lens"),
        )
    })?;
    let cam_from_imu = entry.cam_from_imu().ok_or_else(|| {
        input(
            path,
            format!("lens `{lens}` has no cam_from_imu; run the camera-IMU calibration first"),
        )
    })?;
    Ok(LensImuCalibration {
        cam_from_imu,
        time_shift_s: entry.time_shift_s.unwrap_or(0.0),
        imu_noise: cal.imu.as_ref().map(|imu| {
            [
                imu.gyroscope_noise_density,
                imu.gyroscope_random_walk,
                imu.accelerometer_noise_density,
                imu.accelerometer_random_walk,
            ]
        }),
    })
}

/// Rolling-shutter readout of a full frame (s) in the recording mode a camera recorded in: the
/// mode of that name in the unit calibration, else one with the same frame rate and a known
/// readout; `None` when the calibration knows neither.
pub fn readout_for(calibration: &UnitCalibration, mode: &str, fps: f64) -> Option<f64> {
    /// Frame rates of two modes closer than this are the same rate (29.97 vs 30 are not).
    const SAME_RATE_HZ: f64 = 0.01;
    let modes = &calibration.recording_modes;
    modes
        .iter()
        .find(|m| m.name == mode && m.readout_time_s.is_some())
        .or_else(|| {
            modes
                .iter()
                .find(|m| (m.fps - fps).abs() < SAME_RATE_HZ && m.readout_time_s.is_some())
        })
        .and_then(|m| m.readout_time_s)
}

/// Time from a frame's timestamp (its first row) to its centre row's exposure (s): half the
/// readout of the recording mode (see [`readout_for`]); `None` when the calibration knows no
/// readout for it.
pub fn exposure_centre_delay(calibration: &UnitCalibration, mode: &str, fps: f64) -> Option<f64> {
    readout_for(calibration, mode, fps).map(|r| 0.5 * r)
}

/// IMU parameters from explicit densities, else the calibration's, else an error naming both.
pub fn imu_params(
    explicit: Option<[f64; 4]>,
    calibration: Option<(&Path, &LensImuCalibration)>,
) -> Result<ImuParams> {
    let noise = match (explicit, calibration) {
        (Some(n), _) => n,
        (None, Some((path, cal))) => cal.imu_noise.ok_or_else(|| {
            input(
                path,
                "no `imu` noise block; calibrate the IMU (kiwi-calib imu-noise) or pass \
                 --imu-noise"
                    .into(),
            )
        })?,
        (None, None) => {
            return Err(BackendError::Estimation(
                "without --calibration, give the IMU noise as --imu-noise GN,GW,AN,AW".into(),
            ));
        }
    };
    let [gn, gw, an, aw] = noise;
    Ok(ImuParams::from_densities(gn, gw, an, aw, GRAVITY_M_S2))
}
