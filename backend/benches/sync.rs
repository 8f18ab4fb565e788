//! Audio sync throughput: a 6-minute 48 kHz pair (target < 2 s) and 5 cameras × 10 minutes
//! (target < 15 s) on this machine. Prints wall times and the worst offset error.

#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use std::time::Instant;

use kiwi_backend::sync::audio::Audio;
use kiwi_backend::sync::{SyncInput, synchronise};
use kiwi_fixtures::audio::{AUDIO_RATE_HZ, AmbientSource, Microphone};

fn inputs(n: usize, minutes: f64) -> (Vec<SyncInput>, Vec<f64>) {
    let source = AmbientSource::new(5, -100.0, minutes * 60.0 + 200.0, false);
    let offsets: Vec<f64> = (0..n)
        .map(|k| [0.0, -41.3, 17.9, 55.2, -8.8][k % 5])
        .collect();
    let inputs = offsets
        .iter()
        .enumerate()
        .map(|(k, &offset_s)| {
            let mic = Microphone {
                offset_s,
                drift_ppm: [0.0, 12.0, -20.0, 5.0, 28.0][k % 5],
                propagation_delay_s: 0.003,
                av_delay_s: 0.03,
                gain: 1.0,
                noise_sigma: 0.02,
                video_to_device_s: 0.0,
            };
            let samples = mic.record(&source, minutes * 60.0, 5, &format!("c{k}"));
            SyncInput {
                name: format!("c{k}"),
                audio: Audio {
                    rate_hz: f64::from(AUDIO_RATE_HZ),
                    samples,
                },
                av_delay_s: 0.03,
            }
        })
        .collect();
    (inputs, offsets)
}

fn run(label: &str, n: usize, minutes: f64) {
    let (inputs, offsets) = inputs(n, minutes);
    let start = Instant::now();
    let result = synchronise(&inputs);
    let seconds = start.elapsed().as_secs_f64();
    let worst = result
        .cameras
        .iter()
        .zip(&offsets)
        .map(|(c, o)| {
            c.offset_s
                .map_or(f64::INFINITY, |offset| (offset - o).abs())
        })
        .fold(0.0, f64::max);
    println!(
        "sync {label}: {seconds:.2} s wall on {} threads, worst offset error {:.3} ms",
        rayon::current_num_threads(),
        worst * 1e3
    );
}

fn main() {
    run("2 cameras x 6 min", 2, 6.0);
    run("5 cameras x 10 min", 5, 10.0);
}
