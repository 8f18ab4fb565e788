//! The marker-referenced protocol (`kiwi evaluate markers`) on a simulated session with the two
//! fixed 58 mm workspace markers: each wrist's published trajectory is the simulator's truth in
//! another scene frame with a known smooth error (a wander and a drift, the right hand also
//! misplaced against the left), and each hand's median error with its own alignment must agree
//! within 1 mm with the same protocol run against the truth on the same frames (alignment on
//! the referenced frames of the first 40 %, median over the scored ones); the left-fitted
//! figures are printed beside the truth's. The fitted arrangement is checked against the
//! markers' true placement, and the command refuses unusable arguments with the fix.

#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

mod common;

use std::fmt::Write as _;
use std::path::Path;

use nalgebra::{Translation3, UnitQuaternion, Vector3};

use common::truth::{TruthRow, truth_rows};
use kiwi_backend::evaluate::markers::{
    AlignmentKind, FrameError, MarkerPair, Paired, Phase, SCORE_FROM_FRACTION, evaluate_markers,
    fit_alignment,
};
use kiwi_backend::outputs::TRAJECTORY_HEADER;
use kiwi_backend::pipeline::SessionContext;
use kiwi_backend::pipeline::stages::PUBLISHED_DIR;
use kiwi_backend::vision::align::{Sim3, umeyama};
use kiwi_core::geometry::{Pose, interpolate_pose};
use kiwi_fixtures::scenario::Scenario;
use kiwi_fixtures::session::{
    SessionOptions, WORKSPACE_MARKER_DICTIONARY, WORKSPACE_MARKER_IDS, WORKSPACE_MARKER_SIZE_M,
    write_session,
};

/// The agreement between the marker-referenced and the truth-based errors (m).
const MAX_DISAGREEMENT_M: f64 = 0.001;

/// The pose at `t` of time-ordered `(t, pose)` rows (linear between the two around it).
fn pose_at<T>(rows: &[T], t: f64, row: impl Fn(&T) -> (f64, &Pose)) -> Pose {
    let k = rows
        .partition_point(|r| row(r).0 <= t)
        .clamp(1, rows.len() - 1);
    let ((ta, a), (tb, b)) = (row(&rows[k - 1]), row(&rows[k]));
    interpolate_pose(a, b, ((t - ta) / (tb - ta)).clamp(0.0, 1.0))
}

/// The truth pose at camera time `t`.
fn truth_at(rows: &[TruthRow], t: f64) -> Pose {
    pose_at(rows, t, |r| (r.t, &r.pose))
}

/// KIWI's stand-in: `scene_from_world` times the truth, displaced by a smooth error that wanders
/// by a few millimetres and drifts by `drift` over the sequence, plus a constant `offset`.
fn published(
    rows: &[TruthRow],
    scene_from_world: &Pose,
    drift: Vector3<f64>,
    offset: Vector3<f64>,
) -> Vec<(f64, Pose)> {
    let (t0, t1) = (rows[0].t, rows[rows.len() - 1].t);
    rows.iter()
        .map(|r| {
            let f = (r.t - t0) / (t1 - t0);
            let wander = 0.002
                * Vector3::new(
                    (std::f64::consts::TAU * r.t / 3.7).sin(),
                    (std::f64::consts::TAU * r.t / 2.9).cos(),
                    0.5 * (std::f64::consts::TAU * r.t / 1.7).sin(),
                );
            let error = Translation3::from(wander + drift * f + offset);
            let turn = UnitQuaternion::from_scaled_axis(
                Vector3::new(0.004, -0.003, 0.005) * (r.t / 2.3).sin(),
            );
            (r.t, scene_from_world * (error * r.pose) * turn)
        })
        .collect()
}

/// The published pose at `t`.
fn published_at(poses: &[(f64, Pose)], t: f64) -> Pose {
    pose_at(poses, t, |r| (r.0, &r.1))
}

fn write_published(path: &Path, poses: &[(f64, Pose)]) {
    let mut s = format!("{TRAJECTORY_HEADER}\n");
    for (t, pose) in poses {
        let (p, q) = (pose.translation.vector, pose.rotation.coords);
        let fields = format!("{},{},{},{},{},{},{}", p.x, p.y, p.z, q.x, q.y, q.z, q.w);
        let _ = writeln!(s, ",{t},{fields},{fields},0,0,0,0,front,,,,0,,");
    }
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    std::fs::write(path, s).unwrap();
}

/// The same protocol on the truth, on the same frames: the rigid alignment of the truth onto
/// KIWI's positions at the frames the markers' alignment was fitted on (the first 40 % with a
/// reference).
fn truth_alignment(rows: &[TruthRow], frames: &[FrameError]) -> Sim3 {
    let (source, target): (Vec<_>, Vec<_>) = frames
        .iter()
        .filter(|e| e.phase == Phase::Fit)
        .map(|e| {
            (
                truth_at(rows, e.t_camera).translation.vector,
                e.estimate_scene,
            )
        })
        .unzip();
    umeyama(&source, &target, false).unwrap()
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

fn pose_of(value: &serde_json::Value) -> Pose {
    let p: Vec<f64> = serde_json::from_value(value["p"].clone()).unwrap();
    let q: Vec<f64> = serde_json::from_value(value["q_xyzw"].clone()).unwrap();
    Pose::from_parts(
        Translation3::new(p[0], p[1], p[2]),
        UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(q[3], q[0], q[1], q[2])),
    )
}

#[test]
fn marker_errors_agree_with_the_truth_within_a_millimetre() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("session");
    let mut o = SessionOptions::new(&root);
    // Seed 11 is the one the protocol was developed on; KIWI_MARKERS_SEED runs another.
    o.seed = std::env::var("KIWI_MARKERS_SEED").map_or(11, |s| s.parse().unwrap());
    o.scenario = Scenario::Tabletop;
    o.duration_s = 8.0;
    o.resolution = 960;
    o.rate_hz = 29.97;
    o.head = false;
    o.rolling_shutter = true;
    o.workspace_markers = true;
    // The default room; KIWI_MARKERS_ROOM (studio, photos, kitchen, workshop, divided) films
    // another.
    if let Ok(room) = std::env::var("KIWI_MARKERS_ROOM") {
        o.scene = kiwi_fixtures::scene::SceneOptions::room(
            <kiwi_fixtures::scene::RoomKind as clap::ValueEnum>::from_str(&room, true).unwrap(),
        );
    }
    o.only_lenses = vec!["left/front".into(), "right/front".into()];
    write_session(&o).unwrap();

    let ctx = SessionContext::load(&root.join("session.toml")).unwrap();
    let episode = ctx.episode_names()[0].clone();
    let layout = ctx.episode(&episode);
    let scene_from_world = Pose::from_parts(
        Translation3::new(1.2, -0.4, 0.3),
        UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.7),
    );
    let mut truths = Vec::new();
    let mut publications = Vec::new();
    for (camera, drift, offset) in [
        ("left", Vector3::new(0.004, -0.002, 0.001), Vector3::zeros()),
        (
            "right",
            Vector3::new(-0.002, 0.005, -0.002),
            Vector3::new(0.003, 0.002, -0.002),
        ),
    ] {
        let rows = truth_rows(
            &layout
                .root()
                .join("truth")
                .join(camera)
                .join("front_poses.csv"),
        );
        let poses = published(&rows, &scene_from_world, drift, offset);
        publications.push(poses.clone());
        write_published(
            &layout
                .root()
                .join(PUBLISHED_DIR)
                .join(format!("{camera}.csv")),
            &poses,
        );
        truths.push(rows);
    }

    let pair = MarkerPair {
        dictionary: WORKSPACE_MARKER_DICTIONARY.into(),
        ids: WORKSPACE_MARKER_IDS,
        size_m: WORKSPACE_MARKER_SIZE_M,
    };
    let evaluation = evaluate_markers(
        &ctx,
        &episode,
        &pair,
        AlignmentKind::Positions,
        &|_, _, _| {},
    )
    .unwrap();
    let table = kiwi_backend::evaluate::markers::table(&evaluation);
    print!("{table}");
    // On positions, the table says where the left-fitted figure's rotation comes from.
    assert!(table.contains("--align poses"), "{table}");
    assert!(evaluation.skipped.is_empty(), "{:?}", evaluation.skipped);
    assert_eq!(evaluation.wrists.len(), 2);

    // The arrangement against the markers' true placement.
    let truth: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(root.join("truth").join("workspace_markers.json")).unwrap(),
    )
    .unwrap();
    let world_from = |k: usize| pose_of(&truth["markers"][k]["world_from_marker"]);
    let a_from_b = world_from(0).inverse() * world_from(1);

    let left_truth_alignment = truth_alignment(&truths[0], &evaluation.wrists[0].errors);
    {
        let w = &evaluation.wrists[0];
        let q = w.scene_from_marker_q;
        let marker_rot =
            UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(q[3], q[0], q[1], q[2]));
        let truth_rot = left_truth_alignment.rotation * world_from(0).rotation;
        let p_m = Vector3::from(w.scene_from_marker_p);
        let p_t = left_truth_alignment.transform_point(&world_from(0).translation.vector);
        println!(
            "left alignment vs the truth's: {:.3} deg, {:.2} mm at the marker",
            marker_rot.angle_to(&truth_rot).to_degrees(),
            (p_m - p_t).norm() * 1e3
        );
    }
    for (k, w) in evaluation.wrists.iter().enumerate() {
        let a = &w.arrangement;
        let (dx, dy) = (
            a.x_m - a_from_b.translation.x,
            a.y_m - a_from_b.translation.y,
        );
        let true_yaw = a_from_b.rotation.scaled_axis().z;
        println!(
            "{}: {} of {} frames saw both markers, {} references, {} scored; arrangement off by \
             ({:.2}, {:.2}) mm, {:.3} deg",
            w.camera,
            w.counts.both,
            w.counts.frames,
            w.references,
            w.independent.frames,
            dx * 1e3,
            dy * 1e3,
            (a.yaw_rad - true_yaw).to_degrees()
        );
        assert!(
            dx.hypot(dy) < 0.002,
            "{}: arrangement {a:?} vs {a_from_b}",
            w.camera
        );
        assert!((a.yaw_rad - true_yaw).abs() < 0.01, "{}: {a:?}", w.camera);
        assert!(
            w.independent.frames >= 30,
            "{}: too few scored frames",
            w.camera
        );

        // The references themselves against the truth, through the first marker's true pose.
        let scored: Vec<&FrameError> = w
            .errors
            .iter()
            .filter(|e| e.phase == Phase::Score)
            .collect();
        let (mut dp, mut dr, mut ratio) = (Vec::new(), Vec::new(), Vec::new());
        for e in &scored {
            let truth = truth_at(&truths[k], e.t_camera);
            let reference = world_from(0) * e.marker_from_cam;
            let true_range = (world_from(0).inverse() * truth).translation.vector.norm();
            ratio.push(e.marker_from_cam.translation.vector.norm() / true_range);
            dp.push((reference.translation.vector - truth.translation.vector).norm());
            dr.push(reference.rotation.angle_to(&truth.rotation).to_degrees());
        }
        println!("{}: range ratio {:.5}", w.camera, median(ratio));
        println!(
            "{}: references off the truth by {:.2} mm, {:.3} deg (median); p90 {:.2} mm",
            w.camera,
            median(dp.clone()) * 1e3,
            median(dr),
            {
                dp.sort_by(f64::total_cmp);
                dp[dp.len() * 9 / 10] * 1e3
            }
        );
        let own_truth_alignment = truth_alignment(&truths[k], &w.errors);
        let truth_errors = |alignment: &Sim3| -> Vec<f64> {
            scored
                .iter()
                .map(|e| {
                    let p = alignment
                        .transform_point(&truth_at(&truths[k], e.t_camera).translation.vector);
                    (e.estimate_scene - p).norm()
                })
                .collect()
        };
        let own = median(truth_errors(&own_truth_alignment));
        let shared = median(truth_errors(&left_truth_alignment));
        let marker_shared = w.shared.unwrap().median_m;
        println!(
            "{}: median error {:.2} mm by the markers, {:.2} mm by the truth; with the left's \
             alignment {:.2} and {:.2} mm",
            w.camera,
            w.independent.median_m * 1e3,
            own * 1e3,
            marker_shared * 1e3,
            shared * 1e3
        );
        assert!(
            (w.independent.median_m - own).abs() <= MAX_DISAGREEMENT_M,
            "{}: {} vs {own}",
            w.camera,
            w.independent.median_m
        );
        // The left-fitted alignment applied to the right hand is not held to the bound: the
        // right's references enter it with their absolute error, and the left's turn its
        // rotation, which the 0.4 m between the hands makes millimetres (docs/evaluate.md).
        // The left's shared figure is its own by definition.
        if k == 0 {
            assert_eq!(marker_shared, w.independent.median_m);
        }
        // Both figures are the medians of the scored frames' own errors.
        assert_eq!(
            median(scored.iter().map(|e| e.error_m).collect()),
            w.independent.median_m
        );
        assert_eq!(
            median(scored.iter().map(|e| e.shared_error_m.unwrap()).collect()),
            marker_shared
        );
        // The scored frames are the last half of the sequence.
        let (t0, t1) = (w.span.t0, w.span.t1);
        assert!(
            scored
                .iter()
                .all(|e| (e.t_camera - t0) / (t1 - t0) >= SCORE_FROM_FRACTION)
        );
        assert_eq!(scored.len(), w.independent.frames);
    }

    // The left-fitted figure with the rotation taken from the orientations (`--align poses`)
    // agrees with the truth's: the positions of a hand that moves little in the first 40 %
    // leave the rotation of a position-only fit weakly held, and the 0.4 m to the other hand
    // turns a few hundredths of a degree into a millimetre (docs/evaluate.md).
    let paired = |k: usize, truth: bool| -> Vec<Paired> {
        evaluation.wrists[k]
            .errors
            .iter()
            .map(|e| Paired {
                t_camera: e.t_camera,
                phase: e.phase,
                marker_from_cam: if truth {
                    world_from(0).inverse() * truth_at(&truths[k], e.t_camera)
                } else {
                    e.marker_from_cam
                },
                scene_from_cam: published_at(&publications[k], e.t_camera),
            })
            .collect()
    };
    let by_poses = |truth: bool| -> f64 {
        let alignment = fit_alignment(&paired(0, truth), AlignmentKind::Poses).unwrap();
        median(
            paired(1, truth)
                .iter()
                .filter(|p| p.phase == Phase::Score)
                .map(|p| {
                    (p.scene_from_cam.translation.vector
                        - alignment.transform_point(&p.marker_from_cam.translation.vector))
                    .norm()
                })
                .collect(),
        )
    };
    let (marker_poses, truth_poses) = (by_poses(false), by_poses(true));
    println!(
        "right with the left's alignment by poses: {:.2} mm by the markers, {:.2} mm by the truth",
        marker_poses * 1e3,
        truth_poses * 1e3
    );
    assert!((marker_poses - truth_poses).abs() <= MAX_DISAGREEMENT_M);

    // The command refuses what it cannot use before it searches a frame, naming the fix.
    let kiwi = env!("CARGO_BIN_EXE_kiwi");
    let toml = root.join("session.toml");
    for (args, expected) in [
        (
            vec!["--episode", episode.as_str(), "--ids", "20"],
            "--ids takes the two markers' ids",
        ),
        (vec!["--episode", "nope"], "no episode `nope`"),
        (
            vec!["--episode", episode.as_str(), "--size-mm", "-58"],
            "--size-mm",
        ),
        (
            vec!["--episode", episode.as_str(), "--ids", "20,20"],
            "two distinct ids",
        ),
        (
            vec!["--episode", episode.as_str(), "--ids", "20,50"],
            "not in dictionary 4x4_50",
        ),
        (
            vec!["--episode", episode.as_str(), "--dictionary", "7x7_9"],
            "is not one KIWI reads",
        ),
    ] {
        let out = std::process::Command::new(kiwi)
            .args(["evaluate", "markers", "--session"])
            .arg(&toml)
            .args(&args)
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{args:?} succeeded");
        assert!(stderr.contains(expected), "{args:?}: {stderr}");
    }
}
