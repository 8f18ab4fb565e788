//! The paper's evaluations as commands a lab runs on its own sessions (§5): the map-sharing
//! ablation ([`ablation`], `tab:eval-map-sharing`).

pub mod ablation;

/// Folder of a session's evaluation records, beside `episodes/`.
pub const EVALUATION_DIR: &str = "evaluation";
