//! Simulated sessions for the tests that run `kiwi run` as a command (pipeline_run, report):
//! recorded at test time by the simulator, small enough for `make test`.

#![allow(dead_code, clippy::unwrap_used, clippy::expect_used, missing_docs)]

use std::path::{Path, PathBuf};

use kiwi_fixtures::scenario::Scenario;
use kiwi_fixtures::session::{Cover, SessionOptions, write_session};

/// A session of `episodes` episodes (320 px, 29.97 Hz, no head camera): a 10 s survey that
/// builds the maps, then 2 s tabletop episodes.
pub fn small_session(dir: &Path, episodes: usize) -> PathBuf {
    session_with(dir, episodes, false)
}

/// [`small_session`] with the head camera and the hat marker.
pub fn small_session_with_head(dir: &Path, episodes: usize) -> PathBuf {
    session_with(dir, episodes, true)
}

fn session_with(dir: &Path, episodes: usize, head: bool) -> PathBuf {
    let mut o = SessionOptions::new(dir);
    o.seed = 5;
    o.resolution = 320;
    o.rate_hz = 29.97;
    o.episodes = episodes;
    o.scenario = Scenario::Survey;
    o.episode_scenarios = vec![Scenario::Survey, Scenario::Tabletop];
    o.episode_durations = vec![10.0, 2.0];
    o.duration_s = 10.0;
    o.head = head;
    write_session(&o).unwrap().session_toml
}

/// A two-episode session (160 px, 10 Hz, 3 s) whose mapping wrist's rear lens is covered for
/// the whole map episode: nothing can be mapped.
pub fn unmappable_session(dir: &Path) -> PathBuf {
    let mut o = SessionOptions::new(dir.join("s"));
    o.seed = 9;
    o.resolution = 160;
    o.rate_hz = 10.0;
    o.episodes = 2;
    o.duration_s = 3.0;
    o.head = false;
    o.covers = vec![Cover::parse("0:left:rear:0:3").unwrap()];
    write_session(&o).unwrap().session_toml
}

/// Every file under `dir` (relative path → bytes, sorted), manifests left out (they hold wall
/// times).
pub fn files(dir: &Path) -> Vec<(String, Vec<u8>)> {
    fn walk(base: &Path, dir: &Path, out: &mut Vec<(String, Vec<u8>)>) {
        let Ok(entries) = std::fs::read_dir(dir) else {
            return;
        };
        for e in entries.flatten() {
            let p = e.path();
            if p.is_dir() {
                walk(base, &p, out);
            } else if p.file_name().is_some_and(|n| n != "manifest.json") {
                let rel = p.strip_prefix(base).unwrap().to_string_lossy().into_owned();
                out.push((rel, std::fs::read(&p).unwrap()));
            }
        }
    }
    let mut out = Vec::new();
    walk(dir, dir, &mut out);
    out.sort_by(|a, b| a.0.cmp(&b.0));
    out
}

/// A session's inputs under another folder, as hard links (runs never modify their inputs).
pub fn copy_inputs(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap().flatten() {
        let (src, dst) = (e.path(), to.join(e.file_name()));
        if src.is_dir() {
            copy_inputs(&src, &dst);
        } else {
            std::fs::hard_link(&src, &dst).unwrap();
        }
    }
}

/// Whether a run is localizing a stream of `episode` (its temporary stage folder exists).
pub fn localizing(session: &Path, episode: &str) -> bool {
    std::fs::read_dir(session.join("episodes").join(episode).join("work")).is_ok_and(|d| {
        d.flatten()
            .any(|e| e.file_name().to_string_lossy().starts_with(".tmp-localize"))
    })
}
