//! Gripper opening from the wrist video (paper §4.3.1): per frame of the front lens, the
//! chopstick's opening angle or the parallel jaw's gap, with a confidence, or the reason it
//! could not be measured.
//!
//! [`estimate`] holds the per-frame algorithm (dot-plane rectification through the fisheye
//! model, red-dot segmentation, one line per jaw); this module runs it over a lens folder in
//! parallel and writes `opening.csv` (`t,opening,unit,confidence,status`), `opening.svg`, the
//! tool artifact `tool.json` and a summary `opening.json`.

pub mod aruco;
pub mod calibrate;
pub mod estimate;

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use kiwi_core::camera::Camera;
use kiwi_core::io::write_atomic;
use kiwi_core::tool::{ToolCalibration, ToolDefinition};
use serde::Serialize;

pub use estimate::{ChannelOrder, GripperEstimator, ImageView, Measurement, OpeningUnit};

use crate::error::{BackendError, Result};
use crate::frames::FrameSource;

/// One output row.
#[derive(Debug, Clone, Serialize)]
pub struct OpeningRow {
    /// Frame time (s, camera clock).
    pub t: f64,
    /// The measurement.
    pub measurement: Measurement,
}

/// Summary of a run.
#[derive(Debug, Clone, Serialize)]
pub struct OpeningSummary {
    /// Frames processed.
    pub frames: usize,
    /// Frames measured.
    pub measured: usize,
    /// Frames missing, with their reasons counted.
    pub missing: Vec<(String, usize)>,
    /// Unit of the openings.
    pub unit: OpeningUnit,
    /// Rectified pixels per metre (parallel-jaw px → m).
    pub px_per_m: f64,
    /// Median confidence of the measured frames.
    pub median_confidence: f64,
    /// Processing speed (frames/s, wall clock).
    pub frames_per_s: f64,
}

/// The tool artifact: what the estimator used for this tool on this lens.
#[derive(Debug, Clone, Serialize)]
pub struct ToolArtifact {
    /// Schema version.
    pub schema_version: u32,
    /// The tool definition.
    pub definition: ToolDefinition,
    /// How the dot-plane pose was obtained.
    pub plane_source: String,
    /// The dot plane and its rectification grid in the front-lens frame.
    pub plane: estimate::DotPlane,
}

/// Read one image file as interleaved BGR bytes `(width, height, bytes)`.
pub fn load_bgr(path: &Path) -> Result<(usize, usize, Vec<u8>)> {
    let img = crate::frames::load_image_bgr(path)?;
    Ok((img.width, img.height, img.bgr))
}

/// Measure every frame of a lens folder (`frames.csv` + images or video) in parallel;
/// `progress` is called once per frame from worker threads.
pub fn measure_lens(
    estimator: &GripperEstimator,
    lens_dir: &Path,
    progress: &(dyn Fn() + Sync),
) -> Result<Vec<OpeningRow>> {
    let source = FrameSource::open(lens_dir)?;
    let indices: Vec<usize> = (0..source.len()).collect();
    let frames = source.frames();
    Ok(source.map_color(&indices, |i, img| {
        let m = match img {
            Ok(img) => estimator.measure(&ImageView {
                width: img.width,
                height: img.height,
                data: &img.bgr,
                order: ChannelOrder::Bgr,
            }),
            Err(e) => Measurement {
                opening: None,
                unit: estimator.unit(),
                confidence: 0.0,
                status: format!("missing: unreadable frame ({e})"),
                dots_used: [0, 0],
                fit_rms_m: f64::NAN,
            },
        };
        progress();
        OpeningRow {
            t: frames[i].t,
            measurement: m,
        }
    }))
}

/// `t,opening,unit,confidence,status` text (the status never contains a comma).
pub fn opening_csv(rows: &[OpeningRow]) -> String {
    let mut s = String::from("t,opening,unit,confidence,status\n");
    for r in rows {
        let m = &r.measurement;
        let opening = m.opening.map(|o| format!("{o:.4}")).unwrap_or_default();
        let _ = writeln!(
            s,
            "{:.6},{opening},{},{:.3},{}",
            r.t,
            m.unit.as_str(),
            m.confidence,
            m.status.replace(',', ";")
        );
    }
    s
}

/// A plain SVG chart of the opening over time (missing frames as ticks at the bottom).
pub fn opening_svg(rows: &[OpeningRow], unit: OpeningUnit) -> String {
    let (w, h, ml, mr, mt, mb) = (900.0, 360.0, 70.0, 20.0, 30.0, 45.0);
    let vals: Vec<(f64, f64)> = rows
        .iter()
        .filter_map(|r| r.measurement.opening.map(|o| (r.t, o)))
        .collect();
    let (t0, t1) = (
        rows.first().map_or(0.0, |r| r.t),
        rows.last().map_or(1.0, |r| r.t),
    );
    let (mut y0, mut y1) = vals
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| {
            (a.min(v.1), b.max(v.1))
        });
    if !(y0.is_finite() && y1 > y0) {
        (y0, y1) = (0.0, 1.0);
    }
    let pad = 0.05 * (y1 - y0);
    let (y0, y1) = (y0 - pad, y1 + pad);
    let tspan = (t1 - t0).max(1e-9);
    let x = |t: f64| ml + (t - t0) / tspan * (w - ml - mr);
    let y = |v: f64| mt + (1.0 - (v - y0) / (y1 - y0)) * (h - mt - mb);
    let mut s = format!(
        "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{w}\" height=\"{h}\" \
         font-family=\"sans-serif\" font-size=\"12\">\n<rect width=\"100%\" height=\"100%\" \
         fill=\"white\"/>\n"
    );
    let _ = writeln!(
        s,
        "<rect x=\"{ml}\" y=\"{mt}\" width=\"{}\" height=\"{}\" fill=\"none\" stroke=\"#444\"/>",
        w - ml - mr,
        h - mt - mb
    );
    for k in 0..=4 {
        let v = y0 + (y1 - y0) * f64::from(k) / 4.0;
        let _ = writeln!(
            s,
            "<text x=\"{}\" y=\"{:.1}\" text-anchor=\"end\">{v:.2}</text>",
            ml - 6.0,
            y(v) + 4.0
        );
        let t = t0 + tspan * f64::from(k) / 4.0;
        let _ = writeln!(
            s,
            "<text x=\"{:.1}\" y=\"{}\" text-anchor=\"middle\">{t:.2}</text>",
            x(t),
            h - mb + 16.0
        );
    }
    let _ = writeln!(
        s,
        "<text x=\"{}\" y=\"{}\" text-anchor=\"middle\">time (s)</text>\n<text x=\"14\" \
         y=\"{}\" transform=\"rotate(-90 14 {})\" text-anchor=\"middle\">opening ({})</text>",
        (w + ml) / 2.0,
        h - 8.0,
        h / 2.0,
        h / 2.0,
        unit.as_str()
    );
    let mut path = String::new();
    let mut prev: Option<f64> = None;
    for r in rows {
        match r.measurement.opening {
            Some(v) => {
                let cmd = if prev.is_some() { 'L' } else { 'M' };
                let _ = write!(path, "{cmd}{:.1},{:.1} ", x(r.t), y(v));
                prev = Some(v);
            }
            None => {
                prev = None;
                let _ = writeln!(
                    s,
                    "<line x1=\"{0:.1}\" x2=\"{0:.1}\" y1=\"{1}\" y2=\"{2}\" stroke=\"#c33\"/>",
                    x(r.t),
                    h - mb - 8.0,
                    h - mb
                );
            }
        }
    }
    let _ = writeln!(
        s,
        "<path d=\"{path}\" fill=\"none\" stroke=\"#1f5fbf\" stroke-width=\"1.5\"/>\n</svg>"
    );
    s
}

/// Everything `kiwi gripper` writes.
#[derive(Debug, Clone)]
pub struct GripperOutputs {
    /// `opening.csv`.
    pub csv: PathBuf,
    /// `opening.svg`.
    pub plot: PathBuf,
    /// `tool.json`.
    pub tool: PathBuf,
    /// `opening.json`.
    pub summary: PathBuf,
}

/// Measure a lens folder with the tool definition's CAD geometry and write the outputs into
/// `out_dir`.
pub fn run(
    camera: &Camera,
    def: &ToolDefinition,
    lens_dir: &Path,
    out_dir: &Path,
    progress: &(dyn Fn() + Sync),
) -> Result<(OpeningSummary, GripperOutputs)> {
    run_with(
        camera,
        def,
        "tool definition (nominal CAD geometry; no tool calibration given)",
        lens_dir,
        out_dir,
        progress,
    )
}

/// Measure a lens folder with a tool calibration (`kiwi gripper --calibrate`) and write the
/// outputs into `out_dir`.
pub fn run_calibrated(
    camera: &Camera,
    calibration: &ToolCalibration,
    lens_dir: &Path,
    out_dir: &Path,
    progress: &(dyn Fn() + Sync),
) -> Result<(OpeningSummary, GripperOutputs)> {
    let source = format!(
        "tool calibration of unit {} lens {} (body tag in {} frames, {} jaw lines)",
        calibration.unit_id,
        calibration.lens,
        calibration.quality.frames_with_tag,
        calibration.quality.jaw_lines
    );
    run_with(
        camera,
        &calibration.calibrated_definition(),
        &source,
        lens_dir,
        out_dir,
        progress,
    )
}

/// The files [`run`] and [`run_calibrated`] write into their output folder.
pub const OUTPUT_FILES: [&str; 4] = ["opening.csv", "opening.svg", "tool.json", "opening.json"];

fn run_with(
    camera: &Camera,
    def: &ToolDefinition,
    plane_source: &str,
    lens_dir: &Path,
    out_dir: &Path,
    progress: &(dyn Fn() + Sync),
) -> Result<(OpeningSummary, GripperOutputs)> {
    let estimator = GripperEstimator::new(camera, def)?;
    let start = std::time::Instant::now();
    let rows = measure_lens(&estimator, lens_dir, progress)?;
    let secs = start.elapsed().as_secs_f64();
    let summary = summarize(&rows, &estimator, secs);
    std::fs::create_dir_all(out_dir).map_err(|e| BackendError::Input {
        path: out_dir.to_path_buf(),
        message: format!("cannot create the output folder: {e}"),
    })?;
    let outputs = GripperOutputs {
        csv: out_dir.join("opening.csv"),
        plot: out_dir.join("opening.svg"),
        tool: out_dir.join("tool.json"),
        summary: out_dir.join("opening.json"),
    };
    write_atomic(&outputs.csv, opening_csv(&rows).as_bytes())?;
    write_atomic(
        &outputs.plot,
        opening_svg(&rows, estimator.unit()).as_bytes(),
    )?;
    let artifact = ToolArtifact {
        schema_version: 1,
        definition: def.clone(),
        plane_source: plane_source.into(),
        plane: estimator.rectifier().plane().clone(),
    };
    let json = |v: serde_json::Result<String>, path: &Path| {
        v.map_err(|e| BackendError::Input {
            path: path.to_path_buf(),
            message: format!("cannot encode JSON: {e}"),
        })
    };
    write_atomic(
        &outputs.tool,
        json(serde_json::to_string_pretty(&artifact), &outputs.tool)?.as_bytes(),
    )?;
    write_atomic(
        &outputs.summary,
        json(serde_json::to_string_pretty(&summary), &outputs.summary)?.as_bytes(),
    )?;
    Ok((summary, outputs))
}

/// Counts and speed of a run.
pub fn summarize(rows: &[OpeningRow], est: &GripperEstimator, secs: f64) -> OpeningSummary {
    let mut missing: Vec<(String, usize)> = Vec::new();
    let mut conf: Vec<f64> = Vec::new();
    for r in rows {
        if r.measurement.opening.is_some() {
            conf.push(r.measurement.confidence);
        } else {
            // Group reasons by their text before any count in parentheses.
            let key = r
                .measurement
                .status
                .split(" (")
                .next()
                .unwrap_or_default()
                .to_string();
            match missing.iter_mut().find(|(k, _)| *k == key) {
                Some((_, n)) => *n += 1,
                None => missing.push((key, 1)),
            }
        }
    }
    conf.sort_by(f64::total_cmp);
    OpeningSummary {
        frames: rows.len(),
        measured: conf.len(),
        missing,
        unit: est.unit(),
        px_per_m: est.rectifier().plane().px_per_m,
        median_confidence: conf.get(conf.len() / 2).copied().unwrap_or(0.0),
        frames_per_s: rows.len() as f64 / secs.max(1e-9),
    }
}
