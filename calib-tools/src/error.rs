//! The one error type of `kiwi-calib`.

/// Errors raised by the calibration tools.
#[derive(Debug, thiserror::Error)]
pub enum CalibError {
    /// An error from the shared core (file formats, validation).
    #[error(transparent)]
    Core(#[from] kiwi_core::CoreError),
}

/// Shorthand for results in this crate.
pub type Result<T> = std::result::Result<T, CalibError>;
