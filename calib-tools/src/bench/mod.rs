//! The jaw bench: a Feetech serial-bus servo on the jaw hinge serves as an encoder to validate
//! the gripper opening measured from the wrist video (paper §4.3.1).
//!
//! [`protocol`] frames and checks packets, [`servo`] runs transactions on a port, [`record`]
//! logs the encoder at a steady rate through faults and unplugs, [`fake`] is a simulated servo
//! on a pseudo-terminal, [`compare`] aligns the encoder log with the vision estimate and
//! reports the error, [`cli`] holds the `kiwi-calib bench` commands.

pub mod cli;
pub mod compare;
pub mod error;
pub mod fake;
pub mod protocol;
pub mod record;
pub mod servo;

pub use error::BenchError;
