//! Lens intrinsics over the whole field of view from aprilgrid (or any planar-target) corners.
//!
//! Steps: the corners of each image become a view; [`init`] finds a starting lens with no
//! focal-length hint and every view's pose; the coverage of the image is checked; [`solve`]
//! runs a joint Huber Levenberg–Marquardt over the intrinsics and all poses with pixel
//! residuals of full 3-D projections (corners beyond 90° off-axis count like any other);
//! corners and views whose residuals are far outside the robust noise level are rejected and
//! the fit repeated; parameter standard deviations come from the final normal matrix. A Double
//! Sphere fit starts from the Kannala–Brandt one. [`report`] writes the artifact part and the
//! report folder.

pub(crate) mod init;
pub mod report;
mod solve;

use std::collections::BTreeMap;

use nalgebra::{Vector2, Vector3};
use serde::Serialize;

use kiwi_core::artifact::{Intrinsics, LensCalibration};
use kiwi_core::camera::{Camera, CameraModel, CameraModelKind};
use kiwi_core::geometry::Pose;

use crate::detect::CornerSet;
use crate::error::{CalibError, Result};
use solve::ViewObs;

/// Fewest views a calibration accepts: fewer cannot separate focal length, distortion and
/// board distance over a fisheye's field of view.
pub const MIN_VIEWS: usize = 6;
/// Fewest corners a view must keep to count (two tags).
pub const MIN_CORNERS_PER_VIEW: usize = 8;
/// Huber threshold (px): residuals beyond it weigh linearly, so wrong detections pull less.
pub const HUBER_PX: f64 = 1.5;
/// A corner is rejected if its residual exceeds this many robust noise sigmas (per axis); for
/// Gaussian noise a 2-D residual that large happens once in ~270 000 corners.
pub const OUTLIER_SIGMAS: f64 = 5.0;
/// ... but never below this (px), so a near-perfect fit does not reject good corners.
pub const OUTLIER_FLOOR_PX: f64 = 0.5;
/// A view is rejected if its RMS exceeds this multiple of the median view RMS (a bad view:
/// motion blur, a wrong pose, a misdetected board).
pub const VIEW_RMS_FACTOR: f64 = 3.0;
/// Most rounds of rejection and re-fitting (the set of corners taking part settles in 2–4).
const REJECTION_ROUNDS: usize = 8;
/// Distinct Double Sphere starts fitted jointly (the model has more than one basin; the best
/// lens-to-lens match sometimes leads the joint fit into a wrong one, ~1 in 25 captures).
const DS_JOINT_STARTS: usize = 3;
/// Median of a Rayleigh distribution divided by its per-axis sigma: √(2 ln 2).
const RAYLEIGH_MEDIAN: f64 = 1.177_410_022_515_474_8;
/// Off-axis angle (rad, through the equidistant start) within which corners take part in the
/// first, central fit: 60°, where an equidistant start is within a few per cent of any lens.
const CENTRAL_THETA_RAD: f64 = std::f64::consts::FRAC_PI_3;
/// Coverage grid: the image is cut into this many regions per side.
pub const COVERAGE_GRID: usize = 3;
/// Fewest corners each region inside the image circle needs.
pub const MIN_CORNERS_PER_REGION: usize = 12;

/// Options of [`calibrate`].
#[derive(Debug, Clone)]
pub struct IntrinsicsOptions {
    /// Projection model to fit.
    pub model: CameraModelKind,
    /// Lens name written into the artifact (`front`, `rear`, `main`).
    pub lens_name: String,
    /// Check that the corners cover the image (off only for tests of partial data).
    pub check_coverage: bool,
}

impl Default for IntrinsicsOptions {
    fn default() -> Self {
        Self {
            model: CameraModelKind::Kb4,
            lens_name: "front".into(),
            check_coverage: true,
        }
    }
}

/// One rejected corner, for the report.
#[derive(Debug, Clone, Serialize)]
pub struct RejectedCorner {
    /// Image name.
    pub image: String,
    /// Target point id.
    pub id: u32,
    /// Observed pixel.
    pub pixel: [f64; 2],
    /// Residual norm at rejection (px); NaN if it did not project.
    pub residual_px: f64,
    /// Why.
    pub reason: String,
}

/// Per-view result.
#[derive(Debug, Clone, Serialize)]
pub struct ViewResult {
    /// Image name.
    pub image: String,
    /// Whether the view was used.
    pub used: bool,
    /// Corners used.
    pub corners: usize,
    /// RMS per axis of its used corners (px).
    pub rms_px: f64,
    /// Board pose `cam_from_board` (translation m, quaternion xyzw), if used.
    pub cam_from_board: Option<[f64; 7]>,
}

/// One used corner's final residual.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct CornerResidual {
    /// View index.
    pub view: usize,
    /// Target point id.
    pub id: u32,
    /// Observed pixel.
    pub pixel: [f64; 2],
    /// Projected minus observed (px).
    pub residual: [f64; 2],
    /// Angle off the optical axis of the fitted direction (deg).
    pub theta_deg: f64,
}

/// The result of an intrinsics calibration.
#[derive(Debug, Clone, Serialize)]
pub struct IntrinsicsResult {
    /// The fitted camera.
    #[serde(skip)]
    pub camera: Camera,
    /// Model name.
    pub model: String,
    /// Parameter names in order.
    pub param_names: Vec<String>,
    /// Parameters.
    pub params: Vec<f64>,
    /// Standard deviation of each parameter.
    pub param_std: Vec<f64>,
    /// RMS reprojection error per axis over the used corners (px): √(Σ|r|² / 2N).
    pub rms_px: f64,
    /// Views used.
    pub n_views: usize,
    /// Corners used.
    pub n_corners: usize,
    /// Corners rejected (including those of rejected views).
    pub n_rejected: usize,
    /// Largest angle off-axis among the used corners (deg).
    pub max_theta_deg: f64,
    /// Image size.
    pub resolution: [u32; 2],
    /// LM iterations of the final solve.
    pub iterations: usize,
    /// Every rejected corner and why.
    pub rejected: Vec<RejectedCorner>,
    /// Per-view results.
    pub views: Vec<ViewResult>,
    /// Residuals of the used corners.
    #[serde(skip)]
    pub residuals: Vec<CornerResidual>,
}

impl IntrinsicsResult {
    /// fx, fy, cx, cy.
    pub fn pinhole(&self) -> [f64; 4] {
        [
            self.params[0],
            self.params[1],
            self.params[2],
            self.params[3],
        ]
    }

    /// The `--json` summary: `fx, fy, cx, cy, params, rms_px, n_views, n_corners, n_rejected`.
    pub fn summary_json(&self) -> serde_json::Value {
        let [fx, fy, cx, cy] = self.pinhole();
        serde_json::json!({
            "model": self.model,
            "fx": fx, "fy": fy, "cx": cx, "cy": cy,
            "params": self.params,
            "param_names": self.param_names,
            "param_std": self.param_std,
            "rms_px": self.rms_px,
            "n_views": self.n_views,
            "n_corners": self.n_corners,
            "n_rejected": self.n_rejected,
            "max_theta_deg": self.max_theta_deg,
        })
    }

    /// The lens part of the unit artifact (kiwi-core schema).
    pub fn lens_calibration(&self) -> LensCalibration {
        LensCalibration {
            name: String::new(),
            intrinsics: Intrinsics::from_camera(&self.camera),
            resolution: self.resolution,
            valid_fov_rad: (2.0 * self.max_theta_deg.to_radians()).min(self.camera.valid_fov()),
            rms_px: Some(self.rms_px),
            param_std: Some(self.param_std.clone()),
            cam_from_imu: None,
            time_shift_s: None,
        }
    }
}

/// Names of the coverage regions, row-major from the top-left.
const REGION_NAMES: [&str; 9] = [
    "top-left",
    "top",
    "top-right",
    "left",
    "centre",
    "right",
    "bottom-left",
    "bottom",
    "bottom-right",
];

fn views_from_corners(set: &CornerSet, rejected: &mut Vec<RejectedCorner>) -> Vec<ViewObs> {
    set.images
        .iter()
        .map(|img| {
            // Repeated ids in one image (a misread tag) cannot be told apart: drop them all.
            let mut count: BTreeMap<u32, usize> = BTreeMap::new();
            for c in &img.corners {
                *count.entry(c.id).or_default() += 1;
            }
            let mut v = ViewObs {
                name: img.name.clone(),
                ids: Vec::new(),
                board: Vec::new(),
                pixel: Vec::new(),
                active: Vec::new(),
                usable: Vec::new(),
                view_active: true,
            };
            for c in &img.corners {
                let unique = count.get(&c.id).copied().unwrap_or(0) == 1;
                if !unique {
                    rejected.push(RejectedCorner {
                        image: img.name.clone(),
                        id: c.id,
                        pixel: c.pixel,
                        residual_px: f64::NAN,
                        reason: "id appears more than once in the image".into(),
                    });
                }
                v.ids.push(c.id);
                v.board.push(c.board_point());
                v.pixel.push(Vector2::new(c.pixel[0], c.pixel[1]));
                v.active.push(unique);
                v.usable.push(unique);
            }
            v
        })
        .collect()
}

fn input_error(message: String) -> CalibError {
    CalibError::Input {
        path: "corners".into(),
        message,
    }
}

/// Check every region of the image inside the lens's 90° circle holds corners; the error names
/// the empty regions.
fn check_coverage(camera: &Camera, views: &[ViewObs]) -> Result<()> {
    let (w, h) = camera.resolution();
    let (wf, hf) = (f64::from(w), f64::from(h));
    let mut counts = [0usize; COVERAGE_GRID * COVERAGE_GRID];
    for v in views.iter().filter(|v| v.view_active) {
        for (p, a) in v.pixel.iter().zip(&v.active) {
            if *a {
                let cx = ((p.x / wf * COVERAGE_GRID as f64) as usize).min(COVERAGE_GRID - 1);
                let cy = ((p.y / hf * COVERAGE_GRID as f64) as usize).min(COVERAGE_GRID - 1);
                counts[cy * COVERAGE_GRID + cx] += 1;
            }
        }
    }
    let params = camera.params();
    let centre = Vector2::new(params[2], params[3]);
    let rim = camera
        .project(&Vector3::new(1.0, 0.0, 1e-9))
        .map_or(f64::INFINITY, |p| (p.coords - centre).norm());
    let mut empty = Vec::new();
    for (k, n) in counts.iter().enumerate() {
        let (gx, gy) = (k % COVERAGE_GRID, k / COVERAGE_GRID);
        let region_centre = Vector2::new(
            (gx as f64 + 0.5) * wf / COVERAGE_GRID as f64,
            (gy as f64 + 0.5) * hf / COVERAGE_GRID as f64,
        );
        if (region_centre - centre).norm() <= rim && *n < MIN_CORNERS_PER_REGION {
            empty.push(format!("{} ({n} corners)", REGION_NAMES[k]));
        }
    }
    if empty.is_empty() {
        Ok(())
    } else {
        Err(input_error(format!(
            "coverage too thin: these image regions hold fewer than {MIN_CORNERS_PER_REGION} \
             corners: {}; add views with the board in those parts of the image (the periphery \
             matters most for a fisheye)",
            empty.join(", ")
        )))
    }
}

/// Residual norm of every corner of every view (px): `None` for views out of the fit, corners
/// that are not usable, and corners that do not project.
fn corner_norms(camera: &Camera, poses: &[Pose], views: &[ViewObs]) -> Vec<Vec<Option<f64>>> {
    views
        .iter()
        .zip(poses)
        .map(|(v, pose)| {
            (0..v.board.len())
                .map(|i| {
                    (v.view_active && v.usable[i])
                        .then(|| solve::residual(camera, pose, &v.board[i], &v.pixel[i]))
                        .flatten()
                        .map(|r| r.norm())
                })
                .collect()
        })
        .collect()
}

fn median(values: &mut [f64]) -> f64 {
    if values.is_empty() {
        return 0.0;
    }
    values.sort_by(f64::total_cmp);
    values[values.len() / 2]
}

/// Re-decide which corners and views take part, from the current fit; returns how many
/// decisions changed and the corner threshold used (px).
///
/// Every usable corner of a usable view is judged again each round, so a corner that a poor
/// early fit put outside the threshold comes back once the fit improves (rejections made on a
/// biased first fit would otherwise stay and bias the result). Views are rejected for good:
/// their poses stop being refined.
fn classify(
    camera: &Camera,
    poses: &[Pose],
    views: &mut [ViewObs],
    rejected: &mut Vec<RejectedCorner>,
) -> (usize, f64) {
    // One residual per corner serves the noise level, the corner decisions and the view RMS.
    // The noise level comes from every usable corner, rejected ones included: with a few per
    // cent of outliers the median stays the inliers'.
    let norms = corner_norms(camera, poses, views);
    let mut all: Vec<f64> = norms.iter().flatten().flatten().copied().collect();
    let sigma = median(&mut all) / RAYLEIGH_MEDIAN;
    let threshold = (OUTLIER_SIGMAS * sigma).max(OUTLIER_FLOOR_PX);
    let mut changed = 0;
    for (v, view_norms) in views.iter_mut().zip(&norms) {
        if !v.view_active {
            continue;
        }
        for (active, norm) in v.active.iter_mut().zip(view_norms) {
            let keep = norm.is_some_and(|r| r <= threshold);
            if keep != *active {
                *active = keep;
                changed += 1;
            }
        }
    }
    // Views: too few corners left, or an RMS far above the others'.
    let view_rms: Vec<Option<f64>> = views
        .iter()
        .zip(&norms)
        .map(|(v, view_norms)| {
            let kept: Vec<f64> = view_norms
                .iter()
                .zip(&v.active)
                .filter_map(|(n, a)| n.filter(|_| *a))
                .collect();
            (v.view_active && !kept.is_empty())
                .then(|| (kept.iter().map(|r| r * r).sum::<f64>() / (2 * kept.len()) as f64).sqrt())
        })
        .collect();
    let mut all: Vec<f64> = view_rms.iter().flatten().copied().collect();
    let med = median(&mut all);
    for ((v, rms), pose) in views.iter_mut().zip(&view_rms).zip(poses) {
        if !v.view_active {
            continue;
        }
        let too_few = v.active_count() < MIN_CORNERS_PER_VIEW;
        let too_bad = rms.is_some_and(|r| r > VIEW_RMS_FACTOR * med && r > threshold / 2.0);
        if too_few || too_bad {
            let reason = if too_few {
                format!("view kept fewer than {MIN_CORNERS_PER_VIEW} corners")
            } else {
                format!(
                    "view RMS {:.2} px is above {VIEW_RMS_FACTOR}× the median view RMS",
                    rms.unwrap_or(f64::NAN)
                )
            };
            reject_view(camera, pose, v, &reason, rejected);
            changed += 1;
        }
    }
    (changed, threshold)
}

/// Take a view out of the fit, listing each of its usable corners with the reason.
fn reject_view(
    camera: &Camera,
    pose: &Pose,
    v: &mut ViewObs,
    reason: &str,
    rejected: &mut Vec<RejectedCorner>,
) {
    v.view_active = false;
    for i in 0..v.board.len() {
        v.active[i] = false;
        if v.usable[i] {
            rejected.push(RejectedCorner {
                image: v.name.clone(),
                id: v.ids[i],
                pixel: [v.pixel[i].x, v.pixel[i].y],
                residual_px: solve::residual(camera, pose, &v.board[i], &v.pixel[i])
                    .map_or(f64::NAN, |r| r.norm()),
                reason: reason.to_string(),
            });
        }
    }
}

/// List the usable corners of the views still in the fit that the last round left out.
fn list_rejected_corners(
    camera: &Camera,
    poses: &[Pose],
    views: &[ViewObs],
    threshold: f64,
    rejected: &mut Vec<RejectedCorner>,
) {
    for (v, pose) in views.iter().zip(poses) {
        if !v.view_active {
            continue;
        }
        for i in 0..v.board.len() {
            if v.usable[i] && !v.active[i] {
                let r = solve::residual(camera, pose, &v.board[i], &v.pixel[i]).map(|r| r.norm());
                rejected.push(RejectedCorner {
                    image: v.name.clone(),
                    id: v.ids[i],
                    pixel: [v.pixel[i].x, v.pixel[i].y],
                    residual_px: r.unwrap_or(f64::NAN),
                    reason: match r {
                        Some(_) => format!("residual above {threshold:.2} px ({OUTLIER_SIGMAS}σ)"),
                        None => "does not project through the fitted lens".into(),
                    },
                });
            }
        }
    }
}

fn active_view_count(views: &[ViewObs]) -> usize {
    views.iter().filter(|v| v.view_active).count()
}

fn too_few_views(n: usize, stage: &str) -> CalibError {
    input_error(format!(
        "too few views: {n} usable {stage}, at least {MIN_VIEWS} needed; capture more images \
         with the whole board visible, spread over the field of view"
    ))
}

/// A finished joint fit: camera, poses, views (with their rejections), rejected corners and
/// the final solve's iterations.
type DsFit = (Camera, Vec<Pose>, Vec<ViewObs>, Vec<RejectedCorner>, usize);

/// Robust fit with rejection rounds, re-fitting until the set of corners taking part stops
/// changing; the corners left out at the end are added to `rejected`. Returns the final
/// solve's iterations.
fn fit_with_rejection(
    camera: &mut Camera,
    poses: &mut [Pose],
    views: &mut [ViewObs],
    rejected: &mut Vec<RejectedCorner>,
) -> Result<usize> {
    let mut iterations = 0;
    let mut threshold = f64::INFINITY;
    let mut settled = false;
    for _ in 0..REJECTION_ROUNDS {
        iterations = solve_once(camera, poses, views)?;
        let (changed, t) = classify(camera, poses, views, rejected);
        threshold = t;
        tracing::debug!(changed, threshold, "intrinsics rejection round");
        if changed == 0 {
            settled = true;
            break;
        }
    }
    if !settled {
        // The last round changed the set: fit it once more.
        iterations = solve_once(camera, poses, views)?;
    }
    list_rejected_corners(camera, poses, views, threshold, rejected);
    Ok(iterations)
}

/// One robust solve; checks enough views remain.
fn solve_once(camera: &mut Camera, poses: &mut [Pose], views: &mut [ViewObs]) -> Result<usize> {
    let n = active_view_count(views);
    if n < MIN_VIEWS {
        return Err(too_few_views(n, "after rejecting outliers"));
    }
    let stats = solve::optimize(camera, poses, views, Some(HUBER_PX))
        .ok_or_else(|| CalibError::Internal("the fit could not evaluate any corner".into()))?;
    Ok(stats.iterations)
}

/// Calibrate one lens from a corners set.
pub fn calibrate(set: &CornerSet, options: &IntrinsicsOptions) -> Result<IntrinsicsResult> {
    let Some(first) = set.images.first() else {
        return Err(input_error(
            "no images with corners; run `kiwi-calib detect` on the calibration images first"
                .into(),
        ));
    };
    let (width, height) = (first.width, first.height);
    let mut rejected = Vec::new();
    let mut views = views_from_corners(set, &mut rejected);
    for v in &mut views {
        if v.active_count() < MIN_CORNERS_PER_VIEW {
            v.view_active = false;
        }
    }
    let n = active_view_count(&views);
    if n < MIN_VIEWS {
        return Err(too_few_views(
            n,
            &format!("(images with at least {MIN_CORNERS_PER_VIEW} corners)"),
        ));
    }
    let (kb4, init_poses) = init::initial_kb4(&views, width, height).ok_or_else(|| {
        input_error(
            "no focal length explains the corners; check the board positions (metres) and that \
             the images come from one lens"
                .into(),
        )
    })?;
    let mut poses: Vec<Pose> = Vec::with_capacity(views.len());
    for (v, p) in views.iter_mut().zip(&init_poses) {
        match p {
            Some(p) => poses.push(*p),
            None => {
                v.view_active = false;
                poses.push(Pose::identity());
            }
        }
    }
    let n = active_view_count(&views);
    if n < MIN_VIEWS {
        return Err(too_few_views(n, "after initialisation"));
    }
    let mut camera = Camera::Kb4(kb4);
    if options.check_coverage {
        check_coverage(&camera, &views)?;
    }
    // The Double Sphere fit judges outliers with its own model: a KB4 lens fitted to a DS lens
    // misfits the far periphery by a few tenths of a pixel, so rejections made at the KB4
    // stage would drop good peripheral corners (and keep those whose noise happens to follow
    // the KB4 curve, biasing the DS fit). Remember what the KB4 stage started from.
    let before_kb4 = (views.clone(), rejected.len());
    fit_centre_first(&mut camera, &mut poses, &views);
    let mut iterations = fit_with_rejection(&mut camera, &mut poses, &mut views, &mut rejected)?;
    if options.model == CameraModelKind::DoubleSphere {
        let (start_views, start_rejected) = before_kb4;
        views = start_views;
        rejected.truncate(start_rejected);
        let max_theta = max_theta(&poses, &views);
        let Camera::Kb4(kb4) = &camera else {
            return Err(CalibError::Internal("expected the KB4 stage".into()));
        };
        let candidates = init::ds_candidates_from_camera(kb4, max_theta);
        if candidates.is_empty() {
            return Err(input_error(
                "the lens cannot be described by the Double Sphere model over the observed \
                 field of view; use --model kb4"
                    .into(),
            ));
        }
        // Joint fit from each of the best few lens-to-lens starts; the winner has the lowest
        // robust cost over every corner the KB4 stage started from (rejected ones included,
        // so a start cannot win by rejecting what it misfits).
        let mut best: Option<(f64, DsFit)> = None;
        let mut first_error = None;
        for ds in candidates.into_iter().take(DS_JOINT_STARTS) {
            let mut c = Camera::DoubleSphere(ds);
            let mut p = poses.clone();
            let mut v = views.clone();
            let mut r = rejected.clone();
            match fit_with_rejection(&mut c, &mut p, &mut v, &mut r) {
                Ok(it) => {
                    let score =
                        solve::cost(&c, &p, &views, Some(HUBER_PX)).unwrap_or(f64::INFINITY);
                    if best.as_ref().is_none_or(|b| score < b.0) {
                        best = Some((score, (c, p, v, r, it)));
                    }
                }
                Err(e) => {
                    first_error.get_or_insert(e);
                }
            }
        }
        match (best, first_error) {
            (Some((_, (c, p, v, r, it))), _) => {
                camera = c;
                poses = p;
                views = v;
                rejected = r;
                iterations = it;
            }
            (None, Some(e)) => return Err(e),
            (None, None) => return Err(CalibError::Internal("no Double Sphere start".into())),
        }
    }
    finish(camera, &poses, &views, rejected, iterations)
}

/// Fit the lens to the corners near the image centre first, then re-pose the views that had
/// none there through that lens.
///
/// The equidistant start is fitted to the whole field of view; when the lens departs strongly
/// from `r = f·θ` towards the rim (a Double Sphere lens with its periphery compressed), the
/// start's focal length is several per cent off the centre's, and a joint fit of every corner
/// from there can settle in a wrong minimum (measured: 2 in 48 captures of the recommended
/// design, fit RMS 3 px, focal length 8 % low). Near the centre the equidistant start is close,
/// so the central fit lands in the right basin; the views outside it then start from poses
/// their corners give through the central lens. Best effort: if the central fit cannot run
/// (too few central views), the full fit starts from the equidistant lens as before.
fn fit_centre_first(camera: &mut Camera, poses: &mut [Pose], views: &[ViewObs]) {
    let params = camera.params();
    let centre = Vector2::new(params[2], params[3]);
    let radius = params[0] * CENTRAL_THETA_RAD;
    let mut central: Vec<ViewObs> = views.to_vec();
    for v in &mut central {
        for i in 0..v.board.len() {
            v.active[i] = v.usable[i] && (v.pixel[i] - centre).norm() <= radius;
        }
        v.view_active = v.view_active && v.active_count() >= MIN_CORNERS_PER_VIEW;
    }
    if active_view_count(&central) < MIN_VIEWS {
        return;
    }
    let mut c = camera.clone();
    let mut p = poses.to_vec();
    if solve::optimize(&mut c, &mut p, &mut central, Some(HUBER_PX)).is_none() {
        return;
    }
    for ((v, cv), (pose, fitted)) in views.iter().zip(&central).zip(poses.iter_mut().zip(&p)) {
        if !v.view_active {
            continue;
        }
        if cv.view_active {
            *pose = *fitted;
            continue;
        }
        let (mut bearings, mut board) = (Vec::new(), Vec::new());
        for i in 0..v.board.len() {
            if v.usable[i]
                && let Some(b) = c.unproject(&nalgebra::Point2::from(v.pixel[i]))
            {
                bearings.push(b.into_inner());
                board.push(v.board[i]);
            }
        }
        if let Some((repose, _)) = init::pose_from_bearings(&bearings, &board) {
            *pose = repose;
        }
    }
    *camera = c;
}

fn max_theta(poses: &[Pose], views: &[ViewObs]) -> f64 {
    let mut m: f64 = 0.0;
    for (v, pose) in views.iter().zip(poses) {
        if !v.view_active {
            continue;
        }
        for i in 0..v.board.len() {
            if v.active[i] {
                let pc = pose * nalgebra::Point3::from(v.board[i]);
                m = m.max(pc.coords.xy().norm().atan2(pc.z));
            }
        }
    }
    m
}

fn finish(
    camera: Camera,
    poses: &[Pose],
    views: &[ViewObs],
    rejected: Vec<RejectedCorner>,
    iterations: usize,
) -> Result<IntrinsicsResult> {
    let mut residuals = Vec::new();
    let mut view_results = Vec::new();
    let mut sum = 0.0;
    for (k, (v, pose)) in views.iter().zip(poses).enumerate() {
        let (mut vs, mut vn) = (0.0, 0usize);
        if v.view_active {
            for i in 0..v.board.len() {
                if !v.active[i] {
                    continue;
                }
                let pc = pose * nalgebra::Point3::from(v.board[i]);
                if let Some(r) = solve::residual(&camera, pose, &v.board[i], &v.pixel[i]) {
                    vs += r.norm_squared();
                    vn += 1;
                    residuals.push(CornerResidual {
                        view: k,
                        id: v.ids[i],
                        pixel: [v.pixel[i].x, v.pixel[i].y],
                        residual: [r.x, r.y],
                        theta_deg: pc.coords.xy().norm().atan2(pc.z).to_degrees(),
                    });
                }
            }
        }
        sum += vs;
        let q = pose.rotation;
        let t = pose.translation.vector;
        view_results.push(ViewResult {
            image: v.name.clone(),
            used: v.view_active,
            corners: vn,
            rms_px: if vn > 0 {
                (vs / (2 * vn) as f64).sqrt()
            } else {
                f64::NAN
            },
            cam_from_board: v.view_active.then_some([t.x, t.y, t.z, q.i, q.j, q.k, q.w]),
        });
    }
    let n_corners = residuals.len();
    let n_views = active_view_count(views);
    let ni = camera.params().len();
    let dof = (2 * n_corners).saturating_sub(ni + 6 * n_views).max(1);
    let sigma2 = sum / dof as f64;
    let param_std = solve::intrinsics_covariance(&camera, poses, views, sigma2).map_or_else(
        || vec![f64::NAN; ni],
        |c| (0..ni).map(|i| c[(i, i)].max(0.0).sqrt()).collect(),
    );
    let max_theta_deg = residuals.iter().map(|r| r.theta_deg).fold(0.0, f64::max);
    let names: Vec<String> = Intrinsics::from_camera(&camera)
        .param_names()
        .iter()
        .map(|s| (*s).to_string())
        .collect();
    Ok(IntrinsicsResult {
        model: camera.kind().to_string(),
        param_names: names,
        params: camera.params().to_vec(),
        param_std,
        rms_px: (sum / (2 * n_corners.max(1)) as f64).sqrt(),
        n_views,
        n_corners,
        n_rejected: rejected.len(),
        max_theta_deg,
        resolution: [camera.resolution().0, camera.resolution().1],
        iterations,
        rejected,
        views: view_results,
        residuals,
        camera,
    })
}
