//! Features on raw (unrectified) fisheye images: ORB keypoints and descriptors through OpenCV,
//! static masks, brute-force Hamming matching, and pyramidal KLT tracking between frames.
//!
//! Every keypoint carries its unit bearing from the lens's [`CameraModel`], so downstream
//! geometry never sees pixels. Keypoints whose pixel does not unproject (outside the image
//! circle) are dropped.
//!
//! Cost (BUILD-NOTES): ORB with 1 500 features costs ~32 ms per 960² frame on one core, so the
//! mapper and localizer track with KLT between frames and extract descriptors only for keyframes
//! and relocalization.

use std::path::Path;

use nalgebra::{Matrix2, Point2, Vector3};
use opencv::core::{KeyPoint, Mat, Point2f, Ptr, Size, TermCriteria, TermCriteria_Type, Vector};
use opencv::prelude::*;

use kiwi_core::camera::CameraModel;

use crate::error::{BackendError, Result};

fn cv_err(context: &str) -> impl Fn(opencv::Error) -> BackendError + '_ {
    move |e| BackendError::Vision {
        context: context.to_string(),
        message: format!("OpenCV failed: {e}"),
    }
}

/// An 8-bit single-channel image, row-major, `width × height` bytes.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct GrayImage {
    /// Width (px).
    pub width: u32,
    /// Height (px).
    pub height: u32,
    /// Pixels, row-major.
    pub data: Vec<u8>,
}

impl GrayImage {
    /// An image from raw pixels; the length must be `width · height`.
    pub fn new(width: u32, height: u32, data: Vec<u8>) -> Result<Self> {
        if data.len() != width as usize * height as usize || width == 0 || height == 0 {
            return Err(BackendError::Vision {
                context: "gray image".into(),
                message: format!(
                    "expected {width}x{height} = {} bytes, found {}",
                    width as usize * height as usize,
                    data.len()
                ),
            });
        }
        Ok(Self {
            width,
            height,
            data,
        })
    }

    /// Luma (BT.601 integer weights) of packed 8-bit RGB pixels.
    pub fn from_rgb(width: u32, height: u32, rgb: &[u8]) -> Result<Self> {
        Self::new(width, height, luma::<true>(rgb))
    }

    /// Luma of packed 8-bit BGR pixels (blue first, as OpenCV decodes), with the weights of
    /// [`GrayImage::from_rgb`].
    pub fn from_bgr(width: u32, height: u32, bgr: &[u8]) -> Result<Self> {
        Self::new(width, height, luma::<false>(bgr))
    }

    /// Read an image file (PNG, JPEG, …) as grayscale (BT.601 luma of colour images).
    ///
    /// PNG and JPEG decode through the `image` crate (its PNG inflater is ~2× faster than
    /// libpng's zlib on the prepared episodes' frames); other formats go through OpenCV.
    pub fn load(path: &Path) -> Result<Self> {
        let ext = path
            .extension()
            .map(|e| e.to_string_lossy().to_ascii_lowercase())
            .unwrap_or_default();
        if matches!(ext.as_str(), "png" | "jpg" | "jpeg") {
            let input_err = |e: &dyn std::fmt::Display| BackendError::Input {
                path: path.to_path_buf(),
                message: format!(
                    "cannot read the image ({e}); check the path in frames.csv and that the file \
                     is a complete {ext} image"
                ),
            };
            let decoded = image::ImageReader::open(path)
                .map_err(|e| input_err(&e))?
                .with_guessed_format()
                .map_err(|e| input_err(&e))?
                .decode()
                .map_err(|e| input_err(&e))?;
            return match decoded {
                image::DynamicImage::ImageLuma8(g) => {
                    let (w, h) = g.dimensions();
                    Self::new(w, h, g.into_raw())
                }
                image::DynamicImage::ImageRgb8(rgb) => {
                    Self::from_rgb(rgb.width(), rgb.height(), rgb.as_raw())
                }
                other => {
                    let rgb = other.to_rgb8();
                    Self::from_rgb(rgb.width(), rgb.height(), rgb.as_raw())
                }
            };
        }
        let mat =
            opencv::imgcodecs::imread(path, opencv::imgcodecs::IMREAD_GRAYSCALE).map_err(|e| {
                BackendError::Input {
                    path: path.to_path_buf(),
                    message: format!("cannot read the image: {e}"),
                }
            })?;
        if mat.empty() {
            return Err(BackendError::Input {
                path: path.to_path_buf(),
                message: "cannot read the image (missing, unreadable or not an image); check the \
                          path in frames.csv"
                    .into(),
            });
        }
        let bytes = mat.data_bytes().map_err(|e| BackendError::Input {
            path: path.to_path_buf(),
            message: format!("unexpected image layout: {e}"),
        })?;
        Self::new(mat.cols() as u32, mat.rows() as u32, bytes.to_vec())
    }

    /// A borrowed OpenCV header over the pixels (no copy).
    fn as_mat(&self) -> Result<opencv::boxed_ref::BoxedRef<'_, Mat>> {
        Mat::new_rows_cols_with_data(self.height as i32, self.width as i32, &self.data)
            .map_err(cv_err("gray image"))
    }

    /// Bilinear value at a sub-pixel position (pixel centres at integers), 0 outside.
    #[inline]
    pub fn sample(&self, x: f64, y: f64) -> f32 {
        let (w, h) = (self.width as usize, self.height as usize);
        // Inside the image (all four neighbours exist): truncation is the floor and no neighbour
        // needs a bounds check. The arithmetic is the general path's, so values are identical.
        if x >= 0.0 && y >= 0.0 && x < w.saturating_sub(1) as f64 && y < h.saturating_sub(1) as f64
        {
            let (x0, y0) = (x as usize, y as usize);
            let (ax, ay) = ((x - x0 as f64) as f32, (y - y0 as f64) as f32);
            let i = y0 * w + x0;
            let (a, b) = (f32::from(self.data[i]), f32::from(self.data[i + 1]));
            let (c, d) = (f32::from(self.data[i + w]), f32::from(self.data[i + w + 1]));
            let top = a + (b - a) * ax;
            let bottom = c + (d - c) * ax;
            return top + (bottom - top) * ay;
        }
        self.sample_bounded(x, y)
    }

    /// [`GrayImage::sample`] with every neighbour bounds-checked (any position).
    fn sample_bounded(&self, x: f64, y: f64) -> f32 {
        let (fx, fy) = (x.floor(), y.floor());
        let (ax, ay) = ((x - fx) as f32, (y - fy) as f32);
        let (x0, y0) = (fx as i64, fy as i64);
        let v = |dx: i64, dy: i64| f32::from(self.get(x0 + dx, y0 + dy));
        let top = v(0, 0) + (v(1, 0) - v(0, 0)) * ax;
        let bottom = v(0, 1) + (v(1, 1) - v(0, 1)) * ax;
        top + (bottom - top) * ay
    }

    /// Pixel value at integer coordinates, 0 outside.
    pub fn get(&self, x: i64, y: i64) -> u8 {
        if x < 0 || y < 0 || x >= i64::from(self.width) || y >= i64::from(self.height) {
            return 0;
        }
        self.data[y as usize * self.width as usize + x as usize]
    }
}

/// BT.601 luma in 8-bit fixed point, `(77 R + 150 G + 29 B + 128) / 256`, of packed 8-bit
/// pixels, red first when `RED_FIRST` (blue first otherwise). Written into a buffer made once:
/// about twice as fast as collecting the mapped pixels.
fn luma<const RED_FIRST: bool>(pixels: &[u8]) -> Vec<u8> {
    let (r, b) = if RED_FIRST { (0, 2) } else { (2, 0) };
    let mut out = vec![0u8; pixels.len() / 3];
    for (o, p) in out.iter_mut().zip(pixels.chunks_exact(3)) {
        *o = ((u32::from(p[r]) * 77 + u32::from(p[1]) * 150 + u32::from(p[b]) * 29 + 128) >> 8)
            as u8;
    }
    out
}

/// A per-lens static mask: non-zero pixels may hold features.
pub type Mask = GrayImage;

/// Margin (rad) kept inside the lens's valid field of view by [`fov_mask`]: features at the very
/// edge of the image circle are blurred and their unprojection is least certain.
pub const FOV_MASK_MARGIN_RAD: f64 = 0.03;

/// Largest Hamming distance of a match whose position is already constrained (guided by a
/// pose): ORB-SLAM's "low" threshold.
pub const GUIDED_MAX_DISTANCE: u32 = 50;

/// The mask of pixels that unproject to bearings at most `valid_fov/2 − margin` off-axis.
pub fn fov_mask(camera: &dyn CameraModel, margin_rad: f64) -> Mask {
    let (w, h) = camera.resolution();
    let max_angle = 0.5 * camera.valid_fov() - margin_rad;
    let cos_max = max_angle.cos();
    let mut data = vec![0u8; w as usize * h as usize];
    for y in 0..h {
        for x in 0..w {
            if let Some(b) = camera.unproject(&Point2::new(f64::from(x), f64::from(y)))
                && b.z >= cos_max
            {
                data[y as usize * w as usize + x as usize] = 255;
            }
        }
    }
    Mask {
        width: w,
        height: h,
        data,
    }
}

/// Combine two masks: a pixel is usable only where both allow it.
pub fn intersect_masks(a: &Mask, b: &Mask) -> Result<Mask> {
    if a.width != b.width || a.height != b.height {
        return Err(BackendError::Vision {
            context: "mask".into(),
            message: format!(
                "expected masks of the same size, found {}x{} and {}x{}; resize the static mask \
                 to the lens resolution",
                a.width, a.height, b.width, b.height
            ),
        });
    }
    let data = a
        .data
        .iter()
        .zip(&b.data)
        .map(|(&x, &y)| if x > 0 && y > 0 { 255 } else { 0 })
        .collect();
    Mask::new(a.width, a.height, data)
}

/// A 256-bit ORB descriptor (serialized as 64 hex digits, see [`crate::vision::map`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct Descriptor(pub [u64; 4]);

impl Descriptor {
    /// Hamming distance (0–256).
    pub fn distance(&self, other: &Self) -> u32 {
        (self.0[0] ^ other.0[0]).count_ones()
            + (self.0[1] ^ other.0[1]).count_ones()
            + (self.0[2] ^ other.0[2]).count_ones()
            + (self.0[3] ^ other.0[3]).count_ones()
    }

    fn from_bytes(b: &[u8]) -> Self {
        let mut words = [0u64; 4];
        for (k, word) in words.iter_mut().enumerate() {
            let mut bytes = [0u8; 8];
            bytes.copy_from_slice(&b[8 * k..8 * k + 8]);
            *word = u64::from_le_bytes(bytes);
        }
        Self(words)
    }
}

/// A keypoint with its bearing.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Keypoint {
    /// Pixel position.
    pub pixel: Point2<f64>,
    /// Unit bearing in the camera frame.
    pub bearing: Vector3<f64>,
    /// Pyramid level it was detected on.
    pub octave: i32,
    /// Detector response (higher is stronger).
    pub response: f32,
}

/// Keypoints and their descriptors (same order).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct FrameFeatures {
    /// Keypoints.
    pub keypoints: Vec<Keypoint>,
    /// Descriptors.
    pub descriptors: Vec<Descriptor>,
}

/// ORB settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OrbOptions {
    /// Most keypoints per image.
    pub max_features: i32,
    /// Pyramid scale step.
    pub scale_factor: f32,
    /// Pyramid levels.
    pub levels: i32,
    /// FAST threshold (intensity steps).
    pub fast_threshold: i32,
    /// Describe each keypoint on a patch resampled around its bearing (a small pinhole view
    /// along it, at the keypoint's angular scale) instead of on the raw fisheye image: a point
    /// seen near the image centre in one view and 35-60° off-axis in another is rendered by a
    /// 190° lens at another scale and with an anisotropic stretch, which raw ORB descriptors do
    /// not survive; on the rectified patch only the true change of viewpoint remains.
    pub rectified: bool,
    /// Normalise each rectified patch's affine shape before describing it (with `rectified`):
    /// the patch is sheared and stretched until the local image structure around the keypoint
    /// is isotropic (its second-moment matrix a multiple of the identity), so a surface seen
    /// face-on in one view and obliquely in another gives the same patch up to a rotation, which
    /// the intensity centroid then fixes. Rectification alone removes the lens's distortion but
    /// not the foreshortening of a change of viewing direction. Off by default: it localizes
    /// more of the repeated-texture revisits, but one held-out revisit then accepts poses over
    /// 5 cm where tracking resumes (docs/vision.md, "Affine-normalised patches"), and it doubles
    /// the cost of describing. Map and query must use the same setting (maps do not record it).
    pub affine_adapted: bool,
}

impl Default for OrbOptions {
    fn default() -> Self {
        Self {
            max_features: 1500,
            scale_factor: 1.2,
            levels: 8,
            fast_threshold: 20,
            rectified: true,
            affine_adapted: false,
        }
    }
}

/// Side (px) of the patch resampled around a keypoint for its rectified descriptor: ORB's
/// rotated sampling pattern reaches ~19 px from the centre and its 7 × 7 smoothing 3 px more.
const RECTIFIED_PATCH: usize = 48;
/// Exact projections per side of a rectified patch (the pixel positions between them are
/// interpolated bilinearly: the lens mapping is smooth at this scale).
const RECTIFIED_GRID: usize = 6;
/// Empty border (px) around the mosaic of patches: ORB refuses keypoints nearer its edge
/// threshold to the image border.
const MOSAIC_MARGIN: usize = ORB_PATCH as usize + 1;
/// Radius (px) of the intensity-centroid disc that orients a patch (ORB's half patch).
const ORIENTATION_RADIUS: i64 = 15;

/// Gaussian integration scale (patch px) of the second-moment matrix that measures a patch's
/// affine shape: about a third of ORB's sampling radius, so the shape is that of the region the
/// descriptor sees.
const ADAPT_SIGMA: f64 = 5.0;
/// Spacing (patch px) of the samples the shape is measured on: every pixel. Every other pixel
/// (a quarter of the resampling) lost most of the gain: the gradients at a 4-pixel baseline
/// miss the fine structure that sets a corner's shape (`affine_adapted_patches_…` test: right
/// pairs nearest 290 → 230 of 3977, plain 203).
const ADAPT_SPACING: usize = 1;
/// Samples each side of the shape window's centre: the Gaussian window to 3σ plus one for the
/// gradient.
const ADAPT_HALF_SAMPLES: usize = 3 * ADAPT_SIGMA as usize / ADAPT_SPACING + 1;
/// Samples per side of the shape window.
const ADAPT_SAMPLES: usize = 2 * ADAPT_HALF_SAMPLES + 1;
/// Side (patch px) of the shape window.
const ADAPT_WINDOW: usize = (ADAPT_SAMPLES - 1) * ADAPT_SPACING + 1;
/// Exact projections per side of the shape window (bilinear in between, as for the patch).
const ADAPT_GRID: usize = 4;
/// Most re-measurements of a patch's shape after the plain patch's (the shape settles in two
/// or three on a corner; each costs a resampled window).
const ADAPT_ITERATIONS: usize = 4;
/// Eigenvalue ratio (smaller over larger) of the second-moment matrix at which a patch counts
/// as isotropic.
const ADAPT_ISOTROPIC: f64 = 0.9;
/// Largest stretch (singular-value ratio of the patch's shape) accepted: 3 is the
/// foreshortening of a plane seen 70° from its normal; beyond it the structure is an edge, not
/// a corner, and the patch keeps its plain (isotropic) shape.
const ADAPT_MAX_STRETCH: f64 = 3.0;
/// Smallest `det / trace²` of a second-moment matrix with two usable directions (an edge or
/// flat patch has none and keeps its plain shape).
const ADAPT_MIN_CORNERNESS: f64 = 1e-4;

/// Border (px) that ORB keeps free (its patch radius): also used for its edge threshold.
const ORB_PATCH: i32 = 31;

/// ORB detector/descriptor on raw fisheye images.
pub struct OrbExtractor {
    orb: Ptr<opencv::features2d::ORB>,
    /// One-level ORB that describes the rectified patches (when the options ask for them).
    describer: Option<Ptr<opencv::features2d::ORB>>,
    scale_factor: f64,
    affine_adapted: bool,
}

impl OrbExtractor {
    /// A detector with these settings.
    pub fn new(options: &OrbOptions) -> Result<Self> {
        let create = |levels: i32| {
            opencv::features2d::ORB::create(
                options.max_features,
                options.scale_factor,
                levels,
                ORB_PATCH,
                0,
                2,
                opencv::features2d::ORB_ScoreType::HARRIS_SCORE,
                ORB_PATCH,
                options.fast_threshold,
            )
            .map_err(cv_err("ORB"))
        };
        Ok(Self {
            orb: create(options.levels)?,
            describer: if options.rectified {
                Some(create(1)?)
            } else {
                None
            },
            scale_factor: f64::from(options.scale_factor),
            affine_adapted: options.affine_adapted,
        })
    }

    /// Rectified descriptors of given keypoints (of `image`) when the options ask for them
    /// (`None` per keypoint that cannot be described); `None` overall when they do not (the
    /// caller keeps raw descriptors).
    pub fn describe(
        &mut self,
        image: &GrayImage,
        camera: &dyn CameraModel,
        keypoints: &[Keypoint],
    ) -> Result<Option<Vec<Option<Descriptor>>>> {
        let shape = PatchShape::from_options(self.affine_adapted);
        self.describe_shaped(image, camera, keypoints, shape)
    }

    /// Rectified descriptors of `keypoints` on patches shaped by `shape`; `None` without
    /// rectified descriptors.
    fn describe_shaped(
        &mut self,
        image: &GrayImage,
        camera: &dyn CameraModel,
        keypoints: &[Keypoint],
        shape: PatchShape,
    ) -> Result<Option<Vec<Option<Descriptor>>>> {
        match self.describer.as_mut() {
            Some(d) => Ok(Some(describe_rectified(
                d,
                image,
                camera,
                keypoints,
                self.scale_factor,
                shape,
            )?)),
            None => Ok(None),
        }
    }

    /// Rectified descriptors of given keypoints on patches warped by a fixed affine `shape`
    /// (determinant 1; patch coordinates `(u, v)` look along `shape · (u, v)` of the tangent
    /// plane): the keypoints' surroundings as a view tilted against them would see them, to
    /// measure how descriptors survive a change of viewing direction. `None` per keypoint
    /// whose warped patch leaves the field of view; `None` overall without rectified
    /// descriptors.
    pub fn describe_warped(
        &mut self,
        image: &GrayImage,
        camera: &dyn CameraModel,
        keypoints: &[Keypoint],
        shape: Matrix2<f64>,
    ) -> Result<Option<Vec<Option<Descriptor>>>> {
        self.describe_shaped(image, camera, keypoints, PatchShape::Fixed(shape))
    }

    /// Replace the descriptors by rectified ones when the options ask for them (keypoints
    /// that cannot be described that way are dropped).
    fn finish(
        &mut self,
        image: &GrayImage,
        camera: &dyn CameraModel,
        features: FrameFeatures,
    ) -> Result<FrameFeatures> {
        let Some(describer) = self.describer.as_mut() else {
            return Ok(features);
        };
        let described = describe_rectified(
            describer,
            image,
            camera,
            &features.keypoints,
            self.scale_factor,
            PatchShape::from_options(self.affine_adapted),
        )?;
        let (keypoints, descriptors) = features
            .keypoints
            .into_iter()
            .zip(described)
            .filter_map(|(k, d)| d.map(|d| (k, d)))
            .unzip();
        Ok(FrameFeatures {
            keypoints,
            descriptors,
        })
    }

    /// Detect and describe; keypoints outside `mask` or outside the lens's image circle are
    /// dropped. Output is sorted by response (strongest first, ties by position) so it does not
    /// depend on OpenCV's internal ordering.
    pub fn extract(
        &mut self,
        image: &GrayImage,
        mask: Option<&Mask>,
        camera: &dyn CameraModel,
    ) -> Result<FrameFeatures> {
        let (w, h) = camera.resolution();
        if (w, h) != (image.width, image.height) {
            return Err(BackendError::Vision {
                context: "ORB".into(),
                message: format!(
                    "image is {}x{} but the lens calibration is {w}x{h}; use frames of the \
                     calibrated resolution",
                    image.width, image.height
                ),
            });
        }
        let img = image.as_mat()?;
        let mut keypoints = Vector::<KeyPoint>::new();
        let mut desc = Mat::default();
        match mask {
            Some(m) => {
                if (m.width, m.height) != (w, h) {
                    return Err(BackendError::Vision {
                        context: "ORB".into(),
                        message: format!(
                            "mask is {}x{} but the image is {w}x{h}; resize the mask",
                            m.width, m.height
                        ),
                    });
                }
                let mm = m.as_mat()?;
                self.orb
                    .detect_and_compute(&img, &mm, &mut keypoints, &mut desc, false)
            }
            None => {
                self.orb
                    .detect_and_compute(&img, &Mat::default(), &mut keypoints, &mut desc, false)
            }
        }
        .map_err(cv_err("ORB"))?;
        let mut out = Vec::with_capacity(keypoints.len());
        collect_keypoints(&keypoints, &desc, (0, 0), None, camera, &mut out)?;
        self.finish(image, camera, sorted_features(out))
    }

    /// Like [`OrbExtractor::extract`], but only inside the given pixel rectangles
    /// `[x0, y0, x1, y1)`: each is detected on its own crop (grown by ORB's patch border, so
    /// descriptors near the rectangle's edge see real pixels), which costs roughly the crops'
    /// share of the image instead of a full-frame pyramid. Each rectangle keeps at most
    /// `max_features` scaled by its share of the image area.
    pub fn extract_in_rects(
        &mut self,
        image: &GrayImage,
        mask: &Mask,
        camera: &dyn CameraModel,
        rects: &[[u32; 4]],
    ) -> Result<FrameFeatures> {
        let (w, h) = camera.resolution();
        if (w, h) != (image.width, image.height) || (mask.width, mask.height) != (w, h) {
            return Err(BackendError::Vision {
                context: "ORB".into(),
                message: format!(
                    "image {}x{} and mask {}x{} must both be the calibrated {w}x{h}",
                    image.width, image.height, mask.width, mask.height
                ),
            });
        }
        let img = image.as_mat()?;
        let mm = mask.as_mat()?;
        let full = self.orb.get_max_features().map_err(cv_err("ORB"))?;
        let area = f64::from(w) * f64::from(h);
        let border = ORB_PATCH as u32 + 1;
        let mut out = Vec::new();
        for r in rects {
            let (x0, y0) = (r[0].min(w), r[1].min(h));
            let (x1, y1) = (r[2].min(w), r[3].min(h));
            if x1 <= x0 || y1 <= y0 {
                continue;
            }
            let (cx0, cy0) = (x0.saturating_sub(border), y0.saturating_sub(border));
            let (cx1, cy1) = ((x1 + border).min(w), (y1 + border).min(h));
            let roi = opencv::core::Rect::new(
                cx0 as i32,
                cy0 as i32,
                (cx1 - cx0) as i32,
                (cy1 - cy0) as i32,
            );
            let crop = Mat::roi(&img, roi).map_err(cv_err("ORB crop"))?;
            let crop_mask = Mat::roi(&mm, roi).map_err(cv_err("ORB crop"))?;
            let share = f64::from((x1 - x0) * (y1 - y0)) / area;
            let budget = (f64::from(full) * share * RECT_FEATURE_SURPLUS).ceil() as i32;
            self.orb
                .set_max_features(budget.max(MIN_RECT_FEATURES))
                .map_err(cv_err("ORB"))?;
            let mut keypoints = Vector::<KeyPoint>::new();
            let mut desc = Mat::default();
            let run =
                self.orb
                    .detect_and_compute(&crop, &crop_mask, &mut keypoints, &mut desc, false);
            self.orb.set_max_features(full).map_err(cv_err("ORB"))?;
            run.map_err(cv_err("ORB"))?;
            let inner = [f64::from(x0), f64::from(y0), f64::from(x1), f64::from(y1)];
            collect_keypoints(&keypoints, &desc, (cx0, cy0), Some(inner), camera, &mut out)?;
        }
        self.finish(image, camera, sorted_features(out))
    }
}

/// `v.round().clamp(0.0, 255.0) as u8` (halves away from zero, NaN to 0) without a call to the
/// C library's `roundf` (x86-64's baseline has no rounding instruction).
fn round_to_u8(v: f32) -> u8 {
    let t = v as u8;
    t.saturating_add(u8::from(v - f32::from(t) >= 0.5))
}

/// Pixels per radian of the lens at its image centre.
fn centre_pixels_per_rad(camera: &dyn CameraModel) -> Option<f64> {
    let (w, h) = camera.resolution();
    let c = Point2::new(f64::from(w) / 2.0, f64::from(h) / 2.0);
    let a = camera.unproject(&c)?;
    let b = camera.unproject(&Point2::new(c.x + 1.0, c.y))?;
    let angle = a.angle(&b);
    (angle > 0.0).then(|| 1.0 / angle)
}

/// The tangent frame of a keypoint's rectified patch: unit `e1` along the raw image's x
/// direction at the keypoint, `e2 = b × e1` (image y, down), and the angle per patch pixel:
/// the detection's pyramid scale over the lens's local pixels per radian there (geometric mean
/// of the two directions), so the patch spans the angle raw ORB would have described.
fn patch_frame(
    camera: &dyn CameraModel,
    keypoint: &Keypoint,
    scale_factor: f64,
) -> Option<(Vector3<f64>, Vector3<f64>, f64)> {
    let b = keypoint.bearing;
    let px = camera.unproject(&Point2::new(keypoint.pixel.x + 1.0, keypoint.pixel.y))?;
    let py = camera.unproject(&Point2::new(keypoint.pixel.x, keypoint.pixel.y + 1.0))?;
    let tangent = |v: &Vector3<f64>| v - b * b.dot(v);
    let dx = tangent(&(px.into_inner() - b));
    let dy = tangent(&(py.into_inner() - b));
    // Radians of tangent plane per pixel along x and y; their cross product's length is the
    // area of one pixel in rad².
    let area = dx.cross(&dy).norm();
    if area.is_nan() || area <= 0.0 || dx.norm() <= 0.0 {
        return None;
    }
    let e1 = dx.normalize();
    let e2 = b.cross(&e1);
    let step = scale_factor.powi(keypoint.octave.max(0)) * area.sqrt();
    Some((e1, e2, step))
}

/// The orthonormal tangent-plane directions `(e1, e2)` of a keypoint's rectified patch (patch
/// coordinates `(u, v)` look along `bearing + step · (e1 u + e2 v)`, `e1` along the image's x);
/// `None` where the lens cannot unproject the neighbouring pixels.
pub fn patch_tangent_basis(
    camera: &dyn CameraModel,
    keypoint: &Keypoint,
) -> Option<(Vector3<f64>, Vector3<f64>)> {
    patch_frame(camera, keypoint, 1.0).map(|(e1, e2, _)| (e1, e2))
}

/// The angular step (rad of tangent plane per patch pixel) of a keypoint's rectified patch at
/// its pyramid level (`scale_factor` per level).
pub fn patch_step(camera: &dyn CameraModel, keypoint: &Keypoint, scale_factor: f64) -> Option<f64> {
    patch_frame(camera, keypoint, scale_factor).map(|(_, _, step)| step)
}

/// A fixed orthonormal tangent basis `(f1, f2)` at a unit direction `b` (`f2 = b × f1`): the
/// frame map patches are stored in, reproducible from the direction alone.
pub fn direction_basis(b: &Vector3<f64>) -> (Vector3<f64>, Vector3<f64>) {
    let helper = if b.x.abs() < 0.9 {
        Vector3::x()
    } else {
        Vector3::y()
    };
    let f1 = b.cross(&helper).normalize();
    (f1, b.cross(&f1))
}

/// A tangent-plane patch: its centre direction, tangent basis, angular step (rad per patch
/// pixel) and affine shape; patch pixel `(u, v)` from the centre looks along
/// `direction + step · (e1, e2) · shape · (u, v)`.
#[derive(Debug, Clone, Copy)]
pub struct TangentPatch {
    /// Unit centre direction (camera frame).
    pub direction: Vector3<f64>,
    /// First tangent direction.
    pub e1: Vector3<f64>,
    /// Second tangent direction.
    pub e2: Vector3<f64>,
    /// Angular step (rad of tangent plane per patch pixel).
    pub step: f64,
    /// Affine shape applied to patch coordinates.
    pub shape: Matrix2<f64>,
}

impl TangentPatch {
    /// Resample the `side`-pixel patch (centre pixel `side / 2`) from `image`, row-major;
    /// `None` where it leaves the lens's field of view.
    pub fn sample(
        &self,
        image: &GrayImage,
        camera: &dyn CameraModel,
        side: usize,
    ) -> Option<Vec<f32>> {
        let frame = PatchFrame {
            bearing: self.direction,
            e1: self.e1,
            e2: self.e2,
            step: self.step,
            shape: self.shape,
        };
        let mut nodes = Vec::with_capacity((side + 1) * (side + 1));
        let mut out = vec![0f32; side * side];
        frame
            .sample(image, camera, side, side, &mut nodes, &mut out)
            .then_some(out)
    }
}

/// The tangent-plane frame of one keypoint's patch: patch coordinates `(u, v)` (px from the
/// centre) look along `bearing + step · (e1, e2) · shape · (u, v)`.
struct PatchFrame {
    bearing: Vector3<f64>,
    e1: Vector3<f64>,
    e2: Vector3<f64>,
    step: f64,
    /// Affine shape (determinant 1): the identity for a plain rectified patch.
    shape: Matrix2<f64>,
}

impl PatchFrame {
    /// Resample a `side`-pixel patch (centre pixel `side / 2`) into `out` (row-major): exact
    /// projections on a `grid`-cell lattice, bilinear in between (the lens mapping is smooth at
    /// this scale). False when part of the patch leaves the lens's field of view.
    fn sample(
        &self,
        image: &GrayImage,
        camera: &dyn CameraModel,
        side: usize,
        grid: usize,
        nodes_buf: &mut Vec<Point2<f64>>,
        out: &mut [f32],
    ) -> bool {
        let half = (side / 2) as f64;
        let cell = side as f64 / grid as f64;
        let nodes = grid + 1;
        nodes_buf.clear();
        for gy in 0..nodes {
            for gx in 0..nodes {
                let (u, v) = (gx as f64 * cell - half, gy as f64 * cell - half);
                let t = self.shape * nalgebra::Vector2::new(u, v);
                let d = self.bearing + self.e1 * (t.x * self.step) + self.e2 * (t.y * self.step);
                match camera.project(&d) {
                    Some(p) => nodes_buf.push(p),
                    None => return false,
                }
            }
        }
        let node = |gx: usize, gy: usize| nodes_buf[gy * nodes + gx].coords;
        for (py, row) in out.chunks_exact_mut(side).take(side).enumerate() {
            let fy = py as f64 / cell;
            let gy = (fy as usize).min(grid - 1);
            let ay = fy - gy as f64;
            // Along a row the position is linear in x between the cell edges' positions.
            let edge = |gx: usize| node(gx, gy) + (node(gx, gy + 1) - node(gx, gy)) * ay;
            let mut left = edge(0);
            for gx in 0..grid {
                let right = edge(gx + 1);
                let per_px = (right - left) / cell;
                let origin = gx as f64 * cell;
                // Pixels whose cell is `gx` (the last cell also takes any remainder).
                let first = origin.ceil() as usize;
                let last = if gx + 1 == grid {
                    side
                } else {
                    (((gx + 1) as f64) * cell).ceil() as usize
                };
                for (px, value) in row.iter_mut().enumerate().take(last).skip(first) {
                    let p = left + per_px * (px as f64 - origin);
                    *value = image.sample(p.x, p.y);
                }
                left = right;
            }
        }
        true
    }

    /// [`PatchFrame::sample`] of the [`RECTIFIED_PATCH`]-pixel patch that is described.
    fn sample_patch(
        &self,
        image: &GrayImage,
        camera: &dyn CameraModel,
        nodes_buf: &mut Vec<Point2<f64>>,
        patch: &mut [f32],
    ) -> bool {
        self.sample(
            image,
            camera,
            RECTIFIED_PATCH,
            RECTIFIED_GRID,
            nodes_buf,
            patch,
        )
    }
}

/// The Gaussian weights (σ = [`ADAPT_SIGMA`]) of the [`ADAPT_SAMPLES`]² samples of the shape
/// window, row-major, centred on its middle sample.
fn adapt_weights() -> Vec<f64> {
    let n = ADAPT_SAMPLES;
    let c = (n / 2) as f64;
    let spacing = ADAPT_SPACING as f64;
    (0..n * n)
        .map(|i| {
            let dx = ((i % n) as f64 - c) * spacing;
            let dy = ((i / n) as f64 - c) * spacing;
            (-(dx * dx + dy * dy) / (2.0 * ADAPT_SIGMA * ADAPT_SIGMA)).exp()
        })
        .collect()
}

/// The second-moment matrix (sum of gradient outer products weighted by `weights`, from
/// [`adapt_weights`]) of the shape window's [`ADAPT_SAMPLES`]² samples, which sit in `data`
/// from index `origin` on, `spacing` apart along a row and rows `stride` apart.
fn second_moment(
    data: &[f32],
    stride: usize,
    spacing: usize,
    origin: usize,
    weights: &[f64],
) -> Matrix2<f64> {
    let n = ADAPT_SAMPLES;
    let (mut a, mut b, mut d) = (0.0f64, 0.0f64, 0.0f64);
    for y in 1..n - 1 {
        for x in 1..n - 1 {
            let i = origin + (y * stride + x) * spacing;
            let gx = 0.5 * f64::from(data[i + spacing] - data[i - spacing]);
            let gy = 0.5 * f64::from(data[i + stride * spacing] - data[i - stride * spacing]);
            let w = weights[y * n + x];
            a += w * gx * gx;
            b += w * gx * gy;
            d += w * gy * gy;
        }
    }
    Matrix2::new(a, b, b, d)
}

/// Where the shape window sits in a plain rectified patch: both are centred on the keypoint.
const PATCH_WINDOW_ORIGIN: usize = (RECTIFIED_PATCH / 2 - ADAPT_WINDOW / 2) * (RECTIFIED_PATCH + 1);

/// One step of the shape iteration on the second-moment matrix `m` measured under `shape`.
enum ShapeStep {
    /// `m` is isotropic: `shape` is the answer.
    Settled,
    /// The next shape to measure.
    Next(Matrix2<f64>),
    /// No usable shape (an edge or flat patch, or a stretch beyond [`ADAPT_MAX_STRETCH`]).
    Unusable,
}

fn shape_step(m: &Matrix2<f64>, shape: &Matrix2<f64>) -> ShapeStep {
    let (trace, det) = (m.trace(), m.determinant());
    if !(trace > 0.0 && det > ADAPT_MIN_CORNERNESS * trace * trace) {
        return ShapeStep::Unusable;
    }
    let spread = (0.25 * (m[(0, 0)] - m[(1, 1)]).powi(2) + m[(0, 1)].powi(2)).sqrt();
    let (low, high) = (0.5 * trace - spread, 0.5 * trace + spread);
    if low >= ADAPT_ISOTROPIC * high {
        return ShapeStep::Settled;
    }
    // Square root of a 2 × 2 SPD matrix, (M + √det I) / √(tr + 2√det), scaled to det 1; its
    // inverse (det 1: the adjugate) is the normalised M^{-1/2}.
    let root = (m + Matrix2::identity() * det.sqrt()) / (trace + 2.0 * det.sqrt()).sqrt();
    let root = root / det.powf(0.25);
    let inverse_root = Matrix2::new(root[(1, 1)], -root[(0, 1)], -root[(1, 0)], root[(0, 0)]);
    let next = shape * inverse_root;
    // Singular values s1 ≥ s2 of a det-1 matrix: s1·s2 = 1, s1² + s2² = ‖next‖²_F.
    let f = next.norm_squared();
    let stretch = 0.5 * (f + (f * f - 4.0).max(0.0).sqrt());
    if !stretch.is_finite() || stretch > ADAPT_MAX_STRETCH {
        return ShapeStep::Unusable;
    }
    ShapeStep::Next(next)
}

/// The affine shape that makes a keypoint's patch isotropic (see [`OrbOptions::affine_adapted`]):
/// iterate `shape ← shape · M^{-1/2}` (normalised to determinant 1) on the second-moment matrix
/// `M` of the patch under the current shape until `M` is isotropic, starting from `plain`, the
/// matrix of the plain patch. `None` when the plain patch is already isotropic; the identity
/// when the patch has no two usable directions, leaves the field of view, does not settle, or
/// would stretch more than [`ADAPT_MAX_STRETCH`]: such keypoints keep their plain patch.
fn affine_shape(
    image: &GrayImage,
    camera: &dyn CameraModel,
    frame: &PatchFrame,
    plain: Matrix2<f64>,
    weights: &[f64],
    nodes_buf: &mut Vec<Point2<f64>>,
    window: &mut [f32],
) -> Option<Matrix2<f64>> {
    // The window's samples are a patch of ADAPT_SAMPLES pixels at ADAPT_SPACING times the
    // angular step.
    let mut trial = PatchFrame {
        shape: Matrix2::identity(),
        step: frame.step * ADAPT_SPACING as f64,
        ..*frame
    };
    let mut m = plain;
    for iteration in 0..ADAPT_ITERATIONS {
        match shape_step(&m, &trial.shape) {
            ShapeStep::Settled => return (iteration > 0).then_some(trial.shape),
            ShapeStep::Unusable => return None,
            ShapeStep::Next(shape) => trial.shape = shape,
        }
        if !trial.sample(image, camera, ADAPT_SAMPLES, ADAPT_GRID, nodes_buf, window) {
            return None;
        }
        m = second_moment(window, ADAPT_SAMPLES, 1, 0, weights);
    }
    matches!(shape_step(&m, &trial.shape), ShapeStep::Settled).then_some(trial.shape)
}

/// How a rectified patch is shaped before it is described.
#[derive(Debug, Clone, Copy)]
enum PatchShape {
    /// The plain gnomonic view along the bearing.
    Plain,
    /// Normalised to an isotropic second-moment matrix ([`OrbOptions::affine_adapted`]).
    Adapted,
    /// Warped by this affine shape (determinant 1).
    Fixed(Matrix2<f64>),
}

impl PatchShape {
    fn from_options(affine_adapted: bool) -> Self {
        if affine_adapted {
            Self::Adapted
        } else {
            Self::Plain
        }
    }
}

/// Rectified ORB descriptors of `keypoints` (see [`OrbOptions::rectified`]): around each
/// keypoint's bearing a [`RECTIFIED_PATCH`]-pixel gnomonic view is resampled from the raw
/// image (affine-normalised when `affine_adapted`, see [`OrbOptions::affine_adapted`]),
/// oriented by its intensity centroid, laid into one mosaic image, and described by a
/// one-level ORB at the patch centres. `None` for a keypoint OpenCV could not describe.
fn describe_rectified(
    describer: &mut Ptr<opencv::features2d::ORB>,
    image: &GrayImage,
    camera: &dyn CameraModel,
    keypoints: &[Keypoint],
    scale_factor: f64,
    shape: PatchShape,
) -> Result<Vec<Option<Descriptor>>> {
    let affine_adapted = matches!(shape, PatchShape::Adapted);
    let n = keypoints.len();
    if n == 0 {
        return Ok(Vec::new());
    }
    if centre_pixels_per_rad(camera).is_none() {
        return Ok(vec![None; n]);
    }
    let cols = (n as f64).sqrt().ceil() as usize;
    let rows = n.div_ceil(cols);
    let (mw, mh) = (
        2 * MOSAIC_MARGIN + cols * RECTIFIED_PATCH,
        2 * MOSAIC_MARGIN + rows * RECTIFIED_PATCH,
    );
    let mut mosaic = vec![0u8; mw * mh];
    let mut cv_keypoints = Vector::<KeyPoint>::new();
    let mut patch = vec![0f32; RECTIFIED_PATCH * RECTIFIED_PATCH];
    let mut window = vec![0f32; ADAPT_SAMPLES * ADAPT_SAMPLES];
    let weights = if affine_adapted {
        adapt_weights()
    } else {
        Vec::new()
    };
    let mut nodes = Vec::with_capacity((RECTIFIED_GRID + 1) * (RECTIFIED_GRID + 1));
    for (i, kp) in keypoints.iter().enumerate() {
        let Some((e1, e2, step)) = patch_frame(camera, kp, scale_factor) else {
            continue;
        };
        let mut frame = PatchFrame {
            bearing: kp.bearing,
            e1,
            e2,
            step,
            shape: match shape {
                PatchShape::Fixed(m) => m,
                PatchShape::Plain | PatchShape::Adapted => Matrix2::identity(),
            },
        };
        if !frame.sample_patch(image, camera, &mut nodes, &mut patch) {
            continue;
        }
        if affine_adapted {
            let plain = second_moment(
                &patch,
                RECTIFIED_PATCH,
                ADAPT_SPACING,
                PATCH_WINDOW_ORIGIN,
                &weights,
            );
            if let Some(shape) = affine_shape(
                image,
                camera,
                &frame,
                plain,
                &weights,
                &mut nodes,
                &mut window,
            ) {
                frame.shape = shape;
                if !frame.sample_patch(image, camera, &mut nodes, &mut patch) {
                    // The stretched patch leaves the field of view: describe the plain one.
                    frame.shape = Matrix2::identity();
                    if !frame.sample_patch(image, camera, &mut nodes, &mut patch) {
                        continue;
                    }
                }
            }
        }
        // Orientation: ORB's intensity centroid over a disc about the centre.
        let centre = RECTIFIED_PATCH as i64 / 2;
        let (mut m10, mut m01) = (0.0f64, 0.0f64);
        for dy in -ORIENTATION_RADIUS..=ORIENTATION_RADIUS {
            for dx in -ORIENTATION_RADIUS..=ORIENTATION_RADIUS {
                if dx * dx + dy * dy > ORIENTATION_RADIUS * ORIENTATION_RADIUS {
                    continue;
                }
                let v = f64::from(
                    patch[((centre + dy) as usize) * RECTIFIED_PATCH + (centre + dx) as usize],
                );
                m10 += dx as f64 * v;
                m01 += dy as f64 * v;
            }
        }
        let angle = m01.atan2(m10).to_degrees().rem_euclid(360.0);
        let (col, row) = (i % cols, i / cols);
        let (ox, oy) = (
            MOSAIC_MARGIN + col * RECTIFIED_PATCH,
            MOSAIC_MARGIN + row * RECTIFIED_PATCH,
        );
        let rows = mosaic.chunks_exact_mut(mw).skip(oy);
        for (dst, src) in rows.zip(patch.chunks_exact(RECTIFIED_PATCH)) {
            for (d, &v) in dst[ox..ox + RECTIFIED_PATCH].iter_mut().zip(src) {
                *d = round_to_u8(v);
            }
        }
        let kp_cv = KeyPoint::new_coords(
            (ox + RECTIFIED_PATCH / 2) as f32,
            (oy + RECTIFIED_PATCH / 2) as f32,
            ORB_PATCH as f32,
            angle as f32,
            kp.response,
            0,
            i as i32,
        )
        .map_err(cv_err("ORB rectified"))?;
        cv_keypoints.push(kp_cv);
    }
    let img = Mat::new_rows_cols_with_data(mh as i32, mw as i32, &mosaic)
        .map_err(cv_err("ORB rectified"))?;
    let mut desc = Mat::default();
    describer
        .detect_and_compute(&img, &Mat::default(), &mut cv_keypoints, &mut desc, true)
        .map_err(cv_err("ORB rectified"))?;
    let mut out = vec![None; n];
    for (row, kp) in cv_keypoints.iter().enumerate() {
        let i = kp.class_id();
        let Some(slot) = usize::try_from(i).ok().and_then(|i| out.get_mut(i)) else {
            continue;
        };
        let bytes = desc
            .at_row::<u8>(row as i32)
            .map_err(cv_err("ORB rectified"))?;
        if bytes.len() >= 32 {
            *slot = Some(Descriptor::from_bytes(&bytes[..32]));
        }
    }
    Ok(out)
}

/// A crop's ORB keypoints beyond its share of the full-frame budget: crops are small and their
/// strongest corners cluster, so allow a little more.
const RECT_FEATURE_SURPLUS: f64 = 1.5;
/// Fewest keypoints asked of one crop.
const MIN_RECT_FEATURES: i32 = 40;

/// Keypoints (offset by a crop's origin, kept inside `inner` if given, inside the image circle)
/// with their descriptors.
fn collect_keypoints(
    keypoints: &Vector<KeyPoint>,
    desc: &Mat,
    origin: (u32, u32),
    inner: Option<[f64; 4]>,
    camera: &dyn CameraModel,
    out: &mut Vec<(Keypoint, Descriptor)>,
) -> Result<()> {
    for (i, kp) in keypoints.iter().enumerate() {
        let p = kp.pt();
        let pixel = Point2::new(
            f64::from(p.x) + f64::from(origin.0),
            f64::from(p.y) + f64::from(origin.1),
        );
        if let Some([x0, y0, x1, y1]) = inner
            && !(pixel.x >= x0 && pixel.x < x1 && pixel.y >= y0 && pixel.y < y1)
        {
            continue;
        }
        let Some(bearing) = camera.unproject(&pixel) else {
            continue;
        };
        let row = desc
            .at_row::<u8>(i as i32)
            .map_err(cv_err("ORB descriptors"))?;
        if row.len() < 32 {
            continue;
        }
        out.push((
            Keypoint {
                pixel,
                bearing: bearing.into_inner(),
                octave: kp.octave(),
                response: kp.response(),
            },
            Descriptor::from_bytes(&row[..32]),
        ));
    }
    Ok(())
}

/// Sorted by response (strongest first, ties by position), so the order does not depend on
/// OpenCV's internal ordering.
fn sorted_features(mut out: Vec<(Keypoint, Descriptor)>) -> FrameFeatures {
    out.sort_by(|a, b| {
        b.0.response
            .total_cmp(&a.0.response)
            .then(a.0.pixel.y.total_cmp(&b.0.pixel.y))
            .then(a.0.pixel.x.total_cmp(&b.0.pixel.x))
    });
    let (keypoints, descriptors) = out.into_iter().unzip();
    FrameFeatures {
        keypoints,
        descriptors,
    }
}

/// Settings of descriptor matching.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MatchOptions {
    /// Largest Hamming distance of a match (of 256 bits).
    pub max_distance: u32,
    /// Lowe's ratio: best distance must be below `ratio ×` the second best.
    pub ratio: f32,
    /// Keep only mutual best matches.
    pub mutual: bool,
}

impl Default for MatchOptions {
    fn default() -> Self {
        Self {
            // ORB-SLAM's "high" threshold for a reliable match.
            max_distance: 64,
            ratio: 0.8,
            mutual: true,
        }
    }
}

/// A descriptor match `query[query_index] ↔ train[train_index]`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct DescriptorMatch {
    /// Index in the query set.
    pub query: usize,
    /// Index in the train set.
    pub train: usize,
    /// Hamming distance.
    pub distance: u32,
}

/// Best and second-best train index and distance for one descriptor (ties keep the lower index).
fn best_two(d: &Descriptor, train: &[Descriptor]) -> (usize, u32, u32) {
    let (mut bi, mut bd, mut sd) = (usize::MAX, u32::MAX, u32::MAX);
    for (j, t) in train.iter().enumerate() {
        let dist = d.distance(t);
        if dist < bd {
            sd = bd;
            bd = dist;
            bi = j;
        } else if dist < sd {
            sd = dist;
        }
    }
    (bi, bd, sd)
}

/// Brute-force Hamming matching with distance, ratio and (optionally) mutual checks; output in
/// query order. Deterministic.
pub fn match_descriptors(
    query: &[Descriptor],
    train: &[Descriptor],
    options: &MatchOptions,
) -> Vec<DescriptorMatch> {
    let mut reverse: Vec<Option<usize>> = vec![None; train.len()];
    if options.mutual {
        for (j, t) in train.iter().enumerate() {
            let (bi, bd, _) = best_two(t, query);
            if bi != usize::MAX && bd <= options.max_distance {
                reverse[j] = Some(bi);
            }
        }
    }
    let mut out = Vec::new();
    for (i, q) in query.iter().enumerate() {
        let (bj, bd, sd) = best_two(q, train);
        if bj == usize::MAX || bd > options.max_distance {
            continue;
        }
        if sd != u32::MAX && (bd as f32) >= options.ratio * sd as f32 {
            continue;
        }
        if options.mutual && reverse[bj] != Some(i) {
            continue;
        }
        out.push(DescriptorMatch {
            query: i,
            train: bj,
            distance: bd,
        });
    }
    out
}

/// Brute-force Hamming matching of `query` to groups of train descriptors: `train[j]` belongs to
/// group `groups[j]` (e.g. the keyframe views of one landmark), and a query matches the group of
/// its nearest train descriptor. The ratio test compares the best distance with the best
/// distance to any *other* group (several views of one landmark do not make it ambiguous); the
/// mutual check asks that the matched group's nearest query (over all its views) is this one.
/// `DescriptorMatch::train` is the group. Output in query order; deterministic.
pub fn match_descriptor_groups(
    query: &[Descriptor],
    train: &[Descriptor],
    groups: &[u32],
    options: &MatchOptions,
) -> Vec<DescriptorMatch> {
    let n_groups = groups.iter().map(|&g| g as usize + 1).max().unwrap_or(0);
    // Per group: (best distance, query index) over all of the group's views.
    let mut reverse: Vec<(u32, usize)> = vec![(u32::MAX, usize::MAX); n_groups];
    let mut out = Vec::new();
    for (i, q) in query.iter().enumerate() {
        let (mut bg, mut bd) = (u32::MAX, u32::MAX);
        let mut sd = u32::MAX;
        for (t, &g) in train.iter().zip(groups) {
            let dist = q.distance(t);
            let r = &mut reverse[g as usize];
            if dist < r.0 {
                *r = (dist, i);
            }
            if g == bg {
                bd = bd.min(dist);
            } else if dist < bd {
                sd = bd;
                bd = dist;
                bg = g;
            } else if dist < sd {
                sd = dist;
            }
        }
        if bg == u32::MAX || bd > options.max_distance {
            continue;
        }
        if sd != u32::MAX && (bd as f32) >= options.ratio * sd as f32 {
            continue;
        }
        out.push(DescriptorMatch {
            query: i,
            train: bg as usize,
            distance: bd,
        });
    }
    if options.mutual {
        out.retain(|m| reverse[m.train].1 == m.query);
    }
    out
}

/// Brute-force Hamming matching of `query` to groups of train descriptors (as
/// [`match_descriptor_groups`]) that keeps an ambiguous keypoint's few candidates instead of
/// dropping it: every group whose nearest view is within `max_distance` and no farther than the
/// best group's distance divided by `options.ratio` is proposed, as long as there are at most
/// `max_candidates` such groups (a keypoint on a tile that recurs a dozen times in the train
/// set says nothing). No mutual check (the copies of a repeated pattern all prefer the same
/// query keypoint). Meant for repeated texture, where the right landmark is one of a few
/// look-alikes and a robust estimator chooses among them. Output in query order, each
/// keypoint's candidates by distance; deterministic.
pub fn match_descriptor_groups_ambiguous(
    query: &[Descriptor],
    train: &[Descriptor],
    groups: &[u32],
    options: &MatchOptions,
    max_candidates: usize,
) -> Vec<DescriptorMatch> {
    let k = max_candidates.max(1);
    let mut out = Vec::new();
    // The k + 1 nearest distinct groups of one query: (distance, group), sorted.
    let mut near: Vec<(u32, u32)> = Vec::with_capacity(k + 2);
    for (i, q) in query.iter().enumerate() {
        near.clear();
        for (t, &g) in train.iter().zip(groups) {
            let dist = q.distance(t);
            if dist > options.max_distance {
                continue;
            }
            if near.len() > k && dist >= near[k].0 {
                continue;
            }
            if let Some(pos) = near.iter().position(|e| e.1 == g) {
                if dist < near[pos].0 {
                    near[pos].0 = dist;
                } else {
                    continue;
                }
            } else {
                near.push((dist, g));
            }
            near.sort_unstable();
            near.truncate(k + 1);
        }
        let Some(&(best, _)) = near.first() else {
            continue;
        };
        let limit = best as f32 / options.ratio;
        let close: Vec<(u32, u32)> = near
            .iter()
            .copied()
            .filter(|&(d, _)| (d as f32) <= limit)
            .collect();
        if close.len() > k {
            continue;
        }
        out.extend(close.into_iter().map(|(d, g)| DescriptorMatch {
            query: i,
            train: g as usize,
            distance: d,
        }));
    }
    out
}

/// Settings of pyramidal Lucas–Kanade tracking.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct KltOptions {
    /// Window side (px).
    pub window: i32,
    /// Pyramid levels above the base image.
    pub levels: i32,
    /// Largest forward–backward disagreement (px) of a kept track.
    pub max_forward_backward_px: f64,
    /// Iterations per level.
    pub iterations: i32,
}

impl Default for KltOptions {
    fn default() -> Self {
        Self {
            window: 21,
            levels: 3,
            // Sub-pixel round trips only: a drifting track is worse than a lost one.
            max_forward_backward_px: 0.5,
            iterations: 30,
        }
    }
}

/// A tracked point: its new pixel and bearing.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Track {
    /// Pixel in the next image.
    pub pixel: Point2<f64>,
    /// Unit bearing in the next image.
    pub bearing: Vector3<f64>,
}

/// Track pixels from `prev` into `next` with pyramidal KLT and a forward–backward check; `None`
/// for points lost, inconsistent, outside `mask`, or outside the lens's image circle.
pub fn track_klt(
    prev: &GrayImage,
    next: &GrayImage,
    points: &[Point2<f64>],
    mask: Option<&Mask>,
    camera: &dyn CameraModel,
    options: &KltOptions,
) -> Result<Vec<Option<Track>>> {
    if points.is_empty() {
        return Ok(Vec::new());
    }
    let a = prev.as_mat()?;
    let b = next.as_mat()?;
    klt_forward_backward(&a, &b, points, mask, camera, options)
}

/// A frame's KLT image pyramid (with derivatives), built once and reused for the forward and
/// backward passes and for tracking into the next frame.
pub struct KltPyramid {
    levels: Vector<Mat>,
    width: u32,
    height: u32,
}

impl KltPyramid {
    /// Build the pyramid of `image` for `options`' window and levels (the pixels are copied).
    pub fn new(image: &GrayImage, options: &KltOptions) -> Result<Self> {
        let img = image.as_mat()?;
        let mut levels = Vector::<Mat>::new();
        opencv::video::build_optical_flow_pyramid(
            &img,
            &mut levels,
            Size::new(options.window, options.window),
            options.levels,
            true,
            opencv::core::BORDER_REFLECT_101,
            opencv::core::BORDER_CONSTANT,
            false,
        )
        .map_err(cv_err("KLT pyramid"))?;
        Ok(Self {
            levels,
            width: image.width,
            height: image.height,
        })
    }
}

/// [`track_klt`] on prebuilt pyramids (same window and levels as they were built with).
pub fn track_klt_pyramids(
    prev: &KltPyramid,
    next: &KltPyramid,
    points: &[Point2<f64>],
    mask: Option<&Mask>,
    camera: &dyn CameraModel,
    options: &KltOptions,
) -> Result<Vec<Option<Track>>> {
    if points.is_empty() {
        return Ok(Vec::new());
    }
    if (prev.width, prev.height) != (next.width, next.height) {
        return Err(BackendError::Vision {
            context: "KLT".into(),
            message: format!(
                "expected frames of one size, found {}x{} then {}x{}",
                prev.width, prev.height, next.width, next.height
            ),
        });
    }
    klt_forward_backward(&prev.levels, &next.levels, points, mask, camera, options)
}

/// Forward–backward pyramidal KLT from `prev` to `next` (images or prebuilt pyramids): a point is
/// kept when both directions converge, it returns within the forward–backward threshold, lands
/// inside the mask and the image, and unprojects to a bearing.
fn klt_forward_backward<I: opencv::core::ToInputArray>(
    prev: &I,
    next: &I,
    points: &[Point2<f64>],
    mask: Option<&Mask>,
    camera: &dyn CameraModel,
    options: &KltOptions,
) -> Result<Vec<Option<Track>>> {
    let pts: Vector<Point2f> = points
        .iter()
        .map(|p| Point2f::new(p.x as f32, p.y as f32))
        .collect();
    let criteria = TermCriteria::new(
        TermCriteria_Type::COUNT as i32 + TermCriteria_Type::EPS as i32,
        options.iterations,
        0.01,
    )
    .map_err(cv_err("KLT"))?;
    let win = Size::new(options.window, options.window);
    let run = |from: &I, to: &I, src: &Vector<Point2f>| -> Result<(Vector<Point2f>, Vector<u8>)> {
        let mut dst = Vector::<Point2f>::new();
        let mut status = Vector::<u8>::new();
        let mut err = Vector::<f32>::new();
        opencv::video::calc_optical_flow_pyr_lk(
            from,
            to,
            src,
            &mut dst,
            &mut status,
            &mut err,
            win,
            options.levels,
            criteria,
            0,
            1e-4,
        )
        .map_err(cv_err("KLT"))?;
        Ok((dst, status))
    };
    let (fwd, st1) = run(prev, next, &pts)?;
    let (bwd, st2) = run(next, prev, &fwd)?;
    let mut out = Vec::with_capacity(points.len());
    for i in 0..points.len() {
        let ok = st1.get(i).unwrap_or(0) != 0 && st2.get(i).unwrap_or(0) != 0;
        let (Ok(f), Ok(back)) = (fwd.get(i), bwd.get(i)) else {
            out.push(None);
            continue;
        };
        let fb = (f64::from(back.x) - points[i].x).hypot(f64::from(back.y) - points[i].y);
        let pixel = Point2::new(f64::from(f.x), f64::from(f.y));
        let in_mask =
            mask.is_none_or(|m| m.get(pixel.x.round() as i64, pixel.y.round() as i64) > 0);
        if !ok || fb > options.max_forward_backward_px || !in_mask || !camera.in_image(&pixel) {
            out.push(None);
            continue;
        }
        out.push(camera.unproject(&pixel).map(|b| Track {
            pixel,
            bearing: b.into_inner(),
        }));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rounding_to_u8_matches_round_and_clamp() {
        let edges = [
            f32::NAN,
            f32::NEG_INFINITY,
            f32::INFINITY,
            -0.5,
            -0.49999997,
            0.49999997,
            0.5,
            254.5,
            255.49998,
            255.5,
            256.0,
            1e9,
        ];
        let sweep = (-2000..300_000).map(|k| k as f32 * 0.000_977 - 1.0);
        for v in edges.into_iter().chain(sweep) {
            assert_eq!(round_to_u8(v), v.round().clamp(0.0, 255.0) as u8, "{v}");
        }
        // Every value just below and at each half.
        for k in 0..=256 {
            let half = k as f32 + 0.5;
            for v in [half, f32::from_bits(half.to_bits() - 1)] {
                assert_eq!(round_to_u8(v), v.round().clamp(0.0, 255.0) as u8, "{v}");
            }
        }
    }

    #[test]
    fn sampling_inside_gives_the_bounds_checked_values_exactly() {
        let (w, h) = (7u32, 5u32);
        let data: Vec<u8> = (0..w * h).map(|k| ((k * 37 + 11) % 256) as u8).collect();
        let image = GrayImage::new(w, h, data).unwrap();
        let mut checked = 0;
        for j in -8..=48 {
            for i in -8..=64 {
                let (x, y) = (f64::from(i) * 0.125 - 0.3, f64::from(j) * 0.125 - 0.2);
                assert_eq!(
                    image.sample(x, y).to_bits(),
                    image.sample_bounded(x, y).to_bits(),
                    "({x}, {y})"
                );
                checked += 1;
            }
        }
        assert!(checked > 3000);
        // Beyond the last row and column the missing neighbours are 0.
        assert_eq!(image.sample(6.5, 0.0), 0.5 * f32::from(image.get(6, 0)));
    }

    /// A descriptor with the first `ones` bits set.
    fn bits(ones: u32) -> Descriptor {
        let mut d = [0u64; 4];
        for i in 0..ones as usize {
            d[i / 64] |= 1 << (i % 64);
        }
        Descriptor(d)
    }

    #[test]
    fn grouped_matching_compares_with_the_nearest_view_and_other_groups_only() {
        let options = MatchOptions::default();
        // Landmark 0 has two views far apart (0 and 120 bits); landmark 1 sits at 200 bits.
        let train = [bits(0), bits(120), bits(200)];
        let groups = [0, 0, 1];
        // A query 2 bits from the second view: its nearest other view (same landmark, 118 bits)
        // must not count as an ambiguity; the other landmark is 78 bits away.
        let m = match_descriptor_groups(&[bits(122)], &train, &groups, &options);
        assert_eq!(m.len(), 1);
        assert_eq!((m[0].query, m[0].train, m[0].distance), (0, 0, 2));
        // Halfway between two landmarks' views: ambiguous, refused by the ratio test.
        let m = match_descriptor_groups(&[bits(160)], &train, &groups, &options);
        assert!(m.is_empty(), "{m:?}");
        // Two queries near landmark 0: only its nearest (over both views) is kept (mutual).
        let m = match_descriptor_groups(&[bits(4), bits(121)], &train, &groups, &options);
        assert_eq!(m.len(), 1);
        assert_eq!((m[0].query, m[0].train), (1, 0));
        // Too far from everything.
        let strict = MatchOptions {
            max_distance: 10,
            ..options
        };
        assert!(match_descriptor_groups(&[bits(60)], &train, &groups, &strict).is_empty());
    }
}
