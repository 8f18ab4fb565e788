//! `kiwi gripper` throughput on 120 fps front-lens video: the per-frame estimator on decoded
//! frames (rectification, red dots, jaw lines) and the whole lens-folder path (PNG decode +
//! estimate, parallel over frames, as `kiwi gripper` runs it). Prints frames/s and the
//! multiple of real time (120 fps). `KIWI_BENCH_GRIPPER_SIZE` sets the lens image side
//! (default 960 px).

#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use std::sync::Arc;
use std::time::Instant;

use kiwi_backend::gripper::{self, ChannelOrder, GripperEstimator, ImageView};
use kiwi_core::camera::{Camera, Kb4};
use kiwi_core::layout::{FrameRecord, ToolKind, write_frames_csv};
use kiwi_core::tool::ToolDefinition;
use kiwi_fixtures::motion::look_rotation;
use kiwi_fixtures::render::{Extras, LensRays, RenderOptions, render};
use kiwi_fixtures::scene::{Scene, SceneOptions};
use kiwi_fixtures::tools::ToolGeometry;
use nalgebra::{Isometry3, Translation3, Vector3};
use rayon::prelude::*;

const FPS: f64 = 120.0;
/// Distinct rendered frames (rendering dominates the setup).
const DISTINCT: usize = 24;
/// Frames measured in memory: 10 s of 120 fps video.
const MEMORY_FRAMES: usize = 1200;
/// Frames in the lens folder: 2 s of 120 fps video.
const FOLDER_FRAMES: usize = 240;

fn camera(size: u32) -> Camera {
    let s = f64::from(size);
    Camera::Kb4(
        Kb4::new(
            size,
            size,
            [
                145.0 * s / 480.0,
                145.0 * s / 480.0,
                s / 2.0 - 0.5,
                s / 2.0 - 0.5,
                0.01,
                -0.002,
                0.0,
                0.0,
            ],
        )
        .unwrap(),
    )
}

fn main() {
    let size: u32 = std::env::var("KIWI_BENCH_GRIPPER_SIZE")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(960);
    let cam = camera(size);
    let def = ToolDefinition::builtin(ToolKind::Chopstick).unwrap();
    let g = ToolGeometry::from_definition(&def);
    let tex = g.tag_texture().unwrap();
    let scene = Scene::new(5, SceneOptions::default());
    let rays = LensRays::new(&cam);
    let pose = Isometry3::from_parts(
        Translation3::new(-0.5, 0.3, 1.0),
        look_rotation(&Vector3::new(0.2, 1.0, -0.4), &Vector3::z()),
    );
    let t0 = Instant::now();
    let frames: Vec<Vec<u8>> = (0..DISTINCT)
        .map(|k| {
            let t = k as f64 / FPS * 5.0;
            let opening = 0.45 + 0.35 * (std::f64::consts::TAU * 1.3 * t).sin();
            let extras = Extras {
                items: g.items(opening, &Arc::clone(&tex)),
                ..Extras::default()
            };
            render(
                &scene,
                &rays,
                &|_| pose,
                t,
                &extras,
                &RenderOptions {
                    noise_key: k as u64,
                    ..RenderOptions::default()
                },
            )
            .into_raw()
        })
        .collect();
    eprintln!(
        "rendered {DISTINCT} frames of {size}x{size} in {:.1} s",
        t0.elapsed().as_secs_f64()
    );

    let t0 = Instant::now();
    let est = GripperEstimator::new(&cam, &def).unwrap();
    let setup = t0.elapsed().as_secs_f64();
    let plane = est.rectifier().plane();
    println!(
        "gripper @ {size}x{size}: estimator setup {:.1} ms (rectified window {}x{} px)",
        setup * 1e3,
        plane.width,
        plane.height
    );

    // In memory, parallel over frames as measure_lens does.
    let t0 = Instant::now();
    let measured: usize = (0..MEMORY_FRAMES)
        .into_par_iter()
        .map(|k| {
            let m = est.measure(&ImageView {
                width: size as usize,
                height: size as usize,
                data: &frames[k % DISTINCT],
                order: ChannelOrder::Rgb,
            });
            usize::from(m.opening.is_some())
        })
        .sum();
    let secs = t0.elapsed().as_secs_f64();
    let fps = MEMORY_FRAMES as f64 / secs;
    println!(
        "  estimate (decoded frames, {} threads): {fps:.0} frames/s = {:.1}x real time at 120 fps \
         ({measured}/{MEMORY_FRAMES} measured)",
        rayon::current_num_threads(),
        fps / FPS
    );

    // The whole lens-folder path: PNG decode + estimate, as `kiwi gripper` runs.
    let dir = tempfile::tempdir().unwrap();
    let lens = dir.path().join("front");
    std::fs::create_dir_all(lens.join("frames")).unwrap();
    let mut records = Vec::new();
    for k in 0..DISTINCT {
        let file = format!("frames/{k:06}.png");
        image_png(&lens.join(&file), &frames[k], size);
        records.push(FrameRecord {
            t: k as f64 / FPS,
            file,
        });
    }
    // More rows than images: the folder's rows reuse the distinct frames.
    let rows: Vec<FrameRecord> = (0..FOLDER_FRAMES)
        .map(|k| FrameRecord {
            t: k as f64 / FPS,
            file: records[k % DISTINCT].file.clone(),
        })
        .collect();
    write_frames_csv(&lens.join("frames.csv"), &rows).unwrap();
    let t0 = Instant::now();
    let out = gripper::measure_lens(&est, &lens, &|| {}).unwrap();
    let secs = t0.elapsed().as_secs_f64();
    let fps = out.len() as f64 / secs;
    println!(
        "  kiwi gripper path (PNG decode + estimate): {fps:.0} frames/s = {:.1}x real time at \
         120 fps ({} frames)",
        fps / FPS,
        out.len()
    );
}

/// Write RGB bytes as a PNG through OpenCV (the backend's image I/O).
fn image_png(path: &std::path::Path, rgb: &[u8], size: u32) {
    use opencv::core::{Mat, Vector};
    use opencv::prelude::*;
    let mut bgr = rgb.to_vec();
    for p in bgr.chunks_exact_mut(3) {
        p.swap(0, 2);
    }
    let mat = Mat::new_rows_cols_with_data(size as i32, (size * 3) as i32, &bgr).unwrap();
    let mat = mat.reshape(3, size as i32).unwrap();
    opencv::imgcodecs::imwrite(path.to_str().unwrap(), &mat, &Vector::new()).unwrap();
}
