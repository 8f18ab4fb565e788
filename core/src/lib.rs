//! `kiwi-core`: the vocabulary every KIWI crate shares.
//!
//! - [`geometry`]: SO(3)/SE(3) exponential and logarithm, Jacobians, interpolation, robust
//!   rotation averaging, in the `a_from_b` convention.
//! - [`camera`]: fisheye camera models (KB4, Double Sphere) on unit bearing vectors.
//! - [`imu`]: IMU samples, validated series and the `imu.csv` format.
//! - [`artifact`]: the unit calibration set, with [`kalibr`] and [`basalt`] exports.
//! - [`layout`]: `session.toml` and the prepared-episode folder layout; [`video`] writes a
//!   video-backed lens stream (through the `ffmpeg` program).
//! - [`io`]: atomic writes, never-overwritten dated folders, hashes.
//! - [`args`]: checks of numbers given on command lines.
//! - [`tool`]: tool definitions; [`hardware`]: the hardware parameter file and what is
//!   generated from it (the OpenSCAD parameters, the tool definitions).
//! - [`audio`]: WAV decoding and resampling; [`fit`]: the robust line fit; [`rig`]: the QR-clock
//!   rig's contract.
//!
//! This crate has no OpenCV, no image decoding (video streams are decoded in the backend) and
//! no command-line code, so it builds in
//! seconds and everything else can depend on it. Conventions: `docs/conventions.md`.

pub mod args;
pub mod artifact;
pub mod audio;
pub mod basalt;
pub mod camera;
pub mod error;
pub mod fit;
pub mod geometry;
pub mod hardware;
pub mod head;
pub mod imu;
pub mod io;
pub mod kalibr;
pub mod layout;
pub mod rig;
pub mod tool;
pub mod video;

pub use error::{CoreError, Result};
