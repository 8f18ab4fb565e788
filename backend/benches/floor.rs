//! Floor cost: seconds of floor work (choosing windows, the plane sweep and the motion stereo of
//! both wrists' front streams, pooling) per minute of recording, on a simulated tabletop episode
//! at `KIWI_BENCH_RESOLUTION` px (default 960) and 29.97 Hz with rolling shutter, posed by the
//! simulator's true trajectories. A window is swept per second of video that looks down and
//! moves, at most `max_windows` per wrist: the cost of a minute is the cost of the windows a
//! minute would sweep. Also the floor found and the process's peak memory.

#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

#[path = "../tests/common/truth.rs"]
#[allow(dead_code)]
mod truth;

use std::time::Instant;

use kiwi_backend::floor::{FloorOptions, pool, surfaces_above};
use kiwi_core::layout::{EpisodeLayout, Session, Side};
use kiwi_fixtures::scenario::Scenario;
use kiwi_fixtures::session::{SessionOptions, write_session};

/// Seconds of recording simulated.
const DURATION_S: f64 = 12.0;

/// Peak resident memory of the process (MiB), from `/proc/self/status`.
fn peak_rss_mib() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kib: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib / 1024.0)
}

fn main() {
    let size = std::env::var("KIWI_BENCH_RESOLUTION")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(960u32);
    let tmp = tempfile::tempdir().unwrap();
    let mut o = SessionOptions::new(tmp.path());
    o.seed = 19;
    o.resolution = size;
    o.rate_hz = 29.97;
    o.episodes = 1;
    o.duration_s = DURATION_S;
    o.scenario = Scenario::Tabletop;
    o.head = false;
    o.rolling_shutter = true;
    o.only_lenses = vec!["left/front".into(), "right/front".into()];
    eprintln!("simulating {DURATION_S} s of both front lenses at {size} px ...");
    let written = write_session(&o).unwrap();
    let root = written.session_toml.parent().unwrap();
    let episode = EpisodeLayout::new(root.join("episodes").join(&written.episodes[0]));
    let session = Session::load(&written.session_toml).unwrap();
    let options = FloorOptions::default();

    let mut windows = Vec::new();
    let mut counts = Vec::new();
    let mut qualifying = 0usize;
    let start = Instant::now();
    for side in [Side::Left, Side::Right] {
        let unit = &session.wrists[&side].unit;
        let (w, c) = truth::truth_floor_windows(root, &episode, unit, side, &options);
        qualifying += c.windows - c.unposed - c.not_looking_down - c.no_baseline;
        windows.extend(w);
        counts.push(c);
    }
    let floor = pool(&mut windows, &counts, options.camera_height_m);
    let surfaces = surfaces_above(&windows, &floor);
    let seconds = start.elapsed().as_secs_f64();
    let swept = windows.len();
    let per_window = seconds / swept.max(1) as f64;
    // Windows a minute sweeps: the qualifying rate of this episode, capped by the budget.
    let per_minute_windows =
        (qualifying as f64 / DURATION_S * 60.0).min(2.0 * options.max_windows as f64);
    println!("floor bench: {size} px, 29.97 Hz, {DURATION_S} s tabletop, both wrists");
    println!("  windows: {qualifying} qualifying, {swept} swept ({counts:?})");
    println!("  wall time: {seconds:.2} s ({per_window:.3} s per swept window)");
    println!(
        "  cost per minute of recording: {:.1} s ({per_minute_windows:.0} windows)",
        per_window * per_minute_windows
    );
    println!("  floor: {floor:?}");
    println!(
        "  surfaces: {:?}",
        surfaces.iter().map(|s| s.z_m).collect::<Vec<_>>()
    );
    if let Some(mib) = peak_rss_mib() {
        println!("  peak memory (whole process, simulation included): {mib:.0} MiB");
    }
}
