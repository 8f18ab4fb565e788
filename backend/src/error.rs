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
    /// A batch plan or the cluster scheduler (what failed and what to do).
    #[error("{0}")]
    Batch(String),
    /// An input file cannot be used.
    #[error("{path}: {message}")]
    Input {
        /// The file.
        path: std::path::PathBuf,
        /// What is wrong and what to do.
        message: String,
    },
    /// An Insta360 recording has no gyro record (some X5 firmware versions write none).
    #[error(
        "{file}: no gyro record in the file's metadata trailer ({model}, firmware {firmware}). Some \
         Insta360 X5 firmware versions record video without IMU samples; without them KIWI \
         cannot recover scale and gravity. Update the camera's firmware and record again, or give \
         an IMU log of the same recording with --{camera}-imu FILE (kiwi ingest's generic path)"
    )]
    NoGyroRecord {
        /// The recording.
        file: std::path::PathBuf,
        /// Camera model as the file states it.
        model: String,
        /// Firmware as the file states it.
        firmware: String,
        /// Camera slot (`left`, `right`, `head`).
        camera: String,
    },
    /// A recording has no audio track (the cameras are synchronized by their audio).
    #[error(
        "{file}: no audio track. KIWI places the cameras on one timeline from their sound, so \
         every camera must record audio: check that the camera's microphone is on for this \
         mode (some modes, e.g. timelapse and high-frame-rate slow motion, record none) and \
         record again"
    )]
    MissingAudio {
        /// The recording.
        file: std::path::PathBuf,
    },
    /// A lens track's frame times are not evenly spaced.
    #[error(
        "{file}, video track {track}: variable frame rate: frame {frame} comes {interval_s:.6} s \
         after the one before, the nominal period is {period_s:.6} s. KIWI needs every frame \
         of a lens at a constant rate (dropped frames or a variable-rate mode break the camera \
         and IMU timing); record in a fixed-frame-rate mode and check the card's write speed"
    )]
    VariableFrameRate {
        /// The recording.
        file: std::path::PathBuf,
        /// Video track index in the file.
        track: usize,
        /// First frame whose interval is off.
        frame: usize,
        /// Its interval (s).
        interval_s: f64,
        /// The nominal frame period (s).
        period_s: f64,
    },
    /// A recording lacks a lens track the camera slot needs.
    #[error(
        "{files}: {found} lens video track(s) found, the {camera} camera needs {expected} \
         ({lenses}). {fix}"
    )]
    MissingLensTrack {
        /// The recording's files.
        files: String,
        /// Camera slot (`left`, `right`, `head`).
        camera: String,
        /// Lens tracks found.
        found: usize,
        /// Lens tracks needed.
        expected: usize,
        /// The lens names needed.
        lenses: String,
        /// What to do.
        fix: String,
    },
    /// A dataset export cannot be made as asked (what is wrong and what to do).
    #[error("{0}")]
    Export(String),
    /// A chart of the session report could not be drawn (boxed: the error stays small).
    #[error(transparent)]
    Plot(Box<kiwi_plot::PlotError>),
    /// A computer-vision step failed (feature extraction, geometry, bundle adjustment, maps).
    #[error("{context}: {message}")]
    Vision {
        /// The step or file.
        context: String,
        /// What is wrong and what to do.
        message: String,
    },
}

impl From<kiwi_plot::PlotError> for BackendError {
    fn from(e: kiwi_plot::PlotError) -> Self {
        Self::Plot(Box::new(e))
    }
}

/// Shorthand for results in this crate.
pub type Result<T> = std::result::Result<T, BackendError>;
