//! Outputs of `kiwi-calib cam-imu`: the unit artifact copy (`calibration.json`), Kalibr
//! `camchain-imucam.yaml`, `cam_imu.json`, `report.md` and residual plots; and the command line.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use serde::Serialize;

use kiwi_core::artifact::InputRecord;
use kiwi_core::io::{sha256_file, utc_now_rfc3339, write_atomic};

use super::{CamImuOptions, CamImuResult, calibrate};
use crate::error::{CalibError, Result};
use kiwi_plot::{Axis, Chart, Mark, PALETTE, Series, decimate};

/// Colours of the lenses in plots.
const LENS_COLORS: [[u8; 3]; 4] = [PALETTE[0], PALETTE[3], PALETTE[2], PALETTE[4]];
/// Corner residuals drawn per lens: each is an SVG element (~100 bytes), so more would make the
/// report's pages megabytes heavy without showing more.
const MAX_PLOTTED_CORNERS: usize = 5000;

/// Files written.
#[derive(Debug, Clone, Serialize)]
pub struct WrittenFiles {
    /// The unit artifact copy with the extrinsics.
    pub calibration: PathBuf,
    /// Kalibr camchain with `T_cam_imu` and `timeshift_cam_imu`.
    pub camchain_imucam: PathBuf,
    /// The full result.
    pub result: PathBuf,
    /// Markdown report.
    pub report: PathBuf,
    /// Plots.
    pub plots: Vec<PathBuf>,
}

/// Arguments of `kiwi-calib cam-imu`.
#[derive(Debug, clap::Args)]
pub struct CamImuArgs {
    /// The excitation's camera folder (meta.json, imu.csv, <lens>/frames.csv + frames/).
    #[arg(long)]
    pub capture: PathBuf,
    /// The unit's calibration.json with every lens's intrinsics (and recording modes with
    /// readout times, and the imu noise block if measured).
    #[arg(long)]
    pub intrinsics: PathBuf,
    /// Kalibr aprilgrid target yaml.
    #[arg(long)]
    pub target: PathBuf,
    /// Result folder (calibration.json, camchain-imucam.yaml, cam_imu.json, report.md, plots);
    /// an existing calibration.json there is never overwritten.
    #[arg(long)]
    pub out: PathBuf,
    /// Use every N-th frame (1 = all).
    #[arg(long, default_value_t = 1)]
    pub frame_step: usize,
    /// Detect the board from scratch in a keyframe this often (seconds) and track it in the
    /// frames between (gyro-aided prediction + sub-pixel refinement); 0 detects in every frame.
    #[arg(long, default_value_t = super::DEFAULT_KEYFRAME_INTERVAL_S, value_parser = kiwi_core::args::non_negative)]
    pub keyframe_interval: f64,
    /// Starting guess of the time shift in seconds (t_imu = t_cam + shift).
    #[arg(long, default_value_t = 0.0)]
    pub time_shift_guess: f64,
    /// Half-width of the coarse time-shift search in seconds.
    #[arg(long, default_value_t = 0.25, value_parser = kiwi_core::args::positive)]
    pub search_window: f64,
    /// Knot spacing of the trajectory spline in seconds.
    #[arg(long, default_value_t = 0.02, value_parser = kiwi_core::args::positive)]
    pub knot_spacing: f64,
    /// Rolling-shutter readout of a full frame in seconds (default: the calibration's mode).
    #[arg(long, value_parser = kiwi_core::args::non_negative)]
    pub readout: Option<f64>,
    /// Gravity magnitude in m/s².
    #[arg(long, default_value_t = super::DEFAULT_GRAVITY, value_parser = kiwi_core::args::positive)]
    pub gravity: f64,
    /// Print the per-lens JSON summary.
    #[arg(long)]
    pub json: bool,
}

fn bad_arg(path: &Path, message: &str) -> CalibError {
    CalibError::Input {
        path: path.to_path_buf(),
        message: message.to_owned(),
    }
}

/// Run `kiwi-calib cam-imu`; returns the result and the files written.
pub fn run(args: &CamImuArgs) -> Result<(CamImuResult, WrittenFiles)> {
    if args.frame_step == 0 {
        return Err(bad_arg(&args.capture, "--frame-step must be at least 1"));
    }
    if !(args.knot_spacing > 0.001 && args.knot_spacing <= 0.2) {
        return Err(bad_arg(
            &args.capture,
            "--knot-spacing must be in (0.001, 0.2] s; 0.02 s suits hand-held motion",
        ));
    }
    if !(0.0..=2.0).contains(&args.keyframe_interval) {
        return Err(bad_arg(
            &args.capture,
            "--keyframe-interval must be in [0, 2] s (0 detects in every frame)",
        ));
    }
    if !(args.search_window > 0.0 && args.search_window <= 5.0) {
        return Err(bad_arg(
            &args.capture,
            "--search-window must be in (0, 5] s (0.25 s covers every camera we know)",
        ));
    }
    if !(args.gravity > 9.7 && args.gravity < 9.9) {
        return Err(bad_arg(
            &args.capture,
            "--gravity is in m/s² and must be in (9.7, 9.9)",
        ));
    }
    let guard = args.out.join("calibration.json");
    if guard.exists() {
        return Err(bad_arg(
            &guard,
            "exists and is never overwritten; choose another --out folder",
        ));
    }
    let mut o = CamImuOptions::new(&args.capture, &args.intrinsics, &args.target);
    o.frame_step = args.frame_step;
    o.keyframe_interval_s = args.keyframe_interval;
    o.time_shift_guess_s = args.time_shift_guess;
    o.search_window_s = args.search_window;
    o.knot_spacing_s = args.knot_spacing;
    o.readout_s = args.readout;
    o.gravity_m_s2 = args.gravity;
    o.progress = !args.json;
    let result = calibrate(&o)?;
    let files = write_outputs(&result, &args.out)?;
    Ok((result, files))
}

/// The `--json` summary: per lens `{rotation_deg, translation_m, time_shift_s, rms_px}` plus
/// standard deviations.
pub fn summary_json(result: &CamImuResult) -> serde_json::Value {
    let mut lenses = serde_json::Map::new();
    for l in &result.lenses {
        lenses.insert(
            l.name.clone(),
            serde_json::json!({
                "rotation_deg": l.rotation_deg,
                "translation_m": l.translation_m,
                "time_shift_s": l.time_shift_s,
                "rms_px": l.rms_px,
                "rotation_std_deg": l.rotation_std_deg,
                "translation_std_m": l.translation_std_m,
                "time_shift_std_s": l.time_shift_std_s,
            }),
        );
    }
    serde_json::Value::Object(lenses)
}

/// Write every output into `out` (atomically, file by file).
pub fn write_outputs(result: &CamImuResult, out: &Path) -> Result<WrittenFiles> {
    std::fs::create_dir_all(out).map_err(|e| {
        CalibError::Core(kiwi_core::CoreError::Io {
            action: "creating",
            path: out.to_path_buf(),
            source: e,
        })
    })?;
    let mut cal = result.calibration.clone();
    cal.provenance.tool = "kiwi-calib cam-imu".into();
    cal.provenance.tool_version = env!("CARGO_PKG_VERSION").into();
    cal.provenance.created_utc = utc_now_rfc3339();
    for path in &result.inputs {
        cal.provenance.inputs.push(InputRecord {
            path: path.display().to_string(),
            sha256: sha256_file(path)?,
        });
    }
    let calibration = out.join("calibration.json");
    if calibration.exists() {
        return Err(bad_arg(
            &calibration,
            "exists and is never overwritten; choose another --out folder",
        ));
    }
    let camchain_imucam = out.join("camchain-imucam.yaml");
    write_atomic(
        &camchain_imucam,
        kiwi_core::kalibr::camchain_yaml(&cal).as_bytes(),
    )?;
    let result_path = out.join("cam_imu.json");
    let json = serde_json::to_string_pretty(result)
        .map_err(|e| CalibError::Internal(format!("serializing the result: {e}")))?;
    write_atomic(&result_path, json.as_bytes())?;
    let plots = write_plots(result, out)?;
    let report = out.join("report.md");
    write_atomic(&report, markdown(result, &plots, out).as_bytes())?;
    // The artifact last: its presence means the set is complete.
    cal.save(&calibration)?;
    Ok(WrittenFiles {
        calibration,
        camchain_imucam,
        result: result_path,
        report,
        plots,
    })
}

fn write_plots(result: &CamImuResult, out: &Path) -> Result<Vec<PathBuf>> {
    let mut files = Vec::new();
    let p = &result.plots;
    let mut fig = Chart::new(
        1200,
        500,
        "Corner reprojection error over time",
        Axis::new("time (s, camera clock)"),
        Axis::new("|residual| (px)"),
    );
    for (l, lens) in result.lenses.iter().enumerate() {
        let pts = p.corner_residuals.get(l).map_or(&[][..], Vec::as_slice);
        fig.series.push(Series {
            name: lens.name.clone(),
            color: LENS_COLORS[l % LENS_COLORS.len()],
            mark: Mark::Points(1),
            points: decimate(pts, MAX_PLOTTED_CORNERS),
        });
    }
    let path = out.join("reprojection_time.svg");
    fig.save_svg(&path)?;
    files.push(path);

    let lim = 4.0 * result.pixel_sigma.max(0.1);
    let mut fig = Chart::new(
        700,
        700,
        "Corner residuals",
        Axis::new("du (px)").with_range(-lim, lim),
        Axis::new("dv (px)").with_range(-lim, lim),
    );
    for (l, lens) in result.lenses.iter().enumerate() {
        let pts = p.corner_vectors.get(l).map_or(&[][..], Vec::as_slice);
        fig.series.push(Series {
            name: lens.name.clone(),
            color: LENS_COLORS[l % LENS_COLORS.len()],
            mark: Mark::Points(1),
            points: decimate(pts, MAX_PLOTTED_CORNERS),
        });
    }
    let path = out.join("reprojection_scatter.svg");
    fig.save_svg(&path)?;
    files.push(path);

    let mut fig = Chart::new(
        1200,
        500,
        "IMU residuals (after the fit)",
        Axis::new("time (s, IMU clock)"),
        Axis::new("|gyro| (rad/s ×100), |accel| (m/s²)"),
    );
    fig.series.push(Series {
        name: "gyro x100".into(),
        color: PALETTE[0],
        mark: Mark::Line(1),
        points: p.imu_residuals.iter().map(|r| (r.0, 100.0 * r.1)).collect(),
    });
    fig.series.push(Series {
        name: "accel".into(),
        color: PALETTE[1],
        mark: Mark::Line(1),
        points: p.imu_residuals.iter().map(|r| (r.0, r.2)).collect(),
    });
    let path = out.join("imu_residuals.svg");
    fig.save_svg(&path)?;
    files.push(path);

    let mut fig = Chart::new(
        1200,
        500,
        "Angular rate: camera (from board poses) vs gyro, aligned",
        Axis::new("time (s, camera clock)"),
        Axis::new("|rate| (rad/s)"),
    );
    if let Some(rates) = p.rates.first() {
        let t0 = rates.first().map_or(0.0, |r| r.0);
        let window: Vec<_> = rates.iter().filter(|r| r.0 - t0 <= 10.0).collect();
        fig.series.push(Series {
            name: "gyro".into(),
            color: [120, 120, 120],
            mark: Mark::Line(2),
            points: window.iter().map(|r| (r.0, r.2)).collect(),
        });
        fig.series.push(Series {
            name: format!("camera ({})", result.lenses[0].name),
            color: LENS_COLORS[0],
            mark: Mark::Points(2),
            points: window.iter().map(|r| (r.0, r.1)).collect(),
        });
    }
    let path = out.join("rates.svg");
    fig.save_svg(&path)?;
    files.push(path);
    Ok(files)
}

fn v3(v: &[f64; 3], scale: f64, digits: usize) -> String {
    format!(
        "[{:.d$}, {:.d$}, {:.d$}]",
        v[0] * scale,
        v[1] * scale,
        v[2] * scale,
        d = digits
    )
}

fn markdown(result: &CamImuResult, plots: &[PathBuf], out: &Path) -> String {
    let mut s = String::new();
    let _ = writeln!(s, "# Camera–IMU calibration of unit {}\n", result.unit_id);
    let _ = writeln!(
        s,
        "Convention: `cam_from_imu` maps IMU coordinates into the camera frame; the time shift \
         is Kalibr's, `t_imu = t_cam + time_shift_s`. Standard deviations (1σ) come from the \
         inverse Hessian scaled by the residual variance factor {:.3}.\n",
        result.variance_factor
    );
    let _ = writeln!(
        s,
        "| lens | rotation (axis-angle, deg) | ±1σ (deg) | translation (mm) | ±1σ (mm) | time shift (ms) | ±1σ (ms) | RMS (px) |"
    );
    let _ = writeln!(s, "|---|---|---|---|---|---|---|---|");
    for l in &result.lenses {
        let _ = writeln!(
            s,
            "| {} | {} | {} | {} | {} | {:.3} | {:.4} | {:.3} |",
            l.name,
            v3(&l.rotation_deg, 1.0, 3),
            v3(&l.rotation_std_deg, 1.0, 4),
            v3(&l.translation_m, 1e3, 2),
            v3(&l.translation_std_m, 1e3, 3),
            l.time_shift_s * 1e3,
            l.time_shift_std_s * 1e3,
            l.rms_px
        );
    }
    for p in &result.lens_pairs {
        let _ = writeln!(
            s,
            "\nLens-to-lens extrinsic composed through the IMU, `{}`: rotation {} deg (±{}), \
             translation {} mm (±{}); time shift difference {:.3} ms.",
            p.name,
            v3(&p.rotation_deg, 1.0, 3),
            v3(&p.rotation_std_deg, 1.0, 4),
            v3(&p.translation_m, 1e3, 2),
            v3(&p.translation_std_m, 1e3, 3),
            p.time_shift_difference_s * 1e3
        );
    }
    let _ = writeln!(s, "\n## Data\n");
    let _ = writeln!(
        s,
        "| lens | frames | used | accepted | corners | rejected corners | coarse shift (ms) | rate correlation | RMS rate (rad/s) |"
    );
    let _ = writeln!(s, "|---|---|---|---|---|---|---|---|---|");
    for l in &result.lenses {
        let _ = writeln!(
            s,
            "| {} | {} | {} | {} | {} | {} | {:.2} | {:.3} | {:.2} |",
            l.name,
            l.frames_total,
            l.frames_used,
            l.frames_accepted,
            l.corners,
            l.corners_rejected,
            l.coarse_time_shift_s * 1e3,
            l.correlation,
            l.rotation_rate_rms
        );
    }
    let _ = writeln!(
        s,
        "\nGravity in the first board's frame {} m/s²; mean gyro bias {} rad/s; mean \
         accelerometer bias {} m/s². RMS residuals: gyro {:.2e} rad/s, accelerometer {:.2e} m/s², \
         corner noise {:.3} px. Rolling-shutter readout {:.2} ms ({}); IMU noise: {}. \
         {} Levenberg–Marquardt iterations; wall time {:.1} s detection, {:.1} s \
         initialisation, {:.1} s batch.",
        v3(&result.gravity, 1.0, 4),
        v3(&result.gyro_bias, 1.0, 5),
        v3(&result.accel_bias, 1.0, 4),
        result.gyro_rms,
        result.accel_rms,
        result.pixel_sigma,
        result.readout_s * 1e3,
        result.readout_source,
        result.imu_noise_source,
        result.iterations,
        result.seconds.detection,
        result.seconds.initialisation,
        result.seconds.batch
    );
    let _ = writeln!(s, "\n## Plots\n");
    for p in plots {
        let name = p.strip_prefix(out).unwrap_or(p).display().to_string();
        let _ = writeln!(s, "![{name}]({name})\n");
    }
    s
}
