//! Fusion throughput: a 331 s recording at 119.88 Hz (~39 700 nodes, 1 kHz IMU, front
//! observations with 1 mm / 0.1° noise and 5 % outliers) fused single-threaded; target < 10 s
//! and < 2 GiB peak memory. Prints the wall time, the peak resident memory and the ATE.
//!
//! With `KIWI_BENCH_GTSAM=1` (and `pip install gtsam numpy`) the same files are handed to
//! `backend/benches/fuse_gtsam.py`, which builds the identical graph (same node times,
//! preintegration sub-intervals, factors, priors and noise) in GTSAM 4.3, times its
//! Levenberg–Marquardt, and the ratio is printed.

#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use std::fmt::Write as _;
use std::time::Instant;

use kiwi_backend::fusion::preint::ImuParams;
use kiwi_backend::fusion::{FusionConfig, PoseObservation, Source, fuse};
use kiwi_core::geometry::se3_exp;
use kiwi_fixtures::imu::{GRAVITY, ImuSimulator};
use kiwi_fixtures::rng::{normal, stream, uniform};
use kiwi_fixtures::scenario::{Scenario, episode_motion};
use kiwi_fixtures::unit::{LensModel, SimUnit};
use nalgebra::Vector6;

const FPS: f64 = 119.88;
const DURATION_S: f64 = 331.0;

fn peak_rss_mib() -> f64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines().find(|l| l.starts_with("VmHWM:")).and_then(|l| {
                l.split_whitespace()
                    .nth(1)
                    .and_then(|v| v.parse::<f64>().ok())
            })
        })
        .map_or(f64::NAN, |kib| kib / 1024.0)
}

fn main() {
    // Single-threaded, as the acceptance asks.
    rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build_global()
        .ok();
    let motion = episode_motion(Scenario::Tabletop, 3, 0, DURATION_S + 1.0);
    let unit = SimUnit::x5("BENCH", 3, 96, LensModel::Kb4).unwrap();
    let traj = &motion.left;
    let imu: Vec<_> =
        ImuSimulator::new(traj, unit.imu, 0.0, DURATION_S + 0.5, true, 3, "bench").collect();
    let n = (DURATION_S * FPS) as usize;
    let times: Vec<f64> = (0..n).map(|k| k as f64 / FPS).collect();
    let mut rng = stream(3, "bench/obs");
    let sigma_r = 0.1f64.to_radians();
    let obs: Vec<PoseObservation> = times
        .iter()
        .map(|&t| {
            let mut xi =
                Vector6::from_fn(|i, _| normal(&mut rng, if i < 3 { sigma_r } else { 1e-3 }));
            if uniform(&mut rng, 0.0, 1.0) < 0.05 {
                xi += Vector6::from_fn(|_, _| uniform(&mut rng, -0.1, 0.1));
            }
            PoseObservation {
                t,
                source: Source::Front,
                scene_from_imu: traj.pose(t) * se3_exp(&xi),
            }
        })
        .collect();
    let noise = &unit.imu;
    let densities = [
        noise.gyro_noise_density,
        noise.gyro_random_walk,
        noise.accel_noise_density,
        noise.accel_random_walk,
    ];
    let params = ImuParams::from_densities(
        densities[0],
        densities[1],
        densities[2],
        densities[3],
        GRAVITY,
    );
    let config = FusionConfig::default();
    let rss_before = peak_rss_mib();
    let start = Instant::now();
    let result = fuse(&imu, &params, &times, &obs, &config).unwrap();
    let seconds = start.elapsed().as_secs_f64();
    let ate = (result
        .nodes
        .iter()
        .map(|n| {
            (n.scene_from_imu.translation.vector - traj.pose(n.t).translation.vector).norm_squared()
        })
        .sum::<f64>()
        / n as f64)
        .sqrt();
    println!(
        "fuse: {} nodes, {} IMU samples, {} factors ({} downweighted), {} iterations: {seconds:.2} s \
         single-threaded (target < 10 s); peak RSS {:.0} MiB (inputs alone {rss_before:.0} MiB; \
         target < 2048); ATE {:.3} mm",
        result.nodes.len(),
        imu.len(),
        result.observations_used,
        result.outliers_downweighted,
        result.iterations,
        peak_rss_mib(),
        ate * 1e3
    );

    if std::env::var("KIWI_BENCH_GTSAM").is_ok_and(|v| v == "1") {
        let dir = tempfile::tempdir().unwrap();
        kiwi_core::imu::write_imu_csv(&dir.path().join("imu.csv"), &imu).unwrap();
        let mut frames = String::from("t\n");
        for t in &times {
            writeln!(frames, "{t:.17}").unwrap();
        }
        std::fs::write(dir.path().join("frames.csv"), frames).unwrap();
        let mut o = String::from("t,source,px,py,pz,qx,qy,qz,qw\n");
        for ob in &obs {
            let (p, q) = (
                ob.scene_from_imu.translation.vector,
                ob.scene_from_imu.rotation.coords,
            );
            writeln!(
                o,
                "{:.17},front,{:.17},{:.17},{:.17},{:.17},{:.17},{:.17},{:.17}",
                ob.t, p.x, p.y, p.z, q.x, q.y, q.z, q.w
            )
            .unwrap();
        }
        std::fs::write(dir.path().join("obs.csv"), o).unwrap();
        let script = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("benches/fuse_gtsam.py");
        let noise_arg = densities.map(|d| format!("{d:e}")).join(",");
        let out = std::process::Command::new("python3")
            .arg(script)
            .arg(dir.path())
            .arg(&noise_arg)
            .output();
        match out {
            Ok(o) if o.status.success() => {
                let text = String::from_utf8_lossy(&o.stdout);
                let gtsam_s: Option<f64> = text.lines().find_map(|l| {
                    l.strip_prefix("gtsam_seconds ")
                        .and_then(|v| v.trim().parse().ok())
                });
                print!("{text}");
                if let Some(g) = gtsam_s {
                    println!("GTSAM / KIWI time ratio: {:.1}x", g / seconds);
                }
            }
            Ok(o) => println!("GTSAM run failed: {}", String::from_utf8_lossy(&o.stderr)),
            Err(e) => println!("python3 not available ({e}); skipping the GTSAM comparison"),
        }
    } else {
        println!("(set KIWI_BENCH_GTSAM=1 to time GTSAM on the identical problem)");
    }
}
