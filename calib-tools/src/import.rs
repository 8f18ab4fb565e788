//! Corners from other tools: `kiwi-calib corners import` turns OpenCV FileStorage files
//! (XML, YAML or JSON, as `cv::FileStorage` writes them) of per-view image points and board
//! points into a KIWI corners file (`detect` module docs), so a chessboard, a ChArUco board
//! or any planar target detected elsewhere can be calibrated with `intrinsics --corners`.
//!
//! Accepted layouts, for the image-points file and the object-points file alike:
//! - one top-level node per view (`<image_0>`, `<image_1>`, …): the view's points as a flat
//!   list of numbers (`x y x y …`, or `x y z …` for board points), as a list of points
//!   (`[[x, y], …]`), or as an `opencv-matrix` (N × 1 with 2 or 3 channels, or N × 2 / N × 3);
//! - one top-level node holding a list of views (`vector<vector<Point2f>>` written with
//!   `fs << "points" << v`: `<points><_>…</_><_>…</_></points>`).
//!
//! Top-level numbers and strings (an image size, a comment) are ignored. Views pair by name
//! when both files use the same names, else by order; a single object view is used for every
//! image view (the whole board seen each time). Each board point gets one id over the whole
//! file (board positions sorted by y, then x), so a point keeps its id in every view.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use opencv::core::{FileNode, FileStorage, Mat};
use opencv::prelude::*;

use crate::detect::{Corner, CornerSet, ImageCorners};
use crate::error::{CalibError, Result};

/// Board positions closer than this (m) are the same board point when ids are assigned
/// (float32 round-off in OpenCV files is ~1e-8 m).
const SAME_BOARD_POINT_M: f64 = 1e-6;

/// `kiwi-calib corners`: work with corners files.
#[derive(Debug, clap::Subcommand)]
pub enum CornersCommand {
    /// Convert corners from another tool into a KIWI corners file.
    Import(ImportArgs),
}

/// Arguments of `kiwi-calib corners import`.
#[derive(Debug, clap::Args)]
pub struct ImportArgs {
    /// OpenCV FileStorage file (.xml, .yaml, .yml, .json) of image points per view, e.g. the
    /// `imagePoints` of `cv::calibrateCamera` / `cv::fisheye::calibrate` saved with
    /// `cv::FileStorage`.
    #[arg(long, value_name = "IMAGE_POINTS")]
    pub opencv: PathBuf,
    /// OpenCV FileStorage file of the board points (m) per view, or one view for all.
    #[arg(long, value_name = "OBJECT_POINTS")]
    pub object: PathBuf,
    /// Image size in pixels, WIDTHxHEIGHT (the files do not carry it).
    #[arg(long, value_name = "WxH")]
    pub size: String,
    /// The corners file to write.
    #[arg(long)]
    pub out: PathBuf,
    /// Print `{"images": [{"name", "tags", "corners"}], "total_corners"}`.
    #[arg(long)]
    pub json: bool,
}

/// Run `kiwi-calib corners`; returns the corners written.
pub fn run_corners(cmd: &CornersCommand) -> Result<CornerSet> {
    match cmd {
        CornersCommand::Import(args) => {
            let (width, height) = parse_size(&args.size).ok_or_else(|| CalibError::Input {
                path: args.opencv.clone(),
                message: format!(
                    "--size '{}': expected WIDTHxHEIGHT in pixels, e.g. 1280x800",
                    args.size
                ),
            })?;
            let set = import_opencv(&args.opencv, &args.object, width, height)?;
            set.save(&args.out)?;
            Ok(set)
        }
    }
}

/// Parse `WIDTHxHEIGHT` (positive integers).
pub fn parse_size(text: &str) -> Option<(u32, u32)> {
    let (w, h) = text.trim().split_once(['x', 'X'])?;
    let (w, h): (u32, u32) = (w.trim().parse().ok()?, h.trim().parse().ok()?);
    (w > 0 && h > 0).then_some((w, h))
}

/// Build a corners set from OpenCV FileStorage files of image points and object (board)
/// points; `width` × `height` is the image size.
pub fn import_opencv(
    image_points: &Path,
    object_points: &Path,
    width: u32,
    height: u32,
) -> Result<CornerSet> {
    let images = read_views(image_points, 2)?;
    let objects = read_views(object_points, 3)?;
    let bad = |path: &Path, message: String| CalibError::Input {
        path: path.to_path_buf(),
        message,
    };
    if images.is_empty() {
        return Err(bad(
            image_points,
            "no views of image points found; expected one node per view (x y x y …) or one \
             node holding a list of views"
                .into(),
        ));
    }
    if objects.is_empty() {
        return Err(bad(
            object_points,
            "no board points found; expected one node per view (x y z x y z …, metres) or a \
             single node for every view"
                .into(),
        ));
    }
    let by_name: BTreeMap<&str, &[f64]> = objects
        .iter()
        .map(|(n, v)| (n.as_str(), v.as_slice()))
        .collect();
    let same_names = images.iter().all(|(n, _)| by_name.contains_key(n.as_str()));
    let mut pairs: Vec<(&str, &[f64], &[f64])> = Vec::with_capacity(images.len());
    for (i, (name, pixels)) in images.iter().enumerate() {
        let board = if same_names {
            by_name[name.as_str()]
        } else if objects.len() == 1 {
            objects[0].1.as_slice()
        } else if objects.len() == images.len() {
            objects[i].1.as_slice()
        } else {
            return Err(bad(
                object_points,
                format!(
                    "{} views of board points for {} views of image points ({}); give one \
                     board view per image view (same names or same order), or a single one",
                    objects.len(),
                    images.len(),
                    image_points.display()
                ),
            ));
        };
        if board.len() / 3 != pixels.len() / 2 {
            return Err(bad(
                image_points,
                format!(
                    "view {name}: {} image points but {} board points in {}; each image point \
                     needs its board point, in the same order",
                    pixels.len() / 2,
                    board.len() / 3,
                    object_points.display()
                ),
            ));
        }
        pairs.push((name, pixels, board));
    }
    // One id per distinct board position over the whole file, sorted by (y, x).
    let key = |x: f64| (x / SAME_BOARD_POINT_M).round() as i64;
    let mut ids: BTreeMap<(i64, i64), u32> = BTreeMap::new();
    for (name, _, board) in &pairs {
        for p in board.chunks_exact(3) {
            if !p.iter().all(|v| v.is_finite()) {
                return Err(bad(
                    object_points,
                    format!("view {name}: board point {p:?} is not a finite number"),
                ));
            }
            if p[2].abs() > SAME_BOARD_POINT_M {
                return Err(bad(
                    object_points,
                    format!(
                        "view {name}: board point {p:?} has z = {} but KIWI needs a planar \
                         target with its points on z = 0 (board frame)",
                        p[2]
                    ),
                ));
            }
            ids.insert((key(p[1]), key(p[0])), 0);
        }
    }
    for (next, id) in ids.values_mut().enumerate() {
        *id = u32::try_from(next).map_err(|_| CalibError::Internal("too many points".into()))?;
    }
    let mut set = CornerSet::new(None);
    for (name, pixels, board) in pairs {
        let mut corners = Vec::with_capacity(board.len() / 3);
        for (px, p) in pixels.chunks_exact(2).zip(board.chunks_exact(3)) {
            corners.push(Corner {
                id: ids[&(key(p[1]), key(p[0]))],
                board: [p[0], p[1], 0.0],
                pixel: [px[0], px[1]],
            });
        }
        set.images.push(ImageCorners {
            name: name.to_string(),
            width,
            height,
            tags: Vec::new(),
            corners,
        });
    }
    set.validate(image_points)?;
    Ok(set)
}

/// What one FileStorage node holds.
enum Shape {
    /// One view's points, flattened.
    Points(Vec<f64>),
    /// A list of views.
    Views(Vec<Vec<f64>>),
    /// A scalar or string (ignored at the top level).
    Other,
}

/// The views of a FileStorage file: (name, flattened points with `dim` numbers per point).
fn read_views(path: &Path, dim: usize) -> Result<Vec<(String, Vec<f64>)>> {
    let what = if dim == 2 {
        "image points (x y per point)"
    } else {
        "board points (x y z per point)"
    };
    let bad = |message: String| CalibError::Input {
        path: path.to_path_buf(),
        message,
    };
    let cv = |e: opencv::Error| {
        bad(format!(
            "not a readable OpenCV FileStorage file ({}); expected XML, YAML or JSON as \
             cv::FileStorage writes it, with the {what}",
            e.message.trim()
        ))
    };
    if !path.is_file() {
        return Err(bad("no such file".into()));
    }
    let text_path = path
        .to_str()
        .ok_or_else(|| bad("the path is not UTF-8".into()))?;
    let fs = FileStorage::new(text_path, opencv::core::FileStorage_READ, "").map_err(cv)?;
    if !fs.is_opened().map_err(cv)? {
        return Err(bad(format!(
            "OpenCV cannot open it as a FileStorage file; expected XML, YAML or JSON with the \
             {what}"
        )));
    }
    let root = fs.root(0).map_err(cv)?;
    if !root.is_map().map_err(cv)? {
        return Err(bad(format!(
            "the top level is not a set of named nodes; expected one node per view of {what}"
        )));
    }
    let mut views = Vec::new();
    let mut lists = Vec::new();
    for key in root.keys().map_err(cv)? {
        let node = root.get(&key).map_err(cv)?;
        match shape(&node, dim).map_err(|e| match e {
            NodeError::Cv(e) => cv(e),
            NodeError::Bad(m) => bad(format!("node <{key}>: {m}; expected {what}")),
        })? {
            Shape::Points(p) => views.push((key, p)),
            Shape::Views(v) => lists.push((key, v)),
            Shape::Other => {}
        }
    }
    match (views.is_empty(), lists.len()) {
        (_, 0) => Ok(views),
        (true, 1) => {
            let (key, list) = lists.remove(0);
            Ok(list
                .into_iter()
                .enumerate()
                .map(|(i, p)| (format!("{key}_{i}"), p))
                .collect())
        }
        _ => Err(bad(format!(
            "mixes nodes that are one view with nodes that hold lists of views ({}); keep one \
             layout per file",
            lists
                .iter()
                .map(|(k, _)| k.as_str())
                .collect::<Vec<_>>()
                .join(", ")
        ))),
    }
}

/// Why a node could not be read.
enum NodeError {
    Cv(opencv::Error),
    Bad(String),
}

impl From<opencv::Error> for NodeError {
    fn from(e: opencv::Error) -> Self {
        Self::Cv(e)
    }
}

fn is_number(node: &FileNode) -> opencv::Result<bool> {
    Ok(node.is_real()? || node.is_int()?)
}

/// Numbers of a sequence node whose items are all numbers, else `None`.
fn numbers(node: &FileNode) -> opencv::Result<Option<Vec<f64>>> {
    let n = node.size()?;
    let mut out = Vec::with_capacity(n);
    for i in 0..n {
        let item = node.at(i32::try_from(i).unwrap_or(i32::MAX))?;
        if !is_number(&item)? {
            return Ok(None);
        }
        out.push(item.real()?);
    }
    Ok(Some(out))
}

/// Points of a node that is one view (flat numbers, list of points, or a matrix); `None` if it
/// is something else (a list of views).
fn view_points(node: &FileNode, dim: usize) -> std::result::Result<Option<Vec<f64>>, NodeError> {
    let points = if node.is_map()? {
        if node.get("data")?.is_none()? {
            return Err(NodeError::Bad(
                "a map that is not an opencv-matrix (rows, cols, dt, data)".into(),
            ));
        }
        matrix_values(&node.mat()?, dim)?
    } else if node.is_seq()? {
        if let Some(flat) = numbers(node)? {
            flat
        } else {
            // A list of points, each a sequence of `dim` numbers?
            let mut flat = Vec::new();
            for i in 0..node.size()? {
                let item = node.at(i32::try_from(i).unwrap_or(i32::MAX))?;
                match item
                    .is_seq()?
                    .then(|| numbers(&item))
                    .transpose()?
                    .flatten()
                {
                    Some(p) if p.len() == dim => flat.extend(p),
                    _ => return Ok(None),
                }
            }
            flat
        }
    } else {
        return Ok(None);
    };
    if points.len() % dim != 0 {
        return Err(NodeError::Bad(format!(
            "{} numbers, not a multiple of {dim}",
            points.len()
        )));
    }
    Ok(Some(points))
}

/// Classify a top-level node.
fn shape(node: &FileNode, dim: usize) -> std::result::Result<Shape, NodeError> {
    if is_number(node)? || node.is_string()? || node.is_none()? {
        return Ok(Shape::Other);
    }
    if let Some(p) = view_points(node, dim)? {
        return Ok(Shape::Points(p));
    }
    let mut views = Vec::new();
    for i in 0..node.size()? {
        let item = node.at(i32::try_from(i).unwrap_or(i32::MAX))?;
        match view_points(&item, dim)? {
            Some(p) => views.push(p),
            None => {
                return Err(NodeError::Bad(format!(
                    "item {i} is neither a list of numbers nor a matrix"
                )));
            }
        }
    }
    Ok(Shape::Views(views))
}

/// A matrix's values in row-major, channel-interleaved order (N × 1 × dim channels or
/// N × dim × 1 channel).
fn matrix_values(mat: &Mat, dim: usize) -> std::result::Result<Vec<f64>, NodeError> {
    let per_row = mat.cols() as usize * mat.channels() as usize;
    if mat.empty() {
        return Ok(Vec::new());
    }
    if per_row != dim && mat.rows() != 1 {
        return Err(NodeError::Bad(format!(
            "a {}x{} matrix with {} channels; expected N x 1 with {dim} channels or N x {dim}",
            mat.rows(),
            mat.cols(),
            mat.channels()
        )));
    }
    let mut m64 = Mat::default();
    mat.convert_to(&mut m64, opencv::core::CV_64F, 1.0, 0.0)?;
    let flat = m64.reshape(1, 0)?.try_clone()?;
    Ok(flat.data_typed::<f64>()?.to_vec())
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used, clippy::panic)]
mod tests {
    use super::*;

    /// A 3 × 2 board (0.1 m squares) and two views' pixels.
    const BOARD: [[f64; 3]; 6] = [
        [0.0, 0.0, 0.0],
        [0.1, 0.0, 0.0],
        [0.2, 0.0, 0.0],
        [0.0, 0.1, 0.0],
        [0.1, 0.1, 0.0],
        [0.2, 0.1, 0.0],
    ];

    fn pixel(view: usize, i: usize) -> [f64; 2] {
        [
            100.5 + 10.0 * i as f64 + view as f64,
            200.25 + 3.0 * i as f64,
        ]
    }

    fn list(values: impl Iterator<Item = f64>) -> String {
        values
            .map(|v| format!("{v:?}"))
            .collect::<Vec<_>>()
            .join(", ")
    }

    fn write(dir: &Path, name: &str, text: &str) -> PathBuf {
        let p = dir.join(name);
        std::fs::write(&p, text).unwrap();
        p
    }

    fn check(set: &CornerSet, names: &[&str]) {
        assert_eq!(set.images.len(), names.len());
        for (v, im) in set.images.iter().enumerate() {
            assert_eq!(im.name, names[v]);
            assert_eq!((im.width, im.height), (640, 480));
            assert_eq!(im.corners.len(), 6);
            for (i, c) in im.corners.iter().enumerate() {
                assert_eq!(c.id as usize, i, "ids follow the board, sorted by y then x");
                assert_eq!(c.pixel, pixel(v, i));
                assert!((0..3).all(|k| (c.board[k] - BOARD[i][k]).abs() < 1e-6));
            }
        }
    }

    #[test]
    fn list_of_views_and_one_board_matrix_for_all() {
        let dir = tempfile::tempdir().unwrap();
        let views: String = (0..2)
            .map(|v| format!("   - [ {} ]\n", list((0..6).flat_map(|i| pixel(v, i)))))
            .collect();
        let img = write(
            dir.path(),
            "img.yaml",
            &format!("%YAML:1.0\n---\nimage_width: 640\npoints:\n{views}"),
        );
        let obj = write(
            dir.path(),
            "obj.yaml",
            &format!(
                "%YAML:1.0\n---\nboard: !!opencv-matrix\n   rows: 6\n   cols: 1\n   dt: \"3f\"\n   \
                 data: [ {} ]\n",
                list(BOARD.iter().flatten().copied())
            ),
        );
        let set = import_opencv(&img, &obj, 640, 480).unwrap();
        check(&set, &["points_0", "points_1"]);
    }

    #[test]
    fn named_views_as_matrices_and_point_lists_pair_by_name() {
        let dir = tempfile::tempdir().unwrap();
        let m = |v: usize| {
            format!(
                "!!opencv-matrix\n   rows: 6\n   cols: 2\n   dt: d\n   data: [ {} ]",
                list((0..6).flat_map(|i| pixel(v, i)))
            )
        };
        let img = write(
            dir.path(),
            "img.yaml",
            &format!("%YAML:1.0\n---\nfirst: {}\nsecond: {}\n", m(0), m(1)),
        );
        let points = BOARD
            .iter()
            .map(|p| format!("[{}]", list(p.iter().copied())))
            .collect::<Vec<_>>()
            .join(", ");
        // Object views in the other order: pairing is by name.
        let obj = write(
            dir.path(),
            "obj.yaml",
            &format!("%YAML:1.0\n---\nsecond: [{points}]\nfirst: [{points}]\n"),
        );
        let set = import_opencv(&img, &obj, 640, 480).unwrap();
        check(&set, &["first", "second"]);
    }

    #[test]
    fn malformed_input_says_what_and_where() {
        let dir = tempfile::tempdir().unwrap();
        let board = format!(
            "%YAML:1.0\n---\nb: [ {} ]\n",
            list(BOARD.iter().flatten().copied())
        );
        let obj = write(dir.path(), "obj.yaml", &board);
        let err = |img_text: &str, obj: &Path| {
            let img = write(dir.path(), "img.yaml", img_text);
            import_opencv(&img, obj, 640, 480).unwrap_err().to_string()
        };
        let e = err("%YAML:1.0\n---\nv: [ 1.0, 2.0, 3.0 ]\n", &obj);
        assert!(e.contains("node <v>") && e.contains("multiple of 2"), "{e}");
        let e = err("%YAML:1.0\n---\nv: [ 1.0, 2.0, 3.0, 4.0 ]\n", &obj);
        assert!(e.contains("2 image points but 6 board points"), "{e}");
        let e = err("%YAML:1.0\n---\nwidth: 640\n", &obj);
        assert!(e.contains("no views of image points"), "{e}");
        let e = err("this is not < a FileStorage file", &obj);
        assert!(e.contains("FileStorage"), "{e}");
        let tilted = write(
            dir.path(),
            "tilted.yaml",
            "%YAML:1.0\n---\nb: [ 0.0, 0.0, 0.0, 0.1, 0.0, 0.05 ]\n",
        );
        let e = err("%YAML:1.0\n---\nv: [ 1.0, 2.0, 3.0, 4.0 ]\n", &tilted);
        assert!(e.contains("z = 0"), "{e}");
        assert_eq!(parse_size("1280x800"), Some((1280, 800)));
        assert_eq!(parse_size("1280x"), None);
        assert_eq!(parse_size("0x800"), None);
    }
}
