//! Certification policy: the threshold of every check, with built-in defaults that a lab
//! overrides with a TOML file (`--policy policy.toml`; any subset of the fields below).

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::error::{CalibError, Result};

/// Thresholds of every certification check.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields, default)]
pub struct Policy {
    /// Lens intrinsics.
    pub intrinsics: IntrinsicsPolicy,
    /// IMU noise from the static log.
    pub imu_noise: ImuNoisePolicy,
    /// Camera–IMU extrinsics and time shifts.
    pub cam_imu: CamImuPolicy,
    /// A/V delay from the QR-clock rig.
    pub av_delay: AvDelayPolicy,
    /// What counts as a change against a previous certification.
    pub compare: ComparePolicy,
}

/// Intrinsics checks (per lens).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct IntrinsicsPolicy {
    /// Fewest views showing the board (with at least 8 corners each).
    pub min_views: usize,
    /// Largest RMS reprojection error (px, per axis).
    pub max_rms_px: f64,
    /// Smallest share of the lens's image circle with corners (8 × 8 cells inside the circle).
    pub min_coverage: f64,
    /// Largest relative standard deviation of the focal lengths.
    pub max_focal_rel_std: f64,
    /// Largest standard deviation of the principal point (px).
    pub max_principal_point_std_px: f64,
}

impl Default for IntrinsicsPolicy {
    fn default() -> Self {
        Self {
            // Kalibr's guidance for fisheyes is a few dozen views; 15 still separates focal
            // length, distortion and board distance over the whole field of view.
            min_views: 15,
            // The detector's corner noise is ~0.1–0.3 px; 0.5 px RMS means a bad model or views.
            max_rms_px: 0.5,
            // Half the image circle covered keeps the periphery (where 190° lenses differ) fitted.
            min_coverage: 0.5,
            // 0.1 % of the focal length is ~0.3 px at the image edge of a 960 px lens.
            max_focal_rel_std: 1e-3,
            // Half a pixel keeps the lens-axis direction within ~0.1°.
            max_principal_point_std_px: 0.5,
        }
    }
}

/// IMU-noise checks.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ImuNoisePolicy {
    /// Shortest static log (s).
    pub min_duration_s: f64,
    /// Largest deviation of a 1-s gyro mean from its ±30 s median (rad/s): more is motion.
    pub max_gyro_motion_rad_s: f64,
    /// Largest deviation of a 1-s accelerometer mean from its ±30 s median (m/s²).
    pub max_accel_motion_m_s2: f64,
    /// Largest relative standard deviation of the white-noise densities (worst axis).
    pub max_white_noise_rel_std: f64,
    /// Largest relative standard deviation of the bias random walks (worst axis).
    pub max_random_walk_rel_std: f64,
    /// Largest weighted RMS of the Allan fit's residuals (≈ 1 for a good fit; worst axis).
    pub max_fit_weighted_rms: f64,
}

impl Default for ImuNoisePolicy {
    fn default() -> Self {
        Self {
            // The bias random walk only shows at averaging times of minutes to an hour.
            min_duration_s: 3600.0,
            // The same limits as `imu-noise`'s own static check (a touched bench).
            max_gyro_motion_rad_s: 0.02,
            max_accel_motion_m_s2: 0.1,
            // White noise is determined to a few percent by any log over a minute.
            max_white_noise_rel_std: 0.05,
            // `imu-noise` calls a term poorly determined beyond 25 %.
            max_random_walk_rel_std: 0.25,
            // The five-term model explains a clean log to ~1 σ per averaging time.
            max_fit_weighted_rms: 3.0,
        }
    }
}

/// Camera–IMU checks (per lens, and lens to lens).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CamImuPolicy {
    /// Largest corner reprojection RMS (px) of the joint fit.
    pub max_rms_px: f64,
    /// Largest rotation standard deviation (deg, worst axis).
    pub max_rotation_std_deg: f64,
    /// Largest translation standard deviation (m, worst axis).
    pub max_translation_std_m: f64,
    /// Largest time-shift standard deviation (s).
    pub max_time_shift_std_s: f64,
    /// Nominal second-lens-from-first-lens rotation (rotation vector, deg) of the body.
    pub nominal_pair_rotation_deg: [f64; 3],
    /// Nominal second-lens-from-first-lens translation (m).
    pub nominal_pair_translation_m: [f64; 3],
    /// Largest rotation of the measured lens-to-lens extrinsic away from nominal (deg).
    pub max_pair_rotation_deviation_deg: f64,
    /// Largest distance of the measured lens-to-lens translation from nominal (m).
    pub max_pair_translation_deviation_m: f64,
}

impl Default for CamImuPolicy {
    fn default() -> Self {
        Self {
            // Rolling-shutter, motion-blurred excitation frames fit to well under a pixel.
            max_rms_px: 1.0,
            // The extrinsic tolerances are 0.1° and 2 mm: the estimate must be surer.
            max_rotation_std_deg: 0.05,
            max_translation_std_m: 0.001,
            // ...and 0.2 ms on the time shift.
            max_time_shift_std_s: 1e-4,
            // X5 body: the rear lens looks backwards (180° about y), 24 mm behind the front one.
            nominal_pair_rotation_deg: [0.0, 180.0, 0.0],
            nominal_pair_translation_m: [0.0, 0.0, -0.024],
            // Assembly tolerance of a lens module: a few degrees and millimetres.
            max_pair_rotation_deviation_deg: 3.0,
            max_pair_translation_deviation_m: 0.005,
        }
    }
}

/// A/V-delay checks (per recording mode).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AvDelayPolicy {
    /// Fewest rig recordings per mode (a single recording cannot show its repeatability).
    pub min_repeats: usize,
    /// Fewest periodic rig chirps heard in a recording.
    pub min_chirps: usize,
    /// Largest spread (max − min) of the delay across repeats (s).
    pub max_spread_s: f64,
    /// Largest standard error of a mode's delay (s).
    pub max_std_s: f64,
}

impl Default for AvDelayPolicy {
    fn default() -> Self {
        Self {
            min_repeats: 2,
            // Chirps come every 0.5 s: 10 is 5 s of audible rig.
            min_chirps: 10,
            // Audio-based sync needs the delay to ~1 ms; repeats must agree to 2 ms.
            max_spread_s: 0.002,
            max_std_s: 0.001,
        }
    }
}

/// When a parameter counts as changed against a previous certification: its difference
/// exceeds `sigmas` combined standard deviations *and* the parameter's practical floor.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ComparePolicy {
    /// Combined standard deviations a change must exceed.
    pub sigmas: f64,
    /// Floor for focal lengths and the principal point (px).
    pub min_change_px: f64,
    /// Floor for dimensionless lens parameters (k1..k4, xi, alpha).
    pub min_change_distortion: f64,
    /// Floor for camera–IMU rotations (deg).
    pub min_change_rotation_deg: f64,
    /// Floor for camera–IMU translations (m).
    pub min_change_translation_m: f64,
    /// Floor for time shifts (s).
    pub min_change_time_shift_s: f64,
    /// Floor for IMU noise densities (relative).
    pub min_change_imu_rel: f64,
    /// Floor for A/V delays (s).
    pub min_change_av_delay_s: f64,
}

impl Default for ComparePolicy {
    fn default() -> Self {
        Self {
            // Dozens of parameters are compared: 4 σ keeps chance alarms below 1 in 300 sets.
            sigmas: 4.0,
            // Below these a change does not matter downstream, however certain it is.
            min_change_px: 0.1,
            min_change_distortion: 5e-4,
            min_change_rotation_deg: 0.05,
            min_change_translation_m: 5e-4,
            min_change_time_shift_s: 1e-4,
            min_change_imu_rel: 0.15,
            min_change_av_delay_s: 5e-4,
        }
    }
}

impl Policy {
    /// Read a policy TOML file; missing fields keep their defaults.
    pub fn load(path: &Path) -> Result<Self> {
        let text = kiwi_core::io::read_text(path)?;
        let policy: Self = toml::from_str(&text).map_err(|e| CalibError::Input {
            path: path.to_path_buf(),
            message: format!(
                "not a certification policy: {e}; see docs/certify.md for the fields \
                 (`kiwi-calib certify --print-policy` prints the defaults)"
            ),
        })?;
        policy.validate(path)?;
        Ok(policy)
    }

    /// The policy as TOML text.
    pub fn to_toml(&self) -> Result<String> {
        toml::to_string_pretty(self)
            .map_err(|e| CalibError::Internal(format!("policy does not serialize: {e}")))
    }

    fn validate(&self, path: &Path) -> Result<()> {
        let values = [
            ("intrinsics.max_rms_px", self.intrinsics.max_rms_px),
            ("intrinsics.min_coverage", self.intrinsics.min_coverage),
            (
                "intrinsics.max_focal_rel_std",
                self.intrinsics.max_focal_rel_std,
            ),
            ("imu_noise.min_duration_s", self.imu_noise.min_duration_s),
            ("cam_imu.max_rms_px", self.cam_imu.max_rms_px),
            ("av_delay.max_spread_s", self.av_delay.max_spread_s),
            ("compare.sigmas", self.compare.sigmas),
        ];
        for (name, v) in values {
            if !(v.is_finite() && v >= 0.0) {
                return Err(CalibError::Input {
                    path: path.to_path_buf(),
                    message: format!("{name}: expected a finite value ≥ 0, found {v}"),
                });
            }
        }
        Ok(())
    }
}
