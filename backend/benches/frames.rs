//! Decode throughput of a lens stream at 960 px: frames per CPU-second (all threads of the
//! process, OpenCV's and ffmpeg's decoder threads included) for the PNG folder and the same
//! frames as video (utvideo and FFV1 lossless, H.264 crf 12), sequential in luma as the vision
//! reads them, and random access walking backwards as the localizer's backward pass does; plus
//! bytes per frame on disk, and each codec's round trip against the PNGs (largest difference
//! and PSNR over the BGR bytes). `cargo bench --workspace --bench frames` (set
//! KIWI_BENCH_FRAMES to change the 150-frame stream).

#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use std::path::Path;
use std::time::Instant;

use kiwi_backend::frames::FrameSource;
use kiwi_core::layout::{EpisodeLayout, LensStorage, read_frames_csv};
use kiwi_core::video::{VideoCodec, VideoStreamWriter};
use kiwi_fixtures::recording::FrameOutput;
use kiwi_fixtures::session::{SessionOptions, write_session};

/// CPU seconds (user + system) of this process so far, from /proc/self/stat.
fn cpu_seconds() -> f64 {
    let stat = std::fs::read_to_string("/proc/self/stat").unwrap();
    let after = stat.rsplit_once(')').unwrap().1;
    let f: Vec<&str> = after.split_whitespace().collect();
    let ticks: f64 = f[11].parse::<f64>().unwrap() + f[12].parse::<f64>().unwrap();
    ticks / 100.0
}

fn dir_bytes(dir: &Path) -> u64 {
    let mut total = 0;
    for e in std::fs::read_dir(dir).unwrap().flatten() {
        let p = e.path();
        total += if p.is_dir() {
            dir_bytes(&p)
        } else {
            e.metadata().unwrap().len()
        };
    }
    total
}

fn measure(name: &str, lens_dir: &Path) {
    let src = FrameSource::open(lens_dir).unwrap();
    let n = src.len();
    let bytes = match src.storage() {
        LensStorage::Images => dir_bytes(&lens_dir.join("frames")),
        LensStorage::Video(v) => std::fs::metadata(lens_dir.join(&v.file)).unwrap().len(),
    };
    let (c0, w0) = (cpu_seconds(), Instant::now());
    let mut checksum = 0u64;
    src.for_each_gray(|_, img| {
        checksum = checksum.wrapping_add(img.data.iter().map(|&v| u64::from(v)).sum::<u64>());
        Ok(())
    })
    .unwrap();
    let (cpu, wall) = (cpu_seconds() - c0, w0.elapsed().as_secs_f64());
    let (c1, w1) = (cpu_seconds(), Instant::now());
    let back = n.min(60);
    for i in (n - back..n).rev() {
        src.load_gray(i).unwrap();
    }
    let (cpu_b, wall_b) = (cpu_seconds() - c1, w1.elapsed().as_secs_f64());
    println!(
        "{name:<10} {:>9.0} B/frame  sequential {:>6.1} frames/CPU-s ({:>5.1} frames/s wall)  \
         backward {:>6.1} frames/CPU-s ({:>5.1}/s wall)  luma sum {checksum}",
        bytes as f64 / n as f64,
        n as f64 / cpu.max(1e-9),
        n as f64 / wall,
        back as f64 / cpu_b.max(1e-9),
        back as f64 / wall_b,
    );
}

/// Largest absolute difference and PSNR (dB; infinite when identical) of every frame of
/// `video` against the same frame of `png`, over the BGR bytes.
fn round_trip(png: &FrameSource, video: &FrameSource) -> (u8, f64) {
    let mut worst = 0u8;
    let (mut sq, mut count) = (0.0f64, 0usize);
    video
        .for_each_color(|i, img| {
            let reference = png.load_color(i).unwrap();
            for (a, b) in img.bgr.iter().zip(&reference.bgr) {
                let d = a.abs_diff(*b);
                worst = worst.max(d);
                sq += f64::from(d) * f64::from(d);
            }
            count += img.bgr.len();
            Ok(())
        })
        .unwrap();
    let mse = sq / count as f64;
    (worst, 10.0 * (255.0f64 * 255.0 / mse).log10())
}

fn main() {
    let frames: usize = std::env::var("KIWI_BENCH_FRAMES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(150);
    let tmp = tempfile::tempdir().unwrap();
    let mut o = SessionOptions::new(tmp.path().join("s"));
    o.seed = 3;
    o.resolution = 960;
    o.rate_hz = 29.97;
    o.duration_s = frames as f64 / 29.97;
    o.head = false;
    o.frames = FrameOutput::Png;
    let summary = write_session(&o).unwrap();
    let session = summary.session_toml.parent().unwrap().to_path_buf();
    let layout = EpisodeLayout::new(session.join("episodes/ep000"));
    let png = layout.lens_dir("left", "front");
    let rows = read_frames_csv(&png.join("frames.csv")).unwrap();
    let times: Vec<f64> = rows.iter().map(|r| r.t).collect();
    println!(
        "{} frames of 960 x 960 px (simulated left front lens, noise 2 DN), {} threads",
        rows.len(),
        rayon::current_num_threads()
    );
    measure("png", &png);
    for codec in [
        VideoCodec::Utvideo,
        VideoCodec::Ffv1,
        VideoCodec::H264 { crf: 12 },
    ] {
        let dir = tmp.path().join(codec.name());
        let mut w = VideoStreamWriter::create(&dir, codec, 960, 960, "29.97").unwrap();
        for r in &rows {
            let img = image::open(png.join(&r.file)).unwrap().to_rgb8();
            w.push_rgb(img.as_raw()).unwrap();
        }
        w.finish(&times).unwrap();
        measure(codec.name(), &dir);
        let (worst, psnr) = round_trip(
            &FrameSource::open(&png).unwrap(),
            &FrameSource::open(&dir).unwrap(),
        );
        println!(
            "{:<10} round trip vs PNG: largest difference {worst} DN, PSNR {psnr:.1} dB",
            codec.name()
        );
    }
}
