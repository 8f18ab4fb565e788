//! The tool's body ArUco tag seen through the fisheye lens. Every OpenCV ArUco call of the
//! backend is in this module (the API moved between OpenCV 4.6 and 4.7; BUILD-NOTES.md).
//!
//! The tag sits far off the optical axis, where a 190° lens squeezes it, so it is detected on
//! a virtual perspective view aimed at it and resampled through the lens model
//! ([`TagView`]); the corners come back as bearing vectors in the lens frame, never as
//! pinhole coordinates of the fisheye image.

use kiwi_core::camera::{Camera, CameraModel};
use nalgebra::{Point2, Rotation3, Unit, Vector3};
use opencv::core::{Mat, Point2f, Vector};
use opencv::prelude::*;

use super::estimate::{ChannelOrder, ImageView};
use crate::error::{BackendError, Result};
use crate::vision::geometry::aimed_at;

/// Largest side of the virtual view (px): bounds memory and detection time.
const MAX_VIEW_SIDE: usize = 640;
/// Smallest side of the virtual view (px): the detector needs a few pixels per tag cell.
const MIN_VIEW_SIDE: usize = 48;

/// A virtual perspective camera aimed at the tag, with the source pixel of each view pixel.
pub struct TagView {
    /// `front_from_view` rotation (view z = the aiming direction).
    front_from_view: Rotation3<f64>,
    /// Focal length of the view (px per unit tangent).
    focal: f64,
    /// View side (px).
    side: usize,
    /// Source pixel of every view pixel (NaN outside the lens's image).
    map: Vec<[f32; 2]>,
    /// Source image size.
    src: (usize, usize),
}

impl TagView {
    /// A view of `half_angle` (rad) around `direction` (lens frame) sampled at `px_per_rad`.
    pub fn new(
        camera: &Camera,
        direction: &Vector3<f64>,
        half_angle: f64,
        px_per_rad: f64,
    ) -> Result<Self> {
        let bad = |message: String| BackendError::Input {
            path: "tool definition (marker)".into(),
            message,
        };
        let z = direction
            .try_normalize(1e-12)
            .ok_or_else(|| bad("the tag direction is zero".into()))?;
        if !(half_angle.is_finite() && half_angle > 0.0 && half_angle < 1.2) {
            return Err(bad(format!(
                "tag view half-angle {half_angle} rad is out of range: check marker.size_m"
            )));
        }
        // The detector does not care about the view's roll.
        let front_from_view = aimed_at(&z);
        let tan = half_angle.tan();
        let side = ((2.0 * tan * px_per_rad).ceil() as usize).clamp(MIN_VIEW_SIDE, MAX_VIEW_SIDE);
        let focal = side as f64 / (2.0 * tan);
        let (sw, sh) = camera.resolution();
        let mut view = Self {
            front_from_view,
            focal,
            side,
            map: Vec::with_capacity(side * side),
            src: (sw as usize, sh as usize),
        };
        for j in 0..side {
            for i in 0..side {
                let ray = view.bearing(i as f64, j as f64);
                match camera.project(&ray) {
                    Some(p)
                        if p.x >= 0.0
                            && p.y >= 0.0
                            && p.x <= f64::from(sw) - 1.0
                            && p.y <= f64::from(sh) - 1.0 =>
                    {
                        view.map.push([p.x as f32, p.y as f32]);
                    }
                    _ => view.map.push([f32::NAN, f32::NAN]),
                }
            }
        }
        Ok(view)
    }

    /// Bearing (unit, lens frame) of a view pixel position.
    pub fn bearing(&self, x: f64, y: f64) -> Vector3<f64> {
        let c = (self.side as f64 - 1.0) / 2.0;
        let v = Vector3::new((x - c) / self.focal, (y - c) / self.focal, 1.0);
        (self.front_from_view * v).normalize()
    }

    /// View side (px).
    pub fn side(&self) -> usize {
        self.side
    }

    /// The view as 8-bit grey, bilinear through the lens model (mid-grey outside the image).
    pub fn grey(&self, image: &ImageView<'_>) -> Option<Vec<u8>> {
        if image.width != self.src.0 || image.height != self.src.1 {
            return None;
        }
        let (ri, bi) = match image.order {
            ChannelOrder::Rgb => (0, 2),
            ChannelOrder::Bgr => (2, 0),
        };
        let stride = image.width * 3;
        let data = image.data;
        let luma = |xx: usize, yy: usize| {
            let k = yy * stride + xx * 3;
            0.299 * f32::from(data[k + ri])
                + 0.587 * f32::from(data[k + 1])
                + 0.114 * f32::from(data[k + bi])
        };
        Some(
            self.map
                .iter()
                .map(|&[x, y]| {
                    if !x.is_finite() {
                        return 128;
                    }
                    let (x0, y0) = (x.floor() as usize, y.floor() as usize);
                    let (x1, y1) = (
                        (x0 + 1).min(image.width - 1),
                        (y0 + 1).min(image.height - 1),
                    );
                    let (fx, fy) = (x - x0 as f32, y - y0 as f32);
                    let v = (luma(x0, y0) * (1.0 - fx) + luma(x1, y0) * fx) * (1.0 - fy)
                        + (luma(x0, y1) * (1.0 - fx) + luma(x1, y1) * fx) * fy;
                    v.round().clamp(0.0, 255.0) as u8
                })
                .collect(),
        )
    }
}

/// The OpenCV dictionary of a tool definition's `marker.dictionary` name.
fn dictionary(name: &str) -> Result<opencv::aruco::PREDEFINED_DICTIONARY_NAME> {
    use opencv::aruco::PREDEFINED_DICTIONARY_NAME as D;
    let d = match name.to_ascii_lowercase().as_str() {
        "4x4_50" => D::DICT_4X4_50,
        "4x4_100" => D::DICT_4X4_100,
        "4x4_250" => D::DICT_4X4_250,
        "4x4_1000" => D::DICT_4X4_1000,
        "5x5_50" => D::DICT_5X5_50,
        "5x5_100" => D::DICT_5X5_100,
        "5x5_250" => D::DICT_5X5_250,
        "6x6_50" => D::DICT_6X6_50,
        "6x6_250" => D::DICT_6X6_250,
        "original" => D::DICT_ARUCO_ORIGINAL,
        other => {
            return Err(BackendError::Input {
                path: "tool definition".into(),
                message: format!(
                    "marker.dictionary `{other}` is not supported: use {DICTIONARY_NAMES}"
                ),
            });
        }
    };
    Ok(d)
}

/// The ArUco dictionaries KIWI reads, by name.
pub const DICTIONARY_NAMES: &str =
    "4x4_50, 4x4_100, 4x4_250, 4x4_1000, 5x5_50, 5x5_100, 5x5_250, 6x6_50, 6x6_250 or original";

/// How many markers the named dictionary holds (`None` for a name it does not know).
pub fn dictionary_size(name: &str) -> Option<usize> {
    let lower = name.to_ascii_lowercase();
    if lower == "original" {
        return Some(1024);
    }
    dictionary(name).ok()?;
    lower.split('_').nth(1)?.parse().ok()
}

#[allow(clippy::needless_pass_by_value)] // used as `map_err(cv_err)`
fn cv_err(e: opencv::Error) -> BackendError {
    BackendError::Input {
        path: "opencv aruco".into(),
        message: e.to_string(),
    }
}

/// Finds one tag id in views of the tag. Holds no OpenCV object, so threads can share it
/// (each detection builds its own dictionary handle, a table lookup).
pub struct TagDetector {
    dict: opencv::aruco::PREDEFINED_DICTIONARY_NAME,
    id: i32,
}

impl TagDetector {
    /// Cells across one of the dictionary's markers: its bits plus the black border on each
    /// side (6 for 4x4, 7 for 5x5 and the original ArUco set, 8 for 6x6).
    pub fn marker_cells(&self) -> usize {
        use opencv::aruco::PREDEFINED_DICTIONARY_NAME as D;
        match self.dict {
            D::DICT_4X4_50 | D::DICT_4X4_100 | D::DICT_4X4_250 | D::DICT_4X4_1000 => 6,
            D::DICT_6X6_50 | D::DICT_6X6_100 | D::DICT_6X6_250 | D::DICT_6X6_1000 => 8,
            // 5x5 and the original set: the only others `dictionary` gives.
            _ => 7,
        }
    }

    /// A detector of tag `id` of the named dictionary.
    pub fn new(dictionary_name: &str, id: usize) -> Result<Self> {
        Ok(Self {
            dict: dictionary(dictionary_name)?,
            id: i32::try_from(id).map_err(|_| BackendError::Input {
                path: "tool definition".into(),
                message: format!("marker.id {id} is out of range"),
            })?,
        })
    }

    /// The tag's corners as bearings (lens frame) in OpenCV's order — the printed tag's
    /// top-left, top-right, bottom-right, bottom-left — or `None` when it is not seen.
    pub fn detect(
        &self,
        view: &TagView,
        image: &ImageView<'_>,
    ) -> Result<Option<[Vector3<f64>; 4]>> {
        let Some(grey) = view.grey(image) else {
            return Ok(None);
        };
        let side = view.side();
        Ok(self
            .detect_grey(&grey, side, side)?
            .map(|c| c.map(|p| view.bearing(p.x, p.y))))
    }

    /// The tag's corners (pixels of `grey`, `width × height` 8-bit, rows top to bottom) in
    /// OpenCV's order, or `None` when it is not seen.
    pub fn detect_grey(
        &self,
        grey: &[u8],
        width: usize,
        height: usize,
    ) -> Result<Option<[Point2<f64>; 4]>> {
        if grey.len() != width * height || width == 0 {
            return Ok(None);
        }
        let mat =
            Mat::new_rows_cols_with_data(height as i32, width as i32, grey).map_err(cv_err)?;
        let dict = opencv::aruco::get_predefined_dictionary(self.dict).map_err(cv_err)?;
        let mut params = opencv::aruco::DetectorParameters::create().map_err(cv_err)?;
        params.set_corner_refinement_method(opencv::aruco::CORNER_REFINE_SUBPIX);
        let mut corners: Vector<Vector<Point2f>> = Vector::new();
        let mut ids: Vector<i32> = Vector::new();
        let mut rejected: Vector<Vector<Point2f>> = Vector::new();
        opencv::aruco::detect_markers(&mat, &dict, &mut corners, &mut ids, &params, &mut rejected)
            .map_err(cv_err)?;
        for (k, id) in ids.iter().enumerate() {
            if id != self.id {
                continue;
            }
            let c = corners.get(k).map_err(cv_err)?;
            if c.len() != 4 {
                continue;
            }
            let mut out = [Point2::origin(); 4];
            for (o, p) in out.iter_mut().zip(c.iter()) {
                *o = Point2::new(f64::from(p.x), f64::from(p.y));
            }
            return Ok(Some(out));
        }
        Ok(None)
    }
}

/// Where a bearing lands in the source image (for residuals in pixels).
pub fn project_bearing(camera: &Camera, b: &Vector3<f64>) -> Option<Point2<f64>> {
    camera.project(&Unit::new_normalize(*b).into_inner())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cells_count_the_bits_and_the_border() {
        let cells = |name: &str| TagDetector::new(name, 0).unwrap().marker_cells();
        assert_eq!(cells("4x4_50"), 6);
        assert_eq!(cells("5X5_100"), 7);
        assert_eq!(cells("6x6_250"), 8);
        assert_eq!(cells("original"), 7);
        assert_eq!(dictionary_size("4x4_250"), Some(250));
    }
}
