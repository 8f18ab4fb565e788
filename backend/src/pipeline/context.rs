//! What every stage of a session reads once: `session.toml`, each wrist's certified unit
//! calibration (both lenses' `cam_from_imu` and time shifts, the IMU noise) and its tool.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use kiwi_core::artifact::UnitCalibration;
use kiwi_core::layout::{EpisodeLayout, Session, Side, ToolKind};
use kiwi_core::tool::ToolDefinition;

use crate::error::{BackendError, Result};
use crate::formats::calibration::{LensImuCalibration, imu_params, lens_calibration};
use crate::fusion::preint::ImuParams;

/// One wrist's unit and tool.
#[derive(Debug, Clone)]
pub struct WristContext {
    /// Which wrist.
    pub side: Side,
    /// Its camera folder name in episodes (`left`, `right`).
    pub camera: &'static str,
    /// The unit's `calibration.json`.
    pub calibration_path: PathBuf,
    /// The unit calibration.
    pub calibration: UnitCalibration,
    /// Front lens: `cam_from_imu`, time shift.
    pub front: LensImuCalibration,
    /// Rear lens: `cam_from_imu`, time shift.
    pub rear: LensImuCalibration,
    /// IMU noise model of the unit.
    pub imu: ImuParams,
    /// The tool definition (`None` for the bare-hand cuff, which has no jaws to measure).
    pub tool: Option<ToolDefinition>,
    /// `cam_from_tip` of the tool (front lens to tool tip; for the bare-hand cuff, the hand's
    /// reference point).
    pub cam_from_tip: kiwi_core::geometry::Pose,
    /// The tool kind named in `session.toml`.
    pub tool_kind: ToolKind,
}

impl WristContext {
    /// `E_a = rear_from_front` (paper eq. 2).
    pub fn rear_from_front(&self) -> kiwi_core::geometry::Pose {
        self.rear.cam_from_imu * self.front.cam_from_imu.inverse()
    }

    /// Whether the unit's calibration set carries a passed certification.
    pub fn certified(&self) -> bool {
        self.calibration
            .certification
            .as_ref()
            .is_some_and(|c| c.passed)
    }
}

/// A session, loaded and checked.
#[derive(Debug, Clone)]
pub struct SessionContext {
    /// The session folder.
    pub root: PathBuf,
    /// `session.toml`.
    pub toml: PathBuf,
    /// Its contents.
    pub session: Session,
    /// Wrists by side.
    pub wrists: BTreeMap<Side, WristContext>,
    /// The session's remembered input digests.
    pub digests: std::sync::Arc<super::digests::DigestCache>,
}

fn input(path: &Path, message: String) -> BackendError {
    BackendError::Input {
        path: path.to_path_buf(),
        message,
    }
}

impl SessionContext {
    /// Load `session.toml` and every wrist's calibration and tool.
    pub fn load(session_toml: &Path) -> Result<Self> {
        if session_toml.is_dir() {
            return Err(input(
                session_toml,
                "is a folder; expected the session's session.toml (e.g. SESSION/session.toml)"
                    .into(),
            ));
        }
        let session = Session::load(session_toml)?;
        let root = session_toml
            .parent()
            .filter(|p| !p.as_os_str().is_empty())
            .unwrap_or(Path::new("."))
            .to_path_buf();
        session.check_files(&root)?;
        let mut wrists = BTreeMap::new();
        for (&side, w) in &session.wrists {
            let calibration_path = root.join(&w.calibration).join("calibration.json");
            let calibration = UnitCalibration::load(&calibration_path)?;
            if calibration.unit_id != w.unit {
                return Err(input(
                    &calibration_path,
                    format!(
                        "is the calibration of unit {}, but session.toml puts unit {} on the {} \
                         wrist (wrists.{}.calibration); point it at that unit's calibration set",
                        calibration.unit_id,
                        w.unit,
                        side.camera_name(),
                        side.camera_name()
                    ),
                ));
            }
            let front = lens_calibration(&calibration, &calibration_path, "front")?;
            let rear = lens_calibration(&calibration, &calibration_path, "rear")?;
            let imu = imu_params(None, Some((&calibration_path, &front)))?;
            let definition = ToolDefinition::builtin(w.tool)?;
            let cam_from_tip = definition.cam_from_tip();
            let tool = (w.tool != ToolKind::BareHand).then_some(definition);
            wrists.insert(
                side,
                WristContext {
                    side,
                    camera: side.camera_name(),
                    calibration_path,
                    calibration,
                    front,
                    rear,
                    imu,
                    tool,
                    cam_from_tip,
                    tool_kind: w.tool,
                },
            );
        }
        Ok(Self {
            digests: std::sync::Arc::new(super::digests::DigestCache::load(&root)),
            root,
            toml: session_toml.to_path_buf(),
            session,
            wrists,
        })
    }

    /// The wrist whose rear lens builds the shared rear map.
    pub fn map_side(&self) -> Side {
        self.session.map_side()
    }

    /// An episode's folder layout.
    pub fn episode(&self, name: &str) -> EpisodeLayout {
        EpisodeLayout::new(self.session.episode_dir(&self.root, name))
    }

    /// Episode names in `session.toml` order.
    pub fn episode_names(&self) -> Vec<String> {
        self.session
            .episodes
            .iter()
            .map(|e| e.name.clone())
            .collect()
    }

    /// A path relative to the session folder, for manifests and messages.
    pub fn relative(&self, path: &Path) -> String {
        path.strip_prefix(&self.root)
            .unwrap_or(path)
            .to_string_lossy()
            .replace('\\', "/")
    }
}
