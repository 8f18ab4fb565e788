//! File formats of the estimation stages: the CSV tables they exchange ([`tables`]), their JSON
//! results ([`results`]) and what they read of a unit calibration ([`calibration`]).

pub mod calibration;
pub mod results;
pub mod tables;
