//! One robust straight-line fit for the whole workspace: `y = intercept + slope · x` by
//! iteratively reweighted least squares with Huber weights, points beyond 5 robust sigmas
//! dropped, and standard errors from the inlier residuals.

/// Huber threshold in robust standard deviations.
const HUBER_K: f64 = 2.5;
/// Residuals beyond this many robust sigmas get zero weight (gross outliers).
const REJECT_K: f64 = 5.0;
/// IRLS iterations; the weights settle in a handful.
const ITERATIONS: usize = 25;

/// A fitted line and its uncertainty.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct LineFit {
    /// `y` at `x = 0`.
    pub intercept: f64,
    /// `dy/dx` (0 for a constant fit).
    pub slope: f64,
    /// Standard error of the intercept.
    pub intercept_std: f64,
    /// Standard error of the slope.
    pub slope_std: f64,
    /// Mean `x` of the inliers (where the fit is best determined).
    pub x_mid: f64,
    /// Standard error of the fitted `y` at `x_mid`.
    pub mid_std: f64,
    /// Number of inliers.
    pub inliers: usize,
    /// RMS of inlier residuals.
    pub rms: f64,
    /// Per point: whether it is an inlier.
    #[serde(skip)]
    pub inlier_mask: Vec<bool>,
}

impl LineFit {
    /// The fitted `y` at `x`.
    pub fn at(&self, x: f64) -> f64 {
        self.intercept + self.slope * x
    }
}

/// Fit a line (or a constant, with `with_slope = false`) robustly. `scale_floor` is the smallest
/// residual scale believed (the measurement resolution), which keeps perfect data from
/// rejecting everything. `None` with fewer than two (three with a slope) usable points.
pub fn robust_line(x: &[f64], y: &[f64], with_slope: bool, scale_floor: f64) -> Option<LineFit> {
    let n = x.len().min(y.len());
    if n < if with_slope { 3 } else { 2 } {
        return None;
    }
    let x_ref = x[..n].iter().sum::<f64>() / n as f64;
    let mut weights = vec![1.0; n];
    let (mut a, mut b) = (median(y[..n].to_vec()), 0.0);
    for _ in 0..ITERATIONS {
        let (mut sw, mut sx, mut sy, mut sxx, mut sxy) = (0.0, 0.0, 0.0, 0.0, 0.0);
        for i in 0..n {
            let (t, w) = (x[i] - x_ref, weights[i]);
            sw += w;
            sx += w * t;
            sy += w * y[i];
            sxx += w * t * t;
            sxy += w * t * y[i];
        }
        if sw <= 0.0 {
            return None;
        }
        let det = sw * sxx - sx * sx;
        if with_slope && det > 1e-300 {
            b = (sw * sxy - sx * sy) / det;
            a = (sy - b * sx) / sw;
        } else {
            b = 0.0;
            a = sy / sw;
        }
        let residuals: Vec<f64> = (0..n).map(|i| y[i] - a - b * (x[i] - x_ref)).collect();
        let scale = (1.4826 * median(residuals.iter().map(|r| r.abs()).collect())).max(scale_floor);
        for (w, r) in weights.iter_mut().zip(&residuals) {
            let z = r.abs() / scale;
            *w = if z > REJECT_K {
                0.0
            } else if z > HUBER_K {
                HUBER_K / z
            } else {
                1.0
            };
        }
    }
    let inlier_mask: Vec<bool> = weights.iter().map(|w| *w > 0.0).collect();
    let pts: Vec<(f64, f64)> = (0..n)
        .filter(|i| inlier_mask[*i])
        .map(|i| (x[i], y[i]))
        .collect();
    let m = pts.len();
    if m < if with_slope { 3 } else { 2 } {
        return None;
    }
    let x_mid = pts.iter().map(|p| p.0).sum::<f64>() / m as f64;
    let residuals: Vec<f64> = pts
        .iter()
        .map(|(xi, yi)| yi - a - b * (xi - x_ref))
        .collect();
    let rss: f64 = residuals.iter().map(|r| r * r).sum();
    let dof = (m as f64 - if with_slope { 2.0 } else { 1.0 }).max(1.0);
    let sigma = (rss / dof).sqrt();
    let sxx: f64 = pts.iter().map(|(xi, _)| (xi - x_mid).powi(2)).sum();
    let slope_std = if with_slope && sxx > 0.0 {
        sigma / sxx.sqrt()
    } else {
        0.0
    };
    let mid_std = sigma / (m as f64).sqrt();
    Some(LineFit {
        intercept: a - b * x_ref,
        slope: b,
        intercept_std: (mid_std * mid_std + (slope_std * x_mid).powi(2)).sqrt(),
        slope_std,
        x_mid,
        mid_std,
        inliers: m,
        rms: (rss / m as f64).sqrt(),
        inlier_mask,
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn recovers_a_line_through_outliers() {
        let x: Vec<f64> = (0..100).map(f64::from).collect();
        let mut y: Vec<f64> = x
            .iter()
            .map(|v| 2.0 + 0.5 * v + 0.01 * (v * 1.7).sin())
            .collect();
        for k in [5, 17, 60, 61, 90] {
            y[k] += 40.0;
        }
        let f = robust_line(&x, &y, true, 1e-6).unwrap();
        assert!(
            (f.intercept - 2.0).abs() < 0.01 && (f.slope - 0.5).abs() < 1e-3,
            "{f:?}"
        );
        assert_eq!(f.inliers, 95);
        assert!(f.slope_std > 0.0 && f.slope_std < 1e-3);
        let c = robust_line(&x, &vec![3.0; 100], false, 1e-6).unwrap();
        assert!((c.intercept - 3.0).abs() < 1e-12 && c.slope == 0.0);
        assert!(robust_line(&[1.0], &[1.0], false, 1e-6).is_none());
    }
}
