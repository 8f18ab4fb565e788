//! State estimation: IMU preintegration and factors matching GTSAM 4.3, per-wrist
//! visual–inertial fusion on a chain-structured Levenberg–Marquardt solver, metric recovery of
//! visual maps and scene placement (paper §4.2, eqs. 2–4). See `docs/estimation.md`.

pub mod chain;
pub mod factors;
pub mod files;
pub mod fusion;
pub mod placement;
pub mod preint;
