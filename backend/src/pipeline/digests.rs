//! Remembered input digests: each input file's SHA-256 is computed once and reused while the
//! file keeps its size and modification time, so that deciding which stages are current does not
//! read every video again (a 960 px lens stream stored as video is about 1 GB per 20 s).
//!
//! The record lives at `.kiwi/file-digests.json` in the session (beside the stages' results,
//! not among them), keyed by the path relative to the session folder (so a copied session with
//! its times preserved keeps it). A remembered
//! digest is trusted only when the file was last modified at least [`RACY_MARGIN_NS`] before it
//! was hashed: a file rewritten within the same clock tick as its hashing, at the same size,
//! would otherwise keep a stale digest (the rule git uses for its index). An unreadable or
//! foreign record is ignored and rebuilt; losing it only costs the hashing again.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::sync::atomic::{AtomicBool, Ordering};

use kiwi_core::io::{sha256_file, write_atomic};
use serde::{Deserialize, Serialize};

use crate::error::Result;

/// The session's folder for what KIWI remembers between runs (not results).
pub const STATE_DIR: &str = ".kiwi";
/// The record's file name in [`STATE_DIR`].
pub const DIGESTS_FILE: &str = "file-digests.json";
/// A remembered digest is trusted only for files modified at least this long before they were
/// hashed (ns): above the coarsest common file-time resolution (FAT's 2 s).
pub const RACY_MARGIN_NS: u128 = 2_000_000_000;
/// Version of the record's layout; another version is ignored.
const RECORD_VERSION: u32 = 1;

/// What is remembered of one file.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
struct Entry {
    /// Size in bytes when hashed.
    size: u64,
    /// Modification time when hashed (ns since the Unix epoch).
    modified_ns: u128,
    /// When it was hashed (ns since the Unix epoch).
    hashed_ns: u128,
    /// SHA-256, lowercase hex.
    sha256: String,
}

#[derive(Debug, Default, Serialize, Deserialize)]
struct Record {
    version: u32,
    files: BTreeMap<String, Entry>,
}

/// The session's remembered digests (shared by the threads of a run).
#[derive(Debug)]
pub struct DigestCache {
    /// Where the record is kept.
    path: PathBuf,
    /// The session folder the keys are relative to.
    root: PathBuf,
    files: Mutex<BTreeMap<String, Entry>>,
    changed: AtomicBool,
}

fn nanos(time: std::time::SystemTime) -> Option<u128> {
    time.duration_since(std::time::UNIX_EPOCH)
        .ok()
        .map(|d| d.as_nanos())
}

/// A file's size and modification time (ns), when both can be read.
fn stamp(path: &Path) -> Option<(u64, u128)> {
    let meta = std::fs::metadata(path).ok()?;
    Some((meta.len(), nanos(meta.modified().ok()?)?))
}

impl DigestCache {
    /// The record of the session at `root` (empty when there is none or it cannot be read).
    pub fn load(root: &Path) -> Self {
        let path = root.join(STATE_DIR).join(DIGESTS_FILE);
        let files = std::fs::read_to_string(&path)
            .ok()
            .and_then(|text| serde_json::from_str::<Record>(&text).ok())
            .filter(|r| r.version == RECORD_VERSION)
            .map(|r| r.files)
            .unwrap_or_default();
        Self {
            path,
            root: root.to_path_buf(),
            files: Mutex::new(files),
            changed: AtomicBool::new(false),
        }
    }

    fn key(&self, path: &Path) -> String {
        path.strip_prefix(&self.root)
            .unwrap_or(path)
            .to_string_lossy()
            .replace('\\', "/")
    }

    /// SHA-256 of `path`: the remembered one when the file is unchanged, else computed (and
    /// remembered).
    pub fn sha256(&self, path: &Path) -> Result<String> {
        let before = stamp(path);
        let key = self.key(path);
        if let Some((size, modified_ns)) = before {
            let files = self
                .files
                .lock()
                .unwrap_or_else(std::sync::PoisonError::into_inner);
            if let Some(e) = files.get(&key)
                && e.size == size
                && e.modified_ns == modified_ns
                && e.modified_ns + RACY_MARGIN_NS <= e.hashed_ns
            {
                return Ok(e.sha256.clone());
            }
        }
        let hashed_ns = nanos(std::time::SystemTime::now()).unwrap_or(0);
        let sha256 = sha256_file(path)?;
        // Remember it only if the file did not change while it was read.
        if let Some((size, modified_ns)) = before
            && stamp(path) == before
        {
            let mut files = self
                .files
                .lock()
                .unwrap_or_else(std::sync::PoisonError::into_inner);
            files.insert(
                key,
                Entry {
                    size,
                    modified_ns,
                    hashed_ns,
                    sha256: sha256.clone(),
                },
            );
            self.changed.store(true, Ordering::Relaxed);
        }
        Ok(sha256)
    }

    /// Write the record (atomically) if anything was added; a session folder that cannot be
    /// written keeps working without it.
    pub fn save(&self) {
        if !self.changed.swap(false, Ordering::Relaxed) {
            return;
        }
        let files = self
            .files
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .clone();
        let record = Record {
            version: RECORD_VERSION,
            files,
        };
        let Ok(text) = serde_json::to_string(&record) else {
            return;
        };
        if let Some(dir) = self.path.parent()
            && std::fs::create_dir_all(dir).is_ok()
            && let Err(e) = write_atomic(&self.path, text.as_bytes())
        {
            tracing::warn!(
                "cannot keep the input digests in {}: {e}",
                self.path.display()
            );
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn set_modified(path: &Path, time: std::time::SystemTime) {
        let f = std::fs::File::options().write(true).open(path).unwrap();
        f.set_modified(time).unwrap();
    }

    #[test]
    fn a_remembered_digest_is_reused_until_the_file_changes() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("a.bin");
        let now = std::time::SystemTime::now();
        let (minute_ago, half_minute_ago) = (
            now - std::time::Duration::from_secs(60),
            now - std::time::Duration::from_secs(30),
        );
        std::fs::write(&file, b"first").unwrap();
        set_modified(&file, minute_ago);
        let cache = DigestCache::load(dir.path());
        let first = cache.sha256(&file).unwrap();
        assert_eq!(first, sha256_file(&file).unwrap());
        cache.save();
        assert!(dir.path().join(STATE_DIR).join(DIGESTS_FILE).is_file());

        // A new process reads the record back; the remembered digest is served without reading
        // the file: prove it by changing the content behind an unchanged size and time.
        std::fs::write(&file, b"other").unwrap();
        set_modified(&file, minute_ago);
        let reloaded = DigestCache::load(dir.path());
        assert_eq!(reloaded.sha256(&file).unwrap(), first);

        // A change of time (any rewrite) or size is noticed.
        set_modified(&file, half_minute_ago);
        let changed = reloaded.sha256(&file).unwrap();
        assert_eq!(changed, sha256_file(&file).unwrap());
        assert_ne!(changed, first);
        std::fs::write(&file, b"longer content").unwrap();
        set_modified(&file, half_minute_ago);
        assert_eq!(reloaded.sha256(&file).unwrap(), sha256_file(&file).unwrap());
    }

    #[test]
    fn a_file_hashed_as_it_is_written_is_hashed_again() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("fresh.csv");
        std::fs::write(&file, b"1,2,3\n").unwrap();
        let cache = DigestCache::load(dir.path());
        let first = cache.sha256(&file).unwrap();
        // Rewritten at once with the same size and (on a coarse clock) the same time: the
        // remembered digest was taken within the racy margin, so it is not trusted.
        let modified = std::fs::metadata(&file).unwrap().modified().unwrap();
        std::fs::write(&file, b"4,5,6\n").unwrap();
        std::fs::File::options()
            .write(true)
            .open(&file)
            .unwrap()
            .set_modified(modified)
            .unwrap();
        let second = cache.sha256(&file).unwrap();
        assert_ne!(first, second);
        assert_eq!(second, sha256_file(&file).unwrap());
    }

    #[test]
    fn an_unreadable_record_is_rebuilt() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::create_dir_all(dir.path().join(STATE_DIR)).unwrap();
        std::fs::write(dir.path().join(STATE_DIR).join(DIGESTS_FILE), b"{ not json").unwrap();
        let file = dir.path().join("b.bin");
        std::fs::write(&file, b"content").unwrap();
        let cache = DigestCache::load(dir.path());
        assert_eq!(cache.sha256(&file).unwrap(), sha256_file(&file).unwrap());
        cache.save();
        let text = std::fs::read_to_string(dir.path().join(STATE_DIR).join(DIGESTS_FILE)).unwrap();
        assert!(text.contains("b.bin"), "{text}");
    }
}
