//! The episode pipeline behind `kiwi run`: from a session folder to both hands' tool-tip
//! trajectories with per-frame quality (paper §4, `fig:pipeline`).
//!
//! - [`graph`]: the stages and what each reads (maps, metric recovery and placement once per
//!   session from its map episode; sync, localization, observations, fusion, gripper and
//!   outputs per episode);
//! - [`stage`]: the one stage mechanism (manifests with input digests, current/stale checks,
//!   atomic replacement of a stage's folder);
//! - [`stages`]: each stage's inputs, version, parameters and body;
//! - [`runner`]: executes the graph in parallel and reports per stage and per episode;
//! - [`status`]: `kiwi status`;
//! - [`digests`]: input files' digests, remembered while a file is unchanged.
//!
//! The algorithms live in the stage modules named as the paper names them: [`crate::sync`],
//! [`crate::vision`], [`crate::metric`], [`crate::placement`], [`crate::observations`],
//! [`crate::fusion`], [`crate::gripper`], [`crate::outputs`] and [`crate::quality`].

pub mod context;
pub mod digests;
pub mod graph;
pub mod runner;
pub mod stage;
pub mod stages;
pub mod status;

pub use context::SessionContext;
pub use runner::{RunOptions, RunReport, run};
