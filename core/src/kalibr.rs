//! Kalibr file formats: `camchain-imucam.yaml` and `imu.yaml`, exported from and imported into
//! a [`UnitCalibration`].
//!
//! Mapping: KB4 is Kalibr's `camera_model: pinhole` + `distortion_model: equidistant` with
//! `intrinsics: [fu, fv, pu, pv]` and `distortion_coeffs: [k1, k2, k3, k4]`; Double Sphere is
//! `camera_model: ds` + `distortion_model: none` with `intrinsics: [xi, alpha, fu, fv, pu, pv]`.
//! `T_cam_imu` is `cam_from_imu`; `timeshift_cam_imu` follows Kalibr's sign,
//! `t_imu = t_cam + timeshift`. Lens names travel in the `rostopic` (`/kiwi/<lens>/image_raw`).

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::Path;

use serde::Deserialize;

use crate::artifact::{ImuNoise, Intrinsics, LensCalibration, RigidTransform, UnitCalibration};
use crate::error::{CoreError, Result};

/// Prefix and suffix of the `rostopic` that carries a lens name through Kalibr files.
const TOPIC_PREFIX: &str = "/kiwi/";
const TOPIC_SUFFIX: &str = "/image_raw";

fn matrix_rows(out: &mut String, indent: &str, rows: &[[f64; 4]; 4]) {
    for row in rows {
        let _ = writeln!(
            out,
            "{indent}- [{}, {}, {}, {}]",
            fmt(row[0]),
            fmt(row[1]),
            fmt(row[2]),
            fmt(row[3])
        );
    }
}

/// Shortest representation that reads back to the same `f64`, always with a decimal point or
/// exponent so YAML readers see a float.
fn fmt(v: f64) -> String {
    let s = format!("{v:?}");
    if s.contains(['.', 'e', 'E']) || s.contains("inf") || s.contains("NaN") {
        s
    } else {
        format!("{s}.0")
    }
}

fn list(values: &[f64]) -> String {
    values
        .iter()
        .map(|v| fmt(*v))
        .collect::<Vec<_>>()
        .join(", ")
}

fn homogeneous(t: &RigidTransform) -> [[f64; 4]; 4] {
    let r = t.rotation;
    let p = t.translation_m;
    [
        [r[0][0], r[0][1], r[0][2], p[0]],
        [r[1][0], r[1][1], r[1][2], p[1]],
        [r[2][0], r[2][1], r[2][2], p[2]],
        [0.0, 0.0, 0.0, 1.0],
    ]
}

/// Kalibr `camchain-imucam.yaml` text for every lens of the unit (cam0, cam1, … in lens order).
/// Lenses without `cam_from_imu` are written without `T_cam_imu` (a plain camchain).
pub fn camchain_yaml(calibration: &UnitCalibration) -> String {
    let mut out = String::new();
    let _ = writeln!(
        out,
        "# Kalibr camchain for unit {} ({}), written by KIWI",
        calibration.unit_id, calibration.camera_model
    );
    for (i, lens) in calibration.lenses.iter().enumerate() {
        let _ = writeln!(out, "cam{i}:");
        if let Some(t) = &lens.cam_from_imu {
            let _ = writeln!(out, "  T_cam_imu:");
            matrix_rows(&mut out, "  ", &homogeneous(t));
        }
        if i > 0 {
            let previous = &calibration.lenses[i - 1];
            if let (Some(a), Some(b)) = (lens.cam_from_imu(), previous.cam_from_imu()) {
                // T_cn_cnm1 = this camera from the previous one.
                let cn_from_cnm1 = a * b.inverse();
                let _ = writeln!(out, "  T_cn_cnm1:");
                matrix_rows(
                    &mut out,
                    "  ",
                    &homogeneous(&RigidTransform::from_pose(&cn_from_cnm1)),
                );
            }
        }
        let overlaps: Vec<String> = (0..calibration.lenses.len())
            .filter(|j| *j != i)
            .map(|j| j.to_string())
            .collect();
        let _ = writeln!(out, "  cam_overlaps: [{}]", overlaps.join(", "));
        match lens.intrinsics {
            Intrinsics::Kb4 {
                fx,
                fy,
                cx,
                cy,
                k1,
                k2,
                k3,
                k4,
            } => {
                let _ = writeln!(out, "  camera_model: pinhole");
                let _ = writeln!(out, "  distortion_coeffs: [{}]", list(&[k1, k2, k3, k4]));
                let _ = writeln!(out, "  distortion_model: equidistant");
                let _ = writeln!(out, "  intrinsics: [{}]", list(&[fx, fy, cx, cy]));
            }
            Intrinsics::DoubleSphere {
                fx,
                fy,
                cx,
                cy,
                xi,
                alpha,
            } => {
                let _ = writeln!(out, "  camera_model: ds");
                let _ = writeln!(out, "  distortion_coeffs: []");
                let _ = writeln!(out, "  distortion_model: none");
                let _ = writeln!(
                    out,
                    "  intrinsics: [{}]",
                    list(&[xi, alpha, fx, fy, cx, cy])
                );
            }
        }
        let _ = writeln!(
            out,
            "  resolution: [{}, {}]",
            lens.resolution[0], lens.resolution[1]
        );
        let _ = writeln!(out, "  rostopic: {TOPIC_PREFIX}{}{TOPIC_SUFFIX}", lens.name);
        if let Some(s) = lens.time_shift_s {
            let _ = writeln!(out, "  timeshift_cam_imu: {}", fmt(s));
        }
    }
    out
}

/// Kalibr `imu.yaml` text (the flat form Kalibr's `kalibr_calibrate_imu_camera` reads).
pub fn imu_yaml(imu: &ImuNoise) -> String {
    let mut out = String::new();
    let _ = writeln!(
        out,
        "# Kalibr IMU noise model, continuous time, SI units; written by KIWI"
    );
    let _ = writeln!(out, "rostopic: /kiwi/imu");
    let _ = writeln!(out, "update_rate: {}", fmt(imu.rate_hz));
    let _ = writeln!(
        out,
        "accelerometer_noise_density: {}",
        fmt(imu.accelerometer_noise_density)
    );
    let _ = writeln!(
        out,
        "accelerometer_random_walk: {}",
        fmt(imu.accelerometer_random_walk)
    );
    let _ = writeln!(
        out,
        "gyroscope_noise_density: {}",
        fmt(imu.gyroscope_noise_density)
    );
    let _ = writeln!(
        out,
        "gyroscope_random_walk: {}",
        fmt(imu.gyroscope_random_walk)
    );
    out
}

#[derive(Debug, Deserialize)]
struct KalibrCamera {
    camera_model: String,
    intrinsics: Vec<f64>,
    #[serde(default)]
    distortion_model: Option<String>,
    #[serde(default)]
    distortion_coeffs: Vec<f64>,
    resolution: [u32; 2],
    #[serde(rename = "T_cam_imu", default)]
    t_cam_imu: Option<serde_yaml_ng::Value>,
    #[serde(rename = "T_cn_cnm1", default)]
    t_cn_cnm1: Option<serde_yaml_ng::Value>,
    #[serde(default)]
    timeshift_cam_imu: Option<f64>,
    #[serde(default)]
    rostopic: Option<String>,
}

#[derive(Debug, Deserialize)]
struct KalibrImuFlat {
    update_rate: f64,
    accelerometer_noise_density: f64,
    accelerometer_random_walk: f64,
    gyroscope_noise_density: f64,
    gyroscope_random_walk: f64,
}

fn yaml_error(path: &Path, e: &serde_yaml_ng::Error, fix: &str) -> CoreError {
    let field = e.location().map_or_else(
        || ".".into(),
        |l| format!("line {}, column {}", l.line(), l.column()),
    );
    CoreError::Parse {
        path: path.to_path_buf(),
        format: "Kalibr YAML",
        field,
        message: e.to_string(),
        fix: fix.into(),
    }
}

/// Lenses read from a Kalibr `camchain.yaml` or `camchain-imucam.yaml`, in `camN` order.
/// The field of view is set to what the model supports, since Kalibr does not record it.
///
/// Accepts the variants found in public camchain files: an OpenCV FileStorage first line
/// (`%YAML:1.0`), and `T_cam_imu` / `T_cn_cnm1` as four rows of four, one flat list of 16
/// (row-major), or an OpenCV matrix (`!!opencv-matrix` with `rows`, `cols`, `data`). A camera
/// without `T_cam_imu` gets it from the previous camera's through `T_cn_cnm1`.
pub fn lenses_from_camchain(text: &str, path: &Path) -> Result<Vec<LensCalibration>> {
    let text = strip_opencv_header(text);
    let cams: BTreeMap<String, KalibrCamera> = serde_yaml_ng::from_str(&text).map_err(|e| {
        yaml_error(
            path,
            &e,
            "expected Kalibr's camchain format (cam0: {camera_model, intrinsics, …})",
        )
    })?;
    let mut ordered: Vec<(usize, String, KalibrCamera)> = Vec::new();
    for (key, cam) in cams {
        let index = key
            .strip_prefix("cam")
            .and_then(|n| n.parse::<usize>().ok())
            .ok_or_else(|| CoreError::Invalid {
                path: path.to_path_buf(),
                field: key.clone(),
                expected: "camera keys cam0, cam1, …".into(),
                found: format!("`{key}`"),
                fix: "rename the key".into(),
            })?;
        ordered.push((index, key, cam));
    }
    ordered.sort_by_key(|(i, _, _)| *i);
    let mut lenses = Vec::new();
    for (_, key, cam) in ordered {
        let invalid = |field: &str, expected: &str, found: String| CoreError::Invalid {
            path: path.to_path_buf(),
            field: format!("{key}.{field}"),
            expected: expected.into(),
            found,
            fix: "KIWI imports Kalibr's pinhole/equidistant and ds/none cameras".into(),
        };
        let distortion = cam.distortion_model.as_deref().unwrap_or("none");
        let intrinsics = match (cam.camera_model.as_str(), distortion) {
            ("pinhole", "equidistant") => {
                let (i, d) = (&cam.intrinsics, &cam.distortion_coeffs);
                if i.len() != 4 || d.len() != 4 {
                    return Err(invalid(
                        "intrinsics",
                        "4 intrinsics and 4 distortion coefficients",
                        format!("{} and {}", i.len(), d.len()),
                    ));
                }
                Intrinsics::Kb4 {
                    fx: i[0],
                    fy: i[1],
                    cx: i[2],
                    cy: i[3],
                    k1: d[0],
                    k2: d[1],
                    k3: d[2],
                    k4: d[3],
                }
            }
            ("ds", "none") => {
                let i = &cam.intrinsics;
                if i.len() != 6 {
                    return Err(invalid(
                        "intrinsics",
                        "6 values [xi, alpha, fu, fv, pu, pv]",
                        format!("{}", i.len()),
                    ));
                }
                Intrinsics::DoubleSphere {
                    fx: i[2],
                    fy: i[3],
                    cx: i[4],
                    cy: i[5],
                    xi: i[0],
                    alpha: i[1],
                }
            }
            (model, dist) => {
                return Err(invalid(
                    "camera_model",
                    "pinhole+equidistant or ds+none",
                    format!("{model}+{dist}"),
                ));
            }
        };
        let matrix = |field: &str, value: &Option<serde_yaml_ng::Value>| match value {
            None => Ok(None),
            Some(v) => matrix4(v)
                .map(|m| Some(rigid_from_rows(&m)))
                .ok_or_else(|| CoreError::Invalid {
                    path: path.to_path_buf(),
                    field: format!("{key}.{field}"),
                    expected: "a 4×4 matrix: 4 rows of 4 numbers, 16 numbers row by row, or \
                               an OpenCV matrix"
                        .into(),
                    found: describe_yaml(v),
                    fix: "write the transform as Kalibr does (4 rows of 4)".into(),
                }),
        };
        let t_cn_cnm1 = matrix("T_cn_cnm1", &cam.t_cn_cnm1)?;
        let cam_from_imu = match (matrix("T_cam_imu", &cam.t_cam_imu)?, &t_cn_cnm1) {
            (Some(t), _) => Some(t),
            (None, Some(this_from_previous)) => lenses
                .last()
                .and_then(|l: &LensCalibration| l.cam_from_imu.as_ref())
                .and_then(|prev| chain(this_from_previous, prev)),
            (None, None) => None,
        };
        let name = cam
            .rostopic
            .as_deref()
            .and_then(|t| t.strip_prefix(TOPIC_PREFIX))
            .and_then(|t| t.strip_suffix(TOPIC_SUFFIX))
            .map_or_else(|| key.clone(), str::to_string);
        let mut lens = LensCalibration {
            name,
            intrinsics,
            resolution: cam.resolution,
            valid_fov_rad: std::f64::consts::PI,
            rms_px: None,
            param_std: None,
            cam_from_imu,
            time_shift_s: cam.timeshift_cam_imu,
        };
        let camera = lens.camera().map_err(|e| e.at_path(path))?;
        lens.valid_fov_rad =
            crate::camera::CameraModel::valid_fov(&camera).min(2.0 * std::f64::consts::PI);
        lenses.push(lens);
    }
    if lenses.is_empty() {
        return Err(CoreError::Invalid {
            path: path.to_path_buf(),
            field: ".".into(),
            expected: "at least one camera (cam0)".into(),
            found: "none".into(),
            fix: "is this a Kalibr camchain file?".into(),
        });
    }
    Ok(lenses)
}

/// Drop an OpenCV FileStorage header (`%YAML:1.0`, not a valid YAML directive) and OpenCV's
/// matrix tags, which YAML parsers refuse or keep as unknown tags.
fn strip_opencv_header(text: &str) -> String {
    let body = match text.trim_start().strip_prefix("%YAML:") {
        Some(rest) => rest.split_once('\n').map_or("", |(_, r)| r),
        None => text,
    };
    body.replace("!!opencv-matrix", "")
}

/// A 4×4 matrix from rows of four, a flat row-major list of 16, or an OpenCV matrix map.
fn matrix4(value: &serde_yaml_ng::Value) -> Option<[[f64; 4]; 4]> {
    use serde_yaml_ng::Value;
    let number = |v: &Value| v.as_f64().filter(|x| x.is_finite());
    let flat: Vec<f64> = match value {
        Value::Tagged(t) => return matrix4(&t.value),
        Value::Mapping(m) => {
            let dims = (m.get("rows")?.as_u64()?, m.get("cols")?.as_u64()?);
            if dims != (4, 4) {
                return None;
            }
            m.get("data")?
                .as_sequence()?
                .iter()
                .map(number)
                .collect::<Option<_>>()?
        }
        Value::Sequence(items) if items.len() == 4 && items.iter().all(Value::is_sequence) => {
            let mut out = Vec::with_capacity(16);
            for row in items {
                let row = row.as_sequence()?;
                if row.len() != 4 {
                    return None;
                }
                for v in row {
                    out.push(number(v)?);
                }
            }
            out
        }
        Value::Sequence(items) => items.iter().map(number).collect::<Option<_>>()?,
        _ => return None,
    };
    if flat.len() != 16 {
        return None;
    }
    let mut m = [[0.0; 4]; 4];
    for (i, v) in flat.into_iter().enumerate() {
        m[i / 4][i % 4] = v;
    }
    Some(m)
}

fn rigid_from_rows(rows: &[[f64; 4]; 4]) -> RigidTransform {
    RigidTransform {
        rotation: [
            [rows[0][0], rows[0][1], rows[0][2]],
            [rows[1][0], rows[1][1], rows[1][2]],
            [rows[2][0], rows[2][1], rows[2][2]],
        ],
        translation_m: [rows[0][3], rows[1][3], rows[2][3]],
    }
}

/// `this_from_imu = this_from_previous * previous_from_imu`, when both are proper transforms.
fn chain(
    this_from_previous: &RigidTransform,
    previous_from_imu: &RigidTransform,
) -> Option<RigidTransform> {
    let t = this_from_previous.to_pose().ok()? * previous_from_imu.to_pose().ok()?;
    Some(RigidTransform::from_pose(&t))
}

fn describe_yaml(v: &serde_yaml_ng::Value) -> String {
    match v {
        serde_yaml_ng::Value::Sequence(s) => format!("a list of {} items", s.len()),
        serde_yaml_ng::Value::Mapping(_) => "a map without rows: 4, cols: 4, data".into(),
        other => format!(
            "`{}`",
            serde_yaml_ng::to_string(other).unwrap_or_default().trim()
        ),
    }
}

/// IMU noise read from a Kalibr `imu.yaml`, flat or nested under `imu0:`.
pub fn imu_from_yaml(text: &str, path: &Path) -> Result<ImuNoise> {
    let value: serde_yaml_ng::Value = serde_yaml_ng::from_str(text)
        .map_err(|e| yaml_error(path, &e, "expected Kalibr's imu.yaml"))?;
    let inner = value.get("imu0").cloned().unwrap_or(value);
    let flat: KalibrImuFlat = serde_yaml_ng::from_value(inner).map_err(|e| {
        yaml_error(
            path,
            &e,
            "imu.yaml needs the four noise fields (accelerometer_noise_density, …)",
        )
    })?;
    Ok(ImuNoise {
        rate_hz: flat.update_rate,
        gyroscope_noise_density: flat.gyroscope_noise_density,
        gyroscope_random_walk: flat.gyroscope_random_walk,
        accelerometer_noise_density: flat.accelerometer_noise_density,
        accelerometer_random_walk: flat.accelerometer_random_walk,
        gyroscope_bias_instability: None,
        accelerometer_bias_instability: None,
        axis_convention: "kalibr-import".into(),
    })
}
