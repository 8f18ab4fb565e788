//! `kiwi-calib certify`: one command from a unit's capture folder to a dated, certified artifact
//! set — or a failed one that names the failed checks.
//!
//! The steps run in order, each reusing the earlier ones' outputs: intrinsics per lens, IMU noise
//! from the static log, camera–IMU per lens (needs the intrinsics and uses the noise model), A/V
//! delay per recording mode (uses the lens model to rectify the QR code and the modes' readout
//! times). Every step's figures become checks against the [`policy::Policy`]; a step whose input
//! is missing or that cannot run becomes a failed check with the reason, and the steps that need
//! it are skipped. The set is assembled in a temporary folder beside its final place and renamed
//! into `units/<id>/<YYYY-MM-DD>[-N]/` at the end, so no half-written set is ever visible and no
//! earlier set is ever overwritten. The capture layout is documented in docs/certify.md.

pub mod cli;
pub mod compare;
pub mod policy;
pub mod report;

use std::path::{Path, PathBuf};
use std::time::Instant;

use indicatif::{ProgressBar, ProgressStyle};
use serde::{Deserialize, Serialize};

use kiwi_core::artifact::{
    AvDelay, Certification, Check, ImuNoise, InputRecord, LensCalibration, Provenance,
    RecordingMode, SCHEMA_VERSION, UnitCalibration,
};
use kiwi_core::camera::{CameraModel, CameraModelKind};
use kiwi_core::io::{sha256_file, utc_now_rfc3339, utc_today, write_atomic};

use crate::allan::{AllanOptions, NoiseReport, StaticLog};
use crate::av_delay::{AvDelayOptions, CaptureResult};
use crate::cam_imu::{CamImuOptions, CamImuResult};
use crate::detect::{DetectOptions, detect_folder};
use crate::error::{CalibError, Result};
use crate::intrinsics::{IntrinsicsOptions, IntrinsicsResult, MIN_CORNERS_PER_VIEW};
use crate::target::AprilGridTarget;

use compare::Comparison;
use policy::Policy;

/// Coverage grid cells per image side.
const COVERAGE_CELLS: u32 = 8;
/// Length of the windows whose means detect motion in a static log (s), as `imu-noise`.
const MOTION_WINDOW_S: f64 = 1.0;
/// Half-width of the rolling median the window means are compared with (windows): ±30 s.
const MOTION_MEDIAN_HALF: usize = 30;
/// Two chirp onsets are one rig period apart within this (s): the rig's clock is exact and an
/// onset resolves to ~20 µs, so 5 ms only admits chirps and rejects random room sounds.
const CHIRP_PERIOD_TOLERANCE_S: f64 = 0.005;

/// What the capture folder says the unit is (`unit.toml`).
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct UnitInfo {
    /// The unit's id (must match `--unit`).
    pub unit_id: String,
    /// Camera product.
    pub camera_model: String,
    /// Firmware version the unit runs.
    pub firmware: String,
    /// Projection model to fit: `kb4` (default) or `double_sphere`.
    #[serde(default = "default_lens_model")]
    pub lens_model: String,
    /// Frame of the IMU axes (free text, stored in the artifact).
    #[serde(default = "default_axis_convention")]
    pub axis_convention: String,
    /// Recording modes with their datasheet readout times.
    #[serde(default)]
    pub recording_modes: Vec<RecordingMode>,
    /// Refresh rate of the QR-clock rig's monitor (Hz).
    #[serde(default = "default_rig_refresh_hz")]
    pub rig_refresh_hz: f64,
}

fn default_rig_refresh_hz() -> f64 {
    60.0
}

fn default_lens_model() -> String {
    "kb4".into()
}

fn default_axis_convention() -> String {
    "imu".into()
}

impl UnitInfo {
    /// Read and check `unit.toml`.
    pub fn load(path: &Path) -> Result<Self> {
        let text = kiwi_core::io::read_text(path).map_err(|_| CalibError::Input {
            path: path.to_path_buf(),
            message: "missing: the capture folder needs a unit.toml naming the unit (unit_id, \
                      camera_model, firmware, recording_modes with readout_time_s); see \
                      docs/certify.md"
                .into(),
        })?;
        let info: Self = toml::from_str(&text).map_err(|e| CalibError::Input {
            path: path.to_path_buf(),
            message: format!("not a unit description: {e}; see docs/certify.md"),
        })?;
        if !matches!(info.lens_model.as_str(), "kb4" | "double_sphere") {
            return Err(CalibError::Input {
                path: path.to_path_buf(),
                message: format!(
                    "lens_model: expected `kb4` or `double_sphere`, found `{}`",
                    info.lens_model
                ),
            });
        }
        Ok(info)
    }
}

/// Options of a certification run.
#[derive(Debug, Clone)]
pub struct CertifyOptions {
    /// The unit id (must match the captures' `unit.toml`).
    pub unit_id: String,
    /// The capture folder.
    pub captures: PathBuf,
    /// The units root (`units/`): the set goes to `units/<id>/<date>[-N]/`.
    pub units_dir: PathBuf,
    /// Thresholds.
    pub policy: Policy,
    /// An earlier set of the unit to compare with (its folder).
    pub previous: Option<PathBuf>,
    /// Certification date `YYYY-MM-DD` (default: today, UTC).
    pub date: Option<String>,
    /// Show the progress display on stderr.
    pub progress: bool,
}

/// How a step ended.
#[derive(Debug, Clone, Serialize)]
pub struct StepStatus {
    /// Step name: `intrinsics.front`, `imu_noise`, `cam_imu`, `av_delay`.
    pub step: String,
    /// `passed`, `failed` or `skipped`.
    pub status: String,
    /// Why it failed or was skipped (the step's own error message where it had one).
    pub note: Option<String>,
    /// Wall time (s).
    pub seconds: f64,
}

/// A check with the step it belongs to and a note (the artifact keeps name/value/threshold).
#[derive(Debug, Clone, Serialize)]
pub struct CheckRecord {
    /// The check.
    #[serde(flatten)]
    pub check: Check,
    /// Unit of value and threshold.
    pub unit: String,
    /// Why it failed, when the value alone does not say.
    pub note: Option<String>,
}

/// The outcome of a certification: verdict, checks, steps, where it was written.
#[derive(Debug, Clone, Serialize)]
pub struct CertifyReport {
    /// Unit id.
    pub unit_id: String,
    /// Certification date.
    pub date: String,
    /// The set's folder.
    pub folder: PathBuf,
    /// True when every check passed.
    pub passed: bool,
    /// Names of the failed checks.
    pub failed_checks: Vec<String>,
    /// Every check.
    pub checks: Vec<CheckRecord>,
    /// Every step.
    pub steps: Vec<StepStatus>,
    /// Comparison with `--previous`.
    pub comparison: Option<Comparison>,
    /// Files of the set, relative to its folder.
    pub files: Vec<String>,
    /// Wall time of the whole run (s).
    pub seconds: f64,
    /// The calibration written (absent when no lens could be calibrated).
    #[serde(skip)]
    pub calibration: Option<UnitCalibration>,
}

/// Collects checks and step statuses as the run goes.
struct Ledger {
    checks: Vec<CheckRecord>,
    steps: Vec<StepStatus>,
}

impl Ledger {
    fn check(&mut self, name: &str, value: f64, threshold: f64, at_most: bool, unit: &str) -> bool {
        let passed = value.is_finite()
            && if at_most {
                value <= threshold
            } else {
                value >= threshold
            };
        self.checks.push(CheckRecord {
            check: Check {
                name: name.into(),
                // The artifact stores finite numbers only; a value that could not be measured
                // is stored as the failing extreme and explained in the note.
                value: if value.is_finite() {
                    value
                } else if at_most {
                    f64::MAX
                } else {
                    0.0
                },
                threshold,
                comparison: if at_most { "at_most" } else { "at_least" }.into(),
                passed,
            },
            unit: unit.into(),
            note: (!value.is_finite()).then(|| "could not be measured".to_string()),
        });
        passed
    }

    /// A step that could not produce its figures: one failed check `<name>` (0 of 1) with
    /// the reason.
    fn failure(&mut self, name: &str, note: String) {
        self.checks.push(CheckRecord {
            check: Check {
                name: name.into(),
                value: 0.0,
                threshold: 1.0,
                comparison: "at_least".into(),
                passed: false,
            },
            unit: String::new(),
            note: Some(note),
        });
    }

    fn note_last(&mut self, note: String) {
        if let Some(c) = self.checks.last_mut() {
            c.note = Some(note);
        }
    }

    fn step(&mut self, step: &str, passed: bool, note: Option<String>, started: Instant) {
        self.steps.push(StepStatus {
            step: step.into(),
            status: if passed { "passed" } else { "failed" }.into(),
            note,
            seconds: started.elapsed().as_secs_f64(),
        });
    }

    fn skip(&mut self, step: &str, note: String) {
        self.steps.push(StepStatus {
            step: step.into(),
            status: "skipped".into(),
            note: Some(note),
            seconds: 0.0,
        });
    }

    fn failed_since(&self, start: usize) -> bool {
        self.checks[start..].iter().any(|c| !c.check.passed)
    }
}

/// Step outputs the report page shows.
#[derive(Debug, Default)]
pub struct StepOutputs {
    /// Per lens: the intrinsics result and its report folder (relative to `report/`).
    pub intrinsics: Vec<(String, IntrinsicsResult, String)>,
    /// The IMU noise result.
    pub imu_noise: Option<NoiseReport>,
    /// The camera–IMU result.
    pub cam_imu: Option<CamImuResult>,
    /// Analysed rig captures.
    pub av_delay: Option<crate::av_delay::AvDelayReport>,
}

fn io_error(action: &'static str, path: &Path, source: std::io::Error) -> CalibError {
    CalibError::Core(kiwi_core::CoreError::Io {
        action,
        path: path.to_path_buf(),
        source,
    })
}

/// Lens folders under `intrinsics/`, front first then rear then the rest by name.
fn lens_folders(dir: &Path) -> Vec<(String, PathBuf)> {
    let mut lenses: Vec<(String, PathBuf)> = std::fs::read_dir(dir)
        .map(|entries| {
            entries
                .filter_map(std::result::Result::ok)
                .filter(|e| e.path().is_dir())
                .filter(|e| {
                    // A lens folder without images is no capture (e.g. a unit without views).
                    let p = e.path();
                    let images = if p.join("frames").is_dir() {
                        p.join("frames")
                    } else {
                        p
                    };
                    crate::detect::list_images(&images).is_ok_and(|v| !v.is_empty())
                })
                .map(|e| (e.file_name().to_string_lossy().into_owned(), e.path()))
                .collect()
        })
        .unwrap_or_default();
    let rank = |n: &str| match n {
        "front" => 0,
        "rear" => 1,
        _ => 2,
    };
    lenses.sort_by(|a, b| rank(&a.0).cmp(&rank(&b.0)).then(a.0.cmp(&b.0)));
    lenses
}

/// Every camera folder (with `meta.json`) below `dir`, skipping `truth/` folders, sorted.
pub fn rig_captures(dir: &Path) -> Vec<PathBuf> {
    fn walk(dir: &Path, depth: usize, out: &mut Vec<PathBuf>) {
        if dir.join("meta.json").is_file() {
            out.push(dir.to_path_buf());
            return;
        }
        if depth == 0 {
            return;
        }
        if let Ok(entries) = std::fs::read_dir(dir) {
            for e in entries.filter_map(std::result::Result::ok) {
                let p = e.path();
                if p.is_dir() && e.file_name() != "truth" {
                    walk(&p, depth - 1, out);
                }
            }
        }
    }
    let mut out = Vec::new();
    walk(dir, 4, &mut out);
    out.sort();
    out
}

/// Share of the coverage cells inside the lens's image circle that hold a used corner.
pub fn coverage(result: &IntrinsicsResult) -> f64 {
    let camera = &result.camera;
    let (w, h) = camera.resolution();
    let half_fov = camera.valid_fov() / 2.0;
    let cell = |x: f64, y: f64| {
        let cx = ((x + 0.5) / f64::from(w) * f64::from(COVERAGE_CELLS)).floor();
        let cy = ((y + 0.5) / f64::from(h) * f64::from(COVERAGE_CELLS)).floor();
        (cx >= 0.0 && cy >= 0.0 && cx < f64::from(COVERAGE_CELLS) && cy < f64::from(COVERAGE_CELLS))
            .then(|| (cy as u32 * COVERAGE_CELLS + cx as u32) as usize)
    };
    let n = (COVERAGE_CELLS * COVERAGE_CELLS) as usize;
    let mut inside = vec![false; n];
    for j in 0..COVERAGE_CELLS {
        for i in 0..COVERAGE_CELLS {
            let x = (f64::from(i) + 0.5) / f64::from(COVERAGE_CELLS) * f64::from(w) - 0.5;
            let y = (f64::from(j) + 0.5) / f64::from(COVERAGE_CELLS) * f64::from(h) - 0.5;
            inside[(j * COVERAGE_CELLS + i) as usize] = camera
                .unproject(&nalgebra::Point2::new(x, y))
                .is_some_and(|b| b.z.clamp(-1.0, 1.0).acos() <= half_fov);
        }
    }
    let mut hit = vec![false; n];
    for r in &result.residuals {
        if let Some(k) = cell(r.pixel[0], r.pixel[1]) {
            hit[k] = true;
        }
    }
    let total = inside.iter().filter(|&&b| b).count();
    let covered = inside.iter().zip(&hit).filter(|(a, b)| **a && **b).count();
    if total == 0 {
        0.0
    } else {
        covered as f64 / total as f64
    }
}

/// Largest deviation of 1-s window means from their ±30 s rolling median: gyro (rad/s) and
/// accelerometer (m/s²), with the time (s) of the worst window.
pub fn static_motion(log: &StaticLog) -> ([f64; 2], f64) {
    let window = ((MOTION_WINDOW_S * log.rate_hz).round() as usize).max(1);
    let mut worst = [0.0f64; 2];
    let mut at = [0usize; 2];
    for (a, axis) in log.axes.iter().enumerate() {
        let means: Vec<f64> = axis
            .chunks_exact(window)
            .map(|c| c.iter().sum::<f64>() / c.len() as f64)
            .collect();
        let mut buf = Vec::with_capacity(2 * MOTION_MEDIAN_HALF + 1);
        for k in 0..means.len() {
            buf.clear();
            let lo = k.saturating_sub(MOTION_MEDIAN_HALF);
            let hi = (k + MOTION_MEDIAN_HALF + 1).min(means.len());
            buf.extend_from_slice(&means[lo..hi]);
            buf.sort_by(f64::total_cmp);
            let d = (means[k] - buf[buf.len() / 2]).abs();
            let s = usize::from(a >= 3);
            if d > worst[s] {
                worst[s] = d;
                at[s] = k;
            }
        }
    }
    let k = if worst[0] / 0.02 >= worst[1] / 0.1 {
        at[0]
    } else {
        at[1]
    };
    (
        worst,
        log.time_range.0 + (k as f64 + 0.5) * window as f64 / log.rate_hz,
    )
}

/// Rig chirps heard in a capture's audio: onsets with another onset one chirp period away.
pub fn periodic_chirps(audio_path: &Path) -> Result<usize> {
    let audio = kiwi_core::audio::read_audio(audio_path)?;
    let onsets = crate::av_delay::detect_chirps(&audio.samples, audio.rate_hz);
    let period = kiwi_core::rig::CHIRP_PERIOD_S;
    Ok(onsets
        .iter()
        .filter(|&&t| {
            onsets
                .iter()
                .any(|&u| ((u - t).abs() - period).abs() < CHIRP_PERIOD_TOLERANCE_S)
        })
        .count())
}

fn rel_std(value: f64, std: f64) -> f64 {
    if value.abs() > 0.0 {
        std / value.abs()
    } else {
        f64::INFINITY
    }
}

fn max3(v: &[f64; 3]) -> f64 {
    v.iter().copied().fold(0.0, f64::max)
}

fn progress_bar(show: bool, steps: u64) -> ProgressBar {
    if !show {
        return ProgressBar::hidden();
    }
    let bar = ProgressBar::new(steps);
    if let Ok(style) =
        ProgressStyle::with_template("certify {bar:30} {pos}/{len} steps {elapsed_precise} {msg}")
    {
        bar.set_style(style);
    }
    bar.enable_steady_tick(std::time::Duration::from_millis(500));
    bar
}

/// Certify a unit: run every step, write the set, return the verdict.
pub fn certify(o: &CertifyOptions) -> Result<CertifyReport> {
    let started = Instant::now();
    // The options first: a wrong --date fails before any capture is read.
    let date = o.date.clone().unwrap_or_else(utc_today);
    kiwi_core::artifact::validate_date(&date).map_err(|e| CalibError::Input {
        path: o.captures.clone(),
        message: format!("--date: {e}"),
    })?;
    let info = UnitInfo::load(&o.captures.join("unit.toml"))?;
    if info.unit_id != o.unit_id {
        return Err(CalibError::Input {
            path: o.captures.join("unit.toml"),
            message: format!(
                "the captures are of unit `{}`, not `{}`; check --unit and --captures",
                info.unit_id, o.unit_id
            ),
        });
    }
    if o.unit_id.trim().is_empty() || o.unit_id.contains(['/', '\\']) || o.unit_id.starts_with('.')
    {
        return Err(CalibError::Input {
            path: o.captures.join("unit.toml"),
            message: format!(
                "unit_id `{}` cannot name a folder; use the serial number",
                o.unit_id
            ),
        });
    }
    let previous = match &o.previous {
        Some(dir) => {
            let path = if dir.is_dir() {
                dir.join("calibration.json")
            } else {
                dir.clone()
            };
            Some((dir.clone(), UnitCalibration::load(&path)?))
        }
        None => None,
    };
    let unit_root = o.units_dir.join(&o.unit_id);
    // Claim the dated folder first (atomic: a concurrent run gets the next name), assemble the
    // set beside it, and rename it onto the empty claimed folder at the end.
    let folder = kiwi_core::io::create_dated_dir(&unit_root, &date)?;
    let set_name = folder
        .file_name()
        .map_or_else(String::new, |n| n.to_string_lossy().into_owned());
    let result = report::create_work_dir(&unit_root, &set_name).and_then(|work| {
        let steps = std::fs::create_dir(work.join("report"))
            .map_err(|e| io_error("creating", &work, e))
            .and_then(|()| run_steps(o, &info, &date, &work, &folder, previous.as_ref(), started));
        match steps {
            Ok(report) => Ok((work, report)),
            Err(e) => {
                let _ = std::fs::remove_dir_all(&work);
                Err(e)
            }
        }
    });
    match result {
        Ok((work, mut report)) => {
            std::fs::rename(&work, &folder).map_err(|e| io_error("renaming", &work, e))?;
            report.seconds = started.elapsed().as_secs_f64();
            Ok(report)
        }
        Err(e) => {
            let _ = std::fs::remove_dir(&folder);
            Err(e)
        }
    }
}

fn run_steps(
    o: &CertifyOptions,
    info: &UnitInfo,
    date: &str,
    work: &Path,
    folder: &Path,
    previous: Option<&(PathBuf, UnitCalibration)>,
    started: Instant,
) -> Result<CertifyReport> {
    let p = &o.policy;
    let cap = &o.captures;
    let report_dir = work.join("report");
    let lenses_found = lens_folders(&cap.join("intrinsics"));
    let rigs = rig_captures(&cap.join("qr_rig"));
    let bar = progress_bar(
        o.progress,
        (lenses_found.len().max(1) + 3 + rigs.len()) as u64,
    );
    let mut ledger = Ledger {
        checks: Vec::new(),
        steps: Vec::new(),
    };
    let mut outputs = StepOutputs::default();
    let mut inputs: Vec<PathBuf> = vec![cap.join("unit.toml")];

    // Target.
    let target_path = cap.join("target.yaml");
    let target = AprilGridTarget::load(&target_path);
    if target.is_ok() {
        inputs.push(target_path.clone());
    }

    // 1. Intrinsics per lens.
    let mut lenses: Vec<LensCalibration> = Vec::new();
    let mut intrinsics_ok = !lenses_found.is_empty();
    if lenses_found.is_empty() {
        ledger.failure(
            "intrinsics.captures",
            format!(
                "no lens folders in {}: expected intrinsics/<lens>/ with frames.csv and the \
                 aprilgrid images",
                cap.join("intrinsics").display()
            ),
        );
        ledger.step(
            "intrinsics",
            false,
            Some("no captures".into()),
            Instant::now(),
        );
        bar.inc(1);
    }
    for (lens, dir) in &lenses_found {
        let t0 = Instant::now();
        let step = format!("intrinsics.{lens}");
        bar.set_message(format!(
            "intrinsics of the {lens} lens: detecting the board"
        ));
        let first = ledger.checks.len();
        let target = match &target {
            Ok(t) => *t,
            Err(e) => {
                ledger.failure(&format!("{lens}.target"), e.to_string());
                ledger.step(&step, false, Some(e.to_string()), t0);
                intrinsics_ok = false;
                bar.inc(1);
                continue;
            }
        };
        let frames_csv = dir.join("frames.csv");
        if frames_csv.is_file() {
            inputs.push(frames_csv);
        }
        let image_dir = if dir.join("frames").is_dir() {
            dir.join("frames")
        } else {
            dir.clone()
        };
        let set = match detect_folder(
            &image_dir,
            &target,
            &DetectOptions {
                progress: false,
                ..DetectOptions::default()
            },
        ) {
            Ok(s) => s,
            Err(e) => {
                ledger.check(
                    &format!("{lens}.views"),
                    0.0,
                    p.intrinsics.min_views as f64,
                    false,
                    "views",
                );
                ledger.note_last(e.to_string());
                ledger.step(&step, false, Some(e.to_string()), t0);
                intrinsics_ok = false;
                bar.inc(1);
                continue;
            }
        };
        let views = set
            .images
            .iter()
            .filter(|i| i.corners.len() >= MIN_CORNERS_PER_VIEW)
            .count();
        if !ledger.check(
            &format!("{lens}.views"),
            views as f64,
            p.intrinsics.min_views as f64,
            false,
            "views",
        ) {
            ledger.note_last(format!(
                "{views} images show the board with at least {MIN_CORNERS_PER_VIEW} corners; \
                 record more views spread over the whole field of view"
            ));
            ledger.step(&step, false, Some("too few views".into()), t0);
            intrinsics_ok = false;
            bar.inc(1);
            continue;
        }
        bar.set_message(format!("intrinsics of the {lens} lens: fitting"));
        let options = IntrinsicsOptions {
            model: if info.lens_model == "double_sphere" {
                CameraModelKind::DoubleSphere
            } else {
                CameraModelKind::Kb4
            },
            lens_name: lens.clone(),
            check_coverage: false,
        };
        let result = match crate::intrinsics::calibrate(&set, &options) {
            Ok(r) => r,
            Err(e) => {
                ledger.failure(&format!("{lens}.intrinsics_fit"), e.to_string());
                ledger.step(&step, false, Some(e.to_string()), t0);
                intrinsics_ok = false;
                bar.inc(1);
                continue;
            }
        };
        let pi = &p.intrinsics;
        ledger.check(
            &format!("{lens}.rms_px"),
            result.rms_px,
            pi.max_rms_px,
            true,
            "px",
        );
        ledger.check(
            &format!("{lens}.coverage"),
            coverage(&result),
            pi.min_coverage,
            false,
            "",
        );
        let s = &result.param_std;
        ledger.check(
            &format!("{lens}.focal_rel_std"),
            rel_std(result.params[0], s[0]).max(rel_std(result.params[1], s[1])),
            pi.max_focal_rel_std,
            true,
            "",
        );
        ledger.check(
            &format!("{lens}.principal_point_std_px"),
            s[2].max(s[3]),
            pi.max_principal_point_std_px,
            true,
            "px",
        );
        let folder = format!("intrinsics-{lens}");
        crate::intrinsics::report::write_outputs(&result, lens, &report_dir.join(&folder))?;
        let mut lc = result.lens_calibration();
        lc.name.clone_from(lens);
        lenses.push(lc);
        let failed = ledger.failed_since(first);
        intrinsics_ok &= !failed;
        ledger.step(&step, !failed, None, t0);
        outputs.intrinsics.push((lens.clone(), result, folder));
        bar.inc(1);
    }

    // 2. IMU noise.
    let t0 = Instant::now();
    bar.set_message("IMU noise: reading the static log");
    let first = ledger.checks.len();
    let mut imu: Option<ImuNoise> = None;
    let static_path = cap.join("imu_static").join("imu.csv");
    if static_path.is_file() {
        inputs.push(static_path.clone());
        match crate::allan::read_static_log(&static_path, None) {
            Err(e) => {
                ledger.failure("imu.static_log", e.to_string());
                ledger.step("imu_noise", false, Some(e.to_string()), t0);
            }
            Ok(log) => {
                let pn = &p.imu_noise;
                ledger.check(
                    "imu.duration_s",
                    log.duration_s(),
                    pn.min_duration_s,
                    false,
                    "s",
                );
                let ([gyro, accel], at) = static_motion(&log);
                let still_g = ledger.check(
                    "imu.static_gyro_motion_rad_s",
                    gyro,
                    pn.max_gyro_motion_rad_s,
                    true,
                    "rad/s",
                );
                if !still_g {
                    ledger.note_last(format!(
                        "the IMU moved (worst 1-s window around t = {at:.1} s); record the log \
                         again without touching the unit, or cut it to its static part"
                    ));
                }
                let still_a = ledger.check(
                    "imu.static_accel_motion_m_s2",
                    accel,
                    pn.max_accel_motion_m_s2,
                    true,
                    "m/s²",
                );
                if !still_a {
                    ledger.note_last(format!(
                        "the IMU moved (worst 1-s window around t = {at:.1} s)"
                    ));
                }
                if still_g && still_a {
                    bar.set_message("IMU noise: Allan deviation and fit");
                    let options = AllanOptions {
                        require: Vec::new(),
                        ..AllanOptions::default()
                    };
                    match crate::allan::analyse(log, &options) {
                        Err(e) => ledger.failure("imu.allan_fit", e.to_string()),
                        Ok(report) => {
                            let worst = |f: &dyn Fn(&crate::allan::AxisReport) -> f64| {
                                report.axes.iter().map(f).fold(0.0, f64::max)
                            };
                            ledger.check(
                                "imu.white_noise_rel_std",
                                worst(&|a| rel_std(a.fit.white_noise.value, a.fit.white_noise.std)),
                                pn.max_white_noise_rel_std,
                                true,
                                "",
                            );
                            ledger.check(
                                "imu.random_walk_rel_std",
                                worst(&|a| rel_std(a.fit.random_walk.value, a.fit.random_walk.std)),
                                pn.max_random_walk_rel_std,
                                true,
                                "",
                            );
                            ledger.check(
                                "imu.fit_weighted_rms",
                                worst(&|a| a.fit.weighted_rms),
                                pn.max_fit_weighted_rms,
                                true,
                                "",
                            );
                            crate::allan::write_outputs(
                                &report,
                                &report_dir.join("imu_noise"),
                                None,
                                None,
                            )?;
                            imu =
                                Some(crate::allan::artifact_noise(&report, &info.axis_convention));
                            outputs.imu_noise = Some(report);
                        }
                    }
                }
                let failed = ledger.failed_since(first);
                ledger.step("imu_noise", !failed, None, t0);
            }
        }
    } else {
        ledger.failure(
            "imu.captures",
            format!("no static IMU log at {}", static_path.display()),
        );
        ledger.step("imu_noise", false, Some("no captures".into()), t0);
    }
    let imu_ok = !ledger.failed_since(first);
    bar.inc(1);

    // The calibration so far (what camera–IMU and A/V delay build on).
    let mut calibration = UnitCalibration {
        schema_version: SCHEMA_VERSION,
        unit_id: info.unit_id.clone(),
        camera_model: info.camera_model.clone(),
        firmware: info.firmware.clone(),
        date: date.into(),
        recording_modes: info.recording_modes.clone(),
        lenses,
        imu,
        av_delays: Vec::new(),
        provenance: Provenance {
            tool: "kiwi-calib certify".into(),
            tool_version: env!("CARGO_PKG_VERSION").into(),
            created_utc: utc_now_rfc3339(),
            inputs: Vec::new(),
        },
        certification: None,
    };

    // 3. Camera–IMU.
    let t0 = Instant::now();
    bar.set_message("camera–IMU: detecting, initialising, batch solve");
    let first = ledger.checks.len();
    let cam_imu_dir = cap.join("cam_imu");
    if !cam_imu_dir.join("meta.json").is_file() {
        ledger.failure(
            "cam_imu.captures",
            format!(
                "no excitation capture at {} (meta.json, imu.csv, <lens>/)",
                cam_imu_dir.display()
            ),
        );
        ledger.step("cam_imu", false, Some("no captures".into()), t0);
    } else if !intrinsics_ok || calibration.lenses.is_empty() {
        ledger.failure(
            "cam_imu.intrinsics",
            "camera–IMU needs every lens's intrinsics, which did not certify".into(),
        );
        ledger.skip("cam_imu", "needs the intrinsics of every lens".into());
    } else {
        let input = work.join("cam_imu_input.json");
        calibration.save(&input)?;
        // The excitation may use its own board (large tags survive motion blur).
        let own_target = cam_imu_dir.join("target.yaml");
        let cam_imu_target = if own_target.is_file() {
            inputs.push(own_target.clone());
            own_target
        } else {
            target_path.clone()
        };
        let mut co = CamImuOptions::new(&cam_imu_dir, &input, &cam_imu_target);
        co.progress = false;
        // The input is a staging file, gone once the set is made: name the set's own file.
        co.intrinsics_label = Some("this set's calibration.json (the imu_noise step)".into());
        if !imu_ok {
            tracing::warn!("IMU noise did not certify: camera–IMU uses default noise densities");
        }
        match crate::cam_imu::calibrate(&co) {
            Err(e) => {
                ledger.failure("cam_imu.fit", e.to_string());
                ledger.step("cam_imu", false, Some(e.to_string()), t0);
            }
            Ok(result) => {
                let pc = &p.cam_imu;
                for l in &result.lenses {
                    let n = &l.name;
                    ledger.check(
                        &format!("{n}.cam_imu_rms_px"),
                        l.rms_px,
                        pc.max_rms_px,
                        true,
                        "px",
                    );
                    ledger.check(
                        &format!("{n}.rotation_std_deg"),
                        max3(&l.rotation_std_deg),
                        pc.max_rotation_std_deg,
                        true,
                        "deg",
                    );
                    ledger.check(
                        &format!("{n}.translation_std_m"),
                        max3(&l.translation_std_m),
                        pc.max_translation_std_m,
                        true,
                        "m",
                    );
                    ledger.check(
                        &format!("{n}.time_shift_std_s"),
                        l.time_shift_std_s,
                        pc.max_time_shift_std_s,
                        true,
                        "s",
                    );
                    if let Some(lens) = calibration.lenses.iter_mut().find(|x| &x.name == n) {
                        lens.cam_from_imu = Some(kiwi_core::artifact::RigidTransform::from_pose(
                            &l.cam_from_imu,
                        ));
                        lens.time_shift_s = Some(l.time_shift_s);
                    }
                }
                for pair in &result.lens_pairs {
                    let nominal = compare::rotation_from_deg(&pc.nominal_pair_rotation_deg);
                    let measured = compare::rotation_from_deg(&pair.rotation_deg);
                    let dev = (nominal.inverse() * measured).angle().to_degrees();
                    ledger.check(
                        &format!("{}.rotation_deviation_deg", pair.name),
                        dev,
                        pc.max_pair_rotation_deviation_deg,
                        true,
                        "deg",
                    );
                    let t = nalgebra::Vector3::from(pair.translation_m)
                        - nalgebra::Vector3::from(pc.nominal_pair_translation_m);
                    ledger.check(
                        &format!("{}.translation_deviation_m", pair.name),
                        t.norm(),
                        pc.max_pair_translation_deviation_m,
                        true,
                        "m",
                    );
                }
                crate::cam_imu::report::write_outputs(&result, &report_dir.join("cam_imu"))?;
                // The step's own artifact copy is superseded by the set's calibration.json.
                let _ = std::fs::remove_file(report_dir.join("cam_imu").join("calibration.json"));
                for i in &result.inputs {
                    if !inputs.contains(i) {
                        inputs.push(i.clone());
                    }
                }
                let failed = ledger.failed_since(first);
                ledger.step("cam_imu", !failed, None, t0);
                outputs.cam_imu = Some(result);
            }
        }
        let _ = std::fs::remove_file(&input);
    }
    bar.inc(1);

    // 4. A/V delay per mode.
    let t0 = Instant::now();
    let first = ledger.checks.len();
    if rigs.is_empty() {
        ledger.failure(
            "av_delay.captures",
            format!(
                "no QR-clock rig recordings under {} (camera folders with meta.json)",
                cap.join("qr_rig").display()
            ),
        );
        ledger.step("av_delay", false, Some("no captures".into()), t0);
    } else {
        let options = AvDelayOptions {
            refresh_hz: info.rig_refresh_hz,
            speaker_distance_m: Vec::new(),
            calibrations: vec![(work.join("calibration.json"), calibration.clone())],
        };
        let mut results: Vec<CaptureResult> = Vec::new();
        let mut modes_seen: Vec<String> = Vec::new();
        for dir in &rigs {
            let name = dir
                .strip_prefix(cap.join("qr_rig"))
                .unwrap_or(dir)
                .display()
                .to_string()
                .replace('/', "-");
            bar.set_message(format!("A/V delay: rig recording {name}"));
            let meta = kiwi_core::layout::EpisodeLayout::new(dir.parent().unwrap_or(dir))
                .read_meta(
                    &dir.file_name()
                        .map_or_else(String::new, |n| n.to_string_lossy().into_owned()),
                );
            let mode = meta
                .as_ref()
                .map_or_else(|_| "unknown".to_string(), |m| m.mode.clone());
            if !modes_seen.contains(&mode) {
                modes_seen.push(mode.clone());
            }
            let audio = dir.join("audio.wav");
            inputs.push(audio.clone());
            let chirps = periodic_chirps(&audio);
            let heard = chirps.as_ref().map_or(0, |c| *c);
            if !ledger.check(
                &format!("av_delay.{mode}.{name}.chirps"),
                heard as f64,
                p.av_delay.min_chirps as f64,
                false,
                "chirps",
            ) {
                ledger.note_last(match &chirps {
                    Ok(_) => format!(
                        "{} holds {heard} rig chirps; was the rig's speaker on and audible?",
                        audio.display()
                    ),
                    Err(e) => e.to_string(),
                });
                bar.inc(1);
                continue;
            }
            let mut options = options.clone();
            // The rig's geometry (rig.toml) is read here too, so a bad file fails its own named
            // check rather than the whole analysis.
            match crate::av_delay::rig_speaker_distances(dir) {
                Ok(d) => options.speaker_distance_m = d,
                Err(e) => {
                    ledger.failure(
                        &format!("av_delay.{mode}.{name}.rig_geometry"),
                        e.to_string(),
                    );
                    bar.inc(1);
                    continue;
                }
            }
            match crate::av_delay::analyse_capture(dir, &options) {
                Ok(mut r) => {
                    r.name = name;
                    results.push(r);
                }
                Err(e) => {
                    ledger.failure(&format!("av_delay.{mode}.{name}.analysis"), e.to_string());
                }
            }
            bar.inc(1);
        }
        let summary = crate::av_delay::summarize(results);
        let pa = &p.av_delay;
        for mode in &modes_seen {
            let m = summary.modes.iter().find(|m| &m.mode == mode);
            let repeats = m.map_or(0, |m| m.repeats);
            ledger.check(
                &format!("av_delay.{mode}.repeats"),
                repeats as f64,
                pa.min_repeats as f64,
                false,
                "recordings",
            );
            if let Some(m) = m {
                ledger.check(
                    &format!("av_delay.{mode}.spread_s"),
                    m.spread_s,
                    pa.max_spread_s,
                    true,
                    "s",
                );
                ledger.check(
                    &format!("av_delay.{mode}.std_s"),
                    m.std_s,
                    pa.max_std_s,
                    true,
                    "s",
                );
                calibration.av_delays.push(AvDelay {
                    mode: m.mode.clone(),
                    delay_s: m.delay_s,
                    std_s: m.std_s,
                    repeats: m.repeats as u32,
                });
            }
        }
        if !summary.captures.is_empty() {
            let plain = AvDelayOptions {
                calibrations: Vec::new(),
                ..options
            };
            crate::av_delay::write_outputs(&summary, &plain, &report_dir.join("av_delay"))?;
        }
        let failed = ledger.failed_since(first);
        ledger.step("av_delay", !failed, None, t0);
        outputs.av_delay = Some(summary);
    }
    bar.inc(1);

    // Verdict, artifact, exports, comparison, report.
    bar.set_message("writing the set");
    let passed = ledger.checks.iter().all(|c| c.check.passed);
    calibration.certification = Some(Certification {
        passed,
        checks: ledger.checks.iter().map(|c| c.check.clone()).collect(),
    });
    for path in &inputs {
        if path.is_file() {
            calibration.provenance.inputs.push(InputRecord {
                path: path.strip_prefix(cap).unwrap_or(path).display().to_string(),
                sha256: sha256_file(path)?,
            });
        }
    }
    let mut files = vec![
        "certification.json".to_string(),
        "report/index.md".to_string(),
    ];
    let written_calibration = if calibration.lenses.is_empty() {
        None
    } else {
        calibration.save(&work.join("calibration.json"))?;
        files.push("calibration.json".into());
        let exported = crate::export::export_all(&calibration, work)?;
        for f in std::iter::once(&exported.kalibr_camchain)
            .chain(exported.kalibr_imu.iter())
            .chain(exported.basalt.iter())
        {
            files.push(f.strip_prefix(work).unwrap_or(f).display().to_string());
        }
        Some(calibration)
    };
    let comparison = match (previous, &written_calibration) {
        (Some((dir, prev)), Some(cal)) => Some(compare::compare(
            prev,
            &dir.display().to_string(),
            cal,
            &p.compare,
        )),
        _ => None,
    };
    let failed_checks: Vec<String> = ledger
        .checks
        .iter()
        .filter(|c| !c.check.passed)
        .map(|c| c.check.name.clone())
        .collect();
    let report = CertifyReport {
        unit_id: info.unit_id.clone(),
        date: date.into(),
        folder: folder.to_path_buf(),
        passed,
        failed_checks,
        checks: ledger.checks,
        steps: ledger.steps,
        comparison,
        files,
        seconds: started.elapsed().as_secs_f64(),
        calibration: written_calibration,
    };
    let json = serde_json::to_string_pretty(&report)
        .map_err(|e| CalibError::Internal(format!("the report does not serialize: {e}")))?;
    write_atomic(&work.join("certification.json"), json.as_bytes())?;
    write_atomic(
        &report_dir.join("index.md"),
        report::markdown(&report, info, &outputs, &report_dir).as_bytes(),
    )?;
    write_atomic(&report_dir.join("policy.toml"), p.to_toml()?.as_bytes())?;
    bar.finish_and_clear();
    Ok(report)
}
