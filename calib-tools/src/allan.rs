//! IMU noise from a long static log: overlapping Allan deviation per axis and a joint,
//! non-negative, confidence-weighted fit of its noise terms (`kiwi-calib imu-noise`).
//!
//! Model of the Allan variance of one axis (IEEE Std 952, NIST SP 1065), `τ` the averaging time:
//!
//! | term | Allan variance | coefficient (gyro / accel units) |
//! |---|---|---|
//! | quantization `Q` | `3Q²/τ²` | rad / (m/s) |
//! | white noise `N` | `N²/τ` | rad/s/√Hz / m/s²/√Hz (the continuous-time noise density) |
//! | bias instability `B` | `(2 ln 2/π)·B²` | rad/s / m/s² (the flicker floor is `0.664·B`) |
//! | random walk `K` | `K²τ/3` | rad/s²/√Hz / m/s³/√Hz (the bias random-walk density) |
//! | rate ramp `R` | `R²τ²/2` | rad/s² / m/s³ |
//!
//! The five squared coefficients enter linearly, so they are fitted together by weighted
//! least squares with non-negativity (a QP solved with clarabel). Each `τ` is weighted by the
//! inverse variance of its Allan-variance estimate, `2σ⁴/edf`, with the equivalent degrees of
//! freedom of NIST SP 1065 Table 5 for the noise type that dominates there; the weights are
//! recomputed from the model (not the data) a few times, which removes the downward bias of
//! slope-reading tools. Reading only the white-noise slope at `τ = 1 s` under-estimates `N`
//! wherever another term already contributes; the joint fit does not.
//!
//! Overlapping ADEV is computed exactly like allantools `oadev` (frequency data → mean removed
//! → cumulative sum × `τ₀`; `σ(mτ₀)² = Σ(x[i+2m] − 2x[i+m] + x[i])² / (2(N−2m)(mτ₀)²)`) in
//! O(N) per averaging time, parallel over axes and averaging times.

use std::io::Read;
use std::path::{Path, PathBuf};

use kiwi_core::imu::STANDARD_GRAVITY_M_S2 as STANDARD_GRAVITY;
use nalgebra::{DMatrix, DVector, Vector3};
use rayon::prelude::*;
use serde::Serialize;

use crate::error::{CalibError, Result};

/// Axis names in `imu.csv` column order.
pub const AXES: [&str; 6] = ["gx", "gy", "gz", "ax", "ay", "az"];
/// A static accelerometer must read |g| within this of standard gravity (m/s²): latitude and
/// altitude change g by < 0.05 m/s², scale errors of consumer IMUs by a few per cent.
const GRAVITY_TOLERANCE: f64 = 0.5;
/// A gap is a time step longer than this many nominal sample periods.
const GAP_FACTOR: f64 = 1.5;
/// Bytes read per block; blocks are parsed in parallel.
const BLOCK_BYTES: usize = 8 << 20;
/// Window (s) of the means used to detect motion.
const MOTION_WINDOW_S: f64 = 1.0;
/// Half-width (windows) of the rolling median the window means are compared with: long enough
/// to ignore a single excursion, short enough to follow the slow bias drift of a long log.
const MOTION_MEDIAN_HALF: usize = 30;
/// A window's gyro mean deviating more than this (rad/s, ≈ 1.1°/s) from its neighbourhood is
/// motion, unless the noise itself is that large (see [`MOTION_SIGMAS`]).
const MOTION_GYRO_RAD_S: f64 = 0.02;
/// Same for the accelerometer (m/s²): a tap or a nudge of the table.
const MOTION_ACCEL_M_S2: f64 = 0.1;
/// Deviations beyond this many robust standard deviations of the window means are motion.
const MOTION_SIGMAS: f64 = 10.0;
/// Shortest log (s) the white-noise term can be read from (averaging times up to 1/10 of it).
const MIN_LOG_S: f64 = 60.0;
/// A term whose relative standard deviation exceeds this is reported as poorly determined.
const POORLY_DETERMINED_REL: f64 = 0.25;
/// Scaled coefficients below this fraction of the largest are taken as at their bound (0)
/// when the QP solution is polished.
const ACTIVE_SET_EPS: f64 = 1e-6;
/// A fitted term within this many standard deviations of zero is reported as absent rather
/// than as poorly determined (no warning unless it is required).
const ABSENT_SIGMAS: f64 = 2.0;
/// Reweighting iterations of the fit (weights from the model, not from the noisy data).
const FIT_ITERATIONS: usize = 6;

/// Options of the Allan analysis.
#[derive(Debug, Clone)]
pub struct AllanOptions {
    /// Averaging times per decade.
    pub per_decade: usize,
    /// Longest averaging time as a fraction of the log's duration.
    pub max_tau_fraction: f64,
    /// Terms to fit.
    pub terms: Vec<Term>,
    /// Terms that must come out well determined (otherwise an error says how long a log is
    /// needed).
    pub require: Vec<Term>,
}

impl Default for AllanOptions {
    fn default() -> Self {
        Self {
            per_decade: 20,
            max_tau_fraction: 0.1,
            terms: Term::ALL.to_vec(),
            require: vec![Term::White, Term::RandomWalk],
        }
    }
}

/// One noise term of the Allan-variance model.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Term {
    /// Quantization noise `Q` (`3Q²/τ²`).
    Quantization,
    /// White noise `N` (`N²/τ`): the noise density.
    White,
    /// Bias instability `B` (`(2 ln2/π) B²`).
    BiasInstability,
    /// Bias random walk `K` (`K²τ/3`).
    RandomWalk,
    /// Rate ramp `R` (`R²τ²/2`).
    RateRamp,
}

impl Term {
    /// All five terms, in model order.
    pub const ALL: [Term; 5] = [
        Term::Quantization,
        Term::White,
        Term::BiasInstability,
        Term::RandomWalk,
        Term::RateRamp,
    ];

    /// The term's name on the command line and in files.
    pub fn name(self) -> &'static str {
        match self {
            Term::Quantization => "quantization",
            Term::White => "white",
            Term::BiasInstability => "bias-instability",
            Term::RandomWalk => "random-walk",
            Term::RateRamp => "rate-ramp",
        }
    }

    /// Parse a command-line name.
    pub fn parse(s: &str) -> Option<Term> {
        Term::ALL.into_iter().find(|t| t.name() == s.trim())
    }

    /// The term's Allan variance per unit squared coefficient at `tau`.
    fn basis(self, tau: f64) -> f64 {
        match self {
            Term::Quantization => 3.0 / (tau * tau),
            Term::White => 1.0 / tau,
            Term::BiasInstability => 2.0 * std::f64::consts::LN_2 / std::f64::consts::PI,
            Term::RandomWalk => tau / 3.0,
            Term::RateRamp => tau * tau / 2.0,
        }
    }

    /// Power-law exponent α of the frequency noise this term is (for the degrees of freedom).
    fn alpha(self) -> i32 {
        match self {
            Term::Quantization => 2,
            Term::White => 0,
            Term::BiasInstability => -1,
            Term::RandomWalk | Term::RateRamp => -2,
        }
    }

    fn index(self) -> usize {
        self as usize
    }
}

/// A static log loaded for the analysis: the six axes as evenly spaced samples.
#[derive(Debug, Clone)]
pub struct StaticLog {
    /// The file read.
    pub path: PathBuf,
    /// Sample rate (Hz) from the first and last timestamps.
    pub rate_hz: f64,
    /// First and last timestamps (s).
    pub time_range: (f64, f64),
    /// Median |accelerometer| (m/s²).
    pub gravity_m_s2: f64,
    /// Per axis, the samples (gyro rad/s, accel m/s²).
    pub axes: [Vec<f64>; 6],
}

impl StaticLog {
    /// Number of samples.
    pub fn len(&self) -> usize {
        self.axes[0].len()
    }

    /// True when the log has no samples.
    pub fn is_empty(&self) -> bool {
        self.axes[0].is_empty()
    }

    /// Duration (s).
    pub fn duration_s(&self) -> f64 {
        self.time_range.1 - self.time_range.0
    }

    /// A log from samples already in memory (e.g. from the simulator): `times` in s, `axes`
    /// per axis. Checks like [`read_static_log`] does.
    pub fn from_samples(path: &Path, times: &[f64], axes: [Vec<f64>; 6]) -> Result<Self> {
        let mut gaps = GapCheck::default();
        for (i, &t) in times.iter().enumerate() {
            gaps.push(path, t, i + 2)?;
        }
        finish_log(path, times.first().copied(), times.last().copied(), axes)
    }
}

/// Tracks timestamps: strictly increasing, no gaps, nominal period from the first samples.
#[derive(Debug, Default)]
struct GapCheck {
    previous: Option<f64>,
    first_dts: Vec<f64>,
    nominal_dt: Option<f64>,
}

/// Samples used to estimate the nominal period before gaps are checked.
const NOMINAL_DT_SAMPLES: usize = 1000;

impl GapCheck {
    fn push(&mut self, path: &Path, t: f64, line: usize) -> Result<()> {
        if let Some(prev) = self.previous {
            let dt = t - prev;
            if dt <= 0.0 {
                return Err(input(
                    path,
                    format!(
                        "line {line}: time {t} s does not increase (previous {prev} s); \
                         timestamps must be strictly increasing — sort the log or remove the \
                         repeated samples"
                    ),
                ));
            }
            match self.nominal_dt {
                Some(nominal) if dt > GAP_FACTOR * nominal => {
                    return Err(input(
                        path,
                        format!(
                            "line {line}: gap of {:.1} ms at t = {prev:.3} s (nominal period \
                             {:.3} ms); Allan deviation needs evenly spaced samples — use the \
                             part of the log before or after the gap, or record again",
                            dt * 1e3,
                            nominal * 1e3
                        ),
                    ));
                }
                Some(_) => {}
                None => {
                    self.first_dts.push(dt);
                    if self.first_dts.len() >= NOMINAL_DT_SAMPLES {
                        let mut d = std::mem::take(&mut self.first_dts);
                        d.sort_by(f64::total_cmp);
                        self.nominal_dt = Some(d[d.len() / 2]);
                    }
                }
            }
        }
        self.previous = Some(t);
        Ok(())
    }
}

fn input(path: &Path, message: String) -> CalibError {
    CalibError::Input {
        path: path.to_path_buf(),
        message,
    }
}

/// Read a static `imu.csv` log (kiwi-core format), streaming it in blocks parsed in parallel.
/// Memory is the samples themselves (48 bytes per sample); `progress` gets the bytes read.
pub fn read_static_log(
    path: &Path,
    progress: Option<&indicatif::ProgressBar>,
) -> Result<StaticLog> {
    let io = |e: std::io::Error| {
        CalibError::Core(kiwi_core::CoreError::Io {
            action: "reading",
            path: path.to_path_buf(),
            source: e,
        })
    };
    let mut file = std::fs::File::open(path).map_err(io)?;
    if let (Some(p), Ok(meta)) = (progress, file.metadata()) {
        p.set_length(meta.len());
    }
    let mut axes: [Vec<f64>; 6] = Default::default();
    let mut reserved = false;
    let mut carry: Vec<u8> = Vec::new();
    let mut block = vec![0u8; BLOCK_BYTES];
    let mut header_done = false;
    let mut line_number = 0usize;
    let mut gaps = GapCheck::default();
    let (mut t_first, mut t_last) = (None, None);
    loop {
        let n = file.read(&mut block).map_err(io)?;
        let eof = n == 0;
        carry.extend_from_slice(&block[..n]);
        if let Some(p) = progress {
            p.inc(n as u64);
        }
        // Parse everything up to the last newline (or everything at the end of the file).
        let end = if eof {
            carry.len()
        } else {
            match carry.iter().rposition(|&b| b == b'\n') {
                Some(i) => i + 1,
                None => continue,
            }
        };
        let mut text = std::str::from_utf8(&carry[..end])
            .map_err(|e| input(path, format!("not UTF-8 text ({e}); expected imu.csv")))?;
        if !header_done {
            let (first, rest) = text.split_once('\n').unwrap_or((text, ""));
            line_number += 1;
            let normalized: String = first.chars().filter(|c| !c.is_whitespace()).collect();
            if normalized != kiwi_core::imu::IMU_CSV_HEADER {
                return Err(input(
                    path,
                    format!(
                        "line 1: expected the header `{}` (s, rad/s, m/s²), found `{}`; convert \
                         the log to KIWI's imu.csv format (docs/conventions.md)",
                        kiwi_core::imu::IMU_CSV_HEADER,
                        first.trim()
                    ),
                ));
            }
            header_done = true;
            text = rest;
        }
        let parsed = parse_block(text);
        if !reserved {
            // Size the axes once from the first block's bytes per line (no regrowth copies).
            let lines: usize = parsed.iter().map(|c| c.lines).sum();
            if let (Ok(meta), true) = (file.metadata(), lines > 0) {
                let estimate = (meta.len() as f64 / (text.len() as f64 / lines as f64)) as usize;
                for a in &mut axes {
                    a.reserve(estimate + estimate / 50 + 16);
                }
            }
            reserved = true;
        }
        for chunk in parsed {
            let rows = chunk.rows.map_err(|(rel_line, message)| {
                input(path, format!("line {}: {message}", line_number + rel_line))
            })?;
            for (k, r) in rows.iter().enumerate() {
                gaps.push(path, r[0], line_number + k + 1)?;
                for a in 0..6 {
                    axes[a].push(r[a + 1]);
                }
            }
            if t_first.is_none() {
                t_first = rows.first().map(|r| r[0]);
            }
            if let Some(r) = rows.last() {
                t_last = Some(r[0]);
            }
            line_number += chunk.lines;
        }
        carry.drain(..end);
        if eof {
            break;
        }
    }
    finish_log(path, t_first, t_last, axes)
}

fn finish_log(
    path: &Path,
    t_first: Option<f64>,
    t_last: Option<f64>,
    axes: [Vec<f64>; 6],
) -> Result<StaticLog> {
    let n = axes[0].len();
    let (Some(t0), Some(t1)) = (t_first, t_last) else {
        return Err(input(path, "no samples; expected a static IMU log".into()));
    };
    if n < 3 || t1 <= t0 {
        return Err(input(
            path,
            format!("only {n} samples; record a static log of at least {MIN_LOG_S} s"),
        ));
    }
    let rate_hz = (n - 1) as f64 / (t1 - t0);
    let axis = |a: usize, i: usize| Vector3::new(axes[a][i], axes[a + 1][i], axes[a + 2][i]);
    kiwi_core::imu::check_imu_log(path, n, (t0, t1), |i| axis(0, i), |i| axis(3, i))?;
    let gravity = median_norm(&axes[3], &axes[4], &axes[5]);
    Ok(StaticLog {
        path: path.to_path_buf(),
        rate_hz,
        time_range: (t0, t1),
        gravity_m_s2: gravity,
        axes,
    })
}

fn median_norm(x: &[f64], y: &[f64], z: &[f64]) -> f64 {
    // A subsample is plenty for a median of a static signal.
    let step = (x.len() / 100_000).max(1);
    let mut norms: Vec<f64> = (0..x.len())
        .step_by(step)
        .map(|i| (x[i] * x[i] + y[i] * y[i] + z[i] * z[i]).sqrt())
        .collect();
    norms.sort_by(f64::total_cmp);
    norms.get(norms.len() / 2).copied().unwrap_or(f64::NAN)
}

struct ParsedChunk {
    rows: std::result::Result<Vec<[f64; 7]>, (usize, String)>,
    lines: usize,
}

/// Split `text` at line boundaries into pieces parsed in parallel, in order.
fn parse_block(text: &str) -> Vec<ParsedChunk> {
    let pieces = rayon::current_num_threads() * 4;
    let target = text.len() / pieces + 1;
    let mut bounds = vec![0usize];
    let bytes = text.as_bytes();
    let mut start = 0;
    while start < text.len() {
        let mut end = (start + target).min(text.len());
        while end < text.len() && bytes[end - 1] != b'\n' {
            end += 1;
        }
        bounds.push(end);
        start = end;
    }
    bounds
        .windows(2)
        .collect::<Vec<_>>()
        .into_par_iter()
        .map(|w| parse_lines(&text[w[0]..w[1]]))
        .collect()
}

fn parse_lines(text: &str) -> ParsedChunk {
    let mut rows = Vec::with_capacity(text.len() / 60);
    let mut lines = 0;
    for line in text.split_terminator('\n') {
        lines += 1;
        let line = line.strip_suffix('\r').unwrap_or(line);
        if line.is_empty() || line.bytes().all(|b| b.is_ascii_whitespace()) {
            continue;
        }
        let mut row = [0.0f64; 7];
        let mut count = 0;
        for field in line.split(',') {
            if count == 7 {
                count += 1;
                break;
            }
            // Fast path without trimming; fields with spaces take the second try.
            match field
                .parse::<f64>()
                .or_else(|_| field.trim().parse::<f64>())
            {
                Ok(v) if v.is_finite() => row[count] = v,
                _ => {
                    return ParsedChunk {
                        rows: Err((
                            lines,
                            format!(
                                "column {}: expected a finite number, found `{}`; repair or \
                                 remove the line",
                                AXES.get(count.wrapping_sub(1)).copied().unwrap_or("t"),
                                field.trim()
                            ),
                        )),
                        lines,
                    };
                }
            }
            count += 1;
        }
        if count != 7 {
            return ParsedChunk {
                rows: Err((
                    lines,
                    format!(
                        "expected 7 comma-separated values (t,gx,gy,gz,ax,ay,az), found {}",
                        if count > 7 {
                            "more".to_owned()
                        } else {
                            count.to_string()
                        }
                    ),
                )),
                lines,
            };
        }
        rows.push(row);
    }
    ParsedChunk {
        rows: Ok(rows),
        lines,
    }
}

/// Check that the log is usable: long enough, in SI units (gravity ≈ 9.81 m/s²) and static.
pub fn check_static(log: &StaticLog) -> Result<()> {
    let path = &log.path;
    if log.duration_s() < MIN_LOG_S {
        return Err(input(
            path,
            format!(
                "the log lasts {:.1} s; the white-noise term needs at least {MIN_LOG_S} s and the \
                 bias random walk typically one to several hours of static recording",
                log.duration_s()
            ),
        ));
    }
    let g = log.gravity_m_s2;
    if (g - STANDARD_GRAVITY).abs() > GRAVITY_TOLERANCE {
        let hint = kiwi_core::imu::gravity_unit_hint(g);
        return Err(input(
            path,
            format!("|accelerometer| of a static log should be ≈ 9.81 m/s², found {g:.3}; {hint}"),
        ));
    }
    let window = ((MOTION_WINDOW_S * log.rate_hz).round() as usize).max(1);
    let windows = log.len() / window;
    if windows < 3 {
        return Ok(());
    }
    for (a, name) in AXES.iter().enumerate() {
        let means: Vec<f64> = log.axes[a]
            .chunks_exact(window)
            .map(|c| c.iter().sum::<f64>() / c.len() as f64)
            .collect();
        let baseline = rolling_median(&means, MOTION_MEDIAN_HALF);
        let dev: Vec<f64> = means.iter().zip(&baseline).map(|(m, b)| m - b).collect();
        let mut abs: Vec<f64> = dev.iter().map(|d| d.abs()).collect();
        abs.sort_by(f64::total_cmp);
        let sigma = 1.4826 * abs[abs.len() / 2];
        let floor = if a < 3 {
            MOTION_GYRO_RAD_S
        } else {
            MOTION_ACCEL_M_S2
        };
        let limit = floor.max(MOTION_SIGMAS * sigma);
        if let Some((k, d)) = dev.iter().enumerate().find(|(_, d)| d.abs() > limit) {
            let t = log.time_range.0 + (k as f64 + 0.5) * window as f64 / log.rate_hz;
            let unit = if a < 3 { "rad/s" } else { "m/s²" };
            return Err(input(
                path,
                format!(
                    "the log is not static: the {name} mean over {MOTION_WINDOW_S} s moved by \
                     {d:.4} {unit} (limit {limit:.4}) around t = {t:.1} s; cut the log to its \
                     static part or record again without touching the IMU"
                ),
            ));
        }
    }
    Ok(())
}

fn rolling_median(values: &[f64], half: usize) -> Vec<f64> {
    let mut buf = Vec::with_capacity(2 * half + 1);
    (0..values.len())
        .map(|i| {
            buf.clear();
            let lo = i.saturating_sub(half);
            let hi = (i + half + 1).min(values.len());
            buf.extend_from_slice(&values[lo..hi]);
            let mid = buf.len() / 2;
            let (_, m, _) = buf.select_nth_unstable_by(mid, f64::total_cmp);
            *m
        })
        .collect()
}

/// Averaging factors `m` (τ = m/rate) at `per_decade` log-spaced averaging times from one
/// sample period to `max_fraction` of the `n` samples, rounded and without duplicates
/// (allantools' convention).
pub fn averaging_factors(n: usize, per_decade: usize, max_fraction: f64) -> Vec<usize> {
    let max_m = (n as f64 * max_fraction).floor().max(1.0);
    let steps = (max_m.log10() * per_decade as f64).floor() as usize;
    let mut m: Vec<usize> = (0..=steps)
        .map(|k| 10f64.powf(k as f64 / per_decade as f64).round() as usize)
        .filter(|&m| m >= 1 && (m as f64) <= max_m)
        .collect();
    m.dedup();
    m
}

/// Turn frequency data (rates) into phase data in place, exactly as allantools does:
/// mean removed, cumulative sum, times `1/rate`, with a leading zero (returned length `n + 1`).
pub fn frequency_to_phase(mut values: Vec<f64>, rate_hz: f64) -> Vec<f64> {
    let dt = 1.0 / rate_hz;
    let mean = pairwise_sum(&values) / values.len() as f64;
    values.push(0.0);
    // Shift right by one (the leading zero), subtracting the mean as we go.
    for i in (1..values.len()).rev() {
        values[i] = values[i - 1] - mean;
    }
    values[0] = 0.0;
    let mut sum = 0.0;
    for v in values.iter_mut().skip(1) {
        sum += *v;
        *v = sum * dt;
    }
    values
}

/// Pairwise (cascade) summation, like numpy's.
fn pairwise_sum(v: &[f64]) -> f64 {
    if v.len() <= 128 {
        let mut acc = [0.0f64; 8];
        let mut chunks = v.chunks_exact(8);
        for c in &mut chunks {
            for k in 0..8 {
                acc[k] += c[k];
            }
        }
        let mut s =
            ((acc[0] + acc[1]) + (acc[2] + acc[3])) + ((acc[4] + acc[5]) + (acc[6] + acc[7]));
        for x in chunks.remainder() {
            s += x;
        }
        s
    } else {
        let half = (v.len() / 2) & !7;
        pairwise_sum(&v[..half]) + pairwise_sum(&v[half..])
    }
}

/// Overlapping Allan deviation of phase data `x` (length N+1) at averaging factor `m`, with
/// the number of second differences summed.
pub fn oadev_at(x: &[f64], rate_hz: f64, m: usize) -> (f64, usize) {
    let n = x.len().saturating_sub(2 * m);
    if n == 0 {
        return (f64::NAN, 0);
    }
    let s = second_difference_energy(x, m, 0, n);
    (adev_from_energy(s, n, m, rate_hz), n)
}

/// One axis's Allan deviation curve.
#[derive(Debug, Clone, Serialize)]
pub struct AdevCurve {
    /// Averaging times (s).
    pub taus: Vec<f64>,
    /// Averaging factors (samples).
    pub m: Vec<usize>,
    /// Overlapping Allan deviation (axis units).
    pub adev: Vec<f64>,
    /// Number of second differences behind each value.
    pub n_terms: Vec<usize>,
}

/// Phase samples per block of the blocked ADEV sum: all averaging factors are summed block by
/// block, so the three windows `x[i]`, `x[i+m]`, `x[i+2m]` of neighbouring factors overlap in
/// cache instead of streaming the whole log from memory three times per factor.
const ADEV_BLOCK: usize = 16_384;

/// Overlapping ADEV of several axes' frequency data at the factors `m` (ascending), parallel
/// over axes and blocks of samples, with a fixed summation order (the result does not depend
/// on the thread count). Consumes the data (it becomes phase data in place).
pub fn oadev_axes(axes: Vec<Vec<f64>>, rate_hz: f64, m: &[usize]) -> Vec<AdevCurve> {
    let phases: Vec<Vec<f64>> = axes
        .into_par_iter()
        .map(|v| frequency_to_phase(v, rate_hz))
        .collect();
    let blocks: Vec<usize> = phases
        .iter()
        .map(|x| x.len().div_ceil(ADEV_BLOCK).max(1))
        .collect();
    let tasks: Vec<(usize, usize)> = (0..phases.len())
        .flat_map(|a| (0..blocks[a]).map(move |b| (a, b)))
        .collect();
    let partial: Vec<Vec<f64>> = tasks
        .par_iter()
        .map(|&(a, b)| {
            let x = &phases[a];
            m.iter()
                .map(|&mi| second_difference_energy(x, mi, b * ADEV_BLOCK, ADEV_BLOCK))
                .collect()
        })
        .collect();
    let mut offset = 0;
    (0..phases.len())
        .map(|a| {
            let x = &phases[a];
            let mut adev = Vec::with_capacity(m.len());
            let mut n_terms = Vec::with_capacity(m.len());
            for (k, &mi) in m.iter().enumerate() {
                let n = x.len().saturating_sub(2 * mi);
                let s: f64 = partial[offset..offset + blocks[a]]
                    .iter()
                    .map(|p| p[k])
                    .sum();
                n_terms.push(n);
                adev.push(if n == 0 {
                    f64::NAN
                } else {
                    adev_from_energy(s, n, mi, rate_hz)
                });
            }
            offset += blocks[a];
            AdevCurve {
                taus: m.iter().map(|&mi| mi as f64 / rate_hz).collect(),
                m: m.to_vec(),
                adev,
                n_terms,
            }
        })
        .collect()
}

/// Overlapping ADEV from the sum `s` of `n` squared second differences at factor `m`
/// (allantools' `sqrt(s / 2n) / m · rate`).
fn adev_from_energy(s: f64, n: usize, m: usize, rate_hz: f64) -> f64 {
    (s / (2.0 * n as f64)).sqrt() / m as f64 * rate_hz
}

/// `Σ (x[i+2m] − 2x[i+m] + x[i])²` over `i` in `[start, start + len)` ∩ `[0, N+1−2m)`.
fn second_difference_energy(x: &[f64], m: usize, start: usize, len: usize) -> f64 {
    let n = x.len().saturating_sub(2 * m);
    if start >= n {
        return 0.0;
    }
    let end = (start + len).min(n);
    let k = end - start;
    let (x0, x1, x2) = (
        &x[start..end],
        &x[start + m..start + m + k],
        &x[start + 2 * m..start + 2 * m + k],
    );
    // Eight independent accumulators over fixed-size chunks: no bounds checks, and the
    // compiler vectorizes the body.
    let mut acc = [0.0f64; 8];
    let (a8, a_rest) = x0.as_chunks::<8>();
    let (b8, b_rest) = x1.as_chunks::<8>();
    let (c8, c_rest) = x2.as_chunks::<8>();
    for ((a, b), c) in a8.iter().zip(b8).zip(c8) {
        for j in 0..8 {
            let v = (c[j] - 2.0 * b[j]) + a[j];
            acc[j] += v * v;
        }
    }
    let mut s = ((acc[0] + acc[1]) + (acc[2] + acc[3])) + ((acc[4] + acc[5]) + (acc[6] + acc[7]));
    for ((a, b), c) in a_rest.iter().zip(b_rest).zip(c_rest) {
        let v = (c - 2.0 * b) + a;
        s += v * v;
    }
    s
}

/// Equivalent degrees of freedom of an overlapping Allan variance (NIST SP 1065, Table 5) for
/// power-law noise `alpha`, `n_phase` phase points and averaging factor `m`.
pub fn edf(alpha: i32, n_phase: usize, m: usize) -> f64 {
    let n = n_phase as f64;
    let m = m as f64;
    let v = match alpha {
        2 => (n + 1.0) * (n - 2.0 * m) / (2.0 * (n - m)),
        1 => {
            let a = (n - 1.0) / (2.0 * m);
            let b = (2.0 * m + 1.0) * (n - 1.0) / 4.0;
            (a.ln() * b.ln()).max(0.0).sqrt().exp()
        }
        0 => {
            (3.0 * (n - 1.0) / (2.0 * m) - 2.0 * (n - 2.0) / n) * (4.0 * m * m)
                / (4.0 * m * m + 5.0)
        }
        -1 => {
            if m < 2.0 {
                2.0 * (n - 2.0) / (2.3 * n - 4.9)
            } else {
                5.0 * n * n / (4.0 * m * (n + 3.0 * m))
            }
        }
        _ => {
            (n - 2.0) / (m * (n - 3.0).powi(2))
                * ((n - 1.0).powi(2) - 3.0 * m * (n - 1.0) + 4.0 * m * m)
        }
    };
    // At least one degree of freedom: a single second difference still carries one.
    v.max(1.0)
}

/// A fitted term: its coefficient, standard deviation and whether the log determines it.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct TermEstimate {
    /// The coefficient (units in the module table); 0 when the fit puts it at its bound.
    pub value: f64,
    /// Its standard deviation.
    pub std: f64,
    /// False when `std / value` exceeds 25 % (or the term was not fitted).
    pub determined: bool,
}

/// The fitted noise model of one axis.
#[derive(Debug, Clone, Serialize)]
pub struct AxisFit {
    /// Quantization `Q`.
    pub quantization: TermEstimate,
    /// White noise density `N`.
    pub white_noise: TermEstimate,
    /// Bias instability `B` (flicker floor / 0.664).
    pub bias_instability: TermEstimate,
    /// Bias random walk `K`.
    pub random_walk: TermEstimate,
    /// Rate ramp `R`.
    pub rate_ramp: TermEstimate,
    /// RMS of the weighted residuals (≈ 1 for a good fit, in units of each point's std).
    pub weighted_rms: f64,
}

impl AxisFit {
    /// The estimate of a term.
    pub fn term(&self, t: Term) -> &TermEstimate {
        match t {
            Term::Quantization => &self.quantization,
            Term::White => &self.white_noise,
            Term::BiasInstability => &self.bias_instability,
            Term::RandomWalk => &self.random_walk,
            Term::RateRamp => &self.rate_ramp,
        }
    }

    /// The model's Allan deviation at `tau`.
    pub fn model_adev(&self, tau: f64) -> f64 {
        Term::ALL
            .iter()
            .map(|&t| self.term(t).value.powi(2) * t.basis(tau))
            .sum::<f64>()
            .sqrt()
    }

    /// One term's Allan deviation at `tau`.
    pub fn term_adev(&self, t: Term, tau: f64) -> f64 {
        (self.term(t).value.powi(2) * t.basis(tau)).sqrt()
    }
}

/// Fit the noise terms of one axis's curve jointly (weighted NNLS, model-based weights).
pub fn fit_axis(curve: &AdevCurve, n_phase: usize, options: &AllanOptions) -> Result<AxisFit> {
    let terms: Vec<Term> = Term::ALL
        .into_iter()
        .filter(|t| options.terms.contains(t))
        .collect();
    let points: Vec<usize> = (0..curve.taus.len())
        .filter(|&j| curve.adev[j].is_finite() && curve.adev[j] > 0.0)
        .collect();
    if terms.is_empty() || points.len() < terms.len() + 1 {
        return Err(CalibError::Input {
            path: PathBuf::new(),
            message: format!(
                "{} usable averaging times for {} terms; record a longer log",
                points.len(),
                terms.len()
            ),
        });
    }
    let data: Vec<f64> = points.iter().map(|&j| curve.adev[j].powi(2)).collect();
    let basis = DMatrix::from_fn(points.len(), terms.len(), |r, c| {
        terms[c].basis(curve.taus[points[r]])
    });
    let mut model = data.clone();
    let mut coef = DVector::zeros(terms.len());
    let mut weights = vec![0.0; points.len()];
    for _ in 0..FIT_ITERATIONS {
        for (r, &j) in points.iter().enumerate() {
            // Dominant term at this τ picks the noise type for the degrees of freedom.
            let alpha = if coef.iter().all(|c: &f64| *c <= 0.0) {
                0
            } else {
                let k = (0..terms.len())
                    .max_by(|&a, &b| {
                        (coef[a] * basis[(r, a)]).total_cmp(&(coef[b] * basis[(r, b)]))
                    })
                    .unwrap_or(0);
                terms[k].alpha()
            };
            let dof = edf(alpha, n_phase, curve.m[j]);
            // Var(σ²_est) = 2 σ⁴ / edf.
            weights[r] = (dof / 2.0).sqrt() / model[r].max(f64::MIN_POSITIVE);
        }
        coef = nnls_weighted(&basis, &data, &weights)?;
        let prediction = &basis * &coef;
        for r in 0..points.len() {
            // Keep the weights finite where the model would vanish.
            model[r] = prediction[r].max(data[r] * 1e-3);
        }
    }
    // Covariance of the squared coefficients from the weighted normal equations, inflated for
    // the correlation between neighbouring averaging times.
    let wb = DMatrix::from_fn(points.len(), terms.len(), |r, c| weights[r] * basis[(r, c)]);
    let scale = DVector::from_fn(terms.len(), |c, _| {
        let n = wb.column(c).norm();
        if n > 0.0 { 1.0 / n } else { 1.0 }
    });
    let scaled = DMatrix::from_fn(points.len(), terms.len(), |r, c| wb[(r, c)] * scale[c]);
    let normal = scaled.transpose() * &scaled;
    // Neighbouring overlapping Allan variances are strongly correlated, so the points are not
    // independent: the covariance is multiplied by the number of averaging times per decade,
    // counting one decade as one independent measurement. On simulated 4-h logs (3 seeds × 6
    // axes) the RMS error of K then matches its reported standard deviation (4.2 % vs 4.6 %).
    let inflation = (options.per_decade as f64).max(1.0);
    let cov_scaled = normal
        .clone()
        .try_inverse()
        .or_else(|| normal.pseudo_inverse(1e-12).ok())
        .unwrap_or_else(|| DMatrix::from_element(terms.len(), terms.len(), f64::INFINITY));
    let residual = scaled.clone() * (coef.component_div(&scale))
        - DVector::from_fn(points.len(), |r, _| weights[r] * data[r]);
    let weighted_rms = (residual.norm_squared() / points.len() as f64).sqrt();

    let mut out = [TermEstimate {
        value: 0.0,
        std: f64::INFINITY,
        determined: false,
    }; 5];
    for (c, &t) in terms.iter().enumerate() {
        let var_c2 = cov_scaled[(c, c)] * scale[c] * scale[c] * inflation;
        let c2 = coef[c].max(0.0);
        let value = c2.sqrt();
        // Delta method on the square root; at the bound, the one-sided spread √σ(c²).
        let std = if value > 0.0 {
            var_c2.sqrt() / (2.0 * value)
        } else {
            var_c2.sqrt().sqrt()
        };
        out[t.index()] = TermEstimate {
            value,
            std,
            determined: value > 0.0 && std / value <= POORLY_DETERMINED_REL,
        };
    }
    let [
        quantization,
        white_noise,
        bias_instability,
        random_walk,
        rate_ramp,
    ] = out;
    Ok(AxisFit {
        quantization,
        white_noise,
        bias_instability,
        random_walk,
        rate_ramp,
        weighted_rms,
    })
}

/// min Σ wᵣ²(Aᵣ·c − bᵣ)² subject to c ≥ 0, solved as a QP with clarabel (columns scaled to
/// unit norm so the solver sees a well-conditioned problem).
fn nnls_weighted(a: &DMatrix<f64>, b: &[f64], w: &[f64]) -> Result<DVector<f64>> {
    use clarabel::algebra::CscMatrix;
    use clarabel::solver::{
        DefaultSettingsBuilder, DefaultSolver, IPSolver, NonnegativeConeT, SolverStatus,
    };
    let (rows, cols) = a.shape();
    let m = DMatrix::from_fn(rows, cols, |r, c| w[r] * a[(r, c)]);
    let scale: Vec<f64> = (0..cols)
        .map(|c| {
            let n = m.column(c).norm();
            if n > 0.0 { 1.0 / n } else { 1.0 }
        })
        .collect();
    let ms = DMatrix::from_fn(rows, cols, |r, c| m[(r, c)] * scale[c]);
    let rhs = DVector::from_fn(rows, |r, _| w[r] * b[r]);
    let rhs_norm = rhs.norm().max(f64::MIN_POSITIVE);
    let rhs = rhs / rhs_norm;
    let p = ms.transpose() * &ms;
    let q = -(ms.transpose() * &rhs);
    // Upper triangle of P in CSC.
    let (mut ii, mut jj, mut vv) = (Vec::new(), Vec::new(), Vec::new());
    for j in 0..cols {
        for i in 0..=j {
            ii.push(i);
            jj.push(j);
            vv.push(p[(i, j)]);
        }
    }
    let p_csc = CscMatrix::new_from_triplets(cols, cols, ii, jj, vv);
    let a_csc = CscMatrix::new_from_triplets(
        cols,
        cols,
        (0..cols).collect(),
        (0..cols).collect(),
        vec![-1.0; cols],
    );
    let settings = DefaultSettingsBuilder::default()
        .verbose(false)
        .tol_gap_abs(1e-12)
        .tol_gap_rel(1e-12)
        .tol_feas(1e-12)
        .build()
        .map_err(|e| CalibError::Internal(format!("clarabel settings: {e:?}")))?;
    let cones = [NonnegativeConeT(cols)];
    let mut solver = DefaultSolver::new(
        &p_csc,
        q.as_slice(),
        &a_csc,
        &vec![0.0; cols],
        &cones,
        settings,
    )
    .map_err(|e| CalibError::Internal(format!("clarabel setup: {e:?}")))?;
    solver.solve();
    match solver.solution.status {
        SolverStatus::Solved | SolverStatus::AlmostSolved => {}
        s => {
            return Err(CalibError::Internal(format!(
                "Allan fit QP did not solve: {s:?}"
            )));
        }
    }
    // Polish: the interior-point solution is accurate to ~1e-7; re-solve the least squares
    // exactly on its free set (coefficients clearly above zero) and keep that if it stays
    // non-negative.
    let x: Vec<f64> = solver.solution.x.iter().map(|v| v.max(0.0)).collect();
    let largest = x.iter().copied().fold(0.0f64, f64::max);
    let free: Vec<usize> = (0..cols)
        .filter(|&c| x[c] > ACTIVE_SET_EPS * largest)
        .collect();
    let mut polished = vec![0.0; cols];
    let sub = DMatrix::from_fn(rows, free.len(), |r, k| ms[(r, free[k])]);
    let exact = (sub.transpose() * &sub)
        .cholesky()
        .map(|ch| ch.solve(&(sub.transpose() * &rhs)));
    let x = match exact {
        Some(sol) if sol.iter().all(|v| *v >= 0.0) => {
            for (k, &c) in free.iter().enumerate() {
                polished[c] = sol[k];
            }
            polished
        }
        _ => x,
    };
    Ok(DVector::from_fn(cols, |c, _| x[c] * scale[c] * rhs_norm))
}

/// Result of `imu-noise`: per-axis curves and fits, and the per-sensor densities.
#[derive(Debug, Clone, Serialize)]
pub struct NoiseReport {
    /// The log analysed.
    pub input: PathBuf,
    /// Sample rate (Hz).
    pub rate_hz: f64,
    /// Log duration (s).
    pub duration_s: f64,
    /// Samples per axis.
    pub samples: usize,
    /// Median |accelerometer| (m/s²).
    pub gravity_m_s2: f64,
    /// Per axis, in `gx, gy, gz, ax, ay, az` order.
    pub axes: Vec<AxisReport>,
    /// Gyroscope white noise density (rad/s/√Hz): the largest of the three axes.
    pub gyroscope_noise_density: f64,
    /// Gyroscope bias random walk (rad/s²/√Hz): the largest of the three axes.
    pub gyroscope_random_walk: f64,
    /// Accelerometer white noise density (m/s²/√Hz): the largest of the three axes.
    pub accelerometer_noise_density: f64,
    /// Accelerometer bias random walk (m/s³/√Hz): the largest of the three axes.
    pub accelerometer_random_walk: f64,
    /// Gyroscope bias instability (rad/s): the largest of the three axes.
    pub gyroscope_bias_instability: f64,
    /// Accelerometer bias instability (m/s²): the largest of the three axes.
    pub accelerometer_bias_instability: f64,
    /// Warnings (poorly determined terms and what would fix them).
    pub warnings: Vec<String>,
}

/// One axis: its curve, confidence band and fit.
#[derive(Debug, Clone, Serialize)]
pub struct AxisReport {
    /// Axis name.
    pub axis: String,
    /// The Allan deviation curve.
    pub curve: AdevCurve,
    /// 1-σ confidence interval of each ADEV value (chi-square, from the fitted noise type).
    pub adev_low: Vec<f64>,
    /// Upper end of the interval.
    pub adev_high: Vec<f64>,
    /// The fit.
    pub fit: AxisFit,
}

/// Analyse a loaded static log: checks, ADEV per axis, joint fits, per-sensor values.
pub fn analyse(log: StaticLog, options: &AllanOptions) -> Result<NoiseReport> {
    check_static(&log)?;
    let n = log.len();
    let m = averaging_factors(n, options.per_decade, options.max_tau_fraction);
    let (rate, path, duration, gravity) = (
        log.rate_hz,
        log.path.clone(),
        log.duration_s(),
        log.gravity_m_s2,
    );
    let curves = oadev_axes(log.axes.into_iter().collect(), rate, &m);
    let fits: Vec<AxisFit> = curves
        .par_iter()
        .map(|c| fit_axis(c, n + 1, options))
        .collect::<Result<_>>()
        .map_err(|e| match e {
            CalibError::Input { message, .. } => input(&path, message),
            other => other,
        })?;
    let mut warnings = Vec::new();
    let mut axes = Vec::new();
    for (a, (curve, fit)) in curves.into_iter().zip(fits).enumerate() {
        for &t in &options.terms {
            let e = fit.term(t);
            let required = options.require.contains(&t);
            // A term consistent with zero is simply absent from this IMU, unless required.
            let absent = e.value <= ABSENT_SIGMAS * e.std;
            if !e.determined && (required || !absent) {
                let need = needed_duration(&fit, t, duration, options.max_tau_fraction);
                let message = format!(
                    "{} {}: {} ± {} is poorly determined by this {:.0}-s log{}",
                    AXES[a],
                    t.name(),
                    sig(e.value),
                    sig(e.std),
                    duration,
                    need.map_or(String::new(), |s| format!(
                        "; a static log of at least {} would determine it",
                        human_duration(s)
                    ))
                );
                if required {
                    return Err(input(
                        &path,
                        format!("{message} (required term; record a longer log)"),
                    ));
                }
                warnings.push(message);
            }
        }
        let (low, high): (Vec<f64>, Vec<f64>) = curve
            .taus
            .iter()
            .enumerate()
            .map(|(j, &tau)| {
                let alpha = dominant(&fit, tau).alpha();
                let dof = edf(alpha, n + 1, curve.m[j]);
                // ±1σ of σ² is ±√(2/edf) relative; on σ, half of that.
                let rel = (2.0 / dof).sqrt();
                let v = curve.adev[j];
                (v * (1.0 - rel).max(0.05).sqrt(), v * (1.0 + rel).sqrt())
            })
            .unzip();
        axes.push(AxisReport {
            axis: AXES[a].to_owned(),
            curve,
            adev_low: low,
            adev_high: high,
            fit,
        });
    }
    let worst = |range: std::ops::Range<usize>, t: Term| {
        range
            .map(|a| axes[a].fit.term(t).value)
            .fold(0.0f64, f64::max)
    };
    Ok(NoiseReport {
        input: path,
        rate_hz: rate,
        duration_s: duration,
        samples: n,
        gravity_m_s2: gravity,
        gyroscope_noise_density: worst(0..3, Term::White),
        gyroscope_random_walk: worst(0..3, Term::RandomWalk),
        accelerometer_noise_density: worst(3..6, Term::White),
        accelerometer_random_walk: worst(3..6, Term::RandomWalk),
        gyroscope_bias_instability: worst(0..3, Term::BiasInstability),
        accelerometer_bias_instability: worst(3..6, Term::BiasInstability),
        axes,
        warnings,
    })
}

fn dominant(fit: &AxisFit, tau: f64) -> Term {
    Term::ALL
        .into_iter()
        .max_by(|&a, &b| fit.term_adev(a, tau).total_cmp(&fit.term_adev(b, tau)))
        .unwrap_or(Term::White)
}

/// How long a log would determine term `t`: its region must reach a decade beyond the
/// averaging time where it overtakes the neighbouring term (the longest τ is
/// `max_fraction` of the log).
fn needed_duration(fit: &AxisFit, t: Term, duration: f64, max_fraction: f64) -> Option<f64> {
    let n2 = fit.white_noise.value.powi(2);
    match t {
        Term::RandomWalk => {
            // Use an optimistic (upper) value of K so the figure is a lower bound.
            let k = fit.random_walk.value + fit.random_walk.std.min(1e300);
            (k > 0.0 && n2 > 0.0).then(|| {
                let crossover = 3.0 * n2 / (k * k);
                (10.0 * crossover / max_fraction).max(2.0 * duration)
            })
        }
        Term::White => Some((MIN_LOG_S * 10.0).max(2.0 * duration)),
        Term::Quantization | Term::BiasInstability | Term::RateRamp => None,
    }
}

fn human_duration(s: f64) -> String {
    if s >= 3600.0 {
        format!("{:.1} h", s / 3600.0)
    } else if s >= 60.0 {
        format!("{:.0} min", s / 60.0)
    } else {
        format!("{s:.0} s")
    }
}

/// Three significant digits.
fn sig(v: f64) -> String {
    if v == 0.0 || !v.is_finite() {
        format!("{v}")
    } else {
        format!("{v:.3e}")
    }
}

/// The per-sensor noise as the unit artifact stores it.
pub fn artifact_noise(
    report: &NoiseReport,
    axis_convention: &str,
) -> kiwi_core::artifact::ImuNoise {
    kiwi_core::artifact::ImuNoise {
        rate_hz: report.rate_hz,
        gyroscope_noise_density: report.gyroscope_noise_density,
        gyroscope_random_walk: report.gyroscope_random_walk,
        accelerometer_noise_density: report.accelerometer_noise_density,
        accelerometer_random_walk: report.accelerometer_random_walk,
        gyroscope_bias_instability: Some(report.gyroscope_bias_instability),
        accelerometer_bias_instability: Some(report.accelerometer_bias_instability),
        axis_convention: axis_convention.to_owned(),
    }
}

/// The `--json` summary of the contract (plus uncertainties).
pub fn summary_json(report: &NoiseReport) -> serde_json::Value {
    let mut axes = serde_json::Map::new();
    for a in &report.axes {
        let f = &a.fit;
        axes.insert(
            a.axis.clone(),
            serde_json::json!({
                "taus": a.curve.taus,
                "adev": a.curve.adev,
                "white_noise": f.white_noise.value,
                "white_noise_std": f.white_noise.std,
                "bias_instability": f.bias_instability.value,
                "bias_instability_std": f.bias_instability.std,
                "random_walk": f.random_walk.value,
                "random_walk_std": f.random_walk.std,
                "random_walk_determined": f.random_walk.determined,
                "quantization": f.quantization.value,
                "rate_ramp": f.rate_ramp.value,
                "weighted_rms": f.weighted_rms,
            }),
        );
    }
    serde_json::json!({
        "axes": axes,
        "gyroscope_noise_density": report.gyroscope_noise_density,
        "gyroscope_random_walk": report.gyroscope_random_walk,
        "accelerometer_noise_density": report.accelerometer_noise_density,
        "accelerometer_random_walk": report.accelerometer_random_walk,
        "gyroscope_bias_instability": report.gyroscope_bias_instability,
        "accelerometer_bias_instability": report.accelerometer_bias_instability,
        "rate_hz": report.rate_hz,
        "duration_s": report.duration_s,
        "warnings": report.warnings,
    })
}

/// Log-log plot of every axis's ADEV with its confidence band and the fitted terms: gyro axes
/// in one panel, accelerometer axes in another, stacked into one SVG.
pub fn plot(report: &NoiseReport, path: &Path) -> Result<()> {
    use kiwi_plot::{Axis, Band, Chart, Corner, Mark, PALETTE, Series};
    // x, y, z in red, green, blue; the noise terms in the palette's other colours.
    const AXIS_COLORS: [[u8; 3]; 3] = [PALETTE[3], PALETTE[2], PALETTE[0]];
    const TERM_COLORS: [[u8; 3]; 5] = [PALETTE[4], PALETTE[1], PALETTE[5], PALETTE[6], PALETTE[7]];
    let mut panels = Vec::new();
    for (sensor, range, unit) in [
        ("Gyroscope", 0..3, "ADEV (rad/s)"),
        ("Accelerometer", 3..6, "ADEV (m/s²)"),
    ] {
        let mut fig = Chart::new(
            1000,
            620,
            &format!(
                "{sensor} Allan deviation ({} h)",
                fmt1(report.duration_s / 3600.0)
            ),
            Axis::log("averaging time τ (s)"),
            Axis::log(unit),
        );
        fig.legend = Corner::BottomLeft;
        // The data's range (a decade below its floor): fitted terms leave it, the data does not.
        let (lo, hi) = range.clone().fold((f64::INFINITY, 0.0f64), |(lo, hi), a| {
            let ax = &report.axes[a];
            let lo = ax
                .adev_low
                .iter()
                .copied()
                .filter(|v| *v > 0.0)
                .fold(lo, f64::min);
            (lo, ax.adev_high.iter().copied().fold(hi, f64::max))
        });
        if lo.is_finite() && hi > lo {
            fig.y.range = Some((lo / 10.0, hi));
        }
        for (k, a) in range.clone().enumerate() {
            let ax = &report.axes[a];
            let color = AXIS_COLORS[k];
            fig.bands.push(Band {
                name: String::new(),
                color,
                points: ax
                    .curve
                    .taus
                    .iter()
                    .zip(ax.adev_low.iter().zip(&ax.adev_high))
                    .map(|(&t, (&l, &h))| (t, l, h))
                    .collect(),
            });
            fig.series.push(Series {
                name: format!(
                    "{} N={} K={}",
                    ax.axis,
                    sig(ax.fit.white_noise.value),
                    sig(ax.fit.random_walk.value)
                ),
                color,
                mark: Mark::Line(2),
                points: ax
                    .curve
                    .taus
                    .iter()
                    .copied()
                    .zip(ax.curve.adev.iter().copied())
                    .collect(),
            });
        }
        // Fitted terms of the first axis of the sensor, and the total model.
        let first = &report.axes[range.start];
        let taus = &first.curve.taus;
        for (i, t) in Term::ALL.into_iter().enumerate() {
            let e = first.fit.term(t);
            if e.value > ABSENT_SIGMAS * e.std {
                fig.series.push(Series {
                    name: format!("{} {}", first.axis, t.name()),
                    color: TERM_COLORS[i],
                    mark: Mark::Dashed(1),
                    points: taus
                        .iter()
                        .map(|&tau| (tau, first.fit.term_adev(t, tau)))
                        .collect(),
                });
            }
        }
        fig.series.push(Series {
            name: format!("{} model", first.axis),
            color: [0, 0, 0],
            mark: Mark::Dashed(2),
            points: taus
                .iter()
                .map(|&tau| (tau, first.fit.model_adev(tau)))
                .collect(),
        });
        panels.push(fig);
    }
    Chart::save_stack_svg(&panels, path)?;
    Ok(())
}

fn fmt1(v: f64) -> String {
    format!("{v:.1}")
}

/// A short Markdown report of the analysis.
pub fn markdown(report: &NoiseReport, plot_name: &str) -> String {
    use std::fmt::Write as _;
    let mut s = String::new();
    let _ = writeln!(s, "# IMU noise from Allan deviation\n");
    let _ = writeln!(
        s,
        "Input `{}`: {} samples at {:.3} Hz ({:.2} h), |g| = {:.4} m/s².\n",
        report.input.display(),
        report.samples,
        report.rate_hz,
        report.duration_s / 3600.0,
        report.gravity_m_s2
    );
    let _ = writeln!(s, "![Allan deviation]({plot_name})\n");
    let _ = writeln!(
        s,
        "| axis | white noise N | random walk K | bias instability B | quantization Q | rate ramp R | weighted RMS |"
    );
    let _ = writeln!(s, "|---|---|---|---|---|---|---|");
    for a in &report.axes {
        let f = &a.fit;
        let cell = |e: &TermEstimate| {
            format!(
                "{} ± {}{}",
                sig(e.value),
                sig(e.std),
                if e.determined {
                    ""
                } else {
                    " (poorly determined)"
                }
            )
        };
        let _ = writeln!(
            s,
            "| {} | {} | {} | {} | {} | {} | {:.2} |",
            a.axis,
            cell(&f.white_noise),
            cell(&f.random_walk),
            cell(&f.bias_instability),
            cell(&f.quantization),
            cell(&f.rate_ramp),
            f.weighted_rms
        );
    }
    let _ = writeln!(
        s,
        "\nUnits: gyro N rad/s/√Hz, K rad/s²/√Hz, B rad/s; accelerometer N m/s²/√Hz, K m/s³/√Hz, \
         B m/s². Bias instability B is defined by the flicker floor of the Allan deviation, \
         σ_floor = √(2 ln 2/π)·B ≈ 0.664·B. Per-sensor values are the largest of the three axes.\n"
    );
    let _ = writeln!(
        s,
        "Per sensor: gyroscope_noise_density {}, gyroscope_random_walk {}, \
         accelerometer_noise_density {}, accelerometer_random_walk {}.",
        sig(report.gyroscope_noise_density),
        sig(report.gyroscope_random_walk),
        sig(report.accelerometer_noise_density),
        sig(report.accelerometer_random_walk)
    );
    if !report.warnings.is_empty() {
        let _ = writeln!(s, "\n## Warnings\n");
        for w in &report.warnings {
            let _ = writeln!(s, "- {w}");
        }
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn averaging_factors_are_log_spaced_and_unique() {
        let m = averaging_factors(1_000_000, 20, 0.1);
        assert_eq!(m[0], 1);
        assert!(m.windows(2).all(|w| w[1] > w[0]));
        assert!(*m.last().unwrap() <= 100_000);
        assert!(*m.last().unwrap() > 80_000);
    }

    #[test]
    fn white_noise_adev_follows_one_over_root_tau() {
        use rand::SeedableRng;
        use rand_distr::{Distribution, Normal};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let normal = Normal::new(0.0, 1.0).unwrap();
        let rate = 100.0;
        let y: Vec<f64> = (0..200_000).map(|_| normal.sample(&mut rng)).collect();
        let x = frequency_to_phase(y, rate);
        for m in [1usize, 10, 100] {
            let (adev, _) = oadev_at(&x, rate, m);
            // σ_y = 1 per sample: σ(τ) = 1/√m.
            let expected = 1.0 / (m as f64).sqrt();
            assert!(
                (adev / expected - 1.0).abs() < 0.05,
                "m {m}: {adev} vs {expected}"
            );
        }
    }

    #[test]
    fn edf_white_fm_is_large_for_short_tau() {
        let e = edf(0, 1_000_001, 1);
        assert!(e > 1e5);
        assert!(edf(-2, 1_000_001, 100_000) < 20.0);
    }

    #[test]
    fn nnls_recovers_nonnegative_coefficients() {
        let taus: Vec<f64> = (0..40)
            .map(|k| 10f64.powf(f64::from(k) / 10.0 - 2.0))
            .collect();
        let a = DMatrix::from_fn(40, 3, |r, c| {
            [Term::White, Term::BiasInstability, Term::RandomWalk][c].basis(taus[r])
        });
        let truth = DVector::from_vec(vec![4e-6, 0.0, 1e-8]);
        let b: Vec<f64> = (&a * &truth).iter().copied().collect();
        let w: Vec<f64> = b.iter().map(|v| 1.0 / v).collect();
        let c = nnls_weighted(&a, &b, &w).unwrap();
        assert!((c[0] / 4e-6 - 1.0).abs() < 1e-6, "{c}");
        assert!(c[1].abs() < 1e-12, "{c}");
        assert!((c[2] / 1e-8 - 1.0).abs() < 1e-5, "{c}");
    }
}

/// Files written by [`write_outputs`].
#[derive(Debug, Clone, Serialize)]
pub struct WrittenNoise {
    /// Full result (`imu_noise.json`).
    pub result: PathBuf,
    /// Kalibr `imu.yaml`.
    pub kalibr_imu: PathBuf,
    /// The Allan plot (SVG).
    pub plot: PathBuf,
    /// Markdown report.
    pub report: PathBuf,
    /// The unit artifact with the new noise model, when a calibration was given.
    pub calibration: Option<PathBuf>,
}

/// Write the result folder: `imu_noise.json`, Kalibr `imu.yaml`, the plot (`plot`, default
/// `OUT/allan.svg`), `report.md`, and, given the unit's `calibration.json`, a copy of it in
/// `OUT/` with this noise model (the input is never modified).
pub fn write_outputs(
    report: &NoiseReport,
    out: &Path,
    plot_path: Option<&Path>,
    calibration: Option<(&Path, kiwi_core::artifact::UnitCalibration)>,
) -> Result<WrittenNoise> {
    std::fs::create_dir_all(out).map_err(|e| {
        CalibError::Core(kiwi_core::CoreError::Io {
            action: "creating",
            path: out.to_path_buf(),
            source: e,
        })
    })?;
    let axis_convention = calibration
        .as_ref()
        .and_then(|(_, c)| c.imu.as_ref().map(|i| i.axis_convention.clone()))
        .unwrap_or_else(|| "imu".to_owned());
    let noise = artifact_noise(report, &axis_convention);
    let result = out.join("imu_noise.json");
    let json = serde_json::to_string_pretty(report)
        .map_err(|e| CalibError::Internal(format!("serializing the result: {e}")))?;
    kiwi_core::io::write_atomic(&result, json.as_bytes())?;
    let kalibr_imu = out.join("imu.yaml");
    kiwi_core::io::write_atomic(&kalibr_imu, kiwi_core::kalibr::imu_yaml(&noise).as_bytes())?;
    let plot_file = plot_path.map_or_else(|| out.join("allan.svg"), Path::to_path_buf);
    plot(report, &plot_file)?;
    let report_path = out.join("report.md");
    let plot_name = pathdiff(&plot_file, out);
    kiwi_core::io::write_atomic(&report_path, markdown(report, &plot_name).as_bytes())?;
    let calibration_out = match calibration {
        Some((source, mut cal)) => {
            cal.imu = Some(noise);
            cal.provenance.tool = "kiwi-calib imu-noise".into();
            cal.provenance.tool_version = env!("CARGO_PKG_VERSION").into();
            cal.provenance.created_utc = kiwi_core::io::utc_now_rfc3339();
            cal.provenance
                .inputs
                .push(kiwi_core::artifact::InputRecord {
                    path: report.input.display().to_string(),
                    sha256: kiwi_core::io::sha256_file(&report.input)?,
                });
            let path = out.join("calibration.json");
            if path == source {
                return Err(input(
                    source,
                    "--out would overwrite the input calibration; choose another folder".into(),
                ));
            }
            cal.save(&path)?;
            Some(path)
        }
        None => None,
    };
    Ok(WrittenNoise {
        result,
        kalibr_imu,
        plot: plot_file,
        report: report_path,
        calibration: calibration_out,
    })
}

/// `path` relative to `base` when it lies inside it, else the full path.
fn pathdiff(path: &Path, base: &Path) -> String {
    path.strip_prefix(base)
        .unwrap_or(path)
        .display()
        .to_string()
}
