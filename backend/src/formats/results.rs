//! `metric.json` and `placement.json`: the results of metric recovery ([`crate::metric`]) and
//! scene placement ([`crate::placement`]) as files, and the typed steps that produce them from a
//! lens's localizations (`poses.csv` rows), the IMU log and the unit calibration.
//!
//! `metric.json` holds `world_from_map` (the similarity that makes the map metric and z-up), the
//! scale, gravity in the map, the biases and how well the recording determined them;
//! `kiwi place` can read it to make either map metric before placing the front map in the scene.

use std::path::Path;

use kiwi_core::geometry::Pose;
use kiwi_core::imu::ImuSeries;
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

use super::calibration::LensImuCalibration;
use super::tables::Localization;
use crate::error::{BackendError, Result};
use crate::fusion::preint::ImuParams;
use crate::metric::{Conditioning, MapFrame, MetricConfig, recover_metric};
use crate::placement::{PlacementConfig, PlacementPair, place};
use crate::vision::align::Sim3;

/// Schema of `metric.json` and `placement.json`.
pub const SCHEMA_VERSION: u32 = 1;
/// Front and rear frames of one X5 closer than this (on the IMU clock) are one pair: both lenses
/// expose together, so they differ only by the per-lens time shifts (well under a millisecond).
const MAX_PAIR_DT_S: f64 = 2e-3;

fn input(path: &Path, message: String) -> BackendError {
    BackendError::Input {
        path: path.to_path_buf(),
        message,
    }
}

/// A similarity `x ↦ s R x + t` as stored in JSON.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SimilarityJson {
    /// Scale (metres per map unit).
    pub scale: f64,
    /// Rotation quaternion `[qx, qy, qz, qw]`.
    pub rotation_xyzw: [f64; 4],
    /// Translation (m).
    pub translation_m: [f64; 3],
}

impl SimilarityJson {
    /// From a similarity.
    pub fn from_sim3(s: &Sim3) -> Self {
        let q = s.rotation.quaternion();
        Self {
            scale: s.scale,
            rotation_xyzw: [q.i, q.j, q.k, q.w],
            translation_m: [s.translation.x, s.translation.y, s.translation.z],
        }
    }

    /// To a similarity; `path` names the file in the error when the values are invalid.
    pub fn to_sim3(self, path: &Path) -> Result<Sim3> {
        let [x, y, z, w] = self.rotation_xyzw;
        let q = Quaternion::new(w, x, y, z);
        let finite = self.scale.is_finite()
            && self.rotation_xyzw.iter().all(|v| v.is_finite())
            && self.translation_m.iter().all(|v| v.is_finite());
        if !finite || self.scale <= 0.0 || (q.norm() - 1.0).abs() > 1e-6 {
            return Err(input(
                path,
                "world_from_map: expected a positive finite scale and a unit quaternion; \
                 re-run kiwi metric"
                    .into(),
            ));
        }
        Ok(Sim3 {
            scale: self.scale,
            rotation: UnitQuaternion::from_quaternion(q),
            translation: Vector3::from(self.translation_m),
        })
    }
}

/// Contents of `metric.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MetricFile {
    /// [`SCHEMA_VERSION`].
    pub schema_version: u32,
    /// Lens whose localizations were used.
    pub lens: String,
    /// `world_from_map`: metric, gravity along −z.
    pub world_from_map: SimilarityJson,
    /// Metres per map unit.
    pub scale_m_per_map_unit: f64,
    /// Unit gravity direction in map coordinates.
    pub gravity_in_map: [f64; 3],
    /// Accelerometer bias at mid-recording (m/s²).
    pub accel_bias_m_s2: [f64; 3],
    /// Its 1-σ (m/s²).
    pub accel_bias_sigma_m_s2: [f64; 3],
    /// Gyroscope bias at mid-recording (rad/s).
    pub gyro_bias_rad_s: [f64; 3],
    /// How well the recording determined scale and gravity.
    pub conditioning: ConditioningJson,
    /// Valid localizations used.
    pub frames_used: usize,
    /// Rows reported lost (not used).
    pub frames_lost: usize,
    /// Localizations down-weighted as outliers.
    pub outliers_downweighted: usize,
    /// RMS visual position residual of the inliers (m).
    pub rms_position_m: f64,
    /// RMS visual rotation residual of the inliers (deg).
    pub rms_rotation_deg: f64,
    /// Solver iterations.
    pub iterations: usize,
    /// Wall time (s); left out where files must be byte-identical across runs (the pipeline
    /// keeps wall times in its stage manifests).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub seconds: Option<f64>,
}

/// [`Conditioning`] in JSON units.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ConditioningJson {
    /// RMS world acceleration (m/s²).
    pub excitation_rms_m_s2: f64,
    /// 1-σ relative scale uncertainty (fraction).
    pub scale_sigma: f64,
    /// 1-σ gravity-direction uncertainty (deg).
    pub gravity_sigma_deg: f64,
    /// Posterior variance factor applied to the sigmas.
    pub variance_factor: f64,
}

impl From<Conditioning> for ConditioningJson {
    fn from(c: Conditioning) -> Self {
        Self {
            excitation_rms_m_s2: c.excitation_rms_m_s2,
            scale_sigma: c.scale_sigma,
            gravity_sigma_deg: c.gravity_sigma_rad.to_degrees(),
            variance_factor: c.variance_factor,
        }
    }
}

fn vec3(v: &Vector3<f64>) -> [f64; 3] {
    [v.x, v.y, v.z]
}

/// Write a result as pretty JSON, atomically.
pub fn write_json<T: Serialize>(path: &Path, value: &T) -> Result<()> {
    let text = serde_json::to_string_pretty(value)
        .map_err(|e| input(path, format!("cannot serialize: {e}")))?;
    kiwi_core::io::write_atomic(path, format!("{text}\n").as_bytes())?;
    Ok(())
}

/// Metric recovery of the map that `rows` (one lens's localizations of the mapping episode,
/// `map_from_cam` on the camera clock) were localized in, from the raw `imu` of the same
/// recording and the lens's calibration. `exposure_centre_s` is the time from a frame's
/// timestamp (its first row) to its exposure centre, where its pose holds: half the rolling
/// readout, 0 for a global shutter. `started` is when the caller began (for the timing).
#[allow(clippy::too_many_arguments)]
pub fn metric_from_localizations(
    rows: &[Localization],
    imu: &ImuSeries,
    lens: &str,
    calibration: &LensImuCalibration,
    params: &ImuParams,
    exposure_centre_s: f64,
    config: &MetricConfig,
    started: std::time::Instant,
) -> Result<MetricFile> {
    if !(exposure_centre_s.is_finite() && exposure_centre_s >= 0.0) {
        return Err(BackendError::Estimation(format!(
            "metric recovery of the {lens} map: expected a non-negative exposure-centre delay \
             (half the rolling readout, s), found {exposure_centre_s}"
        )));
    }
    // A pose holds at the frame's exposure centre: off by half the readout (7 ms at 30 fps on
    // an X5), the IMU is rotated into the wrong attitude by the turn in between and gravity
    // leaks into the acceleration the scale is fitted to.
    let frames: Vec<MapFrame> = rows
        .iter()
        .filter(|r| r.valid)
        .map(|r| MapFrame {
            t: r.t + exposure_centre_s,
            map_from_cam: r.map_from_cam,
        })
        .collect();
    let r = recover_metric(
        &frames,
        imu.samples(),
        params,
        &calibration.cam_from_imu,
        calibration.time_shift_s,
        config,
    )?;
    Ok(MetricFile {
        schema_version: SCHEMA_VERSION,
        lens: lens.to_string(),
        world_from_map: SimilarityJson::from_sim3(&r.world_from_map),
        scale_m_per_map_unit: r.scale,
        gravity_in_map: vec3(&r.gravity_in_map),
        accel_bias_m_s2: vec3(&r.accel_bias),
        accel_bias_sigma_m_s2: vec3(&r.accel_bias_sigma),
        gyro_bias_rad_s: vec3(&r.gyro_bias),
        conditioning: r.conditioning.into(),
        frames_used: r.frames_used,
        frames_lost: rows.len() - frames.len(),
        outliers_downweighted: r.outliers_downweighted,
        rms_position_m: r.rms_position_m,
        rms_rotation_deg: r.rms_rotation_rad.to_degrees(),
        iterations: r.iterations,
        seconds: Some(started.elapsed().as_secs_f64()),
    })
}

/// Read a `metric.json`.
pub fn read_metric(path: &Path) -> Result<MetricFile> {
    let text = std::fs::read_to_string(path).map_err(|e| {
        input(
            path,
            format!("cannot read: {}", kiwi_core::error::describe_io(&e)),
        )
    })?;
    let file: MetricFile = serde_json::from_str(&text).map_err(|e| {
        input(
            path,
            format!("not a kiwi metric.json: {e}; write it with `kiwi metric`"),
        )
    })?;
    if file.schema_version != SCHEMA_VERSION {
        return Err(input(
            path,
            format!(
                "schema_version {} is not supported (expected {SCHEMA_VERSION}); re-run kiwi \
                 metric with this build",
                file.schema_version
            ),
        ));
    }
    Ok(file)
}

/// Apply a map's similarity to a camera pose in it.
pub fn apply(sim: &Sim3, map_from_cam: &Pose) -> Pose {
    Isometry3::from_parts(
        Translation3::from(sim.transform_point(&map_from_cam.translation.vector)),
        sim.rotation * map_from_cam.rotation,
    )
}

/// Contents of `placement.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PlacementFile {
    /// [`SCHEMA_VERSION`].
    pub schema_version: u32,
    /// `scene_from_front_map` (scale 1: both maps metric).
    pub scene_from_front_map: SimilarityJson,
    /// Synchronized pairs of valid localizations.
    pub pairs: usize,
    /// Pairs within the inlier thresholds.
    pub inliers: usize,
    /// RMS position residual of the inliers (m).
    pub rms_position_m: f64,
    /// RMS rotation residual of the inliers (deg).
    pub rms_rotation_deg: f64,
    /// Of `pairs`, those a [`FrontWitness`] gave (the front lens in another wrist's front map).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub witness_pairs: usize,
}

fn is_zero(n: &usize) -> bool {
    *n == 0
}

/// The similarity of a `metric.json`, or the identity when there is none (the map is metric).
pub fn metric_of(path: Option<&Path>) -> Result<Sim3> {
    match path {
        Some(p) => read_metric(p)?.world_from_map.to_sim3(p),
        None => Ok(Sim3::identity()),
    }
}

/// Pair front and rear localizations taken together (IMU clock within [`MAX_PAIR_DT_S`]).
fn pair_up(
    front: &[Localization],
    rear: &[Localization],
    front_shift: f64,
    rear_shift: f64,
    front_sim: &Sim3,
    rear_sim: &Sim3,
) -> Vec<PlacementPair> {
    let rear_valid: Vec<&Localization> = rear.iter().filter(|r| r.valid).collect();
    let mut pairs = Vec::new();
    for f in front.iter().filter(|f| f.valid) {
        let t = f.t + front_shift;
        let k = rear_valid.partition_point(|r| r.t + rear_shift < t);
        let best = [k.checked_sub(1), Some(k)]
            .into_iter()
            .flatten()
            .filter_map(|i| rear_valid.get(i))
            .min_by(|a, b| {
                let da = (a.t + rear_shift - t).abs();
                let db = (b.t + rear_shift - t).abs();
                da.total_cmp(&db)
            });
        if let Some(r) = best
            && (r.t + rear_shift - t).abs() <= MAX_PAIR_DT_S
        {
            pairs.push(PlacementPair {
                t,
                front_map_from_front: apply(front_sim, &f.map_from_cam),
                scene_from_rear: apply(rear_sim, &r.map_from_cam),
            });
        }
    }
    pairs
}

/// Read a `placement.json`.
pub fn read_placement(path: &Path) -> Result<PlacementFile> {
    let text = std::fs::read_to_string(path).map_err(|e| {
        input(
            path,
            format!("cannot read: {}", kiwi_core::error::describe_io(&e)),
        )
    })?;
    let file: PlacementFile = serde_json::from_str(&text).map_err(|e| {
        input(
            path,
            format!("not a kiwi placement.json: {e}; write it with `kiwi place`"),
        )
    })?;
    if file.schema_version != SCHEMA_VERSION {
        return Err(input(
            path,
            format!(
                "schema_version {} is not supported (expected {SCHEMA_VERSION}); re-run kiwi \
                 place with this build",
                file.schema_version
            ),
        ));
    }
    Ok(file)
}

/// The wrist's front lens seen in another wrist's front map during the mapping episode: where
/// that map, made metric and placed, puts the front camera in the scene.
#[derive(Debug, Clone, Copy)]
pub struct FrontWitness<'a> {
    /// The front stream's localizations in the other front map (the same frames as the
    /// stream's own localizations in its own front map).
    pub rows: &'a [Localization],
    /// That map's metric similarity (`metric_front_map_from_front_map`).
    pub other_front_sim: Sim3,
    /// That map's placement `G` (`scene_from_front_map`, metric).
    pub scene_from_other_front_map: Pose,
}

/// Scene placement `G_a` of a front map (paper eq. 2) from the mapping episode's front and rear
/// localizations of one unit, made metric by their maps' similarities; with a [`FrontWitness`],
/// also the pairs it adds: at every frame the front lens has a pose in both front maps, its own
/// front map's pose against the scene pose the other map gives (eq. 2 with the other wrist's map and placement standing in for the rear
/// map). Both kinds of pairs enter one robust fit, so a rear stream that saw a distorted part
/// of the scene map, or only a few frames, does not alone decide where the front map stands.
#[allow(clippy::too_many_arguments)]
pub fn placement_from_localizations(
    front: &[Localization],
    rear: &[Localization],
    front_calibration: &LensImuCalibration,
    rear_calibration: &LensImuCalibration,
    front_sim: &Sim3,
    rear_sim: &Sim3,
    witness: Option<FrontWitness<'_>>,
    config: &PlacementConfig,
) -> Result<PlacementFile> {
    let rear_from_front = rear_calibration.cam_from_imu * front_calibration.cam_from_imu.inverse();
    let mut pairs = pair_up(
        front,
        rear,
        front_calibration.time_shift_s,
        rear_calibration.time_shift_s,
        front_sim,
        rear_sim,
    );
    let rear_pairs = pairs.len();
    if let Some(w) = witness {
        pairs.extend(witness_pairs(
            front,
            &w,
            front_calibration.time_shift_s,
            front_sim,
            &rear_from_front,
        ));
        pairs.sort_by(|a, b| a.t.total_cmp(&b.t));
    }
    let witness_pairs = pairs.len() - rear_pairs;
    let p = place(&pairs, &rear_from_front, config).map_err(|e| {
        BackendError::Estimation(format!(
            "{e} ({rear_pairs} synchronized pairs of valid front and rear localizations, \
             {witness_pairs} of the front lens in both front maps)",
        ))
    })?;
    let q = p.scene_from_front_map.rotation;
    let t = p.scene_from_front_map.translation.vector;
    Ok(PlacementFile {
        schema_version: SCHEMA_VERSION,
        scene_from_front_map: SimilarityJson::from_sim3(&Sim3 {
            scale: 1.0,
            rotation: q,
            translation: t,
        }),
        pairs: p.pairs,
        inliers: p.inliers,
        rms_position_m: p.rms_position_m,
        rms_rotation_deg: p.rms_rotation_rad.to_degrees(),
        witness_pairs,
    })
}

/// The placement pairs of a [`FrontWitness`]: at each frame with a pose in both front maps
/// (matched by timestamp), the front camera in its own metric front map, and the rear camera's
/// scene pose that the other map's front pose implies (`scene_from_front · rear_from_front⁻¹`,
/// so that [`place`]'s `scene_from_rear · E_a` is the witness's front pose).
fn witness_pairs(
    front: &[Localization],
    witness: &FrontWitness<'_>,
    front_shift: f64,
    front_sim: &Sim3,
    rear_from_front: &Pose,
) -> Vec<PlacementPair> {
    let front_from_rear = rear_from_front.inverse();
    let seen: Vec<&Localization> = witness.rows.iter().filter(|r| r.valid).collect();
    front
        .iter()
        .filter(|f| f.valid)
        .filter_map(|f| {
            let k = seen.partition_point(|r| r.t < f.t - WITNESS_SAME_FRAME_S);
            let w = seen
                .get(k)
                .filter(|r| (r.t - f.t).abs() <= WITNESS_SAME_FRAME_S)?;
            let scene_from_front = witness.scene_from_other_front_map
                * apply(&witness.other_front_sim, &w.map_from_cam);
            Some(PlacementPair {
                t: f.t + front_shift,
                front_map_from_front: apply(front_sim, &f.map_from_cam),
                scene_from_rear: scene_from_front * front_from_rear,
            })
        })
        .collect()
}

/// Largest timestamp difference (s) of two rows that are the same frame of one stream: rows
/// round-trip through text, so equal times may differ in the last digits.
const WITNESS_SAME_FRAME_S: f64 = 1e-6;
