//! `kiwi run` benchmark: a mapping episode and a tabletop episode recorded with two units
//! certified from their own simulated captures, reconstructed end to end. Prints the wall time
//! of every stage and in total, the ratio to the recording's duration, localization frames per
//! CPU-second over all four streams, the process's peak memory, and the tool-tip and head
//! accuracy against the simulator's truth (the same alignment as the end-to-end tests; the
//! head's marker track and head camera where the session has the head camera, as simulated
//! sessions do).
//!
//! ```text
//! cargo bench -p kiwi-e2e --bench pipeline            # 960 px, 119.88 Hz, 60 s + 60 s
//! KIWI_BENCH_RESOLUTION=480 KIWI_BENCH_RATE=29.97 KIWI_BENCH_DURATIONS=20,10 \
//!   KIWI_BENCH_DIR=/tmp/kiwi-bench cargo bench -p kiwi-e2e --bench pipeline
//! ```
//! `KIWI_BENCH_DIR` keeps the simulated session between runs (the pipeline's work folders are
//! removed before each measurement); `KIWI_BENCH_THREADS` sets the worker threads (default: the
//! machine's cores).

#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

#[path = "../tests/common/mod.rs"]
mod common;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use common::{SessionSpec, UNITS, alignment, build_session, head_errors, median_p95, tip_errors};
use kiwi_backend::outputs::read_quality;
use kiwi_backend::pipeline::runner::{NoProgress, Outcome, RunReport};
use kiwi_backend::pipeline::{RunOptions, SessionContext, run};
use kiwi_fixtures::scenario::Scenario;

fn env_or<T: std::str::FromStr>(name: &str, default: T) -> T {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

/// CPU time of this process so far (user + system, s), from `/proc/self/stat`.
fn process_cpu_seconds() -> f64 {
    let stat = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    // Fields after the command name (which is in parentheses and may hold spaces).
    let rest = stat.rsplit_once(')').map_or("", |(_, r)| r);
    let fields: Vec<&str> = rest.split_whitespace().collect();
    let ticks = |i: usize| {
        fields
            .get(i)
            .and_then(|v| v.parse::<f64>().ok())
            .unwrap_or(0.0)
    };
    // utime and stime are fields 14 and 15 of the whole line: 12 and 13 after the name.
    (ticks(11) + ticks(12)) / 100.0
}

/// Peak resident memory of this process (MiB), from `/proc/self/status`.
fn peak_memory_mib() -> f64 {
    let status = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<f64>().ok())
        .map_or(f64::NAN, |kb| kb / 1024.0)
}

fn frames_in(session: &Path, episode: &str, camera: &str, lens: &str) -> usize {
    let csv = session
        .join("episodes")
        .join(episode)
        .join(camera)
        .join(lens)
        .join("frames.csv");
    std::fs::read_to_string(csv).map_or(0, |t| {
        t.lines().skip(1).filter(|l| !l.trim().is_empty()).count()
    })
}

fn stage_seconds(report: &RunReport, into: &mut BTreeMap<String, f64>) {
    for s in &report.stages {
        match &s.outcome {
            Outcome::Ran { seconds } => {
                into.insert(s.stage.clone(), *seconds);
            }
            Outcome::Failed { reason } | Outcome::Blocked { reason } => {
                println!("  {} did not finish: {reason}", s.stage);
            }
            Outcome::Current | Outcome::Skipped => {}
        }
    }
}

fn phase(ctx: &SessionContext, only: &[&str], threads: Option<usize>) -> (RunReport, f64, f64) {
    let options = RunOptions {
        only: Some(only.iter().map(ToString::to_string).collect()),
        threads,
        ..RunOptions::default()
    };
    let (cpu, wall) = (process_cpu_seconds(), Instant::now());
    let report = run(ctx, &options, &NoProgress).expect("the pipeline runs");
    (
        report,
        wall.elapsed().as_secs_f64(),
        process_cpu_seconds() - cpu,
    )
}

fn main() {
    // `cargo bench` passes `--bench`; a plain `cargo test` of the bench target only builds it.
    if !std::env::args().any(|a| a == "--bench") {
        return;
    }
    let resolution: u32 = env_or("KIWI_BENCH_RESOLUTION", 960);
    let rate_hz: f64 = env_or("KIWI_BENCH_RATE", 119.88);
    let durations: Vec<f64> = std::env::var("KIWI_BENCH_DURATIONS")
        .unwrap_or_else(|_| "60,60".into())
        .split(',')
        .map(|d| {
            d.trim()
                .parse()
                .expect("KIWI_BENCH_DURATIONS: seconds, comma-separated")
        })
        .collect();
    let threads: Option<usize> = std::env::var("KIWI_BENCH_THREADS")
        .ok()
        .and_then(|v| v.parse().ok());
    let seed: u64 = env_or("KIWI_BENCH_SEED", 23);
    let keep = std::env::var("KIWI_BENCH_DIR").ok().map(PathBuf::from);
    let tmp;
    let dir = match &keep {
        Some(d) => d.clone(),
        None => {
            tmp = tempfile::tempdir().expect("temporary folder");
            tmp.path().to_path_buf()
        }
    };
    let spec = SessionSpec {
        seed,
        resolution,
        rate_hz,
        scenarios: vec![Scenario::Survey, Scenario::Tabletop],
        durations: durations.clone(),
        covers: Vec::new(),
    };
    let marker = dir.join(format!(
        "ready-{resolution}-{rate_hz}-{seed}-{}",
        durations
            .iter()
            .map(ToString::to_string)
            .collect::<Vec<_>>()
            .join("_")
    ));
    let toml = dir.join("session").join("session.toml");
    if !marker.is_file() {
        for sub in ["session", "units", "captures"] {
            let _ = std::fs::remove_dir_all(dir.join(sub));
        }
        let started = Instant::now();
        build_session(&dir, &spec);
        std::fs::write(&marker, b"ok").expect("marker");
        println!(
            "simulated and certified in {:.0} s",
            started.elapsed().as_secs_f64()
        );
    }
    let session = toml.parent().unwrap().to_path_buf();
    let _ = std::fs::remove_dir_all(session.join("work"));
    for ep in ["ep000", "ep001"] {
        for sub in ["work", "out"] {
            let _ = std::fs::remove_dir_all(session.join("episodes").join(ep).join(sub));
        }
    }
    let ctx = SessionContext::load(&toml).expect("session loads");
    println!(
        "kiwi run benchmark: {resolution} px, {rate_hz} Hz, episodes {durations:?} s (survey, \
         tabletop), units {UNITS:?} certified at {resolution} px, {} threads",
        threads.map_or_else(|| "all".to_string(), |t| t.to_string())
    );

    let mut seconds = BTreeMap::new();
    let total = Instant::now();
    let total_cpu = process_cpu_seconds();
    let (r, wall_maps, cpu_maps) = phase(&ctx, &["sync", "map", "tool"], threads);
    stage_seconds(&r, &mut seconds);
    let (r, wall_loc, cpu_loc) = phase(&ctx, &["localize"], threads);
    stage_seconds(&r, &mut seconds);
    let report = run(
        &ctx,
        &RunOptions {
            threads,
            ..RunOptions::default()
        },
        &NoProgress,
    )
    .expect("the pipeline runs");
    stage_seconds(&report, &mut seconds);
    let wall = total.elapsed().as_secs_f64();
    let cpu = process_cpu_seconds() - total_cpu;

    let recording: f64 = durations.iter().sum();
    println!("\nstage wall times (s):");
    for (stage, s) in &seconds {
        println!("  {stage:<36} {s:8.1}");
    }
    let mut frames = 0;
    for ep in ["ep000", "ep001"] {
        for camera in ["left", "right"] {
            for lens in ["front", "rear"] {
                frames += frames_in(&session, ep, camera, lens);
            }
        }
    }
    println!(
        "\nmaps, tool and sync: {wall_maps:.0} s wall, {cpu_maps:.0} CPU-s\n\
         localization: {frames} frames over four streams and two episodes in {wall_loc:.0} s \
         wall, {cpu_loc:.0} CPU-s: {:.1} frames per CPU-second\n\
         total: {wall:.0} s wall ({:.1}x the {recording:.0} s recorded), {cpu:.0} CPU-s; \
         peak memory {:.0} MiB",
        frames as f64 / cpu_loc.max(1e-9),
        wall / recording,
        peak_memory_mib()
    );

    let world_from_scene = alignment(&session);
    println!("\naccuracy against the truth (one SE(3) alignment fitted on ep000 left):");
    for ep in ["ep000", "ep001"] {
        let verdict = read_quality(&session.join("episodes").join(ep).join("out/quality.json"))
            .map_or_else(
                |e| format!("no quality record: {e}"),
                |q| format!("{} {:?}", q.verdict.as_str(), q.reasons),
            );
        println!("  {ep}: {verdict}");
        for camera in ["left", "right"] {
            let e = tip_errors(&session, ep, camera, &world_from_scene, None);
            if e.position.is_empty() {
                println!("    {camera}: no frames");
                continue;
            }
            let (pm, p95) = median_p95(e.position.clone());
            let (rm, _) = median_p95(e.rotation_deg.clone());
            println!(
                "    {camera}: {} frames, tool tip median {:.1} mm, p95 {:.1} mm, rotation \
                 median {rm:.2} deg",
                e.frames,
                pm * 1e3,
                p95 * 1e3
            );
        }
        if let Some(h) = head_errors(&session, ep, &world_from_scene) {
            let stats = |p: &[f64], r: &[f64]| {
                if p.is_empty() {
                    return "none compared".to_string();
                }
                let (pm, p95) = median_p95(p.to_vec());
                let (rm, r95) = median_p95(r.to_vec());
                let worst = p.iter().copied().fold(0.0f64, f64::max);
                let worst_r = r.iter().copied().fold(0.0f64, f64::max);
                format!(
                    "position median {:.1} mm, p95 {:.1} mm, worst {:.1} mm; rotation median \
                     {rm:.2} deg, p95 {r95:.2} deg, worst {worst_r:.2} deg",
                    pm * 1e3,
                    p95 * 1e3,
                    worst * 1e3
                )
            };
            println!(
                "    head marker: {} of {} samples posed; {}\n    head camera: {} of {} frames \
                 posed; {}",
                h.posed,
                h.samples,
                stats(&h.position, &h.rotation_deg),
                h.camera_posed,
                h.camera_frames,
                stats(&h.camera_position, &h.camera_rotation_deg)
            );
        }
    }
}
