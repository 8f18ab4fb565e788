//! A node graph: named nodes on a circle joined by labelled edges, with note lines below (the
//! session report's sync graph: cameras, the audio pairs between them, triangle closures).

use plotters::element::DashedPathElement;
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};

use crate::{LABEL_FONT_PX, PlotError, Result, Rgb, SIDE_RANGE_PX, TITLE_FONT_PX};

/// Radius of a node's disc (pixels).
const NODE_RADIUS_PX: i32 = 24;
/// Distance of the outermost nodes' centres from the drawing's left and right edges (pixels):
/// room for the note under a node (about 25 characters).
const NODE_MARGIN_PX: f64 = 100.0;
/// Height of one note line below the graph (pixels).
const NOTE_LINE_PX: u32 = 18;
/// Room for the title above the graph (pixels).
const TITLE_AREA_PX: i32 = 34;
/// Distance of an edge's label from the edge's midpoint, across it (pixels).
const EDGE_LABEL_OFFSET_PX: f64 = 12.0;
/// Fill of a node's disc: a light grey the black name reads on.
const NODE_FILL: Rgb = [225, 230, 240];
/// Dash and gap lengths of an edge that was not accepted (pixels).
const DASH_PX: (u32, u32) = (6, 5);

/// An edge between two nodes.
#[derive(Debug, Clone, PartialEq)]
pub struct Edge {
    /// Index of one node.
    pub a: usize,
    /// Index of the other node.
    pub b: usize,
    /// Text beside the edge's middle.
    pub label: String,
    /// Line colour.
    pub color: Rgb,
    /// Drawn dashed (e.g. evidence that was not accepted).
    pub dashed: bool,
}

/// Nodes on a circle, labelled edges between them, and note lines under the drawing.
#[derive(Debug, Clone, Default)]
pub struct NodeGraph {
    /// Image width (pixels).
    pub width: u32,
    /// Height of the graph part (pixels); the notes add their lines below.
    pub height: u32,
    /// Title.
    pub title: String,
    /// Node names, with a second line under each node (may be empty).
    pub nodes: Vec<(String, String)>,
    /// Edges; edges naming nodes that do not exist are ignored.
    pub edges: Vec<Edge>,
    /// Lines of text under the graph.
    pub notes: Vec<String>,
}

impl NodeGraph {
    /// The graph as an SVG document (also fit to be inlined in HTML).
    pub fn to_svg(&self) -> Result<String> {
        let (lo, hi) = SIDE_RANGE_PX;
        let total_height = self.height + NOTE_LINE_PX * self.notes.len() as u32;
        if !(lo..=hi).contains(&self.width) || !(lo..=hi).contains(&total_height) {
            return Err(PlotError::Invalid {
                title: self.title.clone(),
                message: format!(
                    "size {}×{total_height} px is outside {lo}..={hi} px per side; choose a \
                     size in range",
                    self.width
                ),
            });
        }
        let mut buf = String::new();
        {
            let root =
                SVGBackend::with_string(&mut buf, (self.width, total_height)).into_drawing_area();
            self.draw(&root).map_err(|message| PlotError::Draw {
                title: self.title.clone(),
                message,
            })?;
            root.present().map_err(|e| PlotError::Draw {
                title: self.title.clone(),
                message: e.to_string(),
            })?;
        }
        Ok(buf)
    }

    /// Where node `k` sits: on a circle, the first on the left, going clockwise.
    fn node_position(&self, k: usize) -> (i32, i32) {
        let n = self.nodes.len().max(1) as f64;
        let cx = f64::from(self.width) / 2.0;
        let cy =
            f64::from(TITLE_AREA_PX) + (f64::from(self.height) - f64::from(TITLE_AREA_PX)) / 2.0;
        let margin = NODE_MARGIN_PX;
        let rx = (cx - margin).max(0.0);
        // Vertically, room for the disc and its note below it.
        let ry = ((f64::from(self.height) - f64::from(TITLE_AREA_PX)) / 2.0
            - 2.5 * f64::from(NODE_RADIUS_PX))
        .max(0.0);
        let angle = std::f64::consts::PI + 2.0 * std::f64::consts::PI * k as f64 / n;
        let ry = if self.nodes.len() == 2 { 0.0 } else { ry };
        (
            (cx + rx * angle.cos()).round() as i32,
            (cy - ry * angle.sin()).round() as i32,
        )
    }

    fn draw(
        &self,
        root: &DrawingArea<SVGBackend<'_>, plotters::coord::Shift>,
    ) -> std::result::Result<(), String> {
        let err = |e: DrawingAreaErrorKind<_>| e.to_string();
        root.fill(&WHITE).map_err(err)?;
        let color = |c: Rgb| RGBColor(c[0], c[1], c[2]);
        let centred = |px: u32| {
            TextStyle::from(("sans-serif", px).into_font())
                .pos(Pos::new(HPos::Center, VPos::Center))
        };
        root.draw(&Text::new(
            self.title.clone(),
            (self.width as i32 / 2, TITLE_AREA_PX / 2),
            centred(TITLE_FONT_PX),
        ))
        .map_err(err)?;
        let n = self.nodes.len();
        for e in self
            .edges
            .iter()
            .filter(|e| e.a < n && e.b < n && e.a != e.b)
        {
            let (p, q) = (self.node_position(e.a), self.node_position(e.b));
            let style = color(e.color).stroke_width(2);
            if e.dashed {
                root.draw(&DashedPathElement::new(
                    vec![p, q],
                    DASH_PX.0,
                    DASH_PX.1,
                    style,
                ))
                .map_err(err)?;
            } else {
                root.draw(&PathElement::new(vec![p, q], style))
                    .map_err(err)?;
            }
            // The label sits beside the middle, on the side away from the drawing's centre.
            let (dx, dy) = (f64::from(q.0 - p.0), f64::from(q.1 - p.1));
            let len = dx.hypot(dy).max(1.0);
            let (mut nx, mut ny) = (-dy / len, dx / len);
            let mid = (f64::from(p.0 + q.0) / 2.0, f64::from(p.1 + q.1) / 2.0);
            let centre = (f64::from(self.width) / 2.0, f64::from(self.height) / 2.0);
            if nx * (mid.0 - centre.0) + ny * (mid.1 - centre.1) < 0.0 {
                (nx, ny) = (-nx, -ny);
            }
            if n == 2 {
                (nx, ny) = (0.0, -1.0);
            }
            let at = (
                (mid.0 + nx * EDGE_LABEL_OFFSET_PX).round() as i32,
                (mid.1 + ny * EDGE_LABEL_OFFSET_PX).round() as i32,
            );
            root.draw(&Text::new(e.label.clone(), at, centred(LABEL_FONT_PX)))
                .map_err(err)?;
        }
        for (k, (name, note)) in self.nodes.iter().enumerate() {
            let (x, y) = self.node_position(k);
            root.draw(&Circle::new(
                (x, y),
                NODE_RADIUS_PX,
                color(NODE_FILL).filled(),
            ))
            .map_err(err)?;
            root.draw(&Circle::new((x, y), NODE_RADIUS_PX, BLACK.stroke_width(1)))
                .map_err(err)?;
            root.draw(&Text::new(name.clone(), (x, y), centred(LABEL_FONT_PX)))
                .map_err(err)?;
            if !note.is_empty() {
                root.draw(&Text::new(
                    note.clone(),
                    (x, y + NODE_RADIUS_PX + LABEL_FONT_PX as i32),
                    centred(LABEL_FONT_PX),
                ))
                .map_err(err)?;
            }
        }
        let left = TextStyle::from(("sans-serif", LABEL_FONT_PX).into_font())
            .pos(Pos::new(HPos::Left, VPos::Center));
        for (k, line) in self.notes.iter().enumerate() {
            let y = self.height as i32 + (NOTE_LINE_PX as i32) * k as i32 + NOTE_LINE_PX as i32 / 2;
            root.draw(&Text::new(line.clone(), (10, y), left.clone()))
                .map_err(err)?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::PALETTE;

    fn graph(nodes: usize) -> NodeGraph {
        NodeGraph {
            width: 500,
            height: 260,
            title: "sync".into(),
            nodes: (0..nodes)
                .map(|k| (format!("cam{k}"), format!("+{k}.0 ms")))
                .collect(),
            edges: vec![
                Edge {
                    a: 0,
                    b: 1,
                    label: "lag 37.1 ms".into(),
                    color: PALETTE[2],
                    dashed: false,
                },
                Edge {
                    a: 1,
                    b: 2,
                    label: "unmatched".into(),
                    color: PALETTE[3],
                    dashed: true,
                },
                Edge {
                    a: 0,
                    b: 9,
                    label: "ghost".into(),
                    color: PALETTE[3],
                    dashed: false,
                },
            ],
            notes: vec!["closure cam0-cam1-cam2: 0.02 ms".into()],
        }
    }

    #[test]
    fn nodes_edges_labels_and_notes_render() {
        let svg = graph(3).to_svg().unwrap_or_default();
        for text in [
            "cam0",
            "cam2",
            "+2.0 ms",
            "lag 37.1 ms",
            "unmatched",
            "closure",
        ] {
            assert!(svg.contains(text), "{text} missing");
        }
        assert!(
            !svg.contains("ghost"),
            "an edge to a missing node is not drawn"
        );
        assert_eq!(svg.matches("<circle").count(), 6);
    }

    #[test]
    fn two_nodes_sit_side_by_side_and_bad_sizes_are_refused() {
        let g = graph(2);
        let (a, b) = (g.node_position(0), g.node_position(1));
        assert_eq!(a.1, b.1);
        assert!(a.0 < b.0);
        assert!(g.to_svg().is_ok_and(|s| s.contains("lag 37.1 ms")));
        let tiny = NodeGraph {
            width: 50,
            ..graph(2)
        };
        assert!(matches!(tiny.to_svg(), Err(PlotError::Invalid { .. })));
    }
}
