//! A timeline: one row per stream, time on x, a coloured span for each interval a stream spent
//! in a state (tracking support, a lens localized or lost). The rows are named on the y axis;
//! the meaning of each colour is the caller's legend.

use crate::{Axis, Chart, Rect, Rects, Rgb};

/// Height of a span inside its row (the rest separates the rows).
const SPAN_HEIGHT: f64 = 0.7;
/// Height of the drawing above and below the rows (pixels): title, time axis, margins.
const FRAME_PX: u32 = 110;
/// Height of one row (pixels).
const ROW_PX: u32 = 30;

/// One interval of a row in one state.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Span {
    /// Row index (0 is the top row).
    pub row: usize,
    /// Start (x units).
    pub start: f64,
    /// End (x units).
    pub end: f64,
    /// Colour of the state.
    pub color: Rgb,
}

/// Rows of coloured spans over time.
#[derive(Debug, Clone, Default)]
pub struct Timeline {
    /// Row names, top to bottom.
    pub rows: Vec<String>,
    /// The spans; spans of rows that do not exist are ignored.
    pub spans: Vec<Span>,
}

impl Timeline {
    /// Add a row; returns its index.
    pub fn row(&mut self, name: &str) -> usize {
        self.rows.push(name.to_owned());
        self.rows.len() - 1
    }

    /// Mark `row` as in the state drawn in `color` from `start` to `end`.
    pub fn span(&mut self, row: usize, start: f64, end: f64, color: Rgb) {
        self.spans.push(Span {
            row,
            start,
            end,
            color,
        });
    }

    /// The chart: `width` pixels wide, as tall as its rows need, the first row on top.
    pub fn chart(&self, width: u32, title: &str, time_label: &str) -> Chart {
        let n = self.rows.len();
        let height = FRAME_PX + ROW_PX * n.max(1) as u32;
        let mut chart = Chart::new(
            width,
            height,
            title,
            Axis::new(time_label),
            Axis::new("").with_range(-0.5, n.max(1) as f64 - 0.5),
        );
        // Row k (from the top) sits at y = n − 1 − k, so the category names run bottom-up.
        chart.y_categories = self.rows.iter().rev().cloned().collect();
        let mut layers: Vec<Rects> = Vec::new();
        for s in self.spans.iter().filter(|s| s.row < n) {
            let y = (n - 1 - s.row) as f64;
            let rect = Rect {
                x0: s.start,
                x1: s.end,
                y0: y - 0.5 * SPAN_HEIGHT,
                y1: y + 0.5 * SPAN_HEIGHT,
            };
            match layers.iter_mut().find(|l| l.color == s.color) {
                Some(layer) => layer.rects.push(rect),
                None => layers.push(Rects {
                    name: String::new(),
                    color: s.color,
                    rects: vec![rect],
                }),
            }
        }
        chart.rects = layers;
        chart
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::PALETTE;

    #[test]
    fn rows_are_named_top_down_and_spans_drawn_per_colour() {
        let mut t = Timeline::default();
        let a = t.row("left support");
        let b = t.row("right rear lens");
        t.span(a, 0.0, 1.0, PALETTE[2]);
        t.span(a, 1.0, 1.5, PALETTE[1]);
        t.span(b, 0.0, 2.0, PALETTE[2]);
        t.span(7, 0.0, 2.0, PALETTE[3]);
        let chart = t.chart(600, "support", "session time (s)");
        assert_eq!(
            chart.rects.len(),
            2,
            "one layer per colour, the bad row dropped"
        );
        assert_eq!(chart.rects[0].rects.len(), 2);
        // The first row is drawn on top.
        assert!(chart.rects[0].rects[0].y0 > chart.rects[0].rects[1].y1);
        let svg = chart.to_svg().unwrap_or_default();
        for text in [
            "left support",
            "right rear lens",
            "session time (s)",
            "<rect",
        ] {
            assert!(svg.contains(text), "{text} missing");
        }
    }

    #[test]
    fn an_empty_timeline_still_draws() {
        let chart = Timeline::default().chart(400, "nothing", "t (s)");
        assert!(chart.to_svg().is_ok_and(|s| s.contains("nothing")));
    }
}
