//! Aprilgrid corner detection in fisheye images, and the corners file (`corners.json`) that
//! `kiwi-calib detect` writes and `kiwi-calib intrinsics --corners` reads.
//!
//! Detection: the `aprilgrid` crate finds and decodes the tags (saddle points of the junction
//! squares, so it works on strongly distorted tags); each corner is then refined with OpenCV's
//! `cornerSubPix` on a 5 × 5 window, as Kalibr does, and a tag whose refinement moves any corner
//! by more than √1.5 px is dropped. Tags touching the image border are dropped. Images run in
//! parallel (rayon) with a progress bar.
//!
//! # Corners file
//!
//! ```json
//! {
//!   "format": "kiwi-corners", "version": 1,
//!   "target": {"cols": 6, "rows": 6, "tag_size_m": 0.088, "spacing": 0.3},   // or null
//!   "images": [
//!     {"name": "000000.png", "width": 960, "height": 960, "tags": [0, 1, 7],
//!      "corners": [{"id": 0, "board": [0.0, 0.0, 0.0], "pixel": [412.31, 388.02]}, ...]}
//!   ]
//! }
//! ```
//!
//! `id` is the target point id (Kalibr numbering for aprilgrids, any unique number for other
//! targets), `board` its position on the planar board in metres (z = 0), `pixel` the detected
//! corner with pixel centres at integer coordinates. `target` is informative: a corners file of
//! any planar target (a chessboard from OpenCV, corners from Kalibr) needs no target yaml.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

use image::{DynamicImage, GrayImage};
use indicatif::{ProgressBar, ProgressStyle};
use nalgebra::{Point2, Vector3};
use opencv::core::{Mat, Point2f, Size, TermCriteria, TermCriteria_Type, Vector};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use kiwi_core::camera::{Camera, CameraModel};
use kiwi_core::io::write_atomic;

use crate::error::{CalibError, Result};
use crate::target::AprilGridTarget;

/// Tags with a corner closer than this to the image edge are dropped (Kalibr's
/// `minBorderDistance`): their corners are cut by the border.
const MIN_BORDER_DISTANCE_PX: f64 = 4.0;
/// Half window of the subpixel refinement (Kalibr: `winSize (2, 2)`, a 5 × 5 window).
const SUBPIX_HALF_WINDOW: i32 = 2;
/// A tag is dropped if refinement moves any of its corners by more than this (Kalibr's
/// `maxSubpixDisplacement2 = 1.5` px²): the saddle and the refined corner disagree.
const MAX_SUBPIX_DISPLACEMENT_PX: f64 = 1.224_744_871_391_589;
/// Iterations and step threshold of the subpixel refinement (Kalibr: 30, 0.1).
const SUBPIX_MAX_ITERATIONS: i32 = 30;
const SUBPIX_EPS: f64 = 0.1;
/// Fewest tags for an image to count: fewer give too few corners to fix the board pose.
pub const MIN_TAGS_PER_IMAGE: usize = 2;
/// Image file extensions read from an images folder.
const IMAGE_EXTENSIONS: [&str; 6] = ["png", "jpg", "jpeg", "tif", "tiff", "bmp"];

/// One detected (or imported) corner.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Corner {
    /// Target point id.
    pub id: u32,
    /// Position on the board (m), z = 0 for a planar target.
    pub board: [f64; 3],
    /// Pixel (pixel centres at integers).
    pub pixel: [f64; 2],
}

impl Corner {
    /// Board position as a vector.
    pub fn board_point(&self) -> Vector3<f64> {
        Vector3::new(self.board[0], self.board[1], self.board[2])
    }

    /// Pixel as a point.
    pub fn pixel_point(&self) -> Point2<f64> {
        Point2::new(self.pixel[0], self.pixel[1])
    }
}

/// The corners found in one image.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ImageCorners {
    /// Image file name (relative to the images folder).
    pub name: String,
    /// Image width (px).
    pub width: u32,
    /// Image height (px).
    pub height: u32,
    /// Tag ids found (empty for non-tag targets).
    #[serde(default)]
    pub tags: Vec<u32>,
    /// Corners.
    pub corners: Vec<Corner>,
}

/// A corners file: every image's corners, with the target they belong to if known.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CornerSet {
    /// Always `kiwi-corners`.
    pub format: String,
    /// Format version (1).
    pub version: u32,
    /// The aprilgrid the corners come from, if any.
    #[serde(default)]
    pub target: Option<AprilGridTarget>,
    /// Images in order.
    pub images: Vec<ImageCorners>,
}

/// Format name written into corners files.
pub const CORNERS_FORMAT: &str = "kiwi-corners";

impl CornerSet {
    /// An empty set for a target.
    pub fn new(target: Option<AprilGridTarget>) -> Self {
        Self {
            format: CORNERS_FORMAT.into(),
            version: 1,
            target,
            images: Vec::new(),
        }
    }

    /// Total corners over all images.
    pub fn total_corners(&self) -> usize {
        self.images.iter().map(|i| i.corners.len()).sum()
    }

    /// Read and validate a corners file.
    pub fn load(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|e| CalibError::Input {
            path: path.to_path_buf(),
            message: format!("cannot read the corners file: {e}"),
        })?;
        let set: Self = serde_json::from_str(&text).map_err(|e| CalibError::Input {
            path: path.to_path_buf(),
            message: format!(
                "not a kiwi corners file ({e}); expected {{\"format\": \"kiwi-corners\", \
                 \"version\": 1, \"images\": [{{\"name\", \"width\", \"height\", \"corners\": \
                 [{{\"id\", \"board\": [x, y, z], \"pixel\": [u, v]}}]}}]}}"
            ),
        })?;
        set.validate(path)?;
        Ok(set)
    }

    /// Check format, sizes, finiteness, unique ids per image and consistent image sizes.
    pub fn validate(&self, path: &Path) -> Result<()> {
        let bad = |message: String| {
            Err(CalibError::Input {
                path: path.to_path_buf(),
                message,
            })
        };
        if self.format != CORNERS_FORMAT || self.version != 1 {
            return bad(format!(
                "format '{}' version {}: expected '{CORNERS_FORMAT}' version 1",
                self.format, self.version
            ));
        }
        let mut size = None;
        for img in &self.images {
            if img.width == 0 || img.height == 0 {
                return bad(format!("image {}: width and height must be > 0", img.name));
            }
            match size {
                None => size = Some((img.width, img.height)),
                Some(s) if s != (img.width, img.height) => {
                    return bad(format!(
                        "image {} is {}x{} but earlier images are {}x{}; calibrate one lens and \
                         one resolution at a time",
                        img.name, img.width, img.height, s.0, s.1
                    ));
                }
                Some(_) => {}
            }
            let mut ids = BTreeSet::new();
            for c in &img.corners {
                if !c.board.iter().chain(c.pixel.iter()).all(|v| v.is_finite()) {
                    return bad(format!(
                        "image {}, corner {}: board position and pixel must be finite numbers",
                        img.name, c.id
                    ));
                }
                if c.board[2].abs() > 1e-9 {
                    return bad(format!(
                        "image {}, corner {}: board z is {} but the target must be planar \
                         (z = 0)",
                        img.name, c.id, c.board[2]
                    ));
                }
                if !ids.insert(c.id) {
                    return bad(format!(
                        "image {}: corner id {} appears twice; ids must be unique per image",
                        img.name, c.id
                    ));
                }
            }
        }
        Ok(())
    }

    /// Write the corners file atomically (pretty JSON).
    pub fn save(&self, path: &Path) -> Result<()> {
        let text = serde_json::to_string_pretty(self)
            .map_err(|e| CalibError::Internal(format!("corners do not serialize: {e}")))?;
        write_atomic(path, text.as_bytes())?;
        Ok(())
    }

    /// The `--json` summary of `detect`: `{"images": [{"name", "tags", "corners"}],
    /// "total_corners"}`.
    pub fn summary_json(&self) -> serde_json::Value {
        serde_json::json!({
            "images": self.images.iter().map(|i| serde_json::json!({
                "name": i.name,
                "tags": i.tags.len(),
                "corners": i.corners.len(),
            })).collect::<Vec<_>>(),
            "total_corners": self.total_corners(),
        })
    }
}

/// The image files of a folder (or of its `frames/` subfolder), sorted by name.
pub fn list_images(dir: &Path) -> Result<Vec<PathBuf>> {
    let read = |d: &Path| -> Result<Vec<PathBuf>> {
        let entries = std::fs::read_dir(d).map_err(|e| CalibError::Input {
            path: d.to_path_buf(),
            message: format!("cannot read the images folder: {e}"),
        })?;
        let mut files: Vec<PathBuf> = entries
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| {
                p.is_file()
                    && p.extension().and_then(|e| e.to_str()).is_some_and(|e| {
                        IMAGE_EXTENSIONS.contains(&e.to_ascii_lowercase().as_str())
                    })
            })
            .collect();
        files.sort();
        Ok(files)
    };
    let mut files = read(dir)?;
    if files.is_empty() && dir.join("frames").is_dir() {
        files = read(&dir.join("frames"))?;
    }
    if files.is_empty() {
        return Err(CalibError::Input {
            path: dir.to_path_buf(),
            message: format!(
                "no images ({}) in this folder or its frames/ subfolder; point --images at the \
                 folder of calibration frames",
                IMAGE_EXTENSIONS.join(", ")
            ),
        });
    }
    Ok(files)
}

/// Load an image as 8-bit grey; 16-bit images are stretched between their 0.5 % and 99.5 %
/// levels so dark raw frames (TUM-VI) keep their contrast.
pub fn load_gray(path: &Path) -> Result<GrayImage> {
    let img = image::open(path).map_err(|e| CalibError::Input {
        path: path.to_path_buf(),
        message: format!("cannot read the image ({e}); remove it or convert it to PNG"),
    })?;
    Ok(to_gray8(&img))
}

fn to_gray8(img: &DynamicImage) -> GrayImage {
    match img {
        DynamicImage::ImageLuma16(_)
        | DynamicImage::ImageLumaA16(_)
        | DynamicImage::ImageRgb16(_)
        | DynamicImage::ImageRgba16(_) => {
            let g = img.to_luma16();
            let mut values: Vec<u16> = g.as_raw().clone();
            values.sort_unstable();
            let n = values.len();
            if n == 0 {
                return img.to_luma8();
            }
            let lo = f64::from(values[n / 200]);
            let hi = f64::from(values[(n - 1) - n / 200]).max(lo + 1.0);
            GrayImage::from_fn(g.width(), g.height(), |x, y| {
                let v = (f64::from(g.get_pixel(x, y)[0]) - lo) / (hi - lo);
                image::Luma([(v.clamp(0.0, 1.0) * 255.0).round() as u8])
            })
        }
        _ => img.to_luma8(),
    }
}

/// Corner order the `aprilgrid` crate returns, as Kalibr corner indices (0 BL, 1 BR, 2 TR, 3 TL
/// in the board frame); measured against the simulator's exact corners.
const APRILGRID_CRATE_TO_KALIBR: [usize; 4] = [0, 1, 2, 3];

/// Aprilgrid detector for one target.
pub struct Detector {
    target: AprilGridTarget,
    inner: aprilgrid::detector::TagDetector,
}

/// What one image gave.
#[derive(Debug, Clone)]
pub struct Detection {
    /// Tags kept.
    pub tags: Vec<u32>,
    /// Corners kept.
    pub corners: Vec<Corner>,
    /// Tags dropped by the border or refinement checks.
    pub dropped_tags: usize,
}

impl Detector {
    /// A detector for an aprilgrid.
    pub fn new(target: AprilGridTarget) -> Self {
        Self {
            target,
            inner: aprilgrid::detector::TagDetector::new(
                &aprilgrid::TagFamily::T36H11,
                Some(aprilgrid::detector::DetectorParams {
                    tag_spacing_ratio: target.spacing as f32,
                    ..aprilgrid::detector::DetectorParams::default_params()
                }),
            ),
        }
    }

    /// Detect the target's corners in a grey image.
    pub fn detect(&self, gray: &GrayImage) -> Result<Detection> {
        let tags = self.inner.detect(&DynamicImage::ImageLuma8(gray.clone()));
        let (w, h) = (f64::from(gray.width()), f64::from(gray.height()));
        let mut ids: Vec<u32> = tags
            .keys()
            .copied()
            .filter(|&id| (id as usize) < self.target.tag_count())
            .collect();
        ids.sort_unstable();
        let mut raw: Vec<(u32, [Point2<f64>; 4])> = Vec::new();
        let mut dropped = 0;
        for id in ids {
            let Some(quad) = tags.get(&id) else { continue };
            let pts = quad.map(|(x, y)| Point2::new(f64::from(x), f64::from(y)));
            let inside = pts.iter().all(|p| {
                p.x >= MIN_BORDER_DISTANCE_PX
                    && p.y >= MIN_BORDER_DISTANCE_PX
                    && p.x <= w - 1.0 - MIN_BORDER_DISTANCE_PX
                    && p.y <= h - 1.0 - MIN_BORDER_DISTANCE_PX
            });
            if inside && pts.iter().all(|p| p.x.is_finite() && p.y.is_finite()) {
                raw.push((id, pts));
            } else {
                dropped += 1;
            }
        }
        self.refine_and_number(gray, &raw, dropped)
    }

    /// Refine the tags' corners, drop tags whose refinement moved too far, number the corners.
    fn refine_and_number(
        &self,
        gray: &GrayImage,
        raw: &[(u32, [Point2<f64>; 4])],
        dropped: usize,
    ) -> Result<Detection> {
        if raw.is_empty() {
            return Ok(Detection {
                tags: Vec::new(),
                corners: Vec::new(),
                dropped_tags: dropped,
            });
        }
        let refined = refine_corners(gray, raw)?;
        let mut out = Detection {
            tags: Vec::new(),
            corners: Vec::new(),
            dropped_tags: dropped,
        };
        for ((id, pts), new) in raw.iter().zip(refined.chunks(4)) {
            let moved_too_far = pts
                .iter()
                .zip(new)
                .any(|(a, b)| (a - b).norm() > MAX_SUBPIX_DISPLACEMENT_PX);
            if moved_too_far {
                out.dropped_tags += 1;
                continue;
            }
            out.tags.push(*id);
            for (j, p) in new.iter().enumerate() {
                let point = self
                    .target
                    .corner_point_id(*id as usize, APRILGRID_CRATE_TO_KALIBR[j]);
                let b = self.target.point(point);
                out.corners.push(Corner {
                    id: point as u32,
                    board: [b.x, b.y, b.z],
                    pixel: [p.x, p.y],
                });
            }
        }
        out.corners.sort_by_key(|c| c.id);
        Ok(out)
    }
}

impl Detector {
    /// Tags found in perspective views rendered through `camera` around the periphery, that
    /// `known` does not already hold; corners mapped back and refined in the original image.
    pub fn detect_rectified(
        &self,
        gray: &GrayImage,
        camera: &Camera,
        known: &Detection,
    ) -> Result<Detection> {
        let mut have: BTreeSet<u32> = known.tags.iter().copied().collect();
        let (w, h) = (f64::from(gray.width()), f64::from(gray.height()));
        let half = f64::from(RECTIFY_SIDE - 1) / 2.0;
        let f = half / (RECTIFY_FOV_DEG.to_radians() / 2.0).tan();
        let mut raw: Vec<(u32, [Point2<f64>; 4])> = Vec::new();
        for theta in RECTIFY_THETAS_DEG {
            if theta.to_radians() > camera.valid_fov() / 2.0 {
                continue;
            }
            for k in 0..RECTIFY_AZIMUTHS {
                let phi = std::f64::consts::TAU * (k as f64 + 0.5 * (theta / 40.0).floor())
                    / RECTIFY_AZIMUTHS as f64;
                let z =
                    kiwi_core::camera::bearing_from_angles(theta.to_radians(), phi).into_inner();
                let helper = if z.x.abs() < 0.9 {
                    Vector3::x()
                } else {
                    Vector3::y()
                };
                let y = z.cross(&helper).normalize();
                let x = y.cross(&z);
                let rot = nalgebra::Matrix3::from_columns(&[x, y, z]);
                let to_fisheye = |u: f64, v: f64| -> Option<Point2<f64>> {
                    let ray = rot * Vector3::new((u - half) / f, (v - half) / f, 1.0);
                    camera.project(&ray)
                };
                let mut view = GrayImage::new(RECTIFY_SIDE, RECTIFY_SIDE);
                let mut inside = 0usize;
                for (u, v, px) in view.enumerate_pixels_mut() {
                    if let Some(p) = to_fisheye(f64::from(u), f64::from(v))
                        && p.x >= 0.0
                        && p.y >= 0.0
                        && p.x < w - 1.0
                        && p.y < h - 1.0
                    {
                        px[0] = bilinear(gray, p.x, p.y);
                        inside += 1;
                    }
                }
                if inside * 4 < (RECTIFY_SIDE * RECTIFY_SIDE) as usize {
                    continue;
                }
                let tags = self.inner.detect(&DynamicImage::ImageLuma8(view));
                for (id, quad) in tags {
                    if id as usize >= self.target.tag_count() || have.contains(&id) {
                        continue;
                    }
                    let mapped: Option<Vec<Point2<f64>>> = quad
                        .iter()
                        .map(|(u, v)| to_fisheye(f64::from(*u), f64::from(*v)))
                        .collect();
                    let Some(mapped) = mapped else { continue };
                    let pts = [mapped[0], mapped[1], mapped[2], mapped[3]];
                    let inside = pts.iter().all(|p| {
                        p.x >= MIN_BORDER_DISTANCE_PX
                            && p.y >= MIN_BORDER_DISTANCE_PX
                            && p.x <= w - 1.0 - MIN_BORDER_DISTANCE_PX
                            && p.y <= h - 1.0 - MIN_BORDER_DISTANCE_PX
                    });
                    if inside {
                        have.insert(id);
                        raw.push((id, pts));
                    }
                }
            }
        }
        self.refine_and_number(gray, &raw, 0)
    }
}

/// Bilinear sample of a grey image at a sub-pixel position inside it.
fn bilinear(img: &GrayImage, x: f64, y: f64) -> u8 {
    let (x0, y0) = (x.floor() as u32, y.floor() as u32);
    let (fx, fy) = (x - f64::from(x0), y - f64::from(y0));
    let p = |xx: u32, yy: u32| f64::from(img.get_pixel(xx, yy)[0]);
    let top = p(x0, y0) * (1.0 - fx) + p(x0 + 1, y0) * fx;
    let bottom = p(x0, y0 + 1) * (1.0 - fx) + p(x0 + 1, y0 + 1) * fx;
    (top * (1.0 - fy) + bottom * fy).round().clamp(0.0, 255.0) as u8
}

/// `cornerSubPix` on every tag corner (4 per tag, in order).
pub(crate) fn refine_corners(
    gray: &GrayImage,
    tags: &[(u32, [Point2<f64>; 4])],
) -> Result<Vec<Point2<f64>>> {
    let cv = |e: opencv::Error| CalibError::Internal(format!("OpenCV cornerSubPix: {e}"));
    let mat =
        Mat::new_rows_cols_with_data(gray.height() as i32, gray.width() as i32, gray.as_raw())
            .map_err(cv)?;
    let mut pts: Vector<Point2f> = tags
        .iter()
        .flat_map(|(_, q)| q.iter().map(|p| Point2f::new(p.x as f32, p.y as f32)))
        .collect();
    let criteria = TermCriteria::new(
        TermCriteria_Type::COUNT as i32 + TermCriteria_Type::EPS as i32,
        SUBPIX_MAX_ITERATIONS,
        SUBPIX_EPS,
    )
    .map_err(cv)?;
    opencv::imgproc::corner_sub_pix(
        &mat,
        &mut pts,
        Size::new(SUBPIX_HALF_WINDOW, SUBPIX_HALF_WINDOW),
        Size::new(-1, -1),
        criteria,
    )
    .map_err(cv)?;
    Ok(pts
        .iter()
        .map(|p| Point2::new(f64::from(p.x), f64::from(p.y)))
        .collect())
}

/// A first lens calibration from the first-pass corners (KB4, no coverage check), or `None`
/// if they do not support one.
fn bootstrap_camera(images: &[ImageCorners], target: &AprilGridTarget) -> Option<Camera> {
    let mut set = CornerSet::new(Some(*target));
    set.images = images
        .iter()
        .filter(|i| i.tags.len() >= MIN_TAGS_PER_IMAGE)
        .cloned()
        .collect();
    let options = crate::intrinsics::IntrinsicsOptions {
        check_coverage: false,
        ..crate::intrinsics::IntrinsicsOptions::default()
    };
    match crate::intrinsics::calibrate(&set, &options) {
        Ok(r) => Some(r.camera),
        Err(e) => {
            tracing::info!("no rectified second detection pass: {e}");
            None
        }
    }
}

/// Options of [`detect_folder`].
#[derive(Debug, Clone)]
pub struct DetectOptions {
    /// Show a progress bar on stderr.
    pub progress: bool,
    /// Second pass on locally rectified (perspective) views of the periphery, through a lens
    /// calibrated from the first pass: finds the small, strongly distorted tags the first pass
    /// misses.
    pub rectify: bool,
}

impl Default for DetectOptions {
    fn default() -> Self {
        Self {
            progress: false,
            rectify: true,
        }
    }
}

/// Off-axis angles (deg) of the rectified views' centres, and azimuths per ring.
const RECTIFY_THETAS_DEG: [f64; 4] = [40.0, 65.0, 88.0, 108.0];
const RECTIFY_AZIMUTHS: usize = 8;
/// Side (px) and full field of view (deg) of a rectified view: wide enough that neighbouring
/// views overlap by a tag, small enough that the view is nearly undistorted.
const RECTIFY_SIDE: u32 = 360;
const RECTIFY_FOV_DEG: f64 = 64.0;

/// Detect the target in every image of a folder, in parallel; images with fewer than
/// [`MIN_TAGS_PER_IMAGE`] tags are left out. Errors on an empty folder, an unreadable image,
/// mixed image sizes, or when no image shows the target.
pub fn detect_folder(
    dir: &Path,
    target: &AprilGridTarget,
    options: &DetectOptions,
) -> Result<CornerSet> {
    let files = list_images(dir)?;
    let detector = Detector::new(*target);
    let bar = if options.progress {
        let b = ProgressBar::new(files.len() as u64);
        if let Ok(style) =
            ProgressStyle::with_template("detecting {bar:40} {pos}/{len} images ({eta} left)")
        {
            b.set_style(style);
        }
        b
    } else {
        ProgressBar::hidden()
    };
    if options.rectify {
        bar.set_length(2 * files.len() as u64);
    }
    let results: Vec<Result<ImageCorners>> = files
        .par_iter()
        .map(|path| {
            let gray = load_gray(path)?;
            let found = detector.detect(&gray)?;
            bar.inc(1);
            let name = path
                .strip_prefix(dir)
                .unwrap_or(path)
                .to_string_lossy()
                .into_owned();
            Ok(ImageCorners {
                name,
                width: gray.width(),
                height: gray.height(),
                tags: found.tags,
                corners: found.corners,
            })
        })
        .collect();
    let mut all: Vec<ImageCorners> = Vec::with_capacity(results.len());
    for r in results {
        let img = r?;
        if let Some(first) = all.first()
            && (first.width, first.height) != (img.width, img.height)
        {
            return Err(CalibError::Input {
                path: dir.join(&img.name),
                message: format!(
                    "image is {}x{} but {} is {}x{}; put one lens at one resolution in a folder",
                    img.width, img.height, first.name, first.width, first.height
                ),
            });
        }
        all.push(img);
    }
    if options.rectify
        && let Some(camera) = bootstrap_camera(&all, target)
    {
        let added: Vec<Result<Detection>> = files
            .par_iter()
            .zip(all.par_iter())
            .map(|(path, img)| {
                let gray = load_gray(path)?;
                let known = Detection {
                    tags: img.tags.clone(),
                    corners: Vec::new(),
                    dropped_tags: 0,
                };
                let found = detector.detect_rectified(&gray, &camera, &known);
                bar.inc(1);
                found
            })
            .collect();
        for (img, extra) in all.iter_mut().zip(added) {
            let extra = extra?;
            img.tags.extend(extra.tags);
            img.tags.sort_unstable();
            img.corners.extend(extra.corners);
            img.corners.sort_by_key(|c| c.id);
        }
    }
    bar.finish_and_clear();
    let mut set = CornerSet::new(Some(*target));
    set.images = all
        .into_iter()
        .filter(|img| img.tags.len() >= MIN_TAGS_PER_IMAGE)
        .collect();
    if set.images.is_empty() {
        return Err(CalibError::Input {
            path: dir.to_path_buf(),
            message: format!(
                "the target ({}x{} aprilgrid, 36h11) was not found in any of the {} images; \
                 check the target yaml matches the printed board, and that the board is in \
                 focus and well lit",
                target.cols,
                target.rows,
                files.len()
            ),
        });
    }
    Ok(set)
}
