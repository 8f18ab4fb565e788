//! `kiwi-calib`: certify a KIWI camera unit.
//!
//! Modules grow with the calibration steps of ARCHITECTURE.md §5 (targets, intrinsics,
//! imu_noise, cam_imu, av_delay, bench, certify). Today: [`export`], which turns a unit's
//! `calibration.json` into the files other tools read, and imports Kalibr calibrations.

pub mod error;
pub mod export;

pub use error::CalibError;
