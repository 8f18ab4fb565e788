//! Calibration targets: the Kalibr aprilgrid (layout and numbering of `docs/aprilgrid-layout.md`),
//! its Kalibr target yaml (read and written), a print-ready SVG of the board, and print-ready
//! SVGs of single ArUco 4x4_50 tags for tool and head markers.
//!
//! The code tables are the ones the simulator draws with (`fixtures/data/*.json`, exported from
//! OpenCV and checked against it), so a board printed from here is the board KIWI's tests see.

use std::fmt::Write as _;
use std::path::Path;

use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

use crate::error::{CalibError, Result};

/// AprilTag 36h11 code table (OpenCV's orientation; `rot90_to_official` turns it upright).
const APRILTAG_36H11_JSON: &str = include_str!("../../fixtures/data/apriltag_36h11.json");
/// ArUco 4x4_50 code table (OpenCV's orientation).
const ARUCO_4X4_50_JSON: &str = include_str!("../../fixtures/data/aruco_4x4_50.json");

/// Black and white as printed (pure, for the best contrast on paper).
const INK: &str = "#000000";
/// Width of the white quiet zone around a printed board, in junction-square gaps; Kalibr needs
/// at least one gap of white beyond the outer junction squares.
const BOARD_MARGIN_GAPS: f64 = 2.0;

#[derive(Debug, Deserialize)]
struct CodeTable {
    marker_bits: usize,
    #[serde(default)]
    rot90_to_official: u32,
    codes: Vec<Vec<Vec<u8>>>,
}

fn code_table(text: &str, what: &str) -> Result<CodeTable> {
    serde_json::from_str(text)
        .map_err(|e| CalibError::Internal(format!("bundled {what} code table does not parse: {e}")))
}

/// A Kalibr aprilgrid target: `cols × rows` AprilTag 36h11 tags with black squares of
/// `tag_size_m`, separated by `spacing · tag_size_m`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct AprilGridTarget {
    /// Tags along board x (Kalibr `tagCols`).
    pub cols: usize,
    /// Tags along board y (Kalibr `tagRows`).
    pub rows: usize,
    /// Edge of a tag's black square in metres (Kalibr `tagSize`).
    pub tag_size_m: f64,
    /// Gap between tags divided by the tag size (Kalibr `tagSpacing`).
    pub spacing: f64,
}

/// Number of codes in the AprilTag 36h11 family: the largest board has this many tags.
const MAX_TAGS_36H11: usize = 587;

impl AprilGridTarget {
    /// A validated target.
    pub fn new(cols: usize, rows: usize, tag_size_m: f64, spacing: f64) -> Result<Self> {
        let t = Self {
            cols,
            rows,
            tag_size_m,
            spacing,
        };
        t.validate(Path::new("target"))?;
        Ok(t)
    }

    fn validate(&self, path: &Path) -> Result<()> {
        let bad = |message: String| {
            Err(CalibError::Input {
                path: path.to_path_buf(),
                message,
            })
        };
        if self.cols == 0 || self.rows == 0 || self.cols * self.rows > MAX_TAGS_36H11 {
            return bad(format!(
                "tagCols × tagRows must be between 1 and {MAX_TAGS_36H11} (AprilTag 36h11 has that \
                 many codes), found {} × {}",
                self.cols, self.rows
            ));
        }
        if !(self.tag_size_m.is_finite() && self.tag_size_m > 0.0 && self.tag_size_m < 10.0) {
            return bad(format!(
                "tagSize must be the printed black-square edge in metres (e.g. 0.088), found {}",
                self.tag_size_m
            ));
        }
        if !(self.spacing.is_finite() && self.spacing > 0.0 && self.spacing <= 1.0) {
            return bad(format!(
                "tagSpacing must be the gap divided by the tag size, in (0, 1] (e.g. 0.3), \
                 found {}",
                self.spacing
            ));
        }
        Ok(())
    }

    /// Tag pitch (m): tag size plus gap.
    pub fn pitch_m(&self) -> f64 {
        (1.0 + self.spacing) * self.tag_size_m
    }

    /// Number of target points (`4 · cols · rows`).
    pub fn point_count(&self) -> usize {
        4 * self.cols * self.rows
    }

    /// Number of tags.
    pub fn tag_count(&self) -> usize {
        self.cols * self.rows
    }

    /// Target point `i` on the board (Kalibr numbering `i = gr·2C + gc`), z = 0 (m).
    pub fn point(&self, i: usize) -> Vector3<f64> {
        let (gr, gc) = (i / (2 * self.cols), i % (2 * self.cols));
        let p = self.pitch_m();
        let t = self.tag_size_m;
        Vector3::new(
            (gc / 2) as f64 * p + (gc % 2) as f64 * t,
            (gr / 2) as f64 * p + (gr % 2) as f64 * t,
            0.0,
        )
    }

    /// Point id of corner `k` (0 BL, 1 BR, 2 TR, 3 TL in the board frame) of tag `tag`.
    pub fn corner_point_id(&self, tag: usize, k: usize) -> usize {
        let (r, c) = (tag / self.cols, tag % self.cols);
        let bl = 4 * self.cols * r + 2 * c;
        match k % 4 {
            0 => bl,
            1 => bl + 1,
            2 => bl + 2 * self.cols + 1,
            _ => bl + 2 * self.cols,
        }
    }

    /// Parse a Kalibr target yaml (`target_type: 'aprilgrid'`, `tagCols`, `tagRows`, `tagSize`,
    /// `tagSpacing`); `path` names the file in errors.
    pub fn from_kalibr_yaml(text: &str, path: &Path) -> Result<Self> {
        let mut target_type = None;
        let mut fields: [Option<f64>; 4] = [None; 4];
        const KEYS: [&str; 4] = ["tagCols", "tagRows", "tagSize", "tagSpacing"];
        for (n, raw) in text.lines().enumerate() {
            let line = raw.split('#').next().unwrap_or("").trim();
            if line.is_empty() || line == "---" {
                continue;
            }
            let Some((key, value)) = line.split_once(':') else {
                return Err(CalibError::Input {
                    path: path.to_path_buf(),
                    message: format!(
                        "line {}: expected `key: value` (a Kalibr target yaml), found `{line}`",
                        n + 1
                    ),
                });
            };
            let key = key.trim();
            let value = value.trim().trim_matches(|c| c == '\'' || c == '"');
            if key == "target_type" {
                target_type = Some(value.to_string());
            } else if let Some(i) = KEYS.iter().position(|k| *k == key) {
                fields[i] = Some(value.parse::<f64>().map_err(|_| CalibError::Input {
                    path: path.to_path_buf(),
                    message: format!("line {}: {key} must be a number, found `{value}`", n + 1),
                })?);
            }
        }
        match target_type.as_deref() {
            Some("aprilgrid") => {}
            Some(other) => {
                return Err(CalibError::Input {
                    path: path.to_path_buf(),
                    message: format!(
                        "target_type is '{other}'; KIWI detects 'aprilgrid' targets (for other \
                         planar targets, detect with another tool and pass --corners)"
                    ),
                });
            }
            None => {
                return Err(CalibError::Input {
                    path: path.to_path_buf(),
                    message: "no target_type: expected a Kalibr target yaml with \
                              target_type: 'aprilgrid'"
                        .into(),
                });
            }
        }
        let mut vals = [0.0; 4];
        for (i, key) in KEYS.iter().enumerate() {
            vals[i] = fields[i].ok_or_else(|| CalibError::Input {
                path: path.to_path_buf(),
                message: format!(
                    "missing {key}: an aprilgrid target yaml needs tagCols, tagRows, tagSize \
                     (m) and tagSpacing"
                ),
            })?;
        }
        for (i, key) in KEYS.iter().enumerate().take(2) {
            if vals[i].fract() != 0.0 || vals[i] < 1.0 {
                return Err(CalibError::Input {
                    path: path.to_path_buf(),
                    message: format!("{key} must be a positive whole number, found {}", vals[i]),
                });
            }
        }
        let t = Self {
            cols: vals[0] as usize,
            rows: vals[1] as usize,
            tag_size_m: vals[2],
            spacing: vals[3],
        };
        t.validate(path)?;
        Ok(t)
    }

    /// Read a Kalibr target yaml file.
    pub fn load(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|e| CalibError::Input {
            path: path.to_path_buf(),
            message: format!("cannot read the target yaml: {e}"),
        })?;
        Self::from_kalibr_yaml(&text, path)
    }

    /// The Kalibr target yaml of this board.
    pub fn to_kalibr_yaml(&self) -> String {
        format!(
            "target_type: 'aprilgrid' # Kalibr aprilgrid, written by kiwi-calib\n\
             tagCols: {}\ntagRows: {}\ntagSize: {:?} # black square edge (m)\n\
             tagSpacing: {:?} # gap / tagSize\n",
            self.cols, self.rows, self.tag_size_m, self.spacing
        )
    }

    /// A print-ready SVG of the board at 1 : 1 (millimetres), tag 0 at the bottom-left as in
    /// Kalibr's PDF, with a white quiet zone and a caption.
    pub fn to_svg(&self) -> Result<String> {
        let table = code_table(APRILTAG_36H11_JSON, "AprilTag 36h11")?;
        if table.marker_bits != 6 || table.codes.len() < self.tag_count() {
            return Err(CalibError::Internal(
                "the bundled AprilTag 36h11 table is incomplete".into(),
            ));
        }
        let mm = 1000.0;
        let (t, p, g) = (
            self.tag_size_m * mm,
            self.pitch_m() * mm,
            self.spacing * self.tag_size_m * mm,
        );
        let margin = BOARD_MARGIN_GAPS * g + 5.0;
        let caption_h = 8.0;
        // Black pattern: x ∈ [−g, C·p], y ∈ [−g, R·p] (board frame, y up).
        let (pw, ph) = (self.cols as f64 * p + g, self.rows as f64 * p + g);
        let (w, h) = (pw + 2.0 * margin, ph + 2.0 * margin + caption_h);
        // SVG y runs down: board (x, y) → (x + g + margin, margin + ph − (y + g)).
        let ox = g + margin;
        let oy = margin + ph - g;
        let mut s = String::new();
        let _ = writeln!(
            s,
            "<?xml version=\"1.0\" encoding=\"UTF-8\"?>\n<svg xmlns=\"http://www.w3.org/2000/svg\" \
             width=\"{w:.3}mm\" height=\"{h:.3}mm\" viewBox=\"0 0 {w:.3} {h:.3}\">"
        );
        let _ = writeln!(
            s,
            "<title>Kalibr aprilgrid {}x{} tags, tagSize {} m, tagSpacing {}</title>",
            self.cols, self.rows, self.tag_size_m, self.spacing
        );
        let _ = writeln!(
            s,
            "<rect x=\"0\" y=\"0\" width=\"{w:.3}\" height=\"{h:.3}\" fill=\"#ffffff\"/>"
        );
        let _ = writeln!(s, "<g fill=\"{INK}\" shape-rendering=\"crispEdges\">");
        let rect = |s: &mut String, x0: f64, y0: f64, x1: f64, y1: f64| {
            let _ = writeln!(
                s,
                "<rect x=\"{:.4}\" y=\"{:.4}\" width=\"{:.4}\" height=\"{:.4}\"/>",
                ox + x0,
                oy - y1,
                x1 - x0,
                y1 - y0
            );
        };
        for n in 0..=self.rows {
            for c in 0..=self.cols {
                let (x, y) = (c as f64 * p, n as f64 * p);
                rect(&mut s, x - g, y - g, x, y);
            }
        }
        let b = t / 10.0;
        for id in 0..self.tag_count() {
            let (r, c) = (id / self.cols, id % self.cols);
            let (x0, y0) = (c as f64 * p, r as f64 * p);
            // Border ring (2 cells) and the black data cells, printed upright (official image).
            let code = &table.codes[id];
            for i in 0..10 {
                for j in 0..10 {
                    let black = if (2..8).contains(&i) && (2..8).contains(&j) {
                        let (si, sj) = rotate_index(i - 2, j - 2, 6, table.rot90_to_official);
                        code[si][sj] == 0
                    } else {
                        (1..9).contains(&i) && (1..9).contains(&j)
                    };
                    if black {
                        // Cell i from the top of the 10-cell tag image (incl. a white ring that
                        // is the gap), j from the left; the black square spans cells 1..9.
                        let cx0 = x0 + (j as f64 - 1.0) * b;
                        let cy1 = y0 + t - (i as f64 - 1.0) * b;
                        rect(&mut s, cx0, cy1 - b, cx0 + b, cy1);
                    }
                }
            }
        }
        let _ = writeln!(s, "</g>");
        let _ = writeln!(
            s,
            "<text x=\"{:.3}\" y=\"{:.3}\" font-family=\"sans-serif\" font-size=\"4\" \
             fill=\"#000000\">{}x{} tags, size={} cm, spacing={} cm — print at 100 % (actual \
             size); measure the black square of a tag and put it in tagSize</text>",
            margin,
            h - 3.0,
            self.cols,
            self.rows,
            self.tag_size_m * 100.0,
            self.spacing * self.tag_size_m * 100.0
        );
        let _ = writeln!(s, "</svg>");
        Ok(s)
    }
}

/// The source cell of printed cell `(i, j)` when the table must be turned `quarter_turns`·90°
/// counter-clockwise to reach the printed orientation (as `numpy.rot90`).
fn rotate_index(i: usize, j: usize, n: usize, quarter_turns: u32) -> (usize, usize) {
    match quarter_turns % 4 {
        0 => (i, j),
        1 => (j, n - 1 - i),
        2 => (n - 1 - i, n - 1 - j),
        _ => (n - 1 - j, i),
    }
}

/// A print-ready SVG (millimetres, 1 : 1) of ArUco 4x4_50 marker `id` with black-square edge
/// `size_m`, one cell of white quiet zone and a caption, drawn as OpenCV draws it.
pub fn aruco_svg(dictionary: &str, id: usize, size_m: f64) -> Result<String> {
    if dictionary != "4x4_50" {
        return Err(CalibError::Input {
            path: "--dict".into(),
            message: format!("dictionary '{dictionary}' is not bundled; use 4x4_50"),
        });
    }
    if !(size_m.is_finite() && size_m > 0.0 && size_m < 10.0) {
        return Err(CalibError::Input {
            path: "--size".into(),
            message: format!(
                "expected the black-square edge in metres (e.g. 0.058), found {size_m}"
            ),
        });
    }
    let table = code_table(ARUCO_4X4_50_JSON, "ArUco 4x4_50")?;
    let code = table.codes.get(id).ok_or_else(|| CalibError::Input {
        path: "--id".into(),
        message: format!(
            "marker id {id} is not in 4x4_50; use an id below {}",
            table.codes.len()
        ),
    })?;
    let n = table.marker_bits;
    let edge = size_m * 1000.0;
    let cell = edge / (n + 2) as f64;
    let caption_h = 6.0;
    let total = edge + 2.0 * cell;
    let mut s = String::new();
    let _ = writeln!(
        s,
        "<?xml version=\"1.0\" encoding=\"UTF-8\"?>\n<svg xmlns=\"http://www.w3.org/2000/svg\" \
         width=\"{total:.3}mm\" height=\"{:.3}mm\" viewBox=\"0 0 {total:.3} {:.3}\">",
        total + caption_h,
        total + caption_h
    );
    let _ = writeln!(
        s,
        "<rect x=\"0\" y=\"0\" width=\"{total:.3}\" height=\"{:.3}\" fill=\"#ffffff\"/>",
        total + caption_h
    );
    let _ = writeln!(s, "<g fill=\"{INK}\" shape-rendering=\"crispEdges\">");
    for i in 0..n + 2 {
        for j in 0..n + 2 {
            let border = i == 0 || j == 0 || i == n + 1 || j == n + 1;
            if border || code[i - 1][j - 1] == 0 {
                let _ = writeln!(
                    s,
                    "<rect x=\"{:.4}\" y=\"{:.4}\" width=\"{cell:.4}\" height=\"{cell:.4}\"/>",
                    cell + j as f64 * cell,
                    cell + i as f64 * cell
                );
            }
        }
    }
    let _ = writeln!(s, "</g>");
    let _ = writeln!(
        s,
        "<text x=\"{cell:.3}\" y=\"{:.3}\" font-family=\"sans-serif\" font-size=\"3\">ArUco \
         4x4_50 id {id}, {} mm — print at 100 %</text>",
        total + caption_h - 2.0,
        edge
    );
    let _ = writeln!(s, "</svg>");
    Ok(s)
}

/// The printed black/white cells of tag `id` of the 36h11 family, upright, `true` = black,
/// 10 × 10 cells from the top-left (white ring, black border, data): used to check detections.
pub fn apriltag_cells(id: usize) -> Result<[[bool; 10]; 10]> {
    let table = code_table(APRILTAG_36H11_JSON, "AprilTag 36h11")?;
    let code = table
        .codes
        .get(id)
        .ok_or_else(|| CalibError::Internal(format!("tag id {id} is not in the 36h11 family")))?;
    let mut cells = [[false; 10]; 10];
    for (i, row) in cells.iter_mut().enumerate() {
        for (j, c) in row.iter_mut().enumerate() {
            *c = if (2..8).contains(&i) && (2..8).contains(&j) {
                let (si, sj) = rotate_index(i - 2, j - 2, 6, table.rot90_to_official);
                code[si][sj] == 0
            } else {
                (1..9).contains(&i) && (1..9).contains(&j)
            };
        }
    }
    Ok(cells)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn yaml_round_trip_and_numbering() {
        let t = AprilGridTarget::new(6, 6, 0.088, 0.3).unwrap();
        let back = AprilGridTarget::from_kalibr_yaml(&t.to_kalibr_yaml(), Path::new("x")).unwrap();
        assert_eq!(t, back);
        // docs/aprilgrid-layout.md: for a 2 × 2 grid tag 0 has points {0, 1, 5, 4}.
        let small = AprilGridTarget::new(2, 2, 0.1, 0.3).unwrap();
        let ids: Vec<usize> = (0..4).map(|k| small.corner_point_id(0, k)).collect();
        assert_eq!(ids, vec![0, 1, 5, 4]);
        let ids: Vec<usize> = (0..4).map(|k| small.corner_point_id(3, k)).collect();
        assert_eq!(ids, vec![10, 11, 15, 14]);
        assert!((t.point(2).x - 0.088 * 1.3).abs() < 1e-12);
    }

    #[test]
    fn bad_yaml_is_explained() {
        let p = Path::new("t.yaml");
        let e = AprilGridTarget::from_kalibr_yaml("target_type: 'checkerboard'\n", p);
        assert!(e.unwrap_err().to_string().contains("checkerboard"));
        let e = AprilGridTarget::from_kalibr_yaml("target_type: aprilgrid\ntagCols: 6\n", p);
        assert!(e.unwrap_err().to_string().contains("tagRows"));
        let e = AprilGridTarget::from_kalibr_yaml(
            "target_type: aprilgrid\ntagCols: 6\ntagRows: 6\ntagSize: abc\ntagSpacing: 0.3\n",
            p,
        );
        assert!(e.unwrap_err().to_string().contains("tagSize"));
        let e = AprilGridTarget::from_kalibr_yaml(
            "target_type: aprilgrid\ntagCols: 6\ntagRows: 6\ntagSize: 88\ntagSpacing: 0.3\n",
            p,
        );
        assert!(e.unwrap_err().to_string().contains("metres"));
    }

    #[test]
    fn svgs_are_drawn() {
        let t = AprilGridTarget::new(6, 6, 0.088, 0.3).unwrap();
        let svg = t.to_svg().unwrap();
        assert!(svg.contains("width=\"") && svg.ends_with("</svg>\n"));
        // The 49 junction squares and 36 tags each draw rectangles.
        assert!(svg.matches("<rect").count() > 49 + 36 * 28);
        let tag = aruco_svg("4x4_50", 7, 0.058).unwrap();
        assert!(tag.contains("id 7"));
        assert!(aruco_svg("4x4_50", 50, 0.058).is_err());
        assert!(aruco_svg("6x6_250", 1, 0.058).is_err());
        // Every tag's border is black and its ring white.
        let cells = apriltag_cells(0).unwrap();
        assert!(cells[1][1] && cells[8][8] && !cells[0][0] && !cells[9][5]);
    }
}
