//! Export a unit calibration to Kalibr and Basalt files, and import a Kalibr calibration.

use std::path::{Path, PathBuf};

use kiwi_core::artifact::{InputRecord, LENS_NAMES, Provenance, SCHEMA_VERSION, UnitCalibration};
use kiwi_core::io::{sha256_file, utc_now_rfc3339, write_atomic};
use kiwi_core::{basalt, kalibr};

use crate::error::{CalibError, Result};

/// Files written by [`export_all`].
#[derive(Debug, Clone, serde::Serialize)]
pub struct ExportedFiles {
    /// Kalibr `camchain-imucam.yaml`.
    pub kalibr_camchain: PathBuf,
    /// Kalibr `imu.yaml`, if the unit has an IMU noise model.
    pub kalibr_imu: Option<PathBuf>,
    /// Basalt `calibration.json`, if the unit has everything Basalt needs.
    pub basalt: Option<PathBuf>,
    /// Why an export was skipped.
    pub skipped: Vec<String>,
}

/// Write Kalibr and Basalt files for a calibration into `out_dir`. Exports the calibration
/// cannot support yet (no IMU model, no extrinsics) are skipped with the reason recorded.
pub fn export_all(calibration: &UnitCalibration, out_dir: &Path) -> Result<ExportedFiles> {
    let kalibr_camchain = out_dir.join("camchain-imucam.yaml");
    write_atomic(
        &kalibr_camchain,
        kalibr::camchain_yaml(calibration).as_bytes(),
    )?;
    let mut skipped = Vec::new();
    let kalibr_imu = match &calibration.imu {
        Some(imu) => {
            let path = out_dir.join("imu.yaml");
            write_atomic(&path, kalibr::imu_yaml(imu).as_bytes())?;
            Some(path)
        }
        None => {
            skipped.push(
                "imu.yaml: the unit has no IMU noise model yet (run `kiwi-calib imu-noise`)".into(),
            );
            None
        }
    };
    let basalt = match basalt::calibration_json(calibration) {
        Ok(text) => {
            let path = out_dir.join("basalt_calibration.json");
            write_atomic(&path, text.as_bytes())?;
            Some(path)
        }
        Err(e) => {
            skipped.push(format!("basalt_calibration.json: {e}"));
            None
        }
    };
    Ok(ExportedFiles {
        kalibr_camchain,
        kalibr_imu,
        basalt,
        skipped,
    })
}

/// Which KIWI lens a Kalibr camera became.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize)]
pub struct LensMapping {
    /// The camera's key in the camchain (`cam0`, …).
    pub kalibr: String,
    /// The lens name in `calibration.json`.
    pub lens: String,
}

/// Build a KIWI calibration from Kalibr files (camchain or camchain-imucam, optional imu.yaml).
/// Cameras whose `rostopic` names a KIWI lens keep that name; the others are named in `camN`
/// order from `lens_names` (default: `main` for a one-camera GO 3, else `front`, `rear`).
pub fn import_kalibr(
    camchain: &Path,
    imu_path: Option<&Path>,
    unit_id: &str,
    camera_model: &str,
    date: &str,
    lens_names: Option<&[String]>,
) -> Result<(UnitCalibration, Vec<LensMapping>)> {
    let text = kiwi_core::io::read_text(camchain)?;
    let mut lenses = kalibr::lenses_from_camchain(&text, camchain)?;
    let defaults: Vec<String> = match lens_names {
        Some(names) => names.to_vec(),
        None if lenses.len() == 1 && camera_model.to_ascii_uppercase().contains("GO") => {
            vec!["main".into()]
        }
        None => vec!["front".into(), "rear".into()],
    };
    let mut mapping = Vec::new();
    for (i, lens) in lenses.iter_mut().enumerate() {
        let kalibr_name = format!("cam{i}");
        let keep = lens_names.is_none() && LENS_NAMES.contains(&lens.name.as_str());
        if !keep {
            lens.name = defaults.get(i).cloned().ok_or_else(|| CalibError::Input {
                path: camchain.to_path_buf(),
                message: format!(
                    "{kalibr_name} has no KIWI lens name: the camchain has {} cameras but {} \
                     names were given ({}); pass --lenses with one of front, rear, main per camera",
                    i + 1,
                    defaults.len(),
                    defaults.join(",")
                ),
            })?;
        }
        mapping.push(LensMapping {
            kalibr: kalibr_name,
            lens: lens.name.clone(),
        });
    }
    let imu = match imu_path {
        Some(p) => Some(kalibr::imu_from_yaml(&kiwi_core::io::read_text(p)?, p)?),
        None => None,
    };
    let mut inputs = vec![InputRecord {
        path: camchain.display().to_string(),
        sha256: sha256_file(camchain)?,
    }];
    if let Some(p) = imu_path {
        inputs.push(InputRecord {
            path: p.display().to_string(),
            sha256: sha256_file(p)?,
        });
    }
    let calibration = UnitCalibration {
        schema_version: SCHEMA_VERSION,
        unit_id: unit_id.to_string(),
        camera_model: camera_model.to_string(),
        firmware: "unknown (imported from Kalibr)".into(),
        date: date.to_string(),
        recording_modes: Vec::new(),
        lenses,
        imu,
        av_delays: Vec::new(),
        provenance: Provenance {
            tool: "kiwi-calib import-kalibr".into(),
            tool_version: env!("CARGO_PKG_VERSION").into(),
            created_utc: utc_now_rfc3339(),
            inputs,
        },
        certification: None,
    };
    calibration.validate()?;
    Ok((calibration, mapping))
}
