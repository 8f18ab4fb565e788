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

pub use kiwi_core::fit::LineFit;

/// Residual scale floor (s) for the robust fit: GCC-PHAT windows agree to a few µs.
const FIT_SCALE_FLOOR_S: f64 = 20e-6;

/// Fit `lag = intercept + slope · t_b` (or a constant, with `with_slope = false`) robustly
/// through window lags, with the workspace's one robust line fit.
pub fn robust_line(points: &[WindowLag], with_slope: bool) -> Option<LineFit> {
    let x: Vec<f64> = points.iter().map(|p| p.t_b).collect();
    let y: Vec<f64> = points.iter().map(|p| p.lag_s).collect();
    kiwi_core::fit::robust_line(&x, &y, with_slope, FIT_SCALE_FLOOR_S)
}
