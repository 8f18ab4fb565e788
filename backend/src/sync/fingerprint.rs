//! Coarse lag by spectral landmark fingerprints: spectrogram peaks are paired into hashes
//! (constellation style: anchor frequency, target frequency, time step), and every hash the two
//! recordings share votes for the time difference between them. The true lag collects votes from
//! every shared sound; coincidences scatter. Works at any offset the recordings allow.

use std::collections::HashMap;

use rustfft::FftPlanner;
use rustfft::num_complex::Complex;

/// Sample rate of the fingerprint analysis (Hz): speech and most room sounds live below 4 kHz.
pub const ANALYSIS_RATE_HZ: f64 = 8000.0;
/// STFT frame length (samples at the analysis rate): 64 ms.
const FRAME: usize = 512;
/// STFT hop (samples): 16 ms, the resolution of the coarse lag.
pub const HOP: usize = 128;
/// Half-size of the neighbourhood a peak must dominate: ±6 frames (±96 ms) …
const PEAK_TIME_RADIUS: usize = 6;
/// … and ±10 bins (±156 Hz).
const PEAK_FREQ_RADIUS: usize = 10;
/// A peak must stand this far (dB) above its frame's median: silence and flat noise give none.
const PEAK_MIN_PROMINENCE_DB: f32 = 12.0;
/// Lowest bin used (≈ 94 Hz): below it, rumble and DC.
const MIN_BIN: usize = 6;
/// Targets paired with each anchor.
const FANOUT: usize = 6;
/// Furthest target frame after its anchor (40 frames = 640 ms).
const TARGET_MAX_DT: usize = 40;
/// Largest frequency step between anchor and target (bins).
const TARGET_MAX_DF: usize = 60;

/// A spectrogram peak.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Peak {
    frame: u32,
    bin: u16,
}

/// The landmark hashes of one recording: hash → frames where it occurs.
pub struct Fingerprint {
    index: HashMap<u32, Vec<u32>>,
    hashes: Vec<(u32, u32)>,
    /// Number of STFT frames.
    pub frames: usize,
}

/// Votes for coarse lags between two fingerprints.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CoarseLag {
    /// Lag in frames: a sound at frame `t` of B is at frame `t + lag` of A.
    pub lag_frames: i64,
    /// Votes for the best lag (with its neighbours).
    pub votes: u32,
    /// Votes for the best lag at least 3 frames away from it.
    pub second_votes: u32,
    /// Hashes of A that matched anything in B.
    pub matched_hashes: u32,
}

impl CoarseLag {
    /// Best votes over second-best votes (second counted as at least 1).
    pub fn peak_ratio(&self) -> f64 {
        f64::from(self.votes) / f64::from(self.second_votes.max(1))
    }
}

fn spectrogram(samples: &[f32]) -> (Vec<f32>, usize) {
    let bins = FRAME / 2 + 1;
    if samples.len() < FRAME {
        return (Vec::new(), 0);
    }
    let frames = (samples.len() - FRAME) / HOP + 1;
    let mut planner = FftPlanner::<f32>::new();
    let fft = planner.plan_fft_forward(FRAME);
    let window: Vec<f32> = (0..FRAME)
        .map(|i| 0.5 - 0.5 * (std::f32::consts::TAU * i as f32 / FRAME as f32).cos())
        .collect();
    let mut out = vec![0.0f32; frames * bins];
    let mut buf = vec![Complex::new(0.0f32, 0.0); FRAME];
    let mut scratch = vec![Complex::new(0.0f32, 0.0); fft.get_inplace_scratch_len()];
    for f in 0..frames {
        let start = f * HOP;
        for i in 0..FRAME {
            buf[i] = Complex::new(samples[start + i] * window[i], 0.0);
        }
        fft.process_with_scratch(&mut buf, &mut scratch);
        for b in 0..bins {
            out[f * bins + b] = 10.0 * (buf[b].norm_sqr() + 1e-12).log10();
        }
    }
    (out, frames)
}

fn find_peaks(spec: &[f32], frames: usize) -> Vec<Peak> {
    let bins = FRAME / 2 + 1;
    // Separable max filter: over frequency, then over time.
    let mut fmax = vec![f32::NEG_INFINITY; spec.len()];
    for f in 0..frames {
        let row = &spec[f * bins..(f + 1) * bins];
        for b in 0..bins {
            let lo = b.saturating_sub(PEAK_FREQ_RADIUS);
            let hi = (b + PEAK_FREQ_RADIUS).min(bins - 1);
            fmax[f * bins + b] = row[lo..=hi]
                .iter()
                .copied()
                .fold(f32::NEG_INFINITY, f32::max);
        }
    }
    let mut medians = Vec::with_capacity(frames);
    for f in 0..frames {
        let mut row: Vec<f32> = spec[f * bins + MIN_BIN..(f + 1) * bins].to_vec();
        let mid = row.len() / 2;
        row.select_nth_unstable_by(mid, f32::total_cmp);
        medians.push(row[mid]);
    }
    let mut peaks = Vec::new();
    for f in 0..frames {
        let lo = f.saturating_sub(PEAK_TIME_RADIUS);
        let hi = (f + PEAK_TIME_RADIUS).min(frames - 1);
        for b in MIN_BIN..bins {
            let v = spec[f * bins + b];
            if v < medians[f] + PEAK_MIN_PROMINENCE_DB || v < fmax[f * bins + b] {
                continue;
            }
            if (lo..=hi).all(|g| fmax[g * bins + b] <= v) {
                peaks.push(Peak {
                    frame: f as u32,
                    bin: b as u16,
                });
            }
        }
    }
    peaks
}

impl Fingerprint {
    /// Fingerprint samples taken at [`ANALYSIS_RATE_HZ`].
    pub fn new(samples: &[f32]) -> Self {
        let (spec, frames) = spectrogram(samples);
        let peaks = find_peaks(&spec, frames);
        let mut hashes = Vec::new();
        for (i, a) in peaks.iter().enumerate() {
            let mut n = 0;
            for t in &peaks[i + 1..] {
                let dt = t.frame - a.frame;
                if dt == 0 {
                    continue;
                }
                if dt as usize > TARGET_MAX_DT {
                    break;
                }
                if usize::from(a.bin.abs_diff(t.bin)) > TARGET_MAX_DF {
                    continue;
                }
                let hash = (u32::from(a.bin) << 15) | (u32::from(t.bin) << 6) | dt;
                hashes.push((hash, a.frame));
                n += 1;
                if n >= FANOUT {
                    break;
                }
            }
        }
        let mut index: HashMap<u32, Vec<u32>> = HashMap::with_capacity(hashes.len());
        for &(h, f) in &hashes {
            index.entry(h).or_default().push(f);
        }
        Self {
            index,
            hashes,
            frames,
        }
    }

    /// Number of landmark hashes.
    pub fn len(&self) -> usize {
        self.hashes.len()
    }

    /// Whether the recording produced no landmarks (silence or flat noise).
    pub fn is_empty(&self) -> bool {
        self.hashes.is_empty()
    }

    /// Vote for the lag of `self` (A) relative to `other` (B).
    pub fn coarse_lag(&self, other: &Self) -> Option<CoarseLag> {
        let offset = other.frames as i64;
        let mut votes = vec![0u32; self.frames + other.frames + 1];
        let mut matched = 0;
        for (h, fa) in &self.hashes {
            if let Some(list) = other.index.get(h) {
                matched += 1;
                for fb in list {
                    let lag = i64::from(*fa) - i64::from(*fb);
                    votes[(lag + offset) as usize] += 1;
                }
            }
        }
        // Sum each bin with its neighbours: a peak may land a frame early or late.
        let smoothed: Vec<u32> = (0..votes.len())
            .map(|i| {
                votes[i.saturating_sub(1)..(i + 2).min(votes.len())]
                    .iter()
                    .sum()
            })
            .collect();
        let (best, &best_votes) = smoothed
            .iter()
            .enumerate()
            .max_by_key(|(i, v)| (**v, std::cmp::Reverse(*i)))?;
        let second = smoothed
            .iter()
            .enumerate()
            .filter(|(i, _)| i.abs_diff(best) > 3)
            .map(|(_, v)| *v)
            .max()
            .unwrap_or(0);
        Some(CoarseLag {
            lag_frames: best as i64 - offset,
            votes: best_votes,
            second_votes: second,
            matched_hashes: matched,
        })
    }
}
