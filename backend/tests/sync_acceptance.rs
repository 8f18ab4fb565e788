//! Acceptance tests of audio synchronisation against the simulator's exact clocks.

#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

use kiwi_backend::sync::audio::Audio;
use kiwi_backend::sync::{CameraStatus, SyncInput, synchronise};
use kiwi_fixtures::audio::{AUDIO_RATE_HZ, AmbientSource, Microphone};

/// Root-mean-square of the ambient source over a stretch, for setting the SNR.
fn source_rms(source: &AmbientSource, from: f64, to: f64) -> f64 {
    let n = 20_000;
    let sum: f64 = (0..n)
        .map(|k| {
            source
                .value(from + (to - from) * k as f64 / n as f64)
                .powi(2)
        })
        .sum();
    (sum / n as f64).sqrt()
}

struct Cam {
    mic: Microphone,
    duration: f64,
}

fn simulate(
    seed: u64,
    cams: &[Cam],
    snr_db: f64,
    periodic: bool,
    shared_source: bool,
) -> Vec<SyncInput> {
    // The source only needs to cover what the cameras hear (session time offset .. offset + length).
    let start = cams.iter().map(|c| c.mic.offset_s).fold(0.0, f64::min) - 5.0;
    let end = cams
        .iter()
        .map(|c| c.mic.offset_s + c.duration * 1.001)
        .fold(0.0, f64::max)
        + 5.0;
    let shared = AmbientSource::new(seed, start, end - start, periodic);
    let rms = source_rms(&shared, start.max(0.0), end.min(300.0));
    cams.iter()
        .enumerate()
        .map(|(k, c)| {
            let own;
            let source = if shared_source {
                &shared
            } else {
                own = AmbientSource::new(seed * 1000 + k as u64 + 1, start, end - start, periodic);
                &own
            };
            let mut mic = c.mic;
            mic.noise_sigma = rms * mic.gain / 10f64.powf(snr_db / 20.0);
            let samples = mic.record(source, c.duration, seed, &format!("cam{k}"));
            SyncInput {
                name: format!("cam{k}"),
                audio: Audio {
                    rate_hz: f64::from(AUDIO_RATE_HZ),
                    samples,
                },
                av_delay_s: mic.av_delay_s,
            }
        })
        .collect()
}

fn mic(offset_s: f64, drift_ppm: f64, av_delay_s: f64, gain: f64) -> Microphone {
    Microphone {
        offset_s,
        drift_ppm,
        propagation_delay_s: 0.003,
        av_delay_s,
        gain,
        noise_sigma: 0.0,
        video_to_device_s: 0.0,
    }
}

/// Check every camera against truth: offsets within 0.5 ms, drift within 2 ppm, status right.
fn check(cams: &[Cam], inputs: &[SyncInput], drift_expected: &[bool]) {
    let result = synchronise(inputs);
    let (o0, d0) = (cams[0].mic.offset_s, cams[0].mic.drift_ppm * 1e-6);
    for (k, (c, got)) in cams.iter().zip(&result.cameras).enumerate() {
        let true_offset = (c.mic.offset_s - o0) / (1.0 + d0);
        let true_drift = ((1.0 + c.mic.drift_ppm * 1e-6) / (1.0 + d0) - 1.0) * 1e6;
        let pairs: Vec<_> = result
            .pairs
            .iter()
            .map(|p| {
                (
                    p.a.clone(),
                    p.b.clone(),
                    p.status.clone(),
                    p.reason.clone(),
                    p.votes,
                    p.peak_ratio,
                )
            })
            .collect();
        let offset = got.offset_s.unwrap_or(f64::NAN);
        assert!(
            (offset - true_offset).abs() < 5e-4,
            "cam{k}: offset {offset} vs truth {true_offset} ({:.3} ms off); pairs {pairs:?}",
            (offset - true_offset) * 1e3
        );
        assert!(
            (got.drift_ppm - true_drift).abs() < 2.0,
            "cam{k}: drift {} vs truth {true_drift}",
            got.drift_ppm
        );
        let expected = if k == 0 {
            CameraStatus::Reference
        } else if drift_expected[k] {
            CameraStatus::OffsetAndDrift
        } else {
            CameraStatus::OffsetOnly
        };
        assert_eq!(
            got.status, expected,
            "cam{k}: drift {} (truth {true_drift})",
            got.drift_ppm
        );
    }
    for c in &result.closures {
        assert!(c.residual_s.abs() < 5e-4, "closure {c:?}");
    }
}

#[test]
fn three_cameras_offsets_and_drift_two_minutes() {
    let cams = [
        Cam {
            mic: mic(0.0, 0.0, 0.032, 1.0),
            duration: 130.0,
        },
        Cam {
            mic: mic(-37.25, 18.0, 0.029, 0.6),
            duration: 120.0,
        },
        Cam {
            mic: mic(21.7, -12.0, 0.061, 1.4),
            duration: 150.0,
        },
    ];
    let inputs = simulate(3, &cams, 10.0, false, true);
    check(&cams, &inputs, &[false, true, true]);
}

#[test]
fn five_cameras_at_0_db_up_to_60_s_apart_and_10_minutes() {
    let cams = [
        Cam {
            mic: mic(0.0, 4.0, 0.032, 1.0),
            duration: 600.0,
        },
        Cam {
            mic: mic(-59.5, 30.0, 0.029, 0.6),
            duration: 420.0,
        },
        Cam {
            mic: mic(58.1, -26.0, 0.061, 1.3),
            duration: 300.0,
        },
        Cam {
            mic: mic(12.345, 4.0, 0.035, 0.8),
            duration: 240.0,
        },
        Cam {
            mic: mic(-5.5, 15.0, 0.032, 1.1),
            duration: 150.0,
        },
    ];
    let inputs = simulate(11, &cams, 0.0, false, true);
    // Camera 3 runs at the reference's rate: its relative drift is zero.
    check(&cams, &inputs, &[false, true, true, false, true]);
}

#[test]
fn different_sample_rates_are_resampled() {
    let cams = [
        Cam {
            mic: mic(0.0, 0.0, 0.032, 1.0),
            duration: 150.0,
        },
        Cam {
            mic: mic(-12.5, 0.0, 0.045, 0.9),
            duration: 150.0,
        },
    ];
    let mut inputs = simulate(5, &cams, 6.0, false, true);
    inputs[1].audio = kiwi_backend::sync::audio::resample(&inputs[1].audio, 44_100.0);
    check(&cams, &inputs, &[false, false]);
}

#[test]
fn recordings_without_common_sound_are_never_matched() {
    for seed in 0..12u64 {
        let cams = [
            Cam {
                mic: mic(0.0, 0.0, 0.03, 1.0),
                duration: 120.0,
            },
            Cam {
                mic: mic(-3.0, 10.0, 0.03, 1.0),
                duration: 120.0,
            },
        ];
        let inputs = simulate(100 + seed, &cams, 10.0, false, false);
        let result = synchronise(&inputs);
        assert_eq!(
            result.pairs[0].status, "unmatched",
            "seed {seed}: {:?}",
            result.pairs[0]
        );
        assert_eq!(result.cameras[1].status, CameraStatus::Unmatched);
    }
}

#[test]
fn a_periodic_source_is_rejected_not_guessed() {
    let cams = [
        Cam {
            mic: mic(0.0, 0.0, 0.03, 1.0),
            duration: 120.0,
        },
        Cam {
            mic: mic(-7.3, 0.0, 0.03, 1.0),
            duration: 120.0,
        },
    ];
    let inputs = simulate(9, &cams, 20.0, true, true);
    let result = synchronise(&inputs);
    let pair = &result.pairs[0];
    assert_eq!(pair.status, "unmatched", "{pair:?}");
    assert!(
        pair.reason.as_deref().unwrap_or("").contains("ambiguous"),
        "{pair:?}"
    );
    assert_eq!(result.cameras[1].status, CameraStatus::Unmatched);
}
