//! `kiwi-calib`: certify a KIWI camera unit.
//!
//! Modules grow with the calibration steps of ARCHITECTURE.md §5 (targets, intrinsics,
//! imu_noise, cam_imu, av_delay, bench, certify). Today: [`export`], which turns a unit's
//! `calibration.json` into the files other tools read and imports Kalibr calibrations;
//! [`qr_clock`], the QR-clock rig's display video; [`av_delay`], the rig's analysis.

pub mod allan;
pub mod av_delay;
pub mod bench;
pub mod cam_imu;
pub mod certify;
pub mod detect;
pub mod error;
pub mod export;
pub mod hardware;
pub mod import;
pub mod intrinsics;
pub mod lens_cli;
pub mod qr_clock;
pub mod target;

pub use error::CalibError;
