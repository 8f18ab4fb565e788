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

    /// The board as black rectangles on a page (millimetres, 1 : 1), tag 0 at the bottom-left
    /// as in Kalibr's PDF, with a white quiet zone and a caption.
    pub fn drawing(&self) -> Result<Drawing> {
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
        // The page's y runs down: board (x, y) → (x + g + margin, margin + ph − (y + g)).
        let ox = g + margin;
        let oy = margin + ph - g;
        let mut rects = Vec::new();
        let mut rect = |x0: f64, y0: f64, x1: f64, y1: f64| {
            rects.push(Rect {
                x: ox + x0,
                y: oy - y1,
                w: x1 - x0,
                h: y1 - y0,
            });
        };
        for n in 0..=self.rows {
            for c in 0..=self.cols {
                let (x, y) = (c as f64 * p, n as f64 * p);
                rect(x - g, y - g, x, y);
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
                        rect(cx0, cy1 - b, cx0 + b, cy1);
                    }
                }
            }
        }
        Ok(Drawing {
            width_mm: w,
            height_mm: h,
            title: format!(
                "Kalibr aprilgrid {}x{} tags, tagSize {} m, tagSpacing {}",
                self.cols, self.rows, self.tag_size_m, self.spacing
            ),
            rects,
            caption: Caption {
                x: margin,
                y: h - 3.0,
                size: 4.0,
                text: format!(
                    "{}x{} tags, size={} cm, spacing={} cm — print at 100 % (actual size); \
                     measure the black square of a tag and put it in tagSize",
                    self.cols,
                    self.rows,
                    self.tag_size_m * 100.0,
                    self.spacing * self.tag_size_m * 100.0
                ),
            },
        })
    }

    /// A print-ready SVG of the board at 1 : 1 (millimetres), see [`AprilGridTarget::drawing`].
    pub fn to_svg(&self) -> Result<String> {
        let d = self.drawing()?;
        let (w, h) = (d.width_mm, d.height_mm);
        let mut s = String::new();
        let _ = writeln!(
            s,
            "<?xml version=\"1.0\" encoding=\"UTF-8\"?>\n<svg xmlns=\"http://www.w3.org/2000/svg\" \
             width=\"{w:.3}mm\" height=\"{h:.3}mm\" viewBox=\"0 0 {w:.3} {h:.3}\">"
        );
        let _ = writeln!(s, "<title>{}</title>", d.title);
        let _ = writeln!(
            s,
            "<rect x=\"0\" y=\"0\" width=\"{w:.3}\" height=\"{h:.3}\" fill=\"#ffffff\"/>"
        );
        let _ = writeln!(s, "<g fill=\"{INK}\" shape-rendering=\"crispEdges\">");
        for r in &d.rects {
            let _ = writeln!(
                s,
                "<rect x=\"{:.4}\" y=\"{:.4}\" width=\"{:.4}\" height=\"{:.4}\"/>",
                r.x, r.y, r.w, r.h
            );
        }
        let _ = writeln!(s, "</g>");
        let _ = writeln!(
            s,
            "<text x=\"{:.3}\" y=\"{:.3}\" font-family=\"sans-serif\" font-size=\"{}\" \
             fill=\"#000000\">{}</text>",
            d.caption.x, d.caption.y, d.caption.size, d.caption.text
        );
        let _ = writeln!(s, "</svg>");
        Ok(s)
    }

    /// A print-ready PDF of the board: one page of exactly the board's physical size.
    pub fn to_pdf(&self) -> Result<Vec<u8>> {
        Ok(self.drawing()?.to_pdf())
    }
}

/// A black rectangle on a page (mm; `x`, `y` of its top-left corner, y down).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Rect {
    /// Left edge (mm from the page's left).
    pub x: f64,
    /// Top edge (mm from the page's top).
    pub y: f64,
    /// Width (mm).
    pub w: f64,
    /// Height (mm).
    pub h: f64,
}

/// One line of text on a page.
#[derive(Debug, Clone, PartialEq)]
pub struct Caption {
    /// Left end of the baseline (mm from the page's left).
    pub x: f64,
    /// Baseline (mm from the page's top).
    pub y: f64,
    /// Font size (mm).
    pub size: f64,
    /// The text.
    pub text: String,
}

/// A printable page: black rectangles on white and a caption, in millimetres at 1 : 1.
#[derive(Debug, Clone, PartialEq)]
pub struct Drawing {
    /// Page width (mm).
    pub width_mm: f64,
    /// Page height (mm).
    pub height_mm: f64,
    /// Document title.
    pub title: String,
    /// The black rectangles.
    pub rects: Vec<Rect>,
    /// The caption under the pattern.
    pub caption: Caption,
}

/// PostScript points per millimetre (PDF user space: 1/72 inch).
pub const PT_PER_MM: f64 = 72.0 / 25.4;

/// A PDF string literal's body: ASCII only (the standard Helvetica font has no dash or
/// accented glyphs in PDF's default encoding), with `\`, `(` and `)` escaped.
fn pdf_text(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    for ch in text.chars() {
        match ch {
            '\\' | '(' | ')' => {
                out.push('\\');
                out.push(ch);
            }
            '—' | '–' => out.push('-'),
            c if c.is_ascii() && !c.is_ascii_control() => out.push(c),
            _ => out.push('?'),
        }
    }
    out
}

impl Drawing {
    /// A minimal PDF 1.4 of the drawing: one page whose MediaBox is the drawing's physical size,
    /// the rectangles as filled paths (vector, exact size when printed at 100 %), the caption
    /// in Helvetica. Objects: catalog, page tree, page, content stream, font, info.
    pub fn to_pdf(&self) -> Vec<u8> {
        let (wp, hp) = (self.width_mm * PT_PER_MM, self.height_mm * PT_PER_MM);
        let mut content = String::new();
        // User space in millimetres with y down from the page's top-left, as the drawing.
        let _ = writeln!(
            content,
            "q {PT_PER_MM:.9} 0 0 {:.9} 0 {hp:.4} cm 0 g",
            -PT_PER_MM
        );
        for r in &self.rects {
            let _ = writeln!(content, "{:.4} {:.4} {:.4} {:.4} re", r.x, r.y, r.w, r.h);
        }
        let _ = writeln!(content, "f Q");
        let c = &self.caption;
        let _ = writeln!(
            content,
            "BT /F1 {:.3} Tf {:.4} {:.4} Td ({}) Tj ET",
            c.size * PT_PER_MM,
            c.x * PT_PER_MM,
            hp - c.y * PT_PER_MM,
            pdf_text(&c.text)
        );
        let objects = [
            "<< /Type /Catalog /Pages 2 0 R >>".to_string(),
            "<< /Type /Pages /Kids [3 0 R] /Count 1 >>".to_string(),
            format!(
                "<< /Type /Page /Parent 2 0 R /MediaBox [0 0 {wp:.4} {hp:.4}] /Resources << \
                 /Font << /F1 5 0 R >> >> /Contents 4 0 R >>"
            ),
            format!(
                "<< /Length {} >>\nstream\n{content}endstream",
                content.len()
            ),
            "<< /Type /Font /Subtype /Type1 /BaseFont /Helvetica >>".to_string(),
            format!(
                "<< /Title ({}) /Producer (kiwi-calib) >>",
                pdf_text(&self.title)
            ),
        ];
        let mut out: Vec<u8> = b"%PDF-1.4\n%\xe2\xe3\xcf\xd3\n".to_vec();
        let mut offsets = Vec::with_capacity(objects.len());
        for (k, body) in objects.iter().enumerate() {
            offsets.push(out.len());
            out.extend_from_slice(format!("{} 0 obj\n{body}\nendobj\n", k + 1).as_bytes());
        }
        let xref = out.len();
        let mut tail = format!("xref\n0 {}\n0000000000 65535 f \n", objects.len() + 1);
        for o in &offsets {
            // Each entry is exactly 20 bytes: 10-digit offset, generation, 'n', space, LF.
            let _ = writeln!(tail, "{o:010} 00000 n ");
        }
        let _ = write!(
            tail,
            "trailer\n<< /Size {} /Root 1 0 R /Info 6 0 R >>\nstartxref\n{xref}\n%%EOF\n",
            objects.len() + 1
        );
        out.extend_from_slice(tail.as_bytes());
        out
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

    /// Check a PDF's cross-reference table: every entry points at its `N 0 obj`, `startxref`
    /// at `xref`; returns the MediaBox.
    fn check_pdf(pdf: &[u8]) -> [f64; 4] {
        // One char per byte, so string positions are byte offsets.
        let text: String = pdf
            .iter()
            .map(|&b| if b.is_ascii() { b as char } else { '?' })
            .collect();
        assert!(pdf.starts_with(b"%PDF-1.4\n") && pdf.ends_with(b"%%EOF\n"));
        let sx = text.rfind("startxref\n").unwrap();
        let xref: usize = text[sx + 10..].lines().next().unwrap().parse().unwrap();
        assert!(pdf[xref..].starts_with(b"xref\n"));
        let mut lines = text[xref..].lines().skip(1);
        let header: Vec<usize> = lines
            .next()
            .unwrap()
            .split(' ')
            .map(|x| x.parse().unwrap())
            .collect();
        assert_eq!(header[0], 0);
        let table = &pdf[xref + 5 + format!("0 {}\n", header[1]).len()..];
        for k in 0..header[1] {
            let entry = &table[20 * k..20 * (k + 1)];
            assert_eq!(entry[19], b'\n', "entry {k} is not 20 bytes");
            let off: usize = std::str::from_utf8(&entry[..10]).unwrap().parse().unwrap();
            if k > 0 {
                assert!(pdf[off..].starts_with(format!("{k} 0 obj\n").as_bytes()));
            }
        }
        assert!(text.contains(&format!("/Size {}", header[1])));
        // The content stream's /Length is its byte count up to "endstream".
        let ls = text.find("/Length ").unwrap();
        let len: usize = text[ls + 8..].split(' ').next().unwrap().parse().unwrap();
        let body = text[ls..].find("stream\n").unwrap() + ls + 7;
        assert!(text[body + len..].starts_with("endstream"));
        let mb = text.find("/MediaBox [").unwrap();
        let nums: Vec<f64> = text[mb + 11..]
            .split(']')
            .next()
            .unwrap()
            .split(' ')
            .map(|x| x.parse().unwrap())
            .collect();
        [nums[0], nums[1], nums[2], nums[3]]
    }

    #[test]
    fn board_pdf_is_well_formed_and_true_to_size() {
        let t = AprilGridTarget::new(6, 6, 0.088, 0.3).unwrap();
        let d = t.drawing().unwrap();
        let pdf = t.to_pdf().unwrap();
        let mb = check_pdf(&pdf);
        // 6 tags of 88 mm with 26.4 mm gaps, a 26.4 mm frame of junction squares, 2 gaps + 5 mm
        // of quiet zone each side, 8 mm of caption: 607.6 mm × 615.6 mm.
        let pattern = 6.0 * 88.0 * 1.3 + 26.4;
        let margin = 2.0 * 26.4 + 5.0;
        let (w, h) = (pattern + 2.0 * margin, pattern + 2.0 * margin + 8.0);
        assert!((d.width_mm - w).abs() < 1e-9 && (d.height_mm - h).abs() < 1e-9);
        assert_eq!(mb[0], 0.0);
        assert!((mb[2] - w * 72.0 / 25.4).abs() < 1e-3, "width {} pt", mb[2]);
        assert!(
            (mb[3] - h * 72.0 / 25.4).abs() < 1e-3,
            "height {} pt",
            mb[3]
        );
        // Every black rectangle is in the content stream, in millimetres.
        let text = String::from_utf8_lossy(&pdf);
        assert_eq!(text.matches(" re\n").count(), d.rects.len());
        let r = d.rects[0];
        assert!(text.contains(&format!("{:.4} {:.4} {:.4} {:.4} re", r.x, r.y, r.w, r.h)));
        // The junction squares are 26.4 mm and the tag cells 8.8 mm.
        assert!((r.w - 26.4).abs() < 1e-9 && (d.rects[49].w - 8.8).abs() < 1e-9);
        // The SVG draws the same rectangles.
        let svg = t.to_svg().unwrap();
        assert_eq!(svg.matches("<rect").count(), d.rects.len() + 1);
        assert!(text.contains("/F1 11.339 Tf") && text.contains("(6x6 tags, size="));
        assert_eq!(pdf_text("a (b) \\ — é"), "a \\(b\\) \\\\ - ?");
    }
}
