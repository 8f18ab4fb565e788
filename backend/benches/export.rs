//! Export speed: seconds of `kiwi export` work per minute of recording, for each format, on a
//! synthetic two-wrist session (front lenses at 29.97 Hz stored as PNG frames; the trajectories
//! and openings of `tests/support/export_session.rs`). The scene format (COLMAP, with a mask per
//! image) runs on a second session with both lenses per wrist and maps.
//!
//! `KIWI_BENCH_DURATION` (s, default 60) and `KIWI_BENCH_RESOLUTION` (px, square, default 480)
//! change the setting; `KIWI_BENCH_DIR` keeps the session and exports there.

#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

#[path = "../tests/support/export_session.rs"]
mod synthetic;

use std::time::Instant;

use kiwi_backend::export::{ExportFormat, ExportOptions, export};

fn env_or(name: &str, default: f64) -> f64 {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

/// Bytes of every file under `dir`.
fn dir_bytes(dir: &std::path::Path) -> u64 {
    std::fs::read_dir(dir).map_or(0, |entries| {
        entries
            .flatten()
            .map(|e| match e.file_type() {
                Ok(t) if t.is_dir() => dir_bytes(&e.path()),
                _ => e.metadata().map_or(0, |m| m.len()),
            })
            .sum()
    })
}

fn main() {
    let duration = env_or("KIWI_BENCH_DURATION", 60.0);
    let resolution = env_or("KIWI_BENCH_RESOLUTION", 480.0) as u32 & !1;
    let spec = synthetic::Synthetic {
        frames: (duration * synthetic::RATE).round() as usize,
        width: resolution,
        height: resolution,
        rear_lens: false,
    };
    let tmp = tempfile::tempdir().unwrap();
    let root = std::env::var("KIWI_BENCH_DIR")
        .map_or_else(|_| tmp.path().to_path_buf(), std::path::PathBuf::from);
    let started = Instant::now();
    let session = synthetic::make_session(&spec, &root);
    println!(
        "synthetic session: 2 wrists x {} front frames of {resolution}x{resolution} px \
         ({duration} s at 29.97 Hz), written in {:.1} s",
        spec.frames,
        started.elapsed().as_secs_f64()
    );
    let minutes = duration / 60.0;
    for (name, format) in [
        ("lerobot", ExportFormat::LeRobot),
        ("umi", ExportFormat::Umi),
        ("sidecar", ExportFormat::Sidecar),
    ] {
        let out = root.join(format!("export-{name}"));
        let _ = std::fs::remove_dir_all(&out);
        let t = Instant::now();
        let report = export(
            &session,
            format,
            &ExportOptions {
                episodes: Some(vec!["ep0".into()]),
                ..ExportOptions::default()
            },
            &out,
        )
        .unwrap();
        let s = t.elapsed().as_secs_f64();
        let bytes = dir_bytes(&out);
        // Decoded frame data the video formats pass through (2 views, RGB).
        let raw = match format {
            ExportFormat::Sidecar => 0.0,
            _ => report.frames as f64 * 2.0 * f64::from(resolution).powi(2) * 3.0,
        };
        println!(
            "{name:>8}: {s:7.2} s for {duration} s of recording = {:6.2} s per minute; \
             {} rows = {:7.1} rows/s; frames decoded {:6.1} MB/s; output {:7.1} MB",
            s / minutes,
            report.frames,
            report.frames as f64 / s,
            raw / 1e6 / s,
            bytes as f64 / 1e6
        );
    }
    let scene_spec = synthetic::Synthetic {
        rear_lens: true,
        ..spec
    };
    let scene_root = root.join("scene");
    let session = synthetic::make_session(&scene_spec, &scene_root);
    synthetic::add_scene_inputs(&scene_spec, &scene_root, 1.0);
    let out = scene_root.join("export-colmap");
    let t = Instant::now();
    let report = export(
        &session,
        ExportFormat::Colmap,
        &ExportOptions {
            episodes: Some(vec!["ep0".into()]),
            rate: Some(1.0),
            ..ExportOptions::default()
        },
        &out,
    )
    .unwrap();
    let s = t.elapsed().as_secs_f64();
    println!(
        "  colmap: {s:7.2} s for {duration} s of recording = {:6.2} s per minute; {} images \
         with masks (4 lenses at 1 Hz) = {:6.1} ms per image; output {:7.1} MB",
        s / minutes,
        report.frames,
        1e3 * s / report.frames.max(1) as f64,
        dir_bytes(&out) as f64 / 1e6
    );
}
