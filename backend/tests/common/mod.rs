//! Helpers shared by the vision tests and bench: simulator sessions and truth pose files.
#![allow(dead_code, clippy::unwrap_used)]

pub mod reloc;
pub mod truth;

use std::path::{Path, PathBuf};

use kiwi_backend::vision::align::Sim3;
use kiwi_backend::vision::episode::{LensStream, LocalizeSummary, build_map};
use kiwi_backend::vision::localize::FrameLocalization;
use kiwi_backend::vision::map::VisualMap;
use kiwi_fixtures::scenario::Scenario;
use kiwi_fixtures::session::{SessionOptions, write_session};
use nalgebra::Vector3;

/// A one-episode session at 320 px and 30 Hz without the head camera; returns its episode folder.
pub fn session(root: &Path, name: &str, seed: u64, scenario: Scenario, duration_s: f64) -> PathBuf {
    let out = root.join(name);
    let mut o = SessionOptions::new(&out);
    o.seed = seed;
    o.scenario = scenario;
    o.duration_s = duration_s;
    o.resolution = 320;
    o.rate_hz = 30.0;
    o.head = false;
    write_session(&o).unwrap();
    out.join("episodes").join("ep000")
}

/// The same session as [`session`], rendered once per test binary build and shared by the tests
/// of that binary (the folder is per binary) (nextest runs each test in its own process, possibly at the same time): kept
/// under the build's temporary folder, written under a lock, and rendered again whenever the test
/// binary is newer than the copy (the simulator may have changed). Tests must only read it.
pub fn shared_session(name: &str, seed: u64, scenario: Scenario, duration_s: f64) -> PathBuf {
    // Per test binary: another binary sharing the folder would see this one's copy as stale.
    let binary = std::env::current_exe()
        .ok()
        .and_then(|exe| exe.file_stem().map(|s| s.to_string_lossy().into_owned()))
        .unwrap_or_default();
    let key = format!("{binary}-{name}-seed{seed}-{scenario:?}-{duration_s}s-320px");
    let root = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("vision-sessions");
    std::fs::create_dir_all(&root).unwrap();
    let lock = std::fs::File::create(root.join(format!(".{key}.lock"))).unwrap();
    lock.lock().unwrap();
    let built_by = std::env::current_exe()
        .and_then(|exe| std::fs::metadata(exe)?.modified())
        .map(|t| format!("{t:?}"))
        .unwrap_or_default();
    let ready = root.join(format!("{key}.ready"));
    let dir = root.join(&key);
    if std::fs::read_to_string(&ready).ok().as_deref() != Some(built_by.as_str()) {
        let _ = std::fs::remove_file(&ready);
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        session(&dir, name, seed, scenario, duration_s);
        std::fs::write(&ready, &built_by).unwrap();
    }
    lock.unlock().unwrap();
    dir.join(name).join("episodes").join("ep000")
}

/// `(t, camera centre)` rows of a truth pose file.
pub fn truth(episode: &Path, camera: &str, lens: &str) -> Vec<(f64, Vector3<f64>)> {
    let text =
        std::fs::read_to_string(episode.join(format!("truth/{camera}/{lens}_poses.csv"))).unwrap();
    text.lines()
        .skip(1)
        .map(|l| {
            let v: Vec<f64> = l.split(',').map(|x| x.parse().unwrap()).collect();
            (v[0], Vector3::new(v[2], v[3], v[4]))
        })
        .collect()
}

/// The truth row nearest in time to `t`.
pub fn at(rows: &[(f64, Vector3<f64>)], t: f64) -> Vector3<f64> {
    rows.iter()
        .min_by(|a, b| (a.0 - t).abs().total_cmp(&(b.0 - t).abs()))
        .map(|r| r.1)
        .unwrap()
}

/// Position errors (m) of the localized frames against the truth rows, after the map's Sim(3),
/// sorted.
pub fn errors(results: &[FrameLocalization], sim: &Sim3, rows: &[(f64, Vector3<f64>)]) -> Vec<f64> {
    let mut e: Vec<f64> = results
        .iter()
        .filter_map(|r| {
            r.map_from_cam
                .map(|p| (sim.transform_point(&p.translation.vector) - at(rows, r.t)).norm())
        })
        .collect();
    e.sort_by(f64::total_cmp);
    e
}

/// Each keyframe's camera centre in the map, paired with the true centre at its time:
/// `(estimated, true)`, for a Sim(3) alignment of the map to the world.
pub fn keyframe_centres(
    map: &VisualMap,
    mapping_truth: &[(f64, Vector3<f64>)],
) -> (Vec<Vector3<f64>>, Vec<Vector3<f64>>) {
    map.keyframes
        .iter()
        .map(|k| (reloc::keyframe_centre(k), at(mapping_truth, k.t)))
        .unzip()
}

/// A map of one lens stream of `episode`, built from every frame; the stream must be tracked to
/// its end.
pub fn tracked_map(episode: &Path, camera: &str, lens: &str) -> VisualMap {
    let stream = LensStream::open(episode, camera, lens, None, None).unwrap();
    let (map, summary) = build_map(&stream, &mut |_, _| {}).unwrap();
    eprintln!("map of {camera} {lens}: {summary:?}");
    assert_eq!(
        summary.lost_at, None,
        "{camera} {lens} is tracked to the end"
    );
    map
}

/// Every lost frame says why, and no localized one carries a reason.
pub fn assert_lost_frames_say_why(results: &[FrameLocalization]) {
    for r in results {
        assert_eq!(
            r.map_from_cam.is_none(),
            !r.reason.is_empty(),
            "a lost frame says why, a localized one does not: {r:?}"
        );
    }
}

/// One line on a localized stream: frames localized (tracked, relocalized), median inliers, and
/// the sorted position errors `e` (m) as median, worst and count over 5 cm.
pub fn describe_localization(s: &LocalizeSummary, e: &[f64]) -> String {
    format!(
        "{} of {} localized ({:.1} %: {} tracked, {} relocalized), median {} inliers; position \
         error median {:.1} mm, worst {:.1} mm, {} over 5 cm",
        s.localized,
        s.frames,
        100.0 * s.localized_fraction,
        s.tracked,
        s.relocalized,
        s.median_inliers,
        e.get(e.len() / 2).map_or(f64::NAN, |x| x * 1e3),
        e.last().map_or(f64::NAN, |x| x * 1e3),
        e.iter().filter(|&&x| x > 0.05).count()
    )
}
