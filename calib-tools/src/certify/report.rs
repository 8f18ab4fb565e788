//! The certification's report page (`report/index.md`: verdict first, then every check, the
//! comparison with a previous set and each step's figures and plots), and the readers behind
//! `kiwi-calib units list` / `units show`.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use serde::Serialize;

use kiwi_core::artifact::UnitCalibration;

use super::{CertifyReport, StepOutputs, UnitInfo};
use crate::error::{CalibError, Result};

fn fmt_value(v: f64) -> String {
    if v == f64::MAX {
        "not measured".into()
    } else if v == 0.0 || (1e-3..1e5).contains(&v.abs()) {
        format!("{v:.4}")
    } else {
        format!("{v:.3e}")
    }
}

/// Images (PNG, SVG) in `dir`, relative to `base`, sorted.
fn images(dir: &Path, base: &Path) -> Vec<String> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        if let Ok(entries) = std::fs::read_dir(&d) {
            for e in entries.filter_map(std::result::Result::ok) {
                let p = e.path();
                if p.is_dir() {
                    stack.push(p);
                } else if p
                    .extension()
                    .is_some_and(|x| x.eq_ignore_ascii_case("png") || x.eq_ignore_ascii_case("svg"))
                {
                    out.push(p.strip_prefix(base).unwrap_or(&p).display().to_string());
                }
            }
        }
    }
    out.sort();
    out
}

/// The report page (Markdown; images relative to `report/`).
pub fn markdown(
    report: &CertifyReport,
    info: &UnitInfo,
    outputs: &StepOutputs,
    report_dir: &Path,
) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "# Certification of unit {} — {}\n",
        report.unit_id, report.date
    );
    if report.passed {
        let _ = writeln!(
            s,
            "## Verdict: **CERTIFIED** — all {} checks passed\n",
            report.checks.len()
        );
    } else {
        let _ = writeln!(
            s,
            "## Verdict: **NOT CERTIFIED** — {} of {} checks failed: {}\n",
            report.failed_checks.len(),
            report.checks.len(),
            report
                .failed_checks
                .iter()
                .map(|c| format!("`{c}`"))
                .collect::<Vec<_>>()
                .join(", ")
        );
        for c in report.checks.iter().filter(|c| !c.check.passed) {
            if let Some(note) = &c.note {
                let _ = writeln!(s, "- `{}`: {note}", c.check.name);
            }
        }
        let _ = writeln!(s);
    }
    let _ = writeln!(
        s,
        "{} ({}), firmware {}, lens model {}. Folder `{}`. Thresholds: `policy.toml` beside this \
         page.\n",
        info.camera_model,
        info.unit_id,
        info.firmware,
        info.lens_model,
        report.folder.display()
    );
    if let Some(c) = &report.comparison {
        let _ = writeln!(
            s,
            "## Compared with {} (firmware {}, {})\n",
            c.previous, c.previous_firmware, c.previous_date
        );
        if c.significant.is_empty() {
            let _ = writeln!(
                s,
                "No parameter moved beyond its uncertainty ({} compared).\n",
                c.parameters.len()
            );
        } else {
            let _ = writeln!(
                s,
                "**Changed: {}** ({} of {} parameters moved beyond their uncertainty).\n",
                c.changed_groups.join(", "),
                c.significant.len(),
                c.parameters.len()
            );
        }
        let _ = writeln!(
            s,
            "| parameter | previous | current | change | 1σ | floor | significant |"
        );
        let _ = writeln!(s, "|---|---|---|---|---|---|---|");
        for p in &c.parameters {
            let _ = writeln!(
                s,
                "| {} | {} | {} | {} | {} | {} | {} |",
                p.name,
                fmt_value(p.previous),
                fmt_value(p.current),
                fmt_value(p.change),
                fmt_value(p.sigma),
                fmt_value(p.floor),
                if p.significant { "**yes**" } else { "no" }
            );
        }
        for n in &c.not_compared {
            let _ = writeln!(s, "\nNot compared: {n}");
        }
        let _ = writeln!(s);
    }
    let _ = writeln!(
        s,
        "## Checks\n\n| check | value | threshold | unit | result |\n|---|---|---|---|---|"
    );
    for c in &report.checks {
        let k = &c.check;
        let _ = writeln!(
            s,
            "| `{}` | {} | {} {} | {} | {} |",
            k.name,
            fmt_value(k.value),
            if k.comparison == "at_most" {
                "≤"
            } else {
                "≥"
            },
            fmt_value(k.threshold),
            c.unit,
            if k.passed { "pass" } else { "**FAIL**" }
        );
    }
    let _ = writeln!(
        s,
        "\n## Steps\n\n| step | status | time (s) | note |\n|---|---|---|---|"
    );
    for st in &report.steps {
        let _ = writeln!(
            s,
            "| {} | {} | {:.1} | {} |",
            st.step,
            st.status,
            st.seconds,
            st.note
                .as_deref()
                .unwrap_or("")
                .replace('\n', " ")
                .replace('|', "/")
        );
    }
    for (lens, r, folder) in &outputs.intrinsics {
        let _ = writeln!(s, "\n## Intrinsics: {lens} lens\n");
        let _ = writeln!(
            s,
            "{} over {} views, {} corners ({} rejected), corners to {:.1}° off-axis; RMS {:.3} px.\n",
            r.model, r.n_views, r.n_corners, r.n_rejected, r.max_theta_deg, r.rms_px
        );
        let _ = writeln!(s, "| parameter | value | 1σ |\n|---|---|---|");
        for ((n, v), sd) in r.param_names.iter().zip(&r.params).zip(&r.param_std) {
            let _ = writeln!(s, "| {n} | {} | {} |", fmt_value(*v), fmt_value(*sd));
        }
        let _ = writeln!(s);
        for img in images(&report_dir.join(folder), report_dir) {
            let _ = writeln!(s, "![{img}]({img})\n");
        }
    }
    if let Some(n) = &outputs.imu_noise {
        let _ = writeln!(s, "\n## IMU noise\n");
        let _ = writeln!(
            s,
            "{:.2} h at {:.1} Hz. Gyroscope: noise density {:.3e} rad/s/√Hz, random walk {:.3e} \
             rad/s²/√Hz. Accelerometer: noise density {:.3e} m/s²/√Hz, random walk {:.3e} \
             m/s³/√Hz (worst axis each).\n",
            n.duration_s / 3600.0,
            n.rate_hz,
            n.gyroscope_noise_density,
            n.gyroscope_random_walk,
            n.accelerometer_noise_density,
            n.accelerometer_random_walk
        );
        for img in images(&report_dir.join("imu_noise"), report_dir) {
            let _ = writeln!(s, "![{img}]({img})\n");
        }
    }
    if let Some(c) = &outputs.cam_imu {
        let _ = writeln!(s, "\n## Camera–IMU\n");
        let _ = writeln!(
            s,
            "| lens | rotation (deg, axis-angle) | translation (mm) | time shift (ms) | ±1σ (ms) | RMS (px) |\n|---|---|---|---|---|---|"
        );
        for l in &c.lenses {
            let _ = writeln!(
                s,
                "| {} | [{:.3}, {:.3}, {:.3}] | [{:.2}, {:.2}, {:.2}] | {:.3} | {:.4} | {:.3} |",
                l.name,
                l.rotation_deg[0],
                l.rotation_deg[1],
                l.rotation_deg[2],
                l.translation_m[0] * 1e3,
                l.translation_m[1] * 1e3,
                l.translation_m[2] * 1e3,
                l.time_shift_s * 1e3,
                l.time_shift_std_s * 1e3,
                l.rms_px
            );
        }
        let _ = writeln!(s, "\nDetails: [cam_imu/report.md](cam_imu/report.md)\n");
        for img in images(&report_dir.join("cam_imu"), report_dir) {
            let _ = writeln!(s, "![{img}]({img})\n");
        }
    }
    if let Some(a) = &outputs.av_delay {
        let _ = writeln!(s, "\n## A/V delay\n");
        let _ = writeln!(
            s,
            "| mode | delay (ms) | std (ms) | spread (ms) | repeats |\n|---|---|---|---|---|"
        );
        for m in &a.modes {
            let _ = writeln!(
                s,
                "| {} | {:.3} | {:.3} | {:.3} | {} |",
                m.mode,
                m.delay_s * 1e3,
                m.std_s * 1e3,
                m.spread_s * 1e3,
                m.repeats
            );
        }
        let _ = writeln!(
            s,
            "\n| recording | decoded frames | chirps | delay (ms) |\n|---|---|---|---|"
        );
        for c in &a.captures {
            let _ = writeln!(
                s,
                "| {} | {} of {} | {} | {:.3} ± {:.3} |",
                c.name,
                c.decoded,
                c.frames,
                c.chirps,
                c.av_delay_s * 1e3,
                c.av_delay_std_s * 1e3
            );
        }
        let _ = writeln!(s);
        for img in images(&report_dir.join("av_delay"), report_dir) {
            let _ = writeln!(s, "![{img}]({img})\n");
        }
    }
    s
}

/// One certification set of a unit.
#[derive(Debug, Clone, Serialize)]
pub struct SetSummary {
    /// Unit id.
    pub unit_id: String,
    /// Folder name (`YYYY-MM-DD[-N]`).
    pub name: String,
    /// The folder.
    pub folder: PathBuf,
    /// Verdict (`None` when the set has no certification record).
    pub passed: Option<bool>,
    /// Failed checks.
    pub failed_checks: Vec<String>,
    /// Firmware the unit ran.
    pub firmware: Option<String>,
}

/// Sort key of a set folder name: date, then the same-day counter.
fn set_key(name: &str) -> Option<(String, u32)> {
    kiwi_core::io::parse_set_name(name)
}

/// Prefix of a certification's work folder (`.certify-<set>-<pid>` beside the sets).
const WORK_PREFIX: &str = ".certify-";

/// Create a fresh work folder for the set `set_name` of the unit folder `unit_root`:
/// `.certify-<set>-<pid>`, created exclusively. A folder of that name can only be the
/// leftover of a killed run whose process id this run now has, so it is removed first:
/// nothing of an earlier run ever ends up in a new set.
pub fn create_work_dir(unit_root: &Path, set_name: &str) -> Result<PathBuf> {
    let work = unit_root.join(format!("{WORK_PREFIX}{set_name}-{}", std::process::id()));
    if work.exists() {
        std::fs::remove_dir_all(&work).map_err(|e| CalibError::Input {
            path: work.clone(),
            message: format!("cannot remove the leftover work folder of a killed run: {e}"),
        })?;
    }
    std::fs::create_dir(&work).map_err(|e| CalibError::Input {
        path: work.clone(),
        message: format!("cannot create the work folder: {e}"),
    })?;
    Ok(work)
}

/// Something a killed certification left behind in a unit folder.
#[derive(Debug, Clone, Serialize)]
pub struct Leftover {
    /// The folder.
    pub path: PathBuf,
    /// What it is.
    pub what: String,
}

/// Whether a process with this id runs (Linux `/proc`); unknown elsewhere counts as running,
/// so nothing of a live run is ever reported as a leftover or removed.
fn process_alive(pid: u32) -> bool {
    let proc = Path::new("/proc");
    !proc.is_dir() || proc.join(pid.to_string()).exists()
}

/// The work folders and empty claimed set folders that killed certifications left in the unit
/// folder `unit_dir` (a run still in progress is not reported).
pub fn unit_leftovers(unit_dir: &Path) -> Vec<Leftover> {
    let Ok(entries) = std::fs::read_dir(unit_dir) else {
        return Vec::new();
    };
    let names: Vec<String> = entries
        .filter_map(std::result::Result::ok)
        .filter(|e| e.path().is_dir())
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .collect();
    // The set each running certification claimed.
    let running: Vec<&str> = names
        .iter()
        .filter_map(|n| n.strip_prefix(WORK_PREFIX))
        .filter_map(|rest| {
            let (set, pid) = rest.rsplit_once('-')?;
            (set_key(set).is_some() && process_alive(pid.parse().ok()?)).then_some(set)
        })
        .collect();
    let mut out = Vec::new();
    for name in &names {
        let path = unit_dir.join(name);
        if let Some(rest) = name.strip_prefix(WORK_PREFIX) {
            let live = rest.rsplit_once('-').is_some_and(|(set, pid)| {
                set_key(set).is_some() && pid.parse().is_ok_and(process_alive)
            });
            if !live {
                out.push(Leftover {
                    path,
                    what: "work folder of a certification that was killed".into(),
                });
            }
        } else if set_key(name).is_some()
            && !running.contains(&name.as_str())
            && std::fs::read_dir(&path).is_ok_and(|mut d| d.next().is_none())
        {
            out.push(Leftover {
                path,
                what: "empty set folder claimed by a certification that was killed".into(),
            });
        }
    }
    out.sort_by(|a, b| a.path.cmp(&b.path));
    out
}

/// The unit folders under `units/`, sorted.
fn unit_dirs(units_dir: &Path) -> Result<Vec<PathBuf>> {
    let entries = std::fs::read_dir(units_dir).map_err(|e| CalibError::Input {
        path: units_dir.to_path_buf(),
        message: format!("cannot list units: {e}; give the units/ folder certify wrote into"),
    })?;
    let mut dirs: Vec<PathBuf> = entries
        .filter_map(std::result::Result::ok)
        .map(|e| e.path())
        .filter(|p| p.is_dir())
        .collect();
    dirs.sort();
    Ok(dirs)
}

/// Every leftover of killed certifications under `units/`.
pub fn list_leftovers(units_dir: &Path) -> Result<Vec<Leftover>> {
    let dirs = unit_dirs(units_dir)?;
    Ok(dirs.iter().flat_map(|d| unit_leftovers(d)).collect())
}

/// Remove the leftovers of killed certifications under `units/`; returns what was removed.
pub fn clean_leftovers(units_dir: &Path) -> Result<Vec<Leftover>> {
    let leftovers = list_leftovers(units_dir)?;
    for l in &leftovers {
        std::fs::remove_dir_all(&l.path).map_err(|e| CalibError::Input {
            path: l.path.clone(),
            message: format!("cannot remove: {e}"),
        })?;
    }
    Ok(leftovers)
}

/// The readable lines about leftovers, for `units list` (empty when there are none).
pub fn leftovers_text(leftovers: &[Leftover]) -> String {
    let mut s = String::new();
    for l in leftovers {
        let _ = writeln!(s, "leftover: {} ({})", l.path.display(), l.what);
    }
    if !leftovers.is_empty() {
        let _ = writeln!(
            s,
            "remove them with `kiwi-calib units clean` (no set is touched)"
        );
    }
    s
}

/// Every finished set of one unit folder (`units/<id>`), oldest first.
pub fn unit_sets(unit_dir: &Path) -> Result<Vec<SetSummary>> {
    let entries = std::fs::read_dir(unit_dir).map_err(|e| CalibError::Input {
        path: unit_dir.to_path_buf(),
        message: format!("cannot list the unit's sets: {e}"),
    })?;
    let unit_id = unit_dir
        .file_name()
        .map_or_else(String::new, |n| n.to_string_lossy().into_owned());
    let mut sets = Vec::new();
    for e in entries.filter_map(std::result::Result::ok) {
        let name = e.file_name().to_string_lossy().into_owned();
        let Some(key) = set_key(&name) else { continue };
        let folder = e.path();
        let record = folder.join("certification.json");
        let calibration = folder.join("calibration.json");
        // A claimed folder whose run has not finished is empty: not a set yet.
        if !record.is_file() && !calibration.is_file() {
            continue;
        }
        let json: Option<serde_json::Value> = std::fs::read_to_string(&record)
            .ok()
            .and_then(|t| serde_json::from_str(&t).ok());
        let cal = UnitCalibration::load(&calibration).ok();
        let passed = json
            .as_ref()
            .and_then(|j| j.get("passed"))
            .and_then(serde_json::Value::as_bool)
            .or_else(|| {
                cal.as_ref()
                    .and_then(|c| c.certification.as_ref().map(|x| x.passed))
            });
        let failed_checks = json
            .as_ref()
            .and_then(|j| j.get("failed_checks"))
            .and_then(serde_json::Value::as_array)
            .map(|a| {
                a.iter()
                    .filter_map(|v| v.as_str().map(str::to_string))
                    .collect()
            })
            .unwrap_or_default();
        sets.push((
            key,
            SetSummary {
                unit_id: unit_id.clone(),
                name,
                folder,
                passed,
                failed_checks,
                firmware: cal.map(|c| c.firmware),
            },
        ));
    }
    sets.sort_by(|a, b| a.0.cmp(&b.0));
    Ok(sets.into_iter().map(|(_, s)| s).collect())
}

/// Every unit under `units/` with its sets.
pub fn list_units(units_dir: &Path) -> Result<Vec<SetSummary>> {
    let dirs = unit_dirs(units_dir)?;
    let mut out = Vec::new();
    for d in dirs {
        out.extend(unit_sets(&d)?);
    }
    Ok(out)
}

/// The readable listing of `units list`.
pub fn list_text(sets: &[SetSummary]) -> String {
    let mut s = String::new();
    if sets.is_empty() {
        s.push_str("no certified units\n");
    }
    for set in sets {
        let verdict = match set.passed {
            Some(true) => "CERTIFIED".to_string(),
            Some(false) => format!("FAILED ({})", set.failed_checks.join(", ")),
            None => "no verdict".to_string(),
        };
        let _ = writeln!(
            s,
            "{:<14} {:<14} firmware {:<10} {verdict}",
            set.unit_id,
            set.name,
            set.firmware.as_deref().unwrap_or("-")
        );
    }
    s
}

/// The latest set of a unit folder (`units/<id>`).
pub fn latest_set(unit_dir: &Path) -> Result<SetSummary> {
    unit_sets(unit_dir)?.pop().ok_or_else(|| CalibError::Input {
        path: unit_dir.to_path_buf(),
        message: "holds no certification set; run `kiwi-calib certify` first".into(),
    })
}

/// The readable summary of `units show`.
pub fn show_text(set: &SetSummary) -> Result<String> {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "unit {} — set {} ({})",
        set.unit_id,
        set.name,
        set.folder.display()
    );
    let _ = writeln!(
        s,
        "verdict: {}",
        match set.passed {
            Some(true) => "CERTIFIED".to_string(),
            Some(false) => format!("NOT CERTIFIED — failed: {}", set.failed_checks.join(", ")),
            None => "none".to_string(),
        }
    );
    let cal_path = set.folder.join("calibration.json");
    if cal_path.is_file() {
        let cal = UnitCalibration::load(&cal_path)?;
        let _ = writeln!(
            s,
            "{} firmware {}, date {}",
            cal.camera_model, cal.firmware, cal.date
        );
        for l in &cal.lenses {
            let names = l.intrinsics.param_names();
            let params: Vec<String> = names
                .iter()
                .zip(l.intrinsics.params())
                .map(|(n, v)| format!("{n} {v:.5}"))
                .collect();
            let _ = writeln!(
                s,
                "  lens {}: {}x{}, {}; RMS {}",
                l.name,
                l.resolution[0],
                l.resolution[1],
                params.join(", "),
                l.rms_px.map_or("-".into(), |r| format!("{r:.3} px"))
            );
            if let (Some(p), Some(t)) = (l.cam_from_imu(), l.time_shift_s) {
                let r = p.rotation.scaled_axis() * (180.0 / std::f64::consts::PI);
                let tr = p.translation.vector * 1e3;
                let _ = writeln!(
                    s,
                    "    cam_from_imu rotation [{:.3}, {:.3}, {:.3}] deg, translation [{:.2}, \
                     {:.2}, {:.2}] mm, time shift {:.3} ms",
                    r.x,
                    r.y,
                    r.z,
                    tr.x,
                    tr.y,
                    tr.z,
                    t * 1e3
                );
            }
        }
        if let Some(i) = &cal.imu {
            let _ = writeln!(
                s,
                "  imu {:.0} Hz: gyro N {:.3e} rad/s/√Hz, K {:.3e}; accel N {:.3e} m/s²/√Hz, K {:.3e}",
                i.rate_hz,
                i.gyroscope_noise_density,
                i.gyroscope_random_walk,
                i.accelerometer_noise_density,
                i.accelerometer_random_walk
            );
        }
        for d in &cal.av_delays {
            let _ = writeln!(
                s,
                "  A/V delay {}: {:.3} ± {:.3} ms over {} recordings",
                d.mode,
                d.delay_s * 1e3,
                d.std_s * 1e3,
                d.repeats
            );
        }
    }
    let _ = writeln!(
        s,
        "report: {}",
        set.folder.join("report").join("index.md").display()
    );
    Ok(s)
}
