//! Rectified motion stereo (semi-global matching, Hirschmüller 2008) on two frames of one
//! front lens: both are resampled through the fisheye model into one virtual pinhole that
//! looks down with its x axis along the baseline, so the ground's matches lie on rows; OpenCV's
//! SGBM gives the disparities, each matched pixel a height below the reference camera.

use nalgebra::{Matrix3, Point3, Vector3};
use opencv::core::Mat;
use opencv::prelude::*;

use kiwi_core::camera::CameraModel;

use crate::error::{BackendError, Result};

use super::view::{HeightVotes, PosedView, Surface};

/// What the stereo channel matches and how.
#[derive(Debug, Clone, Copy, serde::Serialize, serde::Deserialize)]
pub struct StereoOptions {
    /// Nearest surface sought, below the reference camera (m).
    pub h_min_m: f64,
    /// Farthest surface sought (m).
    pub h_max_m: f64,
    /// Half field of the rectified view (rad), around its axis.
    pub half_fov_rad: f64,
    /// Rectified image side as a share of the lens image's width.
    pub size_share: f64,
    /// A surface needs this share of the matched pixels.
    pub min_support: f64,
    /// Histogram bin of the votes (m).
    pub bin_m: f64,
}

impl Default for StereoOptions {
    fn default() -> Self {
        Self {
            h_min_m: 0.15,
            h_max_m: 2.6,
            half_fov_rad: 45f64.to_radians(),
            size_share: 0.6,
            min_support: 0.06,
            bin_m: 0.02,
        }
    }
}

/// SGBM's matching block (px, odd).
const BLOCK: i32 = 5;
/// Most disparities searched (OpenCV's cost volume grows with it); the nearest heights are
/// left out beyond it.
const MAX_DISPARITIES: i32 = 256;
/// SGBM's uniqueness margin (%): the best cost must beat the second by this much.
const UNIQUENESS_PERCENT: i32 = 10;
/// Speckle filter: blobs of fewer pixels than this with disparities within
/// [`SPECKLE_RANGE`] are removed.
const SPECKLE_WINDOW: i32 = 60;
/// See [`SPECKLE_WINDOW`] (disparity units of 1/16 px × 16).
const SPECKLE_RANGE: i32 = 2;

/// A stereo result: the votes and the surfaces found.
#[derive(Debug, Clone)]
pub struct StereoResult {
    /// Votes per height below the reference camera.
    pub votes: HeightVotes,
    /// Surfaces, lowest first.
    pub surfaces: Vec<Surface>,
}

#[allow(clippy::needless_pass_by_value)] // a `map_err` adapter
fn cv_err(e: opencv::Error) -> BackendError {
    BackendError::Vision {
        context: "motion stereo".into(),
        message: format!("OpenCV failed: {e}"),
    }
}

/// Match `reference` with `other` (frames of one lens) and vote the heights of the matches.
/// `None` when the baseline is too short for any disparity in the band.
pub fn stereo(
    reference: &PosedView<'_>,
    other: &PosedView<'_>,
    o: &StereoOptions,
) -> Result<Option<StereoResult>> {
    let c_ref = reference.middle().translation.vector;
    let c_other = other.middle().translation.vector;
    let b = c_other - c_ref;
    let baseline = b.norm();
    let camera_z = c_ref.z;
    let mut votes = HeightVotes::new(o.h_min_m, o.h_max_m, o.bin_m);
    if baseline < 1e-3 {
        return Ok(None);
    }
    // Rectifying rotation: x along the baseline, z as close to straight down as it allows.
    let x = b / baseline;
    let down = -Vector3::z();
    let z = down - x * down.dot(&x);
    if z.norm() < 0.3 {
        // A mostly vertical baseline: no downward rectification.
        return Ok(None);
    }
    let z = z.normalize();
    let y = z.cross(&x);
    let scene_from_rect = Matrix3::from_columns(&[x, y, z]);
    let (w, _) = reference.camera.resolution();
    let side = ((f64::from(w) * o.size_share).round() as i32).max(32);
    let f = f64::from(side) / 2.0 / o.half_fov_rad.tan();
    let centre = f64::from(side - 1) / 2.0;
    let d_min = (f * baseline / o.h_max_m).floor().max(0.0) as i32;
    let d_max = (f * baseline / o.h_min_m).ceil() as i32;
    let span = ((d_max - d_min).clamp(16, MAX_DISPARITIES) + 15) / 16 * 16;
    let rectify = |view: &PosedView<'_>, origin: &Vector3<f64>| -> Vec<u8> {
        let mut out = vec![0u8; (side * side) as usize];
        for r in 0..side {
            for c in 0..side {
                let ray = scene_from_rect
                    * Vector3::new(
                        (f64::from(c) - centre) / f,
                        (f64::from(r) - centre) / f,
                        1.0,
                    );
                let p = Point3::from(origin + ray);
                if let Some(q) = view.project(&p)
                    && let Some(v) = view.sample(q.x, q.y)
                {
                    out[(r * side + c) as usize] = v.round().clamp(0.0, 255.0) as u8;
                }
            }
        }
        out
    };
    let left = rectify(reference, &c_ref);
    let right = rectify(other, &c_other);
    let left_mat = Mat::new_rows_cols_with_data(side, side, &left).map_err(cv_err)?;
    let right_mat = Mat::new_rows_cols_with_data(side, side, &right).map_err(cv_err)?;
    let mut matcher = opencv::calib3d::StereoSGBM::create(
        d_min,
        span,
        BLOCK,
        8 * BLOCK * BLOCK,
        32 * BLOCK * BLOCK,
        1,
        31,
        UNIQUENESS_PERCENT,
        SPECKLE_WINDOW,
        SPECKLE_RANGE,
        opencv::calib3d::StereoSGBM_MODE_SGBM,
    )
    .map_err(cv_err)?;
    let mut disparity = Mat::default();
    matcher
        .compute(&left_mat, &right_mat, &mut disparity)
        .map_err(cv_err)?;
    let margin = BLOCK / 2 + 1;
    for r in margin..side - margin {
        for c in margin..side - margin {
            let i = (r * side + c) as usize;
            if left[i] == 0 || right[i] == 0 {
                continue;
            }
            let raw = *disparity.at_2d::<i16>(r, c).map_err(cv_err)?;
            votes.voters += 1;
            // SGBM marks a pixel it could not match with (d_min - 1) · 16.
            if i32::from(raw) < d_min * 16 || raw <= 0 {
                continue;
            }
            let d = f64::from(raw) / 16.0;
            let depth = f * baseline / d;
            let ray = scene_from_rect
                * Vector3::new(
                    (f64::from(c) - centre) / f,
                    (f64::from(r) - centre) / f,
                    1.0,
                );
            let p = c_ref + ray * depth;
            votes.vote(camera_z - p.z);
        }
    }
    let surfaces = votes.surfaces(o.min_support, camera_z);
    Ok(Some(StereoResult { votes, surfaces }))
}
