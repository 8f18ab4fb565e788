//! Sub-sample lag refinement by GCC-PHAT in windows across the overlap, and the robust line fit
//! that separates a constant offset from clock drift.

use rustfft::FftPlanner;
use rustfft::num_complex::Complex;

/// One refined window: B-time of its centre, lag `a_A − a_B` there, and the PHAT peak's strength.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct WindowLag {
    /// Centre of the window on B's clock (s).
    pub t_b: f64,
    /// Lag (s): a sound at `t_b` in B is at `t_b + lag` in A.
    pub lag_s: f64,
    /// PHAT peak over the RMS of the searched correlation.
    pub peak: f64,
}

/// Length of a GCC-PHAT window (s): long enough to hold several sound events.
pub const WINDOW_S: f64 = 1.0;
/// Search half-width around the coarse lag (s): the coarse lag's 16 ms resolution plus 60 ppm of
/// drift over 10 minutes.
pub const SEARCH_S: f64 = 0.06;
/// Windows whose PHAT peak is weaker than this many RMS of the correlation are ignored (silence,
/// or noise only).
pub const MIN_WINDOW_PEAK: f64 = 6.0;

/// GCC-PHAT lags in windows of B starting at each of `starts_b` (samples), searched around
/// `coarse_lag` (samples).
pub fn window_lags(
    a: &[f32],
    b: &[f32],
    rate: f64,
    coarse_lag: i64,
    starts_b: &[usize],
) -> Vec<WindowLag> {
    let w = (WINDOW_S * rate) as usize;
    let m = (SEARCH_S * rate) as usize;
    let n = (2 * w + 2 * m).next_power_of_two();
    let mut planner = FftPlanner::<f64>::new();
    let fft = planner.plan_fft_forward(n);
    let ifft = planner.plan_fft_inverse(n);
    let mut out = Vec::new();
    let mut xa = vec![Complex::new(0.0, 0.0); n];
    let mut xb = vec![Complex::new(0.0, 0.0); n];
    for &b0 in starts_b {
        let a0 = b0 as i64 + coarse_lag - m as i64;
        if a0 < 0 || a0 as usize + w + 2 * m > a.len() || b0 + w > b.len() {
            continue;
        }
        let a0 = a0 as usize;
        xa.iter_mut().for_each(|c| *c = Complex::new(0.0, 0.0));
        xb.iter_mut().for_each(|c| *c = Complex::new(0.0, 0.0));
        for i in 0..w + 2 * m {
            xa[i].re = f64::from(a[a0 + i]);
        }
        for i in 0..w {
            // Taper B so window edges do not ring.
            let taper = 0.5 - 0.5 * (std::f64::consts::TAU * (i as f64 + 0.5) / w as f64).cos();
            xb[i].re = f64::from(b[b0 + i]) * taper;
        }
        fft.process(&mut xa);
        fft.process(&mut xb);
        for (p, q) in xa.iter_mut().zip(&xb) {
            let r = *p * q.conj();
            let mag = r.norm();
            *p = if mag > 1e-20 {
                r / mag
            } else {
                Complex::new(0.0, 0.0)
            };
        }
        ifft.process(&mut xa);
        // xa[k] = Σ a[a0 + i + k] b[b0 + i]: lag of B inside A's window, k ∈ [0, 2m].
        let corr: Vec<f64> = xa[..=2 * m].iter().map(|c| c.re).collect();
        let (k, &peak) = corr
            .iter()
            .enumerate()
            .max_by(|x, y| x.1.total_cmp(y.1))
            .unwrap_or((0, &0.0));
        let rms = (corr.iter().map(|v| v * v).sum::<f64>() / corr.len() as f64).sqrt();
        if rms <= 0.0 || k == 0 || k == 2 * m {
            continue;
        }
        let (l, c, r) = (corr[k - 1], corr[k], corr[k + 1]);
        let denom = l - 2.0 * c + r;
        let frac = if denom.abs() > 1e-300 {
            0.5 * (l - r) / denom
        } else {
            0.0
        };
        let lag_samples = a0 as f64 + k as f64 + frac.clamp(-0.5, 0.5) - b0 as f64;
        out.push(WindowLag {
            t_b: (b0 as f64 + w as f64 / 2.0) / rate,
            lag_s: lag_samples / rate,
            peak: peak / rms,
        });
    }
    out
}

/// A robust straight-line fit `lag = intercept + slope · t_b`.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct LineFit {
    /// Lag at `t_b = 0` (s).
    pub intercept: f64,
    /// d lag / d t_b (dimensionless; 1e-6 = 1 ppm).
    pub slope: f64,
    /// Standard error of the slope.
    pub slope_std: f64,
    /// Standard error of the lag at the middle of the data (s).
    pub mid_std: f64,
    /// Windows that count as inliers.
    pub inliers: usize,
    /// RMS of inlier residuals (s).
    pub rms: f64,
}

/// Residual scale floor (s) for the robust fit: GCC-PHAT windows agree to a few µs.
const FIT_SCALE_FLOOR_S: f64 = 20e-6;
/// Huber threshold in robust standard deviations.
const HUBER_K: f64 = 2.5;

/// Fit a line (or, with `with_slope = false`, a constant) by iteratively reweighted least
/// squares with Huber weights; windows beyond 5 robust sigmas are dropped.
pub fn robust_line(points: &[WindowLag], with_slope: bool) -> Option<LineFit> {
    if points.len() < 2 {
        return None;
    }
    let t_mid = points.iter().map(|p| p.t_b).sum::<f64>() / points.len() as f64;
    let mut weights = vec![1.0; points.len()];
    let (mut a, mut b) = (median(points.iter().map(|p| p.lag_s).collect()), 0.0);
    let mut scale = FIT_SCALE_FLOOR_S;
    for _ in 0..20 {
        // Weighted LS on (t − t_mid).
        let (mut sw, mut st, mut sy, mut stt, mut sty) = (0.0, 0.0, 0.0, 0.0, 0.0);
        for (p, w) in points.iter().zip(&weights) {
            let t = p.t_b - t_mid;
            sw += w;
            st += w * t;
            sy += w * p.lag_s;
            stt += w * t * t;
            sty += w * t * p.lag_s;
        }
        if sw <= 0.0 {
            return None;
        }
        let det = sw * stt - st * st;
        if with_slope && det > 1e-12 {
            b = (sw * sty - st * sy) / det;
            a = (sy - b * st) / sw;
        } else {
            b = 0.0;
            a = sy / sw;
        }
        let residuals: Vec<f64> = points
            .iter()
            .map(|p| p.lag_s - a - b * (p.t_b - t_mid))
            .collect();
        scale =
            (1.4826 * median(residuals.iter().map(|r| r.abs()).collect())).max(FIT_SCALE_FLOOR_S);
        for (w, r) in weights.iter_mut().zip(&residuals) {
            let z = r.abs() / scale;
            *w = if z > 5.0 {
                0.0
            } else if z > HUBER_K {
                HUBER_K / z
            } else {
                1.0
            };
        }
    }
    let inliers: Vec<(f64, f64)> = points
        .iter()
        .zip(&weights)
        .filter(|(_, w)| **w > 0.0)
        .map(|(p, _)| (p.t_b - t_mid, p.lag_s - a - b * (p.t_b - t_mid)))
        .collect();
    let n = inliers.len();
    if n < 2 {
        return None;
    }
    let dof = (n as f64 - if with_slope { 2.0 } else { 1.0 }).max(1.0);
    let rss: f64 = inliers.iter().map(|(_, r)| r * r).sum();
    let sigma = (rss / dof).sqrt().max(1e-7);
    let stt: f64 = inliers.iter().map(|(t, _)| t * t).sum();
    Some(LineFit {
        intercept: a - b * t_mid,
        slope: b,
        slope_std: if with_slope && stt > 0.0 {
            sigma / stt.sqrt()
        } else {
            0.0
        },
        mid_std: sigma / (n as f64).sqrt(),
        inliers: n,
        rms: (rss / n as f64).sqrt().max(scale.min(0.0)),
    })
}

fn median(mut v: Vec<f64>) -> f64 {
    if v.is_empty() {
        return 0.0;
    }
    let mid = v.len() / 2;
    v.select_nth_unstable_by(mid, f64::total_cmp);
    v[mid]
}
