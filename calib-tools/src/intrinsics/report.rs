//! The outputs of `kiwi-calib intrinsics`: the lens part of the unit artifact, a JSON summary,
//! the rejected corners, and report SVGs (coverage heat map, residual vectors, per-view RMS).

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use kiwi_core::io::write_atomic;

use super::IntrinsicsResult;
use crate::error::{CalibError, Result};
use kiwi_plot::{Arrow, Axis, Chart, Mark, Rect, Rects, Series, bars};

/// Heat-map bins per image side.
const HEAT_BINS: u32 = 48;
/// Colour levels of the heat map (finer steps are not told apart by eye).
const HEAT_LEVELS: u32 = 16;
/// Residual arrows are drawn this many times longer than they are, in units of the image width
/// per RMS, so a typical arrow is under 1 % of the image and the field stays readable.
const ARROW_LENGTH_PER_RMS: f64 = 0.008;

/// Files written by [`write_outputs`].
#[derive(Debug, Clone, serde::Serialize)]
pub struct WrittenFiles {
    /// The lens calibration (kiwi-core `LensCalibration` JSON).
    pub lens: PathBuf,
    /// Full summary (parameters, std, per-view RMS, rejected corners).
    pub summary: PathBuf,
    /// Rejected corners (CSV).
    pub rejected: PathBuf,
    /// Report plots (SVG).
    pub plots: Vec<PathBuf>,
}

fn json<T: serde::Serialize>(value: &T) -> Result<String> {
    serde_json::to_string_pretty(value)
        .map_err(|e| CalibError::Internal(format!("result does not serialize: {e}")))
}

/// Write the outputs into `out` (created if needed; existing results are never overwritten).
pub fn write_outputs(
    result: &IntrinsicsResult,
    lens_name: &str,
    out: &Path,
) -> Result<WrittenFiles> {
    std::fs::create_dir_all(out).map_err(|e| CalibError::Input {
        path: out.to_path_buf(),
        message: format!("cannot create the output folder: {e}"),
    })?;
    let lens = out.join("lens.json");
    if lens.exists() {
        return Err(CalibError::Input {
            path: lens,
            message: "a calibration is already there and is never overwritten; choose another \
                      --out"
                .into(),
        });
    }
    let mut lc = result.lens_calibration();
    lc.name = lens_name.to_string();
    write_atomic(&lens, json(&lc)?.as_bytes())?;
    let summary = out.join("summary.json");
    let mut full = serde_json::to_value(result)
        .map_err(|e| CalibError::Internal(format!("result does not serialize: {e}")))?;
    if let Some(map) = full.as_object_mut() {
        map.insert("fx".into(), result.params[0].into());
        map.insert("fy".into(), result.params[1].into());
        map.insert("cx".into(), result.params[2].into());
        map.insert("cy".into(), result.params[3].into());
    }
    write_atomic(&summary, json(&full)?.as_bytes())?;
    let rejected = out.join("rejected_corners.csv");
    let mut csv = String::from("image,id,u,v,residual_px,reason\n");
    for r in &result.rejected {
        let _ = writeln!(
            csv,
            "{},{},{},{},{},\"{}\"",
            r.image,
            r.id,
            r.pixel[0],
            r.pixel[1],
            r.residual_px,
            r.reason.replace('"', "'")
        );
    }
    write_atomic(&rejected, csv.as_bytes())?;
    let plots = vec![
        coverage_svg(result, &out.join("coverage.svg"))?,
        residuals_svg(result, &out.join("residuals.svg"))?,
        view_rms_svg(result, &out.join("view_rms.svg"))?,
    ];
    Ok(WrittenFiles {
        lens,
        summary,
        rejected,
        plots,
    })
}

/// Colour map from white (no corners) through blue and green to red (most corners).
fn heat_colour(v: f64) -> [u8; 3] {
    if v <= 0.0 {
        return [245, 245, 245];
    }
    let stops: [[f64; 3]; 4] = [
        [40.0, 60.0, 200.0],
        [30.0, 170.0, 200.0],
        [60.0, 190.0, 60.0],
        [220.0, 40.0, 30.0],
    ];
    let x = v.clamp(0.0, 1.0) * 3.0;
    let i = (x.floor() as usize).min(2);
    let f = x - i as f64;
    let c = |k: usize| (stops[i][k] * (1.0 - f) + stops[i + 1][k] * f) as u8;
    [c(0), c(1), c(2)]
}

/// Where the used corners fell in the image (heat map of corner counts), and the rejected
/// ones (black dots); image y is drawn from the bottom so the picture is upright.
fn coverage_svg(result: &IntrinsicsResult, path: &Path) -> Result<PathBuf> {
    let [w, h] = result.resolution;
    let (wf, hf) = (f64::from(w), f64::from(h));
    let mut bins = vec![0u32; (HEAT_BINS * HEAT_BINS) as usize];
    for r in &result.residuals {
        let bx = ((r.pixel[0] / wf * f64::from(HEAT_BINS)) as u32).min(HEAT_BINS - 1);
        let by = ((r.pixel[1] / hf * f64::from(HEAT_BINS)) as u32).min(HEAT_BINS - 1);
        bins[(by * HEAT_BINS + bx) as usize] += 1;
    }
    let max = f64::from(bins.iter().copied().max().unwrap_or(1).max(1));
    let mut fig = Chart::new(
        800,
        820,
        &format!(
            "corner coverage: {} corners, {} views (colour: corners per cell, black: rejected)",
            result.n_corners, result.n_views
        ),
        Axis::new("image x (px)").with_range(0.0, wf),
        Axis::new("image y from the bottom (px)").with_range(0.0, hf),
    );
    fig.equal_aspect = true;
    // One layer per colour level keeps the SVG small (cells of one level share a style).
    let mut levels: Vec<Rects> = (0..=HEAT_LEVELS)
        .map(|k| Rects {
            name: String::new(),
            color: heat_colour(f64::from(k) / f64::from(HEAT_LEVELS)),
            rects: Vec::new(),
        })
        .collect();
    let (cw, ch) = (wf / f64::from(HEAT_BINS), hf / f64::from(HEAT_BINS));
    for by in 0..HEAT_BINS {
        for bx in 0..HEAT_BINS {
            let n = bins[(by * HEAT_BINS + bx) as usize];
            if n == 0 {
                continue;
            }
            let level = ((f64::from(n) / max * f64::from(HEAT_LEVELS)).round() as usize).max(1);
            let (x0, y1) = (f64::from(bx) * cw, hf - f64::from(by) * ch);
            levels[level.min(HEAT_LEVELS as usize)].rects.push(Rect {
                x0,
                x1: x0 + cw,
                y0: y1 - ch,
                y1,
            });
        }
    }
    fig.rects = levels;
    fig.series.push(Series {
        name: if result.rejected.is_empty() {
            String::new()
        } else {
            "rejected".into()
        },
        color: [0, 0, 0],
        mark: Mark::Points(2),
        points: result
            .rejected
            .iter()
            .map(|r| (r.pixel[0], hf - r.pixel[1]))
            .collect(),
    });
    fig.save_svg(path)?;
    Ok(path.to_path_buf())
}

/// Residual vectors at each corner, magnified.
fn residuals_svg(result: &IntrinsicsResult, path: &Path) -> Result<PathBuf> {
    let [w, h] = result.resolution;
    let scale = ARROW_LENGTH_PER_RMS * f64::from(w) / result.rms_px.max(1e-6);
    let mut fig = Chart::new(
        900,
        900,
        &format!(
            "residuals ×{scale:.0} (rms {:.3} px, {})",
            result.rms_px, result.model
        ),
        Axis::new("image x (px)").with_range(0.0, f64::from(w)),
        Axis::new("image y from the bottom (px)").with_range(0.0, f64::from(h)),
    );
    fig.equal_aspect = true;
    let hf = f64::from(h);
    fig.arrows = result
        .residuals
        .iter()
        .map(|r| Arrow {
            from: (r.pixel[0], hf - r.pixel[1]),
            to: (
                r.pixel[0] + scale * r.residual[0],
                hf - (r.pixel[1] + scale * r.residual[1]),
            ),
        })
        .collect();
    fig.save_svg(path)?;
    Ok(path.to_path_buf())
}

/// RMS of each view as a bar (rejected views marked red at zero).
fn view_rms_svg(result: &IntrinsicsResult, path: &Path) -> Result<PathBuf> {
    let n = result.views.len();
    let used: Vec<f64> = result
        .views
        .iter()
        .map(|v| {
            if v.used && v.rms_px.is_finite() {
                v.rms_px
            } else {
                f64::NAN
            }
        })
        .collect();
    let max = used
        .iter()
        .copied()
        .filter(|v| v.is_finite())
        .fold(0.0, f64::max);
    let mut fig = Chart::new(
        1000,
        500,
        "per-view RMS",
        Axis::new("view").with_range(-1.0, n as f64),
        Axis::new("RMS per axis (px)").with_range(0.0, (max * 1.2).max(1e-3)),
    );
    fig.rects.push(bars("used", [40, 90, 200], &used));
    let rejected: Vec<(f64, f64)> = result
        .views
        .iter()
        .enumerate()
        .filter(|(_, v)| !(v.used && v.rms_px.is_finite()))
        .map(|(k, _)| (k as f64, 0.0))
        .collect();
    if !rejected.is_empty() {
        fig.series.push(Series {
            name: "rejected".into(),
            color: [200, 40, 40],
            mark: Mark::Points(3),
            points: rejected,
        });
    }
    fig.save_svg(path)?;
    Ok(path.to_path_buf())
}
