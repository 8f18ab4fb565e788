//! Vision building blocks at the X5's 960 × 960 per-lens resolution, one OpenCV thread: ORB
//! extraction, KLT tracking, descriptor matching, P3P RANSAC, and the per-frame budget they
//! imply against the target of ≥ 30 (aim 60) localized frames per second per core.
//! Prints median wall times over repeated runs.
//!
//! Then the end-to-end run: the simulator writes a mapping session and a tabletop session of
//! the same room at 960 px, 30 Hz, with motion blur (`KIWI_BENCH_VISION_SECONDS`, default 1 s;
//! the acceptance run is 60 s, which takes hours to render on two cores), `build_map`
//! maps each wrist-0 lens, and every front/rear stream of both wrists of the tabletop episode is
//! localized against the left maps on one thread (one OpenCV thread, a rayon pool of one):
//! mapping time, keyframe ATE after Sim(3), localized fractions, position errors after the
//! map's Sim(3) and throughput in frames per second per core (image decoding included).

#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use std::time::Instant;

use kiwi_backend::vision::features::{
    FOV_MASK_MARGIN_RAD, GrayImage, KltOptions, MatchOptions, OrbExtractor, OrbOptions, fov_mask,
    match_descriptors, track_klt,
};
use kiwi_backend::vision::geometry::{RansacOptions, absolute_pose_ransac};
use kiwi_core::geometry::{Pose, so3_exp};
use kiwi_fixtures::render::{Extras, LensRays, RenderOptions, render};
use kiwi_fixtures::scene::{Scene, SceneOptions};
use kiwi_fixtures::unit::{LensModel, SimUnit};
use nalgebra::{Matrix3, Point2, Rotation3, Translation3, UnitQuaternion, Vector3};

fn pose(dx: f64) -> Pose {
    let base = Matrix3::new(1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, -1.0, 0.0);
    let tilt = so3_exp(&Vector3::new(-0.35, 0.0, 0.0));
    let r = tilt * UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(base));
    Pose::from_parts(Translation3::new(dx, -0.6, 1.3), r)
}

fn median_ms(mut f: impl FnMut(), runs: usize) -> f64 {
    let mut t: Vec<f64> = (0..runs)
        .map(|_| {
            let s = Instant::now();
            f();
            s.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    t.sort_by(f64::total_cmp);
    t[t.len() / 2]
}

/// `(t, camera centre)` rows of a truth pose file.
fn truth(episode: &std::path::Path, camera: &str, lens: &str) -> Vec<(f64, Vector3<f64>)> {
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

fn at(rows: &[(f64, Vector3<f64>)], t: f64) -> Vector3<f64> {
    rows.iter()
        .min_by(|a, b| (a.0 - t).abs().total_cmp(&(b.0 - t).abs()))
        .map(|r| r.1)
        .unwrap()
}

fn end_to_end() {
    use kiwi_backend::vision::align::{trajectory_error, umeyama};
    use kiwi_backend::vision::episode::{LensStream, build_map, localize_stream};
    use kiwi_backend::vision::localize::LocalizerOptions;
    use kiwi_fixtures::scenario::Scenario;
    use kiwi_fixtures::session::{SessionOptions, write_session};

    let seconds: f64 = std::env::var("KIWI_BENCH_VISION_SECONDS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(1.0);
    let dir = tempfile::tempdir().unwrap();
    let write = |name: &str, scenario: Scenario| {
        let mut o = SessionOptions::new(dir.path().join(name));
        o.seed = 7;
        o.scenario = scenario;
        o.duration_s = seconds;
        o.resolution = 960;
        o.rate_hz = 30.0;
        o.blur_samples = 2;
        o.head = false;
        let s = Instant::now();
        write_session(&o).unwrap();
        println!(
            "  simulated {name} session ({seconds} s at 30 Hz, 960 px, blur): {:.0} s",
            s.elapsed().as_secs_f64()
        );
        dir.path().join(name).join("episodes").join("ep000")
    };
    println!("end to end at 960x960 (one thread):");
    let mapping = write("mapping", Scenario::Mapping);
    let tabletop = write("tabletop", Scenario::Tabletop);
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap();
    for lens in ["front", "rear"] {
        let stream = LensStream::open(&mapping, "left", lens, None, None).unwrap();
        let (map, summary) = pool.install(|| build_map(&stream, &mut |_, _| {})).unwrap();
        let rows = truth(&mapping, "left", lens);
        let est: Vec<Vector3<f64>> = map
            .keyframes
            .iter()
            .map(|k| {
                k.cam_from_map
                    .to_pose()
                    .unwrap()
                    .inverse()
                    .translation
                    .vector
            })
            .collect();
        let tru: Vec<Vector3<f64>> = map.keyframes.iter().map(|k| at(&rows, k.t)).collect();
        let sim = umeyama(&est, &tru, true).unwrap();
        let ate = trajectory_error(&sim, &est, &tru).unwrap();
        println!(
            "  map left {lens}: {} of {} frames, {} keyframes, {} landmarks, {:.1} s; keyframe \
             ATE {:.2} mm = {:.3} % of the extent",
            summary.frames_tracked,
            summary.frames,
            summary.keyframes,
            summary.landmarks,
            summary.seconds,
            ate.rmse * 1e3,
            100.0 * ate.relative_rmse()
        );
        for camera in ["left", "right"] {
            let query = LensStream::open(&tabletop, camera, lens, None, None).unwrap();
            let (results, s) = pool
                .install(|| {
                    localize_stream(&map, &query, &LocalizerOptions::default(), &mut |_, _| {})
                })
                .unwrap();
            let rows = truth(&tabletop, camera, lens);
            let mut e: Vec<f64> = results
                .iter()
                .filter_map(|r| {
                    r.map_from_cam.map(|p| {
                        (sim.transform_point(&p.translation.vector) - at(&rows, r.t)).norm()
                    })
                })
                .collect();
            e.sort_by(f64::total_cmp);
            println!(
                "  localize {camera} {lens} in the left {lens} map: {}/{} = {:.2} % ({} \
                 relocalized), median {} inliers, error median {:.1} mm, worst {:.1} mm, {} \
                 over 5 cm; {:.1} frames/s per core",
                s.localized,
                s.frames,
                100.0 * s.localized_fraction,
                s.relocalized,
                s.median_inliers,
                e.get(e.len() / 2).copied().unwrap_or(f64::NAN) * 1e3,
                e.last().copied().unwrap_or(f64::NAN) * 1e3,
                e.iter().filter(|&&x| x > 0.05).count(),
                s.frames_per_second
            );
        }
    }
}

fn main() {
    opencv::core::set_num_threads(1).unwrap();
    let size = 960;
    let unit = SimUnit::x5("X5-BENCH", 1, size, LensModel::Kb4).unwrap();
    let camera = unit.lenses[0].camera.clone();
    let rays = LensRays::new(&camera);
    let scene = Scene::new(1, SceneOptions::default());
    let shoot = |dx: f64, key: u64| {
        let p = pose(dx);
        let o = RenderOptions {
            noise_key: key,
            ..RenderOptions::default()
        };
        let img = render(&scene, &rays, &|_t| p, 0.0, &Extras::default(), &o);
        GrayImage::from_rgb(img.width(), img.height(), img.as_raw()).unwrap()
    };
    // 8 mm between frames: a hand moving at 1 m/s filmed at 120 Hz.
    let (a, b) = (shoot(0.0, 1), shoot(0.008, 2));
    let mask = fov_mask(&camera, FOV_MASK_MARGIN_RAD);
    let mut orb = OrbExtractor::new(&OrbOptions::default()).unwrap();
    let mut fa = Default::default();
    let orb_ms = median_ms(|| fa = orb.extract(&a, Some(&mask), &camera).unwrap(), 9);
    let fb = orb.extract(&b, Some(&mask), &camera).unwrap();
    let pts: Vec<Point2<f64>> = fa.keypoints.iter().take(600).map(|k| k.pixel).collect();
    let klt_ms = median_ms(
        || {
            track_klt(&a, &b, &pts, Some(&mask), &camera, &KltOptions::default()).unwrap();
        },
        9,
    );
    let mut matches = Vec::new();
    let match_ms = median_ms(
        || matches = match_descriptors(&fa.descriptors, &fb.descriptors, &MatchOptions::default()),
        9,
    );
    // P3P RANSAC on true 3-D points of the matched bearings (depth from the scene).
    let world_from_cam = pose(0.0);
    let cam_b = pose(0.008).inverse();
    let mut bearings = Vec::new();
    let mut points = Vec::new();
    for m in &matches {
        let ray = fa.keypoints[m.query].bearing;
        let dir = world_from_cam.rotation * ray;
        let origin = world_from_cam.translation.vector;
        let hit = scene.intersect(
            [origin.x as f32, origin.y as f32, origin.z as f32],
            [dir.x as f32, dir.y as f32, dir.z as f32],
        );
        if hit.distance.is_finite() {
            let p = origin + dir * f64::from(hit.distance);
            bearings.push(fb.keypoints[m.train].bearing);
            points.push(p);
        }
    }
    let pnp_ms = median_ms(
        || {
            absolute_pose_ransac(&bearings, &points, &RansacOptions::default());
        },
        9,
    );
    let est = absolute_pose_ransac(&bearings, &points, &RansacOptions::default());
    let pnp_err_mm = est.map_or(f64::NAN, |e| {
        (e.cam_from_world.inverse().translation.vector - cam_b.inverse().translation.vector).norm()
            * 1e3
    });
    println!("vision blocks at {size}x{size}, one OpenCV thread (median of 9 runs):");
    println!(
        "  ORB extract ({} keypoints):          {orb_ms:7.2} ms",
        fa.keypoints.len()
    );
    println!("  KLT track 600 points (fwd+bwd):      {klt_ms:7.2} ms");
    println!(
        "  Hamming match {}x{} (mutual+ratio): {match_ms:7.2} ms ({} matches)",
        fa.descriptors.len(),
        fb.descriptors.len(),
        matches.len()
    );
    println!(
        "  P3P RANSAC + refine ({} pairs):      {pnp_ms:7.2} ms (position error {pnp_err_mm:.1} mm)",
        bearings.len()
    );
    let tracked = klt_ms + pnp_ms;
    println!(
        "  tracked-frame budget (KLT + P3P):    {tracked:7.2} ms -> {:.0} frames/s per core",
        1e3 / tracked
    );
    println!(
        "  relocalization (ORB + match + P3P):  {:7.2} ms -> {:.0} frames/s per core",
        orb_ms + match_ms + pnp_ms,
        1e3 / (orb_ms + match_ms + pnp_ms)
    );
    end_to_end();
}
