//! `imu-noise` throughput: a 3-hour static log at 1 kHz (10.8 M samples × 6 axes) read from
//! `imu.csv`, Allan deviation at 20 averaging times per decade, joint fits (target < 10 s and
//! < 1 GiB peak memory on the 2-core machine). `HOURS` and `RATE` override the log size.

#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use std::time::Instant;

use kiwi_calib::allan::{AllanOptions, analyse, read_static_log};
use kiwi_core::imu::ImuCsvWriter;
use kiwi_fixtures::imu::ImuSimulator;
use kiwi_fixtures::motion::Trajectory;
use kiwi_fixtures::unit::SimImuNoise;
use nalgebra::{Isometry3, Translation3, UnitQuaternion};

fn env_f64(name: &str, default: f64) -> f64 {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

/// Peak resident memory of this process (kB), from /proc.
fn peak_rss_kb() -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    status
        .lines()
        .find(|l| l.starts_with("VmHWM:"))?
        .split_whitespace()
        .nth(1)?
        .parse()
        .ok()
}

/// CPU time (user + system) of this process so far (s), from /proc: on a loaded machine the
/// wall time of a parallel section says little, its CPU time does.
fn cpu_s() -> f64 {
    std::fs::read_to_string("/proc/self/stat")
        .ok()
        .and_then(|s| {
            let after = s.rsplit_once(')')?.1.split_whitespace().collect::<Vec<_>>();
            let user: f64 = after.get(11)?.parse().ok()?;
            let system: f64 = after.get(12)?.parse().ok()?;
            Some((user + system) / 100.0)
        })
        .unwrap_or(f64::NAN)
}

fn main() {
    let hours = env_f64("HOURS", 3.0);
    let rate = env_f64("RATE", 1000.0);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("imu.csv");
    let noise = SimImuNoise {
        rate_hz: rate,
        gyro_noise_density: 1.5e-4,
        gyro_random_walk: 2e-5,
        accel_noise_density: 1.5e-3,
        accel_random_walk: 3e-4,
        gyro_turn_on_bias: [0.01, -0.02, 0.005],
        accel_turn_on_bias: [0.05, 0.02, -0.08],
    };
    let t0 = Instant::now();
    {
        let rest = Isometry3::from_parts(
            Translation3::new(0.0, 0.0, 0.8),
            UnitQuaternion::from_euler_angles(0.02, -0.015, 0.7),
        );
        let trajectory = Trajectory::fixed(&rest);
        let sim = ImuSimulator::new(&trajectory, noise, 0.0, hours * 3600.0, true, 1, "bench");
        let file =
            std::io::BufWriter::with_capacity(1 << 20, std::fs::File::create(&path).unwrap());
        let mut w = ImuCsvWriter::new(file).unwrap();
        for s in sim {
            w.write(&s).unwrap();
        }
        w.finish().unwrap();
    }
    let bytes = std::fs::metadata(&path).unwrap().len();
    println!(
        "generated {hours} h at {rate} Hz: {:.0} MB of imu.csv in {:.1} s (not timed below)",
        bytes as f64 / 1e6,
        t0.elapsed().as_secs_f64()
    );
    let rss_before = peak_rss_kb().unwrap_or(0);
    let (t0, c0) = (Instant::now(), cpu_s());
    let log = read_static_log(&path, None).unwrap();
    let (t_read, c_read) = (t0.elapsed().as_secs_f64(), cpu_s() - c0);
    let samples = log.len();
    let report = analyse(log, &AllanOptions::default()).unwrap();
    let (total, c_total) = (t0.elapsed().as_secs_f64(), cpu_s() - c0);
    let taus = report.axes[0].curve.taus.len();
    println!(
        "imu-noise: {samples} samples x 6 axes, {taus} averaging times: read {t_read:.2} s, \
         Allan + fit {:.2} s, total {total:.2} s on {} threads (target < 10 s)",
        total - t_read,
        rayon::current_num_threads()
    );
    println!(
        "CPU time: read {c_read:.2} s, Allan + fit {:.2} s (wall time on an idle 2-core machine \
         is at least half of it)",
        c_total - c_read
    );
    println!(
        "peak resident memory: {:.0} MiB (before the analysis {:.0} MiB; target < 1024 MiB)",
        peak_rss_kb().unwrap_or(0) as f64 / 1024.0,
        rss_before as f64 / 1024.0
    );
    println!(
        "gyro N {:.3e} (truth {:.3e}), K {:.3e} (truth {:.3e})",
        report.gyroscope_noise_density,
        noise.gyro_noise_density,
        report.gyroscope_random_walk,
        noise.gyro_random_walk
    );
}
