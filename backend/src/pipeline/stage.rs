//! The stage mechanism: where a stage's work lives, what it depends on, whether its last result
//! is current, and how a new result replaces the old one without ever leaving half of it.
//!
//! A stage's folder (`<session>/work/<stage>/` or `<session>/episodes/<ep>/work/<stage>/`) holds
//! its output files and `manifest.json`: the stage version, its parameters, a digest of every
//! input (files, lens streams, the outputs of the stages it reads), the digest of every output,
//! the status (`ok` or `failed` with the reason) and the wall time. A stage is *current* when its
//! manifest's fingerprint equals the fingerprint of its inputs now; otherwise it is *stale* and
//! the manifest names the input that changed.
//!
//! Writing is atomic at the level of the whole stage: outputs go to a fresh temporary folder
//! beside the stage folder, the manifest is written last, and the folder is then swapped in by
//! renames. A run killed at any moment leaves either the old result, the new one, or no folder
//! (the stage runs again); never a mix. Leftover temporary folders are removed on the next run.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use kiwi_core::io::{sha256_bytes, sha256_file, write_atomic};

use crate::error::{BackendError, Result};

/// Manifest schema.
pub const MANIFEST_SCHEMA_VERSION: u32 = 1;
/// File name of a stage's manifest.
pub const MANIFEST_FILE: &str = "manifest.json";
/// Prefix of a stage's temporary output folder (removed when left over by a killed run).
const TMP_PREFIX: &str = ".tmp-";
/// The sub-folder of a stage's outputs that [`StageWork::commit_ok`] publishes.
pub const PUBLISH_SUBDIR: &str = "out";
/// Prefix of a replaced stage folder awaiting removal.
const OLD_PREFIX: &str = ".old-";

/// Where a stage's work lives.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
pub enum Scope {
    /// Once per session (maps, metric recovery, placement, tool calibration).
    Session,
    /// Once per episode (sync, localization, observations, fusion, gripper, outputs).
    Episode(String),
}

impl Scope {
    /// `session` or the episode's name.
    pub fn label(&self) -> &str {
        match self {
            Self::Session => "session",
            Self::Episode(name) => name,
        }
    }
}

/// One stage of one scope, e.g. `localize-left-front` of episode `ep001`.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct StageId {
    /// Session or episode.
    pub scope: Scope,
    /// Stage name (`map-rear`, `localize-left-front`, …).
    pub name: String,
}

impl StageId {
    /// A session stage.
    pub fn session(name: impl Into<String>) -> Self {
        Self {
            scope: Scope::Session,
            name: name.into(),
        }
    }

    /// An episode stage.
    pub fn episode(episode: &str, name: impl Into<String>) -> Self {
        Self {
            scope: Scope::Episode(episode.to_string()),
            name: name.into(),
        }
    }

    /// The stage's folder under the session folder `root`.
    pub fn dir(&self, root: &Path) -> PathBuf {
        self.work_root(root).join(&self.name)
    }

    /// The `work/` folder that holds this stage's folder.
    pub fn work_root(&self, root: &Path) -> PathBuf {
        match &self.scope {
            Scope::Session => root.join("work"),
            Scope::Episode(e) => root.join("episodes").join(e).join("work"),
        }
    }

    /// `ep001/localize-left-front` or `session/map-rear`, for messages.
    pub fn label(&self) -> String {
        format!("{}/{}", self.scope.label(), self.name)
    }

    /// The family of the stage: its name up to the first `-` (`localize`, `map`, `fusion`).
    pub fn family(&self) -> &str {
        self.name.split('-').next().unwrap_or(&self.name)
    }
}

/// A digest of one input as the manifest records it.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct InputDigest {
    /// What the input is (`stream left/front`, `file left/imu.csv`, `stage map-rear`).
    pub name: String,
    /// Where it is (relative to the session folder).
    pub path: String,
    /// SHA-256 (hex) of its content (for streams: of `frames.csv` and every frame file's name
    /// and size).
    pub digest: String,
}

/// A digest of one output file.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct OutputDigest {
    /// File name inside the stage folder (or the episode's `out/`).
    pub file: String,
    /// SHA-256 (hex).
    pub sha256: String,
}

/// How a stage's last run ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum RunStatus {
    /// Outputs written.
    Ok,
    /// The stage failed; `reason` says why.
    Failed,
}

/// `manifest.json` of a stage.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    /// [`MANIFEST_SCHEMA_VERSION`].
    pub schema_version: u32,
    /// Stage name.
    pub stage: String,
    /// `session` or the episode name.
    pub scope: String,
    /// Version of the stage's algorithm and output format; a change re-runs the stage.
    pub version: String,
    /// The stage's parameters.
    pub parameters: serde_json::Value,
    /// Every input, sorted by name.
    pub inputs: Vec<InputDigest>,
    /// Digest of version, parameters and inputs: equal fingerprints mean the same work.
    pub fingerprint: String,
    /// How the run ended.
    pub status: RunStatus,
    /// Why it failed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reason: Option<String>,
    /// The outputs (empty when failed).
    pub outputs: Vec<OutputDigest>,
    /// Digest of the outputs: what the stages reading them record as their input.
    pub output_digest: String,
    /// Wall time of the run (s).
    pub seconds: f64,
    /// When the run finished (UTC).
    pub finished_utc: String,
    /// `kiwi <version>`.
    pub tool: String,
}

impl Manifest {
    /// Read `<dir>/manifest.json`, `None` when absent or unreadable (the stage then runs).
    pub fn read(dir: &Path) -> Option<Self> {
        let text = std::fs::read_to_string(dir.join(MANIFEST_FILE)).ok()?;
        let m: Self = serde_json::from_str(&text).ok()?;
        (m.schema_version == MANIFEST_SCHEMA_VERSION).then_some(m)
    }
}

/// What a stage needs before it runs: version, parameters and input digests.
#[derive(Debug, Clone, PartialEq)]
pub struct Fingerprint {
    /// Stage version.
    pub version: String,
    /// Parameters.
    pub parameters: serde_json::Value,
    /// Inputs, sorted by name.
    pub inputs: Vec<InputDigest>,
}

impl Fingerprint {
    /// A fingerprint from its parts (inputs are sorted here).
    pub fn new(version: &str, parameters: serde_json::Value, mut inputs: Vec<InputDigest>) -> Self {
        inputs.sort_by(|a, b| a.name.cmp(&b.name));
        Self {
            version: version.to_string(),
            parameters,
            inputs,
        }
    }

    /// The digest of version, parameters and inputs (paths are not part of it: a session
    /// folder that is moved or copied stays current).
    pub fn digest(&self) -> String {
        let mut text = format!("{}\n{}\n", self.version, self.parameters);
        for i in &self.inputs {
            text.push_str(&format!("{}={}\n", i.name, i.digest));
        }
        sha256_bytes(text.as_bytes())
    }
}

/// Where a stage stands.
#[derive(Debug, Clone, PartialEq)]
pub enum StageState {
    /// Never run (or its folder is gone).
    NotRun,
    /// The last result is for the current inputs.
    Current,
    /// The last result is for other inputs: which ones changed.
    Stale {
        /// Inputs (or `parameters`, `version`) that differ.
        changed: Vec<String>,
    },
    /// The last run with the current inputs failed.
    Failed {
        /// Why.
        reason: String,
    },
}

impl StageState {
    /// One word and the detail, for status listings.
    pub fn describe(&self) -> String {
        match self {
            Self::NotRun => "not run".into(),
            Self::Current => "current".into(),
            Self::Stale { changed } => format!("stale ({} changed)", changed.join(", ")),
            Self::Failed { reason } => format!("failed: {reason}"),
        }
    }
}

/// Compare a stage's manifest with the fingerprint of its inputs now.
pub fn state_of(dir: &Path, now: &Fingerprint) -> StageState {
    let Some(m) = Manifest::read(dir) else {
        return StageState::NotRun;
    };
    let digest = now.digest();
    if m.fingerprint == digest {
        return match m.status {
            RunStatus::Failed => StageState::Failed {
                reason: m.reason.unwrap_or_else(|| "no reason recorded".into()),
            },
            RunStatus::Ok if m.outputs.iter().all(|o| dir.join(&o.file).is_file()) => {
                StageState::Current
            }
            RunStatus::Ok => StageState::Stale {
                changed: vec!["outputs (a file of the stage folder is missing)".into()],
            },
        };
    }
    let mut changed = Vec::new();
    if m.version != now.version {
        changed.push(format!("version {} -> {}", m.version, now.version));
    }
    if m.parameters != now.parameters {
        changed.push("parameters".into());
    }
    let before: BTreeMap<&str, &str> = m
        .inputs
        .iter()
        .map(|i| (i.name.as_str(), i.digest.as_str()))
        .collect();
    for i in &now.inputs {
        match before.get(i.name.as_str()) {
            Some(d) if *d == i.digest => {}
            Some(_) => changed.push(i.path.clone()),
            None => changed.push(format!("{} (new input)", i.path)),
        }
    }
    if changed.is_empty() {
        changed.push("inputs".into());
    }
    StageState::Stale { changed }
}

fn io_err(path: &Path, action: &str, e: &std::io::Error) -> BackendError {
    BackendError::Input {
        path: path.to_path_buf(),
        message: format!("{action}: {e}; check permissions and free disk space"),
    }
}

/// A stage's temporary output folder, removed unless committed.
pub struct StageWork {
    /// The stage.
    pub id: StageId,
    final_dir: PathBuf,
    tmp: PathBuf,
    committed: bool,
}

impl StageWork {
    /// A fresh, empty temporary folder beside the stage folder of `id` under `root`.
    pub fn begin(root: &Path, id: &StageId) -> Result<Self> {
        let final_dir = id.dir(root);
        let parent = id.work_root(root);
        std::fs::create_dir_all(&parent).map_err(|e| io_err(&parent, "creating", &e))?;
        let tmp = parent.join(format!("{TMP_PREFIX}{}-{}", id.name, std::process::id()));
        if tmp.exists() {
            std::fs::remove_dir_all(&tmp).map_err(|e| io_err(&tmp, "removing", &e))?;
        }
        std::fs::create_dir(&tmp).map_err(|e| io_err(&tmp, "creating", &e))?;
        Ok(Self {
            id: id.clone(),
            final_dir,
            tmp,
            committed: false,
        })
    }

    /// The folder the stage writes its outputs into.
    pub fn dir(&self) -> &Path {
        &self.tmp
    }

    /// Write the manifest of a successful run and swap the folder in. With `publish`, the
    /// sub-folder `out/` of the outputs is first moved there (the episode's deliverables), and
    /// recorded in the manifest relative to the stage folder. Returns the manifest.
    pub fn commit_ok(
        self,
        fingerprint: &Fingerprint,
        seconds: f64,
        publish: Option<&Path>,
    ) -> Result<Manifest> {
        let mut outputs = Vec::new();
        if let Some(target) = publish {
            let sub = self.tmp.join(PUBLISH_SUBDIR);
            let prefix = relative_from(&self.final_dir, target);
            for o in digest_outputs(&sub)? {
                outputs.push(OutputDigest {
                    file: format!("{prefix}/{}", o.file),
                    sha256: o.sha256,
                });
            }
            replace_dir(&sub, target)?;
        }
        outputs.extend(digest_outputs(&self.tmp)?);
        self.commit(fingerprint, RunStatus::Ok, None, outputs, seconds)
    }

    /// Record a failure (the stage folder then holds only the manifest with the reason).
    pub fn commit_failed(
        self,
        fingerprint: &Fingerprint,
        reason: &str,
        seconds: f64,
    ) -> Result<Manifest> {
        for entry in std::fs::read_dir(&self.tmp)
            .map_err(|e| io_err(&self.tmp, "listing", &e))?
            .flatten()
        {
            let p = entry.path();
            let _ = if p.is_dir() {
                std::fs::remove_dir_all(&p)
            } else {
                std::fs::remove_file(&p)
            };
        }
        self.commit(
            fingerprint,
            RunStatus::Failed,
            Some(reason.to_string()),
            Vec::new(),
            seconds,
        )
    }

    fn commit(
        mut self,
        fingerprint: &Fingerprint,
        status: RunStatus,
        reason: Option<String>,
        outputs: Vec<OutputDigest>,
        seconds: f64,
    ) -> Result<Manifest> {
        let output_digest = {
            let mut text = String::new();
            for o in &outputs {
                text.push_str(&format!("{}={}\n", o.file, o.sha256));
            }
            sha256_bytes(text.as_bytes())
        };
        let manifest = Manifest {
            schema_version: MANIFEST_SCHEMA_VERSION,
            stage: self.id.name.clone(),
            scope: self.id.scope.label().to_string(),
            version: fingerprint.version.clone(),
            parameters: fingerprint.parameters.clone(),
            inputs: fingerprint.inputs.clone(),
            fingerprint: fingerprint.digest(),
            status,
            reason,
            outputs,
            output_digest,
            seconds,
            finished_utc: kiwi_core::io::utc_now_rfc3339(),
            tool: format!("kiwi {}", env!("CARGO_PKG_VERSION")),
        };
        let text = serde_json::to_string_pretty(&manifest).map_err(|e| BackendError::Input {
            path: self.tmp.join(MANIFEST_FILE),
            message: e.to_string(),
        })?;
        write_atomic(
            &self.tmp.join(MANIFEST_FILE),
            format!("{text}\n").as_bytes(),
        )?;
        replace_dir(&self.tmp, &self.final_dir)?;
        self.committed = true;
        Ok(manifest)
    }
}

impl Drop for StageWork {
    fn drop(&mut self) {
        if !self.committed {
            let _ = std::fs::remove_dir_all(&self.tmp);
        }
    }
}

/// `target` relative to `from` when both share the session folder: `../../out` for an episode's
/// `work/outputs` and `out`.
fn relative_from(from: &Path, target: &Path) -> String {
    let from: Vec<_> = from.components().collect();
    let to: Vec<_> = target.components().collect();
    let common = from.iter().zip(&to).take_while(|(a, b)| a == b).count();
    let mut parts: Vec<String> = vec!["..".into(); from.len() - common];
    parts.extend(
        to[common..]
            .iter()
            .map(|c| c.as_os_str().to_string_lossy().into_owned()),
    );
    parts.join("/")
}

/// SHA-256 of every file in `dir` (not the manifest), sorted by name.
pub fn digest_outputs(dir: &Path) -> Result<Vec<OutputDigest>> {
    let mut files = Vec::new();
    collect_files(dir, dir, &mut files)?;
    files.sort();
    files
        .into_iter()
        .filter(|rel| rel != MANIFEST_FILE)
        .map(|rel| {
            Ok(OutputDigest {
                sha256: sha256_file(&dir.join(&rel))?,
                file: rel,
            })
        })
        .collect()
}

fn collect_files(base: &Path, dir: &Path, out: &mut Vec<String>) -> Result<()> {
    for entry in std::fs::read_dir(dir)
        .map_err(|e| io_err(dir, "listing", &e))?
        .flatten()
    {
        let p = entry.path();
        if p.is_dir() {
            collect_files(base, &p, out)?;
        } else if let Ok(rel) = p.strip_prefix(base) {
            out.push(rel.to_string_lossy().replace('\\', "/"));
        }
    }
    Ok(())
}

/// Put the folder `from` at `to`, replacing what was there: the old folder is renamed aside
/// first and removed after, so `to` is at every moment either the old or the new folder or
/// absent.
pub fn replace_dir(from: &Path, to: &Path) -> Result<()> {
    let parent = to.parent().unwrap_or(Path::new("."));
    std::fs::create_dir_all(parent).map_err(|e| io_err(parent, "creating", &e))?;
    let name = to
        .file_name()
        .map_or_else(|| "stage".into(), |n| n.to_string_lossy().into_owned());
    let old = parent.join(format!("{OLD_PREFIX}{name}-{}", std::process::id()));
    let had_old = to.exists();
    if had_old {
        if old.exists() {
            std::fs::remove_dir_all(&old).map_err(|e| io_err(&old, "removing", &e))?;
        }
        std::fs::rename(to, &old).map_err(|e| io_err(to, "moving aside", &e))?;
    }
    std::fs::rename(from, to).map_err(|e| io_err(to, "renaming into place", &e))?;
    if had_old {
        let _ = std::fs::remove_dir_all(&old);
    }
    Ok(())
}

/// Remove temporary and replaced folders that a killed run left in `work_root` for the stages
/// in `names` (only those: another process may be running other stages of the same session).
pub fn clean_leftovers(work_root: &Path, names: &[&str]) {
    let Ok(entries) = std::fs::read_dir(work_root) else {
        return;
    };
    for entry in entries.flatten() {
        let file = entry.file_name().to_string_lossy().into_owned();
        let Some(rest) = file
            .strip_prefix(TMP_PREFIX)
            .or_else(|| file.strip_prefix(OLD_PREFIX))
        else {
            continue;
        };
        // `<name>-<pid>`: only folders of a process that is gone.
        let Some((name, pid)) = rest.rsplit_once('-') else {
            continue;
        };
        let alive = pid
            .parse::<u32>()
            .is_ok_and(|p| Path::new(&format!("/proc/{p}")).exists());
        if names.contains(&name) && !alive {
            let _ = std::fs::remove_dir_all(entry.path());
        }
    }
}
