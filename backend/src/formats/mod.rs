//! File formats of the estimation stages: the CSV tables they exchange ([`tables`]), their JSON
//! results ([`results`]), what they read of a unit calibration ([`calibration`]) and the video
//! of a video-backed lens stream ([`video`]).

pub mod calibration;
pub mod results;
pub mod tables;
pub mod video;
