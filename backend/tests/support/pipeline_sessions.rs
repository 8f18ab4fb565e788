//! Simulated sessions for the tests that run `kiwi run` as a command (pipeline_run, report):
//! recorded at test time by the simulator, small enough for `make test`.

#![allow(dead_code, clippy::unwrap_used, clippy::expect_used, missing_docs)]

use std::path::{Path, PathBuf};

use kiwi_fixtures::scenario::Scenario;
use kiwi_fixtures::session::{Cover, SessionOptions, write_session};

/// A two-episode session (320 px, 29.97 Hz, no head camera): a 10 s survey that builds the
/// maps and a 2 s tabletop episode, with the lens covers given.
pub fn small_session(dir: &Path, covers: Vec<Cover>) -> PathBuf {
    let mut o = SessionOptions::new(dir);
    o.seed = 5;
    o.resolution = 320;
    o.rate_hz = 29.97;
    o.episodes = 2;
    o.scenario = Scenario::Survey;
    o.episode_scenarios = vec![Scenario::Survey, Scenario::Tabletop];
    o.episode_durations = vec![10.0, 2.0];
    o.duration_s = 10.0;
    o.head = false;
    o.covers = covers;
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
