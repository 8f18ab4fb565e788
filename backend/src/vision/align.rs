//! Similarity alignment of trajectories (Umeyama 1991) and absolute trajectory error.
//!
//! Monocular maps have an arbitrary scale and frame; to compare them with the simulator's
//! truth (or to place one map in another) we fit `target ≈ s R source + t` in least squares and
//! report the residual position errors.

use nalgebra::{Matrix3, Point3, UnitQuaternion, Vector3};

/// A similarity transform `x ↦ s R x + t` (`b_from_a` with a scale).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sim3 {
    /// Scale factor (> 0).
    pub scale: f64,
    /// Rotation.
    pub rotation: UnitQuaternion<f64>,
    /// Translation.
    pub translation: Vector3<f64>,
}

impl Sim3 {
    /// The identity.
    pub fn identity() -> Self {
        Self {
            scale: 1.0,
            rotation: UnitQuaternion::identity(),
            translation: Vector3::zeros(),
        }
    }

    /// Apply to a point.
    pub fn transform_point(&self, p: &Vector3<f64>) -> Vector3<f64> {
        self.rotation * p * self.scale + self.translation
    }

    /// The inverse similarity (`a_from_b` of a `b_from_a`).
    pub fn inverse(&self) -> Self {
        let r = self.rotation.inverse();
        Self {
            scale: 1.0 / self.scale,
            rotation: r,
            translation: -(r * self.translation) / self.scale,
        }
    }
}

/// Fewest point pairs of a similarity fit (three non-collinear points fix it).
const MIN_ALIGNMENT_POINTS: usize = 3;

/// Least-squares similarity `target ≈ s R source + t` (Umeyama). `None` with fewer than three
/// pairs, mismatched lengths, non-finite input or a degenerate (collinear/coincident) source.
/// With `with_scale = false` the scale is fixed to 1 (an SE(3) fit).
pub fn umeyama(source: &[Vector3<f64>], target: &[Vector3<f64>], with_scale: bool) -> Option<Sim3> {
    let n = source.len();
    if n < MIN_ALIGNMENT_POINTS || n != target.len() {
        return None;
    }
    if source
        .iter()
        .chain(target)
        .any(|p| !p.iter().all(|v| v.is_finite()))
    {
        return None;
    }
    let inv_n = 1.0 / n as f64;
    let mu_a = source.iter().sum::<Vector3<f64>>() * inv_n;
    let mu_b = target.iter().sum::<Vector3<f64>>() * inv_n;
    let mut cov = Matrix3::<f64>::zeros();
    let mut var_a = 0.0;
    for (a, b) in source.iter().zip(target) {
        let (da, db) = (a - mu_a, b - mu_b);
        cov += db * da.transpose();
        var_a += da.norm_squared();
    }
    cov *= inv_n;
    var_a *= inv_n;
    if var_a < 1e-24 {
        return None;
    }
    let svd = cov.svd(true, true);
    let (u, vt) = (svd.u?, svd.v_t?);
    let d = svd.singular_values;
    // Collinear sources leave the rotation about their line undetermined.
    if d[1] <= 1e-12 * d[0].max(1e-300) {
        return None;
    }
    let sign = if (u.determinant() * vt.determinant()) < 0.0 {
        -1.0
    } else {
        1.0
    };
    let s_mat = Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, sign));
    let r = u * s_mat * vt;
    let scale = if with_scale {
        (d[0] + d[1] + sign * d[2]) / var_a
    } else {
        1.0
    };
    let rotation = UnitQuaternion::from_matrix(&r);
    let translation = mu_b - rotation * mu_a * scale;
    Some(Sim3 {
        scale,
        rotation,
        translation,
    })
}

/// Absolute trajectory error of an aligned trajectory.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct TrajectoryError {
    /// Root mean square position error (target units).
    pub rmse: f64,
    /// Median position error.
    pub median: f64,
    /// Largest position error.
    pub max: f64,
    /// Diagonal of the target positions' bounding box: the trajectory extent.
    pub extent: f64,
    /// Number of positions compared.
    pub count: usize,
}

impl TrajectoryError {
    /// RMSE as a fraction of the trajectory extent.
    pub fn relative_rmse(&self) -> f64 {
        if self.extent > 0.0 {
            self.rmse / self.extent
        } else {
            f64::INFINITY
        }
    }
}

/// Position errors of `source` mapped by `sim` against `target`.
pub fn trajectory_error(
    sim: &Sim3,
    source: &[Vector3<f64>],
    target: &[Vector3<f64>],
) -> Option<TrajectoryError> {
    if source.is_empty() || source.len() != target.len() {
        return None;
    }
    let mut errors: Vec<f64> = source
        .iter()
        .zip(target)
        .map(|(a, b)| (sim.transform_point(a) - b).norm())
        .collect();
    let rmse = (errors.iter().map(|e| e * e).sum::<f64>() / errors.len() as f64).sqrt();
    errors.sort_by(f64::total_cmp);
    let median = errors[errors.len() / 2];
    let max = errors[errors.len() - 1];
    let mut lo = Point3::from(target[0]);
    let mut hi = lo;
    for p in target {
        lo = lo.inf(&Point3::from(*p));
        hi = hi.sup(&Point3::from(*p));
    }
    Some(TrajectoryError {
        rmse,
        median,
        max,
        extent: (hi - lo).norm(),
        count: errors.len(),
    })
}

/// Fit a similarity from `source` to `target` and return it with the resulting error.
pub fn align_and_measure(
    source: &[Vector3<f64>],
    target: &[Vector3<f64>],
) -> Option<(Sim3, TrajectoryError)> {
    let sim = umeyama(source, target, true)?;
    let err = trajectory_error(&sim, source, target)?;
    Some((sim, err))
}
