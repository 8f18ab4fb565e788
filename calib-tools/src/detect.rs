//! Aprilgrid corner detection in fisheye images, and the corners file (`corners.json`) that
//! `kiwi-calib detect` writes and `kiwi-calib intrinsics --corners` reads.
//!
//! Detection (deterministic: the same images give bit-identical corners with any thread
//! count):
//! 1. OpenCV's aruco (`DICT_APRILTAG_36h11`, Kalibr's two-cell tag border) reads the tags it can
//!    as they are; the image dilated by 1 and 2 px parts the tags from the aprilgrid's corner
//!    squares, and the candidate quads found there are cut out into a mosaic of isolated tiles
//!    that aruco decodes. Images under 960 px are upscaled ×2 first. A coarse `cornerSubPix`
//!    (9 × 9 at 960 px, scaled with the resolution) brings aruco's outline corners (1–3 px off)
//!    onto the grid corners; a tag whose corner moves more than 0.2 tag sides is dropped.
//! 2. Every corner is refined with `cornerSubPix` on a 5 × 5 window, as Kalibr does, and a tag
//!    whose refinement moves any corner by more than √1.5 px is dropped; tags touching the
//!    image border are dropped. Below 960 px a quadratic saddle fit refines further.
//! 3. Second pass, two rounds: a KB4 lens and every image's board pose are fitted to the
//!    corners so far; tags the pose does not explain are dropped; the tags the pose puts in the
//!    image but that are missing are decoded where predicted, or kept undecoded when all four
//!    predicted corners refine onto aprilgrid saddles within 1.5 px; what is still missing is
//!    searched in small perspective views rendered through the lens (a fixed ring of views for
//!    images without a pose).
//!
//! Images run in parallel (rayon) with a progress bar.
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

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use image::{DynamicImage, GrayImage};
use indicatif::{ProgressBar, ProgressStyle};
use nalgebra::{Matrix3, Point2, Vector3};
use opencv::core::{Mat, Point2f, Size, TermCriteria, TermCriteria_Type, Vector};
use opencv::prelude::*;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use kiwi_core::camera::{Camera, CameraModel};
use kiwi_core::geometry::Pose;
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

/// Corner order OpenCV's aruco returns (the tag's own top-left, top-right, bottom-right,
/// bottom-left) as Kalibr corner indices (0 BL, 1 BR, 2 TR, 3 TL in the board frame); measured
/// against the simulator's exact corners.
const ARUCO_TO_KALIBR: [usize; 4] = [1, 0, 3, 2];
/// Kalibr draws its aprilgrid tags with a black border two cells wide (10 × 10 cells per tag;
/// `kalibr_create_target_pdf`'s `borderBits=2`), not apriltag's one.
const KALIBR_BORDER_BITS: i32 = 2;
/// Half window (px) of the coarse refinement of aruco's corners (a 9 × 9 window: reaches a
/// corner 3 px away while seeing little more than the tag border and the corner square).
const ARUCO_COARSE_HALF_WINDOW: i32 = 4;
/// A tag is dropped if the coarse refinement moves a corner further than this (px): it was
/// not near a corner of the grid.
const ARUCO_COARSE_MAX_MOVE_PX: f64 = 4.0;
/// Images smaller than this (px, larger side) are upscaled by an integer factor for the first
/// pass: at 480 px the tag cells are ~1.3 px and aruco reads few tags.
const FIRST_PASS_MIN_SIDE_PX: u32 = 960;
/// Coarse refinement may move a corner by at most this fraction of the tag's shortest side
/// (the neighbouring saddle is 0.3 sides away).
const COARSE_MAX_MOVE_SIDE_FRACTION: f64 = 0.2;
/// Dilations (3 × 3 each) whose candidate quads are decoded in the mosaic.
const ARUCO_DILATIONS: usize = 2;
/// Mosaic tiles: the candidate's tag square (px) and the white margin around it (px); 6 px
/// per cell of the 10 × 10 cell tag.
const MOSAIC_TAG_PX: u32 = 60;
const MOSAIC_MARGIN_PX: u32 = 20;
/// Candidate quads smaller than this (px²) cannot hold a readable tag.
const MIN_CANDIDATE_AREA_PX2: f64 = 16.0;
/// Sightings of one tag from nested candidates count as one if their corners agree within
/// this (px); otherwise the tag is ambiguous and dropped.
const SAME_TAG_PX: f64 = 2.0;
/// A predicted tag is kept undecoded only if refinement moves none of its corners further than
/// this (px): a corner that far off the prediction may be a neighbour's.
const PREDICTED_MAX_MOVE_PX: f64 = 1.5;
/// Saddle check probes: this fraction of the tag's shortest side away from the corner,
/// clamped to [min, max] px (inside the tag border and the corner square, which are 0.2 and
/// 0.3 tag sides wide).
const SADDLE_PROBE_FRACTION: f64 = 0.1;
const SADDLE_PROBE_MIN_PX: f64 = 1.5;
const SADDLE_PROBE_MAX_PX: f64 = 5.0;
/// Brightness (grey levels) the gaps must exceed the tag and corner square by at a saddle.
const SADDLE_MIN_CONTRAST: f64 = 40.0;
/// Smallest tag perimeter aruco considers, as a fraction of the larger image side: 0.02 of a
/// 960 px image is a 5 px tag side, the smallest whose 8 × 8 cells can still be read.
const ARUCO_MIN_PERIMETER_RATE: f64 = 0.02;

/// Tag quads `(id, [4 corners in Kalibr order])` found by OpenCV's aruco (36h11) in a grey
/// image, sorted by id; ids outside the target and ids seen at disagreeing places are left out.
///
/// In an aprilgrid each tag's black border touches the black corner squares at its corners, so
/// the border's outline is not a quad and aruco rarely finds the tag as it is. So: the image is
/// dilated by a pixel (grows the white, parting the tags from the squares) and aruco's
/// candidate quads there are collected; each candidate is cut out of the original image into
/// its own tile of a mosaic with a white surround, aruco decodes the mosaic, and the decoded
/// tags' corners are mapped back. Deterministic: every step is a fixed sequence.
fn aruco_quads(
    gray: &GrayImage,
    tag_count: usize,
    coarse_half: i32,
) -> Result<Vec<(u32, [Point2<f64>; 4])>> {
    let cv = |e: opencv::Error| CalibError::Internal(format!("OpenCV aruco: {e}"));
    let mat =
        Mat::new_rows_cols_with_data(gray.height() as i32, gray.width() as i32, gray.as_raw())
            .map_err(cv)?;
    // Tags aruco reads as they are, then candidate quads of the image and of the image
    // dilated by 1 and 2 px (wider blur joins tags and squares over more pixels).
    let plain = aruco_detect(&mat)?;
    let mut candidates: Vec<[Point2<f64>; 4]> = plain.rejected.clone();
    let mut dilated = mat.try_clone().map_err(cv)?;
    for _ in 0..ARUCO_DILATIONS {
        let mut next = Mat::default();
        opencv::imgproc::dilate_def(&dilated, &mut next, &Mat::default()).map_err(cv)?;
        dilated = next;
        let found = aruco_detect(&dilated)?;
        candidates.extend(found.decoded.iter().map(|(_, q)| *q));
        candidates.extend(found.rejected);
    }
    let candidates: Vec<[Point2<f64>; 4]> = candidates.iter().filter_map(clockwise).collect();
    let mut quads: Vec<(u32, [Point2<f64>; 4])> = Vec::new();
    for (id, q) in &plain.decoded {
        if (*id as usize) < tag_count {
            let mut out = [Point2::origin(); 4];
            for (j, p) in q.iter().enumerate() {
                out[ARUCO_TO_KALIBR[j]] = *p;
            }
            quads.push((*id, out));
        }
    }
    quads.extend(decode_candidates(gray, &candidates, tag_count)?);
    finish_quads(gray, quads, coarse_half)
}

/// The first pass's tag quads in a grey image: small images are first upscaled (so aruco
/// sees tag cells of ~2 px and more) and the quads mapped back.
fn first_pass_quads(gray: &GrayImage, tag_count: usize) -> Result<Vec<(u32, [Point2<f64>; 4])>> {
    let side = gray.width().max(gray.height());
    let k = FIRST_PASS_MIN_SIDE_PX.div_ceil(side.max(1)).max(1);
    if k == 1 {
        return aruco_quads(gray, tag_count, ARUCO_COARSE_HALF_WINDOW);
    }
    let cv = |e: opencv::Error| CalibError::Internal(format!("OpenCV resize: {e}"));
    let mat =
        Mat::new_rows_cols_with_data(gray.height() as i32, gray.width() as i32, gray.as_raw())
            .map_err(cv)?;
    let mut up = Mat::default();
    opencv::imgproc::resize(
        &mat,
        &mut up,
        Size::new(0, 0),
        f64::from(k),
        f64::from(k),
        opencv::imgproc::INTER_LINEAR,
    )
    .map_err(cv)?;
    let bytes = up.data_bytes().map_err(cv)?.to_vec();
    let Some(big) = GrayImage::from_raw(gray.width() * k, gray.height() * k, bytes) else {
        return Err(CalibError::Internal(
            "upscaled image has the wrong size".into(),
        ));
    };
    let kf = f64::from(k);
    // OpenCV's resize puts source pixel x at (x + 0.5)·k − 0.5.
    let back = |p: &Point2<f64>| Point2::new((p.x + 0.5) / kf - 0.5, (p.y + 0.5) / kf - 0.5);
    Ok(aruco_quads(&big, tag_count, ARUCO_COARSE_HALF_WINDOW)?
        .into_iter()
        .map(|(id, q)| (id, [back(&q[0]), back(&q[1]), back(&q[2]), back(&q[3])]))
        .collect())
}

/// Half window of the coarse refinement in an image of this size: [`ARUCO_COARSE_HALF_WINDOW`]
/// at 960 px and up, scaled down with the resolution (tags shrink with it), at least the final
/// window's.
fn coarse_half_window(gray: &GrayImage) -> i32 {
    let side = f64::from(gray.width().max(gray.height()));
    let full = f64::from(FIRST_PASS_MIN_SIDE_PX);
    let h = (f64::from(ARUCO_COARSE_HALF_WINDOW) * side / full).round() as i32;
    h.clamp(SUBPIX_HALF_WINDOW, ARUCO_COARSE_HALF_WINDOW)
}

/// Largest move (px) the coarse refinement may make on a tag's corners: the neighbouring
/// saddle (the far corner of the corner square) lies 0.3 tag sides away, so a corner that moved
/// near that far may have jumped to it.
fn coarse_move_limit(q: &[Point2<f64>; 4]) -> f64 {
    let side = (0..4)
        .map(|i| (q[i] - q[(i + 1) % 4]).norm())
        .fold(f64::INFINITY, f64::min);
    (COARSE_MAX_MOVE_SIDE_FRACTION * side).min(ARUCO_COARSE_MAX_MOVE_PX)
}

/// Cut each candidate quad out of `gray` into its own tile of a mosaic (white surround), let
/// aruco decode the mosaic, and map the decoded tags' corners (Kalibr order) back.
fn decode_candidates(
    gray: &GrayImage,
    candidates: &[[Point2<f64>; 4]],
    tag_count: usize,
) -> Result<Vec<(u32, [Point2<f64>; 4])>> {
    let cv = |e: opencv::Error| CalibError::Internal(format!("OpenCV aruco: {e}"));
    let mut quads = Vec::new();
    if candidates.is_empty() {
        return Ok(quads);
    }
    // The mosaic: candidate k fills the tag square of tile k, the rest of the tile is white.
    let per_row = ((candidates.len() as f64).sqrt().ceil() as u32).max(1);
    let rows = (candidates.len() as u32).div_ceil(per_row).max(1);
    let (m, side) = (MOSAIC_MARGIN_PX, MOSAIC_TAG_PX);
    let tile = side + 2 * m;
    let square = [
        Point2::new(f64::from(m), f64::from(m)),
        Point2::new(f64::from(m + side), f64::from(m)),
        Point2::new(f64::from(m + side), f64::from(m + side)),
        Point2::new(f64::from(m), f64::from(m + side)),
    ];
    let (w, h) = (f64::from(gray.width()), f64::from(gray.height()));
    let mut mosaic = GrayImage::from_pixel(per_row * tile, rows * tile, image::Luma([255]));
    let mut to_image: Vec<Option<Matrix3<f64>>> = Vec::with_capacity(candidates.len());
    for (k, quad) in candidates.iter().enumerate() {
        let Some(hm) = homography(&square, quad) else {
            to_image.push(None);
            continue;
        };
        let (ox, oy) = ((k as u32 % per_row) * tile, (k as u32 / per_row) * tile);
        for v in m..m + side {
            for u in m..m + side {
                let p = hm * Vector3::new(f64::from(u), f64::from(v), 1.0);
                let (x, y) = (p.x / p.z, p.y / p.z);
                if x >= 0.0 && y >= 0.0 && x < w - 1.0 && y < h - 1.0 {
                    mosaic.put_pixel(ox + u, oy + v, image::Luma([bilinear(gray, x, y)]));
                }
            }
        }
        to_image.push(Some(hm));
    }
    let mosaic_mat = Mat::new_rows_cols_with_data(
        mosaic.height() as i32,
        mosaic.width() as i32,
        mosaic.as_raw(),
    )
    .map_err(cv)?;
    let decoded = aruco_detect(&mosaic_mat)?.decoded;
    for (id, q) in decoded {
        if id as usize >= tag_count {
            continue;
        }
        let centre = (q[0].coords + q[1].coords + q[2].coords + q[3].coords) / 4.0;
        let (tx, ty) = (
            (centre.x / f64::from(tile)) as u32,
            (centre.y / f64::from(tile)) as u32,
        );
        let k = (ty * per_row + tx) as usize;
        let Some(Some(hm)) = to_image.get(k) else {
            continue;
        };
        let (ox, oy) = (f64::from(tx * tile), f64::from(ty * tile));
        let mut out = [Point2::origin(); 4];
        for (j, p) in q.iter().enumerate() {
            let r = hm * Vector3::new(p.x - ox, p.y - oy, 1.0);
            out[ARUCO_TO_KALIBR[j]] = Point2::new(r.x / r.z, r.y / r.z);
        }
        quads.push((id, out));
    }
    Ok(quads)
}

/// Sort by id, refine coarsely, and keep each tag once (dropping ids seen at disagreeing
/// places).
fn finish_quads(
    gray: &GrayImage,
    mut quads: Vec<(u32, [Point2<f64>; 4])>,
    coarse_half: i32,
) -> Result<Vec<(u32, [Point2<f64>; 4])>> {
    // Stable sort: candidates of one id keep aruco's order.
    quads.sort_by_key(|q| q.0);
    // aruco's corners lie on the thresholded outline, 1–3 px off the true corner (the outline
    // is bent by the lens and shrunk by the dilation): a coarse refinement on a wider window
    // brings them within reach of the final 5 × 5 one.
    let coarse = refine_corners_window(gray, &quads, coarse_half)?;
    for ((_, q), new) in quads.iter_mut().zip(coarse.chunks(4)) {
        let moved = q
            .iter()
            .zip(new)
            .map(|(a, b)| (a - b).norm())
            .fold(0.0, f64::max);
        if moved <= coarse_move_limit(q) {
            q.copy_from_slice(new);
        } else {
            q[0] = Point2::new(f64::NAN, f64::NAN);
        }
    }
    quads.retain(|q| q.1[0].x.is_finite());
    // One tag may come from nested candidates: keep it if they agree, drop it if not.
    let mut unique: Vec<(u32, [Point2<f64>; 4])> = Vec::with_capacity(quads.len());
    let mut conflicting = BTreeSet::new();
    for (id, q) in quads {
        match unique.last() {
            Some((last, first)) if *last == id => {
                let apart = first
                    .iter()
                    .zip(&q)
                    .map(|(a, b)| (a - b).norm())
                    .fold(0.0, f64::max);
                if apart > SAME_TAG_PX {
                    conflicting.insert(id);
                }
            }
            _ => unique.push((id, q)),
        }
    }
    unique.retain(|q| !conflicting.contains(&q.0));
    Ok(unique)
}

/// What one aruco call returned: decoded tags (corners in aruco's order) and the candidate
/// quads it could not decode.
struct ArucoOutput {
    decoded: Vec<(u32, [Point2<f64>; 4])>,
    rejected: Vec<[Point2<f64>; 4]>,
}

/// OpenCV aruco (36h11, Kalibr's two-cell border, no corner refinement) on an 8-bit image.
fn aruco_detect(mat: &impl opencv::core::ToInputArray) -> Result<ArucoOutput> {
    let cv = |e: opencv::Error| CalibError::Internal(format!("OpenCV aruco: {e}"));
    let dict = opencv::aruco::get_predefined_dictionary(
        opencv::aruco::PREDEFINED_DICTIONARY_NAME::DICT_APRILTAG_36h11,
    )
    .map_err(cv)?;
    let mut params = opencv::aruco::DetectorParameters::create().map_err(cv)?;
    params.set_corner_refinement_method(opencv::aruco::CORNER_REFINE_NONE);
    params.set_min_marker_perimeter_rate(ARUCO_MIN_PERIMETER_RATE);
    params.set_marker_border_bits(KALIBR_BORDER_BITS);
    let mut corners: Vector<Vector<Point2f>> = Vector::new();
    let mut ids: Vector<i32> = Vector::new();
    let mut rejected: Vector<Vector<Point2f>> = Vector::new();
    opencv::aruco::detect_markers(mat, &dict, &mut corners, &mut ids, &params, &mut rejected)
        .map_err(cv)?;
    let quad = |c: &Vector<Point2f>| -> Option<[Point2<f64>; 4]> {
        (c.len() == 4).then(|| {
            std::array::from_fn(|j| {
                c.get(j).map_or(Point2::new(f64::NAN, f64::NAN), |p| {
                    Point2::new(f64::from(p.x), f64::from(p.y))
                })
            })
        })
    };
    let mut out = ArucoOutput {
        decoded: Vec::new(),
        rejected: Vec::new(),
    };
    for (c, id) in corners.iter().zip(ids.iter()) {
        if let (Ok(id), Some(q)) = (u32::try_from(id), quad(&c)) {
            out.decoded.push((id, q));
        }
    }
    out.rejected = rejected.iter().filter_map(|c| quad(&c)).collect();
    Ok(out)
}

/// The quad in clockwise order on screen (y down), or `None` if degenerate or not finite.
fn clockwise(q: &[Point2<f64>; 4]) -> Option<[Point2<f64>; 4]> {
    if !q.iter().all(|p| p.x.is_finite() && p.y.is_finite()) {
        return None;
    }
    let area: f64 = (0..4)
        .map(|i| {
            let (a, b) = (q[i], q[(i + 1) % 4]);
            a.x * b.y - b.x * a.y
        })
        .sum::<f64>()
        / 2.0;
    if area.abs() < MIN_CANDIDATE_AREA_PX2 {
        None
    } else if area > 0.0 {
        Some(*q)
    } else {
        Some([q[0], q[3], q[2], q[1]])
    }
}

/// The homography mapping the four `from` points onto the four `to` points.
fn homography(from: &[Point2<f64>; 4], to: &[Point2<f64>; 4]) -> Option<Matrix3<f64>> {
    let mut a = nalgebra::SMatrix::<f64, 8, 8>::zeros();
    let mut b = nalgebra::SVector::<f64, 8>::zeros();
    for i in 0..4 {
        let (x, y, u, v) = (from[i].x, from[i].y, to[i].x, to[i].y);
        let r = 2 * i;
        a.set_row(
            r,
            &nalgebra::SMatrix::<f64, 1, 8>::from_row_slice(&[
                x,
                y,
                1.0,
                0.0,
                0.0,
                0.0,
                -u * x,
                -u * y,
            ]),
        );
        a.set_row(
            r + 1,
            &nalgebra::SMatrix::<f64, 1, 8>::from_row_slice(&[
                0.0,
                0.0,
                0.0,
                x,
                y,
                1.0,
                -v * x,
                -v * y,
            ]),
        );
        b[r] = u;
        b[r + 1] = v;
    }
    let h = a.lu().solve(&b)?;
    h.iter()
        .all(|x| x.is_finite())
        .then(|| Matrix3::new(h[0], h[1], h[2], h[3], h[4], h[5], h[6], h[7], 1.0))
}

/// Whether every corner lies at least [`MIN_BORDER_DISTANCE_PX`] inside a `w × h` image.
fn inside_border(pts: &[Point2<f64>], w: f64, h: f64) -> bool {
    pts.iter().all(|p| {
        p.x.is_finite()
            && p.y.is_finite()
            && p.x >= MIN_BORDER_DISTANCE_PX
            && p.y >= MIN_BORDER_DISTANCE_PX
            && p.x <= w - 1.0 - MIN_BORDER_DISTANCE_PX
            && p.y <= h - 1.0 - MIN_BORDER_DISTANCE_PX
    })
}

/// Aprilgrid detector for one target.
pub struct Detector {
    target: AprilGridTarget,
    /// The `aprilgrid` crate's detector, for [`Detector::detect`] only.
    crate_detector: aprilgrid::detector::TagDetector,
}

/// Corner order the `aprilgrid` crate returns, as Kalibr corner indices; measured against the
/// simulator's exact corners.
const APRILGRID_CRATE_TO_KALIBR: [usize; 4] = [0, 1, 2, 3];

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
            crate_detector: aprilgrid::detector::TagDetector::new(
                &aprilgrid::TagFamily::T36H11,
                Some(aprilgrid::detector::DetectorParams {
                    tag_spacing_ratio: target.spacing as f32,
                    ..aprilgrid::detector::DetectorParams::default_params()
                }),
            ),
        }
    }

    /// Detect the target's corners in a grey image with the `aprilgrid` crate (saddle-based;
    /// finds more tags than aruco in motion-blurred frames) and the same refinement. NOT
    /// deterministic: the crate's board search iterates std `HashMap`s, so which tags are
    /// found can vary from run to run. Used by the camera–IMU tracker; calibration images go
    /// through [`Detector::detect_first_pass`].
    pub fn detect(&self, gray: &GrayImage) -> Result<Detection> {
        let tags = self
            .crate_detector
            .detect(&DynamicImage::ImageLuma8(gray.clone()));
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
            let mut pts = [Point2::origin(); 4];
            for (j, (x, y)) in quad.iter().enumerate() {
                pts[APRILGRID_CRATE_TO_KALIBR[j]] = Point2::new(f64::from(*x), f64::from(*y));
            }
            if inside_border(&pts, w, h) {
                raw.push((id, pts));
            } else {
                dropped += 1;
            }
        }
        self.refine_and_number(gray, &raw, dropped, false)
    }

    /// Detect the target's corners in a grey image, deterministically, with OpenCV's aruco
    /// (first pass of [`detect_folder`]: the whole image at once).
    pub fn detect_first_pass(&self, gray: &GrayImage) -> Result<Detection> {
        let (w, h) = (f64::from(gray.width()), f64::from(gray.height()));
        let mut raw = Vec::new();
        let mut dropped = 0;
        for (id, pts) in first_pass_quads(gray, self.target.tag_count())? {
            if inside_border(&pts, w, h) {
                raw.push((id, pts));
            } else {
                dropped += 1;
            }
        }
        self.refine_and_number(gray, &raw, dropped, true)
    }

    /// Refine the tags' corners, drop tags whose refinement moved too far, number the corners.
    fn refine_and_number(
        &self,
        gray: &GrayImage,
        raw: &[(u32, [Point2<f64>; 4])],
        dropped: usize,
        saddle: bool,
    ) -> Result<Detection> {
        if raw.is_empty() {
            return Ok(Detection {
                tags: Vec::new(),
                corners: Vec::new(),
                dropped_tags: dropped,
            });
        }
        let mut refined = refine_corners(gray, raw)?;
        if saddle && gray.width().max(gray.height()) < SADDLE_FIT_MAX_SIDE_PX {
            let smooth = SmoothImage::new(gray)?;
            for p in &mut refined {
                if let Some(q) = smooth.saddle(p) {
                    *p = q;
                }
            }
        }
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
                let point = self.target.corner_point_id(*id as usize, j);
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

/// A locally rectified (perspective) view into the fisheye image.
struct RectifiedView {
    /// Columns: the view's x, y and optical axis in the camera frame.
    rot: Matrix3<f64>,
    /// Focal length (px) of the view.
    f: f64,
}

impl RectifiedView {
    /// A view looking along `axis` (camera frame) with focal length `f` (px).
    fn along(axis: &Vector3<f64>, f: f64) -> Self {
        let z = axis.normalize();
        let helper = if z.x.abs() < 0.9 {
            Vector3::x()
        } else {
            Vector3::y()
        };
        let y = z.cross(&helper).normalize();
        let x = y.cross(&z);
        Self {
            rot: Matrix3::from_columns(&[x, y, z]),
            f,
        }
    }

    /// Focal length (px) of a view of [`RECTIFY_FOV_DEG`].
    fn wide_focal() -> f64 {
        f64::from(RECTIFY_SIDE - 1) / 2.0 / (RECTIFY_FOV_DEG.to_radians() / 2.0).tan()
    }

    /// Camera-frame ray of view pixel (u, v).
    fn ray(&self, u: f64, v: f64) -> Vector3<f64> {
        let half = f64::from(RECTIFY_SIDE - 1) / 2.0;
        self.rot * Vector3::new((u - half) / self.f, (v - half) / self.f, 1.0)
    }

    /// View pixel of a camera-frame direction, if it lies in front of the view.
    fn pixel(&self, ray: &Vector3<f64>) -> Option<Point2<f64>> {
        let half = f64::from(RECTIFY_SIDE - 1) / 2.0;
        let r = self.rot.transpose() * ray;
        (r.z > 1e-6).then(|| Point2::new(half + self.f * r.x / r.z, half + self.f * r.y / r.z))
    }

    /// Render the view from the fisheye image through `camera`; `None` when less than a
    /// quarter of it falls inside the image.
    fn render(&self, gray: &GrayImage, camera: &Camera) -> Option<GrayImage> {
        let (w, h) = (f64::from(gray.width()), f64::from(gray.height()));
        let mut view = GrayImage::new(RECTIFY_SIDE, RECTIFY_SIDE);
        let mut inside = 0usize;
        for (u, v, px) in view.enumerate_pixels_mut() {
            if let Some(p) = camera.project(&self.ray(f64::from(u), f64::from(v)))
                && p.x >= 0.0
                && p.y >= 0.0
                && p.x < w - 1.0
                && p.y < h - 1.0
            {
                px[0] = bilinear(gray, p.x, p.y);
                inside += 1;
            }
        }
        (inside * 4 >= (RECTIFY_SIDE * RECTIFY_SIDE) as usize).then_some(view)
    }
}

impl Detector {
    /// Where to look in the second pass. With the board pose known (`cam_from_board`, from the
    /// first-pass fit), one view is centred on each tag the first pass missed that should be
    /// in the image, and a view covers every other missing tag that falls well inside it;
    /// without a pose, a fixed ring of views around the periphery.
    fn plan_views(
        &self,
        camera: &Camera,
        known: &BTreeSet<u32>,
        cam_from_board: Option<&Pose>,
    ) -> Vec<RectifiedView> {
        let Some(pose) = cam_from_board else {
            let mut views = Vec::new();
            for theta in RECTIFY_THETAS_DEG {
                if theta.to_radians() > camera.valid_fov() / 2.0 {
                    continue;
                }
                for k in 0..RECTIFY_AZIMUTHS {
                    let phi = std::f64::consts::TAU * (k as f64 + 0.5 * (theta / 40.0).floor())
                        / RECTIFY_AZIMUTHS as f64;
                    let axis = kiwi_core::camera::bearing_from_angles(theta.to_radians(), phi);
                    views.push(RectifiedView::along(&axis, RectifiedView::wide_focal()));
                }
            }
            return views;
        };
        let missing = self.missing_tags(camera, known, pose);
        let margin = RECTIFY_MARGIN_PX;
        let max = f64::from(RECTIFY_SIDE - 1) - margin;
        let mut covered = vec![false; missing.len()];
        let mut views = Vec::new();
        for i in 0..missing.len() {
            if covered[i] {
                continue;
            }
            let centre: Vector3<f64> = missing[i].iter().map(nalgebra::Matrix::normalize).sum();
            let view = RectifiedView::along(&centre, RectifiedView::wide_focal());
            for (j, tag) in missing.iter().enumerate() {
                covered[j] = covered[j]
                    || tag.iter().all(|c| {
                        view.pixel(c).is_some_and(|p| {
                            p.x >= margin && p.y >= margin && p.x <= max && p.y <= max
                        })
                    });
            }
            covered[i] = true;
            views.push(view);
        }
        views
    }

    /// Corners (camera frame, Kalibr order) of every tag the board pose puts inside the image
    /// that `known` does not hold.
    fn missing_tags(
        &self,
        camera: &Camera,
        known: &BTreeSet<u32>,
        pose: &Pose,
    ) -> Vec<[Vector3<f64>; 4]> {
        let (w, h) = camera.resolution();
        let (w, h) = (f64::from(w), f64::from(h));
        let mut missing = Vec::new();
        for tag in 0..self.target.tag_count() {
            if known.contains(&(tag as u32)) {
                continue;
            }
            let corners: [Vector3<f64>; 4] = std::array::from_fn(|k| {
                let b = self.target.point(self.target.corner_point_id(tag, k));
                pose.transform_point(&nalgebra::Point3::from(b)).coords
            });
            let pixels: Option<Vec<Point2<f64>>> =
                corners.iter().map(|c| camera.project(c)).collect();
            if pixels.is_some_and(|p| inside_border(&p, w, h)) {
                missing.push(corners);
            }
        }
        missing
    }

    /// Tags of the board at `pose` missing from `known` whose predicted corners all refine
    /// (coarse window) by at most [`PREDICTED_MAX_MOVE_PX`] onto an aprilgrid saddle.
    fn predicted_saddles(
        &self,
        gray: &GrayImage,
        camera: &Camera,
        known: &BTreeSet<u32>,
        pose: &Pose,
    ) -> Result<Vec<(u32, [Point2<f64>; 4])>> {
        let mut tags: Vec<(u32, [Point2<f64>; 4])> = Vec::new();
        for tag in 0..self.target.tag_count() as u32 {
            if known.contains(&tag) {
                continue;
            }
            let px: Option<Vec<Point2<f64>>> = (0..4)
                .map(|k| {
                    let b = self
                        .target
                        .point(self.target.corner_point_id(tag as usize, k));
                    camera.project(&pose.transform_point(&nalgebra::Point3::from(b)).coords)
                })
                .collect();
            if let Some(px) = px {
                tags.push((tag, [px[0], px[1], px[2], px[3]]));
            }
        }
        let (w, h) = (f64::from(gray.width()), f64::from(gray.height()));
        tags.retain(|(_, q)| inside_border(q, w, h));
        let refined = refine_corners_window(gray, &tags, coarse_half_window(gray))?;
        let mut out = Vec::new();
        for ((id, q), r) in tags.iter().zip(refined.chunks(4)) {
            let r = [r[0], r[1], r[2], r[3]];
            let close = q
                .iter()
                .zip(&r)
                .all(|(a, b)| (a - b).norm() <= PREDICTED_MAX_MOVE_PX);
            let centre =
                Point2::from((r[0].coords + r[1].coords + r[2].coords + r[3].coords) / 4.0);
            let side = (0..4)
                .map(|i| (r[i] - r[(i + 1) % 4]).norm())
                .fold(f64::INFINITY, f64::min);
            if close && r.iter().all(|p| is_grid_saddle(gray, p, &centre, side)) {
                out.push((*id, r));
            }
        }
        Ok(out)
    }

    /// Whether a tag's corners (Kalibr order) lie where `camera` and the board pose put them
    /// (see [`POSE_CHECK_SIDE_FRACTION`]).
    fn explained(&self, camera: &Camera, pose: &Pose, tag: u32, q: &[Point2<f64>; 4]) -> bool {
        let side = (0..4)
            .map(|i| (q[i] - q[(i + 1) % 4]).norm())
            .fold(f64::INFINITY, f64::min);
        let tol = (POSE_CHECK_SIDE_FRACTION * side).clamp(POSE_CHECK_MIN_PX, POSE_CHECK_MAX_PX);
        (0..4).all(|k| {
            let b = self
                .target
                .point(self.target.corner_point_id(tag as usize, k));
            camera
                .project(&pose.transform_point(&nalgebra::Point3::from(b)).coords)
                .is_some_and(|p| (p - q[k]).norm() <= tol)
        })
    }

    /// Drop the tags of `img` that its board pose does not explain (with their corners).
    fn drop_unexplained(&self, img: &mut ImageCorners, camera: &Camera, pose: &Pose) {
        let mut bad = BTreeSet::new();
        for &tag in &img.tags {
            let q: Option<Vec<Point2<f64>>> = (0..4)
                .map(|k| {
                    let id = self.target.corner_point_id(tag as usize, k) as u32;
                    img.corners
                        .iter()
                        .find(|c| c.id == id)
                        .map(Corner::pixel_point)
                })
                .collect();
            if q.is_none_or(|q| !self.explained(camera, pose, tag, &[q[0], q[1], q[2], q[3]])) {
                bad.insert(tag);
            }
        }
        if bad.is_empty() {
            return;
        }
        let ids: BTreeSet<u32> = bad
            .iter()
            .flat_map(|&t| (0..4).map(move |k| (t, k)))
            .map(|(t, k)| self.target.corner_point_id(t as usize, k) as u32)
            .collect();
        img.tags.retain(|t| !bad.contains(t));
        img.corners.retain(|c| !ids.contains(&c.id));
    }

    /// Second pass: tags `known` does not hold, through `camera` and the image's board pose
    /// (`cam_from_board`, if the first-pass fit has one): predicted tags decoded in place, then
    /// predicted tags verified as saddles, then perspective views (see [`Self::plan_views`])
    /// of what is still missing; corners refined in the original image. Everything runs in a
    /// fixed order and the first sighting of a tag wins, so the result is deterministic.
    pub fn detect_rectified(
        &self,
        gray: &GrayImage,
        camera: &Camera,
        known: &Detection,
        cam_from_board: Option<&Pose>,
    ) -> Result<Detection> {
        let mut have: BTreeSet<u32> = known.tags.iter().copied().collect();
        let (w, h) = (f64::from(gray.width()), f64::from(gray.height()));
        let mut raw: Vec<(u32, [Point2<f64>; 4])> = Vec::new();
        // Where the board pose puts the missing tags: decoded in place, no view needed.
        if let Some(pose) = cam_from_board {
            let predicted: Vec<[Point2<f64>; 4]> = self
                .missing_tags(camera, &have, pose)
                .iter()
                .filter_map(|corners| {
                    let px: Option<Vec<Point2<f64>>> =
                        corners.iter().map(|c| camera.project(c)).collect();
                    let px = px?;
                    clockwise(&[px[0], px[1], px[2], px[3]])
                })
                .collect();
            // Refined first: a tile cut from corners a few pixels off misreads the bits.
            let tagged: Vec<(u32, [Point2<f64>; 4])> = predicted.iter().map(|q| (0, *q)).collect();
            let refined = refine_corners_window(gray, &tagged, coarse_half_window(gray))?;
            let predicted: Vec<[Point2<f64>; 4]> = predicted
                .iter()
                .zip(refined.chunks(4))
                .map(|(q, r)| {
                    let moved = q
                        .iter()
                        .zip(r)
                        .map(|(a, b)| (a - b).norm())
                        .fold(0.0, f64::max);
                    if moved <= coarse_move_limit(q) {
                        [r[0], r[1], r[2], r[3]]
                    } else {
                        *q
                    }
                })
                .collect();
            let found = decode_candidates(gray, &predicted, self.target.tag_count())?;
            for (id, q) in finish_quads(gray, found, coarse_half_window(gray))? {
                if !have.contains(&id) && inside_border(&q, w, h) {
                    have.insert(id);
                    raw.push((id, q));
                }
            }
        }
        // Tags the pose predicts that no decoding found: kept when every predicted corner
        // refines to an aprilgrid saddle (tag and corner square dark, the two gaps bright)
        // within reach of the prediction, i.e. the board is there and the numbering follows
        // from the decoded tags around it.
        if let Some(pose) = cam_from_board {
            for (id, q) in self.predicted_saddles(gray, camera, &have, pose)? {
                if inside_border(&q, w, h) {
                    have.insert(id);
                    raw.push((id, q));
                }
            }
        }
        for view in self.plan_views(camera, &have, cam_from_board) {
            let Some(image) = view.render(gray, camera) else {
                continue;
            };
            for (id, quad) in
                aruco_quads(&image, self.target.tag_count(), ARUCO_COARSE_HALF_WINDOW)?
            {
                if have.contains(&id) {
                    continue;
                }
                let mapped: Option<Vec<Point2<f64>>> = quad
                    .iter()
                    .map(|q| camera.project(&view.ray(q.x, q.y)))
                    .collect();
                let Some(mapped) = mapped else { continue };
                let pts = [mapped[0], mapped[1], mapped[2], mapped[3]];
                if inside_border(&pts, w, h) {
                    have.insert(id);
                    raw.push((id, pts));
                }
            }
        }
        raw.sort_by_key(|r| r.0);
        let mut found = self.refine_and_number(gray, &raw, 0, true)?;
        if let Some(pose) = cam_from_board {
            let mut img = ImageCorners {
                name: String::new(),
                width: gray.width(),
                height: gray.height(),
                tags: found.tags,
                corners: found.corners,
            };
            let before = img.tags.len();
            self.drop_unexplained(&mut img, camera, pose);
            found.dropped_tags += before - img.tags.len();
            found.tags = img.tags;
            found.corners = img.corners;
        }
        Ok(found)
    }
}

/// Whether `p` looks like an aprilgrid tag corner: towards the tag centre (tag border) and
/// away from it (corner square) dark, to either side (the gaps between tags) bright.
fn is_grid_saddle(gray: &GrayImage, p: &Point2<f64>, centre: &Point2<f64>, side: f64) -> bool {
    let to_centre = centre - p;
    if to_centre.norm() < 1e-9 || !side.is_finite() {
        return false;
    }
    let u = to_centre.normalize();
    let v = nalgebra::Vector2::new(-u.y, u.x);
    let r = (SADDLE_PROBE_FRACTION * side).clamp(SADDLE_PROBE_MIN_PX, SADDLE_PROBE_MAX_PX);
    let (w, h) = (f64::from(gray.width()), f64::from(gray.height()));
    let at = |d: nalgebra::Vector2<f64>| -> Option<f64> {
        let q = p + d * r;
        (q.x >= 0.0 && q.y >= 0.0 && q.x < w - 1.0 && q.y < h - 1.0)
            .then(|| f64::from(bilinear(gray, q.x, q.y)))
    };
    match (at(u), at(-u), at(v), at(-v)) {
        (Some(a), Some(b), Some(c), Some(d)) => c.min(d) - a.max(b) >= SADDLE_MIN_CONTRAST,
        _ => false,
    }
}

/// A grey image smoothed with a small Gaussian (f32), for saddle-point refinement.
struct SmoothImage {
    data: Vec<f32>,
    width: i64,
    height: i64,
}

/// Half size of the saddle fit's window (a 5 × 5 pixel neighbourhood).
const SADDLE_FIT_HALF: i64 = 2;
/// Gaussian sigma (px) applied before the saddle fit.
const SADDLE_SMOOTH_SIGMA: f64 = 1.1;
/// Saddle-fit iterations (re-centred on the nearest pixel each time).
const SADDLE_FIT_ITERATIONS: usize = 4;
/// The saddle fit may move a `cornerSubPix` corner by at most this (px); further means the fit
/// found a different feature and the `cornerSubPix` corner is kept.
const SADDLE_MAX_MOVE_PX: f64 = 1.0;
/// The saddle fit runs on images smaller than this (px, larger side) only: there tag cells are
/// under ~2 px and the 5 × 5 `cornerSubPix` window reaches the tag's data bits (480 px: corner
/// median error 0.107 -> 0.080 px, front fx 0.17 -> 0.03 %); at 960 px its 5 × 5 fit of the
/// curved peripheral saddles pulls corners inwards (full-path projection 0.085 px vs ~0.03).
const SADDLE_FIT_MAX_SIDE_PX: u32 = 960;

impl SmoothImage {
    fn new(gray: &GrayImage) -> Result<Self> {
        let cv = |e: opencv::Error| CalibError::Internal(format!("OpenCV blur: {e}"));
        let mat =
            Mat::new_rows_cols_with_data(gray.height() as i32, gray.width() as i32, gray.as_raw())
                .map_err(cv)?;
        let mut f = Mat::default();
        mat.convert_to(&mut f, opencv::core::CV_32F, 1.0, 0.0)
            .map_err(cv)?;
        let mut blurred = Mat::default();
        let sigma = SADDLE_SMOOTH_SIGMA;
        opencv::imgproc::gaussian_blur(
            &f,
            &mut blurred,
            Size::new(0, 0),
            sigma,
            sigma,
            opencv::core::BORDER_REPLICATE,
        )
        .map_err(cv)?;
        let data = blurred.data_typed::<f32>().map_err(cv)?.to_vec();
        Ok(Self {
            data,
            width: i64::from(gray.width()),
            height: i64::from(gray.height()),
        })
    }

    /// The saddle point of a quadratic fitted by least squares to the smoothed image around
    /// `p`, iterated; `None` if the surface is not a saddle there or the point runs away.
    fn saddle(&self, p: &Point2<f64>) -> Option<Point2<f64>> {
        let half = SADDLE_FIT_HALF;
        let mut cur = *p;
        for _ in 0..SADDLE_FIT_ITERATIONS {
            let (cx, cy) = (cur.x.round() as i64, cur.y.round() as i64);
            if cx - half < 0 || cy - half < 0 || cx + half >= self.width || cy + half >= self.height
            {
                return None;
            }
            // Normal equations of f = a x² + b xy + c y² + d x + e y + g.
            let mut ata = nalgebra::Matrix6::<f64>::zeros();
            let mut atb = nalgebra::Vector6::<f64>::zeros();
            for dy in -half..=half {
                for dx in -half..=half {
                    let v = f64::from(self.data[((cy + dy) * self.width + cx + dx) as usize]);
                    let (x, y) = (dx as f64, dy as f64);
                    let row = nalgebra::Vector6::new(x * x, x * y, y * y, x, y, 1.0);
                    ata += row * row.transpose();
                    atb += row * v;
                }
            }
            let k = ata.lu().solve(&atb)?;
            let (a, b, c, d, e) = (k[0], k[1], k[2], k[3], k[4]);
            let det = 4.0 * a * c - b * b;
            if det >= 0.0 {
                return None;
            }
            let sx = (-2.0 * c * d + b * e) / det;
            let sy = (b * d - 2.0 * a * e) / det;
            let next = Point2::new(cx as f64 + sx, cy as f64 + sy);
            if (next - p).norm() > SADDLE_MAX_MOVE_PX || !next.x.is_finite() {
                return None;
            }
            let done = (next - cur).norm() < 1e-3;
            cur = next;
            if done || (sx.abs() <= 0.5 && sy.abs() <= 0.5) {
                return Some(cur);
            }
        }
        Some(cur)
    }
}

/// Bilinear sample of a grey image at a sub-pixel position inside it.
fn bilinear(img: &GrayImage, x: f64, y: f64) -> u8 {
    // `x as u32` is `x.floor() as u32` for every x (a negative one saturates to 0 either way)
    // without the C library's `floor`.
    let (x0, y0) = (x as u32, y as u32);
    let (fx, fy) = (x - f64::from(x0), y - f64::from(y0));
    let p = |xx: u32, yy: u32| f64::from(img.get_pixel(xx, yy)[0]);
    let top = p(x0, y0) * (1.0 - fx) + p(x0 + 1, y0) * fx;
    let bottom = p(x0, y0 + 1) * (1.0 - fx) + p(x0 + 1, y0 + 1) * fx;
    round_clamp_u8(top * (1.0 - fy) + bottom * fy)
}

/// `v.round().clamp(0.0, 255.0) as u8` (halves away from zero, NaN to 0) without the C
/// library's `round` (x86-64's baseline has no rounding instruction).
fn round_clamp_u8(v: f64) -> u8 {
    if v.is_nan() || v < 0.0 {
        return 0;
    }
    if v >= 255.0 {
        return 255;
    }
    let t = v as u8;
    t + u8::from(v - f64::from(t) >= 0.5)
}

/// `cornerSubPix` (Kalibr's 5 × 5 window) on every tag corner (4 per tag, in order).
pub(crate) fn refine_corners(
    gray: &GrayImage,
    tags: &[(u32, [Point2<f64>; 4])],
) -> Result<Vec<Point2<f64>>> {
    refine_corners_window(gray, tags, SUBPIX_HALF_WINDOW)
}

/// `cornerSubPix` on a `(2·half + 1)²` window on every tag corner (4 per tag, in order).
fn refine_corners_window(
    gray: &GrayImage,
    tags: &[(u32, [Point2<f64>; 4])],
    half_window: i32,
) -> Result<Vec<Point2<f64>>> {
    if tags.is_empty() {
        return Ok(Vec::new());
    }
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
        Size::new(half_window, half_window),
        Size::new(-1, -1),
        criteria,
    )
    .map_err(cv)?;
    Ok(pts
        .iter()
        .map(|p| Point2::new(f64::from(p.x), f64::from(p.y)))
        .collect())
}

/// A first lens calibration from the first-pass corners (KB4, no coverage check) and the board
/// pose of every image it used, or `None` if they do not support one.
fn bootstrap_camera(
    images: &[ImageCorners],
    target: &AprilGridTarget,
) -> Option<(Camera, BTreeMap<String, Pose>)> {
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
        Ok(r) => {
            let poses = r
                .views
                .iter()
                .filter_map(|v| {
                    let [x, y, z, qx, qy, qz, qw] = v.cam_from_board?;
                    let q = nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
                        qw, qx, qy, qz,
                    ));
                    Some((
                        v.image.clone(),
                        Pose::from_parts(nalgebra::Translation3::new(x, y, z), q),
                    ))
                })
                .collect();
            Some((r.camera, poses))
        }
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
    /// Second pass through a lens and board poses fitted to the first pass: predicted tags
    /// decoded in place or verified as saddles, and perspective views of what is still
    /// missing; finds the small, strongly distorted tags the first pass misses.
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

/// Second-pass rounds: the second round starts from a lens and board poses fitted to the first
/// round's corners too (certify's 480 px front lens: first pass 9 % of the visible corners, one
/// round 52 %, two rounds 78 %).
const SECOND_PASS_ROUNDS: usize = 2;
/// A tag is unexplained by its board pose if a corner lies further than this fraction of the
/// tag's shortest side from where the pose projects it (a jump to the neighbouring saddle moves
/// it 0.3 sides), clamped to [`POSE_CHECK_MIN_PX`, `POSE_CHECK_MAX_PX`].
const POSE_CHECK_SIDE_FRACTION: f64 = 0.15;
/// Smallest pose-check tolerance (px): a good corner's residual in the first fit is ~0.1 px and
/// the fit's predictions of tags it has not seen are good to well under this.
const POSE_CHECK_MIN_PX: f64 = 1.0;
/// Largest pose-check tolerance (px): on big tags a corner ~2 px off (one tag cell, caught on
/// the tag's inner border) is wrong too.
const POSE_CHECK_MAX_PX: f64 = 1.5;

/// Off-axis angles (deg) of the rectified views' centres, and azimuths per ring.
const RECTIFY_THETAS_DEG: [f64; 4] = [40.0, 65.0, 88.0, 108.0];
const RECTIFY_AZIMUTHS: usize = 8;
/// Side (px) and full field of view (deg) of a rectified view: wide enough that neighbouring
/// views overlap by a tag, small enough that the view is nearly undistorted.
const RECTIFY_SIDE: u32 = 360;
const RECTIFY_FOV_DEG: f64 = 64.0;
/// A missing tag counts as covered by a planned view when its corners lie this far (px) inside
/// the view: aruco needs the tag's white surround.
const RECTIFY_MARGIN_PX: f64 = 24.0;

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
            let found = detector.detect_first_pass(&gray)?;
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
    for _round in 0..SECOND_PASS_ROUNDS {
        if options.rectify
            && let Some((camera, poses)) = bootstrap_camera(&all, target)
        {
            // Tags the fit's board pose does not explain are dropped (a corner that jumped to
            // a neighbouring saddle); the second pass may then find them again where predicted.
            for img in &mut all {
                if let Some(pose) = poses.get(&img.name) {
                    detector.drop_unexplained(img, &camera, pose);
                }
            }
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
                    let found =
                        detector.detect_rectified(&gray, &camera, &known, poses.get(&img.name));
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rounding_to_u8_matches_round_and_clamp() {
        let mut values = vec![
            f64::NAN,
            f64::NEG_INFINITY,
            f64::INFINITY,
            -0.0,
            0.0,
            -0.5,
            -0.49999999999999994,
            0.49999999999999994,
            0.5,
            254.49999999999997,
            254.5,
            254.99999999999997,
            255.0,
            255.49999999999997,
            255.5,
            1e300,
            -1e300,
        ];
        values.extend((-2000..300_000).map(|i| f64::from(i) * 0.000_937));
        for v in values {
            assert_eq!(
                round_clamp_u8(v),
                v.round().clamp(0.0, 255.0) as u8,
                "{v:?}"
            );
        }
    }

    /// The sampler gives the bytes of its `floor`/`round` formulation everywhere a caller may
    /// ask, the border and half-pixel positions included.
    #[test]
    fn bilinear_matches_the_floor_and_round_formula() {
        let img = GrayImage::from_fn(17, 13, |x, y| {
            image::Luma([((x * 37 + y * 91) % 256) as u8])
        });
        let reference = |x: f64, y: f64| -> u8 {
            let (x0, y0) = (x.floor() as u32, y.floor() as u32);
            let (fx, fy) = (x - f64::from(x0), y - f64::from(y0));
            let p = |xx: u32, yy: u32| f64::from(img.get_pixel(xx, yy)[0]);
            let top = p(x0, y0) * (1.0 - fx) + p(x0 + 1, y0) * fx;
            let bottom = p(x0, y0 + 1) * (1.0 - fx) + p(x0 + 1, y0 + 1) * fx;
            (top * (1.0 - fy) + bottom * fy).round().clamp(0.0, 255.0) as u8
        };
        let mut positions = vec![
            (-0.5, 3.0),
            (-0.0, 0.0),
            (0.0, 11.5),
            (15.999_999, 11.999_999),
        ];
        for i in 0..4000 {
            let t = f64::from(i);
            positions.push((
                (t * 0.618_034).rem_euclid(16.0),
                (t * 0.414_214).rem_euclid(12.0),
            ));
        }
        for (x, y) in positions {
            assert_eq!(bilinear(&img, x, y), reference(x, y), "({x}, {y})");
        }
    }
}
