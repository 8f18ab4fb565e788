//! The floor reference from simulated front streams, with the wrists' trajectories taken from
//! the simulator's truth (paper §4.3.3, developed on truth before it runs on fused poses): the
//! floor stage's own functions choose windows, sweep planes, match rectified pairs, combine,
//! reject strays and pool both wrists; the result is compared with the room (floor at z = 0,
//! table top at `TABLE_TOP_Z`, platform top at `PLATFORM_MAX[2]`).

#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

mod common;

use common::truth::truth_floor_windows;
use kiwi_backend::floor::{
    EpisodeSurface, Floor, FloorOptions, WindowEstimate, pool, surfaces_above,
};
use kiwi_core::layout::{EpisodeLayout, Session, Side};
use kiwi_fixtures::scenario::Scenario;
use kiwi_fixtures::scene::{PLATFORM_MAX, RoomKind, SceneOptions, TABLE_TOP_Z};
use kiwi_fixtures::session::{SessionOptions, write_session};

/// The bound on the floor and table heights.
const MAX_HEIGHT_ERROR_M: f64 = 0.01;

/// Record one episode of `scenario` (front lenses only) and run the floor on its truth poses.
fn floor_of(
    scenario: Scenario,
    seed: u64,
    platform: bool,
    room: RoomKind,
) -> (Floor, Vec<EpisodeSurface>, Vec<WindowEstimate>) {
    let tmp = tempfile::tempdir().unwrap();
    let mut o = SessionOptions::new(tmp.path());
    o.seed = seed;
    o.resolution = 480;
    o.rate_hz = 29.97;
    o.episodes = 1;
    o.duration_s = 4.0;
    o.scenario = scenario;
    o.head = false;
    o.rolling_shutter = true;
    o.scene = SceneOptions::room(room);
    o.scene.platform = platform;
    o.only_lenses = vec!["left/front".into(), "right/front".into()];
    let written = write_session(&o).unwrap();
    let root = written.session_toml.parent().unwrap();
    let episode = EpisodeLayout::new(root.join("episodes").join(&written.episodes[0]));
    let session = Session::load(&written.session_toml).unwrap();
    let options = FloorOptions::default();
    let mut windows = Vec::new();
    let mut counts = Vec::new();
    for side in [Side::Left, Side::Right] {
        let unit = &session.wrists[&side].unit;
        let (w, c) = truth_floor_windows(root, &episode, unit, side, &options);
        windows.extend(w);
        counts.push(c);
    }
    let floor = pool(&mut windows, &counts, options.camera_height_m);
    let surfaces = surfaces_above(&windows, &floor);
    for w in &windows {
        eprintln!(
            "{:?} frame {} cam z {:.3} base {:.3} sweep {:?} stereo {:?} -> {:?} {:?}",
            w.side,
            w.frame,
            w.camera_z_m,
            w.baseline_m,
            w.sweep
                .iter()
                .map(|s| (s.z_m, s.support))
                .collect::<Vec<_>>(),
            w.stereo
                .iter()
                .map(|s| (s.z_m, s.support))
                .collect::<Vec<_>>(),
            w.floor_z_m,
            w.status
        );
    }
    eprintln!("{scenario:?} seed {seed}: {floor:?}; surfaces {surfaces:?}; counts {counts:?}");
    (floor, surfaces, windows)
}

fn assert_floor(floor: &Floor) {
    let Floor::Found { z_m, windows, .. } = floor else {
        panic!("expected a floor, got {floor:?}");
    };
    assert!(*windows >= 2, "{windows} windows pooled");
    assert!(
        z_m.abs() < MAX_HEIGHT_ERROR_M,
        "floor at {z_m:.4} m, truth 0 (bound {MAX_HEIGHT_ERROR_M} m)"
    );
}

#[test]
fn tabletop_floor_and_table_heights_match_the_room() {
    let (floor, surfaces, _) = floor_of(Scenario::Tabletop, 41, false, RoomKind::Studio);
    assert_floor(&floor);
    let table = surfaces
        .iter()
        .min_by(|a, b| {
            (a.z_m - TABLE_TOP_Z)
                .abs()
                .total_cmp(&(b.z_m - TABLE_TOP_Z).abs())
        })
        .expect("the table is reported");
    assert!(
        (table.z_m - TABLE_TOP_Z).abs() < MAX_HEIGHT_ERROR_M,
        "table at {:.4} m, truth {TABLE_TOP_Z}",
        table.z_m
    );
}

#[test]
fn walk_floor_height_matches_the_room() {
    let (floor, _, _) = floor_of(Scenario::Walk, 43, false, RoomKind::Studio);
    assert_floor(&floor);
}

#[test]
fn a_low_platform_beside_the_path_does_not_take_the_floors_place() {
    let (floor, surfaces, windows) = floor_of(Scenario::Walk, 47, true, RoomKind::Studio);
    assert_floor(&floor);
    let platform_seen = windows
        .iter()
        .flat_map(|w| w.sweep.iter().chain(&w.stereo))
        .any(|s| (s.z_m - PLATFORM_MAX[2]).abs() < 0.02);
    assert!(
        platform_seen,
        "the platform is a supported surface in some window: {surfaces:?}"
    );
}

#[test]
fn front_views_that_never_see_the_floor_report_no_floor_with_the_reason() {
    let (floor, _, _) = floor_of(Scenario::Overhead, 53, false, RoomKind::Studio);
    let Floor::NoFloor { reason } = floor else {
        panic!("expected no floor, got {floor:?}");
    };
    assert!(reason.contains("never looked down"), "{reason}");
}

#[test]
fn a_wrist_that_mostly_sees_the_table_still_finds_the_floor() {
    // In this room the hands hover over a cluttered table and the floor is in view in only a
    // few windows: the table and the objects on it must not take the floor's place.
    let (floor, _, windows) = floor_of(Scenario::Tabletop, 73, false, RoomKind::Workshop);
    assert_floor(&floor);
    let above = windows
        .iter()
        .filter(|w| w.status == kiwi_backend::floor::WindowStatus::AboveFloor)
        .count();
    assert!(above > 0, "some windows saw only the table");
}
