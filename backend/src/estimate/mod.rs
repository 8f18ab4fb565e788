//! State estimation: IMU preintegration and factors matching GTSAM 4.3, per-wrist
//! visual–inertial fusion on a chain-structured Levenberg–Marquardt solver, and scene placement
//! (paper §4.2, eqs. 2–4), and metric recovery of visual maps (scale, gravity, biases). See
//! `docs/estimation.md`.

pub mod chain;
pub mod factors;
pub mod files;
pub mod fusion;
pub mod metric;
pub mod placement;
pub mod preint;
pub mod stages;
