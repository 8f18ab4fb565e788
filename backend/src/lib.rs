//! `kiwi-backend`: reconstruct episodes recorded on certified units.
//!
//! Stage modules (sync, vision, metric, placement, fusion, gripper, head, ground, export,
//! splat, report) arrive with their issues. Today: [`inspect`], which checks that a session and
//! its prepared episodes are complete before any stage runs, and [`sync`], audio time
//! synchronisation.

pub mod error;
pub mod estimate;
pub mod gripper;
pub mod inspect;
pub mod sync;
pub mod vision;

pub use error::BackendError;
