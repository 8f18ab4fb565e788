//! The hat marker seen by a wrist's rear lens (paper §4.3.2, eq. 5): its corners found in the
//! fisheye image and turned into bearing vectors through the lens model, and `cam_from_marker`
//! from those bearings by IPPE with the planar ambiguity resolved.
//!
//! Marker frame: origin at the black square's centre, x to the printed right, y to the printed
//! top, z out of the printed face (OpenCV's `SOLVEPNP_IPPE_SQUARE` frame).
//!
//! The X5's lens squeezes a marker far off its axis, so corners found on the raw fisheye image
//! are refined on a virtual perspective view aimed at the marker and resampled through the lens
//! model; the pose is solved on a virtual pinhole aimed at the marker too, so no pinhole
//! approximation of the 190° lens enters.

use nalgebra::{Translation3, UnitQuaternion, Vector3};
use opencv::core::{Mat, Point2d, Point3d, Vector};
use opencv::prelude::*;

use kiwi_core::camera::{Camera, CameraModel};
use kiwi_core::geometry::Pose;

use crate::error::{BackendError, Result};
use crate::frames::ColorImage;
use crate::gripper::aruco::{TagDetector, TagView};
use crate::gripper::{ChannelOrder, ImageView};
use crate::vision::geometry::aimed_at;

/// The refinement view spans this many times the marker's angular radius around its centre:
/// room for the white border and the detector's margin.
const REFINE_VIEW_SPAN: f64 = 2.5;
/// Largest half-angle of the refinement view (rad): a near marker is refined on a wide view.
const MAX_REFINE_HALF_ANGLE: f64 = 1.0;
/// The refinement view samples the lens this many times more finely than the source image
/// near the marker: the detector's corner refinement works in view pixels.
const REFINE_UPSAMPLE: f64 = 2.0;
/// Accept the better IPPE solution on its own when the other explains the corners this many
/// times worse (RMS angle). Under image noise alone the wrong branch of a marker seen at an
/// oblique angle scores tens of times worse; a ratio near 1 is the planar ambiguity.
pub const MIN_AMBIGUITY_RATIO: f64 = 4.0;
/// An ambiguous sighting is resolved by the previous pose only when the chosen solution's
/// rotation is this close to it (rad): the head turns less than this between two nearby
/// sightings.
pub const MAX_TEMPORAL_ROTATION_RAD: f64 = 0.35;
/// ... and the other branch is at least this many times further from it: a previous pose
/// that sits between the branches decides nothing.
pub const TEMPORAL_MARGIN_FACTOR: f64 = 2.0;
/// The corners' own angular noise (rad): about 0.1 px at 960 px on a 190° lens. A pose that
/// explains the corners better than this is no better than one at this error, so the
/// ambiguity ratio is taken over at least this much (two near-perfect fits are ambiguous).
pub const CORNER_NOISE_RAD: f64 = 3e-4;
/// Smallest marker that is posed (px, the square root of its area on the image): below this
/// IPPE's rotation errs by degrees and its branch choice is unreliable even at a clear ratio
/// (measured at 960 px: 12-22 px sightings 50-110 mm and 6-109 deg off, one a wrong branch at
/// ratio 6; 25-40 px sightings within 12.5 mm; at 480 px, 16 px markers erred by 5-30 deg).
pub const MIN_MARKER_SIZE_PX: f64 = 25.0;
/// Largest RMS angle (rad) between the corners' bearings and the accepted pose's: about
/// three pixels at 960 px on a 190° lens; worse means a misdetection.
pub const MAX_CORNER_ERROR_RAD: f64 = 0.01;

/// One of IPPE's two poses of a square.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SquarePose {
    /// `cam_from_marker`.
    pub cam_from_marker: Pose,
    /// RMS angle between the observed corner bearings and the pose's (rad).
    pub error_rad: f64,
}

/// IPPE's two poses of a square, the better first.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SquarePoses {
    /// The pose that explains the corners best.
    pub best: SquarePose,
    /// The other branch of the planar ambiguity.
    pub other: SquarePose,
}

impl SquarePoses {
    /// How many times worse the other branch explains the corners than the best one, or than
    /// the corners' own noise when the best fits better than that.
    pub fn ambiguity_ratio(&self) -> f64 {
        self.other.error_rad / self.best.error_rad.max(CORNER_NOISE_RAD)
    }
}

/// What became of one sighting.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Resolved {
    /// One pose, unambiguous by the corners alone.
    Clear(SquarePose),
    /// The ambiguity resolved by the previous pose.
    ByPrevious(SquarePose),
    /// Both branches explain the corners and nothing decides between them.
    Ambiguous,
    /// Even the better pose does not explain the corners: a misdetection.
    BadFit,
}

impl Resolved {
    /// The accepted pose, if any.
    pub fn pose(&self) -> Option<&SquarePose> {
        match self {
            Self::Clear(p) | Self::ByPrevious(p) => Some(p),
            Self::Ambiguous | Self::BadFit => None,
        }
    }
}

/// Resolve IPPE's two poses: the better alone when the other is clearly worse, else the one
/// that agrees with `previous` (`cam_from_marker` of a nearby accepted sighting), else none.
pub fn resolve(poses: &SquarePoses, previous: Option<&Pose>) -> Resolved {
    if poses.best.error_rad > MAX_CORNER_ERROR_RAD {
        return Resolved::BadFit;
    }
    if poses.ambiguity_ratio() >= MIN_AMBIGUITY_RATIO {
        return Resolved::Clear(poses.best);
    }
    let Some(prev) = previous else {
        return Resolved::Ambiguous;
    };
    let turn = |p: &SquarePose| p.cam_from_marker.rotation.angle_to(&prev.rotation);
    let (near, far) = if turn(&poses.best) <= turn(&poses.other) {
        (poses.best, poses.other)
    } else {
        (poses.other, poses.best)
    };
    if near.error_rad <= MAX_CORNER_ERROR_RAD
        && turn(&near) <= MAX_TEMPORAL_ROTATION_RAD
        && turn(&far) >= TEMPORAL_MARGIN_FACTOR * turn(&near)
    {
        Resolved::ByPrevious(near)
    } else {
        Resolved::Ambiguous
    }
}

#[allow(clippy::needless_pass_by_value)] // used as `map_err(cv_err)`
fn cv_err(e: opencv::Error) -> BackendError {
    BackendError::Input {
        path: "opencv solvePnP (IPPE square)".into(),
        message: e.to_string(),
    }
}

/// The corner positions of a square marker of side `size_m` in its frame, in OpenCV's corner
/// order (printed top-left, top-right, bottom-right, bottom-left).
pub fn marker_corners(size_m: f64) -> [Vector3<f64>; 4] {
    let h = size_m / 2.0;
    [
        Vector3::new(-h, h, 0.0),
        Vector3::new(h, h, 0.0),
        Vector3::new(h, -h, 0.0),
        Vector3::new(-h, -h, 0.0),
    ]
}

/// RMS angle between observed bearings and those of the marker's corners at `cam_from_marker`.
fn corner_error(corners: &[Vector3<f64>; 4], cam_from_marker: &Pose, size_m: f64) -> f64 {
    crate::vision::geometry::rms_angular_error(cam_from_marker, corners, &marker_corners(size_m))
}

/// IPPE's two poses of a square marker of side `size_m` from its corners' bearings (lens
/// frame, OpenCV's corner order). `None` when the corners do not form a square's image (a
/// degenerate quadrilateral or a corner behind the virtual view).
pub fn square_poses(corners: &[Vector3<f64>; 4], size_m: f64) -> Result<Option<SquarePoses>> {
    let Some(centre) = corners
        .iter()
        .map(nalgebra::Matrix::normalize)
        .sum::<Vector3<f64>>()
        .try_normalize(1e-9)
    else {
        return Ok(None);
    };
    let cam_from_view = aimed_at(&centre);
    let mut image_points: Vector<Point2d> = Vector::new();
    for c in corners {
        let v = cam_from_view.inverse() * c;
        if v.z <= 1e-6 {
            return Ok(None);
        }
        image_points.push(Point2d::new(v.x / v.z, v.y / v.z));
    }
    let object_points: Vector<Point3d> = marker_corners(size_m)
        .iter()
        .map(|m| Point3d::new(m.x, m.y, m.z))
        .collect();
    let k = Mat::from_slice_2d(&[[1.0f64, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
        .map_err(cv_err)?;
    let dist = Mat::default();
    let mut rvecs: Vector<Mat> = Vector::new();
    let mut tvecs: Vector<Mat> = Vector::new();
    let mut errors = Mat::default();
    let n = opencv::calib3d::solve_pnp_generic(
        &object_points,
        &image_points,
        &k,
        &dist,
        &mut rvecs,
        &mut tvecs,
        false,
        opencv::calib3d::SolvePnPMethod::SOLVEPNP_IPPE_SQUARE,
        &opencv::core::no_array(),
        &opencv::core::no_array(),
        &mut errors,
    )
    .map_err(cv_err)?;
    if n < 2 {
        return Ok(None);
    }
    let mut poses = Vec::with_capacity(2);
    for i in 0..2 {
        let r = rvecs.get(i).map_err(cv_err)?;
        let t = tvecs.get(i).map_err(cv_err)?;
        let rv = Vector3::new(
            *r.at::<f64>(0).map_err(cv_err)?,
            *r.at::<f64>(1).map_err(cv_err)?,
            *r.at::<f64>(2).map_err(cv_err)?,
        );
        let tv = Vector3::new(
            *t.at::<f64>(0).map_err(cv_err)?,
            *t.at::<f64>(1).map_err(cv_err)?,
            *t.at::<f64>(2).map_err(cv_err)?,
        );
        if !(rv.iter().chain(tv.iter()).all(|x| x.is_finite())) {
            return Ok(None);
        }
        let view_from_marker =
            Pose::from_parts(Translation3::from(tv), UnitQuaternion::from_scaled_axis(rv));
        let cam_from_marker =
            Pose::from_parts(Translation3::identity(), cam_from_view.into()) * view_from_marker;
        poses.push(SquarePose {
            cam_from_marker,
            error_rad: corner_error(corners, &cam_from_marker, size_m),
        });
    }
    poses.sort_by(|a, b| a.error_rad.total_cmp(&b.error_rad));
    Ok(Some(SquarePoses {
        best: poses[0],
        other: poses[1],
    }))
}

/// Finds the hat marker in one lens's frames.
pub struct MarkerFinder {
    camera: Camera,
    detector: TagDetector,
    /// Cells across the marker (bits and border), for the edge profiles' reach.
    cells: usize,
}

impl MarkerFinder {
    /// A finder of marker `id` of the named ArUco dictionary through `camera`.
    pub fn new(camera: Camera, dictionary: &str, id: usize) -> Result<Self> {
        let detector = TagDetector::new(dictionary, id)?;
        let cells = detector.marker_cells();
        Ok(Self {
            camera,
            detector,
            cells,
        })
    }

    /// The marker's corners as bearings (lens frame, OpenCV's corner order), or `None` when it
    /// is not seen: found on the fisheye image, then refined on a perspective view aimed at it.
    /// A frame of another size than the lens's calibration is an error.
    pub fn find(&self, image: &ColorImage) -> Result<Option<[Vector3<f64>; 4]>> {
        let (w, h) = self.camera.resolution();
        if image.width != w as usize || image.height != h as usize {
            return Err(BackendError::Input {
                path: "rear lens frame".into(),
                message: format!(
                    "the frame is {}x{} px but the lens calibration is for {w}x{h} px; use the \
                     calibration made at the stream's resolution",
                    image.width, image.height
                ),
            });
        }
        let grey = image.to_gray()?;
        let Some(pixels) = self
            .detector
            .detect_grey(&grey.data, image.width, image.height)?
        else {
            return Ok(None);
        };
        let mut rough = [Vector3::zeros(); 4];
        for (b, p) in rough.iter_mut().zip(&pixels) {
            let Some(v) = self.camera.unproject(p) else {
                return Ok(None);
            };
            *b = v.normalize();
        }
        let view = ImageView {
            width: image.width,
            height: image.height,
            data: &image.bgr,
            order: ChannelOrder::Bgr,
        };
        Ok(Some(self.refine(&view, &rough)?.unwrap_or(rough)))
    }

    /// The marker's size on the image (px): the square root of the area of its corners'
    /// quadrilateral in the fisheye image, so foreshortening counts.
    pub fn size_px(&self, corners: &[Vector3<f64>; 4]) -> Option<f64> {
        let mut px = [nalgebra::Point2::origin(); 4];
        for (p, b) in px.iter_mut().zip(corners) {
            *p = self.camera.project(b)?;
        }
        let twice_area: f64 = (0..4)
            .map(|k| {
                let (a, b) = (px[k], px[(k + 1) % 4]);
                a.x * b.y - b.x * a.y
            })
            .sum();
        Some((twice_area.abs() / 2.0).sqrt())
    }

    /// Where in the frame's readout the marker was exposed: its centre's image row over the
    /// last row (0 at the top). A sighting's time on a rolling-shutter frame is the frame's
    /// timestamp (its first row) plus this fraction of the readout time.
    pub fn row_fraction(&self, corners: &[Vector3<f64>; 4]) -> Option<f64> {
        let centre = corners.iter().sum::<Vector3<f64>>().try_normalize(1e-9)?;
        let (_, h) = self.camera.resolution();
        let p = self.camera.project(&centre)?;
        Some((p.y / f64::from(h.max(2) - 1)).clamp(0.0, 1.0))
    }

    /// Each corner's image row over the last row (0 at the top): when it was exposed within a
    /// rolling-shutter readout.
    pub fn corner_row_fractions(&self, corners: &[Vector3<f64>; 4]) -> Option<[f64; 4]> {
        let (_, h) = self.camera.resolution();
        let mut rows = [0.0; 4];
        for (r, b) in rows.iter_mut().zip(corners) {
            *r = (self.camera.project(b)?.y / f64::from(h.max(2) - 1)).clamp(0.0, 1.0);
        }
        Some(rows)
    }

    /// Corners found again on a view aimed at the rough ones.
    fn refine(
        &self,
        image: &ImageView<'_>,
        rough: &[Vector3<f64>; 4],
    ) -> Result<Option<[Vector3<f64>; 4]>> {
        let Some(centre) = rough.iter().sum::<Vector3<f64>>().try_normalize(1e-9) else {
            return Ok(None);
        };
        let radius = rough
            .iter()
            .map(|b| b.angle(&centre))
            .fold(0.0f64, f64::max);
        let half = (REFINE_VIEW_SPAN * radius).clamp(0.02, MAX_REFINE_HALF_ANGLE);
        // The source's sampling near the marker: pixels per radian from a small step.
        let step = 1e-3;
        let side = aimed_at(&centre) * Vector3::x();
        let nearby = (centre + side * step).normalize();
        let px_per_rad = match (self.camera.project(&centre), self.camera.project(&nearby)) {
            (Some(a), Some(b)) => (b - a).norm() / step,
            _ => return Ok(None),
        };
        let view = TagView::new(&self.camera, &centre, half, REFINE_UPSAMPLE * px_per_rad)?;
        let Some(grey) = view.grey(image) else {
            return Ok(None);
        };
        let side = view.side();
        let Some(found) = self.detector.detect_grey(&grey, side, side)? else {
            return Ok(None);
        };
        let corners = edge_corners(&grey, side, &found, self.cells).unwrap_or(found);
        Ok(Some(corners.map(|p| view.bearing(p.x, p.y))))
    }
}

/// Edge samples along each side start and end this far (share of the side) from its corners:
/// blur rounds a square's corners, never the middle of its edges.
const EDGE_SPAN: (f64, f64) = (0.2, 0.8);
/// Half-length of the profile across an edge, in cells measured across the edge (the square's
/// width perpendicular to it over its cells): the grey levels are read half a cell out, in the
/// middle of the black border and of the white margin, furthest from the next transitions on
/// both sides (a shorter reach reads inside the edge's own blur, a longer one the data cells').
const EDGE_PROFILE_CELLS: f64 = 0.5;
/// Shortest profile half-length (px): room for the blur of the view.
const MIN_EDGE_PROFILE_PX: f64 = 1.5;
/// Step along an edge profile (px).
const EDGE_PROFILE_STEP_PX: f64 = 0.25;
/// Least grey step (DN) across an edge for a sample to count: a printed black-on-white edge
/// steps by well over 100, a shadow or a smudge by less.
const MIN_EDGE_CONTRAST: f64 = 40.0;
/// Fewest edge samples that fit a side's line.
const MIN_EDGE_SAMPLES: usize = 6;
/// A sample further than this (px) from its side's first line is dropped before the refit.
const MAX_EDGE_RESIDUAL_PX: f64 = 1.0;
/// Largest move (px) of a corner by the edge fit: more means the fit found something other
/// than the marker's border, and the detector's corner stands.
const MAX_EDGE_CORNER_SHIFT_PX: f64 = 2.0;

/// Bilinear grey value at `(x, y)` (pixel centres at integers), `None` outside.
fn grey_at(grey: &[u8], side: usize, x: f64, y: f64) -> Option<f64> {
    if !(x >= 0.0 && y >= 0.0 && x <= side as f64 - 1.0 && y <= side as f64 - 1.0) {
        return None;
    }
    let (x0, y0) = (x.floor() as usize, y.floor() as usize);
    let (x1, y1) = ((x0 + 1).min(side - 1), (y0 + 1).min(side - 1));
    let (fx, fy) = (x - x0 as f64, y - y0 as f64);
    let g = |xx: usize, yy: usize| f64::from(grey[yy * side + xx]);
    Some(
        (g(x0, y0) * (1.0 - fx) + g(x1, y0) * fx) * (1.0 - fy)
            + (g(x0, y1) * (1.0 - fx) + g(x1, y1) * fx) * fy,
    )
}

/// Where the profile across an edge at `p` (normal `n`, half-length `reach`) crosses the grey
/// level halfway between its two ends, nearest `p`; `None` on a weak or unreadable edge.
fn edge_crossing(
    grey: &[u8],
    side: usize,
    p: &nalgebra::Point2<f64>,
    n: &nalgebra::Vector2<f64>,
    reach: f64,
) -> Option<nalgebra::Point2<f64>> {
    let steps = (2.0 * reach / EDGE_PROFILE_STEP_PX).round() as usize;
    let mut profile = Vec::with_capacity(steps + 1);
    for j in 0..=steps {
        let o = -reach + j as f64 * EDGE_PROFILE_STEP_PX;
        let q = p + n * o;
        profile.push((o, grey_at(grey, side, q.x, q.y)?));
    }
    let ends = 3.min(profile.len() / 2);
    let lo = profile[..ends].iter().map(|v| v.1).sum::<f64>() / ends as f64;
    let hi = profile[profile.len() - ends..]
        .iter()
        .map(|v| v.1)
        .sum::<f64>()
        / ends as f64;
    if (hi - lo).abs() < MIN_EDGE_CONTRAST {
        return None;
    }
    let mid = 0.5 * (lo + hi);
    profile
        .windows(2)
        .filter(|w| (w[0].1 - mid) * (w[1].1 - mid) <= 0.0 && w[0].1 != w[1].1)
        .map(|w| w[0].0 + (mid - w[0].1) / (w[1].1 - w[0].1) * (w[1].0 - w[0].0))
        .min_by(|a, b| a.abs().total_cmp(&b.abs()))
        .map(|o| p + n * o)
}

/// A line through `points` by total least squares: a point on it and its direction.
fn fit_line(
    points: &[nalgebra::Point2<f64>],
) -> Option<(nalgebra::Point2<f64>, nalgebra::Vector2<f64>)> {
    if points.len() < MIN_EDGE_SAMPLES {
        return None;
    }
    let c = points
        .iter()
        .map(|p| p.coords)
        .sum::<nalgebra::Vector2<f64>>()
        / points.len() as f64;
    let mut m = nalgebra::Matrix2::<f64>::zeros();
    for p in points {
        let d = p.coords - c;
        m += d * d.transpose();
    }
    let eig = m.symmetric_eigen();
    let k = if eig.eigenvalues[0] >= eig.eigenvalues[1] {
        0
    } else {
        1
    };
    let d = eig.eigenvectors.column(k).into_owned();
    Some((nalgebra::Point2::from(c), d))
}

/// The marker's corners from its four border edges: points where each edge crosses mid-grey,
/// a line through each side's points, and the corners where adjacent lines meet. A blurred
/// square's edges stay where they are while its corners round inward, so corners found this
/// way are not pulled into the square (the detector's are, by a fraction of a pixel, which
/// shrinks the marker and lengthens its distance). `None` when an edge cannot be read; the
/// detector's corners then stand.
fn edge_corners(
    grey: &[u8],
    side: usize,
    corners: &[nalgebra::Point2<f64>; 4],
    cells: usize,
) -> Option<[nalgebra::Point2<f64>; 4]> {
    let mut lines = Vec::with_capacity(4);
    for k in 0..4 {
        let (a, b) = (corners[k], corners[(k + 1) % 4]);
        let along = b - a;
        let length = along.norm();
        if length < 4.0 * MIN_EDGE_SAMPLES as f64 {
            return None;
        }
        let t = along / length;
        let n = nalgebra::Vector2::new(-t.y, t.x);
        // The square's width across this edge, at the middle of the opposite edge.
        let opposite = nalgebra::center(&corners[(k + 2) % 4], &corners[(k + 3) % 4]);
        let across = (opposite - a).dot(&n).abs();
        let reach = (EDGE_PROFILE_CELLS * across / cells as f64).max(MIN_EDGE_PROFILE_PX);
        let samples = ((EDGE_SPAN.1 - EDGE_SPAN.0) * length).floor() as usize;
        let points: Vec<nalgebra::Point2<f64>> = (0..=samples)
            .filter_map(|j| {
                let p = a + t * (EDGE_SPAN.0 * length + j as f64);
                edge_crossing(grey, side, &p, &n, reach)
            })
            .collect();
        let (c, d) = fit_line(&points)?;
        let normal = nalgebra::Vector2::new(-d.y, d.x);
        let kept: Vec<nalgebra::Point2<f64>> = points
            .into_iter()
            .filter(|p| (p - c).dot(&normal).abs() <= MAX_EDGE_RESIDUAL_PX)
            .collect();
        lines.push(fit_line(&kept)?);
    }
    let mut out = *corners;
    for k in 0..4 {
        let (pa, da) = lines[(k + 3) % 4];
        let (pb, db) = lines[k];
        // pa + s da = pb + u db.
        let m = nalgebra::Matrix2::new(da.x, -db.x, da.y, -db.y);
        let s = m.try_inverse()? * (pb - pa);
        let corner = pa + da * s.x;
        if (corner - corners[k]).norm() > MAX_EDGE_CORNER_SHIFT_PX {
            return None;
        }
        out[k] = corner;
    }
    Some(out)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]

    use std::sync::Arc;

    use super::*;
    use kiwi_fixtures::markers::{aruco_texture_aligned, aruco_texture_side};
    use kiwi_fixtures::render::{Extras, LensRays, RenderOptions, Rigid32, WorldQuad, render};
    use kiwi_fixtures::scene::{Scene, SceneOptions};
    use kiwi_fixtures::unit::{LensModel, SimUnit};

    use nalgebra::Rotation3;

    const ID: usize = 3;

    /// A rear-lens frame of the marker (side `size_m`) at `cam_from_marker`, the lens at the
    /// origin in front of a plain backdrop.
    fn frame(rays: &LensRays, cam_from_marker: &Pose, size_m: f64, key: u64) -> ColorImage {
        let scene = Scene::new(1, SceneOptions::default());
        let side = aruco_texture_side(size_m);
        let texture = Arc::new(aruco_texture_aligned(ID, size_m, size_m / 200.0).unwrap());
        let corner = Pose::from_parts(
            Translation3::new(-side / 2.0, -side / 2.0, 0.0),
            UnitQuaternion::identity(),
        );
        let extras = Extras {
            quads: vec![WorldQuad {
                world_from_quad: Rigid32::from_pose(&(cam_from_marker * corner)),
                width: side as f32,
                height: side as f32,
                texture,
            }],
            hide_room: true,
            ..Extras::default()
        };
        let options = RenderOptions {
            noise_key: key,
            ..RenderOptions::default()
        };
        let img = render(
            &scene,
            rays,
            &|_t: f64| Pose::identity(),
            0.0,
            &extras,
            &options,
        );
        ColorImage::from_rgb(img.width() as usize, img.height() as usize, img.as_raw()).unwrap()
    }

    /// `cam_from_marker` at `distance` along the direction `theta` off the axis (azimuth
    /// `phi`), the face turned `tilt` away from looking straight at the lens, rolled by `roll`.
    fn placed(distance: f64, theta: f64, phi: f64, tilt: f64, roll: f64) -> Pose {
        let b = kiwi_core::camera::bearing_from_angles(theta, phi).into_inner();
        // The marker's roll about its normal follows this fixed construction (the scenes the
        // accuracy figures were measured on; docs/head.md gives another roll's worst case).
        let z = -b;
        let helper = if z.x.abs() < 0.9 {
            Vector3::x()
        } else {
            Vector3::y()
        };
        let x = helper.cross(&z).normalize();
        let facing =
            Rotation3::from_matrix_unchecked(nalgebra::Matrix3::from_columns(&[x, z.cross(&x), z]));
        let r = facing
            * Rotation3::from_axis_angle(&Vector3::x_axis(), tilt)
            * Rotation3::from_axis_angle(&Vector3::z_axis(), roll);
        Pose::from_parts(Translation3::from(b * distance), r.into())
    }

    fn sighting(
        finder: &MarkerFinder,
        rays: &LensRays,
        truth: &Pose,
        size_m: f64,
        key: u64,
    ) -> Option<SquarePoses> {
        let corners = finder.find(&frame(rays, truth, size_m, key)).unwrap()?;
        square_poses(&corners, size_m).unwrap()
    }

    fn errors(a: &Pose, b: &Pose) -> (f64, f64) {
        (
            (a.translation.vector - b.translation.vector).norm(),
            a.rotation.angle_to(&b.rotation),
        )
    }

    #[test]
    fn the_hat_marker_is_placed_within_a_centimetre_and_a_degree_across_the_field() {
        for model in [LensModel::Kb4, LensModel::Ds] {
            let unit = SimUnit::x5("H", 5, 960, model).unwrap();
            let camera = unit.lenses[1].camera.clone();
            let rays = LensRays::new(&camera);
            let finder = MarkerFinder::new(camera.clone(), "4x4_50", ID).unwrap();
            let mut worst = (0.0f64, 0.0f64);
            let mut k = 0;
            for (distance, theta) in [
                (0.35, 0.0),
                (0.45, 0.5),
                (0.6, 1.0),
                (0.4, 1.3),
                (0.7, 1.45),
            ] {
                for (phi, tilt, roll) in [(0.3, 0.5, 0.2), (2.2, -0.7, 1.9), (4.0, 0.35, -2.5)] {
                    k += 1;
                    let truth = placed(distance, theta, phi, tilt, roll);
                    let poses = sighting(&finder, &rays, &truth, 0.08, k).unwrap_or_else(|| {
                        panic!("{model:?}: not found at {distance} m, {theta} rad")
                    });
                    let resolved = resolve(&poses, None);
                    let pose = resolved.pose().unwrap_or_else(|| {
                        panic!("{model:?} {distance} m {theta} rad: {resolved:?}")
                    });
                    let (dp, dr) = errors(&pose.cam_from_marker, &truth);
                    worst = (worst.0.max(dp), worst.1.max(dr));
                    assert!(
                        dp < 0.01 && dr < 1f64.to_radians(),
                        "{model:?} {distance} m {theta} rad tilt {tilt}: {dp} m, {} deg (ratio {})",
                        dr.to_degrees(),
                        poses.ambiguity_ratio()
                    );
                }
            }
            eprintln!(
                "{model:?}: worst {:.2} mm, {:.3} deg",
                worst.0 * 1e3,
                worst.1.to_degrees()
            );
        }
    }

    #[test]
    fn the_row_fraction_is_the_marker_centre_row() {
        let unit = SimUnit::x5("H", 5, 321, LensModel::Kb4).unwrap();
        let camera = unit.lenses[1].camera.clone();
        let finder = MarkerFinder::new(camera.clone(), "4x4_50", ID).unwrap();
        for (theta, phi) in [(0.0, 0.0), (0.8, std::f64::consts::FRAC_PI_2), (0.8, -1.2)] {
            let pose = placed(0.5, theta, phi, 0.3, 0.1);
            let corners =
                marker_corners(0.08).map(|m| (pose * nalgebra::Point3::from(m)).coords.normalize());
            let centre = camera
                .project(&(pose.translation.vector.normalize()))
                .unwrap();
            let got = finder.row_fraction(&corners).unwrap();
            // The corners' mean bearing is within a fraction of a pixel of the centre's.
            assert!(
                (got * 320.0 - centre.y).abs() < 0.5,
                "{got} vs row {}",
                centre.y
            );
        }
        // A frame of another size is refused, naming both sizes.
        let small = ColorImage {
            width: 100,
            height: 100,
            bgr: vec![0; 100 * 100 * 3],
        };
        let err = finder.find(&small).unwrap_err().to_string();
        assert!(err.contains("100x100") && err.contains("321x321"), "{err}");
    }

    #[test]
    fn a_small_far_nearly_frontal_marker_never_gets_the_wrong_branch() {
        let unit = SimUnit::x5("H", 6, 960, LensModel::Kb4).unwrap();
        let camera = unit.lenses[1].camera.clone();
        let rays = LensRays::new(&camera);
        let finder = MarkerFinder::new(camera.clone(), "4x4_50", ID).unwrap();
        let (mut ambiguous, mut by_previous, mut seen) = (0, 0, 0);
        // The accepted pose is the branch nearer the truth (at this size even the right branch
        // may be a few degrees off; the wrong one is mirrored about the line of sight).
        let right_branch = |p: &SquarePose, poses: &SquarePoses, truth: &Pose| {
            let other = if p == &poses.best {
                &poses.other
            } else {
                &poses.best
            };
            p.cam_from_marker.rotation.angle_to(&truth.rotation)
                < other.cam_from_marker.rotation.angle_to(&truth.rotation)
        };
        for k in 0..24u64 {
            let tilt = 0.03 + 0.01 * (k % 6) as f64;
            let truth = placed(
                1.0,
                0.1 * (k % 4) as f64,
                0.7 * k as f64,
                tilt,
                0.4 * k as f64,
            );
            let Some(poses) = sighting(&finder, &rays, &truth, 0.06, 100 + k) else {
                continue;
            };
            seen += 1;
            // Alone: the right branch or nothing.
            match resolve(&poses, None) {
                Resolved::Clear(p) => {
                    assert!(
                        right_branch(&p, &poses, &truth),
                        "wrong branch accepted: k {k} tilt {tilt} ratio {} errors {} / {} rad",
                        poses.ambiguity_ratio(),
                        poses.best.error_rad,
                        poses.other.error_rad
                    );
                }
                Resolved::Ambiguous => ambiguous += 1,
                other @ (Resolved::ByPrevious(_) | Resolved::BadFit) => {
                    panic!("unexpected {other:?}")
                }
            }
            // With the previous sighting's pose, 1° off the truth: the right branch or nothing.
            let previous = Pose::from_parts(
                truth.translation,
                truth.rotation * UnitQuaternion::from_scaled_axis(Vector3::new(0.0, 0.0175, 0.0)),
            );
            if let Some(p) = resolve(&poses, Some(&previous)).pose() {
                assert!(
                    right_branch(p, &poses, &truth),
                    "wrong branch by the previous pose"
                );
                by_previous += 1;
            }
        }
        eprintln!(
            "{seen} seen, {ambiguous} ambiguous alone, {by_previous} accepted with the previous \
             pose"
        );
        assert!(seen >= 20, "the marker is found: {seen} of 24");
        assert!(ambiguous > 0, "the test provokes the ambiguity");
        // Every sighting here is ambiguous alone or clear, so a pose accepted with the previous
        // pose beyond the clear ones came from it (and was the right branch).
        assert!(
            by_previous > seen - ambiguous,
            "the previous pose resolves an ambiguous sighting"
        );
    }
}
