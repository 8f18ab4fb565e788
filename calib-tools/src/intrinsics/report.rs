//! The outputs of `kiwi-calib intrinsics`: the lens part of the unit artifact, a JSON summary,
//! the rejected corners, and report PNGs (coverage heat map, residual vectors, per-view RMS).

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use image::{Rgb, RgbImage};

use kiwi_core::io::write_atomic;

use super::IntrinsicsResult;
use crate::error::{CalibError, Result};
use crate::plot::{Arrow, Figure, Series, Style, fill_rect, text};

/// Heat-map bins per image side.
const HEAT_BINS: u32 = 48;
/// Heat-map cell size in the PNG (pixels).
const HEAT_CELL: u32 = 12;
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
    /// Report PNGs.
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
        coverage_png(result, &out.join("coverage.png"))?,
        residuals_png(result, &out.join("residuals.png"))?,
        view_rms_png(result, &out.join("view_rms.png"))?,
    ];
    Ok(WrittenFiles {
        lens,
        summary,
        rejected,
        plots,
    })
}

fn save_png(img: RgbImage, path: &Path) -> Result<PathBuf> {
    crate::plot::save_png(img, path)?;
    Ok(path.to_path_buf())
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

/// Where the used corners fell in the image, and the rejected ones (black dots).
fn coverage_png(result: &IntrinsicsResult, path: &Path) -> Result<PathBuf> {
    let [w, h] = result.resolution;
    let (wf, hf) = (f64::from(w), f64::from(h));
    let mut bins = vec![0u32; (HEAT_BINS * HEAT_BINS) as usize];
    for r in &result.residuals {
        let bx = ((r.pixel[0] / wf * f64::from(HEAT_BINS)) as u32).min(HEAT_BINS - 1);
        let by = ((r.pixel[1] / hf * f64::from(HEAT_BINS)) as u32).min(HEAT_BINS - 1);
        bins[(by * HEAT_BINS + bx) as usize] += 1;
    }
    let max = f64::from(bins.iter().copied().max().unwrap_or(1).max(1));
    let top = 50;
    let side = HEAT_BINS * HEAT_CELL;
    let mut img = RgbImage::from_pixel(side + 40, side + top + 30, Rgb([255, 255, 255]));
    for by in 0..HEAT_BINS {
        for bx in 0..HEAT_BINS {
            let v = f64::from(bins[(by * HEAT_BINS + bx) as usize]) / max;
            let (x0, y0) = ((20 + bx * HEAT_CELL) as i32, (top + by * HEAT_CELL) as i32);
            fill_rect(
                &mut img,
                x0,
                y0,
                x0 + HEAT_CELL as i32 - 1,
                y0 + HEAT_CELL as i32 - 1,
                heat_colour(v),
            );
        }
    }
    for r in &result.rejected {
        let x = 20 + (r.pixel[0] / wf * f64::from(side)) as i32;
        let y = top as i32 + (r.pixel[1] / hf * f64::from(side)) as i32;
        fill_rect(&mut img, x - 1, y - 1, x + 1, y + 1, [0, 0, 0]);
    }
    text(
        &mut img,
        20,
        12,
        &format!(
            "corner coverage: {} corners, {} views (black: rejected)",
            result.n_corners, result.n_views
        ),
        [0, 0, 0],
    );
    save_png(img, path)
}

/// Residual vectors at each corner, magnified.
fn residuals_png(result: &IntrinsicsResult, path: &Path) -> Result<PathBuf> {
    let [w, h] = result.resolution;
    let scale = ARROW_LENGTH_PER_RMS * f64::from(w) / result.rms_px.max(1e-6);
    let mut fig = Figure::new(
        900,
        900,
        &format!(
            "residuals x{scale:.0} (rms {:.3} px, {})",
            result.rms_px, result.model
        ),
        "image x (px)",
        "image y from the bottom (px)",
    );
    fig.x_range = Some((0.0, f64::from(w)));
    fig.y_range = Some((0.0, f64::from(h)));
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
    fig.save_png(path)?;
    Ok(path.to_path_buf())
}

/// RMS of each view as a bar (rejected views at zero).
fn view_rms_png(result: &IntrinsicsResult, path: &Path) -> Result<PathBuf> {
    let mut fig = Figure::new(1000, 500, "per-view RMS", "view", "RMS per axis (px)");
    let n = result.views.len();
    let bar = (600 / n.max(1)).clamp(2, 20) as u32;
    for (k, v) in result.views.iter().enumerate() {
        let rms = if v.used && v.rms_px.is_finite() {
            v.rms_px
        } else {
            0.0
        };
        fig.series.push(Series {
            name: String::new(),
            color: if v.used { [40, 90, 200] } else { [200, 40, 40] },
            style: Style::Line(bar),
            points: vec![(k as f64, 0.0), (k as f64, rms)],
        });
    }
    let max = result
        .views
        .iter()
        .filter(|v| v.used)
        .map(|v| v.rms_px)
        .fold(0.0, f64::max);
    fig.x_range = Some((-1.0, n as f64));
    fig.y_range = Some((0.0, (max * 1.2).max(1e-3)));
    fig.save_png(path)?;
    Ok(path.to_path_buf())
}
