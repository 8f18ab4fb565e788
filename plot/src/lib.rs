//! KIWI's charts, in one crate that every program can use (the certification report of
//! `kiwi-calib` draws with it).
//!
//! A [`Chart`] holds named axes (label with unit, linear or logarithmic, optional fixed range),
//! data series drawn as lines, dashed lines or points, shaded bands, filled rectangles in data
//! coordinates (bar charts, heat-map cells), arrows, and a legend. It renders to SVG with `plotters`: text stays `<text>` elements, so no system
//! font is needed and the result is the same on every machine. The helper [`bars`] builds
//! a bar chart's rectangles and [`decimate`] thins long point series. A [`Timeline`] (rows of
//! coloured time spans, named on the y axis) and a [`NodeGraph`] (named nodes joined by
//! labelled edges) serve the session report of `kiwi`.

mod graph;
mod timeline;

pub use graph::{Edge, NodeGraph};
pub use timeline::{Span, Timeline};

use std::path::Path;

use plotters::coord::Shift;
use plotters::coord::ranged1d::{AsRangedCoord, ValueFormatter};
use plotters::prelude::*;

/// Errors of the plotting crate.
#[derive(Debug, thiserror::Error)]
pub enum PlotError {
    /// The drawing backend failed (it only writes into memory, so this is a bug in a chart).
    #[error("drawing the chart `{title}` failed: {message}")]
    Draw {
        /// The chart's title.
        title: String,
        /// The backend's message.
        message: String,
    },
    /// A chart's settings are not drawable.
    #[error("chart `{title}`: {message}")]
    Invalid {
        /// The chart's title.
        title: String,
        /// What is wrong and what to do.
        message: String,
    },
    /// Writing the SVG file failed.
    #[error(transparent)]
    Io(#[from] kiwi_core::CoreError),
}

/// Result of this crate.
pub type Result<T> = std::result::Result<T, PlotError>;

/// An RGB colour.
pub type Rgb = [u8; 3];

/// Colours for classes and series, distinguishable on white and in print (Tableau 10).
pub const PALETTE: [Rgb; 10] = [
    [31, 119, 180],
    [255, 127, 14],
    [44, 160, 44],
    [214, 39, 40],
    [148, 103, 189],
    [140, 86, 75],
    [227, 119, 194],
    [127, 127, 127],
    [188, 189, 34],
    [23, 190, 207],
];

/// Font size of the title (pixels).
const TITLE_FONT_PX: u32 = 18;
/// Font size of axis labels, ticks and legend (pixels).
const LABEL_FONT_PX: u32 = 13;
/// Room for the x tick labels and the x-axis name (pixels).
const X_LABEL_AREA_PX: u32 = 45;
/// Room for the y tick labels and the y-axis name (pixels).
const Y_LABEL_AREA_PX: u32 = 70;
/// Share of the data span added on each side of an automatic linear range, so points on the
/// edge stay visible.
const AUTO_RANGE_PAD: f64 = 0.04;
/// Opacity of shaded bands.
const BAND_OPACITY: f64 = 0.3;
/// Colour of arrows (residual vectors): red stands out over the blue and grey layers.
const ARROW_COLOR: Rgb = [200, 30, 30];
/// Smallest and largest accepted image side (pixels): smaller charts cannot hold their
/// labels, larger ones only bloat the pages they are embedded in.
const SIDE_RANGE_PX: (u32, u32) = (120, 4000);

/// One axis: its name with unit, scale and range.
#[derive(Debug, Clone, Default)]
pub struct Axis {
    /// Name with unit, e.g. `time (s)`.
    pub label: String,
    /// Logarithmic scale (non-positive values are skipped).
    pub log: bool,
    /// Fixed range; otherwise taken from the data.
    pub range: Option<(f64, f64)>,
}

impl Axis {
    /// A linear axis with automatic range.
    pub fn new(label: &str) -> Self {
        Self {
            label: label.to_owned(),
            log: false,
            range: None,
        }
    }

    /// A logarithmic axis with automatic range.
    pub fn log(label: &str) -> Self {
        Self {
            log: true,
            ..Self::new(label)
        }
    }

    /// The same axis with a fixed range.
    pub fn with_range(mut self, lo: f64, hi: f64) -> Self {
        self.range = Some((lo, hi));
        self
    }
}

/// How a series is drawn.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Mark {
    /// Connected line of the given width (pixels).
    Line(u32),
    /// Dashed line of the given width (pixels).
    Dashed(u32),
    /// A filled circle of the given radius (pixels) at each point.
    Points(u32),
}

/// One data series.
#[derive(Debug, Clone)]
pub struct Series {
    /// Legend text (empty: not in the legend).
    pub name: String,
    /// Colour.
    pub color: Rgb,
    /// How it is drawn.
    pub mark: Mark,
    /// Points `(x, y)`; non-finite points (and non-positive ones on a log axis) are skipped,
    /// and a skipped point breaks a line.
    pub points: Vec<(f64, f64)>,
}

impl Series {
    /// A named series.
    pub fn new(name: &str, color: Rgb, mark: Mark, points: Vec<(f64, f64)>) -> Self {
        Self {
            name: name.to_owned(),
            color,
            mark,
            points,
        }
    }
}

/// A shaded band between a lower and an upper curve.
#[derive(Debug, Clone)]
pub struct Band {
    /// Legend text (empty: not in the legend).
    pub name: String,
    /// Colour (drawn translucent).
    pub color: Rgb,
    /// `(x, lower, upper)` sorted by `x`.
    pub points: Vec<(f64, f64, f64)>,
}

/// An axis-aligned rectangle in data coordinates.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Rect {
    /// Left edge.
    pub x0: f64,
    /// Right edge.
    pub x1: f64,
    /// Bottom edge.
    pub y0: f64,
    /// Top edge.
    pub y1: f64,
}

/// Filled rectangles of one colour: bars, heat-map cells.
#[derive(Debug, Clone)]
pub struct Rects {
    /// Legend text (empty: not in the legend).
    pub name: String,
    /// Fill colour.
    pub color: Rgb,
    /// The rectangles.
    pub rects: Vec<Rect>,
}

/// An arrow from a point to another (data coordinates), e.g. a magnified residual.
#[derive(Debug, Clone, Copy)]
pub struct Arrow {
    /// Start `(x, y)`.
    pub from: (f64, f64),
    /// End `(x, y)`; drawn with a dot.
    pub to: (f64, f64),
}

/// Where the legend goes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Corner {
    /// Inside, top right (the default).
    #[default]
    TopRight,
    /// Inside, top left.
    TopLeft,
    /// Inside, bottom left.
    BottomLeft,
    /// Inside, bottom right.
    BottomRight,
}

/// A chart: title, axes and layers, rendered to SVG.
#[derive(Debug, Clone)]
pub struct Chart {
    /// Image width (pixels).
    pub width: u32,
    /// Image height (pixels).
    pub height: u32,
    /// Title above the plot.
    pub title: String,
    /// Horizontal axis.
    pub x: Axis,
    /// Vertical axis.
    pub y: Axis,
    /// Show one data unit as the same length on both axes (maps, image planes): the shorter
    /// range is widened. Ignored on logarithmic axes.
    pub equal_aspect: bool,
    /// Rectangles, drawn first.
    pub rects: Vec<Rects>,
    /// Bands, drawn over the rectangles.
    pub bands: Vec<Band>,
    /// Series, drawn in order over the bands.
    pub series: Vec<Series>,
    /// Arrows, drawn over the series.
    pub arrows: Vec<Arrow>,
    /// Where the legend goes.
    pub legend: Corner,
    /// Names of the rows y = 0, 1, 2, … (bottom to top): when set, the y ticks show these
    /// names instead of numbers (timelines, category charts).
    pub y_categories: Vec<String>,
}

/// Width of one character of tick text (pixels, 13 px sans-serif), to size the y label area for
/// category names.
const CHAR_WIDTH_PX: u32 = 7;
/// How close a y tick must be to a whole number to carry that row's category name.
const CATEGORY_TICK_TOLERANCE: f64 = 1e-6;

impl Chart {
    /// An empty chart.
    pub fn new(width: u32, height: u32, title: &str, x: Axis, y: Axis) -> Self {
        Self {
            width,
            height,
            title: title.to_owned(),
            x,
            y,
            equal_aspect: false,
            rects: Vec::new(),
            bands: Vec::new(),
            series: Vec::new(),
            arrows: Vec::new(),
            legend: Corner::TopRight,
            y_categories: Vec::new(),
        }
    }

    /// Write charts stacked top to bottom as one SVG file, atomically.
    pub fn save_stack_svg(charts: &[Chart], path: &Path) -> Result<()> {
        let svg = Self::stack_to_svg(charts)?;
        kiwi_core::io::write_atomic(path, svg.as_bytes())?;
        Ok(())
    }

    /// Write the chart as an SVG file, atomically.
    pub fn save_svg(&self, path: &Path) -> Result<()> {
        let svg = self.to_svg()?;
        kiwi_core::io::write_atomic(path, svg.as_bytes())?;
        Ok(())
    }

    /// The chart as an SVG document (also fit to be inlined in HTML).
    pub fn to_svg(&self) -> Result<String> {
        Self::stack_to_svg(std::slice::from_ref(self))
    }

    /// Charts stacked top to bottom in one SVG document (each keeps its own size; the
    /// document is as wide as the widest).
    pub fn stack_to_svg(charts: &[Chart]) -> Result<String> {
        let Some(first) = charts.first() else {
            return Err(PlotError::Invalid {
                title: String::new(),
                message: "no chart to stack; pass at least one".into(),
            });
        };
        for c in charts {
            c.check_size()?;
        }
        let width = charts.iter().map(|c| c.width).fold(first.width, u32::max);
        let height: u32 = charts.iter().map(|c| c.height).sum();
        let mut buf = String::new();
        {
            let root = SVGBackend::with_string(&mut buf, (width, height)).into_drawing_area();
            let mut top = 0i32;
            for c in charts {
                let bottom = top + c.height as i32;
                let area = root.clone().shrink((0, top), (c.width, c.height));
                c.draw_on(&area).map_err(|message| PlotError::Draw {
                    title: c.title.clone(),
                    message,
                })?;
                top = bottom;
            }
            root.present().map_err(|e| PlotError::Draw {
                title: first.title.clone(),
                message: e.to_string(),
            })?;
        }
        Ok(buf)
    }

    fn check_size(&self) -> Result<()> {
        let (lo, hi) = SIDE_RANGE_PX;
        if !(lo..=hi).contains(&self.width) || !(lo..=hi).contains(&self.height) {
            return Err(PlotError::Invalid {
                title: self.title.clone(),
                message: format!(
                    "size {}×{} px is outside {lo}..={hi} px per side; choose a size in range",
                    self.width, self.height
                ),
            });
        }
        Ok(())
    }

    fn draw_on(
        &self,
        root: &DrawingArea<SVGBackend<'_>, Shift>,
    ) -> std::result::Result<(), String> {
        root.fill(&WHITE).map_err(|e| e.to_string())?;
        let (mut xr, mut yr) = (self.range(true), self.range(false));
        if self.equal_aspect && !self.x.log && !self.y.log {
            let pw = f64::from(self.width.saturating_sub(Y_LABEL_AREA_PX + 20).max(1));
            let ph = f64::from(
                self.height
                    .saturating_sub(X_LABEL_AREA_PX + TITLE_FONT_PX + 30)
                    .max(1),
            );
            let per_px = ((xr.1 - xr.0) / pw).max((yr.1 - yr.0) / ph);
            let widen = |r: (f64, f64), px: f64| {
                let c = 0.5 * (r.0 + r.1);
                (c - 0.5 * per_px * px, c + 0.5 * per_px * px)
            };
            xr = widen(xr, pw);
            yr = widen(yr, ph);
        }
        match (self.x.log, self.y.log) {
            (false, false) => self.draw_in(root, xr.0..xr.1, yr.0..yr.1),
            (true, false) => self.draw_in(root, (xr.0..xr.1).log_scale(), yr.0..yr.1),
            (false, true) => self.draw_in(root, xr.0..xr.1, (yr.0..yr.1).log_scale()),
            (true, true) => self.draw_in(root, (xr.0..xr.1).log_scale(), (yr.0..yr.1).log_scale()),
        }
    }

    /// Whether a point can be drawn on this chart's axes.
    fn drawable(&self, x: f64, y: f64) -> bool {
        x.is_finite() && y.is_finite() && (!self.x.log || x > 0.0) && (!self.y.log || y > 0.0)
    }

    /// The range of one axis: fixed, or from every layer's data (padded on linear axes).
    fn range(&self, horizontal: bool) -> (f64, f64) {
        let axis = if horizontal { &self.x } else { &self.y };
        if let Some((lo, hi)) = axis.range.filter(|(lo, hi)| lo < hi) {
            return (lo, hi);
        }
        let mut lo = f64::INFINITY;
        let mut hi = f64::NEG_INFINITY;
        let mut add = |x: f64, y: f64| {
            if self.drawable(x, y) {
                let v = if horizontal { x } else { y };
                lo = lo.min(v);
                hi = hi.max(v);
            }
        };
        for s in &self.series {
            s.points.iter().for_each(|&(x, y)| add(x, y));
        }
        for b in &self.bands {
            for &(x, l, u) in &b.points {
                add(x, l);
                add(x, u);
            }
        }
        for g in &self.rects {
            for r in &g.rects {
                add(r.x0, r.y0);
                add(r.x1, r.y1);
            }
        }
        for a in &self.arrows {
            add(a.from.0, a.from.1);
            add(a.to.0, a.to.1);
        }
        if lo > hi {
            return if axis.log { (0.1, 10.0) } else { (0.0, 1.0) };
        }
        if axis.log {
            if hi <= lo * 1.0001 {
                return (lo / 2.0, hi * 2.0);
            }
            return (lo / 1.2, hi * 1.2);
        }
        let span = hi - lo;
        if span <= f64::EPSILON * lo.abs().max(1.0) {
            let d = lo.abs().max(1.0) * 0.5;
            return (lo - d, hi + d);
        }
        (lo - AUTO_RANGE_PAD * span, hi + AUTO_RANGE_PAD * span)
    }

    fn draw_in<X, Y>(
        &self,
        root: &DrawingArea<SVGBackend<'_>, Shift>,
        x: X,
        y: Y,
    ) -> std::result::Result<(), String>
    where
        X: AsRangedCoord<Value = f64>,
        Y: AsRangedCoord<Value = f64>,
        X::CoordDescType: ValueFormatter<f64>,
        Y::CoordDescType: ValueFormatter<f64>,
    {
        let err = |e: DrawingAreaErrorKind<_>| e.to_string();
        let longest = self
            .y_categories
            .iter()
            .map(|c| c.chars().count() as u32)
            .max()
            .unwrap_or(0);
        let y_area = Y_LABEL_AREA_PX.max(CHAR_WIDTH_PX * longest + 30);
        let mut chart = ChartBuilder::on(root)
            .caption(&self.title, ("sans-serif", TITLE_FONT_PX))
            .margin(10)
            .x_label_area_size(X_LABEL_AREA_PX)
            .y_label_area_size(y_area)
            .build_cartesian_2d(x, y)
            .map_err(err)?;
        let category = |v: &f64| -> String {
            let k = v.round();
            if (v - k).abs() > CATEGORY_TICK_TOLERANCE || k < 0.0 {
                return String::new();
            }
            self.y_categories
                .get(k as usize)
                .cloned()
                .unwrap_or_default()
        };
        let mut mesh = chart.configure_mesh();
        mesh.x_desc(self.x.label.as_str())
            .y_desc(self.y.label.as_str())
            .label_style(("sans-serif", LABEL_FONT_PX))
            .axis_desc_style(("sans-serif", LABEL_FONT_PX))
            .light_line_style(RGBColor(235, 235, 235));
        if !self.y_categories.is_empty() {
            // One tick per row: the rows sit at whole numbers.
            mesh.y_labels(self.y_categories.len() + 1)
                .y_label_formatter(&category)
                .disable_y_mesh();
        }
        mesh.draw().map_err(err)?;

        let color = |c: Rgb| RGBColor(c[0], c[1], c[2]);
        let mut legend_any = false;
        for g in &self.rects {
            let c = color(g.color);
            let ann = chart
                .draw_series(
                    g.rects
                        .iter()
                        .filter(|r| self.drawable(r.x0, r.y0) && self.drawable(r.x1, r.y1))
                        .map(|r| Rectangle::new([(r.x0, r.y0), (r.x1, r.y1)], c.filled())),
                )
                .map_err(err)?;
            if !g.name.is_empty() {
                legend_any = true;
                ann.label(g.name.as_str()).legend(move |(x, y)| {
                    Rectangle::new([(x, y - 5), (x + 14, y + 5)], c.filled())
                });
            }
        }
        for b in &self.bands {
            let c = color(b.color);
            let pts: Vec<(f64, f64, f64)> = b
                .points
                .iter()
                .copied()
                .filter(|&(x, l, u)| self.drawable(x, l) && self.drawable(x, u))
                .collect();
            let poly: Vec<(f64, f64)> = pts
                .iter()
                .map(|&(x, _, u)| (x, u))
                .chain(pts.iter().rev().map(|&(x, l, _)| (x, l)))
                .collect();
            let ann = chart
                .draw_series(std::iter::once(Polygon::new(
                    poly,
                    c.mix(BAND_OPACITY).filled(),
                )))
                .map_err(err)?;
            if !b.name.is_empty() {
                legend_any = true;
                ann.label(b.name.as_str()).legend(move |(x, y)| {
                    Rectangle::new([(x, y - 5), (x + 14, y + 5)], c.mix(BAND_OPACITY).filled())
                });
            }
        }
        for s in &self.series {
            let c = color(s.color);
            let ann = match s.mark {
                Mark::Points(r) => chart
                    .draw_series(
                        s.points
                            .iter()
                            .filter(|&&(x, y)| self.drawable(x, y))
                            .map(|&p| Circle::new(p, r, c.filled())),
                    )
                    .map_err(err)?,
                Mark::Line(w) | Mark::Dashed(w) => {
                    let style = c.stroke_width(w);
                    let mut last = None;
                    for run in s.points.split(|&(x, y)| !self.drawable(x, y)) {
                        if run.is_empty() {
                            continue;
                        }
                        last = Some(if matches!(s.mark, Mark::Dashed(_)) {
                            chart
                                .draw_series(DashedLineSeries::new(
                                    run.iter().copied(),
                                    6 * w.max(1),
                                    4 * w.max(1),
                                    style,
                                ))
                                .map_err(err)?
                        } else {
                            chart
                                .draw_series(LineSeries::new(run.iter().copied(), style))
                                .map_err(err)?
                        });
                    }
                    match last {
                        Some(a) => a,
                        None => chart
                            .draw_series(std::iter::empty::<Circle<(f64, f64), u32>>())
                            .map_err(err)?,
                    }
                }
            };
            if !s.name.is_empty() {
                legend_any = true;
                match s.mark {
                    Mark::Points(_) => {
                        ann.label(s.name.as_str())
                            .legend(move |(x, y)| Circle::new((x + 7, y), 4, c.filled()));
                    }
                    Mark::Line(w) | Mark::Dashed(w) => {
                        ann.label(s.name.as_str()).legend(move |(x, y)| {
                            PathElement::new(vec![(x, y), (x + 16, y)], c.stroke_width(w.max(2)))
                        });
                    }
                }
            }
        }
        if !self.arrows.is_empty() {
            let c = color(ARROW_COLOR);
            let arrows: Vec<&Arrow> = self
                .arrows
                .iter()
                .filter(|a| self.drawable(a.from.0, a.from.1) && self.drawable(a.to.0, a.to.1))
                .collect();
            chart
                .draw_series(
                    arrows
                        .iter()
                        .map(|a| PathElement::new(vec![a.from, a.to], c)),
                )
                .map_err(err)?;
            chart
                .draw_series(arrows.iter().map(|a| Circle::new(a.to, 1, c.filled())))
                .map_err(err)?;
        }
        if legend_any {
            let pos = match self.legend {
                Corner::TopRight => SeriesLabelPosition::UpperRight,
                Corner::TopLeft => SeriesLabelPosition::UpperLeft,
                Corner::BottomLeft => SeriesLabelPosition::LowerLeft,
                Corner::BottomRight => SeriesLabelPosition::LowerRight,
            };
            chart
                .configure_series_labels()
                .position(pos)
                .label_font(("sans-serif", LABEL_FONT_PX))
                .background_style(WHITE.mix(0.85))
                .border_style(RGBColor(160, 160, 160))
                .draw()
                .map_err(err)?;
        }
        Ok(())
    }
}

/// Share of a category slot a bar fills (the rest is the gap between bars).
const BAR_FILL: f64 = 0.7;

/// One bar per value at x = 0, 1, 2, … (a bar chart; name the categories in the axis
/// label). Non-finite values leave their slot empty.
pub fn bars(name: &str, color: Rgb, values: &[f64]) -> Rects {
    Rects {
        name: name.to_owned(),
        color,
        rects: values
            .iter()
            .enumerate()
            .filter(|(_, v)| v.is_finite())
            .map(|(i, &v)| Rect {
                x0: i as f64 - 0.5 * BAR_FILL,
                x1: i as f64 + 0.5 * BAR_FILL,
                y0: v.min(0.0),
                y1: v.max(0.0),
            })
            .collect(),
    }
}

/// Keep at most `max_points` of a polyline, evenly spaced by index (always the first and last),
/// for display: the shape of a path survives while a page stays small.
pub fn decimate<T: Copy>(points: &[T], max_points: usize) -> Vec<T> {
    if points.len() <= max_points.max(2) {
        return points.to_vec();
    }
    let n = max_points.max(2);
    let last = points.len() - 1;
    (0..n).map(|i| points[i * last / (n - 1)]).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn svg_of(c: &Chart) -> String {
        c.to_svg().unwrap_or_else(|e| format!("ERROR {e}"))
    }

    #[test]
    fn line_chart_has_axes_title_and_legend() {
        let mut c = Chart::new(
            600,
            400,
            "Rates",
            Axis::new("time (s)"),
            Axis::new("rate (Hz)"),
        );
        c.series.push(Series::new(
            "gyro",
            PALETTE[0],
            Mark::Line(2),
            (0..50)
                .map(|i| (f64::from(i) * 0.1, (f64::from(i) * 0.2).sin()))
                .collect(),
        ));
        c.series.push(Series::new(
            "drop",
            PALETTE[1],
            Mark::Points(3),
            vec![(1.0, 0.5), (f64::NAN, 1.0)],
        ));
        let s = svg_of(&c);
        assert!(s.starts_with("<svg"), "{}", &s[..s.len().min(200)]);
        for t in [
            "Rates",
            "time (s)",
            "rate (Hz)",
            "gyro",
            "drop",
            "<polyline",
            "<circle",
        ] {
            assert!(s.contains(t), "{t} missing");
        }
    }

    #[test]
    fn log_axes_bands_and_dashes_render() {
        let mut c = Chart::new(600, 400, "Allan", Axis::log("tau (s)"), Axis::log("adev"));
        c.bands.push(Band {
            name: "band".into(),
            color: PALETTE[2],
            points: (1..20)
                .map(|i| (f64::from(i), 0.8 / f64::from(i), 1.2 / f64::from(i)))
                .collect(),
        });
        c.series.push(Series::new(
            "fit",
            PALETTE[3],
            Mark::Dashed(1),
            vec![(1.0, 1.0), (0.0, 1.0), (10.0, 0.1)],
        ));
        let s = svg_of(&c);
        assert!(
            s.contains("<polygon") && s.contains("fit") && s.contains("band"),
            "{s}"
        );
    }

    #[test]
    fn bars_and_arrows_render() {
        let b = bars("", PALETTE[1], &[1.0, -2.0, f64::INFINITY]);
        assert_eq!(b.rects.len(), 2);
        assert!(b.rects[1].y0 == -2.0 && b.rects[1].y1 == 0.0);

        let mut c = Chart::new(400, 400, "res", Axis::new("x (px)"), Axis::new("y (px)"));
        c.equal_aspect = true;
        c.arrows.push(Arrow {
            from: (0.0, 0.0),
            to: (1.0, 2.0),
        });
        assert!(svg_of(&c).contains("<circle"));
    }

    #[test]
    fn empty_chart_renders_and_bad_size_is_refused() {
        let c = Chart::new(300, 200, "nothing", Axis::new("x (m)"), Axis::log("y (m)"));
        assert!(svg_of(&c).contains("nothing"));
        let e = Chart::new(10, 200, "tiny", Axis::new("x"), Axis::new("y")).to_svg();
        assert!(matches!(e, Err(PlotError::Invalid { .. })));
    }

    #[test]
    fn stacked_charts_share_one_document() {
        let a = Chart::new(500, 300, "upper", Axis::new("x"), Axis::new("y"));
        let b = Chart::new(400, 200, "lower", Axis::new("x"), Axis::new("y"));
        let s = Chart::stack_to_svg(&[a, b]).unwrap_or_default();
        assert!(
            s.contains("upper") && s.contains("lower") && s.contains("height=\"500\""),
            "{s}"
        );
        assert!(Chart::stack_to_svg(&[]).is_err());
    }

    #[test]
    fn decimate_keeps_ends_and_bounds_count() {
        let p: Vec<usize> = (0..1001).collect();
        let d = decimate(&p, 100);
        assert_eq!(d.len(), 100);
        assert_eq!((d[0], d[99]), (0, 1000));
        assert_eq!(decimate(&p[..5], 100).len(), 5);
    }
}
