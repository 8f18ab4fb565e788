//! The floor's figure (like the paper's plane-support plot): the sweep's support per
//! camera-to-plane distance in the best window, with the floor and the other surfaces marked,
//! and every window's floor height over time for both wrists.

use kiwi_core::layout::Side;
use kiwi_plot::{Axis, Chart, Mark, PALETTE, Series};

use super::{EpisodeSurface, Floor, WindowEstimate, WindowStatus};

/// Figure width and each chart's height (px).
const SIZE: (u32, u32) = (760, 300);

/// The figure's charts (an SVG stack).
pub fn charts(
    windows: &[WindowEstimate],
    floor: &Floor,
    surfaces: &[EpisodeSurface],
) -> Vec<Chart> {
    let mut out = Vec::new();
    // The accepted window with the most decisive floor (smallest sigma), else any swept one.
    let best = windows
        .iter()
        .filter(|w| w.status == WindowStatus::Accepted)
        .min_by(|a, b| {
            a.sigma_m
                .unwrap_or(f64::INFINITY)
                .total_cmp(&b.sigma_m.unwrap_or(f64::INFINITY))
        })
        .or_else(|| windows.first());
    if let Some(w) = best {
        let mut support = Chart::new(
            SIZE.0,
            SIZE.1,
            &format!(
                "Plane support, {} wrist window at frame {}",
                w.side.camera_name(),
                w.frame
            ),
            Axis::new("camera-to-plane distance H (m)"),
            Axis::new("share of pixels agreeing"),
        );
        let curve: Vec<(f64, f64)> = w.sweep_support.iter().map(|p| (p[0], p[1])).collect();
        let top = curve.iter().map(|p| p.1).fold(0.0f64, f64::max).max(1e-3);
        support
            .series
            .push(Series::new("plane sweep", PALETTE[0], Mark::Line(2), curve));
        if let Some(z) = floor.z_m() {
            let h = w.camera_z_m - z;
            support.series.push(Series::new(
                &format!("floor (H = {h:.3} m)"),
                PALETTE[2],
                Mark::Dashed(2),
                vec![(h, 0.0), (h, top)],
            ));
        }
        for s in surfaces {
            let h = w.camera_z_m - s.z_m;
            support.series.push(Series::new(
                &format!("surface (H = {h:.3} m)"),
                PALETTE[1],
                Mark::Dashed(1),
                vec![(h, 0.0), (h, top)],
            ));
        }
        out.push(support);
    }
    let mut over_time = Chart::new(
        SIZE.0,
        SIZE.1,
        "Floor height per window",
        Axis::new("session time (s)"),
        Axis::new("floor height, scene z (m)"),
    );
    for (k, side) in [Side::Left, Side::Right].into_iter().enumerate() {
        let points = |status: WindowStatus| -> Vec<(f64, f64)> {
            windows
                .iter()
                .filter(|w| w.side == side && w.status == status)
                .filter_map(|w| Some((w.t_session.unwrap_or(w.t_camera), w.floor_z_m?)))
                .collect()
        };
        over_time.series.push(Series::new(
            &format!("{} wrist", side.camera_name()),
            PALETTE[3 + k],
            Mark::Points(4),
            points(WindowStatus::Accepted),
        ));
    }
    let t: Vec<f64> = windows
        .iter()
        .map(|w| w.t_session.unwrap_or(w.t_camera))
        .collect();
    if let (Some(z), Some(t0), Some(t1)) = (
        floor.z_m(),
        t.iter().copied().reduce(f64::min),
        t.iter().copied().reduce(f64::max),
    ) {
        over_time.series.push(Series::new(
            "episode floor",
            PALETTE[2],
            Mark::Dashed(2),
            vec![(t0, z), (t1, z)],
        ));
    }
    out.push(over_time);
    out
}
