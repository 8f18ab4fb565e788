//! The one error type of `kiwi-core`.
//!
//! Every variant says what was expected, what was found, where, and what to do about it,
//! so a binary can print the chain and a person can act on it without reading code.

use std::path::PathBuf;

/// Errors raised by `kiwi-core` when reading, validating or writing KIWI data.
#[derive(Debug, thiserror::Error)]
pub enum CoreError {
    /// A file or folder could not be read or written.
    #[error("{action} {path}: {}", describe_io(source))]
    Io {
        /// What was being done ("reading", "writing", "creating folder").
        action: &'static str,
        /// The file or folder concerned.
        path: PathBuf,
        /// The operating system's error.
        #[source]
        source: std::io::Error,
    },

    /// A file could not be parsed in its format (JSON, TOML, YAML, CSV).
    #[error("{path}: cannot parse as {format} at `{field}`: {message}; {fix}")]
    Parse {
        /// The file concerned (or a description such as `<memory>`).
        path: PathBuf,
        /// The format that was expected.
        format: &'static str,
        /// Path of the offending field inside the document (`.` for the root).
        field: String,
        /// The parser's message.
        message: String,
        /// What the user can do.
        fix: String,
    },

    /// A value was read but is not acceptable.
    #[error("{path}: field `{field}`: expected {expected}, found {found}; {fix}")]
    Invalid {
        /// The file concerned (or `<memory>` for values built in code).
        path: PathBuf,
        /// Path of the offending field, e.g. `lenses[0].intrinsics.fx` or `line 12, column t`.
        field: String,
        /// What a valid value looks like.
        expected: String,
        /// What was found instead.
        found: String,
        /// What the user can do.
        fix: String,
    },

    /// A required file of a layout is missing.
    #[error("{path}: missing; {fix}")]
    Missing {
        /// The file or folder that should exist.
        path: PathBuf,
        /// What the user can do.
        fix: String,
    },

    /// A folder that must never be overwritten already exists.
    #[error("{path}: already exists and is never overwritten; {fix}")]
    WouldOverwrite {
        /// The folder that exists.
        path: PathBuf,
        /// What the user can do.
        fix: String,
    },
}

/// An operating-system error in words a user can act on.
pub fn describe_io(e: &std::io::Error) -> String {
    use std::io::ErrorKind;
    match e.kind() {
        ErrorKind::IsADirectory => {
            "it is a folder; expected a file (give the file inside it)".into()
        }
        ErrorKind::NotADirectory => "a part of the path is a file; expected a folder".into(),
        ErrorKind::NotFound => "no such file or folder; check the path".into(),
        ErrorKind::PermissionDenied => "permission denied; check the file's permissions".into(),
        ErrorKind::InvalidData => format!("not UTF-8 text ({e}); expected a text file"),
        _ => e.to_string(),
    }
}

impl CoreError {
    /// An [`CoreError::Invalid`] for a value that was built in memory rather than read from a file.
    pub fn invalid_value(
        field: impl Into<String>,
        expected: impl Into<String>,
        found: impl Into<String>,
        fix: impl Into<String>,
    ) -> Self {
        Self::Invalid {
            path: PathBuf::from("<memory>"),
            field: field.into(),
            expected: expected.into(),
            found: found.into(),
            fix: fix.into(),
        }
    }

    /// Replace the `<memory>` placeholder path of an [`CoreError::Invalid`] with a real file path.
    #[must_use]
    pub fn at_path(self, file: &std::path::Path) -> Self {
        match self {
            Self::Invalid {
                path,
                field,
                expected,
                found,
                fix,
            } if path.as_os_str() == "<memory>" => Self::Invalid {
                path: file.to_path_buf(),
                field,
                expected,
                found,
                fix,
            },
            other => other,
        }
    }

    /// The field path this error names, if it names one.
    pub fn field(&self) -> Option<&str> {
        match self {
            Self::Invalid { field, .. } | Self::Parse { field, .. } => Some(field),
            _ => None,
        }
    }
}

/// Shorthand for results in this crate.
pub type Result<T> = std::result::Result<T, CoreError>;
