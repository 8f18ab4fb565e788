//! Multi-view geometry on unit bearing vectors: residuals, two-view relative pose (essential
//! matrix with RANSAC), absolute pose (P3P with RANSAC and robust refinement) and triangulation.
//!
//! Nothing here divides by `z`: every quantity is an angle between unit directions, so rays
//! beyond 90° off the optical axis (the X5 lenses see ~190°) count like any other.
//!
//! Conventions: a bearing is a unit `Vector3` in its camera frame (x right, y down, z forward);
//! `cam_from_world` maps world points into the camera; `cam2_from_cam1` maps camera-1
//! coordinates into camera 2. RANSAC draws its samples from a ChaCha8 generator seeded by the
//! caller and runs sequentially, so results are bit-identical across runs and thread counts.

use nalgebra::{
    Matrix2x3, Matrix3, Matrix3x6, Matrix6, Point3, SMatrix, SymmetricEigen, Translation3,
    UnitQuaternion, Vector2, Vector3, Vector6,
};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use kiwi_core::geometry::{Pose, hat, se3_exp};

/// Vectors shorter than this are treated as zero (degenerate geometry).
const TINY: f64 = 1e-12;
/// Sampling attempts per RANSAC iteration before a degenerate sample is accepted as a failure.
const SAMPLE_ATTEMPTS: usize = 16;
/// Local-optimization rounds after each new best RANSAC model (re-fit on all inliers).
const LOCAL_OPTIMIZATION_ROUNDS: usize = 3;
/// Gauss–Newton iterations of the robust absolute-pose refinement; it converges in < 10.
const ABSOLUTE_REFINE_ITERATIONS: usize = 15;
/// Step norm (rad or scene units) at which an iterative refinement has converged.
const REFINE_STEP_TOLERANCE: f64 = 1e-12;

// ---------------------------------------------------------------------------------------------
// Residuals on the unit sphere
// ---------------------------------------------------------------------------------------------

/// A rotation whose third column is the unit `z` and whose first two are
/// [`tangent_basis`]'s: `source_from_view` of a virtual camera aimed along `z` (its roll is
/// arbitrary but fixed).
pub fn aimed_at(z: &Vector3<f64>) -> nalgebra::Rotation3<f64> {
    let t = tangent_basis(z);
    nalgebra::Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[
        t.row(0).transpose(),
        t.row(1).transpose(),
        *z,
    ]))
}

/// An orthonormal basis `[e1 e2]` of the tangent plane of the unit sphere at `bearing`.
pub fn tangent_basis(bearing: &Vector3<f64>) -> Matrix2x3<f64> {
    // Cross with the axis least aligned with the bearing: well conditioned for any direction.
    let a = bearing.abs();
    let helper = if a.x <= a.y && a.x <= a.z {
        Vector3::x()
    } else if a.y <= a.z {
        Vector3::y()
    } else {
        Vector3::z()
    };
    let e1 = helper.cross(bearing).normalize();
    let e2 = bearing.cross(&e1);
    Matrix2x3::from_rows(&[e1.transpose(), e2.transpose()])
}

/// Angle (rad) between a measured bearing and the direction to a point in the same frame;
/// π for a zero point.
pub fn angular_error(bearing: &Vector3<f64>, point: &Vector3<f64>) -> f64 {
    let n = point.norm();
    if n < TINY {
        return std::f64::consts::PI;
    }
    // atan2 of |cross| and dot is accurate at small and large angles alike.
    bearing.cross(point).norm().atan2(bearing.dot(point))
}

/// A threshold on [`angular_error`] that rejects most points far beyond it without the
/// arc tangent (RANSAC scores every correspondence of every hypothesis, and in relocalization
/// most are outliers): exactly the same decisions and values as comparing `angular_error`.
#[derive(Debug, Clone, Copy)]
struct AngleThreshold {
    /// The threshold (rad).
    rad: f64,
    /// `tan(rad)` widened by [`ANGLE_PRECHECK_MARGIN`], or infinity when `rad` is not below
    /// 90° (no pre-check).
    tan: f64,
}

/// Relative widening of the pre-check's tangent: far above the arc tangent's rounding (~1e-16),
/// so a point the pre-check rejects is beyond the threshold whatever the rounding.
const ANGLE_PRECHECK_MARGIN: f64 = 1e-9;

impl AngleThreshold {
    fn new(rad: f64) -> Self {
        let tan = if rad > 0.0 && rad < std::f64::consts::FRAC_PI_2 {
            rad.tan() * (1.0 + ANGLE_PRECHECK_MARGIN)
        } else {
            f64::INFINITY
        };
        Self { rad, tan }
    }

    /// `Some(angular_error(bearing, point))` when it is within the threshold, else `None`.
    #[inline]
    fn error_within(&self, bearing: &Vector3<f64>, point: &Vector3<f64>) -> Option<f64> {
        if self.tan.is_finite() {
            let d = bearing.dot(point);
            // At or beyond 90°, or (for a point not at the origin) clearly beyond the tangent.
            if d <= 0.0 || bearing.cross(point).norm() > d * self.tan {
                return None;
            }
        }
        let e = angular_error(bearing, point);
        (e <= self.rad).then_some(e)
    }
}

/// RMS of [`angular_error`] between `bearings` and `points` (their frame) seen from
/// `cam_from_world` (rad); 0 for no points.
pub fn rms_angular_error(
    cam_from_world: &Pose,
    bearings: &[Vector3<f64>],
    points: &[Vector3<f64>],
) -> f64 {
    let sum: f64 = bearings
        .iter()
        .zip(points)
        .map(|(b, x)| angular_error(b, &(cam_from_world * Point3::from(*x)).coords).powi(2))
        .sum();
    (sum / bearings.len().max(1) as f64).sqrt()
}

/// Jacobian of a camera-frame point `pc = T x` with respect to a left update of its pose,
/// `T ← exp(δ) T` with `δ = [ω; v]`: `[−[pc]×, I]`.
pub fn point_jacobian_left_update(pc: &Vector3<f64>) -> Matrix3x6<f64> {
    let mut dp = Matrix3x6::<f64>::zeros();
    dp.fixed_view_mut::<3, 3>(0, 0).copy_from(&(-hat(pc)));
    dp.fixed_view_mut::<3, 3>(0, 3)
        .copy_from(&Matrix3::identity());
    dp
}

/// Tangent-plane residual of a point `point` (camera frame) against the measured unit
/// `bearing`, with its 2×3 Jacobian with respect to `point`.
///
/// `r = 2 Bᵀ n / (1 + bᵀ n)` with `n = point/|point|` and `B` the tangent basis at `b`: its norm
/// is `2 tan(α/2)` for an angular error `α`, so it equals the angle to first order and grows
/// monotonically up to 180° (a point behind the ray never looks like a good fit).
/// `None` for a point at the origin or exactly opposite the bearing.
pub fn tangent_residual(
    bearing: &Vector3<f64>,
    basis: &Matrix2x3<f64>,
    point: &Vector3<f64>,
) -> Option<(Vector2<f64>, Matrix2x3<f64>)> {
    let norm = point.norm();
    if norm < TINY {
        return None;
    }
    let n = point / norm;
    let denom = 1.0 + bearing.dot(&n);
    if denom < TINY {
        return None;
    }
    let bn = basis * n;
    let r = bn * (2.0 / denom);
    // dr/dn = 2 B/denom − 2 (B n) bᵀ/denom²; dn/dp = (I − n nᵀ)/|p|.
    let dr_dn = basis * (2.0 / denom) - (bn * bearing.transpose()) * (2.0 / (denom * denom));
    let dn_dp = (Matrix3::identity() - n * n.transpose()) / norm;
    Some((r, dr_dn * dn_dp))
}

// ---------------------------------------------------------------------------------------------
// RANSAC options and sampling
// ---------------------------------------------------------------------------------------------

/// Options of the RANSAC estimators.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RansacOptions {
    /// Inlier threshold: largest angular error (rad) of an inlier.
    pub threshold_rad: f64,
    /// Desired probability of drawing at least one all-inlier sample (adaptive stopping).
    pub confidence: f64,
    /// Hard cap on iterations.
    pub max_iterations: usize,
    /// Fewest inliers of an acceptable model.
    pub min_inliers: usize,
    /// Seed of the sampling generator (ChaCha8).
    pub seed: u64,
    /// When non-zero and the data are larger than twice this: a model is scored on all data
    /// only if at least [`PREVERIFY_MIN_INLIERS`] of this many evenly spread data are its
    /// inliers (a cheap test that lets RANSAC draw the many samples a low inlier share needs).
    pub preverify: usize,
}

/// Inliers a model needs among the `preverify` test data to be scored on all of them.
pub const PREVERIFY_MIN_INLIERS: usize = 2;

impl Default for RansacOptions {
    fn default() -> Self {
        Self {
            // ~1 px at the centre of a 960 px X5 lens (≈ 290 px/rad).
            threshold_rad: 0.004,
            confidence: 0.9999,
            max_iterations: 2000,
            min_inliers: 12,
            seed: 0x4B49_5749,
            preverify: 0,
        }
    }
}

/// Iterations needed so that an all-inlier sample of `k` points is drawn with probability
/// `confidence` when a fraction `inlier_ratio` of the data are inliers.
fn adaptive_iterations(confidence: f64, inlier_ratio: f64, k: usize, cap: usize) -> usize {
    let p_good = inlier_ratio.clamp(0.0, 1.0).powi(k as i32);
    if p_good >= 1.0 - 1e-15 {
        return 1;
    }
    if p_good <= 1e-15 {
        return cap;
    }
    let n = (1.0 - confidence).ln() / (1.0 - p_good).ln();
    if n.is_finite() && n >= 0.0 {
        (n.ceil() as usize).clamp(1, cap)
    } else {
        cap
    }
}

/// Draw `k` distinct indices below `n` into `out`.
fn sample_distinct(rng: &mut ChaCha8Rng, n: usize, k: usize, out: &mut Vec<usize>) {
    out.clear();
    while out.len() < k {
        let i = rng.random_range(0..n);
        if !out.contains(&i) {
            out.push(i);
        }
    }
}

/// MSAC score (lower is better) and inlier count of a set of errors.
fn msac(errors: impl Iterator<Item = f64>, threshold: f64) -> (f64, usize) {
    let t2 = threshold * threshold;
    let mut cost = 0.0;
    let mut count = 0;
    for e in errors {
        let e2 = e * e;
        if e2 <= t2 {
            cost += e2;
            count += 1;
        } else {
            cost += t2;
        }
    }
    (cost, count)
}

// ---------------------------------------------------------------------------------------------
// Two-view geometry
// ---------------------------------------------------------------------------------------------

/// Essential matrix `E = [t]ₓ R` of `cam2_from_cam1 = (R, t)`: `b2ᵀ E b1 = 0` for matching
/// bearings.
pub fn essential_from_pose(cam2_from_cam1: &Pose) -> Matrix3<f64> {
    hat(&cam2_from_cam1.translation.vector) * cam2_from_cam1.rotation.to_rotation_matrix().matrix()
}

/// Sine of the angle between each bearing and the epipolar plane of its partner; the larger of
/// the two (symmetric epipolar error, rad to first order).
pub fn epipolar_error(e: &Matrix3<f64>, b1: &Vector3<f64>, b2: &Vector3<f64>) -> f64 {
    let n2 = e * b1;
    let n1 = e.transpose() * b2;
    let d = b2.dot(&n2).abs();
    let l2 = n2.norm();
    let l1 = n1.norm();
    if l1 < TINY || l2 < TINY {
        return std::f64::consts::FRAC_PI_2;
    }
    (d / l2).max(d / l1)
}

/// Least-squares essential matrix from ≥ 8 bearing pairs (the 8-point algorithm on unit
/// bearings, with the two equal singular values enforced). `None` if degenerate.
pub fn essential_8point(b1: &[Vector3<f64>], b2: &[Vector3<f64>]) -> Option<Matrix3<f64>> {
    if b1.len() < 8 || b1.len() != b2.len() {
        return None;
    }
    let mut ata = SMatrix::<f64, 9, 9>::zeros();
    for (f1, f2) in b1.iter().zip(b2) {
        let mut row = SMatrix::<f64, 9, 1>::zeros();
        for i in 0..3 {
            for j in 0..3 {
                row[3 * i + j] = f2[i] * f1[j];
            }
        }
        ata += row * row.transpose();
    }
    let eig = SymmetricEigen::new(ata);
    let (imin, _) =
        eig.eigenvalues
            .iter()
            .enumerate()
            .fold(
                (0, f64::INFINITY),
                |(bi, bv), (i, &v)| {
                    if v < bv { (i, v) } else { (bi, bv) }
                },
            );
    let v = eig.eigenvectors.column(imin);
    let e = Matrix3::from_fn(|i, j| v[3 * i + j]);
    let svd = e.svd(true, true);
    let (u, vt) = (svd.u?, svd.v_t?);
    let s = (svd.singular_values[0] + svd.singular_values[1]) * 0.5;
    if s < TINY {
        return None;
    }
    let d = Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, 0.0));
    Some(u * d * vt)
}

/// The four `(R, t)` factorizations of an essential matrix (`t` unit length).
pub fn decompose_essential(e: &Matrix3<f64>) -> Option<[Pose; 4]> {
    let svd = e.svd(true, true);
    let (mut u, mut vt) = (svd.u?, svd.v_t?);
    if u.determinant() < 0.0 {
        u = -u;
    }
    if vt.determinant() < 0.0 {
        vt = -vt;
    }
    let w = Matrix3::new(0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0);
    let r1 = UnitQuaternion::from_matrix(&(u * w * vt));
    let r2 = UnitQuaternion::from_matrix(&(u * w.transpose() * vt));
    let t: Vector3<f64> = u.column(2).into();
    let pose = |r: UnitQuaternion<f64>, t: Vector3<f64>| Pose::from_parts(Translation3::from(t), r);
    Some([pose(r1, t), pose(r1, -t), pose(r2, t), pose(r2, -t)])
}

/// Depths `(λ1, λ2)` along two rays `c1 + λ1 d1` and `c2 + λ2 d2` at their closest approach;
/// `None` for (nearly) parallel rays.
pub fn closest_approach(
    c1: &Vector3<f64>,
    d1: &Vector3<f64>,
    c2: &Vector3<f64>,
    d2: &Vector3<f64>,
) -> Option<(f64, f64)> {
    let w = c1 - c2;
    let (a, b, c) = (d1.dot(d1), d1.dot(d2), d2.dot(d2));
    let (d, e) = (d1.dot(&w), d2.dot(&w));
    let den = a * c - b * b;
    if den <= 1e-14 * a * c {
        return None;
    }
    Some(((b * e - c * d) / den, (a * e - b * d) / den))
}

/// Whether a bearing pair triangulates in front of both cameras (along both rays) for a
/// candidate `cam2_from_cam1`.
fn in_front(cam2_from_cam1: &Pose, b1: &Vector3<f64>, b2: &Vector3<f64>) -> bool {
    // In camera-1 coordinates: camera 2's centre and its ray direction.
    let cam1_from_cam2 = cam2_from_cam1.inverse();
    let c2 = cam1_from_cam2.translation.vector;
    let d2 = cam1_from_cam2.rotation * b2;
    match closest_approach(&Vector3::zeros(), b1, &c2, &d2) {
        Some((l1, l2)) => l1 > 0.0 && l2 > 0.0,
        None => false,
    }
}

/// A two-view relative pose estimated from bearing correspondences.
#[derive(Debug, Clone, PartialEq)]
pub struct RelativePose {
    /// Camera-1 coordinates to camera-2 coordinates; the translation has unit length (scale is
    /// not observable from two views).
    pub cam2_from_cam1: Pose,
    /// Per correspondence: inlier of the epipolar model and triangulated in front of both.
    pub inliers: Vec<bool>,
    /// Number of inliers.
    pub num_inliers: usize,
    /// RANSAC iterations run.
    pub iterations: usize,
}

/// Robust relative pose from bearing pairs: 8-point RANSAC (MSAC scoring, adaptive stopping,
/// local re-fit on all inliers), then the factorization of `E` that puts most inliers in
/// front of both cameras. `None` when no model reaches `options.min_inliers`.
pub fn relative_pose_ransac(
    b1: &[Vector3<f64>],
    b2: &[Vector3<f64>],
    options: &RansacOptions,
) -> Option<RelativePose> {
    const K: usize = 8;
    let n = b1.len();
    if n < K.max(options.min_inliers) || n != b2.len() {
        return None;
    }
    let mut rng = ChaCha8Rng::seed_from_u64(options.seed);
    let mut sample = Vec::with_capacity(K);
    let (mut s1, mut s2) = (Vec::with_capacity(n), Vec::with_capacity(n));
    let mut best: Option<(Matrix3<f64>, f64, usize)> = None;
    let mut needed = options.max_iterations;
    let mut it = 0;
    let score = |e: &Matrix3<f64>| {
        msac(
            b1.iter().zip(b2).map(|(x, y)| epipolar_error(e, x, y)),
            options.threshold_rad,
        )
    };
    while it < needed {
        it += 1;
        let mut model = None;
        for _ in 0..SAMPLE_ATTEMPTS {
            sample_distinct(&mut rng, n, K, &mut sample);
            s1.clear();
            s2.clear();
            s1.extend(sample.iter().map(|&i| b1[i]));
            s2.extend(sample.iter().map(|&i| b2[i]));
            model = essential_8point(&s1, &s2);
            if model.is_some() {
                break;
            }
        }
        let Some(mut e) = model else { continue };
        let (mut cost, mut count) = score(&e);
        if best.as_ref().is_some_and(|b| cost >= b.1) {
            continue;
        }
        // Local optimization: re-fit on all inliers while it improves.
        for _ in 0..LOCAL_OPTIMIZATION_ROUNDS {
            s1.clear();
            s2.clear();
            for (x, y) in b1.iter().zip(b2) {
                if epipolar_error(&e, x, y) <= options.threshold_rad {
                    s1.push(*x);
                    s2.push(*y);
                }
            }
            let Some(e2) = essential_8point(&s1, &s2) else {
                break;
            };
            let (c2, n2) = score(&e2);
            if c2 < cost {
                (e, cost, count) = (e2, c2, n2);
            } else {
                break;
            }
        }
        best = Some((e, cost, count));
        needed = adaptive_iterations(options.confidence, count as f64 / n as f64, K, needed);
    }
    let (e, _, _) = best?;
    // Pick the factorization with the most inliers in front of both cameras.
    let candidates = decompose_essential(&e)?;
    let mut chosen: Option<(Pose, Vec<bool>, usize)> = None;
    for pose in candidates {
        let flags: Vec<bool> = b1
            .iter()
            .zip(b2)
            .map(|(x, y)| {
                epipolar_error(&e, x, y) <= options.threshold_rad && in_front(&pose, x, y)
            })
            .collect();
        let count = flags.iter().filter(|&&f| f).count();
        if chosen.as_ref().is_none_or(|c| count > c.2) {
            chosen = Some((pose, flags, count));
        }
    }
    let (pose, inliers, num_inliers) = chosen?;
    (num_inliers >= options.min_inliers).then_some(RelativePose {
        cam2_from_cam1: pose,
        inliers,
        num_inliers,
        iterations: it,
    })
}

// ---------------------------------------------------------------------------------------------
// Absolute pose
// ---------------------------------------------------------------------------------------------

/// Real roots of `a x³ + b x² + c x + d` (a ≠ 0 after scaling; lower degrees handled).
fn cubic_roots(a: f64, b: f64, c: f64, d: f64) -> Vec<f64> {
    let scale = a.abs().max(b.abs()).max(c.abs()).max(d.abs());
    if scale < TINY {
        return Vec::new();
    }
    if a.abs() < 1e-12 * scale {
        return quadratic_roots(b, c, d);
    }
    let (b, c, d) = (b / a, c / a, d / a);
    // Depressed cubic t³ + p t + q with x = t − b/3.
    let p = c - b * b / 3.0;
    let q = 2.0 * b * b * b / 27.0 - b * c / 3.0 + d;
    let shift = -b / 3.0;
    let disc = q * q / 4.0 + p * p * p / 27.0;
    let mut roots = if disc > 0.0 {
        let s = disc.sqrt();
        vec![(-q / 2.0 + s).cbrt() + (-q / 2.0 - s).cbrt() + shift]
    } else if p.abs() < TINY {
        vec![shift]
    } else {
        let r = (-p / 3.0).sqrt();
        let phi = (3.0 * q / (2.0 * p * r)).clamp(-1.0, 1.0).acos() / 3.0;
        (0..3)
            .map(|k| {
                2.0 * r * (phi - 2.0 * std::f64::consts::PI * f64::from(k) / 3.0).cos() + shift
            })
            .collect()
    };
    // Two Newton steps polish each root.
    for x in &mut roots {
        for _ in 0..2 {
            let f = ((*x + b) * *x + c) * *x + d;
            let df = (3.0 * *x + 2.0 * b) * *x + c;
            if df.abs() > TINY {
                *x -= f / df;
            }
        }
    }
    roots
}

/// Real roots of `a x² + b x + c`.
fn quadratic_roots(a: f64, b: f64, c: f64) -> Vec<f64> {
    let scale = a.abs().max(b.abs()).max(c.abs());
    if scale < TINY {
        return Vec::new();
    }
    if a.abs() < 1e-12 * scale {
        return if b.abs() > TINY {
            vec![-c / b]
        } else {
            Vec::new()
        };
    }
    let disc = b * b - 4.0 * a * c;
    if disc < 0.0 {
        return Vec::new();
    }
    // Numerically stable form.
    let q = -0.5 * (b + b.signum() * disc.sqrt());
    if q.abs() < TINY {
        return vec![-b / (2.0 * a)];
    }
    vec![q / a, c / q]
}

/// The rigid transform mapping three points `src` onto `dst` exactly (up to their shape
/// mismatch), from the orthonormal frames of the two triangles.
fn rigid_from_triangles(src: &[Vector3<f64>; 3], dst: &[Vector3<f64>; 3]) -> Option<Pose> {
    let frame = |p: &[Vector3<f64>; 3]| -> Option<Matrix3<f64>> {
        let e1 = (p[1] - p[0]).try_normalize(TINY)?;
        let e3 = e1.cross(&(p[2] - p[0])).try_normalize(TINY)?;
        let e2 = e3.cross(&e1);
        Some(Matrix3::from_columns(&[e1, e2, e3]))
    };
    let r = frame(dst)? * frame(src)?.transpose();
    // `r` is orthonormal by construction: Shepperd's method reads it off directly, where
    // `UnitQuaternion::from_matrix` iterates from the identity (slowly near a half turn, and
    // not at all from one).
    let rotation =
        UnitQuaternion::from_rotation_matrix(&nalgebra::Rotation3::from_matrix_unchecked(r));
    let t = dst[0] - rotation * src[0];
    Some(Pose::from_parts(Translation3::from(t), rotation))
}

/// All `cam_from_world` poses (up to four) that see the three world `points` along the three
/// unit `bearings`. Works for any bearing directions, including beyond 90° off-axis.
///
/// Method (after Persson & Nordberg's Lambda Twist): the depths `λ` satisfy three quadrics
/// `λᵀ Mᵢⱼ λ = |xᵢ − xⱼ|²`; two homogeneous combinations `D1, D2` vanish on `λ`, a root `γ` of
/// `det(D1 + γ D2) = 0` makes the combination a degenerate (two-plane) quadric, each plane
/// leaves a quadratic in one ratio, and the scale follows from one distance.
pub fn p3p(bearings: &[Vector3<f64>; 3], points: &[Vector3<f64>; 3]) -> Vec<Pose> {
    let y = bearings;
    let x = points;
    let a12 = (x[0] - x[1]).norm_squared();
    let a13 = (x[0] - x[2]).norm_squared();
    let a23 = (x[1] - x[2]).norm_squared();
    if a12 < TINY || a13 < TINY || a23 < TINY {
        return Vec::new();
    }
    let (c12, c13, c23) = (y[0].dot(&y[1]), y[0].dot(&y[2]), y[1].dot(&y[2]));
    let m12 = Matrix3::new(1.0, -c12, 0.0, -c12, 1.0, 0.0, 0.0, 0.0, 0.0);
    let m13 = Matrix3::new(1.0, 0.0, -c13, 0.0, 0.0, 0.0, -c13, 0.0, 1.0);
    let m23 = Matrix3::new(0.0, 0.0, 0.0, 0.0, 1.0, -c23, 0.0, -c23, 1.0);
    let d1 = m12 * a23 - m23 * a12;
    let d2 = m13 * a23 - m23 * a13;
    // det(D1 + γ D2) = k3 γ³ + k2 γ² + k1 γ + k0, coefficients from four evaluations.
    let det = |g: f64| (d1 + d2 * g).determinant();
    let k0 = d1.determinant();
    let k3 = d2.determinant();
    let (fp, fm) = (det(1.0), det(-1.0));
    let k2 = 0.5 * (fp + fm) - k0;
    let k1 = 0.5 * (fp - fm) - k3;
    let mut gammas = cubic_roots(k3, k2, k1, k0);
    // Prefer the most decisive root: the largest |γ| keeps D2's share well conditioned.
    gammas.sort_by(|a, b| b.abs().total_cmp(&a.abs()));

    let mut solutions: Vec<Pose> = Vec::new();
    let mut found_indefinite = false;
    for &gamma in &gammas {
        let d0 = d1 + d2 * gamma;
        let eig = SymmetricEigen::new(d0);
        let mut order = [0usize, 1, 2];
        order.sort_by(|&i, &j| {
            eig.eigenvalues[j]
                .abs()
                .total_cmp(&eig.eigenvalues[i].abs())
        });
        let (sa, sb) = (eig.eigenvalues[order[0]], eig.eigenvalues[order[1]]);
        if sa * sb >= 0.0 {
            continue;
        }
        found_indefinite = true;
        let (pos, neg) = if sa > 0.0 {
            (order[0], order[1])
        } else {
            (order[1], order[0])
        };
        let e_pos: Vector3<f64> = eig.eigenvectors.column(pos).into();
        let e_neg: Vector3<f64> = eig.eigenvectors.column(neg).into();
        let e_null: Vector3<f64> = eig.eigenvectors.column(order[2]).into();
        let s = (-eig.eigenvalues[neg] / eig.eigenvalues[pos]).sqrt();
        // The quadratic to solve on each plane: whichever of D1, D2 is larger there.
        for sign in [1.0, -1.0] {
            // Plane (e_pos − sign·s·e_neg)·λ = 0, spanned by e_null and s·e_pos + sign·e_neg.
            let u = e_pos * s + e_neg * sign;
            let form = |d: &Matrix3<f64>| {
                (
                    e_null.dot(&(d * e_null)),
                    e_null.dot(&(d * u)),
                    u.dot(&(d * u)),
                )
            };
            let f1 = form(&d1);
            let f2 = form(&d2);
            let mag = |f: (f64, f64, f64)| f.0.abs() + f.1.abs() + f.2.abs();
            let (qa, qb, qc) = if mag(f1) >= mag(f2) { f1 } else { f2 };
            // qa α² + 2 qb α β + qc β² = 0.
            let mut dirs = Vec::with_capacity(2);
            if qa.abs() >= qc.abs() {
                for alpha in quadratic_roots(qa, 2.0 * qb, qc) {
                    dirs.push(e_null * alpha + u);
                }
            } else {
                for beta in quadratic_roots(qc, 2.0 * qb, qa) {
                    dirs.push(e_null + u * beta);
                }
            }
            for lambda in dirs {
                if let Some(pose) =
                    pose_from_depth_direction(y, x, &lambda, [a12, a13, a23], [&m12, &m13, &m23])
                {
                    solutions.push(pose);
                }
            }
        }
        break;
    }
    if !found_indefinite && let Some(&gamma) = gammas.first() {
        // Semidefinite degenerate quadric: λ lies on its null line.
        let eig = SymmetricEigen::new(d1 + d2 * gamma);
        let (imin, _) =
            eig.eigenvalues
                .iter()
                .enumerate()
                .fold((0, f64::INFINITY), |(bi, bv), (i, &v)| {
                    if v.abs() < bv { (i, v.abs()) } else { (bi, bv) }
                });
        let lambda: Vector3<f64> = eig.eigenvectors.column(imin).into();
        if let Some(pose) =
            pose_from_depth_direction(y, x, &lambda, [a12, a13, a23], [&m12, &m13, &m23])
        {
            solutions.push(pose);
        }
    }
    solutions
}

/// Scale a depth direction to the largest point distance, keep it if all depths are positive,
/// and align the three camera-frame points to the world points.
fn pose_from_depth_direction(
    y: &[Vector3<f64>; 3],
    x: &[Vector3<f64>; 3],
    lambda: &Vector3<f64>,
    a: [f64; 3],
    m: [&Matrix3<f64>; 3],
) -> Option<Pose> {
    let k = if a[0] >= a[1] && a[0] >= a[2] {
        0
    } else if a[1] >= a[2] {
        1
    } else {
        2
    };
    let q = lambda.dot(&(m[k] * lambda));
    if q <= TINY * lambda.norm_squared() {
        return None;
    }
    let mut l = lambda * (a[k] / q).sqrt();
    if l.x < 0.0 && l.y < 0.0 && l.z < 0.0 {
        l = -l;
    }
    if !(l.x > 0.0 && l.y > 0.0 && l.z > 0.0) {
        return None;
    }
    let cam = [y[0] * l.x, y[1] * l.y, y[2] * l.z];
    let pose = rigid_from_triangles(x, &cam)?;
    let ok = pose.translation.vector.iter().all(|v| v.is_finite());
    ok.then_some(pose)
}

/// A camera pose estimated from bearing–point correspondences.
#[derive(Debug, Clone, PartialEq)]
pub struct AbsolutePose {
    /// World coordinates to camera coordinates.
    pub cam_from_world: Pose,
    /// Per correspondence: angular error within the threshold after refinement.
    pub inliers: Vec<bool>,
    /// Number of inliers.
    pub num_inliers: usize,
    /// RANSAC iterations run.
    pub iterations: usize,
}

/// Robust absolute pose from bearings and world points: P3P RANSAC (MSAC scoring, adaptive
/// stopping), then Huber-robust Gauss–Newton refinement on the inliers' tangent-plane
/// residuals and a final inlier count. `None` below `options.min_inliers`.
pub fn absolute_pose_ransac(
    bearings: &[Vector3<f64>],
    points: &[Vector3<f64>],
    options: &RansacOptions,
) -> Option<AbsolutePose> {
    const K: usize = 3;
    let n = bearings.len();
    if n < K.max(options.min_inliers) || n != points.len() {
        return None;
    }
    let mut rng = ChaCha8Rng::seed_from_u64(options.seed);
    let mut sample = Vec::with_capacity(K);
    let mut best: Option<(Pose, f64, usize)> = None;
    let mut needed = options.max_iterations;
    let mut it = 0;
    let threshold = AngleThreshold::new(options.threshold_rad);
    let within = |i: usize, pose: &Pose| {
        threshold.error_within(&bearings[i], &(pose * Point3::from(points[i])).coords)
    };
    // A point beyond the threshold costs the threshold whatever its error: infinity says so.
    let score = |pose: &Pose| {
        msac(
            (0..n).map(|i| within(i, pose).unwrap_or(f64::INFINITY)),
            options.threshold_rad,
        )
    };
    let test: Option<Vec<usize>> =
        (options.preverify > 0 && n > 2 * options.preverify).then(|| {
            (0..options.preverify)
                .map(|j| j * n / options.preverify)
                .collect()
        });
    while it < needed {
        it += 1;
        sample_distinct(&mut rng, n, K, &mut sample);
        let ys = [
            bearings[sample[0]],
            bearings[sample[1]],
            bearings[sample[2]],
        ];
        let xs = [points[sample[0]], points[sample[1]], points[sample[2]]];
        for pose in p3p(&ys, &xs) {
            if let Some(test) = &test
                && test.iter().filter(|&&i| within(i, &pose).is_some()).count()
                    < PREVERIFY_MIN_INLIERS
            {
                continue;
            }
            let (cost, count) = score(&pose);
            if best.as_ref().is_none_or(|b| cost < b.1) {
                best = Some((pose, cost, count));
                needed =
                    adaptive_iterations(options.confidence, count as f64 / n as f64, K, needed);
            }
        }
    }
    let (mut pose, _, _) = best?;
    // Refine on the current inliers, then once more on the refined inlier set.
    for _ in 0..2 {
        let inl: Vec<usize> = (0..n).filter(|&i| within(i, &pose).is_some()).collect();
        if inl.len() < K {
            return None;
        }
        let b: Vec<Vector3<f64>> = inl.iter().map(|&i| bearings[i]).collect();
        let p: Vec<Vector3<f64>> = inl.iter().map(|&i| points[i]).collect();
        pose = refine_absolute_pose(&pose, &b, &p, options.threshold_rad);
    }
    let inliers: Vec<bool> = (0..n).map(|i| within(i, &pose).is_some()).collect();
    let num_inliers = inliers.iter().filter(|&&f| f).count();
    (num_inliers >= options.min_inliers).then_some(AbsolutePose {
        cam_from_world: pose,
        inliers,
        num_inliers,
        iterations: it,
    })
}

/// Huber weight of a residual norm `r` with threshold `k`.
pub fn huber_weight(r: f64, k: f64) -> f64 {
    if r <= k { 1.0 } else { k / r }
}

/// Robust (Huber, threshold `huber_rad`) Gauss–Newton refinement of `cam_from_world` on
/// tangent-plane residuals. Updates are left-multiplied: `T ← exp(δ) T`, `δ = [ω; v]`.
pub fn refine_absolute_pose(
    cam_from_world: &Pose,
    bearings: &[Vector3<f64>],
    points: &[Vector3<f64>],
    huber_rad: f64,
) -> Pose {
    let bases: Vec<Matrix2x3<f64>> = bearings.iter().map(tangent_basis).collect();
    let mut pose = *cam_from_world;
    let cost = |pose: &Pose| -> f64 {
        let mut c = 0.0;
        for ((b, basis), x) in bearings.iter().zip(&bases).zip(points) {
            let pc = pose * Point3::from(*x);
            c += match tangent_residual(b, basis, &pc.coords) {
                Some((r, _)) => huber_cost(r.norm(), huber_rad),
                None => huber_cost(std::f64::consts::PI, huber_rad),
            };
        }
        c
    };
    let mut current = cost(&pose);
    for _ in 0..ABSOLUTE_REFINE_ITERATIONS {
        let mut h = Matrix6::<f64>::zeros();
        let mut g = Vector6::<f64>::zeros();
        for ((b, basis), x) in bearings.iter().zip(&bases).zip(points) {
            let pc = (pose * Point3::from(*x)).coords;
            let Some((r, j_p)) = tangent_residual(b, basis, &pc) else {
                continue;
            };
            let w = huber_weight(r.norm(), huber_rad);
            let j = j_p * point_jacobian_left_update(&pc);
            h += j.transpose() * j * w;
            g += j.transpose() * r * w;
        }
        let Some(chol) = h.cholesky() else { break };
        let delta = -chol.solve(&g);
        let candidate = se3_exp(&delta) * pose;
        let c = cost(&candidate);
        if c > current {
            break;
        }
        pose = candidate;
        current = c;
        if delta.norm() < REFINE_STEP_TOLERANCE {
            break;
        }
    }
    pose
}

/// Standard deviation (scene units) of the camera centre of `cam_from_world` along its least
/// constrained direction, for bearings with isotropic angular noise `sigma_rad`: the square root
/// of the largest eigenvalue of the translation block of the inverse Gauss–Newton information
/// (tangent-plane residuals, rotation marginalized). The centre moves by `−Rᵀ δv` under a
/// left update `exp([ω; v])`, and the eigenvalues are rotation invariant. Far points constrain
/// the rotation but hardly the position; this says how well the inliers pin the position down.
/// `observations` are (measured bearing, world point) pairs. `None` when the information is
/// singular (fewer than three usable points or degenerate).
pub fn absolute_pose_position_std(
    cam_from_world: &Pose,
    observations: impl IntoIterator<Item = (Vector3<f64>, Vector3<f64>)>,
    sigma_rad: f64,
) -> Option<f64> {
    let mut h = Matrix6::<f64>::zeros();
    let mut used = 0;
    for (b, x) in observations {
        let pc = (cam_from_world * Point3::from(x)).coords;
        let basis = tangent_basis(&b);
        let Some((_, j_p)) = tangent_residual(&b, &basis, &pc) else {
            continue;
        };
        let j = j_p * point_jacobian_left_update(&pc);
        h += j.transpose() * j;
        used += 1;
    }
    if used < 3 || sigma_rad <= 0.0 {
        return None;
    }
    let cov = h.try_inverse()?;
    let block: Matrix3<f64> = cov.fixed_view::<3, 3>(3, 3).into_owned();
    let largest = block
        .symmetric_eigenvalues()
        .iter()
        .copied()
        .fold(0.0_f64, f64::max);
    (largest.is_finite() && largest > 0.0).then(|| largest.sqrt() * sigma_rad)
}

/// Huber cost `ρ(r)` of a residual norm (`r²/2` inside, linear outside).
pub fn huber_cost(r: f64, k: f64) -> f64 {
    if r <= k {
        0.5 * r * r
    } else {
        k * (r - 0.5 * k)
    }
}

// ---------------------------------------------------------------------------------------------
// Planes
// ---------------------------------------------------------------------------------------------

/// Plane samples drawn by [`dominant_plane`]: with half the points on one plane, 200 draws of
/// three miss it with probability 0.875^200 ≈ 3e-12.
const PLANE_DRAWS: usize = 200;

/// The plane holding the most of `points` within `tolerance` (same units), as
/// `(unit normal, offset, count)` with `normal · p = offset` on the plane; `None` for fewer
/// than three points or when every sample is degenerate. Deterministic (fixed seed).
pub fn dominant_plane(
    points: &[Vector3<f64>],
    tolerance: f64,
) -> Option<(Vector3<f64>, f64, usize)> {
    if points.len() < 3 {
        return None;
    }
    let mut rng = ChaCha8Rng::seed_from_u64(0x504C_414E);
    let mut sample = Vec::with_capacity(3);
    let mut best: Option<(Vector3<f64>, f64, usize)> = None;
    for _ in 0..PLANE_DRAWS {
        sample_distinct(&mut rng, points.len(), 3, &mut sample);
        let (a, b, c) = (points[sample[0]], points[sample[1]], points[sample[2]]);
        let n = (b - a).cross(&(c - a));
        let norm = n.norm();
        if norm <= TINY * (1.0 + (b - a).norm_squared() + (c - a).norm_squared()) {
            continue;
        }
        let n = n / norm;
        let d = n.dot(&a);
        let count = points
            .iter()
            .filter(|p| (n.dot(p) - d).abs() <= tolerance)
            .count();
        if best.is_none_or(|(_, _, k)| count > k) {
            best = Some((n, d, count));
        }
    }
    best
}

// ---------------------------------------------------------------------------------------------
// Triangulation
// ---------------------------------------------------------------------------------------------

/// One observation of a point for triangulation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RayObservation {
    /// The observing camera's `cam_from_world`.
    pub cam_from_world: Pose,
    /// The measured unit bearing in that camera.
    pub bearing: Vector3<f64>,
}

/// A triangulated point and how well it is determined.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Triangulated {
    /// The point in world coordinates.
    pub point: Vector3<f64>,
    /// Largest angle (rad) between any two viewing rays at the point: its parallax.
    pub parallax_rad: f64,
    /// Largest angular error (rad) of any observation.
    pub max_error_rad: f64,
}

/// Acceptance limits of a triangulated point.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TriangulationLimits {
    /// Smallest parallax (rad) between viewing rays: below it depth is ill-determined.
    pub min_parallax_rad: f64,
    /// Largest angular error (rad) of any observation.
    pub max_error_rad: f64,
}

impl Default for TriangulationLimits {
    fn default() -> Self {
        Self {
            // ~1°: depth uncertainty stays below ~25 % of the distance at 1 px noise.
            min_parallax_rad: 1.0f64.to_radians(),
            max_error_rad: 0.004,
        }
    }
}

/// Triangulate a point from two or more rays: the linear midpoint (least squares of the
/// distances to all rays, `Σ Rᵢᵀ Pᵢ (Rᵢ X + tᵢ) = 0`, `Pᵢ = I − bᵢbᵢᵀ`), then a few Gauss–Newton
/// steps on the angular residuals. `None` when the rays are degenerate, the point lies behind
/// a camera (against a bearing), or the parallax or errors fail `limits`.
pub fn triangulate(obs: &[RayObservation], limits: &TriangulationLimits) -> Option<Triangulated> {
    if obs.len() < 2 {
        return None;
    }
    let mut a = Matrix3::<f64>::zeros();
    let mut rhs = Vector3::<f64>::zeros();
    for o in obs {
        let r = o.cam_from_world.rotation.to_rotation_matrix();
        let p = Matrix3::identity() - o.bearing * o.bearing.transpose();
        let rtp = r.matrix().transpose() * p;
        a += rtp * r.matrix();
        rhs -= rtp * o.cam_from_world.translation.vector;
    }
    let mut x = a.cholesky()?.solve(&rhs);
    // Gauss–Newton on tangent residuals: the midpoint weights far cameras more than near ones.
    let bases: Vec<Matrix2x3<f64>> = obs.iter().map(|o| tangent_basis(&o.bearing)).collect();
    for _ in 0..5 {
        let mut h = Matrix3::<f64>::zeros();
        let mut g = Vector3::<f64>::zeros();
        for (o, basis) in obs.iter().zip(&bases) {
            let pc = (o.cam_from_world * Point3::from(x)).coords;
            let (r, j_p) = tangent_residual(&o.bearing, basis, &pc)?;
            let j = j_p * o.cam_from_world.rotation.to_rotation_matrix().matrix();
            h += j.transpose() * j;
            g += j.transpose() * r;
        }
        let Some(chol) = h.cholesky() else { break };
        let dx = -chol.solve(&g);
        x += dx;
        if dx.norm() < REFINE_STEP_TOLERANCE * (1.0 + x.norm()) {
            break;
        }
    }
    let mut max_error: f64 = 0.0;
    let mut rays = Vec::with_capacity(obs.len());
    for o in obs {
        let pc = (o.cam_from_world * Point3::from(x)).coords;
        if pc.dot(&o.bearing) <= 0.0 {
            return None;
        }
        max_error = max_error.max(angular_error(&o.bearing, &pc));
        let centre = o.cam_from_world.inverse().translation.vector;
        rays.push((x - centre).try_normalize(TINY)?);
    }
    let mut parallax: f64 = 0.0;
    for i in 0..rays.len() {
        for j in i + 1..rays.len() {
            parallax = parallax.max(angular_error(&rays[i], &rays[j]));
        }
    }
    (x.iter().all(|v| v.is_finite())
        && parallax >= limits.min_parallax_rad
        && max_error <= limits.max_error_rad)
        .then_some(Triangulated {
            point: x,
            parallax_rad: parallax,
            max_error_rad: max_error,
        })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_angle_pre_check_decides_as_the_arc_tangent_does() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        for threshold in [1e-4, 0.015, 0.3, 1.5, 2.0] {
            let t = AngleThreshold::new(threshold);
            let mut near = 0;
            for k in 0..20_000 {
                let b = Vector3::new(
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-1.0..1.0),
                )
                .normalize();
                // Points at angles around the threshold (every fourth one anywhere), at several
                // distances, and a few at the origin.
                let axis = b.cross(&Vector3::new(0.3, -0.5, 0.8)).normalize();
                let angle = if k % 4 == 0 {
                    rng.random_range(0.0..std::f64::consts::PI)
                } else {
                    threshold * (1.0 + rng.random_range(-1e-6..1e-6))
                };
                let dir = nalgebra::Rotation3::from_axis_angle(
                    &nalgebra::Unit::new_normalize(axis),
                    angle,
                ) * b;
                let p = dir * [1e-13, 0.2, 3.0, 1e4][k % 4];
                let expected = angular_error(&b, &p);
                let got = t.error_within(&b, &p);
                assert_eq!(
                    got,
                    (expected <= threshold).then_some(expected),
                    "{threshold} {k}"
                );
                near += usize::from((expected - threshold).abs() < 1e-5 * threshold);
            }
            assert!(near > 1000, "{threshold}: {near} points near the threshold");
        }
    }
}
