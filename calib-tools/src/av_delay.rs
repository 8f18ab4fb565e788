//! A/V delay per camera and recording mode from the QR-clock rig (paper eq. 1, `eq:sync-av`),
//! and optical cross-camera offsets that share no mechanism with audio.
//!
//! Per capture (a prepared camera folder filming the rig): every frame's QR code is decoded,
//! its time corrected for rolling-shutter readout at the code's image row, and the frame times
//! robustly fitted to the display clock; chirp onsets are found by matched filtering and fitted
//! the same way. The A/V delay `d` is the difference of the two fits at mid-recording: a sound
//! at video time `t` is in the audio at `t + d`. Captures recorded together give cross-camera
//! offsets by differencing their video fits.

use std::path::{Path, PathBuf};

use rayon::prelude::*;
use rustfft::FftPlanner;
use rustfft::num_complex::Complex;
use serde::Serialize;

use kiwi_core::artifact::UnitCalibration;
use kiwi_core::audio::read_audio;
use kiwi_core::camera::CameraModel;
use kiwi_core::fit::{LineFit, robust_line};
use kiwi_core::layout::{CameraMeta, EpisodeLayout, read_frames_csv};
use kiwi_core::rig::{
    CHIRP_PERIOD_S, CHIRPS_PER_MARK, DOUBLE_GAP_S, chirp_waveform, parse_qr_text,
};

use crate::error::{CalibError, Result};

/// A video fit whose rate departs from 1 by more than this is not a clock (wrong refresh rate,
/// or a recording sped up by its player).
const MAX_RATE_ERROR: f64 = 2e-3;
/// Fewest decoded frames for a video fit.
const MIN_DECODED_FRAMES: usize = 20;
/// Fewest chirps for an audio fit.
const MIN_CHIRPS: usize = 4;
/// Chirp onsets resolve to ~20 µs; the fit does not believe residuals smaller than this.
const AUDIO_SCALE_FLOOR_S: f64 = 20e-6;
/// Matched-filter peaks below this fraction of the strongest are not chirps.
const CHIRP_RELATIVE_THRESHOLD: f64 = 0.3;
/// Audio and frames of one capture may differ in length by this much (s) before they are
/// judged to come from different recordings.
const MAX_DURATION_MISMATCH_S: f64 = 2.0;
/// Tolerance on the gap of a double chirp (s).
const DOUBLE_GAP_TOLERANCE_S: f64 = 0.004;

/// Options of the analysis.
#[derive(Debug, Clone)]
pub struct AvDelayOptions {
    /// Display refresh rate (Hz).
    pub refresh_hz: f64,
    /// Distance from the rig's speaker to each capture's camera (m), by capture name; the
    /// propagation delay is removed. A capture not named here takes its distance from the
    /// `rig.toml` beside its camera folder ([`rig_speaker_distances`]), else 0.
    pub speaker_distance_m: Vec<(String, f64)>,
    /// Unit calibrations, matched to captures by unit id (readout times; A/V delays written).
    pub calibrations: Vec<(PathBuf, UnitCalibration)>,
}

/// One capture's result.
#[derive(Debug, Clone, Serialize)]
pub struct CaptureResult {
    /// Capture folder name.
    pub name: String,
    /// Unit id.
    pub unit_id: String,
    /// Camera product.
    pub camera_model: String,
    /// Recording mode.
    pub mode: String,
    /// Frames in the capture.
    pub frames: usize,
    /// Frames whose QR decoded consistently.
    pub decoded: usize,
    /// Rolling-shutter readout used for the row correction (s).
    pub readout_s: f64,
    /// Video fit: display clock = intercept + slope · frame time.
    pub video_fit: LineFit,
    /// Chirps found in the audio.
    pub chirps: usize,
    /// Audio fit: display clock = intercept + slope · audio time.
    pub audio_fit: LineFit,
    /// A/V delay `d` (s).
    pub av_delay_s: f64,
    /// Its standard error (s).
    pub av_delay_std_s: f64,
    /// Speaker-to-camera distance whose travel time was removed (m).
    pub speaker_distance_m: f64,
    /// Where that distance came from: `option`, `rig.toml` or `none` (0 m assumed).
    pub speaker_distance_source: String,
    /// Video frame times and fit residuals (s), for the report.
    #[serde(skip)]
    pub video_residuals: Vec<(f64, f64)>,
    /// Chirp times and fit residuals (s).
    #[serde(skip)]
    pub audio_residuals: Vec<(f64, f64)>,
}

/// A/V delay aggregated per camera model and mode.
#[derive(Debug, Clone, Serialize)]
pub struct ModeDelay {
    /// Camera product.
    pub camera_model: String,
    /// Recording mode.
    pub mode: String,
    /// Mean delay (s).
    pub delay_s: f64,
    /// Standard error of the mean (s).
    pub std_s: f64,
    /// Largest minus smallest delay across repeats (s).
    pub spread_s: f64,
    /// Captures aggregated.
    pub repeats: usize,
}

/// Optical offset of one capture's clock relative to the first capture of its recording.
#[derive(Debug, Clone, Serialize)]
pub struct CrossOffset {
    /// Reference capture.
    pub reference: String,
    /// This capture.
    pub capture: String,
    /// `reference_time = capture_time · (1 + drift_ppm·1e-6) + offset_s` (video clocks).
    pub offset_s: f64,
    /// Relative clock rate (ppm).
    pub drift_ppm: f64,
    /// Standard error of the drift (ppm).
    pub drift_std_ppm: f64,
    /// Standard error of the offset (s).
    pub offset_std_s: f64,
}

/// Everything the analysis found.
#[derive(Debug, Clone, Serialize)]
pub struct AvDelayReport {
    /// Per capture.
    pub captures: Vec<CaptureResult>,
    /// Per camera model and mode.
    pub modes: Vec<ModeDelay>,
    /// Cross-camera offsets of captures recorded together (same display clock span).
    pub offsets: Vec<CrossOffset>,
}

fn input_error(path: &Path, message: String) -> CalibError {
    CalibError::Input {
        path: path.to_path_buf(),
        message,
    }
}

/// Highest display refresh rate (Hz) whose frames the rig's millisecond codes tell apart after
/// rounding: frames at least 2 ms apart, so a code rounded by up to 0.5 ms names one frame.
const MAX_REFRESH_HZ: f64 = 500.0;

/// The start (s, display clock) of the display frame a rig code names. The code shows the
/// frame's start rounded to the millisecond (`round(n · 1000 / refresh)`), up to 1/3 ms off at
/// 60 Hz; the clock fit's bounds rest on single codes, so the rounding reached the fit (0.108 ms
/// for an ideal 119.88 fps camera). The frame index is recovered exactly instead.
pub fn display_frame_start(code_clock_s: f64, refresh_hz: f64) -> f64 {
    (code_clock_s * refresh_hz).round() / refresh_hz
}

/// Size of the rectified (pinhole) view a fisheye frame is resampled into for QR decoding (px).
const RECTIFIED_SIZE: usize = 640;
/// Half field of view of the rectified view (deg): the monitor fills the middle of the lens.
const RECTIFIED_HALF_FOV_DEG: f64 = 55.0;

/// For each pixel of a virtual pinhole view along the lens axis, the fisheye pixel it samples:
/// QR codes are straight only in a perspective view, and rqrr expects straight codes.
pub struct RectifyMap {
    size: usize,
    source: Vec<Option<(f32, f32)>>,
    /// The fisheye image size the taps were made for (the lens's resolution).
    tap_size: (usize, usize),
    /// Per rectified pixel, its bilinear taps in a `tap_size` image (`None`: off the lens).
    taps: Vec<Option<Tap>>,
}

/// Where a rectified pixel reads a fisheye image of known size: the top-left neighbour's index,
/// the steps to its right and lower neighbours (0 on the last column or row), and the weights.
#[derive(Debug, Clone, Copy)]
struct Tap {
    index: usize,
    right: usize,
    down: usize,
    fx: f32,
    fy: f32,
}

impl Tap {
    /// The taps of a fisheye position in a `w` × `h` image, clamped at the edges as
    /// [`RectifyMap::rectify`] clamps them.
    fn new(x: f32, y: f32, w: usize, h: usize) -> Self {
        let (x0, y0) = ((x as usize).min(w - 1), (y as usize).min(h - 1));
        let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
        Self {
            index: y0 * w + x0,
            right: x1 - x0,
            down: (y1 - y0) * w,
            fx: x - x0 as f32,
            fy: y - y0 as f32,
        }
    }
}

impl RectifyMap {
    /// The map for a camera model.
    pub fn new(camera: &dyn CameraModel) -> Self {
        let size = RECTIFIED_SIZE;
        let f = (size as f64 / 2.0) / RECTIFIED_HALF_FOV_DEG.to_radians().tan();
        let c = (size as f64 - 1.0) / 2.0;
        let source = (0..size * size)
            .map(|i| {
                let (u, v) = ((i % size) as f64, (i / size) as f64);
                let ray = nalgebra::Vector3::new((u - c) / f, (v - c) / f, 1.0);
                camera
                    .project(&ray)
                    .filter(|p| camera.in_image(p))
                    .map(|p| (p.x as f32, p.y as f32))
            })
            .collect::<Vec<_>>();
        let (w, h) = camera.resolution();
        let tap_size = (w as usize, h as usize);
        let taps: Vec<Option<Tap>> = if tap_size.0 > 0 && tap_size.1 > 0 {
            source
                .iter()
                .map(|s| s.map(|(x, y)| Tap::new(x, y, tap_size.0, tap_size.1)))
                .collect()
        } else {
            Vec::new()
        };
        Self {
            size,
            source,
            tap_size,
            taps,
        }
    }

    fn rectify(&self, img: &image::GrayImage) -> Vec<u8> {
        let (w, h) = (img.width() as usize, img.height() as usize);
        let raw = img.as_raw();
        if (w, h) == self.tap_size && raw.len() == w * h && self.taps.len() == self.source.len() {
            self.rectify_with_taps(raw)
        } else {
            self.rectify_any(img)
        }
    }

    /// [`RectifyMap::rectify`] of an image of the lens's own size through the precomputed taps
    /// (the same arithmetic as [`RectifyMap::rectify_any`]).
    fn rectify_with_taps(&self, raw: &[u8]) -> Vec<u8> {
        self.taps
            .iter()
            .map(|t| match t {
                Some(t) => {
                    let i = t.index;
                    let p = |k: usize| f32::from(raw.get(k).copied().unwrap_or(0));
                    let (a, b) = (p(i), p(i + t.right));
                    let (c, d) = (p(i + t.down), p(i + t.down + t.right));
                    let top = a + (b - a) * t.fx;
                    let bottom = c + (d - c) * t.fx;
                    (top + (bottom - top) * t.fy).clamp(0.0, 255.0) as u8
                }
                None => 255,
            })
            .collect()
    }

    /// [`RectifyMap::rectify`] of an image of any size.
    fn rectify_any(&self, img: &image::GrayImage) -> Vec<u8> {
        let (w, h) = (img.width() as usize, img.height() as usize);
        if w == 0 || h == 0 {
            return vec![255; self.source.len()];
        }
        let raw = img.as_raw();
        self.source
            .iter()
            .map(|s| match s {
                Some((x, y)) => {
                    let (x0, y0) = ((*x as usize).min(w - 1), (*y as usize).min(h - 1));
                    let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
                    let (fx, fy) = (x - x0 as f32, y - y0 as f32);
                    let p = |xx: usize, yy: usize| f32::from(raw[yy * w + xx]);
                    let top = p(x0, y0) + (p(x1, y0) - p(x0, y0)) * fx;
                    let bottom = p(x0, y1) + (p(x1, y1) - p(x0, y1)) * fx;
                    (top + (bottom - top) * fy).clamp(0.0, 255.0) as u8
                }
                None => 255,
            })
            .collect()
    }

    /// The fisheye image row of a rectified pixel.
    fn source_row(&self, x: f64, y: f64) -> Option<f64> {
        let (xi, yi) = (x.round() as usize, y.round() as usize);
        if xi >= self.size || yi >= self.size {
            return None;
        }
        self.source[yi * self.size + xi].map(|(_, row)| f64::from(row))
    }
}

/// Decode the rig code of one frame: the clock and the code centre's image row, or `None` when
/// no rig code is readable or two codes disagree (a refresh caught mid-exposure).
fn decode_frame(path: &Path, map: Option<&RectifyMap>) -> Option<(f64, f64)> {
    let img = image::open(path).ok()?.to_luma8();
    let (pixels, w, h) = match map {
        Some(m) => (m.rectify(&img), m.size, m.size),
        None => (
            img.as_raw().clone(),
            img.width() as usize,
            img.height() as usize,
        ),
    };
    let mut prepared = rqrr::PreparedImage::prepare_from_greyscale(w, h, |x, y| pixels[y * w + x]);
    let mut found: Option<(f64, f64)> = None;
    for grid in prepared.detect_grids() {
        let Ok((_, text)) = grid.decode() else {
            continue;
        };
        let Some(clock) = parse_qr_text(&text) else {
            continue;
        };
        let cx = grid.bounds.iter().map(|p| f64::from(p.x)).sum::<f64>() / 4.0;
        let cy = grid.bounds.iter().map(|p| f64::from(p.y)).sum::<f64>() / 4.0;
        let row = match map {
            Some(m) => m.source_row(cx, cy)?,
            None => cy,
        };
        match found {
            Some((c, _)) if (c - clock).abs() > 1e-9 => return None,
            _ => found = Some((clock, row)),
        }
    }
    found
}

/// Chirp onsets (s) by matched filtering of the audio with the rig's chirp.
pub fn detect_chirps(samples: &[f32], rate_hz: f64) -> Vec<f64> {
    let template = chirp_waveform(rate_hz);
    let n = (samples.len() + template.len()).next_power_of_two();
    let mut planner = FftPlanner::<f64>::new();
    let fft = planner.plan_fft_forward(n);
    let ifft = planner.plan_fft_inverse(n);
    let mut a: Vec<Complex<f64>> = (0..n)
        .map(|i| Complex::new(samples.get(i).map_or(0.0, |v| f64::from(*v)), 0.0))
        .collect();
    let mut b: Vec<Complex<f64>> = (0..n)
        .map(|i| Complex::new(template.get(i).map_or(0.0, |v| f64::from(*v)), 0.0))
        .collect();
    fft.process(&mut a);
    fft.process(&mut b);
    for (x, y) in a.iter_mut().zip(&b) {
        *x *= y.conj();
    }
    ifft.process(&mut a);
    let corr: Vec<f64> = a[..samples.len()].iter().map(|c| c.re.abs()).collect();
    let max = corr.iter().copied().fold(0.0, f64::max);
    if max <= 0.0 {
        return Vec::new();
    }
    let mut sorted = corr.clone();
    let mid = sorted.len() / 2;
    sorted.select_nth_unstable_by(mid, f64::total_cmp);
    let noise = sorted[mid];
    let threshold = (CHIRP_RELATIVE_THRESHOLD * max).max(20.0 * noise);
    let half_window = (0.02 * rate_hz) as usize;
    let mut onsets = Vec::new();
    let mut i = 1;
    while i + 1 < corr.len() {
        if corr[i] >= threshold {
            let end = (i + 2 * half_window).min(corr.len() - 1);
            let (k, _) =
                corr[i..end]
                    .iter()
                    .enumerate()
                    .fold((0, f64::NEG_INFINITY), |acc, (j, v)| {
                        if *v > acc.1 { (j, *v) } else { acc }
                    });
            let k = i + k;
            // The real part oscillates at the chirp frequency: refine on the envelope of |corr|
            // by a parabola through the neighbours.
            let (l, c, r) = (
                corr[k.saturating_sub(1)],
                corr[k],
                corr[(k + 1).min(corr.len() - 1)],
            );
            let denom = l - 2.0 * c + r;
            let frac = if denom.abs() > 1e-300 {
                (0.5 * (l - r) / denom).clamp(-0.5, 0.5)
            } else {
                0.0
            };
            onsets.push((k as f64 + frac) / rate_hz);
            i = k + half_window;
        } else {
            i += 1;
        }
    }
    onsets
}

/// Assign display-clock values to chirp onsets using a video fit (good to ±0.25 s) refined by
/// double-chirp marks (good to ±5 s of A/V delay).
fn label_chirps(onsets: &[f64], video: &LineFit) -> Vec<(f64, f64)> {
    let is_second = |k: usize| {
        k > 0 && ((onsets[k] - onsets[k - 1]) - DOUBLE_GAP_S).abs() < DOUBLE_GAP_TOLERANCE_S
    };
    let mark_period = CHIRP_PERIOD_S * CHIRPS_PER_MARK as f64;
    // Correction from marks: how far the video-predicted clock is from the mark's true clock.
    let mut corrections: Vec<f64> = (0..onsets.len())
        .filter(|&k| k + 1 < onsets.len() && is_second(k + 1))
        .map(|k| {
            let predicted = video.at(onsets[k]);
            (predicted / mark_period).round() * mark_period - predicted
        })
        .collect();
    corrections.sort_by(f64::total_cmp);
    let correction = corrections
        .get(corrections.len() / 2)
        .copied()
        .unwrap_or(0.0);
    (0..onsets.len())
        .filter(|&k| !is_second(k))
        .map(|k| {
            let clock =
                ((video.at(onsets[k]) + correction) / CHIRP_PERIOD_S).round() * CHIRP_PERIOD_S;
            (onsets[k], clock)
        })
        .collect()
}

/// Largest rate difference searched between a camera clock and the display clock: consumer
/// crystals are within ±100 ppm each.
const MAX_CLOCK_RATE_PPM: f64 = 300.0;
/// Slope steps of the coarse search.
const SLOPE_STEPS: usize = 400;

/// The intervals' best stabbing point: how many of `[lo_i, hi_i)` contain it, and the range of
/// such points `[from, to]`.
fn best_stab(intervals: &mut [(f64, f64)]) -> (usize, f64, f64) {
    let mut events: Vec<(f64, i32)> = intervals
        .iter()
        .flat_map(|&(lo, hi)| [(lo, 1), (hi, -1)])
        .collect();
    // Ends sort before starts at equal values (half-open intervals).
    events.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    let (mut depth, mut best, mut from, mut to) = (0i32, 0i32, 0.0, 0.0);
    for k in 0..events.len() {
        depth += events[k].1;
        if depth > best {
            best = depth;
            from = events[k].0;
            to = events.get(k + 1).map_or(from, |e| e.0);
        }
    }
    (best.max(0) as usize, from, to)
}

/// Fit `clock = a + b·t` to frames whose codes show the display clock rounded down to the
/// refresh: the line must pass through `[q_i, q_i + period)` at `t_i`. Maximizes the number of
/// frames it passes (robust to mis-decoded frames) over slopes within ±[`MAX_CLOCK_RATE_PPM`]
/// of 1, and takes the centre of the best region (`initial` only seeds a degenerate case). Unlike least squares on interval
/// midpoints, this stays unbiased when the camera rate nearly divides the refresh (119.88 fps
/// on 60 Hz beats with an 8 s period).
pub fn quantized_clock_fit(t: &[f64], q: &[f64], period: f64, initial: &LineFit) -> LineFit {
    let n = t.len().min(q.len());
    let t_ref = t[..n].iter().sum::<f64>() / n.max(1) as f64;
    let half_range = MAX_CLOCK_RATE_PPM * 1e-6;
    let evaluate = |b: f64| {
        let mut intervals: Vec<(f64, f64)> = (0..n)
            .map(|i| {
                (
                    q[i] - b * (t[i] - t_ref),
                    q[i] + period - b * (t[i] - t_ref),
                )
            })
            .collect();
        best_stab(&mut intervals)
    };
    let search = |lo: f64, hi: f64, steps: usize| {
        let mut results = Vec::with_capacity(steps + 1);
        for k in 0..=steps {
            let b = lo + (hi - lo) * k as f64 / steps as f64;
            results.push((b, evaluate(b)));
        }
        results
    };
    let coarse = search(1.0 - half_range, 1.0 + half_range, SLOPE_STEPS);
    let best_count = coarse.iter().map(|r| r.1.0).max().unwrap_or(0);
    let winners: Vec<f64> = coarse
        .iter()
        .filter(|r| r.1.0 == best_count)
        .map(|r| r.0)
        .collect();
    let step = 2.0 * half_range / SLOPE_STEPS as f64;
    let (b_lo, b_hi) = (
        winners.first().copied().unwrap_or(initial.slope) - step,
        winners.last().copied().unwrap_or(initial.slope) + step,
    );
    let fine = search(b_lo, b_hi, SLOPE_STEPS);
    let best_count = fine.iter().map(|r| r.1.0).max().unwrap_or(0);
    let winners: Vec<&(f64, (usize, f64, f64))> =
        fine.iter().filter(|r| r.1.0 == best_count).collect();
    let b = winners.iter().map(|r| r.0).sum::<f64>() / winners.len().max(1) as f64;
    let (count, from, to) = evaluate(b);
    let a_mid = 0.5 * (from + to);
    let b_range = winners.last().map_or(0.0, |r| r.0) - winners.first().map_or(0.0, |r| r.0);
    let fine_step = (b_hi - b_lo) / SLOPE_STEPS as f64;
    let inlier_mask: Vec<bool> = (0..n)
        .map(|i| {
            let v = a_mid + b * (t[i] - t_ref);
            v >= q[i] && v < q[i] + period
        })
        .collect();
    let rms = ((0..n)
        .filter(|i| inlier_mask[*i])
        .map(|i| (q[i] + period / 2.0 - a_mid - b * (t[i] - t_ref)).powi(2))
        .sum::<f64>()
        / count.max(1) as f64)
        .sqrt();
    // Uncertainty: the feasible region's width, but never less than what the scatter about the
    // line supports (rows, blends and decoding errors are not in the interval model).
    let stt: f64 = (0..n)
        .filter(|i| inlier_mask[*i])
        .map(|i| (t[i] - t_ref).powi(2))
        .sum();
    let slope_std =
        (b_range.max(fine_step) / 12f64.sqrt()).max(if stt > 0.0 { rms / stt.sqrt() } else { 0.0 });
    let mid_std = ((to - from).max(1e-6) / 12f64.sqrt()).max(rms / (count.max(1) as f64).sqrt());
    LineFit {
        intercept: a_mid - b * t_ref,
        slope: b,
        intercept_std: (mid_std * mid_std + (slope_std * t_ref).powi(2)).sqrt(),
        slope_std,
        x_mid: t_ref,
        mid_std,
        inliers: count,
        rms,
        inlier_mask,
    }
}

/// Variance of a fit's value at `x` (from its mid-point and slope uncertainties).
fn fit_variance(fit: &LineFit, x: f64) -> f64 {
    fit.mid_std.powi(2) + (fit.slope_std * (x - fit.x_mid)).powi(2)
}

/// Analyse one capture folder.
pub fn analyse_capture(dir: &Path, options: &AvDelayOptions) -> Result<CaptureResult> {
    if !(options.refresh_hz > 0.0 && options.refresh_hz <= MAX_REFRESH_HZ) {
        return Err(input_error(
            dir,
            format!(
                "display refresh {} Hz: expected a rate above 0 and at most {MAX_REFRESH_HZ} Hz \
                 (the monitor's refresh rate, e.g. --refresh 60)",
                options.refresh_hz
            ),
        ));
    }
    let name = dir.file_name().map_or_else(
        || dir.display().to_string(),
        |n| n.to_string_lossy().into_owned(),
    );
    let parent = dir.parent().unwrap_or(Path::new("."));
    let layout = EpisodeLayout::new(parent);
    let meta: CameraMeta = layout.read_meta(&name)?;
    let lens = meta
        .lenses
        .first()
        .ok_or_else(|| input_error(dir, "meta.json lists no lens".into()))?;
    let frames = read_frames_csv(&layout.frames_csv(&name, lens))?;
    let calibration = options
        .calibrations
        .iter()
        .find(|(_, c)| c.unit_id == meta.unit_id);
    let readout_s = calibration
        .and_then(|(_, c)| c.recording_modes.iter().find(|m| m.name == meta.mode))
        .and_then(|m| m.readout_time_s)
        .unwrap_or(0.0);
    let Some(first) = frames.first() else {
        return Err(input_error(dir, "frames.csv lists no frames".into()));
    };
    let height = image::image_dimensions(layout.frame_path(&name, lens, first))
        .map_err(|e| {
            input_error(
                &layout.frame_path(&name, lens, first),
                format!("unreadable image: {e}"),
            )
        })
        .map(|(_, h)| f64::from(h))?;
    // With the lens model known, decode in a rectified perspective view.
    let map = match calibration.and_then(|(_, c)| c.lens(lens)) {
        Some(l) => Some(RectifyMap::new(&l.camera()?)),
        None => None,
    };
    let decoded: Vec<(f64, f64, f64)> = frames
        .par_iter()
        .filter_map(|f| {
            decode_frame(&layout.frame_path(&name, lens, f), map.as_ref())
                .map(|(clock, row)| (f.t, display_frame_start(clock, options.refresh_hz), row))
        })
        .collect();
    if decoded.len() < MIN_DECODED_FRAMES {
        return Err(input_error(
            dir,
            format!(
                "{} of {} frames show a readable rig QR code (need {MIN_DECODED_FRAMES}); is the monitor in view, in focus and large enough?",
                decoded.len(),
                frames.len()
            ),
        ));
    }
    // A code showing clock c was on screen during [c, c + 1/refresh): its mean is half a refresh later.
    let half_refresh = 0.5 / options.refresh_hz;
    let x: Vec<f64> = decoded
        .iter()
        .map(|(t, _, row)| t + readout_s * row / height)
        .collect();
    let y: Vec<f64> = decoded.iter().map(|(_, c, _)| c + half_refresh).collect();
    let initial = robust_line(&x, &y, true, 1.0 / options.refresh_hz / 12f64.sqrt())
        .ok_or_else(|| input_error(dir, "the video clock fit failed".into()))?;
    let q: Vec<f64> = decoded.iter().map(|(_, c, _)| *c).collect();
    let video_fit = quantized_clock_fit(&x, &q, 1.0 / options.refresh_hz, &initial);
    if (video_fit.slope - 1.0).abs() > MAX_RATE_ERROR {
        return Err(input_error(
            dir,
            format!(
                "frame times and the displayed clock disagree in rate by {:.0} ppm; is --refresh {} Hz the monitor's rate?",
                (video_fit.slope - 1.0) * 1e6,
                options.refresh_hz
            ),
        ));
    }
    let audio = read_audio(&layout.audio_wav(&name))?;
    let frames_span = frames.last().map_or(0.0, |f| f.t) - frames.first().map_or(0.0, |f| f.t);
    if (audio.duration_s() - frames_span).abs() > MAX_DURATION_MISMATCH_S.max(0.05 * frames_span) {
        return Err(input_error(
            &layout.audio_wav(&name),
            format!(
                "the audio lasts {:.1} s but the frames span {:.1} s; are audio.wav and the frames from the same recording?",
                audio.duration_s(),
                frames_span
            ),
        ));
    }
    let onsets = detect_chirps(&audio.samples, audio.rate_hz);
    let labelled = label_chirps(&onsets, &video_fit);
    if labelled.len() < MIN_CHIRPS {
        return Err(input_error(
            &layout.audio_wav(&name),
            format!(
                "found {} rig chirps (need {MIN_CHIRPS}); was the rig's sound on and audible?",
                labelled.len()
            ),
        ));
    }
    let (distance, distance_source) =
        match options.speaker_distance_m.iter().find(|(n, _)| *n == name) {
            Some((_, d)) => (*d, "option"),
            None => match rig_speaker_distances(dir)?
                .into_iter()
                .find(|(n, _)| *n == name)
            {
                Some((_, d)) => (d, "rig.toml"),
                None => (0.0, "none"),
            },
        };
    let propagation = distance / kiwi_core::rig::SPEED_OF_SOUND_M_S;
    let ax: Vec<f64> = labelled.iter().map(|(t, _)| t - propagation).collect();
    let ay: Vec<f64> = labelled.iter().map(|(_, c)| *c).collect();
    let audio_fit = robust_line(&ax, &ay, true, AUDIO_SCALE_FLOOR_S)
        .ok_or_else(|| input_error(dir, "the audio clock fit failed".into()))?;
    // d at the middle of the display clock span covered.
    let clock_mid = video_fit.at(video_fit.x_mid);
    let t_video = (clock_mid - video_fit.intercept) / video_fit.slope;
    let t_audio = (clock_mid - audio_fit.intercept) / audio_fit.slope;
    let av_delay_s = t_audio - t_video;
    let av_delay_std_s = (fit_variance(&video_fit, t_video) / video_fit.slope.powi(2)
        + fit_variance(&audio_fit, t_audio) / audio_fit.slope.powi(2))
    .sqrt();
    let video_residuals = x
        .iter()
        .zip(&y)
        .map(|(t, c)| (*t, c - video_fit.at(*t)))
        .collect();
    let audio_residuals = ax
        .iter()
        .zip(&ay)
        .map(|(t, c)| (*t, c - audio_fit.at(*t)))
        .collect();
    Ok(CaptureResult {
        name,
        unit_id: meta.unit_id,
        camera_model: meta.camera_model,
        mode: meta.mode,
        frames: frames.len(),
        decoded: video_fit.inliers,
        readout_s,
        chirps: audio_fit.inliers,
        av_delay_s,
        av_delay_std_s,
        speaker_distance_m: distance,
        speaker_distance_source: distance_source.to_string(),
        video_fit,
        audio_fit,
        video_residuals,
        audio_residuals,
    })
}

/// A rig speaker further than this from the camera is a unit mistake (cm or mm for m).
pub const MAX_SPEAKER_DISTANCE_M: f64 = 20.0;

/// Check a speaker distance in metres read from `path` (`what` names the entry).
fn check_speaker_distance(d: f64, path: &Path, what: &str) -> Result<f64> {
    if d.is_finite() && (0.0..MAX_SPEAKER_DISTANCE_M).contains(&d) {
        Ok(d)
    } else {
        Err(input_error(
            path,
            format!(
                "{what} = {d}: expected metres in [0, {MAX_SPEAKER_DISTANCE_M}) (a distance in cm \
                 or mm?)"
            ),
        ))
    }
}

/// The rig's measured speaker distances from the `rig.toml` beside a rig recording's camera
/// folders (`[speaker_distance_m]`, `camera = metres`), so the analysis removes the sound's
/// travel time; none when the file is absent.
pub fn rig_speaker_distances(camera_dir: &Path) -> Result<Vec<(String, f64)>> {
    #[derive(serde::Deserialize)]
    #[serde(deny_unknown_fields)]
    struct RigGeometry {
        #[serde(default)]
        speaker_distance_m: std::collections::BTreeMap<String, f64>,
    }
    let Some(path) = camera_dir.parent().map(|p| p.join("rig.toml")) else {
        return Ok(Vec::new());
    };
    if !path.exists() {
        return Ok(Vec::new());
    }
    let text = std::fs::read_to_string(&path)
        .map_err(|e| input_error(&path, format!("cannot read the rig geometry: {e}")))?;
    let rig: RigGeometry = toml::from_str(&text).map_err(|e| {
        input_error(
            &path,
            format!("expected `[speaker_distance_m]` with `camera = metres` entries: {e}"),
        )
    })?;
    for (camera, d) in &rig.speaker_distance_m {
        check_speaker_distance(*d, &path, &format!("speaker_distance_m.{camera}"))?;
    }
    Ok(rig.speaker_distance_m.into_iter().collect())
}

/// Analyse captures, aggregate per mode, and difference the video fits of captures whose
/// display-clock spans overlap (recorded together).
pub fn analyse(captures: &[PathBuf], options: &AvDelayOptions) -> Result<AvDelayReport> {
    let results: Vec<CaptureResult> = captures
        .iter()
        .map(|c| analyse_capture(c, options))
        .collect::<Result<_>>()?;
    Ok(summarize(results))
}

/// Aggregate analysed captures per camera model and mode, and difference the video fits of
/// captures whose display-clock spans overlap (recorded together).
pub fn summarize(results: Vec<CaptureResult>) -> AvDelayReport {
    let mut modes: Vec<ModeDelay> = Vec::new();
    for r in &results {
        if modes
            .iter()
            .any(|m| m.camera_model == r.camera_model && m.mode == r.mode)
        {
            continue;
        }
        let group: Vec<&CaptureResult> = results
            .iter()
            .filter(|x| x.camera_model == r.camera_model && x.mode == r.mode)
            .collect();
        let n = group.len() as f64;
        let mean = group.iter().map(|g| g.av_delay_s).sum::<f64>() / n;
        let spread = group
            .iter()
            .map(|g| g.av_delay_s)
            .fold(f64::NEG_INFINITY, f64::max)
            - group
                .iter()
                .map(|g| g.av_delay_s)
                .fold(f64::INFINITY, f64::min);
        // Standard error: propagated fit errors, or the scatter across repeats if larger.
        let propagated = (group.iter().map(|g| g.av_delay_std_s.powi(2)).sum::<f64>()).sqrt() / n;
        let scatter = if group.len() > 1 {
            (group
                .iter()
                .map(|g| (g.av_delay_s - mean).powi(2))
                .sum::<f64>()
                / (n - 1.0))
                .sqrt()
                / n.sqrt()
        } else {
            0.0
        };
        modes.push(ModeDelay {
            camera_model: r.camera_model.clone(),
            mode: r.mode.clone(),
            delay_s: mean,
            std_s: propagated.max(scatter),
            spread_s: spread,
            repeats: group.len(),
        });
    }
    let span = |r: &CaptureResult| {
        let first = r.video_residuals.first().map_or(0.0, |p| p.0);
        let last = r.video_residuals.last().map_or(0.0, |p| p.0);
        (r.video_fit.at(first), r.video_fit.at(last))
    };
    let mut offsets = Vec::new();
    for (k, r) in results.iter().enumerate() {
        let Some(reference) = results[..k].iter().find(|q| {
            let (a0, a1) = span(q);
            let (b0, b1) = span(r);
            a0.max(b0) < a1.min(b1)
        }) else {
            continue;
        };
        let (rf, cf) = (&reference.video_fit, &r.video_fit);
        // reference_time = (cf.intercept + cf.slope·t − rf.intercept) / rf.slope.
        offsets.push(CrossOffset {
            reference: reference.name.clone(),
            capture: r.name.clone(),
            offset_s: (cf.intercept - rf.intercept) / rf.slope,
            drift_ppm: (cf.slope / rf.slope - 1.0) * 1e6,
            drift_std_ppm: (cf.slope_std.powi(2) + rf.slope_std.powi(2)).sqrt() * 1e6,
            offset_std_s: (fit_variance(cf, 0.0)
                + fit_variance(rf, (cf.intercept - rf.intercept) / rf.slope))
            .sqrt(),
        });
    }
    AvDelayReport {
        captures: results,
        modes,
        offsets,
    }
}

/// A scatter plot of a clock fit's residuals (ms) against time (s).
pub fn residual_chart(title: &str, points: &[(f64, f64)]) -> kiwi_plot::Chart {
    use kiwi_plot::{Axis, Chart, Mark, Series};
    let mut c = Chart::new(
        640,
        280,
        title,
        Axis::new("time (s)"),
        Axis::new("residual (ms)"),
    );
    c.series.push(Series::new(
        "",
        kiwi_plot::PALETTE[0],
        Mark::Points(2),
        points.iter().map(|&(t, r)| (t, r * 1e3)).collect(),
    ));
    c
}

/// Write the report folder: `av_delay.json`, `report.md` and residual plots (SVG), plus, for
/// each unit with a calibration given, its `calibration.json` with the measured A/V delays.
pub fn write_outputs(
    report: &AvDelayReport,
    options: &AvDelayOptions,
    out: &Path,
) -> Result<Vec<PathBuf>> {
    use kiwi_core::artifact::AvDelay;
    let mut written = Vec::new();
    let json =
        serde_json::to_string_pretty(report).map_err(|e| CalibError::Internal(e.to_string()))?;
    let path = out.join("av_delay.json");
    kiwi_core::io::write_atomic(&path, json.as_bytes())?;
    written.push(path);
    let mut md = String::from(
        "# A/V delay from the QR-clock rig\n\n| camera model | mode | d (ms) | std (ms) | spread (ms) | repeats |\n|---|---|---|---|---|---|\n",
    );
    for m in &report.modes {
        md.push_str(&format!(
            "| {} | {} | {:.3} | {:.3} | {:.3} | {} |\n",
            m.camera_model,
            m.mode,
            m.delay_s * 1e3,
            m.std_s * 1e3,
            m.spread_s * 1e3,
            m.repeats
        ));
    }
    md.push_str("\n## Captures\n\n");
    for c in &report.captures {
        md.push_str(&format!(
            "### {}\n{} of {} frames decoded, {} chirps; d = {:.3} ± {:.3} ms; video rate {:+.1} ppm, residual RMS {:.2} ms; audio residual RMS {:.3} ms\n\n![video](plots/{}_video.svg)\n![audio](plots/{}_audio.svg)\n\n",
            c.name, c.decoded, c.frames, c.chirps, c.av_delay_s * 1e3, c.av_delay_std_s * 1e3, (c.video_fit.slope - 1.0) * 1e6, c.video_fit.rms * 1e3, c.audio_fit.rms * 1e3, c.name, c.name
        ));
        for (kind, points) in [("video", &c.video_residuals), ("audio", &c.audio_residuals)] {
            let p = out.join("plots").join(format!("{}_{kind}.svg", c.name));
            residual_chart(&format!("{} {kind} clock fit", c.name), points).save_svg(&p)?;
        }
    }
    if !report.offsets.is_empty() {
        md.push_str("## Cross-camera offsets (optical)\n\n| reference | capture | offset (s) | drift (ppm) | std (ms) |\n|---|---|---|---|---|\n");
        for o in &report.offsets {
            md.push_str(&format!(
                "| {} | {} | {:.6} | {:+.2} | {:.3} |\n",
                o.reference,
                o.capture,
                o.offset_s,
                o.drift_ppm,
                o.offset_std_s * 1e3
            ));
        }
    }
    let path = out.join("report.md");
    kiwi_core::io::write_atomic(&path, md.as_bytes())?;
    written.push(path);
    for (_, calibration) in &options.calibrations {
        let mut updated = calibration.clone();
        let mut changed = false;
        // The unit's own captures, per mode (the per-model aggregate mixes units).
        let own: Vec<&CaptureResult> = report
            .captures
            .iter()
            .filter(|c| c.unit_id == calibration.unit_id)
            .collect();
        let mut modes: Vec<&str> = own.iter().map(|c| c.mode.as_str()).collect();
        modes.sort_unstable();
        modes.dedup();
        for mode in modes {
            let repeats: Vec<&&CaptureResult> = own.iter().filter(|c| c.mode == mode).collect();
            let n = repeats.len() as f64;
            let mean = repeats.iter().map(|c| c.av_delay_s).sum::<f64>() / n;
            let std = (repeats
                .iter()
                .map(|c| c.av_delay_std_s.powi(2))
                .sum::<f64>())
            .sqrt()
                / n;
            updated.av_delays.retain(|d| d.mode != mode);
            updated.av_delays.push(AvDelay {
                mode: mode.to_string(),
                delay_s: mean,
                std_s: std,
                repeats: repeats.len() as u32,
            });
            changed = true;
        }
        if changed {
            updated.provenance.tool = "kiwi-calib av-delay".into();
            updated.provenance.tool_version = env!("CARGO_PKG_VERSION").into();
            updated.provenance.created_utc = kiwi_core::io::utc_now_rfc3339();
            let path = out.join(&calibration.unit_id).join("calibration.json");
            updated.save(&path)?;
            written.push(path);
        }
    }
    Ok(written)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every display frame's start is recovered exactly from its rounded code, at common
    /// refresh rates and far into the display clock.
    #[test]
    fn codes_name_their_display_frame_exactly() {
        for refresh in [24.0, 50.0, 60.0, 120.0, 144.0, 240.0, MAX_REFRESH_HZ] {
            for n in (0u64..200_000).step_by(7).chain(10_000_000..10_000_050) {
                let clock = parse_qr_text(&kiwi_core::rig::qr_text(n, refresh))
                    .unwrap_or_else(|| panic!("frame {n} at {refresh} Hz: no clock"));
                let start = display_frame_start(clock, refresh);
                assert_eq!(start, n as f64 / refresh, "frame {n} at {refresh} Hz");
            }
        }
    }

    /// An ideal camera (global shutter, instantaneous exposure) at 119.88 fps filming the 60 Hz
    /// clock for the recommended 20 s: the video fit places the display clock within 0.05 ms at
    /// mid-recording whatever the clock's phase (0.006 ms worst). Taking the rounded codes as the
    /// frames' starts left it 0.108 ms off.
    #[test]
    fn the_clock_fit_of_an_ideal_camera_is_exact() {
        let (refresh, fps, seconds) = (60.0, 119.88, 20.0);
        let t: Vec<f64> = (0..(seconds * fps) as usize)
            .map(|i| i as f64 / fps)
            .collect();
        let mut worst: f64 = 0.0;
        for k in 0..24 {
            let clock0 = 100.0 + 0.000_731 * f64::from(k) + 0.019 * f64::from(k % 5);
            let clock = |t: f64| clock0 + t * (1.0 + 20e-6);
            let q: Vec<f64> = t
                .iter()
                .map(|&ti| {
                    let n = (clock(ti) * refresh).floor() as u64;
                    let code = parse_qr_text(&kiwi_core::rig::qr_text(n, refresh))
                        .unwrap_or_else(|| panic!("frame {n}: no clock"));
                    display_frame_start(code, refresh)
                })
                .collect();
            let y: Vec<f64> = q.iter().map(|c| c + 0.5 / refresh).collect();
            let initial = robust_line(&t, &y, true, 1.0 / refresh / 12f64.sqrt())
                .unwrap_or_else(|| panic!("no initial line"));
            let fit = quantized_clock_fit(&t, &q, 1.0 / refresh, &initial);
            let mid = 0.5 * seconds;
            worst = worst.max((fit.intercept + fit.slope * mid - clock(mid)).abs());
        }
        assert!(worst < 5e-5, "clock fit off by up to {:.3} ms", worst * 1e3);
    }

    /// The precomputed taps rectify exactly as the general path does.
    #[test]
    fn rectify_with_taps_matches_the_general_path() {
        let camera = kiwi_core::camera::Kb4::new(
            96,
            80,
            [30.0, 30.5, 47.5, 39.5, 0.02, -0.01, 0.003, -0.0005],
        )
        .map_err(|e| e.to_string())
        .unwrap_or_else(|e| panic!("{e}"));
        let map = RectifyMap::new(&camera);
        assert_eq!(map.taps.len(), map.source.len());
        let pixels: Vec<u8> = (0u32..96 * 80)
            .map(|i| (i.wrapping_mul(2_654_435_761) >> 24) as u8)
            .collect();
        let img =
            image::GrayImage::from_raw(96, 80, pixels).unwrap_or_else(|| panic!("image size"));
        let fast = map.rectify_with_taps(img.as_raw());
        assert_eq!(fast, map.rectify_any(&img));
        assert_eq!(fast, map.rectify(&img));
        assert!(fast.iter().any(|&v| v != 255));
        // An image of another size goes the general way; an empty one is all white.
        let empty = map.rectify(&image::GrayImage::new(0, 0));
        assert!(empty.len() == map.source.len() && empty.iter().all(|&v| v == 255));
    }
}
