//! The head mount (`hardware/head/hat.toml`): where the hat's ArUco marker sits relative to the
//! head camera. The head's track is the marker's pose in the scene (seen by the wrists' rear
//! lenses); `marker_from_cam` turns it into the head camera's pose, so the head camera's video
//! frames get poses. The built-in mount is the printed hat's CAD geometry; a lab that measured
//! its own mount names its file in `session.toml` (`[head] mount`), as it would a tool's
//! `cam_from_tip`.

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::error::Result;
use crate::geometry::Pose;
use crate::tool::TransformDef;

/// Schema version of head mount files.
pub const HEAD_MOUNT_SCHEMA_VERSION: u32 = 1;

/// Where the built-in mount lives in the repository (named in messages).
pub const BUILTIN_HEAD_MOUNT_PATH: &str = "hardware/head/hat.toml";

const HAT: &str = include_str!("../../hardware/head/hat.toml");

/// A head mount file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HeadMount {
    /// [`HEAD_MOUNT_SCHEMA_VERSION`].
    pub schema_version: u32,
    /// Mount name.
    pub name: String,
    /// `marker_from_cam`: the head camera's lens frame (x right, y down, z forward) in the
    /// marker's frame (x right, y up along the printed marker, z out of its face; m).
    pub marker_from_cam: TransformDef,
}

impl HeadMount {
    /// The printed hat of `hardware/` (CAD geometry).
    pub fn builtin() -> Result<Self> {
        Self::parse(HAT, Path::new(BUILTIN_HEAD_MOUNT_PATH))
    }

    /// Read and validate a mount file.
    pub fn load(path: &Path) -> Result<Self> {
        let text = crate::io::read_text(path)?;
        Self::parse(&text, path)
    }

    /// Parse and validate mount text; `path` names it in errors.
    pub fn parse(text: &str, path: &Path) -> Result<Self> {
        let mount: Self = crate::io::parse_toml(
            text,
            path,
            "TOML head mount",
            "fix the syntax (compare with hardware/head/hat.toml)",
            "compare with hardware/head/hat.toml",
        )?;
        mount.validate().map_err(|e| e.at_path(path))?;
        Ok(mount)
    }

    /// Check the schema and the transform.
    pub fn validate(&self) -> Result<()> {
        if self.schema_version != HEAD_MOUNT_SCHEMA_VERSION {
            return Err(crate::error::CoreError::invalid_value(
                "schema_version",
                HEAD_MOUNT_SCHEMA_VERSION.to_string(),
                self.schema_version.to_string(),
                "write the file in the current schema (see hardware/head/hat.toml)",
            ));
        }
        self.marker_from_cam.validate(
            "marker_from_cam",
            "measure the mount again, or start from hardware/head/hat.toml",
        )
    }

    /// `marker_from_cam` as a pose.
    pub fn marker_from_cam(&self) -> Pose {
        self.marker_from_cam.to_pose()
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn the_builtin_mount_reads_and_round_trips() {
        let mount = HeadMount::builtin().unwrap();
        let text = crate::hardware::head_mount_toml(&mount);
        assert_eq!(HeadMount::parse(&text, Path::new("t")).unwrap(), mount);
        // The marker is above and ahead of the camera: the camera sits below and behind it.
        let cam_in_marker = mount.marker_from_cam().translation.vector;
        assert!(cam_in_marker.norm() > 0.05 && cam_in_marker.norm() < 0.3);
    }

    #[test]
    fn a_bad_rotation_names_the_field() {
        let text = HAT.replace("rotation = [[-1.0", "rotation = [[-2.0");
        assert_ne!(text, HAT);
        let e = HeadMount::parse(&text, Path::new("m.toml"))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("marker_from_cam.rotation") && e.contains("m.toml"),
            "{e}"
        );
    }
}
