//! Fisheye visual mapping and localization (issue 10, paper §4.2).
//!
//! Everything downstream of feature detection works on unit bearing vectors from the lens's
//! [`kiwi_core::camera::CameraModel`], so observations beyond 90° off-axis are first-class.
//!
//! - [`geometry`]: residuals on the unit sphere, two-view relative pose (8-point RANSAC on
//!   bearings), absolute pose (P3P RANSAC + robust refinement), triangulation.
//! - [`ba`]: robust bundle adjustment with tangent-plane residuals and a Schur complement
//!   solved with faer.
//! - [`align`]: Umeyama Sim(3) alignment of trajectories and absolute trajectory error.
//! - [`features`]: ORB on raw fisheye images with masks, descriptor matching, KLT tracking.
//! - [`frontend`]: frame-to-frame KLT tracking topped up with ORB keypoints → bearing tracks.
//! - [`mapping`]: incremental mapping on bearing tracks (two-view init, P3P per frame,
//!   keyframes, triangulation, local and global robust BA).
//! - [`loop_closure`]: loop detection by place recognition, geometric verification, Sim(3)
//!   pose-graph correction and landmark fusion over a finished reconstruction.
//! - [`map`]: the versioned `.kmap` file and its export from a reconstruction.
//! - [`place`]: place recognition over keyframes (bag of binary words learned from the map).
//! - [`quality`]: the mapper's own check of a finished map (forward against reversed mapping).
//! - [`localize`]: every frame against a frozen map (KLT tracking with guided and correlation
//!   top-ups, relocalization by place recognition, strict acceptance).
//! - [`runs`]: the runs of a localized stream and whether they join (a look-alike place is
//!   withdrawn).
//! - [`episode`]: prepared-episode drivers behind `kiwi map` and `kiwi localize`.
//!
//! Determinism: every random choice comes from a seeded ChaCha8 generator and every reduction
//! runs in a fixed order, so results are bit-identical across runs and thread counts.

pub mod align;
pub mod ba;
pub mod episode;
pub mod features;
pub mod frontend;
pub mod geometry;
pub mod localize;
pub mod loop_closure;
pub mod map;
pub mod mapping;
pub mod place;
pub mod quality;
pub mod runs;
