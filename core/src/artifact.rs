//! The unit calibration artifact (`calibration.json`): the contract between `kiwi-calib`, which
//! writes it, and `kiwi`, which reads it (ARCHITECTURE.md §3).
//!
//! [`UnitCalibration::load`] parses and validates every field (finite values, positive focal
//! lengths, proper rotations, known schema version, consistent resolutions); each error names
//! the file, the field path (`lenses[1].intrinsics.fx`) and the fix. [`UnitCalibration::save`]
//! writes atomically. Exports for other tools live in [`crate::kalibr`] and [`crate::basalt`].

use std::path::Path;

use nalgebra::{Isometry3, Matrix3, Translation3, Vector3};
use serde::{Deserialize, Serialize};

use crate::camera::{Camera, DoubleSphere, Kb4};
use crate::error::{CoreError, Result};
use crate::geometry::{Pose, rotation_from_matrix};
use crate::io::{read_text, write_atomic};

/// The schema version this build reads and writes.
pub const SCHEMA_VERSION: u32 = 1;

/// A camera unit's calibration set (one `calibration.json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct UnitCalibration {
    /// Always [`SCHEMA_VERSION`] when written by this build.
    pub schema_version: u32,
    /// The unit's identifier (e.g. its serial number), also its folder name under `units/`.
    pub unit_id: String,
    /// The camera product, e.g. `Insta360 X5` or `Insta360 GO 3`.
    pub camera_model: String,
    /// Firmware version the unit ran when calibrated (a change means recalibrate).
    pub firmware: String,
    /// Calibration date, `YYYY-MM-DD`.
    pub date: String,
    /// Recording modes the unit was certified for.
    #[serde(default)]
    pub recording_modes: Vec<RecordingMode>,
    /// One entry per lens (`front`, `rear` for an X5; one lens for a GO 3).
    pub lenses: Vec<LensCalibration>,
    /// IMU noise model; absent until `imu-noise` has run.
    #[serde(default)]
    pub imu: Option<ImuNoise>,
    /// Audio-to-video delay per recording mode; empty until `av-delay` has run.
    #[serde(default)]
    pub av_delays: Vec<AvDelay>,
    /// Where the numbers came from.
    pub provenance: Provenance,
    /// The certification verdict; absent for an uncertified (work-in-progress) set.
    #[serde(default)]
    pub certification: Option<Certification>,
}

/// A recording mode of the camera (resolution and frame rate as the file stores them).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RecordingMode {
    /// Mode name, e.g. `x5-960-119.88`.
    pub name: String,
    /// Per-lens image width (px).
    pub width: u32,
    /// Per-lens image height (px).
    pub height: u32,
    /// Frame rate (Hz).
    pub fps: f64,
    /// Rolling-shutter readout time of a full frame (s), if known.
    #[serde(default)]
    pub readout_time_s: Option<f64>,
}

/// One lens: its projection, and where it sits relative to the IMU.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LensCalibration {
    /// Lens name: `front`, `rear` (X5) or `main` (single-lens cameras).
    pub name: String,
    /// Projection model and parameters.
    pub intrinsics: Intrinsics,
    /// Image size `[width, height]` in pixels the intrinsics refer to.
    pub resolution: [u32; 2],
    /// Full apex angle (rad) of the field of view the calibration covered and is trusted over.
    pub valid_fov_rad: f64,
    /// RMS reprojection error of the intrinsics fit (px), if fitted.
    #[serde(default)]
    pub rms_px: Option<f64>,
    /// Standard deviation of each intrinsic parameter, in the model's parameter order.
    #[serde(default)]
    pub param_std: Option<Vec<f64>>,
    /// `cam_from_imu`: maps IMU-frame coordinates into this lens's camera frame.
    #[serde(default)]
    pub cam_from_imu: Option<RigidTransform>,
    /// Kalibr's time shift (s): `t_imu = t_cam + time_shift_s`.
    #[serde(default)]
    pub time_shift_s: Option<f64>,
}

/// Projection parameters, tagged by model (`"model": "kb4"` or `"model": "double_sphere"`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "RawIntrinsics", into = "RawIntrinsics")]
pub enum Intrinsics {
    /// Kannala–Brandt (OpenCV fisheye, Kalibr `pinhole`/`equidistant`).
    Kb4 {
        /// Focal length x (px).
        fx: f64,
        /// Focal length y (px).
        fy: f64,
        /// Principal point x (px).
        cx: f64,
        /// Principal point y (px).
        cy: f64,
        /// θ³ coefficient.
        k1: f64,
        /// θ⁵ coefficient.
        k2: f64,
        /// θ⁷ coefficient.
        k3: f64,
        /// θ⁹ coefficient.
        k4: f64,
    },
    /// Double Sphere (Kalibr `ds`/`none`).
    DoubleSphere {
        /// Focal length x (px).
        fx: f64,
        /// Focal length y (px).
        fy: f64,
        /// Principal point x (px).
        cx: f64,
        /// Principal point y (px).
        cy: f64,
        /// Distance between the two sphere centres.
        xi: f64,
        /// Blend between the second sphere and the image plane.
        alpha: f64,
    },
}

/// The flat file form of [`Intrinsics`]. Deserializing through a plain struct (rather than a
/// serde-tagged enum, which buffers its content) keeps the exact field path in error messages.
#[derive(Debug, Clone, Copy, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawIntrinsics {
    model: RawModel,
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    k1: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    k2: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    k3: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    k4: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    xi: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    alpha: Option<f64>,
}

#[derive(Debug, Clone, Copy, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
enum RawModel {
    #[default]
    Kb4,
    DoubleSphere,
}

impl TryFrom<RawIntrinsics> for Intrinsics {
    type Error = String;

    fn try_from(r: RawIntrinsics) -> std::result::Result<Self, String> {
        let need = |v: Option<f64>, name: &str| v.ok_or_else(|| format!("missing field `{name}`"));
        let forbid = |v: Option<f64>, name: &str, model: &str| match v {
            Some(_) => Err(format!("unknown field `{name}` for model `{model}`")),
            None => Ok(()),
        };
        Ok(match r.model {
            RawModel::Kb4 => {
                forbid(r.xi, "xi", "kb4")?;
                forbid(r.alpha, "alpha", "kb4")?;
                Self::Kb4 {
                    fx: r.fx,
                    fy: r.fy,
                    cx: r.cx,
                    cy: r.cy,
                    k1: need(r.k1, "k1")?,
                    k2: need(r.k2, "k2")?,
                    k3: need(r.k3, "k3")?,
                    k4: need(r.k4, "k4")?,
                }
            }
            RawModel::DoubleSphere => {
                for (v, n) in [(r.k1, "k1"), (r.k2, "k2"), (r.k3, "k3"), (r.k4, "k4")] {
                    forbid(v, n, "double_sphere")?;
                }
                Self::DoubleSphere {
                    fx: r.fx,
                    fy: r.fy,
                    cx: r.cx,
                    cy: r.cy,
                    xi: need(r.xi, "xi")?,
                    alpha: need(r.alpha, "alpha")?,
                }
            }
        })
    }
}

impl From<Intrinsics> for RawIntrinsics {
    fn from(i: Intrinsics) -> Self {
        match i {
            Intrinsics::Kb4 {
                fx,
                fy,
                cx,
                cy,
                k1,
                k2,
                k3,
                k4,
            } => Self {
                model: RawModel::Kb4,
                fx,
                fy,
                cx,
                cy,
                k1: Some(k1),
                k2: Some(k2),
                k3: Some(k3),
                k4: Some(k4),
                ..Self::default()
            },
            Intrinsics::DoubleSphere {
                fx,
                fy,
                cx,
                cy,
                xi,
                alpha,
            } => Self {
                model: RawModel::DoubleSphere,
                fx,
                fy,
                cx,
                cy,
                xi: Some(xi),
                alpha: Some(alpha),
                ..Self::default()
            },
        }
    }
}

impl Intrinsics {
    /// Parameters in the camera model's order.
    pub fn params(&self) -> Vec<f64> {
        match *self {
            Self::Kb4 {
                fx,
                fy,
                cx,
                cy,
                k1,
                k2,
                k3,
                k4,
            } => vec![fx, fy, cx, cy, k1, k2, k3, k4],
            Self::DoubleSphere {
                fx,
                fy,
                cx,
                cy,
                xi,
                alpha,
            } => vec![fx, fy, cx, cy, xi, alpha],
        }
    }

    /// Names of the parameters in order.
    pub fn param_names(&self) -> &'static [&'static str] {
        match self {
            Self::Kb4 { .. } => &crate::camera::KB4_PARAM_NAMES,
            Self::DoubleSphere { .. } => &crate::camera::DS_PARAM_NAMES,
        }
    }

    /// Build a validated camera of this model at the given resolution.
    pub fn camera(&self, width: u32, height: u32) -> Result<Camera> {
        Ok(match *self {
            Self::Kb4 {
                fx,
                fy,
                cx,
                cy,
                k1,
                k2,
                k3,
                k4,
            } => Camera::Kb4(Kb4::new(width, height, [fx, fy, cx, cy, k1, k2, k3, k4])?),
            Self::DoubleSphere {
                fx,
                fy,
                cx,
                cy,
                xi,
                alpha,
            } => Camera::DoubleSphere(DoubleSphere::new(
                width,
                height,
                [fx, fy, cx, cy, xi, alpha],
            )?),
        })
    }

    /// The intrinsics of a camera.
    pub fn from_camera(camera: &Camera) -> Self {
        match camera {
            Camera::Kb4(c) => {
                let p = crate::camera::CameraModel::params(c);
                Self::Kb4 {
                    fx: p[0],
                    fy: p[1],
                    cx: p[2],
                    cy: p[3],
                    k1: p[4],
                    k2: p[5],
                    k3: p[6],
                    k4: p[7],
                }
            }
            Camera::DoubleSphere(c) => {
                let p = crate::camera::CameraModel::params(c);
                Self::DoubleSphere {
                    fx: p[0],
                    fy: p[1],
                    cx: p[2],
                    cy: p[3],
                    xi: p[4],
                    alpha: p[5],
                }
            }
        }
    }
}

/// A rigid transform as stored in files: a row-major rotation matrix and a translation (m).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RigidTransform {
    /// Rotation matrix, rows.
    pub rotation: [[f64; 3]; 3],
    /// Translation (m).
    pub translation_m: [f64; 3],
}

impl RigidTransform {
    /// From a pose.
    pub fn from_pose(pose: &Pose) -> Self {
        let r = pose.rotation.to_rotation_matrix().into_inner();
        let t = pose.translation.vector;
        Self {
            rotation: [
                [r[(0, 0)], r[(0, 1)], r[(0, 2)]],
                [r[(1, 0)], r[(1, 1)], r[(1, 2)]],
                [r[(2, 0)], r[(2, 1)], r[(2, 2)]],
            ],
            translation_m: [t.x, t.y, t.z],
        }
    }

    /// The rotation matrix.
    pub fn rotation_matrix(&self) -> Matrix3<f64> {
        Matrix3::from_fn(|i, j| self.rotation[i][j])
    }

    /// To a pose, checking the rotation is proper; the error message says how far off it is.
    pub fn to_pose(&self) -> std::result::Result<Pose, String> {
        if !self.translation_m.iter().all(|v| v.is_finite()) {
            return Err("a translation with non-finite entries".into());
        }
        let rotation = rotation_from_matrix(&self.rotation_matrix())?;
        Ok(Isometry3::from_parts(
            Translation3::from(Vector3::from(self.translation_m)),
            rotation,
        ))
    }
}

/// IMU noise model in continuous time, SI units (Kalibr's parameter names).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ImuNoise {
    /// Sample rate (Hz).
    pub rate_hz: f64,
    /// Gyroscope white noise density (rad/s/√Hz).
    pub gyroscope_noise_density: f64,
    /// Gyroscope bias random walk (rad/s²/√Hz).
    pub gyroscope_random_walk: f64,
    /// Accelerometer white noise density (m/s²/√Hz).
    pub accelerometer_noise_density: f64,
    /// Accelerometer bias random walk (m/s³/√Hz).
    pub accelerometer_random_walk: f64,
    /// Gyroscope bias instability (rad/s): the Allan-deviation floor divided by 0.664.
    #[serde(default)]
    pub gyroscope_bias_instability: Option<f64>,
    /// Accelerometer bias instability (m/s²), same definition.
    #[serde(default)]
    pub accelerometer_bias_instability: Option<f64>,
    /// The IMU axes relative to the camera body, as measured (free text, e.g. `x5-imu`).
    pub axis_convention: String,
}

/// Audio-to-video delay of one recording mode (paper eq. 1, `eq:sync-av`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AvDelay {
    /// Recording mode name (matches a [`RecordingMode::name`]).
    pub mode: String,
    /// Delay `d` (s): a sound at video time `t` is heard at audio time `t + d`.
    pub delay_s: f64,
    /// Standard error of `delay_s` (s).
    pub std_s: f64,
    /// Number of rig recordings aggregated.
    pub repeats: u32,
}

/// Provenance: which tool wrote the set, when, and from which inputs.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Provenance {
    /// Tool name, e.g. `kiwi-calib certify`.
    pub tool: String,
    /// Tool version.
    pub tool_version: String,
    /// Creation time, UTC, RFC 3339.
    pub created_utc: String,
    /// Input files and their SHA-256.
    #[serde(default)]
    pub inputs: Vec<InputRecord>,
}

/// An input file of a calibration.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct InputRecord {
    /// Path as given (relative to the capture folder where possible).
    pub path: String,
    /// SHA-256 of the content, lowercase hex.
    pub sha256: String,
}

/// The certification verdict and the checks behind it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Certification {
    /// True when every check passed.
    pub passed: bool,
    /// Every check, passed or not.
    pub checks: Vec<Check>,
}

/// One certification check.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Check {
    /// What was checked, e.g. `front.rms_px`.
    pub name: String,
    /// The measured value.
    pub value: f64,
    /// The threshold it was held to.
    pub threshold: f64,
    /// `at_most` or `at_least`.
    pub comparison: String,
    /// Whether the value met the threshold.
    pub passed: bool,
}

impl UnitCalibration {
    /// Parse and validate a `calibration.json` file.
    pub fn load(path: &Path) -> Result<Self> {
        Self::from_json(&read_text(path)?, path)
    }

    /// Parse and validate JSON text; `path` names the source in errors.
    pub fn from_json(text: &str, path: &Path) -> Result<Self> {
        let probe: serde_json::Value = serde_json::from_str(text).map_err(|e| CoreError::Parse {
            path: path.to_path_buf(),
            format: "JSON",
            field: format!("line {}, column {}", e.line(), e.column()),
            message: e.to_string(),
            fix: "the file is not valid JSON (NaN and Infinity are not JSON numbers); re-export it".into(),
        })?;
        let version = probe.get("schema_version");
        match version.and_then(serde_json::Value::as_u64) {
            Some(v) if v == u64::from(SCHEMA_VERSION) => {}
            Some(v) => {
                return Err(CoreError::Invalid {
                    path: path.to_path_buf(),
                    field: "schema_version".into(),
                    expected: format!("{SCHEMA_VERSION}"),
                    found: v.to_string(),
                    fix: if v > u64::from(SCHEMA_VERSION) {
                        "the file was written by a newer KIWI; upgrade kiwi".into()
                    } else {
                        "re-run the calibration with this KIWI version".into()
                    },
                });
            }
            None => {
                return Err(CoreError::Invalid {
                    path: path.to_path_buf(),
                    field: "schema_version".into(),
                    expected: format!("the integer {SCHEMA_VERSION}"),
                    found: version.map_or_else(|| "no such field".into(), ToString::to_string),
                    fix: "is this a KIWI calibration.json? Kalibr files are imported with `kiwi-calib import-kalibr`".into(),
                });
            }
        }
        let calibration: Self = serde_path_to_error::deserialize(probe).map_err(|e| {
            let (field, message) =
                describe_serde_error(&e.path().to_string(), &e.inner().to_string());
            CoreError::Parse {
                path: path.to_path_buf(),
                format: "KIWI calibration JSON",
                field,
                message,
                fix: "see docs/conventions.md for the artifact fields".into(),
            }
        })?;
        calibration.validate().map_err(|e| e.at_path(path))?;
        Ok(calibration)
    }

    /// Serialize to pretty JSON.
    pub fn to_json(&self) -> Result<String> {
        serde_json::to_string_pretty(self).map_err(|e| {
            CoreError::invalid_value(
                "calibration",
                "finite, serializable values",
                e.to_string(),
                "validate before saving",
            )
        })
    }

    /// Validate, then write atomically.
    pub fn save(&self, path: &Path) -> Result<()> {
        self.validate().map_err(|e| e.at_path(path))?;
        write_atomic(path, self.to_json()?.as_bytes())
    }

    /// The lens with this name.
    pub fn lens(&self, name: &str) -> Option<&LensCalibration> {
        self.lenses.iter().find(|l| l.name == name)
    }

    /// What `kiwi` needs for reconstruction and this calibration lacks (field paths): the IMU
    /// noise block, and each lens's `cam_from_imu` and `time_shift_s`. Empty when complete; a
    /// calibration in progress (intrinsics only, a Kalibr import without imu.yaml) is valid
    /// but not complete.
    pub fn missing_for_reconstruction(&self) -> Vec<String> {
        let mut missing = Vec::new();
        if self.imu.is_none() {
            missing.push("imu (the IMU noise model: `kiwi-calib imu-noise`)".to_string());
        }
        for (i, lens) in self.lenses.iter().enumerate() {
            if lens.cam_from_imu.is_none() {
                missing.push(format!(
                    "lenses[{i}].cam_from_imu ({}: `kiwi-calib cam-imu`)",
                    lens.name
                ));
            }
            if lens.time_shift_s.is_none() {
                missing.push(format!("lenses[{i}].time_shift_s ({})", lens.name));
            }
        }
        missing
    }

    /// Check every field; errors name the field path.
    pub fn validate(&self) -> Result<()> {
        if self.schema_version != SCHEMA_VERSION {
            return Err(CoreError::invalid_value(
                "schema_version",
                SCHEMA_VERSION.to_string(),
                self.schema_version.to_string(),
                "write the current schema version",
            ));
        }
        if self.unit_id.trim().is_empty() || self.unit_id.contains(['/', '\\']) {
            return Err(CoreError::invalid_value(
                "unit_id",
                "a non-empty name without path separators",
                format!("`{}`", self.unit_id),
                "use the unit's serial number",
            ));
        }
        validate_date(&self.date)?;
        for (i, mode) in self.recording_modes.iter().enumerate() {
            let field = format!("recording_modes[{i}]");
            positive(&format!("{field}.fps"), mode.fps, "Hz")?;
            if let Some(r) = mode.readout_time_s {
                non_negative(&format!("{field}.readout_time_s"), r, "s")?;
            }
        }
        if self.lenses.is_empty() {
            return Err(CoreError::invalid_value(
                "lenses",
                "at least one lens",
                "none",
                "add the lens calibrations",
            ));
        }
        for (i, lens) in self.lenses.iter().enumerate() {
            lens.validate(&format!("lenses[{i}]"))?;
            if self.lenses[..i].iter().any(|l| l.name == lens.name) {
                return Err(CoreError::invalid_value(
                    format!("lenses[{i}].name"),
                    "a name not used by another lens",
                    format!("`{}` twice", lens.name),
                    "name each lens once (front, rear)",
                ));
            }
        }
        if let Some(imu) = &self.imu {
            positive("imu.rate_hz", imu.rate_hz, "Hz")?;
            positive(
                "imu.gyroscope_noise_density",
                imu.gyroscope_noise_density,
                "rad/s/√Hz",
            )?;
            positive(
                "imu.gyroscope_random_walk",
                imu.gyroscope_random_walk,
                "rad/s²/√Hz",
            )?;
            positive(
                "imu.accelerometer_noise_density",
                imu.accelerometer_noise_density,
                "m/s²/√Hz",
            )?;
            positive(
                "imu.accelerometer_random_walk",
                imu.accelerometer_random_walk,
                "m/s³/√Hz",
            )?;
            if let Some(b) = imu.gyroscope_bias_instability {
                non_negative("imu.gyroscope_bias_instability", b, "rad/s")?;
            }
            if let Some(b) = imu.accelerometer_bias_instability {
                non_negative("imu.accelerometer_bias_instability", b, "m/s²")?;
            }
        }
        for (i, d) in self.av_delays.iter().enumerate() {
            finite(&format!("av_delays[{i}].delay_s"), d.delay_s, "s")?;
            non_negative(&format!("av_delays[{i}].std_s"), d.std_s, "s")?;
        }
        if let Some(c) = &self.certification {
            for (i, check) in c.checks.iter().enumerate() {
                finite(&format!("certification.checks[{i}].value"), check.value, "")?;
                finite(
                    &format!("certification.checks[{i}].threshold"),
                    check.threshold,
                    "",
                )?;
                if check.comparison != "at_most" && check.comparison != "at_least" {
                    return Err(CoreError::invalid_value(
                        format!("certification.checks[{i}].comparison"),
                        "`at_most` or `at_least`",
                        format!("`{}`", check.comparison),
                        "fix the comparison name",
                    ));
                }
            }
        }
        Ok(())
    }
}

impl LensCalibration {
    /// The validated camera model of this lens.
    pub fn camera(&self) -> Result<Camera> {
        self.intrinsics
            .camera(self.resolution[0], self.resolution[1])
    }

    /// `cam_from_imu` as a pose, if calibrated.
    pub fn cam_from_imu(&self) -> Option<Pose> {
        self.cam_from_imu.as_ref().and_then(|t| t.to_pose().ok())
    }

    fn validate(&self, field: &str) -> Result<()> {
        if !LENS_NAMES.contains(&self.name.as_str()) {
            return Err(CoreError::invalid_value(
                format!("{field}.name"),
                "a lens name: front, rear (X5) or main (GO 3)",
                format!("`{}`", self.name),
                "name the lens as the camera's folders do (a Kalibr import names cam0 front, \
                 cam1 rear)",
            ));
        }
        let names = self.intrinsics.param_names();
        let values = self.intrinsics.params();
        for (name, value) in names.iter().zip(&values) {
            finite(&format!("{field}.intrinsics.{name}"), *value, "")?;
        }
        for name in ["fx", "fy"] {
            let idx = if name == "fx" { 0 } else { 1 };
            if values[idx] <= 0.0 {
                return Err(CoreError::invalid_value(
                    format!("{field}.intrinsics.{name}"),
                    "a positive focal length in pixels",
                    values[idx].to_string(),
                    "focal lengths are in pixels and must be > 0; check the sign and units",
                ));
            }
        }
        if self.resolution[0] == 0 || self.resolution[1] == 0 {
            return Err(CoreError::invalid_value(
                format!("{field}.resolution"),
                "[width, height] in pixels, both > 0",
                format!("{:?}", self.resolution),
                "set the lens image size",
            ));
        }
        let (w, h) = (f64::from(self.resolution[0]), f64::from(self.resolution[1]));
        for (name, value, size) in [("cx", values[2], w), ("cy", values[3], h)] {
            if !(-0.5..size - 0.5).contains(&value) {
                return Err(CoreError::invalid_value(
                    format!("{field}.intrinsics.{name}"),
                    format!(
                        "a principal point inside the {w} × {h} image (-0.5 to {})",
                        size - 0.5
                    ),
                    format!("{value} px"),
                    "check that the intrinsics belong to this resolution (a calibration at \
                     another image size must be rescaled)",
                ));
            }
        }
        self.camera().map_err(|e| match e {
            CoreError::Invalid {
                field: f,
                expected,
                found,
                fix,
                ..
            } => CoreError::invalid_value(
                format!("{field}.intrinsics.{}", f.rsplit('.').next().unwrap_or(&f)),
                expected,
                found,
                fix,
            ),
            other => other,
        })?;
        if !(self.valid_fov_rad > 0.0 && self.valid_fov_rad <= 2.0 * std::f64::consts::PI) {
            return Err(CoreError::invalid_value(
                format!("{field}.valid_fov_rad"),
                "an angle in (0, 2π] radians",
                self.valid_fov_rad.to_string(),
                "the field of view is in radians (190° = 3.316 rad)",
            ));
        }
        if let Some(rms) = self.rms_px {
            non_negative(&format!("{field}.rms_px"), rms, "px")?;
        }
        if let Some(std) = &self.param_std {
            if std.len() != values.len() {
                return Err(CoreError::invalid_value(
                    format!("{field}.param_std"),
                    format!("{} values, one per parameter", values.len()),
                    format!("{} values", std.len()),
                    "write one standard deviation per intrinsic parameter",
                ));
            }
            for (i, s) in std.iter().enumerate() {
                non_negative(&format!("{field}.param_std[{i}]"), *s, "")?;
            }
        }
        if let Some(t) = &self.cam_from_imu {
            t.to_pose().map_err(|found| {
                CoreError::invalid_value(
                    format!("{field}.cam_from_imu.rotation"),
                    "a proper rotation matrix (orthonormal rows, determinant +1)",
                    found,
                    "write all 9 entries with at least 9 significant digits; re-export from the calibration",
                )
            })?;
            let distance = t.translation_m.iter().map(|v| v * v).sum::<f64>().sqrt();
            if distance.is_nan() || distance > MAX_CAM_IMU_DISTANCE_M {
                return Err(CoreError::invalid_value(
                    format!("{field}.cam_from_imu.translation_m"),
                    format!(
                        "a lens within {MAX_CAM_IMU_DISTANCE_M} m of its IMU (both sit in one \
                         camera body)"
                    ),
                    format!("{:?}, {distance} m away", t.translation_m),
                    "translations are in metres (not mm or cm); recalibrate with `kiwi-calib \
                     cam-imu` if the value is wrong",
                ));
            }
        }
        if let Some(s) = self.time_shift_s {
            finite(&format!("{field}.time_shift_s"), s, "s")?;
            if s.abs() > 1.0 {
                return Err(CoreError::invalid_value(
                    format!("{field}.time_shift_s"),
                    "a shift of at most 1 s",
                    format!("{s} s"),
                    "time shifts are in seconds (not ms or ns)",
                ));
            }
        }
        Ok(())
    }
}

/// The lens names a calibration may use: the X5's two lenses and the GO 3's one.
pub const LENS_NAMES: [&str; 3] = ["front", "rear", "main"];

/// A lens and its IMU sit in one camera body: an X5 is 5 cm across, so a camera–IMU distance
/// beyond this (m) is a unit mistake or a failed calibration.
pub const MAX_CAM_IMU_DISTANCE_M: f64 = 0.2;

/// Turn a serde error at `path` into (field path, message), naming a missing field itself.
fn describe_serde_error(path: &str, message: &str) -> (String, String) {
    let field = if let Some(rest) = message.strip_prefix("missing field `")
        && let Some(name) = rest.split('`').next()
    {
        if path == "." || path.is_empty() {
            name.to_string()
        } else {
            format!("{path}.{name}")
        }
    } else {
        path.to_string()
    };
    (field, message.to_string())
}

fn finite(field: &str, value: f64, unit: &str) -> Result<()> {
    if value.is_finite() {
        Ok(())
    } else {
        Err(CoreError::invalid_value(
            field,
            format!(
                "a finite number{}",
                if unit.is_empty() {
                    String::new()
                } else {
                    format!(" in {unit}")
                }
            ),
            value.to_string(),
            "re-run the step that wrote it, or fix the file",
        ))
    }
}

fn positive(field: &str, value: f64, unit: &str) -> Result<()> {
    finite(field, value, unit)?;
    if value > 0.0 {
        Ok(())
    } else {
        Err(CoreError::invalid_value(
            field,
            format!("a positive value in {unit}"),
            value.to_string(),
            "check the sign and units",
        ))
    }
}

fn non_negative(field: &str, value: f64, unit: &str) -> Result<()> {
    finite(field, value, unit)?;
    if value >= 0.0 {
        Ok(())
    } else {
        Err(CoreError::invalid_value(
            field,
            format!("a value ≥ 0 in {unit}"),
            value.to_string(),
            "check the sign",
        ))
    }
}

/// Check a `YYYY-MM-DD` date: a real calendar day (2026-02-30 is not one).
pub fn validate_date(date: &str) -> Result<()> {
    let parts: Vec<&str> = date.split('-').collect();
    let numbers = (parts.len() == 3
        && parts[0].len() == 4
        && parts[1].len() == 2
        && parts[2].len() == 2
        && parts.iter().all(|p| p.chars().all(|c| c.is_ascii_digit())))
    .then(|| {
        (
            parts[0].parse::<u32>().ok(),
            parts[1].parse::<u32>().ok(),
            parts[2].parse::<u32>().ok(),
        )
    });
    let Some((Some(year), Some(month), Some(day))) = numbers else {
        return Err(CoreError::invalid_value(
            "date",
            "a date `YYYY-MM-DD`",
            format!("`{date}`"),
            "write the calibration date",
        ));
    };
    let days = days_in_month(year, month);
    if days == 0 || !(1..=days).contains(&day) {
        return Err(CoreError::invalid_value(
            "date",
            "a calendar date `YYYY-MM-DD`",
            format!(
                "`{date}` ({})",
                if days == 0 {
                    format!("there is no month {month}")
                } else {
                    format!("month {month} of {year} has {days} days")
                }
            ),
            "write the real date of the calibration",
        ));
    }
    Ok(())
}

/// Days in `month` (1–12) of `year` in the Gregorian calendar; 0 for a month that does not exist.
fn days_in_month(year: u32, month: u32) -> u32 {
    let leap = (year.is_multiple_of(4) && !year.is_multiple_of(100)) || year.is_multiple_of(400);
    match month {
        1 | 3 | 5 | 7 | 8 | 10 | 12 => 31,
        4 | 6 | 9 | 11 => 30,
        2 if leap => 29,
        2 => 28,
        _ => 0,
    }
}
