//! State estimation: IMU preintegration and factors matching GTSAM 4.3, per-wrist
//! visual–inertial fusion on a chain-structured Levenberg–Marquardt solver, and scene placement
//! (paper §4.2, eqs. 2–4). Metric recovery of visual maps is not implemented yet. See
//! `docs/estimation.md`.

pub mod chain;
pub mod factors;
pub mod files;
pub mod fusion;
pub mod placement;
pub mod preint;
