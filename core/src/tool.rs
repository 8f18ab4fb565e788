//! Tool definitions (`hardware/tools/*.toml`): the geometry of a wrist tool in the front-lens
//! frame — hinge and jaws, the row of red dots on each jaw, the body ArUco tag and the
//! camera-to-tip transform. The simulator renders tools from these files and the gripper
//! estimator measures openings with them, so both read the same numbers.

use std::path::Path;

use nalgebra::{Isometry3, Matrix3, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

use crate::error::{CoreError, Result};
use crate::geometry::Pose;
use crate::layout::ToolKind;

/// Schema version of tool definition files.
pub const TOOL_SCHEMA_VERSION: u32 = 1;
/// Tolerance on unit lengths and perpendicularity of the definition's directions and rotation.
const ORTHO_TOL: f64 = 1e-6;

/// The pivot (chopstick) or rail centre (parallel jaw) and the dot plane's orientation.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HingeDef {
    /// Hinge position in the front-lens frame (m).
    pub in_front_m: [f64; 3],
    /// Direction the closed jaws point (normalized on load).
    pub jaw_direction: [f64; 3],
    /// Dot-plane normal, away from the camera (normalized on load).
    pub plane_normal: [f64; 3],
}

/// Jaw dimensions.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct JawsDef {
    /// Jaw length (m).
    pub length_m: f64,
    /// Hinge to the jaw's near end (m).
    pub offset_m: f64,
    /// Jaw centre plane to the dotted face (m).
    pub half_thickness_m: f64,
    /// Dot line to the jaw's inner face (m).
    pub half_width_m: f64,
    /// Widest opening: rad (chopstick) or m (parallel jaw).
    pub max_opening: f64,
}

/// The row of dots on each jaw.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DotsDef {
    /// Dots per jaw.
    pub count: usize,
    /// Centre-to-centre spacing (m).
    pub pitch_m: f64,
    /// Dot radius (m).
    pub radius_m: f64,
    /// Printed colour (sRGB).
    pub color_rgb: [u8; 3],
}

/// The body ArUco tag.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MarkerDef {
    /// ArUco dictionary name.
    pub dictionary: String,
    /// Tag id.
    pub id: usize,
    /// Side of the black square (m).
    pub size_m: f64,
    /// Tag centre behind the hinge along the jaw direction, in the jaw centre plane (m).
    pub behind_hinge_m: f64,
    /// The tag's printed face in front of the jaw centre plane, towards the camera (m): half
    /// the thickness of the plate it is printed on. Printed "up" points along the jaws.
    #[serde(default = "default_tag_face_offset")]
    pub face_offset_m: f64,
}

/// Default [`MarkerDef::face_offset_m`]: a tag on a 1.6 mm plate centred in the jaw plane.
fn default_tag_face_offset() -> f64 {
    0.0008
}

/// How the bench encoder's counts become the jaw opening (`[encoder]`, optional): the servo's
/// horn sits on the hinge (chopstick) or drives the plates (parallel jaw).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EncoderDef {
    /// Encoder count with the jaws closed.
    pub zero_count: f64,
    /// Counts per horn revolution (4096 on Feetech STS/SCS).
    #[serde(default = "default_counts_per_rev")]
    pub counts_per_rev: f64,
    /// Opening per horn radian: rad/rad for the chopstick (1 with the horn on the hinge, −1
    /// when it turns the other way), m/rad for the parallel jaw.
    pub opening_per_horn_rad: f64,
}

fn default_counts_per_rev() -> f64 {
    4096.0
}

impl EncoderDef {
    /// The opening (rad or m) at a raw encoder count.
    pub fn opening(&self, raw: f64) -> f64 {
        (raw - self.zero_count) / self.counts_per_rev
            * std::f64::consts::TAU
            * self.opening_per_horn_rad
    }
}

/// A rigid transform as written in the file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TransformDef {
    /// Rotation matrix, rows.
    pub rotation: [[f64; 3]; 3],
    /// Translation (m).
    pub translation_m: [f64; 3],
}

impl TransformDef {
    /// Check that the rotation is proper and the translation finite; `field` names the table in
    /// errors and `fix` says where to look.
    pub fn validate(&self, field: &str, fix: &str) -> Result<()> {
        let r = Matrix3::from_fn(|i, j| self.rotation[i][j]);
        let ortho = (r.transpose() * r - Matrix3::identity()).abs().max();
        if !(ortho < ORTHO_TOL * 10.0 && (r.determinant() - 1.0).abs() < ORTHO_TOL * 10.0) {
            return Err(CoreError::invalid_value(
                format!("{field}.rotation"),
                "a proper rotation matrix (orthonormal rows, determinant +1)",
                format!("|RᵀR − I| = {ortho:.2e}, det {:.6}", r.determinant()),
                fix,
            ));
        }
        if !self.translation_m.iter().all(|v| v.is_finite()) {
            return Err(CoreError::invalid_value(
                format!("{field}.translation_m"),
                "finite metres",
                format!("{:?}", self.translation_m),
                fix,
            ));
        }
        Ok(())
    }
}

/// A tool definition file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ToolDefinition {
    /// [`TOOL_SCHEMA_VERSION`].
    pub schema_version: u32,
    /// Tool name.
    pub name: String,
    /// Which tool.
    pub kind: ToolKind,
    /// Hinge and dot plane.
    pub hinge: HingeDef,
    /// Jaw dimensions.
    pub jaws: JawsDef,
    /// Dot layout.
    pub dots: DotsDef,
    /// Body tag.
    pub marker: MarkerDef,
    /// `front_from_tip` (the camera-to-tip transform).
    pub cam_from_tip: TransformDef,
    /// The bench encoder's count-to-opening map, when the tool has been on the servo bench.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub encoder: Option<EncoderDef>,
}

const CHOPSTICK: &str = include_str!("../../hardware/tools/chopstick.toml");
const PARALLEL_JAW: &str = include_str!("../../hardware/tools/parallel_jaw.toml");
const BARE_HAND: &str = include_str!("../../hardware/tools/bare_hand.toml");

fn unit3(v: [f64; 3]) -> Option<Vector3<f64>> {
    let v = Vector3::from(v);
    let n = v.norm();
    (n.is_finite() && n > 0.0).then(|| v / n)
}

impl ToolDefinition {
    /// The definition shipped in `hardware/tools/` for a kind of tool.
    pub fn builtin(kind: ToolKind) -> Result<Self> {
        let (name, text) = match kind {
            ToolKind::Chopstick => ("hardware/tools/chopstick.toml", CHOPSTICK),
            ToolKind::ParallelJaw => ("hardware/tools/parallel_jaw.toml", PARALLEL_JAW),
            ToolKind::BareHand => ("hardware/tools/bare_hand.toml", BARE_HAND),
        };
        Self::parse(text, Path::new(name))
    }

    /// Read and validate a definition file.
    pub fn load(path: &Path) -> Result<Self> {
        let text = crate::io::read_text(path)?;
        Self::parse(&text, path)
    }

    /// Parse and validate definition text; `path` names it in errors.
    pub fn parse(text: &str, path: &Path) -> Result<Self> {
        let def: Self = crate::io::parse_toml(
            text,
            path,
            "TOML tool definition",
            "fix the syntax (see hardware/tools/README.md)",
            "compare with hardware/tools/chopstick.toml and README.md there",
        )?;
        def.validate().map_err(|e| e.at_path(path))?;
        Ok(def)
    }

    /// Check every number (finite, positive where it must be, unit and perpendicular
    /// directions, a proper rotation).
    pub fn validate(&self) -> Result<()> {
        let bad = |field: &str, expected: &str, found: String| {
            Err(CoreError::invalid_value(
                field,
                expected,
                found,
                "measure it again as hardware/tools/README.md describes",
            ))
        };
        if self.schema_version != TOOL_SCHEMA_VERSION {
            return bad("schema_version", "1", self.schema_version.to_string());
        }
        let Some(d) = unit3(self.hinge.jaw_direction) else {
            return bad(
                "hinge.jaw_direction",
                "a non-zero finite vector",
                format!("{:?}", self.hinge.jaw_direction),
            );
        };
        let Some(n) = unit3(self.hinge.plane_normal) else {
            return bad(
                "hinge.plane_normal",
                "a non-zero finite vector",
                format!("{:?}", self.hinge.plane_normal),
            );
        };
        if d.dot(&n).abs() > ORTHO_TOL {
            return bad(
                "hinge.plane_normal",
                "perpendicular to hinge.jaw_direction",
                format!("cosine {:.3e}", d.dot(&n)),
            );
        }
        if !self.hinge.in_front_m.iter().all(|v| v.is_finite()) {
            return bad(
                "hinge.in_front_m",
                "finite metres",
                format!("{:?}", self.hinge.in_front_m),
            );
        }
        let positive = [
            ("jaws.length_m", self.jaws.length_m),
            ("jaws.half_thickness_m", self.jaws.half_thickness_m),
            ("jaws.half_width_m", self.jaws.half_width_m),
            ("dots.radius_m", self.dots.radius_m),
            ("marker.size_m", self.marker.size_m),
            ("marker.face_offset_m", self.marker.face_offset_m),
        ];
        for (field, v) in positive {
            if !(v.is_finite() && v > 0.0) {
                return bad(field, "a positive length in m", v.to_string());
            }
        }
        let non_negative = [
            ("jaws.offset_m", self.jaws.offset_m),
            ("jaws.max_opening", self.jaws.max_opening),
            ("dots.pitch_m", self.dots.pitch_m),
            ("marker.behind_hinge_m", self.marker.behind_hinge_m),
        ];
        for (field, v) in non_negative {
            if !(v.is_finite() && v >= 0.0) {
                return bad(field, "a finite value ≥ 0", v.to_string());
            }
        }
        if self.kind != ToolKind::BareHand {
            if self.dots.count < 2 {
                return bad(
                    "dots.count",
                    "at least 2 dots per jaw",
                    self.dots.count.to_string(),
                );
            }
            let span = self.dots.pitch_m * (self.dots.count - 1) as f64 + 2.0 * self.dots.radius_m;
            if span > self.jaws.length_m + 1e-9 || self.dots.pitch_m < 2.0 * self.dots.radius_m {
                return bad(
                    "dots.pitch_m",
                    "dots apart from each other and within the jaw length",
                    format!(
                        "pitch {} m, {} dots, jaw {} m",
                        self.dots.pitch_m, self.dots.count, self.jaws.length_m
                    ),
                );
            }
            if self.jaws.max_opening <= 0.0 {
                return bad(
                    "jaws.max_opening",
                    "a positive opening",
                    self.jaws.max_opening.to_string(),
                );
            }
        }
        if let Some(e) = &self.encoder {
            if !(e.zero_count.is_finite() && e.counts_per_rev.is_finite() && e.counts_per_rev > 0.0)
            {
                return bad(
                    "encoder.counts_per_rev",
                    "a finite zero_count and a positive counts_per_rev",
                    format!("{} and {}", e.zero_count, e.counts_per_rev),
                );
            }
            if !(e.opening_per_horn_rad.is_finite() && e.opening_per_horn_rad != 0.0) {
                return bad(
                    "encoder.opening_per_horn_rad",
                    "a finite non-zero gain",
                    e.opening_per_horn_rad.to_string(),
                );
            }
        }
        self.cam_from_tip.validate(
            "cam_from_tip",
            "measure it again as hardware/tools/README.md describes",
        )
    }

    /// Hinge position in the front-lens frame (m).
    pub fn hinge(&self) -> Vector3<f64> {
        Vector3::from(self.hinge.in_front_m)
    }

    /// Unit direction the closed jaws point.
    pub fn jaw_direction(&self) -> Vector3<f64> {
        unit3(self.hinge.jaw_direction).unwrap_or_else(Vector3::z)
    }

    /// Unit normal of the dot plane (away from the camera).
    pub fn plane_normal(&self) -> Vector3<f64> {
        unit3(self.hinge.plane_normal).unwrap_or_else(Vector3::y)
    }

    /// Dot positions along a jaw, measured from the jaw's middle (m).
    pub fn dot_positions_m(&self) -> Vec<f64> {
        let n = self.dots.count;
        (0..n)
            .map(|k| (k as f64 - (n as f64 - 1.0) / 2.0) * self.dots.pitch_m)
            .collect()
    }

    /// `front_from_tip`.
    pub fn cam_from_tip(&self) -> Pose {
        self.cam_from_tip.to_pose()
    }

    /// The tool's solid parts at an opening (rad for the chopstick, m for the parallel jaw), as
    /// boxes in the front-lens frame: each jaw (its dotted face included) and the body tag's
    /// plate. These parts move with the camera, so they are what a scene export masks out. The
    /// bare hand has none.
    pub fn solids(&self, opening: f64) -> Vec<ToolSolid> {
        if self.kind == ToolKind::BareHand {
            return Vec::new();
        }
        let hinge = self.hinge();
        let d0 = self.jaw_direction();
        let n = self.plane_normal();
        let jaw_half = Vector3::new(
            self.jaws.length_m / 2.0,
            self.jaws.half_thickness_m,
            self.jaws.half_width_m,
        );
        // A jaw's box: x along the jaw, y the dot plane's normal, z across the jaw.
        let jaw = |dir: Vector3<f64>, center: Vector3<f64>| ToolSolid {
            front_from_solid: Isometry3::from_parts(
                Translation3::from(center),
                UnitQuaternion::from_matrix(&Matrix3::from_columns(&[
                    dir,
                    n,
                    dir.cross(&n).normalize(),
                ])),
            ),
            half_m: jaw_half,
        };
        let mid = self.jaws.offset_m + self.jaws.length_m / 2.0;
        let mut solids: Vec<ToolSolid> = [-0.5, 0.5]
            .iter()
            .map(|s| match self.kind {
                ToolKind::Chopstick => {
                    let dir = UnitQuaternion::from_axis_angle(
                        &nalgebra::Unit::new_normalize(n),
                        s * opening,
                    ) * d0;
                    jaw(dir, hinge + dir * mid)
                }
                // The plates slide apart along the jaw plane's cross direction; the opening is
                // the gap between their inner faces.
                _ => {
                    let across = d0.cross(&n).normalize();
                    let offset = s * (opening + 2.0 * self.jaws.half_width_m);
                    jaw(d0, hinge + d0 * mid + across * offset)
                }
            })
            .collect();
        // The tag plate lies in the jaw plane behind the hinge, facing the camera.
        let tag_z = -n;
        let tag_x = d0.cross(&tag_z).normalize();
        let plate = self.marker.size_m * tag_plate_scale(&self.marker.dictionary);
        solids.push(ToolSolid {
            front_from_solid: Isometry3::from_parts(
                Translation3::from(hinge - d0 * self.marker.behind_hinge_m),
                UnitQuaternion::from_matrix(&Matrix3::from_columns(&[
                    tag_x,
                    tag_z.cross(&tag_x),
                    tag_z,
                ])),
            ),
            half_m: Vector3::new(plate / 2.0, plate / 2.0, self.marker.face_offset_m),
        });
        solids
    }

    /// Openings that sweep the tool's whole range (0 to `jaws.max_opening`) so closely that no
    /// point of a jaw moves further than the jaw is wide between two of them: the union of
    /// their [`solids`](Self::solids) covers every opening.
    pub fn sweep_openings(&self) -> Vec<f64> {
        let range = self.jaws.max_opening.max(0.0);
        let width = 2.0 * self.jaws.half_width_m;
        // How far the farthest jaw point moves per unit of opening.
        let reach = match self.kind {
            ToolKind::Chopstick => (self.jaws.offset_m + self.jaws.length_m) / 2.0,
            _ => 0.5,
        };
        let steps = if width > 0.0 {
            ((range * reach / width).ceil() as usize).clamp(1, MAX_SWEEP_STEPS)
        } else {
            MAX_SWEEP_STEPS
        };
        (0..=steps)
            .map(|k| range * k as f64 / steps as f64)
            .collect()
    }
}

/// Most openings [`ToolDefinition::sweep_openings`] returns (a guard against a degenerate
/// definition, far above the 10–20 the built-in tools need).
const MAX_SWEEP_STEPS: usize = 256;

/// Side of an ArUco tag's plate over its black square's side: an N×N dictionary's black square
/// is N + 2 modules wide and the printed plate adds one white module on each side.
fn tag_plate_scale(dictionary: &str) -> f64 {
    let bits = dictionary
        .split_once('x')
        .and_then(|(n, _)| n.parse::<f64>().ok())
        .unwrap_or(4.0);
    (bits + 4.0) / (bits + 2.0)
}

/// A solid part of a tool: a box rigid with the front camera.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ToolSolid {
    /// `front_from_solid`: the box's centre and axes in the front-lens frame.
    pub front_from_solid: Pose,
    /// Half extents along the box's axes (m).
    pub half_m: Vector3<f64>,
}

/// Schema version of tool calibration artifacts.
pub const TOOL_CALIBRATION_SCHEMA_VERSION: u32 = 1;

/// File name of a tool's calibration artifact.
pub fn tool_calibration_file_name(tool_name: &str, lens: &str) -> String {
    format!("tool_{tool_name}_{lens}.json")
}

/// Where a tool calibration of the unit calibrated by `calibration_json` lives by default:
/// `units/<unit>/tools/tool_<name>_<lens>.json` when the calibration is in a dated set (a set
/// is never written after it is created), else beside `calibration_json`.
pub fn default_tool_calibration_path(
    calibration_json: &Path,
    tool_name: &str,
    lens: &str,
) -> std::path::PathBuf {
    let folder = calibration_json
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    let file = tool_calibration_file_name(tool_name, lens);
    match crate::io::dated_set_containing(folder) {
        Some(set) => set
            .parent()
            .unwrap_or(Path::new("."))
            .join("tools")
            .join(file),
        None => folder.join(file),
    }
}

/// How well a tool calibration is supported by the frames it came from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ToolCalibrationQuality {
    /// Frames searched for the body tag.
    pub frames_searched: usize,
    /// Frames where the tag was found and used.
    pub frames_with_tag: usize,
    /// RMS of the tag corners' reprojection over all frames (source pixels).
    pub tag_rms_px: f64,
    /// Scatter of the per-frame tag normals about the joint fit (deg, RMS).
    pub tag_normal_spread_deg: f64,
    /// Scatter of the per-frame tag centres about the joint fit (m, RMS).
    pub tag_position_spread_m: f64,
    /// Jaw lines (one per jaw and frame) the hinge and jaw direction were refined from; 0
    /// when they come from the tag and the definition's offsets alone.
    pub jaw_lines: usize,
    /// RMS distance of the dots from their jaw lines (m); none when no jaw line was fitted
    /// (`jaw_lines` 0).
    pub dot_line_rms_m: Option<f64>,
    /// Angle between the calibrated and the definition's plane normal (deg).
    pub plane_tilt_from_definition_deg: f64,
    /// Angle between the calibrated and the definition's jaw direction (deg).
    pub jaw_direction_from_definition_deg: f64,
    /// Distance between the calibrated and the definition's hinge (m).
    pub hinge_shift_from_definition_m: f64,
}

/// A tool calibrated on one lens of one unit: the dot plane and hinge as the camera sees them
/// (from the body ArUco tag and the jaw dots), saved beside the unit's artifacts.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ToolCalibration {
    /// [`TOOL_CALIBRATION_SCHEMA_VERSION`].
    pub schema_version: u32,
    /// Unit the tool was calibrated on.
    pub unit_id: String,
    /// Lens that sees the tool.
    pub lens: String,
    /// Date of the unit calibration used (`YYYY-MM-DD`).
    pub unit_calibration_date: String,
    /// The tool definition as read (CAD numbers, the definition's `cam_from_tip`).
    pub definition: ToolDefinition,
    /// Calibrated hinge in the front-lens frame (m).
    pub hinge_in_front_m: [f64; 3],
    /// Calibrated direction of the closed jaws (unit).
    pub jaw_direction: [f64; 3],
    /// Calibrated dot-plane normal, away from the camera (unit).
    pub plane_normal: [f64; 3],
    /// `front_from_tag` of the body tag (x along the printed rows, y its printed up, z out of
    /// the printed face towards the camera; origin at the face centre).
    pub front_from_tag: TransformDef,
    /// `front_from_tip` moved with the calibrated tool body (the definition's tip offset).
    pub cam_from_tip: TransformDef,
    /// Support and change from the definition.
    pub quality: ToolCalibrationQuality,
}

fn transform_pose(t: &TransformDef) -> Pose {
    let r = Matrix3::from_fn(|i, j| t.rotation[i][j]);
    Isometry3::from_parts(
        Translation3::from(Vector3::from(t.translation_m)),
        UnitQuaternion::from_matrix(&r),
    )
}

impl TransformDef {
    /// The transform of a pose.
    pub fn from_pose(pose: &Pose) -> Self {
        let r = pose.rotation.to_rotation_matrix();
        let m = r.matrix();
        Self {
            rotation: [
                [m[(0, 0)], m[(0, 1)], m[(0, 2)]],
                [m[(1, 0)], m[(1, 1)], m[(1, 2)]],
                [m[(2, 0)], m[(2, 1)], m[(2, 2)]],
            ],
            translation_m: pose.translation.vector.into(),
        }
    }

    /// The pose of this transform.
    pub fn to_pose(&self) -> Pose {
        transform_pose(self)
    }
}

impl ToolDefinition {
    /// `front_from_body`: the tool body frame (origin at the hinge, x the jaw direction, y the
    /// plane normal) in the front-lens frame.
    pub fn front_from_body(&self) -> Pose {
        body_frame(self.hinge(), self.jaw_direction(), self.plane_normal())
    }
}

/// The body frame of a hinge, jaw direction and plane normal (orthonormalized).
pub fn body_frame(hinge: Vector3<f64>, jaw: Vector3<f64>, normal: Vector3<f64>) -> Pose {
    let z = jaw.cross(&normal).normalize();
    let y = z.cross(&jaw).normalize();
    let x = y.cross(&z);
    Isometry3::from_parts(
        Translation3::from(hinge),
        UnitQuaternion::from_matrix(&Matrix3::from_columns(&[x, y, z])),
    )
}

impl ToolCalibration {
    /// Read and validate an artifact.
    pub fn load(path: &Path) -> Result<Self> {
        let text = crate::io::read_text(path)?;
        Self::from_json(&text, path)
    }

    /// Parse and validate artifact text; `path` names it in errors.
    pub fn from_json(text: &str, path: &Path) -> Result<Self> {
        let mut de = serde_json::Deserializer::from_str(text);
        let cal: Self =
            serde_path_to_error::deserialize(&mut de).map_err(|e| CoreError::Parse {
                path: path.to_path_buf(),
                format: "JSON tool calibration",
                field: e.path().to_string(),
                message: e.inner().to_string(),
                fix: "write it again with `kiwi gripper --calibrate` (docs/gripper.md)".into(),
            })?;
        cal.validate().map_err(|e| e.at_path(path))?;
        Ok(cal)
    }

    /// Pretty JSON text.
    pub fn to_json(&self) -> Result<String> {
        serde_json::to_string_pretty(self).map_err(|e| {
            CoreError::invalid_value("tool calibration", "encodable numbers", e.to_string(), "")
        })
    }

    /// Check the schema, the definition, and that the calibrated directions are unit and
    /// perpendicular.
    pub fn validate(&self) -> Result<()> {
        let bad = |field: &str, expected: &str, found: String| {
            Err(CoreError::invalid_value(
                field,
                expected,
                found,
                "calibrate the tool again with `kiwi gripper --calibrate`",
            ))
        };
        if self.schema_version != TOOL_CALIBRATION_SCHEMA_VERSION {
            return bad("schema_version", "1", self.schema_version.to_string());
        }
        self.definition.validate()?;
        for (field, v) in [
            ("jaw_direction", self.jaw_direction),
            ("plane_normal", self.plane_normal),
        ] {
            let n = Vector3::from(v).norm();
            if !(n.is_finite() && (n - 1.0).abs() < ORTHO_TOL * 10.0) {
                return bad(field, "a unit vector", format!("{v:?}"));
            }
        }
        let c = Vector3::from(self.jaw_direction).dot(&Vector3::from(self.plane_normal));
        if c.abs() > ORTHO_TOL * 10.0 {
            return bad(
                "plane_normal",
                "perpendicular to jaw_direction",
                format!("cosine {c:.3e}"),
            );
        }
        if !self.hinge_in_front_m.iter().all(|v| v.is_finite()) {
            return bad(
                "hinge_in_front_m",
                "finite metres",
                format!("{:?}", self.hinge_in_front_m),
            );
        }
        for (field, t) in [
            ("front_from_tag", &self.front_from_tag),
            ("cam_from_tip", &self.cam_from_tip),
        ] {
            let r = Matrix3::from_fn(|i, j| t.rotation[i][j]);
            let ortho = (r.transpose() * r - Matrix3::identity()).abs().max();
            let finite = t.translation_m.iter().all(|v| v.is_finite());
            if !(finite && ortho < 1e-5 && (r.determinant() - 1.0).abs() < 1e-5) {
                return bad(
                    field,
                    "a proper rotation and finite translation",
                    format!("|RᵀR − I| = {ortho:.2e}"),
                );
            }
        }
        Ok(())
    }

    /// The tool definition with the calibrated hinge, jaw direction, plane normal and tip: what
    /// the estimator measures with.
    pub fn calibrated_definition(&self) -> ToolDefinition {
        let mut def = self.definition.clone();
        def.hinge = HingeDef {
            in_front_m: self.hinge_in_front_m,
            jaw_direction: self.jaw_direction,
            plane_normal: self.plane_normal,
        };
        def.cam_from_tip = self.cam_from_tip.clone();
        def
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn builtin_definitions_load_and_are_consistent() {
        for kind in [
            ToolKind::Chopstick,
            ToolKind::ParallelJaw,
            ToolKind::BareHand,
        ] {
            let d = ToolDefinition::builtin(kind).unwrap();
            assert_eq!(d.kind, kind);
            // The tip lies on the jaw direction from the hinge.
            let tip = d.cam_from_tip().translation.vector - d.hinge();
            assert!(
                tip.normalize().dot(&d.jaw_direction()) > 1.0 - 1e-8,
                "{kind:?}"
            );
            // The tip frame's z is the jaw direction.
            let z = d.cam_from_tip().rotation * Vector3::z();
            assert!((z - d.jaw_direction()).norm() < 1e-8);
        }
        let c = ToolDefinition::builtin(ToolKind::Chopstick).unwrap();
        let tip = c.cam_from_tip().translation.vector - c.hinge();
        assert!((tip.norm() - (c.jaws.offset_m + c.jaws.length_m)).abs() < 1e-8);
        assert_eq!(c.dot_positions_m().len(), 8);
        assert!((c.dot_positions_m()[0] + 0.07).abs() < 1e-12);
    }

    #[test]
    fn errors_name_the_field() {
        let text = CHOPSTICK.replace("radius_m = 0.0028", "radius_m = -1.0");
        let e = ToolDefinition::parse(&text, Path::new("x.toml")).unwrap_err();
        assert_eq!(e.field(), Some("dots.radius_m"));
        assert!(e.to_string().contains("x.toml"));
        let text = CHOPSTICK.replace(
            "plane_normal = [0.0, 1.0, -0.5]",
            "plane_normal = [0.0, 1.0, 0.0]",
        );
        let e = ToolDefinition::parse(&text, Path::new("x.toml")).unwrap_err();
        assert_eq!(e.field(), Some("hinge.plane_normal"));
        let text = CHOPSTICK.replace("count = 8", "count = 8\nextra = 1");
        let e = ToolDefinition::parse(&text, Path::new("x.toml")).unwrap_err();
        assert!(e.to_string().contains("extra"), "{e}");
    }
}
