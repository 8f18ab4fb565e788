//! The one error type of `kiwi-calib`.

/// Errors raised by the calibration tools.
#[derive(Debug, thiserror::Error)]
pub enum CalibError {
    /// An error from the shared core (file formats, validation).
    #[error(transparent)]
    Core(#[from] kiwi_core::CoreError),
    /// An input cannot be used; the message says what is wrong and what to do.
    #[error("{path}: {message}")]
    Input {
        /// The file or folder.
        path: std::path::PathBuf,
        /// What is wrong and the fix.
        message: String,
    },
    /// A chart could not be drawn or written (boxed: the variant would otherwise make every
    /// result of this crate larger).
    #[error(transparent)]
    Plot(Box<kiwi_plot::PlotError>),
    /// A servo-bench failure (protocol, device, bench files).
    #[error(transparent)]
    Bench(#[from] crate::bench::BenchError),
    /// A bug in the calibration tools.
    #[error("internal error: {0}")]
    Internal(String),
}

/// Shorthand for results in this crate.
pub type Result<T> = std::result::Result<T, CalibError>;

impl From<kiwi_plot::PlotError> for CalibError {
    fn from(e: kiwi_plot::PlotError) -> Self {
        Self::Plot(Box::new(e))
    }
}
