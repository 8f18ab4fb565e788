//! `kiwi-backend`: reconstruct episodes recorded on certified units.
//!
//! One module per stage, named as the paper names it: [`sync`] (§4.1), [`vision`] (maps and
//! localization, §4.2), [`metric`] (metric recovery), [`placement`] (eq. 2),
//! [`observations`] (eq. 3), [`fusion`] (eq. 4), [`gripper`] (§4.3.1) and [`outputs`] with
//! [`quality`] (the deliverables and how far to trust them). [`pipeline`] runs them as one
//! graph (`kiwi run`); [`formats`] holds the files the stages exchange; [`frames`] reads a lens
//! stream's frames (images or video) for every stage; [`ingest`] turns camera files into a
//! prepared episode; [`inspect`] checks a session before anything runs; [`export`] writes the outputs as datasets
//! (LeRobot v3.0, UMI, KIWI's sidecar); [`report`] draws a session's report page.

pub mod batch;
pub mod error;
pub mod evaluate;
pub mod export;
pub mod floor;
pub mod formats;
pub mod frames;
pub mod fusion;
pub mod gripper;
pub mod head;
pub mod ingest;
pub mod inspect;
pub mod metric;
pub mod observations;
pub mod outputs;
pub mod pipeline;
pub mod placement;
pub mod quality;
pub mod report;
pub mod sync;
pub mod vision;

pub use error::BackendError;
