//! An episode's deliverables (`episodes/<ep>/out/`): per wrist, the tool-tip and front-camera
//! trajectories on the session timeline at every front frame with their marginal sigmas, the
//! support class and the gripper opening; TUM files for trajectory tools such as evo; and
//! `quality.json`, the record of how far to trust it all with the verdict. With a head camera,
//! the head stage's `head.csv` (the hat marker's track and the head camera's pose on it, 30 Hz
//! on the session timeline, empty in gaps), `head.tum` (the head camera) and `head_camera.csv`
//! (the head camera's pose at each of its frames).
//!
//! `<wrist>.csv` columns:
//!
//! | column | meaning |
//! |---|---|
//! | `t_session` | frame time on the session timeline (s); empty when the camera could not be synchronized |
//! | `t_camera` | frame time on the camera's own clock (s) |
//! | `tip_p{x,y,z}`, `tip_q{x,y,z,w}` | `scene_from_tip` (m, unit quaternion) |
//! | `cam_p{x,y,z}`, `cam_q{x,y,z,w}` | `scene_from_front_cam` |
//! | `tip_sigma_p_m`, `tip_sigma_r_rad`, `cam_sigma_p_m`, `cam_sigma_r_rad` | marginal sigmas (square roots of the traces of the 3×3 position and rotation blocks) |
//! | `support` | `front`, `rear`, `rear-interpolated` or `imu-only` |
//! | `factors` | the visual factors at the frame (`front+rear`, a `*` when Huber down-weighted one) |
//! | `opening`, `opening_unit`, `opening_confidence` | gripper opening (rad for an angle, m for a width), empty when not measured |

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::Path;

use serde::{Deserialize, Serialize};

use kiwi_core::geometry::Pose;
use kiwi_core::io::write_atomic;

use crate::error::Result;
use crate::formats::results::{MetricFile, PlacementFile};
use crate::formats::tables::FusedRow;
use crate::fusion::FusionStatistics;
use crate::observations::ObservationCounts;
use crate::quality::{
    SUSPECT_GRIPPER_FRACTION, SUSPECT_HEAD_SIGMA_P_M, SUSPECT_HEAD_SIGMA_R_RAD,
    SUSPECT_HEAD_TRACKED_FRACTION, SUSPECT_PLACEMENT_INLIER_FRACTION, SUSPECT_POSITION_SIGMA_M,
    SUSPECT_RESIDUAL_P95_M, SUSPECT_SUPPORTED_FRACTION, SUSPECT_UNSUPPORTED_RUN_S, Thresholds,
    UNUSABLE_POSITION_SIGMA_M, UNUSABLE_SUPPORTED_FRACTION, UNUSABLE_UNSUPPORTED_RUN_S, Verdict,
    VerdictBuilder, longest_unsupported_run,
};
use crate::sync::{CameraStatus, SyncResult};

/// Frame times of `opening.csv` are written to the microsecond; a frame and an opening row
/// closer than this are the same frame.
const OPENING_TIME_MATCH_S: f64 = 2e-6;

/// A floor whose height is uncertain by more than this is suspect (m): half the heights'
/// accuracy goal of 1 cm, leaving the other half to the trajectory.
const SUSPECT_FLOOR_SE_M: f64 = 0.005;

/// Schema of `quality.json`.
pub const QUALITY_SCHEMA_VERSION: u32 = 1;
/// Header of `<wrist>.csv`.
pub const TRAJECTORY_HEADER: &str = "t_session,t_camera,tip_px,tip_py,tip_pz,tip_qx,tip_qy,tip_qz,tip_qw,\
cam_px,cam_py,cam_pz,cam_qx,cam_qy,cam_qz,cam_qw,tip_sigma_p_m,tip_sigma_r_rad,cam_sigma_p_m,\
cam_sigma_r_rad,support,factors,opening,opening_unit,opening_confidence,tip_height_m,cam_height_m";

/// What supported a frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SupportClass {
    /// A front-lens observation at the frame.
    Front,
    /// A rear-lens observation at the frame (no front).
    Rear,
    /// A rear observation interpolated inside a tracked run (no front).
    RearInterpolated,
    /// No visual observation: the IMU carries the frame.
    ImuOnly,
}

impl SupportClass {
    /// Name in files.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Front => "front",
            Self::Rear => "rear",
            Self::RearInterpolated => "rear-interpolated",
            Self::ImuOnly => "imu-only",
        }
    }

    /// Whether the frame is supported in the paper's sense.
    pub fn supported(self) -> bool {
        self != Self::ImuOnly
    }

    /// The class of a fused node.
    pub fn of(support: &crate::fusion::Support) -> Self {
        match (support.front, support.rear, support.rear_interpolated) {
            (Some(_), _, _) => Self::Front,
            (None, Some(_), false) => Self::Rear,
            (None, Some(_), true) => Self::RearInterpolated,
            (None, None, _) => Self::ImuOnly,
        }
    }
}

/// One frame's gripper opening in SI units.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Opening {
    /// Frame time on the camera clock (s).
    pub t: f64,
    /// The opening (rad or m), `None` when not measured.
    pub value: Option<f64>,
    /// Confidence in [0, 1].
    pub confidence: f64,
}

/// A wrist's gripper openings.
#[derive(Debug, Clone, PartialEq)]
pub struct OpeningSeries {
    /// `rad` (angle) or `m` (width).
    pub unit: &'static str,
    /// One per front frame.
    pub rows: Vec<Opening>,
}

/// One lens's localization outcome, for the quality record.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct LocalizationRecord {
    /// Frames in the stream.
    pub frames: usize,
    /// Frames with an accepted pose.
    pub localized: usize,
    /// Lost frames per reason (numbers replaced by `#`).
    pub lost_reasons: BTreeMap<String, usize>,
    /// Of the localized frames, those found only around the pose the wrist's other lens
    /// predicted (a front lens after the map episode; docs/vision.md).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub from_other_lens: usize,
}

/// Serde's skip test for a count that is usually zero.
fn is_zero(n: &usize) -> bool {
    *n == 0
}

/// Everything the outputs need of one wrist.
#[derive(Debug, Clone)]
pub struct WristInputs {
    /// `left` or `right`.
    pub camera: String,
    /// Unit id and calibration date.
    pub unit: String,
    /// Calibration date.
    pub calibration_date: String,
    /// Whether the unit's calibration set is certified.
    pub certified: bool,
    /// The fused trajectory (one row per front frame).
    pub fused: Vec<FusedRow>,
    /// Front lens `cam_from_imu`.
    pub front_cam_from_imu: Pose,
    /// Tool `cam_from_tip`.
    pub cam_from_tip: Pose,
    /// Gripper openings, when the tool has jaws.
    pub opening: Option<OpeningSeries>,
    /// Front and rear localization outcomes.
    pub front: LocalizationRecord,
    /// Rear localization outcome.
    pub rear: LocalizationRecord,
    /// Observations made from them.
    pub observations: ObservationCounts,
    /// Fusion statistics.
    pub fusion: FusionStatistics,
    /// Front frames outside the IMU log (not fused, not in the outputs).
    pub frames_outside_imu: usize,
    /// The wrist's front-map placement.
    pub placement: PlacementFile,
    /// Whether the tool was calibrated from its body tag (else CAD geometry).
    pub tool_calibrated: Option<bool>,
}

/// Everything the outputs need of an episode.
#[derive(Debug, Clone)]
pub struct EpisodeInputs {
    /// Episode name.
    pub episode: String,
    /// The map episode of the session.
    pub map_episode: String,
    /// Wrists in order (those whose stages gave their outputs).
    pub wrists: Vec<WristInputs>,
    /// Wrists without a trajectory, each with why (`left`/`right`, the reason): the episode is
    /// `unusable`, and the other wrist is published.
    pub missing_wrists: Vec<(String, String)>,
    /// Parts of the episode not published because their stage failed (the head's track, the
    /// floor), each with why: the episode is at best `suspect`.
    pub missing_parts: Vec<String>,
    /// The episode's sync result.
    pub sync: SyncResult,
    /// Metric recovery of each map (`rear`, `front-left`, …).
    pub metric: BTreeMap<String, MetricFile>,
    /// The head stage's files and record, when the session has a head camera.
    pub head: Option<HeadOutputs>,
    /// The floor stage's files and record.
    pub floor: Option<FloorOutputs>,
}

/// What the floor stage hands the outputs: its files (published as they are) and its record.
#[derive(Debug, Clone)]
pub struct FloorOutputs {
    /// `(file name, bytes)`: `floor.json`, `floor_windows.csv`, `floor.svg`.
    pub files: Vec<(String, Vec<u8>)>,
    /// The record, `quality.json`'s `floor` section.
    pub summary: crate::floor::FloorSummary,
}

/// What the head stage hands the outputs: its files (published as they are) and its record.
#[derive(Debug, Clone)]
pub struct HeadOutputs {
    /// `(file name, bytes)`: `head.csv`, `head.tum`, `head_camera.csv`.
    pub files: Vec<(String, Vec<u8>)>,
    /// The record, `quality.json`'s `head` section.
    pub summary: crate::head::episode::HeadSummary,
}

/// A wrist's section of `quality.json`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct WristQuality {
    /// Unit id.
    pub unit: String,
    /// Calibration date.
    pub calibration_date: String,
    /// Whether the calibration set is certified.
    pub calibration_certified: bool,
    /// Front frames (= fused nodes).
    pub frames: usize,
    /// Fraction of frames supported by a visual observation (paper §5).
    pub supported_fraction: f64,
    /// Fraction per support class.
    pub support_fractions: BTreeMap<String, f64>,
    /// Longest run of unsupported frames (s).
    pub longest_unsupported_s: f64,
    /// Largest tool-tip position sigma over the frames (m).
    pub max_tip_sigma_p_m: f64,
    /// Median tool-tip position sigma (m).
    pub median_tip_sigma_p_m: f64,
    /// Front-lens localization.
    pub front_localization: LocalizationRecord,
    /// Rear-lens localization.
    pub rear_localization: LocalizationRecord,
    /// Observations made (eq. 3).
    pub observations: ObservationCounts,
    /// Fusion solver and residuals.
    pub fusion: FusionStatistics,
    /// Front frames outside the IMU log: not fused and not in the outputs.
    pub frames_outside_imu: usize,
    /// Placement of the front map: pairs, inliers, RMS.
    pub placement: PlacementFile,
    /// The clock on the session timeline.
    pub clock: Option<crate::sync::CameraClock>,
    /// Fraction of frames with a gripper opening, and its median confidence.
    pub gripper_measured_fraction: Option<f64>,
    /// Whether the tool's dot plane came from its body tag (else from CAD).
    pub tool_calibrated: Option<bool>,
}

/// `quality.json`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct QualityRecord {
    /// [`QUALITY_SCHEMA_VERSION`].
    pub schema_version: u32,
    /// Episode.
    pub episode: String,
    /// `usable`, `suspect` or `unusable`.
    pub verdict: Verdict,
    /// Every finding behind the verdict.
    pub reasons: Vec<String>,
    /// The thresholds used.
    pub thresholds: Thresholds,
    /// Per wrist.
    pub wrists: BTreeMap<String, WristQuality>,
    /// Sync evidence: cameras, pairs, triangle closures (absent when sync did not run).
    pub sync: Option<SyncResult>,
    /// Metric recovery of the session's maps (scale, gravity, conditioning).
    pub metric: BTreeMap<String, MetricFile>,
    /// The episode whose recordings built the maps.
    pub map_episode: String,
    /// The head's track and the head camera's poses (absent without a head camera).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub head: Option<crate::head::episode::HeadSummary>,
    /// The floor and the other horizontal surfaces (absent when the floor stage did not run).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub floor: Option<crate::floor::FloorSummary>,
}

/// A camera-clock time on the session timeline (`None` when the camera is not on it).
pub fn session_time(clock: Option<&crate::sync::CameraClock>, t: f64) -> Option<f64> {
    clock
        .filter(|c| c.status != CameraStatus::Unmatched)
        .and_then(|c| {
            c.offset_s
                .map(|offset| t * (1.0 + c.drift_ppm * 1e-6) + offset)
        })
}

/// Append a pose as `px,py,pz,qx,qy,qz,qw` (micrometres, 1e-9 on the quaternion).
pub(crate) fn pose_fields(s: &mut String, pose: &Pose) {
    let p = pose.translation.vector;
    let q = pose.rotation.coords;
    let _ = write!(
        s,
        "{:.6},{:.6},{:.6},{:.9},{:.9},{:.9},{:.9}",
        p.x, p.y, p.z, q.x, q.y, q.z, q.w
    );
}

/// Append a TUM line `t tx ty tz qx qy qz qw`.
pub(crate) fn tum_line(s: &mut String, t: f64, pose: &Pose) {
    let p = pose.translation.vector;
    let q = pose.rotation.coords;
    let _ = writeln!(
        s,
        "{t:.6} {:.6} {:.6} {:.6} {:.9} {:.9} {:.9} {:.9}",
        p.x, p.y, p.z, q.x, q.y, q.z, q.w
    );
}

fn median(mut v: Vec<f64>) -> f64 {
    if v.is_empty() {
        return 0.0;
    }
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Write one wrist's CSV and TUM files into `dir`, and return its quality section.
fn write_wrist(
    w: &WristInputs,
    clock: Option<&crate::sync::CameraClock>,
    floor_z: Option<f64>,
    dir: &Path,
) -> Result<WristQuality> {
    let n = w.fused.len();
    let mut csv = String::with_capacity(n * 400 + 512);
    csv.push_str(TRAJECTORY_HEADER);
    csv.push('\n');
    let mut tip_tum = String::with_capacity(n * 110);
    let mut cam_tum = String::with_capacity(n * 110);
    let tip_from_imu = w.cam_from_tip.inverse() * w.front_cam_from_imu;
    let mut classes = Vec::with_capacity(n);
    let mut sigmas = Vec::with_capacity(n);
    let openings: Vec<&Opening> = w.opening.iter().flat_map(|o| o.rows.iter()).collect();
    // `opening.csv` keeps microseconds: match a frame to the opening row within that.
    let opening_at = |t: f64| -> Option<&Opening> {
        let k = openings.partition_point(|o| o.t < t - OPENING_TIME_MATCH_S);
        openings
            .get(k)
            .copied()
            .filter(|o| (o.t - t).abs() <= OPENING_TIME_MATCH_S)
    };
    let mut measured = 0usize;
    for row in &w.fused {
        let (cam_pose, cam_sp, cam_sr) = row.node.camera_pose(&w.front_cam_from_imu);
        let (tip_pose, tip_sp, tip_sr) = row.node.camera_pose(&tip_from_imu);
        let class = SupportClass::of(&row.node.support);
        classes.push(class);
        sigmas.push(tip_sp);
        let t_session = session_time(clock, row.t_camera);
        let t_out = t_session.unwrap_or(row.t_camera);
        match t_session {
            Some(t) => {
                let _ = write!(csv, "{t:.6},");
            }
            None => csv.push(','),
        }
        let _ = write!(csv, "{:.6},", row.t_camera);
        pose_fields(&mut csv, &tip_pose);
        csv.push(',');
        pose_fields(&mut csv, &cam_pose);
        let _ = write!(
            csv,
            ",{tip_sp:.3e},{tip_sr:.3e},{cam_sp:.3e},{cam_sr:.3e},{},{}",
            class.as_str(),
            row.node.support.label()
        );
        let opening = w
            .opening
            .as_ref()
            .and_then(|series| opening_at(row.t_camera).map(|o| (series.unit, o)));
        match opening {
            Some((unit, o)) => {
                let value = o.value.map(|v| format!("{v:.6}")).unwrap_or_default();
                measured += usize::from(o.value.is_some());
                let _ = write!(csv, ",{value},{unit},{:.3}", o.confidence);
            }
            None => csv.push_str(",,,"),
        }
        // Heights above the floor (eq. 6), empty without one.
        match floor_z {
            Some(f) => {
                let _ = writeln!(
                    csv,
                    ",{:.6},{:.6}",
                    tip_pose.translation.vector.z - f,
                    cam_pose.translation.vector.z - f
                );
            }
            None => csv.push_str(",,\n"),
        }
        tum_line(&mut tip_tum, t_out, &tip_pose);
        tum_line(&mut cam_tum, t_out, &cam_pose);
    }
    let name = &w.camera;
    write_atomic(&dir.join(format!("{name}.csv")), csv.as_bytes())?;
    write_atomic(&dir.join(format!("{name}_tip.tum")), tip_tum.as_bytes())?;
    write_atomic(
        &dir.join(format!("{name}_front_cam.tum")),
        cam_tum.as_bytes(),
    )?;

    let times: Vec<f64> = w.fused.iter().map(|r| r.t_camera).collect();
    let supported: Vec<bool> = classes.iter().map(|c| c.supported()).collect();
    let frac = |pred: &dyn Fn(&SupportClass) -> bool| {
        classes.iter().filter(|c| pred(c)).count() as f64 / n.max(1) as f64
    };
    let mut support_fractions = BTreeMap::new();
    for c in [
        SupportClass::Front,
        SupportClass::Rear,
        SupportClass::RearInterpolated,
        SupportClass::ImuOnly,
    ] {
        support_fractions.insert(c.as_str().to_string(), frac(&|x| *x == c));
    }
    Ok(WristQuality {
        unit: w.unit.clone(),
        calibration_date: w.calibration_date.clone(),
        calibration_certified: w.certified,
        frames: n,
        supported_fraction: frac(&|c| c.supported()),
        support_fractions,
        longest_unsupported_s: longest_unsupported_run(&times, &supported),
        max_tip_sigma_p_m: sigmas.iter().copied().fold(0.0, f64::max),
        median_tip_sigma_p_m: median(sigmas),
        front_localization: w.front.clone(),
        rear_localization: w.rear.clone(),
        observations: w.observations.clone(),
        fusion: w.fusion,
        frames_outside_imu: w.frames_outside_imu,
        placement: w.placement.clone(),
        clock: clock.cloned(),
        gripper_measured_fraction: w
            .opening
            .as_ref()
            .map(|_| measured as f64 / n.max(1) as f64),
        tool_calibrated: w.tool_calibrated,
    })
}

/// Grade one wrist.
fn grade_wrist(v: &mut VerdictBuilder, name: &str, q: &WristQuality) {
    v.check_at_least(
        &format!("{name}: supported fraction"),
        q.supported_fraction,
        SUSPECT_SUPPORTED_FRACTION,
        UNUSABLE_SUPPORTED_FRACTION,
    );
    v.check_at_most(
        &format!("{name}: longest IMU-only run (s)"),
        q.longest_unsupported_s,
        SUSPECT_UNSUPPORTED_RUN_S,
        UNUSABLE_UNSUPPORTED_RUN_S,
    );
    v.check_at_most(
        &format!("{name}: largest tool-tip position sigma (m)"),
        q.max_tip_sigma_p_m,
        SUSPECT_POSITION_SIGMA_M,
        UNUSABLE_POSITION_SIGMA_M,
    );
    for (source, r) in [("front", &q.fusion.front), ("rear", &q.fusion.rear)] {
        if r.observations > 0 && r.p95_position_m > SUSPECT_RESIDUAL_P95_M {
            v.add(
                Verdict::Suspect,
                format!(
                    "{name}: {source} observations disagree with the fused trajectory \
                     (95th percentile {:.1} mm > {:.0} mm): check the maps and the calibration",
                    r.p95_position_m * 1e3,
                    SUSPECT_RESIDUAL_P95_M * 1e3
                ),
            );
        }
    }
    let p = &q.placement;
    let inliers = p.inliers as f64 / p.pairs.max(1) as f64;
    if inliers < SUSPECT_PLACEMENT_INLIER_FRACTION {
        v.add(
            Verdict::Suspect,
            format!(
                "{name}: the front map's placement rests on {} of {} pairs",
                p.inliers, p.pairs
            ),
        );
    }
    if !q.calibration_certified {
        v.add(
            Verdict::Suspect,
            format!(
                "{name}: unit {} has no passed certification in its calibration set ({})",
                q.unit, q.calibration_date
            ),
        );
    }
    match &q.clock {
        Some(c) if c.status == CameraStatus::Unmatched => v.add(
            Verdict::Unusable,
            format!(
                "{name}: the camera could not be placed on the session timeline (its audio \
                 shares no accepted sound with the other cameras; see sync.pairs)"
            ),
        ),
        None => v.add(
            Verdict::Unusable,
            format!("{name}: the camera is missing from the sync result"),
        ),
        Some(_) => {}
    }
    if let Some(f) = q.gripper_measured_fraction
        && f < SUSPECT_GRIPPER_FRACTION
    {
        v.add(
            Verdict::Suspect,
            format!(
                "{name}: gripper opening measured on {:.1} % of frames (< {:.0} %)",
                f * 100.0,
                SUSPECT_GRIPPER_FRACTION * 100.0
            ),
        );
    }
}

/// Grade the floor: its height is uncertain by the standard error of the windows' median
/// (1.2533 × spread / √windows); above [`SUSPECT_FLOOR_SE_M`], or resting on one window, the
/// heights above the floor are suspect. No floor is not a fault of the trajectories: the
/// heights stay empty and `quality.json`'s `floor` section says why.
fn grade_floor(v: &mut VerdictBuilder, f: &crate::floor::FloorSummary) {
    let crate::floor::Floor::Found {
        spread_m, windows, ..
    } = f.floor
    else {
        return;
    };
    if windows < 2 {
        v.add(
            Verdict::Suspect,
            "floor: found in one window only; the heights above the floor rest on it (see \
             floor_windows.csv)"
                .to_string(),
        );
        return;
    }
    let standard_error = 1.2533 * spread_m / (windows as f64).sqrt();
    if standard_error > SUSPECT_FLOOR_SE_M {
        v.add(
            Verdict::Suspect,
            format!(
                "floor: uncertain by {:.1} mm (its {windows} windows spread {:.1} cm about it; \
                 suspect above {:.0} mm): the heights above the floor are uncertain by as much; \
                 see floor_windows.csv",
                standard_error * 1e3,
                spread_m * 1e2,
                SUSPECT_FLOOR_SE_M * 1e3
            ),
        );
    }
}

/// Write every deliverable of an episode into `dir` and return the quality record (also
/// written there as `quality.json`).
pub fn write_outputs(inputs: &EpisodeInputs, dir: &Path) -> Result<QualityRecord> {
    std::fs::create_dir_all(dir).map_err(|e| crate::error::BackendError::Input {
        path: dir.to_path_buf(),
        message: format!("cannot create: {e}"),
    })?;
    let mut wrists = BTreeMap::new();
    let mut v = VerdictBuilder::default();
    for (camera, why) in &inputs.missing_wrists {
        v.add(
            Verdict::Unusable,
            format!("{camera}: no trajectory (only the other wrist is published): {why}"),
        );
    }
    for why in &inputs.missing_parts {
        v.add(Verdict::Suspect, why.clone());
    }
    for w in &inputs.wrists {
        let clock = inputs.sync.cameras.iter().find(|c| c.name == w.camera);
        let floor_z = inputs.floor.as_ref().and_then(|f| f.summary.floor.z_m());
        let q = write_wrist(w, clock, floor_z, dir)?;
        grade_wrist(&mut v, &w.camera, &q);
        wrists.insert(w.camera.clone(), q);
    }
    if let Some(head) = &inputs.head {
        for (name, bytes) in &head.files {
            write_atomic(&dir.join(name), bytes)?;
        }
        let h = &head.summary;
        if h.posed_fraction < SUSPECT_HEAD_TRACKED_FRACTION {
            let sighted: usize = h.wrists.values().map(|c| c.accepted).sum();
            let searched: usize = h.wrists.values().map(|c| c.frames).sum();
            v.add(
                Verdict::Suspect,
                format!(
                    "head: tracked on {:.1} % of the episode (< {:.0} %); the hat marker was \
                     posed in {sighted} of {searched} rear frames",
                    h.posed_fraction * 100.0,
                    SUSPECT_HEAD_TRACKED_FRACTION * 100.0
                ),
            );
        }
        if let (Some(sp), Some(sr)) = (h.median_sigma_p_m, h.median_sigma_r_rad)
            && (sp > SUSPECT_HEAD_SIGMA_P_M || sr > SUSPECT_HEAD_SIGMA_R_RAD)
        {
            v.add(
                Verdict::Suspect,
                format!(
                    "head: the track's median sigma is {:.1} mm and {:.2} deg (suspect above \
                     {:.0} mm or {:.0} deg): the hat marker's sightings disagree; record the rear \
                     lenses at 960 px or use a larger marker",
                    sp * 1e3,
                    sr.to_degrees(),
                    SUSPECT_HEAD_SIGMA_P_M * 1e3,
                    SUSPECT_HEAD_SIGMA_R_RAD.to_degrees()
                ),
            );
        }
    }
    if let Some(floor) = &inputs.floor {
        for (name, bytes) in &floor.files {
            write_atomic(&dir.join(name), bytes)?;
        }
        grade_floor(&mut v, &floor.summary);
    }
    let (verdict, reasons) = v.finish();
    let record = QualityRecord {
        schema_version: QUALITY_SCHEMA_VERSION,
        episode: inputs.episode.clone(),
        verdict,
        reasons,
        thresholds: Thresholds::default(),
        wrists,
        sync: Some(inputs.sync.clone()),
        metric: inputs.metric.clone(),
        map_episode: inputs.map_episode.clone(),
        head: inputs.head.as_ref().map(|h| h.summary.clone()),
        floor: inputs.floor.as_ref().map(|f| f.summary.clone()),
    };
    crate::formats::results::write_json(&dir.join("quality.json"), &record)?;
    Ok(record)
}

/// Read an episode's `quality.json`.
pub fn read_quality(path: &Path) -> Result<QualityRecord> {
    let text = kiwi_core::io::read_text(path)?;
    serde_json::from_str(&text).map_err(|e| crate::error::BackendError::Input {
        path: path.to_path_buf(),
        message: format!("not a KIWI quality.json: {e}; re-run `kiwi run`"),
    })
}

/// The quality record of an episode whose stages failed: verdict `unusable`, the reasons, and
/// nothing else (no trajectory is written for it).
pub fn failed_record(episode: &str, map_episode: &str, reasons: Vec<String>) -> QualityRecord {
    QualityRecord {
        schema_version: QUALITY_SCHEMA_VERSION,
        episode: episode.to_string(),
        verdict: Verdict::Unusable,
        reasons,
        thresholds: Thresholds::default(),
        wrists: BTreeMap::new(),
        sync: None,
        metric: BTreeMap::new(),
        map_episode: map_episode.to_string(),
        head: None,
        floor: None,
    }
}
