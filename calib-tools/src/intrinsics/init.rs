//! Initialisation without a focal-length guess.
//!
//! With the principal point at the image centre and an equidistant lens (`r = f·θ`), every
//! focal length `f` turns the corners into unit bearings — over the whole sphere, so corners
//! beyond 90° keep their meaning. For a planar board the bearings must satisfy
//! `b ∝ H·(X, Y, 1)` for one homography `H = [r1 r2 t]` per view; a direct linear solve with
//! the cross-product constraint `b × H·q = 0` finds it for any direction, and the angle between
//! each bearing and its reconstructed direction measures how well `f` explains the view. A
//! log-spaced scan over `f` followed by golden-section refinement picks the focal length, and
//! the homographies give every view's starting pose. A Double Sphere start is fitted to the
//! solved Kannala–Brandt lens over the observed field of view.

use nalgebra::{DMatrix, Matrix3, Point2, SMatrix, SymmetricEigen, Translation3, Vector2, Vector3};

use kiwi_core::camera::{CameraModel, DoubleSphere, Kb4};
use kiwi_core::geometry::{Pose, project_to_rotation};

use super::solve::ViewObs;

/// Focal-length scan range as fractions of the image width: 0.03 w is a 1000° "lens", 3 w a
/// 20° one — wider than any lens this tool calibrates.
const F_SCAN_MIN: f64 = 0.03;
const F_SCAN_MAX: f64 = 3.0;
/// Log-spaced steps of the focal scan.
const F_SCAN_STEPS: usize = 90;
/// Golden-section iterations refining the best scan step.
const F_REFINE_ITERATIONS: usize = 40;
/// Fewest corners for a view's homography: 4 suffice, more keep the solve well-conditioned.
pub(crate) const MIN_INIT_CORNERS: usize = 6;
/// A view's angular error is capped at this (rad) in the focal score so one bad view cannot
/// dominate.
const ANGLE_ERROR_CAP: f64 = 0.2;

/// Unit bearing of a pixel under an equidistant lens with focal `f` and centre `c`.
fn equidistant_bearing(p: &Vector2<f64>, c: &Vector2<f64>, f: f64) -> Option<Vector3<f64>> {
    let d = p - c;
    let r = d.norm();
    let theta = r / f;
    if theta >= std::f64::consts::PI {
        return None;
    }
    if r < 1e-12 {
        return Some(Vector3::z());
    }
    let s = theta.sin() / r;
    Some(Vector3::new(d.x * s, d.y * s, theta.cos()))
}

/// Pose `cam_from_board` of a planar board from bearings, and the median angle (rad) between
/// each bearing and the direction the pose predicts.
pub(crate) fn pose_from_bearings(
    bearings: &[Vector3<f64>],
    board: &[Vector3<f64>],
) -> Option<(Pose, f64)> {
    let n = bearings.len();
    if n < MIN_INIT_CORNERS {
        return None;
    }
    let mean = board.iter().fold(Vector3::zeros(), |a, b| a + b) / n as f64;
    let scale = (board.iter().map(|b| (b - mean).norm_squared()).sum::<f64>() / n as f64).sqrt();
    if scale < 1e-12 {
        return None;
    }
    let mut m = SMatrix::<f64, 9, 9>::zeros();
    for (b, p) in bearings.iter().zip(board) {
        let q = Vector3::new((p.x - mean.x) / scale, (p.y - mean.y) / scale, 1.0);
        // b × (H q) = 0: rows for the x and y components (the z one is dependent).
        let mut r1 = SMatrix::<f64, 1, 9>::zeros();
        let mut r2 = SMatrix::<f64, 1, 9>::zeros();
        for k in 0..3 {
            // Row 0 of H at 0..3, row 1 at 3..6, row 2 at 6..9.
            r1[3 + k] = -b.z * q[k];
            r1[6 + k] = b.y * q[k];
            r2[k] = b.z * q[k];
            r2[6 + k] = -b.x * q[k];
        }
        m += r1.transpose() * r1 + r2.transpose() * r2;
    }
    let eig = SymmetricEigen::new(m);
    let (imin, _) = eig
        .eigenvalues
        .iter()
        .enumerate()
        .min_by(|a, b| a.1.total_cmp(b.1))?;
    let h = eig.eigenvectors.column(imin);
    let mut hm = Matrix3::new(h[0], h[1], h[2], h[3], h[4], h[5], h[6], h[7], h[8]);
    let agree: f64 = bearings
        .iter()
        .zip(board)
        .map(|(b, p)| {
            let q = Vector3::new((p.x - mean.x) / scale, (p.y - mean.y) / scale, 1.0);
            b.dot(&(hm * q))
        })
        .sum();
    if agree < 0.0 {
        hm = -hm;
    }
    let (c1, c2, c3) = (hm.column(0), hm.column(1), hm.column(2));
    let lambda = 0.5 * (c1.norm() + c2.norm());
    if lambda < 1e-12 {
        return None;
    }
    let r1 = c1 / c1.norm();
    let r2 = c2 / c2.norm();
    let rot = project_to_rotation(&Matrix3::from_columns(&[r1, r2, r1.cross(&r2)]))?;
    let t_norm = c3 / lambda;
    let t = t_norm * scale - rot * mean;
    let pose = Pose::from_parts(Translation3::from(t), rot);
    let mut errors: Vec<f64> = bearings
        .iter()
        .zip(board)
        .map(|(b, p)| {
            let d = pose * nalgebra::Point3::from(*p);
            let d = d.coords.normalize();
            b.dot(&d).clamp(-1.0, 1.0).acos()
        })
        .collect();
    errors.sort_by(f64::total_cmp);
    Some((pose, errors[n / 2]))
}

/// Score of a focal length: the sum over views of the capped median angular error.
fn focal_score(views: &[ViewObs], c: &Vector2<f64>, f: f64) -> f64 {
    views
        .iter()
        .filter(|v| v.view_active)
        .map(|v| match view_pose(v, c, f) {
            Some((_, e)) => e.min(ANGLE_ERROR_CAP),
            None => ANGLE_ERROR_CAP,
        })
        .sum()
}

fn view_pose(v: &ViewObs, c: &Vector2<f64>, f: f64) -> Option<(Pose, f64)> {
    let mut bearings = Vec::with_capacity(v.board.len());
    let mut board = Vec::with_capacity(v.board.len());
    for i in 0..v.board.len() {
        if v.active[i]
            && let Some(b) = equidistant_bearing(&v.pixel[i], c, f)
        {
            bearings.push(b);
            board.push(v.board[i]);
        }
    }
    pose_from_bearings(&bearings, &board)
}

/// The starting Kannala–Brandt lens (equidistant, centred) and every view's pose (`None` where
/// the view cannot be solved), or `None` if no focal length explains the views.
pub(crate) fn initial_kb4(
    views: &[ViewObs],
    width: u32,
    height: u32,
) -> Option<(Kb4, Vec<Option<Pose>>)> {
    let w = f64::from(width);
    let c = Vector2::new((w - 1.0) / 2.0, (f64::from(height) - 1.0) / 2.0);
    let (lo, hi) = ((F_SCAN_MIN * w).ln(), (F_SCAN_MAX * w).ln());
    let step = (hi - lo) / (F_SCAN_STEPS - 1) as f64;
    let scores: Vec<f64> = (0..F_SCAN_STEPS)
        .map(|k| focal_score(views, &c, (lo + step * k as f64).exp()))
        .collect();
    let (best, _) = scores
        .iter()
        .enumerate()
        .min_by(|a, b| a.1.total_cmp(b.1))?;
    // Golden-section search on log f between the neighbours of the best step.
    let (mut a, mut b) = (
        lo + step * best.saturating_sub(1) as f64,
        lo + step * (best + 1).min(F_SCAN_STEPS - 1) as f64,
    );
    let g = 0.5 * (5f64.sqrt() - 1.0);
    let mut x1 = b - g * (b - a);
    let mut x2 = a + g * (b - a);
    let mut f1 = focal_score(views, &c, x1.exp());
    let mut f2 = focal_score(views, &c, x2.exp());
    for _ in 0..F_REFINE_ITERATIONS {
        if f1 < f2 {
            b = x2;
            x2 = x1;
            f2 = f1;
            x1 = b - g * (b - a);
            f1 = focal_score(views, &c, x1.exp());
        } else {
            a = x1;
            x1 = x2;
            f1 = f2;
            x2 = a + g * (b - a);
            f2 = focal_score(views, &c, x2.exp());
        }
    }
    let f = (0.5 * (a + b)).exp();
    let camera = Kb4::new(width, height, [f, f, c.x, c.y, 0.0, 0.0, 0.0, 0.0]).ok()?;
    let poses = views
        .iter()
        .map(|v| {
            if v.view_active {
                view_pose(v, &c, f).map(|(p, _)| p)
            } else {
                None
            }
        })
        .collect();
    Some((camera, poses))
}

/// Starting `(ξ, α)` grid of the Double Sphere fit: spans the lenses the model is used for.
const DS_XI_GRID: [f64; 7] = [-0.6, -0.4, -0.2, 0.0, 0.2, 0.5, 0.8];
const DS_ALPHA_GRID: [f64; 6] = [0.3, 0.4, 0.5, 0.6, 0.7, 0.8];
/// Samples per ring and rings of the lens-to-lens fit.
const DS_FIT_AZIMUTHS: usize = 12;
const DS_FIT_RINGS: usize = 24;
/// Gauss–Newton iterations of the lens-to-lens fit.
const DS_FIT_ITERATIONS: usize = 200;
/// Grid starts refined by the lens-to-lens fit (the model has more than one basin).
const DS_FIT_STARTS: usize = 8;

/// A Double Sphere lens that projects like `kb4` (any model) over directions up to `max_theta` off-axis.
#[cfg(test)]
pub(crate) fn ds_from_camera(kb4: &dyn CameraModel, max_theta: f64) -> Option<DoubleSphere> {
    ds_candidates_from_camera(kb4, max_theta).into_iter().next()
}

/// Two lens-to-lens fits count as the same candidate if their ξ differ by less than this (the
/// basins of the Double Sphere model lie far apart in ξ).
const DS_SAME_XI: f64 = 0.02;

/// Double Sphere lenses that project like `kb4` (any model) over directions up to `max_theta`
/// off-axis: the distinct local minima of the lens-to-lens fit, best first. Several are
/// returned because the best lens-to-lens match need not lie in the basin of the best joint
/// fit (ξ, α and the focal length trade off over the observed field of view).
pub(crate) fn ds_candidates_from_camera(
    kb4: &dyn CameraModel,
    max_theta: f64,
) -> Vec<DoubleSphere> {
    let (w, h) = kb4.resolution();
    let p = kb4.params();
    let mut samples: Vec<(Vector3<f64>, Point2<f64>)> = Vec::new();
    for ring in 1..=DS_FIT_RINGS {
        let theta = max_theta * ring as f64 / DS_FIT_RINGS as f64;
        for k in 0..DS_FIT_AZIMUTHS {
            let phi = std::f64::consts::TAU * k as f64 / DS_FIT_AZIMUTHS as f64;
            let d = kiwi_core::camera::bearing_from_angles(theta, phi).into_inner();
            if let Some(px) = kb4.project(&d) {
                samples.push((d, px));
            }
        }
    }
    if samples.len() < 10 {
        return Vec::new();
    }
    let err = |cam: &DoubleSphere| -> Option<f64> {
        samples
            .iter()
            .map(|(d, px)| cam.project(d).map(|q| (q - px).norm_squared()))
            .sum()
    };
    // Grid starts: the focal follows from the mean radius ratio for each shape. The model has
    // several basins (ξ and α trade off), so the best few starts are each refined.
    let mut starts: Vec<(f64, DoubleSphere)> = Vec::new();
    for xi in DS_XI_GRID {
        for alpha in DS_ALPHA_GRID {
            let Ok(unit) = DoubleSphere::new(w, h, [1.0, 1.0, 0.0, 0.0, xi, alpha]) else {
                continue;
            };
            let (mut num, mut den) = (0.0, 0.0);
            let mut ok = true;
            for (d, px) in &samples {
                match unit.project(d) {
                    Some(q) => {
                        let target = Vector2::new(px.x - p[2], px.y - p[3]);
                        num += q.coords.dot(&target);
                        den += q.coords.norm_squared();
                    }
                    None => ok = false,
                }
            }
            if !ok || den <= 0.0 {
                continue;
            }
            let f = num / den;
            let Ok(cam) = DoubleSphere::new(w, h, [f, f, p[2], p[3], xi, alpha]) else {
                continue;
            };
            if let Some(e) = err(&cam) {
                starts.push((e, cam));
            }
        }
    }
    starts.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut fits: Vec<(f64, DoubleSphere)> = starts
        .into_iter()
        .take(DS_FIT_STARTS)
        .filter_map(|(e, cam)| refine_ds(cam, e, &samples))
        .collect();
    fits.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut out: Vec<DoubleSphere> = Vec::new();
    for (_, cam) in fits {
        if out
            .iter()
            .all(|c| (c.params()[4] - cam.params()[4]).abs() > DS_SAME_XI)
        {
            out.push(cam);
        }
    }
    out
}

/// Levenberg–Marquardt of a Double Sphere lens's parameters to match `samples` (direction,
/// pixel); returns the final squared error and the lens.
fn refine_ds(
    mut cam: DoubleSphere,
    start_error: f64,
    samples: &[(Vector3<f64>, Point2<f64>)],
) -> Option<(f64, DoubleSphere)> {
    let err = |cam: &DoubleSphere| -> Option<f64> {
        samples
            .iter()
            .map(|(d, px)| cam.project(d).map(|q| (q - px).norm_squared()))
            .sum()
    };
    let mut current = start_error;
    let n = cam.params().len();
    let mut lambda = 1e-4;
    let mut dp = nalgebra::Matrix2xX::zeros(n);
    for _ in 0..DS_FIT_ITERATIONS {
        let mut hm = DMatrix::<f64>::zeros(n, n);
        let mut g = nalgebra::DVector::<f64>::zeros(n);
        for (d, px) in samples {
            let (q, _) = cam.project_with_jacobians(d, Some(&mut dp))?;
            let r = q - px;
            hm += dp.transpose() * &dp;
            g += dp.transpose() * r;
        }
        let mut improved = false;
        while lambda < 1e10 {
            let mut a = hm.clone();
            for i in 0..n {
                a[(i, i)] += lambda * hm[(i, i)].max(1e-12);
            }
            let Some(ch) = a.cholesky() else {
                lambda *= 10.0;
                continue;
            };
            let step = ch.solve(&(-&g));
            let params: Vec<f64> = cam
                .params()
                .iter()
                .zip(step.iter())
                .map(|(a, b)| a + b)
                .collect();
            let mut trial = cam.clone();
            if trial.set_params(&params).is_ok()
                && let Some(e) = err(&trial)
                && e < current
            {
                let rel = (current - e) / current.max(1e-300);
                cam = trial;
                current = e;
                lambda *= 0.3;
                improved = rel > 1e-12;
                break;
            }
            lambda *= 10.0;
        }
        if !improved {
            break;
        }
    }
    Some((current, cam))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ds_fit_recovers_a_ds_lens() {
        let truth =
            DoubleSphere::new(960, 960, [238.79, 238.67, 485.3, 483.0, -0.2014, 0.5938]).unwrap();
        let fit = ds_from_camera(&truth, 2.1).unwrap();
        println!("{:?}", fit.params());
        for (a, b) in fit.params().iter().zip(truth.params()) {
            assert!((a - b).abs() < 1e-3 * b.abs().max(1.0), "{a} vs {b}");
        }
    }
}
