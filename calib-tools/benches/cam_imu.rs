//! `cam-imu` on the full case: a simulated 60 s camera–IMU excitation of an X5 unit
//! (front and rear lens, 119.88 Hz rolling-shutter frames at 480 × 480, 1 kHz IMU with noise,
//! turn-on biases and bias random walk), started from a time shift 50 ms wrong. Prints the wall
//! and CPU time of the whole command (detection, tracking, initialisation, batch; target < 60 s
//! on the 2-core machine) and the errors against the simulator's truth.
//!
//! The capture (≈ 14 400 PNGs) is rendered once into `target/cam-imu-bench/` and reused.
//! Environment: `CAM_IMU_BENCH_DIR` (capture folder), `KEYFRAME_INTERVAL` (s, default: the
//! command's default), `FRAME_STEP` (default 1).

#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use std::path::{Path, PathBuf};
use std::time::Instant;

use kiwi_calib::cam_imu::{CamImuOptions, calibrate};
use kiwi_core::artifact::UnitCalibration;
use kiwi_fixtures::captures::{UnitCaptureOptions, write_unit_captures};

fn env_usize(name: &str, default: usize) -> usize {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

/// CPU time (user + system) of this process so far (s), from /proc.
fn cpu_s() -> f64 {
    std::fs::read_to_string("/proc/self/stat")
        .ok()
        .and_then(|s| {
            let fields: Vec<&str> = s.rsplit_once(')')?.1.split_whitespace().collect();
            let ticks: f64 =
                fields.get(11)?.parse::<f64>().ok()? + fields.get(12)?.parse::<f64>().ok()?;
            Some(ticks / 100.0)
        })
        .unwrap_or(f64::NAN)
}

fn capture_dir() -> PathBuf {
    std::env::var("CAM_IMU_BENCH_DIR").map_or_else(
        |_| Path::new(env!("CARGO_MANIFEST_DIR")).join("../target/cam-imu-bench/x5-480-60s"),
        PathBuf::from,
    )
}

fn ensure_capture(dir: &Path) {
    if dir.join("cam_imu/rear/frames.csv").exists() {
        return;
    }
    if dir.exists() {
        std::fs::remove_dir_all(dir).unwrap();
    }
    println!(
        "rendering the 60 s capture into {} (once; ~30 min on 2 cores)",
        dir.display()
    );
    let t = Instant::now();
    let mut o = UnitCaptureOptions::new(dir, "BENCH-X5");
    o.seed = 7;
    o.resolution = 480;
    o.views = 0;
    o.cam_imu_duration_s = 60.0;
    o.static_duration_s = 0.0;
    o.bench_duration_s = 0.0;
    o.rig_duration_s = 0.0;
    o.progress = true;
    write_unit_captures(&o).unwrap();
    println!("rendered in {:.0} s", t.elapsed().as_secs_f64());
}

fn main() {
    let dir = capture_dir();
    ensure_capture(&dir);
    let truth = UnitCalibration::load(&dir.join("truth/calibration.json")).unwrap();
    let mut o = CamImuOptions::new(
        &dir.join("cam_imu"),
        &dir.join("truth/calibration.json"),
        // Captures rendered before the excitation had its own target yaml use the unit's.
        &[dir.join("cam_imu/target.yaml"), dir.join("target.yaml")]
            .into_iter()
            .find(|p| p.is_file())
            .unwrap_or_else(|| dir.join("target.yaml")),
    );
    o.frame_step = env_usize("FRAME_STEP", o.frame_step);
    o.keyframe_interval_s = std::env::var("KEYFRAME_INTERVAL")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(o.keyframe_interval_s);
    o.time_shift_guess_s = truth.lenses[0].time_shift_s.unwrap() + 0.05;
    let cpu0 = cpu_s();
    let t0 = Instant::now();
    let r = calibrate(&o).unwrap();
    let wall = t0.elapsed().as_secs_f64();
    let cpu = cpu_s() - cpu0;
    println!(
        "cam-imu 60 s excitation, 480 px, frame step {}, keyframe interval {} s: wall {wall:.1} s \
         (target < 60 s), CPU {cpu:.1} s on {} threads; detection+tracking {:.1} s, \
         initialisation {:.1} s, batch {:.1} s ({} iterations)",
        o.frame_step,
        o.keyframe_interval_s,
        rayon::current_num_threads(),
        r.seconds.detection,
        r.seconds.initialisation,
        r.seconds.batch,
        r.iterations
    );
    for (lens, l) in truth.lenses.iter().zip(&r.lenses) {
        let x = lens.cam_from_imu().unwrap();
        let rot = (x.inverse() * l.cam_from_imu).rotation.angle().to_degrees();
        let trans = (x.translation.vector - l.cam_from_imu.translation.vector).norm() * 1e3;
        let shift = (l.time_shift_s - lens.time_shift_s.unwrap()).abs() * 1e3;
        println!(
            "  {}: rotation error {rot:.4} deg (limit 0.1), translation error {trans:.3} mm \
             (limit 2), time shift error {shift:.4} ms (limit 0.2); 1σ {:.4} deg, {:.3} mm, \
             {:.4} ms; RMS {:.3} px; {} of {} frames, {} corners",
            l.name,
            l.rotation_std_deg.iter().fold(0.0f64, |a, b| a.max(*b)),
            l.translation_std_m.iter().fold(0.0f64, |a, b| a.max(*b)) * 1e3,
            l.time_shift_std_s * 1e3,
            l.rms_px,
            l.frames_accepted,
            l.frames_total,
            l.corners
        );
    }
    println!(
        "  {}",
        if wall < 60.0 {
            "PASS: under 60 s"
        } else {
            "FAIL: over 60 s"
        }
    );
}
