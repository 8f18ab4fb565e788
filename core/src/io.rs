//! File helpers shared by every crate: atomic writes, never-overwritten dated folders, hashes.
//!
//! Every artifact KIWI writes goes through [`write_atomic_with`]: the content lands in a
//! temporary file in the same folder, is flushed to disk, then renamed over the target, so a
//! crash or a full disk never leaves a half-written file behind.

use std::io::Write;
use std::path::{Path, PathBuf};

use sha2::{Digest, Sha256};

use crate::error::{CoreError, Result};

/// How many `-N` suffixes [`create_dated_dir`] tries before giving up (a unit certified more
/// than this many times on one day points at a script in a loop).
const MAX_SAME_DAY_FOLDERS: u32 = 999;

/// Write a file atomically: `fill` writes the content into a temporary file next to `path`,
/// which is synced and renamed onto `path` only if `fill` succeeds.
pub fn write_atomic_with<F>(path: &Path, fill: F) -> Result<()>
where
    F: FnOnce(&mut std::fs::File) -> std::io::Result<()>,
{
    let io_err = |action, source| CoreError::Io {
        action,
        path: path.to_path_buf(),
        source,
    };
    let parent = path
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    std::fs::create_dir_all(parent).map_err(|e| io_err("creating the folder of", e))?;
    let file_name = path
        .file_name()
        .map_or_else(|| "out".into(), |n| n.to_string_lossy().into_owned());
    let tmp = parent.join(format!(".{file_name}.{}.tmp", std::process::id()));
    let result = (|| {
        let mut file = std::fs::File::create(&tmp)?;
        fill(&mut file)?;
        file.flush()?;
        file.sync_all()?;
        std::fs::rename(&tmp, path)
    })();
    if let Err(e) = result {
        let _ = std::fs::remove_file(&tmp);
        return Err(io_err("writing", e));
    }
    Ok(())
}

/// Write bytes to a file atomically.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    write_atomic_with(path, |f| f.write_all(bytes))
}

/// Read a whole text file, naming it in the error.
pub fn read_text(path: &Path) -> Result<String> {
    std::fs::read_to_string(path).map_err(|source| CoreError::Io {
        action: "reading",
        path: path.to_path_buf(),
        source,
    })
}

/// Parse TOML text into `T`, naming the file and the offending field in errors: `format` names
/// the document ("TOML tool definition"), `syntax_fix` and `field_fix` say what to do about a
/// syntax error and about a missing, unknown or mistyped field.
pub fn parse_toml<T: serde::de::DeserializeOwned>(
    text: &str,
    path: &Path,
    format: &'static str,
    syntax_fix: &str,
    field_fix: &str,
) -> Result<T> {
    let de = toml::Deserializer::parse(text).map_err(|e| CoreError::Parse {
        path: path.to_path_buf(),
        format: "TOML",
        field: ".".into(),
        message: e.to_string(),
        fix: syntax_fix.into(),
    })?;
    serde_path_to_error::deserialize(de).map_err(|e| CoreError::Parse {
        path: path.to_path_buf(),
        format,
        field: e.path().to_string(),
        message: e.inner().to_string(),
        fix: field_fix.into(),
    })
}

/// Create `root/<date>` or, if that exists, `root/<date>-2`, `-3`, …, and return it.
/// Creation is atomic (`create_dir` fails if the folder exists), so two processes certifying
/// the same unit at once still get two folders and nothing is ever overwritten.
pub fn create_dated_dir(root: &Path, date: &str) -> Result<PathBuf> {
    std::fs::create_dir_all(root).map_err(|source| CoreError::Io {
        action: "creating folder",
        path: root.to_path_buf(),
        source,
    })?;
    for n in 1..=MAX_SAME_DAY_FOLDERS {
        let name = if n == 1 {
            date.to_string()
        } else {
            format!("{date}-{n}")
        };
        let candidate = root.join(name);
        match std::fs::create_dir(&candidate) {
            Ok(()) => return Ok(candidate),
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {}
            Err(source) => {
                return Err(CoreError::Io {
                    action: "creating folder",
                    path: candidate,
                    source,
                });
            }
        }
    }
    Err(CoreError::WouldOverwrite {
        path: root.join(date),
        fix: format!("more than {MAX_SAME_DAY_FOLDERS} sets exist for this date; archive old ones"),
    })
}

/// The date and same-day counter of a dated set's folder name (`YYYY-MM-DD` or
/// `YYYY-MM-DD-N`), or `None` for any other name.
pub fn parse_set_name(name: &str) -> Option<(String, u32)> {
    let date = name.get(..10)?;
    crate::artifact::validate_date(date).ok()?;
    let n = match name.get(10..) {
        Some("") | None => 1,
        Some(rest) => rest.strip_prefix('-')?.parse().ok()?,
    };
    Some((date.to_string(), n))
}

/// The dated calibration set that `path` is or lies inside, if any: a folder named
/// `YYYY-MM-DD[-N]` that holds a `calibration.json` (see [`create_dated_dir`]).
pub fn dated_set_containing(path: &Path) -> Option<PathBuf> {
    // Resolve the path the way the OS will (symbolic links, `..`), also where it does not
    // exist yet: canonicalize every prefix that exists.
    let absolute = if path.is_absolute() {
        path.to_path_buf()
    } else {
        std::env::current_dir().ok()?.join(path)
    };
    let mut resolved = PathBuf::new();
    for component in absolute.components() {
        match component {
            std::path::Component::ParentDir => {
                resolved.pop();
            }
            std::path::Component::CurDir => {}
            other => {
                resolved.push(other);
                if let Ok(real) = resolved.canonicalize() {
                    resolved = real;
                }
            }
        }
    }
    resolved
        .ancestors()
        .find(|a| {
            a.file_name()
                .and_then(|n| n.to_str())
                .and_then(parse_set_name)
                .is_some()
                && a.join("calibration.json").is_file()
        })
        .map(Path::to_path_buf)
}

/// Refuse to write `path` (a file or an output folder) when it is or lies inside a dated set:
/// a set is written once, by the command that creates it, and never changed afterwards.
pub fn ensure_outside_dated_set(path: &Path) -> Result<()> {
    match dated_set_containing(path) {
        Some(set) => Err(CoreError::Invalid {
            path: path.to_path_buf(),
            field: "output".into(),
            expected: "a place outside the dated calibration sets (a set is never changed \
                       after it is written)"
                .into(),
            found: format!("a path inside the dated calibration set {}", set.display()),
            fix: "write to a folder outside units/<unit>/<date>/ (recalibrating makes a new set)"
                .into(),
        }),
        None => Ok(()),
    }
}

/// SHA-256 of a file's content as lowercase hex, for provenance records.
pub fn sha256_file(path: &Path) -> Result<String> {
    let mut file = std::fs::File::open(path).map_err(|source| CoreError::Io {
        action: "opening",
        path: path.to_path_buf(),
        source,
    })?;
    let mut hasher = Sha256::new();
    std::io::copy(&mut file, &mut hasher).map_err(|source| CoreError::Io {
        action: "reading",
        path: path.to_path_buf(),
        source,
    })?;
    Ok(hex(&hasher.finalize()))
}

/// SHA-256 of bytes as lowercase hex.
pub fn sha256_bytes(bytes: &[u8]) -> String {
    hex(&Sha256::digest(bytes))
}

/// Seconds since the Unix epoch → (year, month, day, hour, minute, second) in UTC
/// (proleptic Gregorian calendar, days-from-civil inverted).
fn civil_from_unix(seconds: u64) -> (i64, u32, u32, u32, u32, u32) {
    let days = i64::try_from(seconds / 86_400).unwrap_or(0);
    let rem = seconds % 86_400;
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z.rem_euclid(146_097);
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = u32::try_from(doy - (153 * mp + 2) / 5 + 1).unwrap_or(1);
    let month = u32::try_from(if mp < 10 { mp + 3 } else { mp - 9 }).unwrap_or(1);
    let year = yoe + era * 400 + i64::from(month <= 2);
    let h = u32::try_from(rem / 3600).unwrap_or(0);
    let m = u32::try_from((rem % 3600) / 60).unwrap_or(0);
    let s = u32::try_from(rem % 60).unwrap_or(0);
    (year, month, day, h, m, s)
}

fn unix_now() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs())
}

/// The current UTC time as RFC 3339 (`2026-11-22T01:02:03Z`), for provenance records.
pub fn utc_now_rfc3339() -> String {
    let (y, mo, d, h, mi, s) = civil_from_unix(unix_now());
    format!("{y:04}-{mo:02}-{d:02}T{h:02}:{mi:02}:{s:02}Z")
}

/// Today's UTC date as `YYYY-MM-DD`, the name of a new calibration folder.
pub fn utc_today() -> String {
    let (y, mo, d, ..) = civil_from_unix(unix_now());
    format!("{y:04}-{mo:02}-{d:02}")
}

fn hex(bytes: &[u8]) -> String {
    use std::fmt::Write as _;
    bytes
        .iter()
        .fold(String::with_capacity(bytes.len() * 2), |mut s, b| {
            let _ = write!(s, "{b:02x}");
            s
        })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn atomic_write_leaves_nothing_on_failure() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.json");
        write_atomic(&path, b"first").unwrap();
        let err = write_atomic_with(&path, |_| Err(std::io::Error::other("disk full")));
        assert!(err.is_err());
        assert_eq!(std::fs::read(&path).unwrap(), b"first");
        let names: Vec<_> = std::fs::read_dir(dir.path()).unwrap().collect();
        assert_eq!(names.len(), 1, "temporary file left behind");
    }

    #[test]
    fn dated_dirs_are_never_reused() {
        let dir = tempfile::tempdir().unwrap();
        let a = create_dated_dir(dir.path(), "2026-11-22").unwrap();
        let b = create_dated_dir(dir.path(), "2026-11-22").unwrap();
        assert!(a.ends_with("2026-11-22"));
        assert!(b.ends_with("2026-11-22-2"));
    }

    #[test]
    fn dated_sets_are_recognized_through_relative_and_dotted_paths() {
        let dir = tempfile::tempdir().unwrap();
        let set = dir.path().join("units/X5-1/2026-11-22-2");
        std::fs::create_dir_all(&set).unwrap();
        // An empty dated folder (a claimed, unfinished set) is not a set yet.
        assert!(dated_set_containing(&set).is_none());
        std::fs::write(set.join("calibration.json"), "{}").unwrap();
        let set = set.canonicalize().unwrap();
        assert_eq!(dated_set_containing(&set).as_deref(), Some(set.as_path()));
        let inside = set.join("exports/new/camchain.yaml");
        assert_eq!(
            dated_set_containing(&inside).as_deref(),
            Some(set.as_path())
        );
        let dotted = set.join("../2026-11-22-2/report");
        assert_eq!(
            dated_set_containing(&dotted).as_deref(),
            Some(set.as_path())
        );
        assert!(dated_set_containing(&dir.path().join("units/X5-1")).is_none());
        let err = ensure_outside_dated_set(&inside).unwrap_err().to_string();
        assert!(err.contains("never changed"), "{err}");
        assert_eq!(
            parse_set_name("2026-11-22-3"),
            Some(("2026-11-22".into(), 3))
        );
        assert_eq!(parse_set_name("2026-02-30"), None);
        assert_eq!(parse_set_name("2026-11-22x"), None);
    }

    #[test]
    fn civil_dates_are_right() {
        assert_eq!(civil_from_unix(0), (1970, 1, 1, 0, 0, 0));
        // 2026-11-22T00:52:44Z
        assert_eq!(civil_from_unix(1_795_308_764), (2026, 11, 22, 0, 52, 44));
        // A leap day.
        assert_eq!(civil_from_unix(951_782_400), (2000, 2, 29, 0, 0, 0));
    }

    #[test]
    fn hashes_are_stable() {
        assert_eq!(
            sha256_bytes(b"abc"),
            "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"
        );
    }
}
