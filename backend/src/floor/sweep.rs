//! Photometric plane sweep (Collins 1996) over horizontal planes: a patch around each
//! downward-looking pixel of a reference frame is carried, through the fisheye model and each
//! candidate plane, into the window's other frames; the plane where the frames agree best
//! (zero-mean normalized cross-correlation) is the pixel's vote for a surface height.

use nalgebra::{Point2, Point3, Vector3};

use kiwi_core::camera::CameraModel;

use super::view::{HeightVotes, PosedView, Surface, is_flat, zncc};

/// What the sweep looks at and how finely.
#[derive(Debug, Clone, Copy, serde::Serialize, serde::Deserialize)]
pub struct SweepOptions {
    /// Nearest plane swept, below the reference camera (m).
    pub h_min_m: f64,
    /// Farthest plane swept (m).
    pub h_max_m: f64,
    /// Pixels looking within this angle of straight down take part (rad).
    pub max_nadir_rad: f64,
    /// Reference pixels sampled across the image width (the grid's density).
    pub grid_across: usize,
    /// Plane spacing as the largest image shift it causes in the widest-baseline view (px).
    pub step_px: f64,
    /// A pixel votes when the frames agree at least this well (mean ZNCC).
    pub min_agreement: f32,
    /// A surface needs this share of the voting pixels.
    pub min_support: f64,
    /// Histogram bin of the votes (m).
    pub bin_m: f64,
}

impl Default for SweepOptions {
    fn default() -> Self {
        Self {
            h_min_m: 0.15,
            h_max_m: 2.6,
            max_nadir_rad: 60f64.to_radians(),
            grid_across: 72,
            step_px: 0.75,
            min_agreement: 0.75,
            min_support: 0.06,
            bin_m: 0.02,
        }
    }
}

/// Patch side (samples) of the compared patches.
const PATCH: usize = 5;
/// A patch flatter than this (luma standard deviation) carries no height.
const MIN_PATCH_STD: f32 = 3.0;
/// Most planes one window sweeps (the step widens beyond, bounding the cost).
const MAX_PLANES: usize = 240;
/// Fewest other frames that must see a patch for it to vote.
const MIN_VIEWS: usize = 2;

/// A sweep's result: the votes (the support curve of the figure) and the surfaces found.
#[derive(Debug, Clone)]
pub struct SweepResult {
    /// Votes per height below the reference camera.
    pub votes: HeightVotes,
    /// Surfaces, lowest first.
    pub surfaces: Vec<Surface>,
}

/// Angular size of one pixel at the image centre (rad): the scale between image shifts and
/// ray angles.
pub fn pixel_angle(camera: &dyn CameraModel) -> Option<f64> {
    let (w, h) = camera.resolution();
    let c = Point2::new(f64::from(w) / 2.0, f64::from(h) / 2.0);
    let a = camera.unproject(&c)?;
    let b = camera.unproject(&Point2::new(c.x + 1.0, c.y))?;
    let angle = a.angle(&b);
    (angle > 0.0).then_some(angle)
}

/// Sweep `reference` against `others`.
pub fn sweep(reference: &PosedView<'_>, others: &[PosedView<'_>], o: &SweepOptions) -> SweepResult {
    let c_ref = reference.middle().translation.vector;
    let camera_z = c_ref.z;
    let mut votes = HeightVotes::new(o.h_min_m, o.h_max_m, o.bin_m);
    let Some(pixel_rad) = pixel_angle(reference.camera) else {
        return SweepResult {
            votes,
            surfaces: Vec::new(),
        };
    };
    let baseline = others
        .iter()
        .map(|v| (v.middle().translation.vector - c_ref).xy().norm())
        .fold(0.0f64, f64::max);
    // Planes even in inverse height: a step moves a point of the widest-baseline view by at
    // most `step_px` (shift ≈ baseline · Δ(1/h) / pixel angle).
    let (inv_near, inv_far) = (1.0 / o.h_min_m, 1.0 / o.h_max_m);
    let mut inv_step = o.step_px * pixel_rad / baseline.max(1e-3);
    if (inv_near - inv_far) / inv_step > MAX_PLANES as f64 {
        inv_step = (inv_near - inv_far) / MAX_PLANES as f64;
    }
    let planes: Vec<f64> = {
        let n = ((inv_near - inv_far) / inv_step).floor() as usize + 1;
        (0..n)
            .map(|k| 1.0 / (inv_far + k as f64 * inv_step))
            .collect()
    };
    let (w, h) = reference.camera.resolution();
    let stride = (f64::from(w) / o.grid_across as f64).max(1.0);
    let step = (f64::from(w) / 240.0).round().max(1.0);
    let half = (PATCH / 2) as f64;
    let down = -o.max_nadir_rad.cos();
    let mut grid = Vec::new();
    let mut y = stride / 2.0 + half * step;
    while y < f64::from(h) - 1.0 - (half + 1.0) * step {
        let mut x = stride / 2.0 + half * step;
        while x < f64::from(w) - 1.0 - (half + 1.0) * step {
            grid.push(Point2::new(x, y));
            x += stride;
        }
        y += stride;
    }
    let heights: Vec<Option<f64>> = {
        use rayon::prelude::*;
        grid.par_iter()
            .map(|u| pixel_height(reference, others, u, step, down, camera_z, &planes, o))
            .collect()
    };
    for h in heights.into_iter().flatten() {
        votes.voters += 1;
        if h.is_finite() {
            votes.vote(h);
        }
    }
    let surfaces = votes.surfaces(o.min_support, camera_z);
    SweepResult { votes, surfaces }
}

/// One reference pixel's best plane: `None` when it cannot vote (not looking down, flat, off
/// the lens), `Some(NaN)` when it could but the frames agree on no plane, else the height
/// below the reference camera (m), interpolated between planes.
#[allow(clippy::too_many_arguments)]
fn pixel_height(
    reference: &PosedView<'_>,
    others: &[PosedView<'_>],
    u: &Point2<f64>,
    step: f64,
    down: f64,
    camera_z: f64,
    planes: &[f64],
    o: &SweepOptions,
) -> Option<f64> {
    let (c, d) = reference.ray(u)?;
    if d.z > down {
        return None;
    }
    let (_, dx) = reference.ray(&Point2::new(u.x + step, u.y))?;
    let (cy, dy) = reference.ray(&Point2::new(u.x, u.y + step))?;
    let half = (PATCH / 2) as i32;
    let mut patch = [0.0f32; PATCH * PATCH];
    for j in -half..=half {
        for i in -half..=half {
            let k = ((j + half) as usize) * PATCH + (i + half) as usize;
            patch[k] = reference.sample(u.x + f64::from(i) * step, u.y + f64::from(j) * step)?;
        }
    }
    if is_flat(&patch, MIN_PATCH_STD) {
        return None;
    }
    let on_plane = |origin: &Point3<f64>, dir: &Vector3<f64>, z: f64| -> Option<Point3<f64>> {
        let t = (z - origin.z) / dir.z;
        (t > 0.0).then(|| origin + dir * t)
    };
    let mut scores = Vec::with_capacity(planes.len());
    let mut warped = [0.0f32; PATCH * PATCH];
    for &plane_h in planes {
        let z = camera_z - plane_h;
        let (Some(p0), Some(px), Some(py)) = (
            on_plane(&c, &d, z),
            on_plane(&c, &dx, z),
            on_plane(&cy, &dy, z),
        ) else {
            scores.push(f32::NAN);
            continue;
        };
        let (mut sum, mut seen) = (0.0f32, 0usize);
        for view in others {
            let Some(q0) = view.project(&p0) else {
                continue;
            };
            let pose = view.cam_from_scene_at(q0.y);
            let (Some(qx), Some(qy)) = (view.project_in(pose, &px), view.project_in(pose, &py))
            else {
                continue;
            };
            let (ex, ey) = (qx - q0, qy - q0);
            let mut ok = true;
            for j in -half..=half {
                for i in -half..=half {
                    let q = q0 + ex * f64::from(i) + ey * f64::from(j);
                    match view.sample(q.x, q.y) {
                        Some(v) => warped[((j + half) as usize) * PATCH + (i + half) as usize] = v,
                        None => ok = false,
                    }
                }
            }
            if !ok {
                continue;
            }
            if let Some(s) = zncc(&patch, &warped, 0.5) {
                sum += s;
                seen += 1;
            }
        }
        scores.push(if seen >= MIN_VIEWS.min(others.len()) {
            sum / seen as f32
        } else {
            f32::NAN
        });
    }
    let (best, score) = scores
        .iter()
        .enumerate()
        .filter(|(_, s)| s.is_finite())
        .max_by(|a, b| a.1.total_cmp(b.1))?;
    if *score < o.min_agreement {
        return Some(f64::NAN);
    }
    // Parabola through the best plane and its neighbours, in inverse height.
    let inv = |k: usize| 1.0 / planes[k];
    let mut inv_h = inv(best);
    if best > 0 && best + 1 < planes.len() {
        let (a, b, cc) = (scores[best - 1], *score, scores[best + 1]);
        if a.is_finite() && cc.is_finite() {
            let denom = f64::from(a - 2.0 * b + cc);
            if denom < 0.0 {
                let offset = (0.5 * f64::from(a - cc) / denom).clamp(-0.5, 0.5);
                let (lo, hi) = (inv(best - 1), inv(best + 1));
                inv_h += offset * 0.5 * (hi - lo);
            }
        }
    }
    Some(1.0 / inv_h)
}
