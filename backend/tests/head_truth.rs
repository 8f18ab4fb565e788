//! The head's track from a simulated session's rear streams, with the wrists' poses taken from
//! the simulator's truth (paper §4.3.2, developed on truth before it runs on fused poses): the
//! hat marker is found in both rear lenses, posed by IPPE, turned into scene observations and
//! fused, and the track is compared with the simulator's `head_marker_poses.csv`.

#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

use std::path::Path;

use nalgebra::{Quaternion, Translation3, UnitQuaternion};

use kiwi_backend::frames::FrameSource;
use kiwi_backend::head::marker::{MarkerFinder, Resolved, resolve, square_poses};
use kiwi_backend::head::track::{HeadObservation, TrackOptions, fuse, observe};
use kiwi_core::artifact::UnitCalibration;
use kiwi_core::geometry::Pose;
use kiwi_core::layout::{EpisodeLayout, Session, Side};
use kiwi_fixtures::scenario::Scenario;
use kiwi_fixtures::session::{HAT_MARKER_ID, HAT_MARKER_SIZE_M, SessionOptions, write_session};

/// The bounds where the marker is observed.
const MAX_POSITION_ERROR_M: f64 = 0.01;
const MAX_ROTATION_ERROR_RAD: f64 = 0.017_453_292_5;

/// Rows `t_session, pose` of a truth CSV whose columns include `t_session,px,py,pz,qx,qy,qz,qw`.
fn truth_poses(path: &Path) -> Vec<(f64, Pose)> {
    let text = std::fs::read_to_string(path).unwrap();
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    let col = |name: &str| header.iter().position(|h| *h == name).unwrap();
    let (ts, px) = (col("t_session"), col("px"));
    lines
        .map(|l| {
            let v: Vec<f64> = l.split(',').map(|x| x.parse().unwrap()).collect();
            let q = UnitQuaternion::from_quaternion(Quaternion::new(
                v[px + 6],
                v[px + 3],
                v[px + 4],
                v[px + 5],
            ));
            (
                v[ts],
                Pose::from_parts(Translation3::new(v[px], v[px + 1], v[px + 2]), q),
            )
        })
        .collect()
}

/// The truth pose at `t` (linear on the 100 Hz truth rows).
fn at(rows: &[(f64, Pose)], t: f64) -> Pose {
    let k = rows.partition_point(|r| r.0 <= t).clamp(1, rows.len() - 1);
    let (a, b) = (&rows[k - 1], &rows[k]);
    let s = ((t - a.0) / (b.0 - a.0)).clamp(0.0, 1.0);
    a.1.lerp_slerp(&b.1, s)
}

#[test]
fn the_head_track_from_both_rear_lenses_matches_the_truth() {
    let tmp = tempfile::tempdir().unwrap();
    let mut o = SessionOptions::new(tmp.path());
    o.seed = 21;
    // The paper's processing resolution: at 480 px the 8 cm marker 0.7 m away spans 16 px and
    // IPPE's rotation errs by 5-30°.
    o.resolution = 960;
    o.rate_hz = 29.97;
    o.episodes = 1;
    o.duration_s = 3.0;
    o.scenario = Scenario::Tabletop;
    o.head = true;
    o.rolling_shutter = false;
    o.only_lenses = vec!["left/rear".into(), "right/rear".into()];
    let written = write_session(&o).unwrap();
    let root = written.session_toml.parent().unwrap();
    let episode = EpisodeLayout::new(root.join("episodes").join(&written.episodes[0]));
    let truth_dir = episode.truth_dir();
    let head_truth = truth_poses(&truth_dir.join("head_marker_poses.csv"));
    let session = Session::load(&written.session_toml).unwrap();

    let mut observations = Vec::new();
    let (mut frames, mut found, mut ambiguous) = (0, 0, 0);
    for side in [Side::Left, Side::Right] {
        let camera = side.camera_name();
        // The exact calibration the simulator keeps beside its truth.
        let unit = &session.wrists[&side].unit;
        let cal =
            UnitCalibration::load(&root.join("truth/units").join(unit).join("calibration.json"))
                .unwrap();
        let lens = cal.lens("rear").unwrap().camera().unwrap();
        let finder = MarkerFinder::new(lens, "4x4_50", HAT_MARKER_ID).unwrap();
        let rear_truth = truth_poses(&truth_dir.join(camera).join("rear_poses.csv"));
        let source = FrameSource::open(&episode.lens_dir(camera, "rear")).unwrap();
        let mut previous: Option<Pose> = None;
        for (i, (t_session, scene_from_rear)) in rear_truth.iter().enumerate() {
            frames += 1;
            let image = source.load_color(i).unwrap();
            let Some(corners) = finder.find(&image).unwrap() else {
                continue;
            };
            found += 1;
            let Some(poses) = square_poses(&corners, HAT_MARKER_SIZE_M).unwrap() else {
                continue;
            };
            let resolved = resolve(&poses, previous.as_ref());
            if resolved == Resolved::Ambiguous {
                ambiguous += 1;
            }
            let Some(p) = resolved.pose() else {
                continue;
            };
            previous = Some(p.cam_from_marker);
            observations.push(HeadObservation {
                t_session: *t_session,
                side,
                scene_from_marker: observe(scene_from_rear, &Pose::identity(), &p.cam_from_marker),
            });
        }
    }
    let t0 = head_truth[0].0;
    let t1 = head_truth[head_truth.len() - 1].0;
    let track = fuse(&observations, t0, t1, &TrackOptions::default());
    let (mut worst_p, mut worst_r, mut posed) = (0.0f64, 0.0f64, 0);
    for s in &track {
        let Some(p) = s.scene_from_marker else {
            continue;
        };
        posed += 1;
        let truth = at(&head_truth, s.t_session);
        worst_p = worst_p.max((p.translation.vector - truth.translation.vector).norm());
        worst_r = worst_r.max(p.rotation.angle_to(&truth.rotation));
    }
    eprintln!(
        "{found} sightings in {frames} rear frames ({ambiguous} ambiguous), {} observations; \
         {posed} of {} track samples posed; worst {:.2} mm, {:.3} deg",
        observations.len(),
        track.len(),
        worst_p * 1e3,
        worst_r.to_degrees()
    );
    assert!(
        posed * 2 > track.len(),
        "the head is tracked most of the time"
    );
    assert!(worst_p < MAX_POSITION_ERROR_M, "{worst_p} m");
    assert!(
        worst_r < MAX_ROTATION_ERROR_RAD,
        "{} deg",
        worst_r.to_degrees()
    );
}
