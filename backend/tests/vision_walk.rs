//! Localization far from where mapping started: a map built from the simulator's room-covering
//! mapping sweep (20 s: at the table, along the walking path, back to the table) serves a walk
//! episode of the same room (another session with the same seed: same scene and units). Before
//! the sweep covered the room, every walk frame was lost (1.3-2.2 m from any mapping position).
//!
//! Checked against the simulator's truth: the left rear map's keyframe trajectory is within
//! 0.8 % of its extent after Sim(3) without loop closure, and within 0.5 % (the mapping
//! criterion) with it (the default); the left rear stream of the walk, in the middle of the
//! walk (every frame at least 1 m from the mapping's first keyframe), is localized in the
//! loop-closed left rear map with position errors (after the map's Sim(3) to the truth) under
//! 2 cm median and no accepted pose over 5 cm; so is the right wrist's rear stream in the same
//! map (the shared rear map).
//! Small images (320 px, 30 Hz) keep the test short.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

mod common;

use common::{
    assert_lost_frames_say_why, at, describe_localization, errors, keyframe_centres, session,
    tracked_map, truth,
};

use kiwi_backend::vision::align::{trajectory_error, umeyama};
use kiwi_backend::vision::episode::{LensStream, build_map, build_map_with, localize_stream};
use kiwi_backend::vision::localize::LocalizerOptions;
use kiwi_fixtures::scenario::Scenario;

const SEED: u64 = 5;
/// Survey (mapping) episode (s): the room sweep at up to ~1 m/s.
const MAPPING_S: f64 = 20.0;
/// Walk episode (s): the walker crosses 4 m in 80 % of it (~1 m/s at its fastest).
const WALK_S: f64 = 10.0;
/// Walk frames localized (indices in `frames.csv`): the middle of the walk.
const WINDOW: std::ops::Range<usize> = 90..240;
/// Every left-wrist frame of the window is at least this far from the mapping's first keyframe
/// (m).
const MIN_DISTANCE_FROM_START_M: f64 = 1.0;
/// Median position error (m) of the window's rear poses (either wrist) after the map's Sim(3)
/// to the truth. Measured 15.3 / 11.9 mm (left / right); before the front end kept near tracks,
/// 16.1 mm (left): a near-constant offset (8-21 mm over the window) that is the map's own
/// error in that part of the room (keyframe RMSE 21.8 mm); the earlier map (ATE 2.02 %) gave
/// 12.7 mm here by a local coincidence. vision_localize's 1.5 cm is for a map built where it
/// is queried.
const MAX_MEDIAN_ERROR_M: f64 = 0.02;
/// Rear keyframe ATE after Sim(3) to the truth, as a fraction of the trajectory extent, without
/// loop closure (measured 0.40 %).
const MAX_ATE_FRACTION_OPEN: f64 = 0.008;
/// The same with loop closure (the default): the criterion (measured 0.18 %).
const MAX_ATE_FRACTION_CLOSED: f64 = 0.005;

#[test]
fn walk_far_from_the_start_localizes_in_the_room_sweep_map() {
    let dir = tempfile::tempdir().unwrap();
    let mapping = session(dir.path(), "mapping", SEED, Scenario::Survey, MAPPING_S);
    let walk = session(dir.path(), "walk", SEED, Scenario::Walk, WALK_S);

    let stream = LensStream::open(&mapping, "left", "rear", None, None).unwrap();
    let (open, summary) = build_map_with(&stream, false, &mut |_, _| {}).unwrap();
    eprintln!("rear map without loop closure: {summary:?}");
    assert_eq!(summary.lost_at, None, "the rear is tracked to the end");
    let mapping_truth = truth(&mapping, "left", "rear");
    let (est, tru) = keyframe_centres(&open, &mapping_truth);
    let sim = umeyama(&est, &tru, true).unwrap();
    let ate = trajectory_error(&sim, &est, &tru).unwrap();
    eprintln!("keyframe trajectory after Sim(3): {ate:?}");
    // Drift of the rear map (the harder lens: far walls, few keyframes) without loop closure:
    // measured 0.40 % of the extent (16.6 mm of 4.17 m, seed 5, 320 px; 0.52 % before the front
    // end kept near tracks, 2.02 % before drifting tracks were split off their landmarks).
    assert!(
        ate.rmse < MAX_ATE_FRACTION_OPEN * ate.extent,
        "rear keyframe ATE {:.3} % of the extent (limit {:.1} %)",
        100.0 * ate.rmse / ate.extent,
        100.0 * MAX_ATE_FRACTION_OPEN
    );
    // With loop closure (the default; the survey returns to the table) the mapping
    // criterion holds: measured 0.18 % (7.6 mm), 4 loops closed. The walk is localized in this
    // map, as `kiwi map` builds it.
    let (map, summary) = build_map(&stream, &mut |_, _| {}).unwrap();
    eprintln!("rear map with loop closure: {summary:?}");
    assert_eq!(summary.lost_at, None, "the rear is tracked to the end");
    let (est, tru) = keyframe_centres(&map, &mapping_truth);
    let sim = umeyama(&est, &tru, true).unwrap();
    {
        let closed_ate = trajectory_error(&sim, &est, &tru).unwrap();
        eprintln!("loop-closed keyframe trajectory after Sim(3): {closed_ate:?}");
        assert!(summary.loops_closed >= 1, "{summary:?}");
        assert!(
            closed_ate.rmse < MAX_ATE_FRACTION_CLOSED * closed_ate.extent
                && closed_ate.rmse < ate.rmse,
            "loop-closed rear keyframe ATE {:.3} % (limit {:.1} %, open {:.3} %)",
            100.0 * closed_ate.rmse / closed_ate.extent,
            100.0 * MAX_ATE_FRACTION_CLOSED,
            100.0 * ate.rmse / ate.extent
        );
    }
    let start = tru[0];

    let options = LocalizerOptions::default();
    for camera in ["left", "right"] {
        let mut query = LensStream::open(&walk, camera, "rear", None, None).unwrap();
        query.select(&WINDOW.collect::<Vec<_>>()).unwrap();
        let rows = truth(&walk, camera, "rear");
        let nearest = query
            .frames
            .iter()
            .map(|f| (at(&rows, f.t) - start).norm())
            .fold(f64::INFINITY, f64::min);
        // The mapping wrist's stream must be far from where its map started.
        assert!(
            camera != "left" || nearest >= MIN_DISTANCE_FROM_START_M,
            "the window must lie far from the mapping start ({nearest:.2} m)"
        );
        let (results, s) = localize_stream(&map, &query, &options, &mut |_, _| {}).unwrap();
        let e = errors(&results, &sim, &rows);
        let over = e.iter().filter(|&&x| x > 0.05).count();
        eprintln!(
            "{camera} rear, walk frames {WINDOW:?} ({nearest:.2} m or more from the mapping \
             start): {}",
            describe_localization(&s, &e)
        );
        let uncertain = results
            .iter()
            .filter(|r| r.reason.contains("poorly constrained"))
            .count();
        eprintln!("{camera} rear: {uncertain} frames lost as position poorly constrained");
        // Zero false localizations: a pose is right or the frame is reported lost.
        assert_eq!(over, 0, "accepted poses over 5 cm: {e:?}");
        assert_lost_frames_say_why(&results);
        // Both wrists: the rear map is shared (measured 150/150 each, medians 15.3 and 11.9 mm,
        // since the front end keeps tracks on the near floor and walls; the right wrist was
        // 98/150 before). The right wrist's margin is wider: in the map without loop closure
        // it had 6 frames lost as poorly constrained (σ 0.51-0.56 % of the depth, limit 0.5 %,
        // at 320 px's 3× larger pixel).
        let min_fraction = if camera == "left" { 0.95 } else { 0.9 };
        assert!(s.localized_fraction >= min_fraction, "{camera}: {s:?}");
        assert!(
            e[e.len() / 2] < MAX_MEDIAN_ERROR_M,
            "{camera}: errors {e:?}"
        );
    }
}

/// The walk's front streams against the survey's left front map, every frame of the walk
/// (the survey passes within ~0.3 m of every walk pose, looking the same way).
///
/// Checked against the truth: the mapping wrist's front stream is localized on at least
/// `MIN_FRONT_FRACTION` of the walk with a median position error under 1.5 cm (320 px) and no
/// accepted pose over 5 cm; the other wrist's front stream in the same map (the cross-hand case:
/// another lens unit, a view from ~0.4 m to the side) never yields a pose over 5 cm — each frame
/// is right or reported lost.
#[test]
fn walk_front_streams_localize_in_the_survey_front_map() {
    /// Measured 398/398 (seed 5); a margin for platform differences in OpenCV's ORB and KLT.
    const MIN_FRONT_FRACTION: f64 = 0.95;
    let dir = tempfile::tempdir().unwrap();
    let mapping = session(dir.path(), "mapping", SEED, Scenario::Survey, MAPPING_S);
    let walk = session(dir.path(), "walk", SEED, Scenario::Walk, WALK_S);

    let map = tracked_map(&mapping, "left", "front");
    let (est, tru) = keyframe_centres(&map, &truth(&mapping, "left", "front"));
    let sim = umeyama(&est, &tru, true).unwrap();
    let ate = trajectory_error(&sim, &est, &tru).unwrap();
    eprintln!("front keyframe trajectory after Sim(3): {ate:?}");

    let options = LocalizerOptions::default();
    for camera in ["left", "right"] {
        let query = LensStream::open(&walk, camera, "front", None, None).unwrap();
        let rows = truth(&walk, camera, "front");
        let (results, s) = localize_stream(&map, &query, &options, &mut |_, _| {}).unwrap();
        let e = errors(&results, &sim, &rows);
        let over = e.iter().filter(|&&x| x > 0.05).count();
        eprintln!(
            "{camera} front, whole walk: {}",
            describe_localization(&s, &e)
        );
        // Zero false localizations: a pose is right or the frame is reported lost.
        assert_eq!(over, 0, "{camera} front: accepted poses over 5 cm: {e:?}");
        assert_lost_frames_say_why(&results);
        if camera == "left" {
            assert!(s.localized_fraction >= MIN_FRONT_FRACTION, "{s:?}");
            assert!(e[e.len() / 2] < 0.015, "errors {e:?}");
        }
    }
}
