//! Audio time synchronisation of all cameras of an episode (paper §4.1, eq. 1 `eq:sync-av`).
//!
//! For every pair of cameras: landmark fingerprints vote for a coarse lag ([`fingerprint`]),
//! GCC-PHAT refines it in windows across the overlap and a robust line fit separates offset from
//! drift ([`refine`]). A pair is accepted only with strong, unambiguous evidence; otherwise it is
//! reported unmatched with the reason. All accepted pairs are then solved together for each
//! camera's clock (robust Gauss–Newton on the window lags), after dropping pairs that do not
//! close around triangles. A/V delays turn audio placement into video placement.
//!
//! Result convention: `session_time = local_video_time · (1 + drift_ppm·1e-6) + offset_s`, the
//! first camera being the reference (0, 0).

pub mod audio;
pub mod fingerprint;
pub mod refine;

use std::path::Path;

use rayon::prelude::*;
use serde::Serialize;

use audio::{Audio, decimate, resample};
use fingerprint::{ANALYSIS_RATE_HZ, Fingerprint, HOP};
use refine::{LineFit, WindowLag, robust_line, window_lags};

use crate::error::{BackendError, Result};

/// Common sample rate every recording is brought to (Hz).
pub const COMMON_RATE_HZ: f64 = 48_000.0;
/// Fewest fingerprint votes for the best lag: below this a shared sound is not proven. Unrelated
/// recordings give chance votes spread over every lag (60 pairs of simulated 8-20 s recordings
/// from different sessions: at most 2 at any lag), while two cameras of one 8 s episode share
/// 22-95 (18 episodes of six sessions, 40-322 over 8-20 s); with [`MIN_PEAK_RATIO`] and the
/// GCC-PHAT windows after it, a chance lag does not reach 12.
pub const MIN_VOTES: u32 = 12;
/// Best lag votes over the runner-up: below this the lag is ambiguous (periodic sounds).
pub const MIN_PEAK_RATIO: f64 = 4.0;
/// Fewest GCC-PHAT windows that must agree with the coarse lag.
pub const MIN_WINDOWS: usize = 4;
/// A refined lag further than this from the coarse one means the two stages disagree (s).
const COARSE_AGREEMENT_S: f64 = 0.04;
/// Drift below this (ppm) is not reported even if significant: it is under 0.3 ms over 10 min.
const MIN_REPORTED_DRIFT_PPM: f64 = 0.5;
/// Clock tolerance (ppm): consumer camera crystals stay well within ±100 ppm; a well-supported
/// larger drift means a wrong match (or a camera whose clock jumped) and rejects the pair.
pub const MAX_DRIFT_PPM: f64 = 150.0;
/// Significance (standard errors) for calling a drift real.
const DRIFT_SIGMAS: f64 = 4.0;
/// A pair whose mean residual in the joint solution exceeds this (s) is inconsistent and dropped.
const PAIR_CONSISTENCY_S: f64 = 0.002;
/// Windows refined per pair at most (spread over the overlap).
const MAX_WINDOWS: usize = 48;

/// One camera's audio and its A/V delay.
#[derive(Debug, Clone)]
pub struct SyncInput {
    /// Camera name.
    pub name: String,
    /// Its audio track.
    pub audio: Audio,
    /// A/V delay `d` of its recording mode (s); 0 if unknown.
    pub av_delay_s: f64,
}

/// How a camera was placed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum CameraStatus {
    /// The reference (first) camera.
    Reference,
    /// Offset from audio; no drift measured.
    OffsetOnly,
    /// Offset and drift from audio.
    OffsetAndDrift,
    /// No accepted evidence connects it to the reference.
    Unmatched,
}

/// One camera's clock on the session timeline.
#[derive(Debug, Clone, Serialize, serde::Deserialize)]
pub struct CameraClock {
    /// Camera name.
    pub name: String,
    /// Session time at local video time 0 (s); `None` when the camera is unmatched (no
    /// accepted evidence connects it to the reference, so it has no place on the timeline).
    pub offset_s: Option<f64>,
    /// Clock rate error relative to the reference (ppm).
    pub drift_ppm: f64,
    /// Standard error of the offset (s).
    pub offset_std_s: f64,
    /// How it was placed.
    pub status: CameraStatus,
}

/// The evidence for one pair.
#[derive(Debug, Clone, Serialize, serde::Deserialize)]
pub struct PairEvidence {
    /// Camera A.
    pub a: String,
    /// Camera B.
    pub b: String,
    /// `accepted`, `unmatched` or `dropped` (inconsistent with the other pairs).
    pub status: String,
    /// Why it was not accepted.
    pub reason: Option<String>,
    /// Fingerprint votes for the best lag.
    pub votes: u32,
    /// Best over second-best votes.
    pub peak_ratio: f64,
    /// Coarse lag `a_A − a_B` (s).
    pub coarse_lag_s: f64,
    /// Refined audio lag at B's time 0 (s).
    pub lag_s: Option<f64>,
    /// Relative drift (ppm), when measured.
    pub drift_ppm: Option<f64>,
    /// `offset-only` or `offset-and-drift`.
    pub class: Option<String>,
    /// Median GCC-PHAT peak strength of the windows used.
    pub gcc_peak: Option<f64>,
    /// GCC-PHAT windows that agreed.
    pub windows: usize,
    /// RMS of the windows about the fitted line (s).
    pub residual_rms_s: Option<f64>,
    /// Mean residual of this pair in the joint solution (s).
    pub solution_residual_s: Option<f64>,
    #[serde(skip)]
    points: Vec<WindowLag>,
    #[serde(skip)]
    indices: (usize, usize),
    #[serde(skip)]
    fit: Option<LineFit>,
}

/// A triangle's closure residual (s): the lag around it should sum to zero.
#[derive(Debug, Clone, Serialize, serde::Deserialize)]
pub struct Closure {
    /// The three cameras.
    pub cameras: [String; 3],
    /// Residual (s).
    pub residual_s: f64,
}

/// The result of synchronising an episode's cameras.
#[derive(Debug, Clone, Serialize, serde::Deserialize)]
pub struct SyncResult {
    /// Per camera, in input order (the first is the reference).
    pub cameras: Vec<CameraClock>,
    /// Per pair, the evidence.
    pub pairs: Vec<PairEvidence>,
    /// Closure residuals of triangles of accepted pairs.
    pub closures: Vec<Closure>,
}

struct Prepared {
    full: Vec<f32>,
    fingerprint: Fingerprint,
}

fn prepare(audio: &Audio) -> Prepared {
    let full = resample(audio, COMMON_RATE_HZ).samples;
    let common = Audio {
        rate_hz: COMMON_RATE_HZ,
        samples: full,
    };
    let low = decimate(
        &common,
        (COMMON_RATE_HZ / ANALYSIS_RATE_HZ).round() as usize,
    );
    let fingerprint = Fingerprint::new(&low.samples);
    Prepared {
        full: common.samples,
        fingerprint,
    }
}

/// Analyse one pair (A, B): coarse lag, windows, line fit, classification.
fn analyse_pair(
    names: (&str, &str),
    indices: (usize, usize),
    a: &Prepared,
    b: &Prepared,
) -> PairEvidence {
    let mut ev = PairEvidence {
        a: names.0.into(),
        b: names.1.into(),
        status: "unmatched".into(),
        reason: None,
        votes: 0,
        peak_ratio: 0.0,
        coarse_lag_s: 0.0,
        lag_s: None,
        drift_ppm: None,
        class: None,
        gcc_peak: None,
        windows: 0,
        residual_rms_s: None,
        solution_residual_s: None,
        points: Vec::new(),
        indices,
        fit: None,
    };
    let Some(coarse) = a.fingerprint.coarse_lag(&b.fingerprint) else {
        ev.reason = Some("no landmarks in one of the recordings (silent?)".into());
        return ev;
    };
    ev.votes = coarse.votes;
    ev.peak_ratio = coarse.peak_ratio();
    ev.coarse_lag_s = coarse.lag_frames as f64 * HOP as f64 / ANALYSIS_RATE_HZ;
    if coarse.votes < MIN_VOTES {
        ev.reason = Some(format!(
            "only {} fingerprint votes (need {MIN_VOTES}): no common sound proven",
            coarse.votes
        ));
        return ev;
    }
    if ev.peak_ratio < MIN_PEAK_RATIO {
        ev.reason = Some(format!(
            "ambiguous lag: best/second votes {:.1} (need {MIN_PEAK_RATIO}); periodic sound?",
            ev.peak_ratio
        ));
        return ev;
    }
    let rate = COMMON_RATE_HZ;
    let coarse_lag = (ev.coarse_lag_s * rate).round() as i64;
    // Windows over B's part of the overlap.
    let b_start = (-coarse_lag).max(0) as usize;
    let b_end = (b.full.len() as i64)
        .min(a.full.len() as i64 - coarse_lag)
        .max(0) as usize;
    let w = (refine::WINDOW_S * rate) as usize;
    let margin = (refine::SEARCH_S * rate) as usize;
    let (first, last) = (b_start + margin, b_end.saturating_sub(w + margin));
    if last <= first {
        ev.reason = Some("overlap shorter than one refinement window".into());
        return ev;
    }
    let count = ((last - first) / w).clamp(1, MAX_WINDOWS);
    let starts: Vec<usize> = (0..count)
        .map(|k| first + (last - first) * k / count.max(2).saturating_sub(1).max(1))
        .collect();
    let windows: Vec<WindowLag> = window_lags(&a.full, &b.full, rate, coarse_lag, &starts)
        .into_iter()
        .filter(|wl| {
            wl.peak >= refine::MIN_WINDOW_PEAK
                && (wl.lag_s - ev.coarse_lag_s).abs() <= COARSE_AGREEMENT_S
        })
        .collect();
    ev.windows = windows.len();
    if windows.len() < MIN_WINDOWS {
        ev.reason = Some(format!(
            "only {} GCC-PHAT windows agree with the coarse lag (need {MIN_WINDOWS})",
            windows.len()
        ));
        return ev;
    }
    let mut peaks: Vec<f64> = windows.iter().map(|w| w.peak).collect();
    peaks.sort_by(f64::total_cmp);
    ev.gcc_peak = Some(peaks[peaks.len() / 2]);
    let Some(with_drift) = robust_line(&windows, true) else {
        ev.reason = Some("line fit failed".into());
        return ev;
    };
    let drift_ppm = with_drift.slope * 1e6;
    let significant = with_drift.slope.abs() > DRIFT_SIGMAS * with_drift.slope_std
        && drift_ppm.abs() > MIN_REPORTED_DRIFT_PPM;
    if significant && drift_ppm.abs() > MAX_DRIFT_PPM {
        ev.reason = Some(format!(
            "drift {drift_ppm:.0} ppm is beyond the clock tolerance ±{MAX_DRIFT_PPM} ppm"
        ));
        return ev;
    }
    let fit = if significant {
        with_drift
    } else {
        robust_line(&windows, false).unwrap_or(with_drift)
    };
    if fit.inliers < MIN_WINDOWS {
        ev.reason = Some(format!("only {} consistent windows", fit.inliers));
        return ev;
    }
    ev.status = "accepted".into();
    ev.lag_s = Some(fit.intercept);
    ev.drift_ppm = Some(fit.slope * 1e6);
    ev.class = Some(
        if significant {
            "offset-and-drift"
        } else {
            "offset-only"
        }
        .into(),
    );
    ev.residual_rms_s = Some(fit.rms);
    ev.points = windows;
    ev.fit = Some(fit);
    ev
}

/// Predicted lag `a_i − a_j` for a sound heard at local audio time `a_j` of camera `j`.
fn predicted_lag(
    a_j: f64,
    (o_i, r_i, d_i): (f64, f64, f64),
    (o_j, r_j, d_j): (f64, f64, f64),
) -> f64 {
    let session = (a_j - d_j) * (1.0 + r_j) + o_j;
    (session - o_i) / (1.0 + r_i) + d_i - a_j
}

/// Synchronise cameras from their audio. The first input is the reference.
pub fn synchronise(inputs: &[SyncInput]) -> SyncResult {
    let prepared: Vec<Prepared> = inputs.par_iter().map(|i| prepare(&i.audio)).collect();
    let pair_indices: Vec<(usize, usize)> = (0..inputs.len())
        .flat_map(|i| (i + 1..inputs.len()).map(move |j| (i, j)))
        .collect();
    let mut pairs: Vec<PairEvidence> = pair_indices
        .par_iter()
        .map(|&(i, j)| {
            analyse_pair(
                (&inputs[i].name, &inputs[j].name),
                (i, j),
                &prepared[i],
                &prepared[j],
            )
        })
        .collect();
    let delays: Vec<f64> = inputs.iter().map(|i| i.av_delay_s).collect();
    let closures = triangle_closures(&pairs, inputs);
    // Solve, then drop the most inconsistent pair while any is beyond tolerance.
    let solution = loop {
        let solution = solve_with_drift_test(&pairs, inputs.len(), &delays);
        for p in &mut pairs {
            p.solution_residual_s = None;
        }
        solution.fill_residuals(&mut pairs, &delays);
        let worst = pairs
            .iter()
            .enumerate()
            .filter(|(_, p)| p.status == "accepted")
            .filter_map(|(k, p)| p.solution_residual_s.map(|r| (k, r.abs())))
            .max_by(|x, y| x.1.total_cmp(&y.1));
        match worst {
            Some((k, r)) if r > PAIR_CONSISTENCY_S => {
                pairs[k].status = "dropped".into();
                pairs[k].reason = Some(format!(
                    "inconsistent with the other pairs by {:.1} ms (triangle closure)",
                    r * 1e3
                ));
            }
            _ => break solution,
        }
    };
    let cameras = inputs
        .iter()
        .enumerate()
        .map(|(k, input)| CameraClock {
            name: input.name.clone(),
            offset_s: (solution.status[k] != CameraStatus::Unmatched)
                .then_some(solution.params[k].0),
            drift_ppm: solution.params[k].1 * 1e6,
            offset_std_s: solution.offset_std[k],
            status: solution.status[k],
        })
        .collect();
    SyncResult {
        cameras,
        pairs,
        closures,
    }
}

struct Solution {
    /// (offset, drift) per camera.
    params: Vec<(f64, f64)>,
    offset_std: Vec<f64>,
    drift_std: Vec<f64>,
    status: Vec<CameraStatus>,
}

impl Solution {
    fn fill_residuals(&self, pairs: &mut [PairEvidence], delays: &[f64]) {
        for p in pairs.iter_mut().filter(|p| p.status == "accepted") {
            let (i, j) = p.indices;
            if self.status[i] == CameraStatus::Unmatched
                || self.status[j] == CameraStatus::Unmatched
            {
                continue;
            }
            let ci = (self.params[i].0, self.params[i].1, delays[i]);
            let cj = (self.params[j].0, self.params[j].1, delays[j]);
            let mean = p
                .points
                .iter()
                .map(|w| w.lag_s - predicted_lag(w.t_b, ci, cj))
                .sum::<f64>()
                / p.points.len().max(1) as f64;
            p.solution_residual_s = Some(mean);
        }
    }
}

/// Solve; then fix to zero the drift of every camera whose estimate is not significant, and
/// solve again, so `offset-and-drift` means a drift was established.
fn solve_with_drift_test(pairs: &[PairEvidence], n: usize, delays: &[f64]) -> Solution {
    let mut allowed = vec![false; n];
    for p in pairs
        .iter()
        .filter(|p| p.status == "accepted" && p.class.as_deref() == Some("offset-and-drift"))
    {
        allowed[p.indices.0] = true;
        allowed[p.indices.1] = true;
    }
    let first = solve(pairs, n, delays, &allowed);
    let mut changed = false;
    for k in 1..n {
        let drift = first.params[k].1;
        if allowed[k]
            && (drift.abs() * 1e6 <= MIN_REPORTED_DRIFT_PPM
                || drift.abs() <= DRIFT_SIGMAS * first.drift_std[k])
        {
            allowed[k] = false;
            changed = true;
        }
    }
    if changed {
        solve(pairs, n, delays, &allowed)
    } else {
        first
    }
}

/// Joint robust Gauss–Newton over every accepted pair's window lags; cameras not in
/// `drift_allowed` keep drift 0.
fn solve(pairs: &[PairEvidence], n: usize, delays: &[f64], drift_allowed: &[bool]) -> Solution {
    let accepted: Vec<&PairEvidence> = pairs.iter().filter(|p| p.status == "accepted").collect();
    // Connectivity and initial guesses by breadth-first composition from the reference.
    let mut params = vec![(0.0, 0.0); n];
    let mut status = vec![CameraStatus::Unmatched; n];
    if n == 0 {
        return Solution {
            params,
            offset_std: vec![],
            drift_std: vec![],
            status,
        };
    }
    status[0] = CameraStatus::Reference;
    let mut frontier = vec![0usize];
    while let Some(k) = frontier.pop() {
        for p in &accepted {
            let (i, j) = p.indices;
            let Some(fit) = &p.fit else { continue };
            // lag(a_j) ≈ intercept + slope a_j  ⇒  o_j ≈ o_i + intercept + d_j − d_i (small drift).
            let (from, to, sign) = if i == k {
                (i, j, 1.0)
            } else if j == k {
                (j, i, -1.0)
            } else {
                continue;
            };
            if status[to] != CameraStatus::Unmatched {
                continue;
            }
            let offset = params[from].0 + sign * (fit.intercept + delays[j] - delays[i]);
            let drift = params[from].1 + sign * fit.slope;
            params[to] = (offset, drift);
            status[to] = CameraStatus::OffsetOnly;
            frontier.push(to);
        }
    }
    let drift_free = drift_allowed;
    let mut index = vec![None; n];
    let mut unknowns = 0;
    for k in 1..n {
        if status[k] == CameraStatus::Unmatched {
            continue;
        }
        index[k] = Some((unknowns, drift_free[k].then_some(unknowns + 1)));
        unknowns += if drift_free[k] { 2 } else { 1 };
        if drift_free[k] {
            status[k] = CameraStatus::OffsetAndDrift;
        } else {
            params[k].1 = 0.0;
        }
    }
    let mut offset_std = vec![0.0; n];
    let mut drift_std = vec![0.0; n];
    if unknowns == 0 {
        return Solution {
            params,
            offset_std,
            drift_std,
            status,
        };
    }
    for _ in 0..10 {
        let mut h = nalgebra::DMatrix::<f64>::zeros(unknowns, unknowns);
        let mut g = nalgebra::DVector::<f64>::zeros(unknowns);
        for p in &accepted {
            let (i, j) = p.indices;
            if status[i] == CameraStatus::Unmatched || status[j] == CameraStatus::Unmatched {
                continue;
            }
            for wl in &p.points {
                let ci = (params[i].0, params[i].1, delays[i]);
                let cj = (params[j].0, params[j].1, delays[j]);
                let r = wl.lag_s - predicted_lag(wl.t_b, ci, cj);
                let weight = if r.abs() > 3e-4 { 3e-4 / r.abs() } else { 1.0 };
                // Analytic Jacobian of `predicted_lag` (at most four non-zero entries).
                let (o_i, r_i) = params[i];
                let (o_j, r_j) = params[j];
                let session = (wl.t_b - delays[j]) * (1.0 + r_j) + o_j;
                let inv = 1.0 / (1.0 + r_i);
                let mut jac: [(usize, f64); 4] = [(0, 0.0); 4];
                let mut m = 0;
                if let Some((oi, di)) = index[i] {
                    jac[m] = (oi, -inv);
                    m += 1;
                    if let Some(di) = di {
                        jac[m] = (di, -(session - o_i) * inv * inv);
                        m += 1;
                    }
                }
                if let Some((oj, dj)) = index[j] {
                    jac[m] = (oj, inv);
                    m += 1;
                    if let Some(dj) = dj {
                        jac[m] = (dj, (wl.t_b - delays[j]) * inv);
                        m += 1;
                    }
                }
                let jac = &jac[..m];
                for &(a, ja) in jac {
                    g[a] += weight * ja * r;
                    for &(b, jb) in jac {
                        h[(a, b)] += weight * ja * jb;
                    }
                }
            }
        }
        for d in 0..unknowns {
            h[(d, d)] += 1e-12;
        }
        let Some(chol) = h.clone().cholesky() else {
            break;
        };
        let step = chol.solve(&g);
        for k in 1..n {
            if let Some((oi, di)) = index[k] {
                params[k].0 += step[oi];
                if let Some(di) = di {
                    params[k].1 += step[di];
                }
            }
        }
        if step.amax() < 1e-9 {
            // Offset standard errors: σ² (JᵀJ)⁻¹ with σ the RMS window residual.
            let (mut sum, mut count) = (0.0, 0usize);
            for p in &accepted {
                let (i, j) = p.indices;
                for wl in &p.points {
                    let r = wl.lag_s
                        - predicted_lag(
                            wl.t_b,
                            (params[i].0, params[i].1, delays[i]),
                            (params[j].0, params[j].1, delays[j]),
                        );
                    sum += r * r;
                    count += 1;
                }
            }
            let sigma = (sum / count.max(1) as f64).sqrt();
            let inv = chol.inverse();
            for k in 1..n {
                if let Some((oi, di)) = index[k] {
                    offset_std[k] = inv[(oi, oi)].max(0.0).sqrt() * sigma;
                    if let Some(di) = di {
                        drift_std[k] = inv[(di, di)].max(0.0).sqrt() * sigma;
                    }
                }
            }
            break;
        }
    }
    Solution {
        params,
        offset_std,
        drift_std,
        status,
    }
}

/// Closure residuals of every triangle of accepted pairs, from the pairs' own line fits.
fn triangle_closures(pairs: &[PairEvidence], inputs: &[SyncInput]) -> Vec<Closure> {
    let fit = |i: usize, j: usize| {
        pairs
            .iter()
            .find(|p| p.indices == (i, j) && p.status == "accepted")
            .and_then(|p| p.fit.as_ref())
    };
    let lag_at = |f: &LineFit, t: f64| f.at(t);
    let n = inputs.len();
    let mut out = Vec::new();
    for i in 0..n {
        for j in i + 1..n {
            for k in j + 1..n {
                let (Some(ij), Some(jk), Some(ik)) = (fit(i, j), fit(j, k), fit(i, k)) else {
                    continue;
                };
                // A sound at k-time t: j hears it at t + lag_jk(t), i at that + lag_ij(·).
                let t = inputs[k].audio.duration_s() / 2.0;
                let a_j = t + lag_at(jk, t);
                let a_i = a_j + lag_at(ij, a_j);
                out.push(Closure {
                    cameras: [
                        inputs[i].name.clone(),
                        inputs[j].name.clone(),
                        inputs[k].name.clone(),
                    ],
                    residual_s: (a_i - t) - lag_at(ik, t),
                });
            }
        }
    }
    out
}

/// The A/V delay of `mode` in a calibration, or an error saying how to get it.
pub fn av_delay_for(
    calibration: &kiwi_core::artifact::UnitCalibration,
    mode: Option<&str>,
    path: &Path,
) -> Result<f64> {
    let found = match mode {
        Some(m) => calibration.av_delays.iter().find(|d| d.mode == m),
        None if calibration.av_delays.len() == 1 => calibration.av_delays.first(),
        None => None,
    };
    found.map(|d| d.delay_s).ok_or_else(|| BackendError::Input {
        path: path.to_path_buf(),
        message: format!(
            "no A/V delay for recording mode {}; the unit has delays for [{}]: certify it with `kiwi-calib av-delay`, or name the mode",
            mode.unwrap_or("(unspecified)"),
            calibration.av_delays.iter().map(|d| d.mode.as_str()).collect::<Vec<_>>().join(", ")
        ),
    })
}
