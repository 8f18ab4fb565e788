//! The paper's evaluations as commands a lab runs on its own sessions (§5): the map-sharing
//! ablation ([`ablation`], `tab:eval-map-sharing`) and the marker-referenced pose accuracy
//! ([`markers`]).

pub mod ablation;
pub mod markers;

/// Folder of a session's evaluation records, beside `episodes/`.
pub const EVALUATION_DIR: &str = "evaluation";
