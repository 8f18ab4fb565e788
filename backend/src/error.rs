//! The one error type of `kiwi-backend`.

/// Errors raised by the reconstruction stages.
#[derive(Debug, thiserror::Error)]
pub enum BackendError {
    /// An error from the shared core (file formats, validation).
    #[error(transparent)]
    Core(#[from] kiwi_core::CoreError),
    /// State estimation cannot run on the given data (what is wrong and what to do).
    #[error("{0}")]
    Estimation(String),
    /// An input file cannot be used.
    #[error("{path}: {message}")]
    Input {
        /// The file.
        path: std::path::PathBuf,
        /// What is wrong and what to do.
        message: String,
    },
    /// A computer-vision step failed (feature extraction, geometry, bundle adjustment, maps).
    #[error("{context}: {message}")]
    Vision {
        /// The step or file.
        context: String,
        /// What is wrong and what to do.
        message: String,
    },
}

/// Shorthand for results in this crate.
pub type Result<T> = std::result::Result<T, BackendError>;
