//! Small PNG charts for calibration reports: lines, markers and shaded bands on linear or
//! logarithmic axes, with a built-in 5×7 pixel font so no system font is needed.
//!
//! Reports must render the same on every machine (CI included) and without a font library, so
//! this module draws directly into an [`image::RgbImage`].

use std::path::Path;

use image::{Rgb, RgbImage};

use crate::error::{CalibError, Result};

/// Pixel scale of the built-in font (each font pixel is drawn as a `FONT_SCALE²` square).
const FONT_SCALE: i32 = 2;
/// Glyph advance in font pixels (5 wide + 1 space).
const GLYPH_ADVANCE: i32 = 6;
/// Margins around the plot area (pixels): left leaves room for tick labels and the y label.
const MARGIN_LEFT: i32 = 110;
const MARGIN_RIGHT: i32 = 30;
const MARGIN_TOP: i32 = 50;
const MARGIN_BOTTOM: i32 = 70;

/// How a series is drawn.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Style {
    /// Connected line of the given width (pixels).
    Line(u32),
    /// Dashed line of the given width (pixels).
    Dashed(u32),
    /// A filled square marker of the given size (pixels) at each point.
    Markers(u32),
}

/// One data series.
#[derive(Debug, Clone)]
pub struct Series {
    /// Legend text (empty: not in the legend).
    pub name: String,
    /// RGB colour.
    pub color: [u8; 3],
    /// Drawing style.
    pub style: Style,
    /// Points `(x, y)`; non-finite points (or non-positive on a log axis) are skipped.
    pub points: Vec<(f64, f64)>,
}

/// A shaded band between `lower` and `upper` at common `x` values.
#[derive(Debug, Clone)]
pub struct Band {
    /// RGB colour (drawn at 30 % opacity).
    pub color: [u8; 3],
    /// `(x, lower, upper)` sorted by `x`.
    pub points: Vec<(f64, f64, f64)>,
}

/// An arrow from a point by a displacement (both in data units), for residual vector plots.
#[derive(Debug, Clone, Copy)]
pub struct Arrow {
    /// Start `(x, y)`.
    pub from: (f64, f64),
    /// End `(x, y)`.
    pub to: (f64, f64),
}

/// A chart: axes, series, bands, labels.
#[derive(Debug, Clone)]
pub struct Figure {
    /// Image width (pixels).
    pub width: u32,
    /// Image height (pixels).
    pub height: u32,
    /// Title above the plot.
    pub title: String,
    /// x-axis label.
    pub x_label: String,
    /// y-axis label.
    pub y_label: String,
    /// Logarithmic x axis.
    pub x_log: bool,
    /// Logarithmic y axis.
    pub y_log: bool,
    /// Fixed x range (otherwise from the data).
    pub x_range: Option<(f64, f64)>,
    /// Fixed y range (otherwise from the data).
    pub y_range: Option<(f64, f64)>,
    /// Data series, drawn in order.
    pub series: Vec<Series>,
    /// Shaded bands, drawn below the series.
    pub bands: Vec<Band>,
    /// Arrows, drawn in the colour `arrow_color`.
    pub arrows: Vec<Arrow>,
    /// Arrow colour.
    pub arrow_color: [u8; 3],
    /// Where the legend goes.
    pub legend: Corner,
}

/// A corner of the plot area (for the legend).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Corner {
    /// Top right (the default).
    TopRight,
    /// Top left.
    TopLeft,
    /// Bottom left.
    BottomLeft,
    /// Bottom right.
    BottomRight,
}

impl Figure {
    /// An empty figure of the given size.
    pub fn new(width: u32, height: u32, title: &str, x_label: &str, y_label: &str) -> Self {
        Self {
            width,
            height,
            title: title.to_owned(),
            x_label: x_label.to_owned(),
            y_label: y_label.to_owned(),
            x_log: false,
            y_log: false,
            x_range: None,
            y_range: None,
            series: Vec::new(),
            bands: Vec::new(),
            arrows: Vec::new(),
            arrow_color: [200, 30, 30],
            legend: Corner::TopRight,
        }
    }

    /// Write the chart as a PNG, atomically.
    pub fn save_png(&self, path: &Path) -> Result<()> {
        save_png(self.render(), path)
    }

    /// Render the chart.
    pub fn render(&self) -> RgbImage {
        let mut img = RgbImage::from_pixel(self.width, self.height, Rgb([255, 255, 255]));
        let area = PlotArea {
            x0: MARGIN_LEFT,
            y0: MARGIN_TOP,
            x1: self.width as i32 - MARGIN_RIGHT,
            y1: self.height as i32 - MARGIN_BOTTOM,
            x: Axis::new(self.x_range.or_else(|| self.data_range(true)), self.x_log),
            y: Axis::new(self.y_range.or_else(|| self.data_range(false)), self.y_log),
        };
        self.draw_grid(&mut img, &area);
        for band in &self.bands {
            draw_band(&mut img, &area, band);
        }
        for s in &self.series {
            draw_series(&mut img, &area, s);
        }
        for a in &self.arrows {
            if let (Some(p), Some(q)) = (area.to_px(a.from), area.to_px(a.to)) {
                line(&mut img, p, q, 1.0, self.arrow_color, None);
            }
        }
        // Frame, labels, legend on top.
        rect_outline(&mut img, area.x0, area.y0, area.x1, area.y1, [0, 0, 0]);
        let title_w = text_width(&self.title);
        text(
            &mut img,
            (self.width as i32 - title_w) / 2,
            14,
            &self.title,
            [0, 0, 0],
        );
        let xl_w = text_width(&self.x_label);
        text(
            &mut img,
            (area.x0 + area.x1 - xl_w) / 2,
            self.height as i32 - 24,
            &self.x_label,
            [0, 0, 0],
        );
        text(&mut img, 8, MARGIN_TOP - 24, &self.y_label, [0, 0, 0]);
        self.draw_legend(&mut img, &area);
        img
    }

    fn data_range(&self, x_axis: bool) -> Option<(f64, f64)> {
        let log = if x_axis { self.x_log } else { self.y_log };
        let mut lo = f64::INFINITY;
        let mut hi = f64::NEG_INFINITY;
        let mut add = |v: f64| {
            if v.is_finite() && (!log || v > 0.0) {
                lo = lo.min(v);
                hi = hi.max(v);
            }
        };
        for s in &self.series {
            for &(x, y) in &s.points {
                add(if x_axis { x } else { y });
            }
        }
        for b in &self.bands {
            for &(x, l, u) in &b.points {
                if x_axis {
                    add(x);
                } else {
                    add(l);
                    add(u);
                }
            }
        }
        for a in &self.arrows {
            add(if x_axis { a.from.0 } else { a.from.1 });
            add(if x_axis { a.to.0 } else { a.to.1 });
        }
        (lo <= hi).then_some((lo, hi))
    }

    fn draw_grid(&self, img: &mut RgbImage, area: &PlotArea) {
        let grid = [225, 225, 225];
        for (v, label) in area.x.ticks() {
            let px = area.x_px(v);
            if let Some(px) = px {
                let xi = px.round() as i32;
                vline(img, xi, area.y0, area.y1, grid);
                let w = text_width(&label);
                text(img, xi - w / 2, area.y1 + 8, &label, [0, 0, 0]);
            }
        }
        for (v, label) in area.y.ticks() {
            if let Some(py) = area.y_px(v) {
                let yi = py.round() as i32;
                hline(img, area.x0, area.x1, yi, grid);
                let w = text_width(&label);
                text(img, area.x0 - w - 6, yi - 7, &label, [0, 0, 0]);
            }
        }
    }

    fn draw_legend(&self, img: &mut RgbImage, area: &PlotArea) {
        let named: Vec<&Series> = self.series.iter().filter(|s| !s.name.is_empty()).collect();
        if named.is_empty() {
            return;
        }
        let w = named.iter().map(|s| text_width(&s.name)).max().unwrap_or(0) + 40;
        let h = named.len() as i32 * 20 + 8;
        let (x0, y0) = match self.legend {
            Corner::TopRight => (area.x1 - w - 8, area.y0 + 8),
            Corner::TopLeft => (area.x0 + 8, area.y0 + 8),
            Corner::BottomLeft => (area.x0 + 8, area.y1 - h - 8),
            Corner::BottomRight => (area.x1 - w - 8, area.y1 - h - 8),
        };
        fill_rect(img, x0, y0, x0 + w, y0 + h, [255, 255, 255]);
        rect_outline(img, x0, y0, x0 + w, y0 + h, [120, 120, 120]);
        for (i, s) in named.iter().enumerate() {
            let y = y0 + 6 + i as i32 * 20;
            fill_rect(img, x0 + 6, y + 4, x0 + 26, y + 10, s.color);
            text(img, x0 + 32, y, &s.name, [0, 0, 0]);
        }
    }
}

/// One axis's mapping from data to the unit interval.
#[derive(Debug, Clone, Copy)]
struct Axis {
    lo: f64,
    hi: f64,
    log: bool,
}

impl Axis {
    fn new(range: Option<(f64, f64)>, log: bool) -> Self {
        let (mut lo, mut hi) = range.unwrap_or(if log { (1.0, 10.0) } else { (0.0, 1.0) });
        if log {
            lo = lo.max(f64::MIN_POSITIVE).log10().floor();
            hi = hi.max(f64::MIN_POSITIVE).log10().ceil();
            if hi <= lo {
                hi = lo + 1.0;
            }
        } else {
            if hi <= lo {
                let pad = if lo == 0.0 { 1.0 } else { lo.abs() * 0.1 };
                lo -= pad;
                hi += pad;
            }
            let pad = (hi - lo) * 0.05;
            lo -= pad;
            hi += pad;
        }
        Self { lo, hi, log }
    }

    /// Position in [0, 1] along the axis, `None` for values a log axis cannot show.
    fn unit(&self, v: f64) -> Option<f64> {
        if !v.is_finite() {
            return None;
        }
        let v = if self.log {
            if v <= 0.0 {
                return None;
            }
            v.log10()
        } else {
            v
        };
        Some((v - self.lo) / (self.hi - self.lo))
    }

    /// Tick positions and their labels.
    fn ticks(&self) -> Vec<(f64, String)> {
        if self.log {
            let decades = (self.hi - self.lo).round() as i32;
            let step = (decades / 8).max(1);
            (self.lo as i32..=self.hi as i32)
                .step_by(step as usize)
                .map(|e| (10f64.powi(e), format!("1E{e}")))
                .collect()
        } else {
            let span = self.hi - self.lo;
            let raw = span / 6.0;
            let mag = 10f64.powf(raw.log10().floor());
            let step = [1.0, 2.0, 5.0, 10.0]
                .iter()
                .map(|k| k * mag)
                .find(|s| *s >= raw)
                .unwrap_or(10.0 * mag);
            let first = (self.lo / step).ceil() as i64;
            let last = (self.hi / step).floor() as i64;
            (first..=last)
                .map(|i| {
                    let v = i as f64 * step;
                    (v, format_tick(v, step))
                })
                .collect()
        }
    }
}

fn format_tick(v: f64, step: f64) -> String {
    let decimals = if step >= 1.0 {
        0
    } else {
        (-step.log10().floor()) as usize
    };
    if v.abs() >= 1e5 || (v != 0.0 && v.abs() < 1e-3) {
        format!("{v:.1E}")
    } else {
        format!("{v:.decimals$}")
    }
}

struct PlotArea {
    x0: i32,
    y0: i32,
    x1: i32,
    y1: i32,
    x: Axis,
    y: Axis,
}

impl PlotArea {
    fn x_px(&self, v: f64) -> Option<f64> {
        self.x
            .unit(v)
            .map(|u| f64::from(self.x0) + u * f64::from(self.x1 - self.x0))
    }

    fn y_px(&self, v: f64) -> Option<f64> {
        self.y
            .unit(v)
            .map(|u| f64::from(self.y1) - u * f64::from(self.y1 - self.y0))
    }

    fn to_px(&self, p: (f64, f64)) -> Option<(f64, f64)> {
        Some((self.x_px(p.0)?, self.y_px(p.1)?))
    }

    fn inside(&self, x: i32, y: i32) -> bool {
        x >= self.x0 && x <= self.x1 && y >= self.y0 && y <= self.y1
    }
}

fn draw_series(img: &mut RgbImage, area: &PlotArea, s: &Series) {
    let pts: Vec<(f64, f64)> = s.points.iter().filter_map(|&p| area.to_px(p)).collect();
    match s.style {
        Style::Line(w) | Style::Dashed(w) => {
            let dash = if matches!(s.style, Style::Dashed(_)) {
                8.0
            } else {
                f64::INFINITY
            };
            for pair in pts.windows(2) {
                line(
                    img,
                    pair[0],
                    pair[1],
                    f64::from(w),
                    s.color,
                    Some((dash, area)),
                );
            }
        }
        Style::Markers(size) => {
            let h = size as i32 / 2;
            for &(x, y) in &pts {
                let (xi, yi) = (x.round() as i32, y.round() as i32);
                if area.inside(xi, yi) {
                    fill_rect(img, xi - h, yi - h, xi + h, yi + h, s.color);
                }
            }
        }
    }
}

fn draw_band(img: &mut RgbImage, area: &PlotArea, band: &Band) {
    let pts: Vec<(f64, f64, f64)> = band
        .points
        .iter()
        .filter_map(|&(x, l, u)| Some((area.x_px(x)?, area.y_px(l)?, area.y_px(u)?)))
        .collect();
    for pair in pts.windows(2) {
        let (a, b) = (pair[0], pair[1]);
        let (xa, xb) = (a.0.min(b.0).round() as i32, a.0.max(b.0).round() as i32);
        for x in xa..=xb {
            let f = if (b.0 - a.0).abs() < 1e-9 {
                0.0
            } else {
                (f64::from(x) - a.0) / (b.0 - a.0)
            };
            let lo = a.1 + (b.1 - a.1) * f;
            let hi = a.2 + (b.2 - a.2) * f;
            let (y0, y1) = (lo.min(hi).round() as i32, lo.max(hi).round() as i32);
            for y in y0.max(area.y0)..=y1.min(area.y1) {
                if area.inside(x, y) {
                    blend(img, x, y, band.color, 0.3);
                }
            }
        }
    }
}

/// A line of width `w` from `p` to `q`; with `dash = Some((period, area))` it is dashed (an
/// infinite period draws it solid) and clipped to the plot area.
fn line(
    img: &mut RgbImage,
    p: (f64, f64),
    q: (f64, f64),
    w: f64,
    color: [u8; 3],
    dash: Option<(f64, &PlotArea)>,
) {
    let len = ((q.0 - p.0).powi(2) + (q.1 - p.1).powi(2)).sqrt();
    let steps = (len * 2.0).ceil().max(1.0) as usize;
    let r = (w / 2.0).max(0.5);
    let ri = r.ceil() as i32;
    for i in 0..=steps {
        let f = i as f64 / steps as f64;
        if let Some((period, _)) = dash
            && (f * len / period).floor() as i64 % 2 == 1
        {
            continue;
        }
        let (x, y) = (p.0 + (q.0 - p.0) * f, p.1 + (q.1 - p.1) * f);
        let (xi, yi) = (x.round() as i32, y.round() as i32);
        for dy in -ri..=ri {
            for dx in -ri..=ri {
                let d2 = f64::from(dx * dx + dy * dy);
                if d2 <= r * r + 0.25 {
                    let (px, py) = (xi + dx, yi + dy);
                    if dash.is_none_or(|(_, a)| a.inside(px, py)) {
                        put(img, px, py, color);
                    }
                }
            }
        }
    }
}

fn put(img: &mut RgbImage, x: i32, y: i32, color: [u8; 3]) {
    if x >= 0 && y >= 0 && (x as u32) < img.width() && (y as u32) < img.height() {
        img.put_pixel(x as u32, y as u32, Rgb(color));
    }
}

fn blend(img: &mut RgbImage, x: i32, y: i32, color: [u8; 3], alpha: f64) {
    if x >= 0 && y >= 0 && (x as u32) < img.width() && (y as u32) < img.height() {
        let p = img.get_pixel_mut(x as u32, y as u32);
        for c in 0..3 {
            p.0[c] =
                (f64::from(p.0[c]) * (1.0 - alpha) + f64::from(color[c]) * alpha).round() as u8;
        }
    }
}

fn hline(img: &mut RgbImage, x0: i32, x1: i32, y: i32, color: [u8; 3]) {
    for x in x0..=x1 {
        put(img, x, y, color);
    }
}

fn vline(img: &mut RgbImage, x: i32, y0: i32, y1: i32, color: [u8; 3]) {
    for y in y0..=y1 {
        put(img, x, y, color);
    }
}

fn rect_outline(img: &mut RgbImage, x0: i32, y0: i32, x1: i32, y1: i32, color: [u8; 3]) {
    hline(img, x0, x1, y0, color);
    hline(img, x0, x1, y1, color);
    vline(img, x0, y0, y1, color);
    vline(img, x1, y0, y1, color);
}

/// Encode an image as PNG and write it atomically (every report image goes through here).
pub fn save_png(image: RgbImage, path: &Path) -> Result<()> {
    let mut bytes = Vec::new();
    image::DynamicImage::ImageRgb8(image)
        .write_to(
            &mut std::io::Cursor::new(&mut bytes),
            image::ImageFormat::Png,
        )
        .map_err(|e| CalibError::Internal(format!("encoding {}: {e}", path.display())))?;
    kiwi_core::io::write_atomic(path, &bytes)?;
    Ok(())
}

/// Fill the rectangle `[x0, x1] × [y0, y1]`.
pub fn fill_rect(img: &mut RgbImage, x0: i32, y0: i32, x1: i32, y1: i32, color: [u8; 3]) {
    for y in y0..=y1 {
        hline(img, x0, x1, y, color);
    }
}

/// Width in pixels of `s` in the built-in font.
pub fn text_width(s: &str) -> i32 {
    s.chars().count() as i32 * GLYPH_ADVANCE * FONT_SCALE
}

/// Draw `s` with its top-left corner at `(x, y)` in the built-in 5×7 font (letters are drawn
/// upper-case).
pub fn text(img: &mut RgbImage, x: i32, y: i32, s: &str, color: [u8; 3]) {
    for (i, ch) in s.chars().enumerate() {
        let rows = glyph(ch);
        let gx = x + i as i32 * GLYPH_ADVANCE * FONT_SCALE;
        for (r, bits) in rows.iter().enumerate() {
            for c in 0..5 {
                if bits & (0x10 >> c) != 0 {
                    let px = gx + c * FONT_SCALE;
                    let py = y + r as i32 * FONT_SCALE;
                    fill_rect(img, px, py, px + FONT_SCALE - 1, py + FONT_SCALE - 1, color);
                }
            }
        }
    }
}

/// The 5×7 bitmap of a character (bit 4 is the leftmost column).
fn glyph(ch: char) -> [u8; 7] {
    match ch.to_ascii_uppercase() {
        ' ' => [0; 7],
        '0' => [0x0E, 0x11, 0x13, 0x15, 0x19, 0x11, 0x0E],
        '1' => [0x04, 0x0C, 0x04, 0x04, 0x04, 0x04, 0x0E],
        '2' => [0x0E, 0x11, 0x01, 0x02, 0x04, 0x08, 0x1F],
        '3' => [0x1F, 0x02, 0x04, 0x02, 0x01, 0x11, 0x0E],
        '4' => [0x02, 0x06, 0x0A, 0x12, 0x1F, 0x02, 0x02],
        '5' => [0x1F, 0x10, 0x1E, 0x01, 0x01, 0x11, 0x0E],
        '6' => [0x06, 0x08, 0x10, 0x1E, 0x11, 0x11, 0x0E],
        '7' => [0x1F, 0x01, 0x02, 0x04, 0x08, 0x08, 0x08],
        '8' => [0x0E, 0x11, 0x11, 0x0E, 0x11, 0x11, 0x0E],
        '9' => [0x0E, 0x11, 0x11, 0x0F, 0x01, 0x02, 0x0C],
        'A' => [0x0E, 0x11, 0x11, 0x1F, 0x11, 0x11, 0x11],
        'B' => [0x1E, 0x11, 0x11, 0x1E, 0x11, 0x11, 0x1E],
        'C' => [0x0E, 0x11, 0x10, 0x10, 0x10, 0x11, 0x0E],
        'D' => [0x1C, 0x12, 0x11, 0x11, 0x11, 0x12, 0x1C],
        'E' => [0x1F, 0x10, 0x10, 0x1E, 0x10, 0x10, 0x1F],
        'F' => [0x1F, 0x10, 0x10, 0x1E, 0x10, 0x10, 0x10],
        'G' => [0x0E, 0x11, 0x10, 0x17, 0x11, 0x11, 0x0F],
        'H' => [0x11, 0x11, 0x11, 0x1F, 0x11, 0x11, 0x11],
        'I' => [0x0E, 0x04, 0x04, 0x04, 0x04, 0x04, 0x0E],
        'J' => [0x07, 0x02, 0x02, 0x02, 0x02, 0x12, 0x0C],
        'K' => [0x11, 0x12, 0x14, 0x18, 0x14, 0x12, 0x11],
        'L' => [0x10, 0x10, 0x10, 0x10, 0x10, 0x10, 0x1F],
        'M' => [0x11, 0x1B, 0x15, 0x15, 0x11, 0x11, 0x11],
        'N' => [0x11, 0x11, 0x19, 0x15, 0x13, 0x11, 0x11],
        'O' => [0x0E, 0x11, 0x11, 0x11, 0x11, 0x11, 0x0E],
        'P' => [0x1E, 0x11, 0x11, 0x1E, 0x10, 0x10, 0x10],
        'Q' => [0x0E, 0x11, 0x11, 0x11, 0x15, 0x12, 0x0D],
        'R' => [0x1E, 0x11, 0x11, 0x1E, 0x14, 0x12, 0x11],
        'S' => [0x0F, 0x10, 0x10, 0x0E, 0x01, 0x01, 0x1E],
        'T' => [0x1F, 0x04, 0x04, 0x04, 0x04, 0x04, 0x04],
        'U' => [0x11, 0x11, 0x11, 0x11, 0x11, 0x11, 0x0E],
        'V' => [0x11, 0x11, 0x11, 0x11, 0x11, 0x0A, 0x04],
        'W' => [0x11, 0x11, 0x11, 0x15, 0x15, 0x15, 0x0A],
        'X' => [0x11, 0x11, 0x0A, 0x04, 0x0A, 0x11, 0x11],
        'Y' => [0x11, 0x11, 0x11, 0x0A, 0x04, 0x04, 0x04],
        'Z' => [0x1F, 0x01, 0x02, 0x04, 0x08, 0x10, 0x1F],
        '.' => [0x00, 0x00, 0x00, 0x00, 0x00, 0x0C, 0x0C],
        ',' => [0x00, 0x00, 0x00, 0x00, 0x0C, 0x04, 0x08],
        '-' => [0x00, 0x00, 0x00, 0x1F, 0x00, 0x00, 0x00],
        '+' => [0x00, 0x04, 0x04, 0x1F, 0x04, 0x04, 0x00],
        '/' => [0x00, 0x01, 0x02, 0x04, 0x08, 0x10, 0x00],
        '(' => [0x02, 0x04, 0x08, 0x08, 0x08, 0x04, 0x02],
        ')' => [0x08, 0x04, 0x02, 0x02, 0x02, 0x04, 0x08],
        '[' => [0x0E, 0x08, 0x08, 0x08, 0x08, 0x08, 0x0E],
        ']' => [0x0E, 0x02, 0x02, 0x02, 0x02, 0x02, 0x0E],
        ':' => [0x00, 0x0C, 0x0C, 0x00, 0x0C, 0x0C, 0x00],
        '%' => [0x18, 0x19, 0x02, 0x04, 0x08, 0x13, 0x03],
        '=' => [0x00, 0x00, 0x1F, 0x00, 0x1F, 0x00, 0x00],
        '_' => [0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x1F],
        '\'' => [0x04, 0x04, 0x08, 0x00, 0x00, 0x00, 0x00],
        '*' => [0x00, 0x04, 0x15, 0x0E, 0x15, 0x04, 0x00],
        '<' => [0x02, 0x04, 0x08, 0x10, 0x08, 0x04, 0x02],
        '>' => [0x08, 0x04, 0x02, 0x01, 0x02, 0x04, 0x08],
        '|' => [0x04; 7],
        '°' => [0x0C, 0x12, 0x12, 0x0C, 0x00, 0x00, 0x00],
        'µ' | 'Μ' => [0x00, 0x11, 0x11, 0x11, 0x13, 0x1D, 0x10],
        '√' => [0x07, 0x04, 0x04, 0x04, 0x14, 0x0C, 0x04],
        '²' => [0x0C, 0x12, 0x04, 0x08, 0x1E, 0x00, 0x00],
        '·' => [0x00, 0x00, 0x00, 0x0C, 0x0C, 0x00, 0x00],
        _ => [0x0E, 0x11, 0x01, 0x02, 0x04, 0x00, 0x04],
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn log_chart_draws_series_inside_the_frame() {
        let mut f = Figure::new(400, 300, "Test", "tau (s)", "adev");
        f.x_log = true;
        f.y_log = true;
        f.series.push(Series {
            name: "data".into(),
            color: [0, 0, 255],
            style: Style::Line(2),
            points: (0..20)
                .map(|i| {
                    (
                        10f64.powf(f64::from(i) / 5.0 - 2.0),
                        1e-3 / f64::from(i + 1),
                    )
                })
                .collect(),
        });
        let img = f.render();
        let blue = img.pixels().filter(|p| p.0 == [0, 0, 255]).count();
        assert!(blue > 100, "{blue}");
    }

    #[test]
    fn ticks_are_round_numbers() {
        let a = Axis::new(Some((0.0, 9.3)), false);
        let t = a.ticks();
        assert!(t.iter().any(|(v, s)| *v == 4.0 && s == "4"), "{t:?}");
        let l = Axis::new(Some((2e-4, 3.0)), true);
        assert_eq!(
            l.ticks().first().map(|x| x.1.clone()),
            Some("1E-4".to_owned())
        );
    }
}
