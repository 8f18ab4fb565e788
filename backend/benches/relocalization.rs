//! Relocalization in rooms and along paths the mapping did not take, measured against the
//! simulator's truth: per room kind and seed, a hand-held mapping scan (`scan`) builds a map of
//! one lens, and a later visit (`revisit`: centred 0.3 m away, heading offset and sweeping
//! differently, other lighting) is localized in it. Printed per room: the map (keyframes, loops,
//! keyframe ATE), the query (localized share, time to the first pose, position errors after the
//! map's Sim(3), poses over 5 cm, lost reasons), relocalization cost (ms per attempt, attempts
//! per lost second), throughput (frames per CPU second), and, with `KIWI_RELOC_DIAGNOSE=N`, a
//! truth diagnosis of relocalization attempts on the query's first N frames (retrieved
//! keyframes against the right ones, correct 2D-3D matches that exist against those found).
//!
//! Settings (environment): `KIWI_RELOC_ROOMS` (`photos:1,kitchen:2,...`, default
//! `photos:1`), `KIWI_RELOC_RES` (px, default 640), `KIWI_RELOC_LENS` (`left/front`),
//! `KIWI_RELOC_MAP` (`seconds@fps`, default `24@15`), `KIWI_RELOC_QUERY` (default `12@30`),
//! `KIWI_RELOC_QUERY_GAIN` (lighting of the query, default 0.8), `KIWI_RELOC_DIR` (render the
//! sessions once into this folder and reuse them), `KIWI_RELOC_DIAGNOSE` (frames, default 0;
//! every `KIWI_RELOC_DIAGNOSE_STEP`-th of them, default 5),
//! `KIWI_RELOC_BASELINE=1` (the localizer as it was before rectified descriptors: raw-image
//! descriptors in map and query, a 45-inlier hypothesis, one view-blind densification round,
//! relocalization every 4th frame after two failures, no view-support or uniqueness rule, no
//! whole-map attempt), `KIWI_RELOC_MIN_UNIQUE` (unique inlier landmarks a relocalization
//! needs; 0 turns the uniqueness rule off), `KIWI_RELOC_MAP_CANDIDATES` (look-alike landmarks per keypoint of the whole-map
//! attempt; 0 turns it off), `KIWI_RELOC_MAP_ONLY=1` (build and check the maps, no query),
//! `KIWI_RELOC_SERVE_UNTRUSTED=1` (localize even in a map its own check refused, to see what
//! it would give), `KIWI_RELOC_MAP_ATTEMPTS` (whole-map attempts per lost run),
//! `KIWI_RELOC_FRAMES=1` (every query frame's status, inliers and full reason),
//! `KIWI_RELOC_LOG` (a log filter, e.g. `kiwi_backend::vision::runs=debug` for every meeting of
//! two runs),
//! `KIWI_RELOC_GUIDED_VIEWS=0` (guided matching against representative descriptors only),
//! `KIWI_RELOC_TOPUP_BY_VIEW=0` (tracking's top-up from the keyframes nearest in centre),
//! `KIWI_RELOC_DENSIFY_UNCERTAIN=0` (a poorly constrained tracked pose is refused at once),
//! `KIWI_RELOC_AFFINE=1|0` (affine-normalised rectified patches in map and query, or not),
//! `KIWI_RELOC_GLOBAL_SHUTTER=1` (render without rolling shutter; use another
//! `KIWI_RELOC_DIR`), `KIWI_RELOC_ROTATED_VARIANTS=1` (the diagnosis's query variants turned by
//! a few degrees instead of tilted).

#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

use std::time::Instant;

#[path = "../tests/common/mod.rs"]
mod common;
use common::reloc::{
    Alignment, Take, describe_attempt, diagnose_attempt, room_session, truth_poses,
};

use kiwi_backend::vision::align::trajectory_error;
use kiwi_backend::vision::episode::{LensStream, build_map_with_orb, localize_stream};
use kiwi_backend::vision::localize::{LocalizationStatus, LocalizerOptions, is_refused_as_copy};
use kiwi_backend::vision::runs::{STEP_ALLOWANCE_DEPTHS, is_withdrawn, step_between};
use kiwi_fixtures::scenario::Scenario;
use kiwi_fixtures::scene::{RoomKind, Scene, SceneOptions};

fn cpu_seconds() -> f64 {
    let Ok(text) = std::fs::read_to_string("/proc/self/stat") else {
        return f64::NAN;
    };
    let Some(i) = text.rfind(')') else {
        return f64::NAN;
    };
    let f: Vec<&str> = text[i + 2..].split_whitespace().collect();
    let ticks: f64 = f
        .get(11)
        .and_then(|x| x.parse::<f64>().ok())
        .unwrap_or(f64::NAN)
        + f.get(12)
            .and_then(|x| x.parse::<f64>().ok())
            .unwrap_or(f64::NAN);
    ticks / 100.0
}

fn env(name: &str, default: &str) -> String {
    std::env::var(name).unwrap_or_else(|_| default.to_string())
}

fn take(spec: &str, scenario: Scenario, light_gain: f32) -> Take {
    let (s, f) = spec.split_once('@').expect("seconds@fps");
    Take {
        scenario,
        seconds: s.parse().unwrap(),
        fps: f.parse().unwrap(),
        light_gain,
    }
}

fn room_kind(name: &str) -> RoomKind {
    match name {
        "studio" => RoomKind::Studio,
        "photos" => RoomKind::Photos,
        "kitchen" => RoomKind::Kitchen,
        "workshop" => RoomKind::Workshop,
        "divided" => RoomKind::Divided,
        other => panic!("unknown room {other}"),
    }
}

fn main() {
    if std::env::args().any(|a| a == "--list") {
        return;
    }
    if let Ok(filter) = std::env::var("KIWI_RELOC_LOG") {
        tracing_subscriber::fmt()
            .with_env_filter(tracing_subscriber::EnvFilter::new(filter))
            .init();
    }
    let rooms = env("KIWI_RELOC_ROOMS", "photos:1");
    let resolution: u32 = env("KIWI_RELOC_RES", "640").parse().unwrap();
    let lens_spec = env("KIWI_RELOC_LENS", "left/front");
    let (camera, lens) = lens_spec.split_once('/').unwrap();
    let query_gain: f32 = env("KIWI_RELOC_QUERY_GAIN", "0.8").parse().unwrap();
    let map_take = take(&env("KIWI_RELOC_MAP", "24@15"), Scenario::Scan, 1.0);
    let query_take = take(
        &env("KIWI_RELOC_QUERY", "12@30"),
        Scenario::Revisit,
        query_gain,
    );
    let diagnose: usize = env("KIWI_RELOC_DIAGNOSE", "0").parse().unwrap();
    let diagnose_step: usize = env("KIWI_RELOC_DIAGNOSE_STEP", "5")
        .parse::<usize>()
        .unwrap()
        .max(1);
    let keep = std::env::var("KIWI_RELOC_DIR").ok();
    let tmp = tempfile::tempdir().unwrap();
    let root = keep
        .as_deref()
        .map_or_else(|| tmp.path().to_path_buf(), std::path::PathBuf::from);
    println!(
        "relocalization bench: {resolution} px, lens {lens_spec}, map {:?} s @ {} Hz, query {:?} s @ {} Hz (light {query_gain})",
        map_take.seconds, map_take.fps, query_take.seconds, query_take.fps
    );
    let baseline = env("KIWI_RELOC_BASELINE", "0") == "1";
    let mut options = LocalizerOptions::default();
    if baseline {
        options.orb.rectified = false;
        options.relocalization_hypothesis_inliers = options.min_inliers_relocalization;
        options.relocalization_guided_rounds = 2;
        options.relocalization_eager_s = 0.0;
        options.min_view_support = 0.0;
        options.min_unique_inliers = 0;
        options.relocalization_map_candidates = 0;
        options.relocalization_guided_keyframes = options.guided_keyframes;
        options.guided_views = false;
        options.topup_by_view = false;
        options.densify_uncertain = false;
        println!("baseline: {options:?}");
    }
    if let Ok(a) = std::env::var("KIWI_RELOC_AFFINE") {
        options.orb.affine_adapted = a == "1";
    }
    if env("KIWI_RELOC_SERVE_UNTRUSTED", "0") == "1" {
        options.serve_untrusted_map = true;
    }
    if let Ok(k) = std::env::var("KIWI_RELOC_MAP_CANDIDATES") {
        options.relocalization_map_candidates = k.parse().unwrap();
    }
    if env("KIWI_RELOC_GUIDED_VIEWS", "1") == "0" {
        options.guided_views = false;
    }
    if env("KIWI_RELOC_TOPUP_BY_VIEW", "1") == "0" {
        options.topup_by_view = false;
    }
    if env("KIWI_RELOC_DENSIFY_UNCERTAIN", "1") == "0" {
        options.densify_uncertain = false;
    }
    if let Ok(k) = std::env::var("KIWI_RELOC_MIN_UNIQUE") {
        options.min_unique_inliers = k.parse().unwrap();
    }
    if let Ok(k) = std::env::var("KIWI_RELOC_MAP_ATTEMPTS") {
        options.relocalization_map_attempts = k.parse().unwrap();
    }
    let print_frames = env("KIWI_RELOC_FRAMES", "0") == "1";
    for spec in rooms.split(',') {
        let (kind, seed) = spec.split_once(':').unwrap();
        let (kind, seed) = (room_kind(kind), seed.parse::<u64>().unwrap());
        let tag = format!(
            "{}-{seed}-{resolution}{}",
            kind.name(),
            if baseline { "-baseline" } else { "" }
        );
        let session_tag = format!("{}-{seed}-{resolution}", kind.name());
        let started = Instant::now();
        let mapping = room_session(
            &root,
            &format!("{session_tag}-scan"),
            kind,
            seed,
            resolution,
            &lens_spec,
            map_take,
        );
        let query = room_session(
            &root,
            &format!("{session_tag}-revisit"),
            kind,
            seed,
            resolution,
            &lens_spec,
            query_take,
        );
        let render_s = started.elapsed().as_secs_f64();
        let stream = LensStream::open(&mapping, camera, lens, None, None).unwrap();
        let (cpu0, t0) = (cpu_seconds(), Instant::now());
        let (map, summary) =
            build_map_with_orb(&stream, true, &options.orb, &mut |_, _| {}).unwrap();
        let (map_cpu, map_wall) = (cpu_seconds() - cpu0, t0.elapsed().as_secs_f64());
        let mapping_truth = truth_poses(&mapping, camera, lens);
        let alignment = Alignment::new(&map, &mapping_truth);
        let (est, tru): (Vec<_>, Vec<_>) = map
            .keyframes
            .iter()
            .map(|k| {
                (
                    k.cam_from_map
                        .to_pose()
                        .unwrap()
                        .inverse()
                        .translation
                        .vector,
                    common::reloc::pose_at(&mapping_truth, k.t)
                        .translation
                        .vector,
                )
            })
            .unzip();
        let ate = trajectory_error(&alignment.sim, &est, &tru).unwrap();
        println!(
            "\n[{tag}] rendered in {render_s:.0} s; map: {}/{} frames tracked, {} keyframes, {} landmarks, {} loops closed, keyframe ATE {:.1} mm = {:.3} % of {:.2} m; {:.0} s wall, {:.0} s CPU",
            summary.frames_tracked,
            summary.frames,
            summary.keyframes,
            summary.landmarks,
            summary.loops_closed,
            ate.rmse * 1e3,
            100.0 * ate.rmse / ate.extent,
            ate.extent,
            map_wall,
            map_cpu
        );
        println!("[{tag}] map quality: {}", summary.quality);
        if env("KIWI_RELOC_MAP_ONLY", "0") == "1" {
            continue;
        }
        let qstream = LensStream::open(&query, camera, lens, None, None).unwrap();
        let qtruth = truth_poses(&query, camera, lens);
        let (cpu0, t0) = (cpu_seconds(), Instant::now());
        let (results, s) = localize_stream(&map, &qstream, &options, &mut |_, _| {}).unwrap();
        let (loc_cpu, loc_wall) = (cpu_seconds() - cpu0, t0.elapsed().as_secs_f64());
        // Each posed frame's position error against the truth (m), once.
        let errors: Vec<Option<f64>> = results
            .iter()
            .map(|r| {
                r.map_from_cam.map(|p| {
                    (alignment.world_from_cam(&p).translation.vector
                        - common::reloc::pose_at(&qtruth, r.t).translation.vector)
                        .norm()
                })
            })
            .collect();
        let mut e: Vec<f64> = errors.iter().flatten().copied().collect();
        e.sort_by(f64::total_cmp);
        let first = results
            .iter()
            .find(|r| r.status != LocalizationStatus::Lost)
            .map(|r| r.t - results[0].t);
        let withdrawn = (results.iter()).filter(|f| is_withdrawn(f)).count();
        let refused_as_copy = (results.iter()).filter(|f| is_refused_as_copy(f)).count();
        let mut reasons: std::collections::BTreeMap<String, usize> = Default::default();
        for r in results
            .iter()
            .filter(|r| r.status == LocalizationStatus::Lost)
        {
            let key: String = r.reason.chars().take(60).collect();
            *reasons.entry(key).or_default() += 1;
        }
        println!(
            "[{tag}] query: {}/{} localized ({:.1} %: {} tracked, {} relocalized), first pose after {}, median {} inliers; error median {:.1} mm, worst {:.1} mm, {} over 5 cm, {withdrawn} withdrawn, {refused_as_copy} refused as a copy; {:.1} s wall, {:.1} frames per CPU s",
            s.localized,
            s.frames,
            100.0 * s.localized_fraction,
            s.tracked,
            s.relocalized,
            first.map_or("never".into(), |t| format!("{t:.2} s")),
            s.median_inliers,
            e.get(e.len() / 2).map_or(f64::NAN, |x| x * 1e3),
            e.last().map_or(f64::NAN, |x| x * 1e3),
            e.iter().filter(|&&x| x > 0.05).count(),
            loc_wall,
            s.frames as f64 / loc_cpu
        );
        println!(
            "[{tag}] relocalization: {} attempts, {:.1} ms per attempt, {:.1} attempts per lost second",
            s.relocalization_attempts,
            s.relocalization_ms_per_attempt,
            s.relocalization_attempts_per_lost_second
        );
        // What the run check's carried step is on runs at the right place: every four
        // consecutive poses of one run (the last three tracked) within 5 cm of the truth, as if
        // the run were split in the middle.
        let depth = kiwi_backend::vision::localize::median_keyframe_depth(&map).unwrap();
        let centre = |k: usize| {
            let p = results[k].map_from_cam.unwrap();
            (results[k].t, p.translation.vector / depth)
        };
        let mut steps: Vec<f64> = (0..results.len().saturating_sub(3))
            .filter(|&k| {
                (k..k + 4).all(|i| errors[i].is_some_and(|x| x < 0.05))
                    && (k + 1..k + 4).all(|i| results[i].status == LocalizationStatus::Tracked)
            })
            .filter_map(|k| {
                step_between([centre(k + 1), centre(k)], [centre(k + 2), centre(k + 3)])
            })
            .collect();
        steps.sort_by(f64::total_cmp);
        let pct = |q: f64| steps.get(((steps.len() as f64 - 1.0) * q).round() as usize);
        println!(
            "[{tag}] carried step within right runs (median map depth {depth:.3}): {} splits, median {:.4}, p99 {:.4}, max {:.4} depths, {} over the allowance {STEP_ALLOWANCE_DEPTHS}",
            steps.len(),
            pct(0.5).copied().unwrap_or(f64::NAN),
            pct(0.99).copied().unwrap_or(f64::NAN),
            steps.last().copied().unwrap_or(f64::NAN),
            steps.iter().filter(|&&x| x > STEP_ALLOWANCE_DEPTHS).count()
        );
        for (r, n) in reasons.iter().take(6) {
            println!("[{tag}]   lost {n}: {r}");
        }
        if print_frames {
            for (r, e) in results.iter().zip(&errors) {
                let error = e.map_or(String::new(), |x| format!("error {:.1} mm ", x * 1e3));
                println!(
                    "[{tag}] frame {} t {:.3} {} {} inliers {error}{}",
                    r.frame,
                    r.t,
                    r.status.name(),
                    r.inliers,
                    r.reason
                );
            }
        }
        if diagnose > 0 {
            let scene = Scene::new(seed, SceneOptions::room(kind));
            for f in (0..diagnose.min(results.len())).step_by(diagnose_step) {
                let d = diagnose_attempt(&map, &qstream, &alignment, &qtruth, &scene, f, &options);
                println!("[{tag}] {}", describe_attempt(&d));
            }
        }
    }
}
