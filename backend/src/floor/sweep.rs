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
    /// Every this many planes are scored first; the planes around the best of them are then
    /// scored one by one (0 or 1 scores every plane).
    #[serde(default = "default_coarse_step")]
    pub coarse_step: usize,
}

fn default_coarse_step() -> usize {
    COARSE_STEP
}

/// Coarse plane step of the sweep: two planes shift the widest-baseline view by at most
/// 1.5 px, inside the width of a 5-sample patch's correlation peak, so such a peak is not
/// stepped over; the peaks found are then refined plane by plane.
pub const COARSE_STEP: usize = 2;
/// Coarse peaks refined per pixel: a pixel over a cluttered table has a peak per surface (the
/// table, the tops of things on it) and a narrow one may be the best only at full resolution;
/// each refined peak costs two planes (with two refined, a cluttered table lost a surface).
const REFINED_PEAKS: usize = 4;

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
            coarse_step: COARSE_STEP,
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
    let mut warped = [0.0f32; PATCH * PATCH];
    // The mean agreement of the views on one plane, NaN when too few views see the patch.
    let mut score_of = |plane_h: f64| -> f32 {
        let z = camera_z - plane_h;
        let (Some(p0), Some(px), Some(py)) = (
            on_plane(&c, &d, z),
            on_plane(&c, &dx, z),
            on_plane(&cy, &dy, z),
        ) else {
            return f32::NAN;
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
        if seen >= MIN_VIEWS.min(others.len()) {
            sum / seen as f32
        } else {
            f32::NAN
        }
    };
    let scores = plane_scores(planes.len(), o.coarse_step, |k| score_of(planes[k]));
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

/// The score of every plane that matters for the best one: with `coarse_step` > 1, every
/// `coarse_step`-th plane (and the last), then every plane around the [`REFINED_PEAKS`] best
/// coarse local maxima and the [`REFINED_PEAKS`] coarse samples that rise most above the chord
/// of their neighbours, then the neighbours of the best plane (for its parabola). Planes not
/// scored are NaN, as planes no view agrees on.
fn plane_scores(n: usize, coarse_step: usize, mut score: impl FnMut(usize) -> f32) -> Vec<f32> {
    let mut scores = vec![f32::NAN; n];
    if coarse_step <= 1 || n <= 2 * coarse_step {
        for (k, s) in scores.iter_mut().enumerate() {
            *s = score(k);
        }
        return scores;
    }
    let mut scored = vec![false; n];
    let mut score_at = |k: usize, scores: &mut [f32], scored: &mut [bool]| {
        if !scored[k] {
            scores[k] = score(k);
            scored[k] = true;
        }
    };
    let coarse: Vec<usize> = (0..n)
        .step_by(coarse_step)
        .chain((!(n - 1).is_multiple_of(coarse_step)).then_some(n - 1))
        .collect();
    for &k in &coarse {
        score_at(k, &mut scores, &mut scored);
    }
    // Coarse local maxima, best first.
    let mut peaks: Vec<usize> = (0..coarse.len())
        .filter(|&i| {
            let s = scores[coarse[i]];
            let below = |j: Option<usize>| {
                j.and_then(|j| coarse.get(j))
                    .is_none_or(|&k| scores[k].partial_cmp(&s) != Some(std::cmp::Ordering::Greater))
            };
            s.is_finite() && below(i.checked_sub(1)) && below(Some(i + 1))
        })
        .map(|i| coarse[i])
        .collect();
    peaks.sort_by(|a, b| scores[*b].total_cmp(&scores[*a]).then(a.cmp(b)));
    peaks.truncate(REFINED_PEAKS);
    // A peak narrower than the coarse step on the flank of a broad one is no coarse maximum,
    // but it lifts its coarse sample above the chord of its neighbours: the samples that rise
    // most above their chords are refined too.
    let mut bumps: Vec<(usize, f32)> = (1..coarse.len().saturating_sub(1))
        .map(|i| {
            let (a, b, c) = (
                scores[coarse[i - 1]],
                scores[coarse[i]],
                scores[coarse[i + 1]],
            );
            (coarse[i], b - 0.5 * (a + c))
        })
        .filter(|(_, excess)| *excess > 0.0)
        .collect();
    bumps.sort_by(|a, b| b.1.total_cmp(&a.1).then(a.0.cmp(&b.0)));
    peaks.extend(bumps.iter().take(REFINED_PEAKS).map(|(k, _)| *k));
    for &k in &peaks {
        let (lo, hi) = (k.saturating_sub(coarse_step - 1), (k + coarse_step).min(n));
        for j in lo..hi {
            score_at(j, &mut scores, &mut scored);
        }
    }
    // Climb until the best plane's neighbours are scored (a neighbour may be better still).
    loop {
        let Some(best) = (0..n)
            .filter(|&k| scores[k].is_finite())
            .max_by(|&a, &b| scores[a].total_cmp(&scores[b]))
        else {
            return scores;
        };
        let unscored: Vec<usize> = [best.checked_sub(1), Some(best + 1)]
            .into_iter()
            .flatten()
            .filter(|&k| k < n && !scored[k])
            .collect();
        if unscored.is_empty() {
            return scores;
        }
        for k in unscored {
            score_at(k, &mut scores, &mut scored);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The best plane of a coarse-to-fine search, its score and its neighbours' scores, as
    /// [`plane_scores`] returns them.
    fn best_of(scores: &[f32]) -> Option<(usize, f32, f32, f32)> {
        let (best, s) = scores
            .iter()
            .enumerate()
            .filter(|(_, s)| s.is_finite())
            .max_by(|a, b| a.1.total_cmp(b.1))?;
        let at = |k: Option<usize>| k.and_then(|k| scores.get(k)).copied().unwrap_or(f32::NAN);
        Some((best, *s, at(best.checked_sub(1)), at(Some(best + 1))))
    }

    /// Correlation-like curves over 240 planes: a narrow true peak (falling to 1/e of its
    /// height 2.5 or 1.7 planes from its top: 1.9 or 1.3 px of the widest-baseline view) at
    /// every position, beside a broad look-alike hump and a second, smaller one, with a stretch
    /// of NaN (planes no view sees). The coarse-to-fine search finds the exhaustive search's
    /// best plane, with the same neighbours' scores, and scores about half the planes. (A peak
    /// narrower still, 1/e at 1.3 planes, can hide under a hump's top: a 5-sample patch's
    /// correlation peak is wider than a pixel.)
    #[test]
    fn coarse_to_fine_finds_the_best_plane_beside_look_alike_peaks() {
        let n = 240;
        let mut calls_fine = 0usize;
        let mut calls_coarse = 0usize;
        for centre in 0..n {
            for (broad, width) in [(30.0f32, 2.5f32), (120.0, 1.7), (200.0, 1.7)] {
                let curve = |k: usize| -> f32 {
                    let x = k as f32;
                    if (100..104).contains(&k) && centre % 7 == 0 {
                        return f32::NAN;
                    }
                    let g =
                        |top: f32, at: f32, sigma: f32| top * (-((x - at) / sigma).powi(2)).exp();
                    let narrow = g(0.95, centre as f32 + 0.3, width);
                    let look_alikes = g(0.8, broad, 12.0).max(g(0.7, (broad + 97.0) % 240.0, 3.0));
                    narrow.max(look_alikes) + 1e-4 * x
                };
                let exhaustive = plane_scores(n, 1, |k| {
                    calls_fine += 1;
                    curve(k)
                });
                let coarse = plane_scores(n, COARSE_STEP, |k| {
                    calls_coarse += 1;
                    curve(k)
                });
                assert_eq!(
                    best_of(&exhaustive).map(|b| (b.0, b.1)),
                    best_of(&coarse).map(|b| (b.0, b.1)),
                    "peak at {centre}, look-alike at {broad}"
                );
                let (e, c) = (best_of(&exhaustive), best_of(&coarse));
                assert_eq!(format!("{e:?}"), format!("{c:?}"), "neighbours differ");
            }
        }
        assert_eq!(calls_fine, 3 * n * n);
        assert!(
            (calls_coarse as f64) < 0.6 * calls_fine as f64,
            "{calls_coarse} of {calls_fine} planes scored"
        );
        // Tiny sweeps are scored whole.
        let all = plane_scores(3, COARSE_STEP, |k| k as f32);
        assert_eq!(all, vec![0.0, 1.0, 2.0]);
        assert!(plane_scores(0, COARSE_STEP, |_| 1.0).is_empty());
    }
}
