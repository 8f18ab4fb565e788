//! The report page: HTML with inline SVG charts drawn by `kiwi-plot` and a small inline style
//! sheet; no script, no external resource, so it opens from disk anywhere.
//!
//! Every chart sits in a `<figure class="plot" data-plot="…">` (the browser test counts them).
//! Long series are thinned so the page stays small: paths and openings to
//! [`MAX_PATH_POINTS`] points, the landmarks to [`MAX_LANDMARKS`], a timeline row to
//! [`MAX_TIMELINE_SPANS`] spans.

use std::collections::BTreeMap;
use std::fmt::Write as _;

use kiwi_core::layout::ToolKind;
use kiwi_plot::{
    Axis, Chart, Corner, Edge, Mark, NodeGraph, PALETTE, Rgb, Series, Timeline, decimate,
};

use super::{EpisodeReport, SessionReport, StageTiming, WristTrack};
use crate::error::Result;
use crate::evaluate::markers::Phase;
use crate::outputs::SupportClass;
use crate::quality::{Verdict, reason_class};
use crate::sync::{CameraStatus, SyncResult};

/// Points of a path or an opening curve kept per wrist and episode: a path drawn 600 px wide
/// shows no more detail, and ten long episodes stay well under 5 MB.
pub const MAX_PATH_POINTS: usize = 1000;
/// Landmarks drawn per top view: enough to show the room's layout, each is an SVG element.
pub const MAX_LANDMARKS: usize = 600;
/// Spans per timeline row: more than the row's pixels would not show (a bin then shows the
/// weakest state inside it).
pub const MAX_TIMELINE_SPANS: usize = 400;
/// Lost-frame reasons with a colour of their own per episode (the rest share one).
const MAX_REASON_COLOURS: usize = 4;
/// Margin of a top view around the paths, as a share of their extent …
const TOP_VIEW_PAD: f64 = 0.25;
/// … and at least this much (m), so the landmarks around a small tabletop path show.
const TOP_VIEW_MIN_PAD_M: f64 = 0.3;
/// Chart widths (pixels): top views and timelines are the main charts, the others half-width.
const WIDE_PX: u32 = 900;
/// Width of the top view, sync graph and gripper charts (pixels).
const HALF_PX: u32 = 600;
/// Radius of a path's start marker (pixels).
const START_MARKER_PX: u32 = 5;

/// Colours of the support classes (green front, blue rear, cyan interpolated rear, orange IMU).
const SUPPORT_COLORS: [(SupportClass, Rgb); 4] = [
    (SupportClass::Front, PALETTE[2]),
    (SupportClass::Rear, PALETTE[0]),
    (SupportClass::RearInterpolated, PALETTE[9]),
    (SupportClass::ImuOnly, PALETTE[1]),
];
/// A localized lens frame: a light green, quieter than the support classes.
const LOCALIZED_COLOR: Rgb = [152, 223, 138];
/// Lost-frame reasons, most frequent first: red, purple, brown, pink.
const LOST_COLORS: [Rgb; MAX_REASON_COLOURS] = [PALETTE[3], PALETTE[4], PALETTE[5], PALETTE[6]];
/// Every other lost reason: grey.
const OTHER_LOST_COLOR: Rgb = PALETTE[7];
/// Landmarks: light grey, behind the paths.
const LANDMARK_COLOR: Rgb = [190, 190, 190];
/// The head's path.
const HEAD_COLOR: Rgb = PALETTE[8];
/// Start markers of the paths.
const START_COLOR: Rgb = [40, 40, 40];
/// Accepted sync pairs …
const ACCEPTED_COLOR: Rgb = PALETTE[2];
/// … and the others.
const REJECTED_COLOR: Rgb = PALETTE[3];

/// The rendered page.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Page {
    /// The HTML document.
    pub html: String,
    /// Charts on it.
    pub plots: usize,
}

const STYLE: &str = "body{font-family:sans-serif;margin:1.5em;max-width:1200px;color:#222}\
h1{margin-bottom:0}h2{border-top:2px solid #ccc;padding-top:.6em;margin-top:2em}\
table{border-collapse:collapse;margin:.5em 0}td,th{border:1px solid #ccc;padding:2px 8px;\
text-align:left;font-size:13px;vertical-align:top}th{background:#f2f2f2}\
.usable{background:#d4edda}.suspect{background:#fff3cd}.unusable{background:#f8d7da}\
.notrun{background:#e2e3e5}.verdict{padding:2px 8px;border-radius:4px;font-weight:bold}\
figure.plot{margin:.5em 0;display:inline-block;vertical-align:top}\
figure.plot svg{max-width:100%;height:auto}figcaption{font-size:13px;color:#555;max-width:600px}\
.legend span.sw{display:inline-block;width:14px;height:10px;margin:0 4px 0 12px}\
.legend{font-size:13px}.note{color:#8a5a00}";

/// Escape text for HTML.
fn esc(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    for c in s.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&#39;"),
            c => out.push(c),
        }
    }
    out
}

fn hex(c: Rgb) -> String {
    format!("#{:02x}{:02x}{:02x}", c[0], c[1], c[2])
}

fn support_color(s: SupportClass) -> Rgb {
    SUPPORT_COLORS[support_rank(s)].1
}

/// A support class's row in [`SUPPORT_COLORS`]: its rank, weakest last.
fn support_rank(s: SupportClass) -> usize {
    crate::export::support_code(s) as usize
}

fn verdict_badge(v: Option<Verdict>) -> String {
    match v {
        Some(v) => format!("<span class=\"verdict {0}\">{0}</span>", v.as_str()),
        None => "<span class=\"verdict notrun\">not processed</span>".into(),
    }
}

/// Collects the page and counts its charts.
struct Writer {
    html: String,
    plots: usize,
}

impl Writer {
    fn figure(&mut self, kind: &str, svg: &str, caption: &str) {
        self.plots += 1;
        let _ = write!(
            self.html,
            "<figure class=\"plot\" data-plot=\"{}\">{svg}",
            esc(kind)
        );
        if !caption.is_empty() {
            let _ = write!(self.html, "<figcaption>{caption}</figcaption>");
        }
        self.html.push_str("</figure>\n");
    }
}

/// Render the report page.
pub fn render(report: &SessionReport) -> Result<Page> {
    let mut w = Writer {
        html: String::with_capacity(1 << 20),
        plots: 0,
    };
    let title = format!("KIWI session report: {}", report.name);
    let _ = write!(
        w.html,
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">\
         <title>{}</title><style>{STYLE}</style></head><body>\n<h1>{}</h1>\n",
        esc(&title),
        esc(&title)
    );
    let wrists: Vec<String> = report
        .wrists
        .iter()
        .map(|x| format!("{} wrist: unit {}, {}", x.camera, x.unit, tool_name(x.tool)))
        .collect();
    let _ = writeln!(
        w.html,
        "<p>Maps built from episode <b>{}</b>. {}.</p>",
        esc(&report.map_episode),
        esc(&wrists.join("; "))
    );
    summary_table(&mut w.html, report);
    for ep in &report.episodes {
        episode_section(&mut w, report, ep)?;
    }
    ablation_section(&mut w.html, report);
    markers_section(&mut w, report)?;
    w.html
        .push_str("<h2 id=\"session-stages\">Session stages</h2>\n");
    if let Some(note) = &report.landmarks_note {
        let _ = writeln!(w.html, "<p class=\"note\">{}</p>", esc(note));
    }
    stage_table(&mut w.html, &report.session_stages);
    w.html.push_str("</body></html>\n");
    Ok(Page {
        html: w.html,
        plots: w.plots,
    })
}

/// The map-sharing ablation's table (paper `tab:eval-map-sharing`), or how to make it.
fn ablation_section(html: &mut String, report: &SessionReport) {
    html.push_str("<h2 id=\"ablation\">Front-only ablation</h2>\n");
    let Some(a) = &report.ablation else {
        html.push_str(
            "<p class=\"note\">Not evaluated: `kiwi evaluate ablation --session …` localizes the \
             right front lens in the left front map (front-only, cross-hand) and compares its \
             support with KIWI's on the same frames.</p>\n",
        );
        return;
    };
    let pct = |n: usize, d: usize| 100.0 * n as f64 / d.max(1) as f64;
    let _ = writeln!(
        html,
        "<p>Right front frames supported by front-only cross-hand localization (right front in \
         {}) and by KIWI.</p>\n<table><tr><th>episode</th><th>frames</th><th>front-only</th>\
         <th>KIWI</th></tr>",
        esc(&a.map)
    );
    let rows = a
        .episodes
        .iter()
        .map(|e| {
            (
                e.episode.as_str(),
                e.frames,
                e.cross_hand_supported,
                e.kiwi_supported,
            )
        })
        .chain(std::iter::once((
            "total",
            a.frames,
            a.cross_hand_supported,
            a.kiwi_supported,
        )));
    for (name, frames, cross, kiwi) in rows {
        let _ = writeln!(
            html,
            "<tr><td>{}</td><td>{frames}</td><td>{:.1} %</td><td>{:.1} %</td></tr>",
            esc(name),
            pct(cross, frames),
            pct(kiwi, frames)
        );
    }
    html.push_str("</table>\n");
}

/// The marker-referenced accuracy (paper §5) of each episode it was run on: a table per hand
/// and the scored frames' errors over time, or how to run it.
fn markers_section(w: &mut Writer, report: &SessionReport) -> Result<()> {
    w.html
        .push_str("<h2 id=\"markers\">Marker-referenced accuracy</h2>\n");
    if report.markers.is_empty() {
        w.html.push_str(
            "<p class=\"note\">Not evaluated: with two fixed ArUco markers in the workspace, \
             `kiwi evaluate markers --session … --episode …` scores each hand's camera \
             trajectory against eight-corner marker poses (median translation error over the \
             last half of the episode).</p>\n",
        );
        return Ok(());
    }
    w.html.push_str(
        "<p>Median translation error on the last 50 % of each episode, after a rigid alignment \
         fitted on the first 40 %: each hand with its own alignment, and with the left hand's \
         (which keeps the hands' relative placement).</p>\n<table><tr><th>episode</th>\
         <th>hand</th><th>references</th><th>scored</th><th>own (mm)</th><th>left-fitted (mm)\
         </th><th>p90 (mm)</th><th>rotation (deg)</th></tr>\n",
    );
    for m in &report.markers {
        let e = &m.evaluation;
        for h in &e.wrists {
            let _ = writeln!(
                w.html,
                "<tr><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{:.2}</td><td>{}</td>\
                 <td>{:.2}</td><td>{:.2}</td></tr>",
                esc(&e.episode),
                esc(&h.camera),
                h.references,
                h.independent.frames,
                h.independent.median_m * 1e3,
                h.shared
                    .map_or("-".to_string(), |a| format!("{:.2}", a.median_m * 1e3)),
                h.independent.p90_m * 1e3,
                h.independent.median_rotation_deg
            );
        }
        for (camera, why) in &e.skipped {
            let _ = writeln!(
                w.html,
                "<tr><td>{}</td><td>{}</td><td colspan=\"6\">left out: {}</td></tr>",
                esc(&e.episode),
                esc(camera),
                esc(why)
            );
        }
    }
    w.html.push_str("</table>\n");
    for m in &report.markers {
        if m.frames.is_empty() {
            continue;
        }
        let mut chart = Chart::new(
            HALF_PX,
            260,
            &format!(
                "{}: marker-referenced error (own alignment)",
                m.evaluation.episode
            ),
            Axis::new("camera time (s)"),
            Axis::new("translation error (mm)"),
        );
        for (k, h) in m.evaluation.wrists.iter().enumerate() {
            let points: Vec<(f64, f64)> = m
                .frames
                .iter()
                .filter(|f| f.camera == h.camera && f.phase == Phase::Score)
                .map(|f| (f.t_camera, f.error_m * 1e3))
                .collect();
            chart.series.push(Series::new(
                &h.camera,
                PALETTE[k % PALETTE.len()],
                Mark::Points(2),
                decimate(&points, MAX_PATH_POINTS),
            ));
        }
        let svg = chart.to_svg()?;
        w.figure("markers", &svg, "");
    }
    Ok(())
}

fn tool_name(t: ToolKind) -> &'static str {
    match t {
        ToolKind::Chopstick => "chopstick",
        ToolKind::ParallelJaw => "parallel jaw",
        ToolKind::BareHand => "bare hand",
    }
}

fn summary_table(html: &mut String, report: &SessionReport) {
    html.push_str(
        "<h2>Episodes</h2>\n<table><tr><th>episode</th><th>description</th><th>verdict</th>",
    );
    for x in &report.wrists {
        let _ = write!(html, "<th>{} supported</th>", esc(&x.camera));
    }
    html.push_str("<th>duration (s)</th><th>first reason</th></tr>\n");
    for ep in &report.episodes {
        let _ = write!(
            html,
            "<tr><td><a href=\"#ep-{0}\">{0}</a></td><td>{1}</td><td>{2}</td>",
            esc(&ep.name),
            esc(&ep.description),
            verdict_badge(ep.verdict)
        );
        for x in &report.wrists {
            let f = ep
                .quality
                .as_ref()
                .and_then(|q| q.wrists.get(&x.camera))
                .map_or_else(
                    || "—".into(),
                    |q| format!("{:.1} %", q.supported_fraction * 100.0),
                );
            let _ = write!(html, "<td>{f}</td>");
        }
        let duration = ep
            .wrists
            .iter()
            .filter_map(|t| Some(t.samples.last()?.t - t.samples.first()?.t))
            .fold(None, |a: Option<f64>, d| Some(a.map_or(d, |a| a.max(d))))
            .map_or_else(|| "—".into(), |d| format!("{d:.1}"));
        let _ = writeln!(
            html,
            "<td>{duration}</td><td>{}</td></tr>",
            esc(ep.reasons.first().map_or("", String::as_str))
        );
    }
    html.push_str("</table>\n");
}

fn episode_section(w: &mut Writer, report: &SessionReport, ep: &EpisodeReport) -> Result<()> {
    let _ = writeln!(
        w.html,
        "<h2 id=\"ep-{0}\">Episode {0} {1}</h2>\n<p>{2}</p>",
        esc(&ep.name),
        verdict_badge(ep.verdict),
        esc(&ep.description)
    );
    quality_section(&mut w.html, ep);
    for note in &ep.notes {
        let _ = writeln!(w.html, "<p class=\"note\">{}</p>", esc(note));
    }
    if let Some(chart) = top_view(report, ep) {
        let caption = "Top view of the scene (x, y; m): the tool tips' paths coloured by what \
                       supported each frame (left wrist solid, right dashed, ● the start), over \
                       the scene map's landmarks (grey).";
        w.figure("top-view", &chart.to_svg()?, caption);
    } else {
        w.html
            .push_str("<p class=\"note\">No trajectory to draw: the episode has no outputs.</p>\n");
    }
    if let Some((chart, legend)) = timeline(ep) {
        w.figure(
            "timeline",
            &chart.to_svg()?,
            "Support per stream over time: each wrist's support class, and each lens localized \
             or lost (coloured by the reason).",
        );
        w.html.push_str("<p class=\"legend\">");
        for (name, color) in legend {
            let _ = write!(
                w.html,
                "<span class=\"sw\" style=\"background:{}\"></span>{}",
                hex(color),
                esc(&name)
            );
        }
        w.html.push_str("</p>\n");
    }
    for chart in gripper_charts(ep) {
        w.figure("gripper", &chart.to_svg()?, "");
    }
    floor_section(w, ep);
    match &ep.sync {
        Some(sync) => {
            w.figure(
                "sync-graph",
                &sync_graph(sync).to_svg()?,
                "Cameras on the session timeline: each camera's offset and drift against the \
                 reference; each audio pair's lag and drift (solid accepted, dashed not).",
            );
            sync_tables(&mut w.html, sync);
        }
        None => w.html.push_str(
            "<p class=\"note\">No sync result: the sync stage did not run or failed.</p>\n",
        ),
    }
    let total: f64 = ep.stages.iter().filter_map(|s| s.seconds).sum();
    let _ = writeln!(
        w.html,
        "<h3>Stages of {} ({total:.1} s in all)</h3>",
        esc(&ep.name)
    );
    stage_table(&mut w.html, &ep.stages);
    Ok(())
}

/// The floor and the surfaces above it, with the floor stage's figure.
fn floor_section(w: &mut Writer, ep: &EpisodeReport) {
    let Some(f) = ep.quality.as_ref().and_then(|q| q.floor.as_ref()) else {
        return;
    };
    match &f.floor {
        crate::floor::Floor::Found {
            z_m,
            spread_m,
            windows,
        } => {
            let _ = write!(
                w.html,
                "<p>Floor at z = {z_m:.3} m in the scene frame (spread {:.1} mm over {windows}                  windows)",
                spread_m * 1e3
            );
            for s in &f.surfaces {
                if let Some(h) = s.above_floor_m {
                    let _ = write!(
                        w.html,
                        "; a horizontal surface {h:.3} m above it ({} windows)",
                        s.windows
                    );
                }
            }
            w.html.push_str(".</p>\n");
        }
        crate::floor::Floor::NoFloor { reason } => {
            let _ = writeln!(w.html, "<p class=\"note\">No floor: {}.</p>", esc(reason));
        }
    }
    if let Some(svg) = &ep.floor_figure {
        w.figure(
            "floor",
            svg,
            "Floor: the plane sweep's support per camera-to-plane distance in the most decisive \
             window (floor and other surfaces marked), and every window's floor height over time.",
        );
    }
}

fn quality_section(html: &mut String, ep: &EpisodeReport) {
    html.push_str("<h3>Verdict</h3>\n<ul>");
    if ep.reasons.is_empty() {
        html.push_str("<li>every check passed</li>");
    }
    for r in &ep.reasons {
        let _ = write!(html, "<li>{}</li>", esc(r));
    }
    html.push_str("</ul>\n");
    let Some(q) = &ep.quality else {
        return;
    };
    if q.wrists.is_empty() {
        return;
    }
    html.push_str("<table><tr><th>wrist</th><th>frames</th><th>supported</th>");
    for (c, _) in SUPPORT_COLORS {
        let _ = write!(html, "<th>{}</th>", c.as_str());
    }
    html.push_str(
        "<th>longest IMU-only (s)</th><th>tip σ max / median (mm)</th><th>front localized</th>\
         <th>rear localized</th><th>gripper measured</th><th>certified</th></tr>\n",
    );
    for (name, x) in &q.wrists {
        let _ = write!(
            html,
            "<tr><td>{}</td><td>{}</td><td>{:.1} %</td>",
            esc(name),
            x.frames,
            x.supported_fraction * 100.0
        );
        for (c, _) in SUPPORT_COLORS {
            let f = x.support_fractions.get(c.as_str()).copied().unwrap_or(0.0);
            let _ = write!(html, "<td>{:.1} %</td>", f * 100.0);
        }
        let loc = |l: &crate::outputs::LocalizationRecord| {
            let mut s = format!("{} / {}", l.localized, l.frames);
            if l.from_other_lens > 0 {
                let _ = write!(
                    s,
                    "<br>{} found around the other lens's pose",
                    l.from_other_lens
                );
            }
            for (reason, n) in &l.lost_reasons {
                let _ = write!(s, "<br>lost {n}: {}", esc(reason));
            }
            s
        };
        let _ = writeln!(
            html,
            "<td>{:.2}</td><td>{:.1} / {:.1}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td></tr>",
            x.longest_unsupported_s,
            x.max_tip_sigma_p_m * 1e3,
            x.median_tip_sigma_p_m * 1e3,
            loc(&x.front_localization),
            loc(&x.rear_localization),
            x.gripper_measured_fraction
                .map_or_else(|| "—".into(), |f| format!("{:.1} %", f * 100.0)),
            if x.calibration_certified { "yes" } else { "no" },
        );
    }
    html.push_str("</table>\n");
}

/// Consecutive frames in one state as `(start, end, state)` spans: a frame lasts until the
/// next one, the last one a median frame interval. With more runs than
/// [`MAX_TIMELINE_SPANS`], the time is cut into that many bins, each in the highest-ranked
/// (weakest) state of its frames.
fn state_spans(times: &[f64], states: &[usize]) -> Vec<(f64, f64, usize)> {
    let n = times.len().min(states.len());
    if n == 0 {
        return Vec::new();
    }
    let step = crate::export::median_period(&times[..n]).unwrap_or(0.0);
    let end_of = |k: usize| {
        if k + 1 < n {
            times[k + 1]
        } else {
            times[k] + step
        }
    };
    let runs = 1 + (1..n).filter(|&k| states[k] != states[k - 1]).count();
    let mut spans: Vec<(f64, f64, usize)> = Vec::new();
    if runs <= MAX_TIMELINE_SPANS {
        for k in 0..n {
            match spans.last_mut() {
                Some(last) if last.2 == states[k] => last.1 = end_of(k),
                _ => spans.push((times[k], end_of(k), states[k])),
            }
        }
        return spans;
    }
    let (t0, t1) = (times[0], end_of(n - 1));
    let width = (t1 - t0) / MAX_TIMELINE_SPANS as f64;
    let mut bins: Vec<Option<usize>> = vec![None; MAX_TIMELINE_SPANS];
    for k in 0..n {
        let b = (((times[k] - t0) / width) as usize).min(MAX_TIMELINE_SPANS - 1);
        bins[b] = Some(bins[b].map_or(states[k], |s| s.max(states[k])));
    }
    for (b, state) in bins.iter().enumerate() {
        let Some(state) = *state else { continue };
        let (a, z) = (t0 + b as f64 * width, t0 + (b + 1) as f64 * width);
        match spans.last_mut() {
            Some(last) if last.2 == state && (last.1 - a).abs() < 1e-9 * width.max(1.0) => {
                last.1 = z;
            }
            _ => spans.push((a, z, state)),
        }
    }
    spans
}

/// The episode's support timeline and its legend (names and colours).
fn timeline(ep: &EpisodeReport) -> Option<(Chart, Vec<(String, Rgb)>)> {
    if ep.wrists.is_empty() && ep.lenses.is_empty() {
        return None;
    }
    let mut t = Timeline::default();
    let mut legend: Vec<(String, Rgb)> = Vec::new();
    let mut session_clock = true;
    for track in &ep.wrists {
        session_clock &= track.session_clock;
        let row = t.row(&format!("{} support", track.camera));
        let times: Vec<f64> = track.samples.iter().map(|s| s.t).collect();
        let states: Vec<usize> = track
            .samples
            .iter()
            .map(|s| support_rank(s.support))
            .collect();
        for (a, z, s) in state_spans(&times, &states) {
            t.span(row, a, z, SUPPORT_COLORS[s].1);
        }
    }
    if !ep.wrists.is_empty() {
        legend.extend(
            SUPPORT_COLORS
                .iter()
                .map(|(c, rgb)| (format!("support {}", c.as_str()), *rgb)),
        );
    }
    // The most frequent lost reasons of the episode get their own colours.
    let mut counts: BTreeMap<String, usize> = BTreeMap::new();
    for l in &ep.lenses {
        for f in &l.frames {
            if let Some(why) = &f.lost {
                *counts.entry(reason_class(why)).or_insert(0) += 1;
            }
        }
    }
    let mut frequent: Vec<(String, usize)> = counts.into_iter().collect();
    frequent.sort_by(|a, b| b.1.cmp(&a.1).then_with(|| a.0.cmp(&b.0)));
    let named: Vec<String> = frequent
        .iter()
        .take(MAX_REASON_COLOURS)
        .map(|(r, _)| r.clone())
        .collect();
    let state_color = |s: usize| match s {
        0 => LOCALIZED_COLOR,
        s if s <= named.len() => LOST_COLORS[s - 1],
        _ => OTHER_LOST_COLOR,
    };
    for l in &ep.lenses {
        session_clock &= l.session_clock;
        let row = t.row(&format!("{} {} lens", l.camera, l.lens));
        let times: Vec<f64> = l.frames.iter().map(|f| f.t).collect();
        let states: Vec<usize> = l
            .frames
            .iter()
            .map(|f| match &f.lost {
                None => 0,
                Some(why) => {
                    let class = reason_class(why);
                    named
                        .iter()
                        .position(|r| *r == class)
                        .map_or(named.len() + 1, |k| k + 1)
                }
            })
            .collect();
        for (a, z, s) in state_spans(&times, &states) {
            t.span(row, a, z, state_color(s));
        }
    }
    if !ep.lenses.is_empty() {
        legend.push(("lens localized".into(), LOCALIZED_COLOR));
        for (k, (reason, n)) in frequent.iter().enumerate() {
            if k < named.len() {
                legend.push((format!("lost ({n} frames): {reason}"), LOST_COLORS[k]));
            }
        }
        let others: usize = frequent.iter().skip(named.len()).map(|(_, n)| n).sum();
        if others > 0 {
            legend.push((
                format!("lost ({others} frames): other reasons"),
                OTHER_LOST_COLOR,
            ));
        }
    }
    let axis = if session_clock {
        "session time (s)"
    } else {
        "time (s; a camera's own clock where it is not synchronized)"
    };
    Some((
        t.chart(WIDE_PX, &format!("{}: support per stream", ep.name), axis),
        legend,
    ))
}

/// The top view of the episode, when it has a path.
fn top_view(report: &SessionReport, ep: &EpisodeReport) -> Option<Chart> {
    let head: Vec<[f64; 3]> = ep.head.iter().flatten().map(|(_, p)| *p).collect();
    let all: Vec<[f64; 3]> = ep
        .wrists
        .iter()
        .flat_map(|w| w.samples.iter().map(|s| s.tip))
        .chain(head.iter().copied())
        .filter(|p| p.iter().all(|v| v.is_finite()))
        .collect();
    if all.is_empty() {
        return None;
    }
    let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
    for p in &all {
        for k in 0..2 {
            lo[k] = lo[k].min(p[k]);
            hi[k] = hi[k].max(p[k]);
        }
    }
    let extent = (hi[0] - lo[0]).max(hi[1] - lo[1]);
    let pad = (TOP_VIEW_PAD * extent).max(TOP_VIEW_MIN_PAD_M);
    let (x0, x1, y0, y1) = (lo[0] - pad, hi[0] + pad, lo[1] - pad, hi[1] + pad);
    let mut chart = Chart::new(
        HALF_PX,
        HALF_PX,
        &format!("{}: tool-tip paths, top view", ep.name),
        Axis::new("scene x (m)").with_range(x0, x1),
        Axis::new("scene y (m)").with_range(y0, y1),
    );
    chart.equal_aspect = true;
    chart.legend = Corner::TopRight;
    let near: Vec<(f64, f64)> = report
        .landmarks
        .iter()
        .filter(|p| (x0..=x1).contains(&p[0]) && (y0..=y1).contains(&p[1]))
        .map(|p| (p[0], p[1]))
        .collect();
    chart.series.push(Series::new(
        "landmarks",
        LANDMARK_COLOR,
        Mark::Points(1),
        decimate(&near, MAX_LANDMARKS),
    ));
    let mut named: Vec<SupportClass> = Vec::new();
    for (k, track) in ep.wrists.iter().enumerate() {
        let samples = decimate(&track.samples, MAX_PATH_POINTS);
        let mut start = 0;
        while start < samples.len() {
            let class = samples[start].support;
            let mut end = start;
            while end + 1 < samples.len() && samples[end + 1].support == class {
                end += 1;
            }
            // Each run ends at the next run's first point, so the path stays unbroken.
            let last = (end + 1).min(samples.len() - 1);
            let points: Vec<(f64, f64)> = samples[start..=last]
                .iter()
                .map(|s| (s.tip[0], s.tip[1]))
                .collect();
            let name = if named.contains(&class) {
                String::new()
            } else {
                named.push(class);
                class.as_str().to_string()
            };
            let mark = if k == 0 {
                Mark::Line(2)
            } else {
                Mark::Dashed(2)
            };
            chart
                .series
                .push(Series::new(&name, support_color(class), mark, points));
            start = end + 1;
        }
        if let Some(first) = samples.first() {
            chart.series.push(Series::new(
                "",
                START_COLOR,
                Mark::Points(START_MARKER_PX),
                vec![(first.tip[0], first.tip[1])],
            ));
        }
    }
    if !head.is_empty() {
        let points: Vec<(f64, f64)> = decimate(&head, MAX_PATH_POINTS)
            .iter()
            .map(|p| (p[0], p[1]))
            .collect();
        chart
            .series
            .push(Series::new("head", HEAD_COLOR, Mark::Line(1), points));
    }
    Some(chart)
}

/// One opening chart per wrist whose tool has jaws and was measured.
fn gripper_charts(ep: &EpisodeReport) -> Vec<Chart> {
    ep.wrists
        .iter()
        .filter(|w| w.samples.iter().any(|s| s.opening.is_some()))
        .filter_map(|w: &WristTrack| {
            let (label, scale) = match w.tool {
                ToolKind::Chopstick => ("opening angle (deg)", 180.0 / std::f64::consts::PI),
                ToolKind::ParallelJaw => ("jaw width (mm)", 1e3),
                ToolKind::BareHand => return None,
            };
            let points: Vec<(f64, f64)> = decimate(&w.samples, MAX_PATH_POINTS)
                .iter()
                .map(|s| (s.t, s.opening.map_or(f64::NAN, |v| v * scale)))
                .collect();
            let mut chart = Chart::new(
                HALF_PX,
                260,
                &format!("{}: {} gripper opening", ep.name, w.camera),
                Axis::new(if w.session_clock {
                    "session time (s)"
                } else {
                    "camera time (s)"
                }),
                Axis::new(label),
            );
            chart
                .series
                .push(Series::new("", PALETTE[0], Mark::Line(1), points));
            Some(chart)
        })
        .collect()
}

/// The sync graph: cameras with their clocks, audio pairs with their lags.
fn sync_graph(sync: &SyncResult) -> NodeGraph {
    let nodes: Vec<(String, String)> = sync
        .cameras
        .iter()
        .map(|c| {
            let note = match (c.status, c.offset_s) {
                (CameraStatus::Reference, _) => "reference".to_string(),
                (CameraStatus::Unmatched, _) | (_, None) => "not synchronized".to_string(),
                (CameraStatus::OffsetOnly, Some(o)) => format!("{:+.3} ms", o * 1e3),
                (CameraStatus::OffsetAndDrift, Some(o)) => {
                    format!("{:+.3} ms, {:+.1} ppm", o * 1e3, c.drift_ppm)
                }
            };
            (c.name.clone(), note)
        })
        .collect();
    let index = |name: &str| sync.cameras.iter().position(|c| c.name == name);
    let edges = sync
        .pairs
        .iter()
        .filter_map(|p| {
            let (a, b) = (index(&p.a)?, index(&p.b)?);
            let accepted = p.status == "accepted";
            let label = match (accepted, p.lag_s) {
                (true, Some(lag)) => match p.drift_ppm {
                    Some(d) => format!("lag {:+.3} ms, {d:+.1} ppm", lag * 1e3),
                    None => format!("lag {:+.3} ms", lag * 1e3),
                },
                _ => p.status.clone(),
            };
            Some(Edge {
                a,
                b,
                label,
                color: if accepted {
                    ACCEPTED_COLOR
                } else {
                    REJECTED_COLOR
                },
                dashed: !accepted,
            })
        })
        .collect();
    let mut notes: Vec<String> = sync
        .closures
        .iter()
        .map(|c| {
            format!(
                "triangle {}–{}–{} closes to {:.3} ms",
                c.cameras[0],
                c.cameras[1],
                c.cameras[2],
                c.residual_s * 1e3
            )
        })
        .collect();
    if notes.is_empty() {
        notes.push(if sync.cameras.len() < 3 {
            "no triangle to close: fewer than three cameras".into()
        } else {
            "no triangle of accepted pairs to close".into()
        });
    }
    NodeGraph {
        width: HALF_PX,
        height: 240,
        title: "sync graph".into(),
        nodes,
        edges,
        notes,
    }
}

fn sync_tables(html: &mut String, sync: &SyncResult) {
    html.push_str(
        "<table><tr><th>camera</th><th>placed</th><th>offset (ms)</th><th>± (ms)</th>\
         <th>drift (ppm)</th></tr>\n",
    );
    for c in &sync.cameras {
        let status = match c.status {
            CameraStatus::Reference => "reference",
            CameraStatus::OffsetOnly => "offset only",
            CameraStatus::OffsetAndDrift => "offset and drift",
            CameraStatus::Unmatched => "not synchronized",
        };
        let _ = writeln!(
            html,
            "<tr><td>{}</td><td>{status}</td><td>{}</td><td>{:.3}</td><td>{:+.2}</td></tr>",
            esc(&c.name),
            c.offset_s
                .map_or_else(|| "—".into(), |o| format!("{:+.3}", o * 1e3)),
            c.offset_std_s * 1e3,
            c.drift_ppm
        );
    }
    html.push_str(
        "</table>\n<table><tr><th>pair</th><th>status</th><th>lag (ms)</th><th>drift (ppm)</th>\
         <th>votes</th><th>peak ratio</th><th>windows</th><th>solution residual (ms)</th>\
         <th>reason</th></tr>\n",
    );
    for p in &sync.pairs {
        let ms = |v: Option<f64>| v.map_or_else(|| "—".into(), |v| format!("{:+.3}", v * 1e3));
        let _ = writeln!(
            html,
            "<tr><td>{}–{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{:.2}</td>\
             <td>{}</td><td>{}</td><td>{}</td></tr>",
            esc(&p.a),
            esc(&p.b),
            esc(&p.status),
            ms(p.lag_s),
            p.drift_ppm
                .map_or_else(|| "—".into(), |d| format!("{d:+.2}")),
            p.votes,
            p.peak_ratio,
            p.windows,
            ms(p.solution_residual_s),
            esc(p.reason.as_deref().unwrap_or(""))
        );
    }
    html.push_str("</table>\n");
}

fn stage_table(html: &mut String, stages: &[StageTiming]) {
    html.push_str(
        "<table><tr><th>stage</th><th>status</th><th>wall time (s)</th><th>reason</th></tr>\n",
    );
    for s in stages {
        let class = match s.status.as_str() {
            "ok" => "usable",
            "failed" => "unusable",
            _ => "notrun",
        };
        let _ = writeln!(
            html,
            "<tr><td>{}</td><td class=\"{class}\">{}</td><td>{}</td><td>{}</td></tr>",
            esc(&s.stage),
            esc(&s.status),
            s.seconds.map_or_else(|| "—".into(), |t| format!("{t:.2}")),
            esc(s.reason.as_deref().unwrap_or(""))
        );
    }
    html.push_str("</table>\n");
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]

    use super::*;
    use crate::formats::tables::LensFrame;
    use crate::report::{LensTrack, TrackSample, WristSetup};
    use crate::sync::{CameraClock, Closure};

    fn sync() -> SyncResult {
        let clock = |name: &str, status, offset: Option<f64>| CameraClock {
            name: name.into(),
            offset_s: offset,
            drift_ppm: 12.0,
            offset_std_s: 1e-5,
            status,
        };
        SyncResult {
            cameras: vec![
                clock("left", CameraStatus::Reference, Some(0.0)),
                clock("right", CameraStatus::OffsetAndDrift, Some(0.0371)),
                clock("head", CameraStatus::Unmatched, None),
            ],
            pairs: Vec::new(),
            closures: vec![Closure {
                cameras: ["left".into(), "right".into(), "head".into()],
                residual_s: 2e-5,
            }],
        }
    }

    /// A two-minute episode at 119.88 Hz whose support and lenses change state at every frame,
    /// with a hundred different lost reasons: the worst case for the page's size (longer
    /// episodes are thinned to the same number of points and spans).
    fn long_episode(name: &str) -> EpisodeReport {
        let n = 120 * 120;
        let classes = [
            SupportClass::Front,
            SupportClass::Rear,
            SupportClass::RearInterpolated,
            SupportClass::ImuOnly,
        ];
        let track = |camera: &str, tool| WristTrack {
            camera: camera.into(),
            tool,
            session_clock: true,
            samples: (0..n)
                .map(|k| {
                    let t = k as f64 / 119.88;
                    TrackSample {
                        t,
                        tip: [(t * 0.1).sin(), (t * 0.13).cos(), 0.8],
                        support: classes[k % 4],
                        opening: (k % 7 != 0).then_some(0.01 * (t * 0.5).sin()),
                    }
                })
                .collect(),
        };
        let lens = |camera: &str, lens: &str| LensTrack {
            camera: camera.into(),
            lens: lens.into(),
            session_clock: true,
            frames: (0..n)
                .map(|k| LensFrame {
                    t: k as f64 / 119.88,
                    lost: (k % 2 == 1).then(|| format!("reason {} of many", (k / 2) % 100)),
                })
                .collect(),
        };
        EpisodeReport {
            name: name.into(),
            description: "tabletop".into(),
            verdict: Some(Verdict::Suspect),
            reasons: vec!["left: supported fraction 0.75 < 0.99".into()],
            quality: None,
            wrists: vec![
                track("left", ToolKind::Chopstick),
                track("right", ToolKind::ParallelJaw),
            ],
            head: Some(
                (0..n)
                    .map(|k| (k as f64, [0.0, 0.1 * k as f64, 1.6]))
                    .collect(),
            ),
            floor_figure: None,
            lenses: vec![
                lens("left", "front"),
                lens("left", "rear"),
                lens("right", "front"),
                lens("right", "rear"),
            ],
            sync: Some(sync()),
            stages: vec![StageTiming {
                stage: "outputs".into(),
                status: "failed".into(),
                seconds: Some(1.5),
                reason: Some("<bad> & \"quoted\"".into()),
            }],
            notes: Vec::new(),
        }
    }

    fn session(episodes: Vec<EpisodeReport>) -> SessionReport {
        SessionReport {
            name: "kitchen".into(),
            map_episode: "ep000".into(),
            wrists: vec![WristSetup {
                camera: "left".into(),
                unit: "X5-0001".into(),
                tool: ToolKind::Chopstick,
            }],
            landmarks: (0..200_000)
                .map(|k| {
                    let a = k as f64 * 0.001;
                    [a.sin(), a.cos() * 1.1, 0.5]
                })
                .collect(),
            landmarks_note: None,
            episodes,
            session_stages: Vec::new(),
            ablation: None,
            markers: Vec::new(),
        }
    }

    #[test]
    fn ten_long_episodes_stay_under_five_megabytes() {
        let episodes: Vec<EpisodeReport> = (0..10)
            .map(|k| long_episode(&format!("ep{k:03}")))
            .collect();
        let page = render(&session(episodes)).unwrap();
        let mb = page.html.len() as f64 / 1e6;
        assert!(mb < 5.0, "{mb:.2} MB");
        // Per episode: top view, timeline, two gripper charts, sync graph.
        assert_eq!(page.plots, 50);
        assert_eq!(page.html.matches("<svg").count(), page.plots);
        assert!(page.html.contains("&lt;bad&gt; &amp; &quot;quoted&quot;"));
        assert!(!page.html.contains("<script"));
        println!("10 episodes: {mb:.2} MB");
    }

    #[test]
    fn a_failed_episode_shows_its_reason_and_no_path() {
        let failed = EpisodeReport {
            name: "ep001".into(),
            description: "walk".into(),
            verdict: Some(Verdict::Unusable),
            reasons: vec!["needs session/map-rear, which failed: left/rear: no map".into()],
            quality: None,
            wrists: Vec::new(),
            head: None,
            floor_figure: None,
            lenses: Vec::new(),
            sync: None,
            stages: Vec::new(),
            notes: Vec::new(),
        };
        let page = render(&session(vec![failed])).unwrap();
        assert_eq!(page.plots, 0);
        for text in [
            "class=\"verdict unusable\">unusable",
            "which failed: left/rear: no map",
            "No trajectory to draw",
        ] {
            assert!(page.html.contains(text), "{text} missing");
        }
    }

    #[test]
    fn spans_merge_runs_and_bin_when_there_are_too_many() {
        let times: Vec<f64> = (0..10).map(f64::from).collect();
        let states = [0, 0, 1, 1, 1, 0, 0, 0, 0, 2];
        let spans = state_spans(&times, &states);
        assert_eq!(
            spans,
            vec![(0.0, 2.0, 0), (2.0, 5.0, 1), (5.0, 9.0, 0), (9.0, 10.0, 2)]
        );
        let times: Vec<f64> = (0..100_000).map(|k| f64::from(k) * 0.01).collect();
        let states: Vec<usize> = (0..100_000).map(|k| k % 2).collect();
        let spans = state_spans(&times, &states);
        assert!(spans.len() <= MAX_TIMELINE_SPANS, "{}", spans.len());
        // Every bin holds a lost frame: the weakest state shows.
        assert!(spans.iter().all(|s| s.2 == 1));
    }
}
