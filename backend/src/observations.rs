//! Body-pose observations (paper eq. 3, `eq:state-observations`): every successful front or
//! rear localization becomes an observation of `scene_from_imu` on the IMU clock, through the
//! frozen maps' metric similarities, the front map's scene placement `G_a` and the lens's
//! camera–IMU calibration:
//!
//! ```text
//! Z_f(t) = G_a · T̃_{F_a C_f}(t) · T_{C_f I}        (front lens, front map made metric)
//! Z_r(t) = T̃_{S C_r}(t) · T_{C_r I}                 (rear lens, scene map made metric)
//! ```
//!
//! Times move to the IMU clock with each lens's Kalibr time shift (`t_imu = t_cam + shift`) and
//! to the exposure centre of the rolling-shutter frame (half the readout after the frame's
//! timestamp, its first row), where a pose fitted to the whole image belongs.
//! Failed localizations stay missing: nothing is filled in here. Rear observations are later
//! interpolated to front-frame times by the fusion only inside tracked runs (neighbours at most
//! [`crate::fusion::DEFAULT_MAX_INTERPOLATION_GAP_S`] apart).

use serde::{Deserialize, Serialize};

use kiwi_core::geometry::Pose;

use crate::formats::calibration::LensImuCalibration;
use crate::formats::results::apply;
use crate::formats::tables::Localization;
use crate::fusion::{PoseObservation, Source};
use crate::vision::align::Sim3;

/// The frozen scene reference of one wrist: both maps' metric similarities and the front map's
/// placement in the scene.
#[derive(Debug, Clone, Copy)]
pub struct SceneReference {
    /// `metric_front_map_from_front_map` (the front map's `world_from_map` of metric recovery).
    pub front_metric: Sim3,
    /// `scene_from_rear_map` (the rear map's `world_from_map`: the scene frame `S`).
    pub rear_metric: Sim3,
    /// `G_a = scene_from_front_map` (metric front map to scene).
    pub scene_from_front_map: Pose,
}

/// How many localizations became observations, per lens.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct ObservationCounts {
    /// Front frames in the episode.
    pub front_frames: usize,
    /// Front observations made.
    pub front_observations: usize,
    /// Rear frames in the episode.
    pub rear_frames: usize,
    /// Rear observations made.
    pub rear_observations: usize,
}

/// Eq. 3 for one wrist: front and rear localizations (`map_from_cam` on the camera clock) to
/// `scene_from_imu` observations on the IMU clock, sorted by time. `exposure_centre_s` is the
/// time from a frame's timestamp to its exposure centre (half the rolling readout; 0 for a
/// global shutter).
pub fn body_observations(
    front: &[Localization],
    rear: &[Localization],
    reference: &SceneReference,
    front_calibration: &LensImuCalibration,
    rear_calibration: &LensImuCalibration,
    exposure_centre_s: f64,
) -> (Vec<PoseObservation>, ObservationCounts) {
    let mut out = Vec::with_capacity(front.len() + rear.len());
    for f in front.iter().filter(|f| f.valid) {
        let front_map_from_cam = apply(&reference.front_metric, &f.map_from_cam);
        out.push(PoseObservation {
            t: f.t + front_calibration.time_shift_s + exposure_centre_s,
            source: Source::Front,
            scene_from_imu: reference.scene_from_front_map
                * front_map_from_cam
                * front_calibration.cam_from_imu,
        });
    }
    let front_observations = out.len();
    for r in rear.iter().filter(|r| r.valid) {
        let scene_from_cam = apply(&reference.rear_metric, &r.map_from_cam);
        out.push(PoseObservation {
            t: r.t + rear_calibration.time_shift_s + exposure_centre_s,
            source: Source::Rear,
            scene_from_imu: scene_from_cam * rear_calibration.cam_from_imu,
        });
    }
    let counts = ObservationCounts {
        front_frames: front.len(),
        front_observations,
        rear_frames: rear.len(),
        rear_observations: out.len() - front_observations,
    };
    out.sort_by(|a, b| a.t.total_cmp(&b.t));
    (out, counts)
}
