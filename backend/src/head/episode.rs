//! The head of one episode, from recordings to deliverables (paper §4.3.2, eq. 5): the hat
//! marker found in each wrist's rear stream and timed on that stream's rolling shutter; each
//! sighting placed in the scene through the wrist's fused trajectory at its exposure time;
//! both wrists' observations fused into the marker's track on the session timeline; and the
//! head camera's poses through the head mount's `marker_from_cam`.
//!
//! Clocks: a wrist's fused nodes are on its IMU clock; a lens's frame `t` is exposed at
//! `t + time_shift` on that clock (plus the readout up to the marker's rows); the session
//! timeline places the wrist's front frames, so an IMU time `τ` is the front-camera time
//! `τ − front time_shift` on it.

use std::fmt::Write as _;

use serde::{Deserialize, Serialize};

use kiwi_core::geometry::Pose;
use kiwi_core::layout::Side;

use crate::error::Result;
use crate::frames::FrameSource;
use crate::fusion::FusedNode;
use crate::outputs::{pose_fields, session_time, tum_line};
use crate::sync::CameraClock;

use super::marker::{
    MIN_MARKER_SIZE_PX, MarkerFinder, Resolved, SquarePoses, resolve, square_poses,
};
use super::track::{HeadObservation, HeadSample, observe};

/// A previous sighting older than this (s) does not resolve a planar ambiguity: wrist and head
/// turn relative to each other by up to ~1.5 rad/s, so after this long the previous pose may
/// be as far from the right branch as from the wrong one.
pub const PREVIOUS_SIGHTING_MAX_AGE_S: f64 = 0.25;
/// A sighting is placed only between two fused nodes at most this far apart (s): three frames
/// at 30 Hz; across a longer gap (frames outside the IMU log) the wrist's pose is unknown.
pub const MAX_NODE_GAP_S: f64 = 0.1;

/// A rear lens's sighting of the hat marker.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sighting {
    /// Frame index in the rear stream.
    pub frame: usize,
    /// When the marker's rows were exposed, on the wrist camera's clock (s): the frame's
    /// timestamp plus the readout up to the marker's centre row.
    pub t_camera: f64,
    /// `rear_from_marker`.
    pub rear_from_marker: Pose,
    /// Whether a previous sighting resolved the planar ambiguity.
    pub by_previous: bool,
}

/// What became of a rear stream's frames.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct SightingCounts {
    /// Frames searched.
    pub frames: usize,
    /// Frames where the marker was found.
    pub found: usize,
    /// Sightings too small on the image to pose ([`super::marker::MIN_MARKER_SIZE_PX`]).
    #[serde(default)]
    pub too_small: usize,
    /// Sightings with an accepted pose.
    pub accepted: usize,
    /// Of those, resolved by a previous sighting.
    pub resolved_by_previous: usize,
    /// Sightings whose two IPPE poses explained the corners alike, with nothing to decide.
    pub ambiguous: usize,
    /// Sightings that no pose explained (misdetections).
    pub bad_fit: usize,
    /// Accepted sightings outside the wrist's fused trajectory (not placed).
    pub unplaced: usize,
}

/// Find, pose and time the marker in every frame of a rear stream (frames in parallel, the
/// ambiguity resolved in frame order). `readout_s` is the recording mode's rolling readout (0
/// for a global shutter); `tick` is called once per frame.
pub fn find_sightings(
    source: &FrameSource,
    finder: &MarkerFinder,
    marker_size_m: f64,
    readout_s: f64,
    tick: &(dyn Fn() + Sync),
) -> Result<(Vec<Sighting>, SightingCounts)> {
    let indices: Vec<usize> = (0..source.len()).collect();
    /// What one frame gave: nothing, a marker too small to pose, or its poses and row.
    enum Seen {
        Nothing,
        TooSmall,
        Posed(Option<(SquarePoses, f64)>),
    }
    let per_frame: Vec<Result<Seen>> = source.map_color(&indices, |_, image| {
        let result = (|| {
            let Some(corners) = finder.find(&image?)? else {
                return Ok(Seen::Nothing);
            };
            if finder.size_px(&corners).unwrap_or(0.0) < MIN_MARKER_SIZE_PX {
                return Ok(Seen::TooSmall);
            }
            // A centre the lens cannot project is not a marker the detector found; the middle
            // row is then the best guess of its time.
            let row = finder.row_fraction(&corners).unwrap_or(0.5);
            Ok(Seen::Posed(
                square_poses(&corners, marker_size_m)?.map(|poses| (poses, row)),
            ))
        })();
        tick();
        result
    });
    let mut counts = SightingCounts {
        frames: indices.len(),
        ..SightingCounts::default()
    };
    let mut sightings = Vec::new();
    let mut previous: Option<(f64, Pose)> = None;
    for (frame, (record, seen)) in source.frames().iter().zip(per_frame).enumerate() {
        let (poses, row) = match seen? {
            Seen::Nothing => continue,
            Seen::TooSmall => {
                counts.found += 1;
                counts.too_small += 1;
                continue;
            }
            Seen::Posed(None) => {
                counts.found += 1;
                continue;
            }
            Seen::Posed(Some(p)) => {
                counts.found += 1;
                p
            }
        };
        let t_camera = record.t + readout_s * row;
        let recent = previous
            .filter(|(t, _)| (t_camera - t).abs() <= PREVIOUS_SIGHTING_MAX_AGE_S)
            .map(|(_, p)| p);
        let resolved = resolve(&poses, recent.as_ref());
        let pose = match resolved {
            Resolved::Clear(p) | Resolved::ByPrevious(p) => p,
            Resolved::Ambiguous => {
                counts.ambiguous += 1;
                continue;
            }
            Resolved::BadFit => {
                counts.bad_fit += 1;
                continue;
            }
        };
        let by_previous = matches!(resolved, Resolved::ByPrevious(_));
        counts.accepted += 1;
        counts.resolved_by_previous += usize::from(by_previous);
        previous = Some((t_camera, pose.cam_from_marker));
        sightings.push(Sighting {
            frame,
            t_camera,
            rear_from_marker: pose.cam_from_marker,
            by_previous,
        });
    }
    Ok((sightings, counts))
}

/// A wrist's fused trajectory and what places its rear lens on it.
#[derive(Debug, Clone, Copy)]
pub struct WristPlacement<'a> {
    /// Which wrist.
    pub side: Side,
    /// Fused nodes in time order (IMU clock).
    pub nodes: &'a [FusedNode],
    /// The rear lens's `cam_from_imu`.
    pub rear_cam_from_imu: Pose,
    /// The rear lens's frame time shift to the IMU clock (s).
    pub rear_time_shift_s: f64,
    /// The front lens's frame time shift to the IMU clock (s).
    pub front_time_shift_s: f64,
    /// The wrist camera's clock on the session timeline.
    pub clock: Option<&'a CameraClock>,
}

/// `scene_from_imu` at IMU time `t`, between the two fused nodes around it when they are at
/// most [`MAX_NODE_GAP_S`] apart.
pub fn imu_pose_at(nodes: &[FusedNode], t: f64) -> Option<Pose> {
    let k = nodes.partition_point(|n| n.t <= t);
    if k == 0 || k == nodes.len() {
        // Exactly on the last node.
        return nodes
            .last()
            .filter(|n| k == nodes.len() && n.t == t)
            .map(|n| n.scene_from_imu);
    }
    let (a, b) = (&nodes[k - 1], &nodes[k]);
    let dt = b.t - a.t;
    if !(dt > 0.0 && dt <= MAX_NODE_GAP_S) {
        return None;
    }
    Some(
        a.scene_from_imu
            .lerp_slerp(&b.scene_from_imu, (t - a.t) / dt),
    )
}

/// The scene observations of a wrist's sightings (eq. 5) and how many could not be placed (no
/// fused pose at their time, or the camera is not on the session timeline).
pub fn observations(
    wrist: &WristPlacement<'_>,
    sightings: &[Sighting],
) -> (Vec<HeadObservation>, usize) {
    let imu_from_rear = wrist.rear_cam_from_imu.inverse();
    let mut out = Vec::with_capacity(sightings.len());
    let mut unplaced = 0;
    for s in sightings {
        let t_imu = s.t_camera + wrist.rear_time_shift_s;
        let placed = imu_pose_at(wrist.nodes, t_imu).and_then(|scene_from_imu| {
            let t_session = session_time(wrist.clock, t_imu - wrist.front_time_shift_s)?;
            Some(HeadObservation {
                t_session,
                side: wrist.side,
                scene_from_marker: observe(&scene_from_imu, &imu_from_rear, &s.rear_from_marker),
            })
        });
        match placed {
            Some(o) => out.push(o),
            None => unplaced += 1,
        }
    }
    (out, unplaced)
}

/// The marker's track with the head camera's pose on it.
#[derive(Debug, Clone)]
pub struct HeadTrack {
    /// Samples on the session timeline, gaps included.
    pub samples: Vec<HeadSample>,
    /// The head mount's `marker_from_cam`.
    pub marker_from_cam: Pose,
}

/// The head camera's pose at one time, with its sigmas.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HeadCameraPose {
    /// `scene_from_head_cam`.
    pub scene_from_cam: Pose,
    /// Position sigma (m): the marker's, plus its rotation sigma over the mount's lever arm.
    pub sigma_p_m: f64,
    /// Rotation sigma (rad).
    pub sigma_r_rad: f64,
}

impl HeadTrack {
    /// The head camera's pose of a posed sample.
    pub fn camera_of(&self, s: &HeadSample) -> Option<HeadCameraPose> {
        let marker = s.scene_from_marker?;
        let lever = self.marker_from_cam.translation.vector.norm();
        Some(HeadCameraPose {
            scene_from_cam: marker * self.marker_from_cam,
            sigma_p_m: s.sigma_p_m.hypot(s.sigma_r_rad * lever),
            sigma_r_rad: s.sigma_r_rad,
        })
    }

    /// The head camera's poses on the track's samples.
    pub fn camera_track(&self) -> CameraTrack {
        CameraTrack {
            samples: self
                .samples
                .iter()
                .map(|s| (s.t_session, self.camera_of(s)))
                .collect(),
        }
    }

    /// Median position and rotation sigmas of the posed samples (m, rad).
    pub fn median_sigmas(&self) -> Option<(f64, f64)> {
        let median = |mut v: Vec<f64>| {
            v.sort_by(f64::total_cmp);
            v.get(v.len() / 2).copied()
        };
        let posed = || {
            self.samples
                .iter()
                .filter(|s| s.scene_from_marker.is_some())
        };
        Some((
            median(posed().map(|s| s.sigma_p_m).collect())?,
            median(posed().map(|s| s.sigma_r_rad).collect())?,
        ))
    }

    /// Fraction of samples posed.
    pub fn posed_fraction(&self) -> f64 {
        if self.samples.is_empty() {
            return 0.0;
        }
        let posed = self
            .samples
            .iter()
            .filter(|s| s.scene_from_marker.is_some())
            .count();
        posed as f64 / self.samples.len() as f64
    }

    /// The longest run of samples without a pose (s).
    pub fn longest_gap_s(&self) -> f64 {
        let mut longest = 0.0f64;
        let mut start: Option<f64> = None;
        for s in &self.samples {
            match (s.scene_from_marker.is_some(), start) {
                (false, None) => start = Some(s.t_session),
                (true, Some(t0)) => {
                    longest = longest.max(s.t_session - t0);
                    start = None;
                }
                _ => {}
            }
        }
        if let (Some(t0), Some(last)) = (start, self.samples.last()) {
            longest = longest.max(last.t_session - t0);
        }
        longest
    }
}

/// The head camera's poses on the session timeline (the track's samples, `None` in gaps), as
/// `head.csv` gives them.
#[derive(Debug, Clone, Default)]
pub struct CameraTrack {
    /// `(session time, pose)` in time order.
    pub samples: Vec<(f64, Option<HeadCameraPose>)>,
}

impl CameraTrack {
    /// The head camera's pose at session time `t`: between the two samples around it when
    /// both are posed (no pose across a gap or outside the track).
    pub fn at(&self, t: f64) -> Option<HeadCameraPose> {
        let k = self.samples.partition_point(|s| s.0 <= t);
        let (ta, a) = self.samples.get(k.checked_sub(1)?)?;
        let a = (*a)?;
        let Some((tb, b)) = self.samples.get(k) else {
            // On the last sample exactly.
            return (*ta == t).then_some(a);
        };
        let b = (*b)?;
        let f = ((t - ta) / (tb - ta)).clamp(0.0, 1.0);
        Some(HeadCameraPose {
            scene_from_cam: a.scene_from_cam.lerp_slerp(&b.scene_from_cam, f),
            sigma_p_m: a.sigma_p_m.max(b.sigma_p_m),
            sigma_r_rad: a.sigma_r_rad.max(b.sigma_r_rad),
        })
    }

    /// Read the head camera's poses from an episode's `head.csv`.
    pub fn read_csv(path: &std::path::Path) -> Result<Self> {
        let text = kiwi_core::io::read_text(path)?;
        let bad = |line: usize, message: String| crate::error::BackendError::Input {
            path: path.to_path_buf(),
            message: format!("line {line}: {message}; re-run `kiwi run` (stage head)"),
        };
        let mut lines = text.lines().enumerate();
        match lines.next() {
            Some((_, h)) if h.trim() == HEAD_HEADER => {}
            other => {
                return Err(bad(
                    1,
                    format!(
                        "expected the header `{HEAD_HEADER}`, found `{}`",
                        other.map_or("", |(_, h)| h)
                    ),
                ));
            }
        }
        let column = |name: &str| HEAD_HEADER.split(',').position(|c| c == name).unwrap_or(0);
        let (cam, sp, sr) = (
            column("cam_px"),
            column("cam_sigma_p_m"),
            column("marker_sigma_r_rad"),
        );
        let mut samples = Vec::new();
        for (i, line) in lines.filter(|(_, l)| !l.trim().is_empty()) {
            let f: Vec<&str> = line.split(',').collect();
            if f.len() != HEAD_HEADER.split(',').count() {
                return Err(bad(
                    i + 1,
                    format!(
                        "{} fields, expected {}",
                        f.len(),
                        HEAD_HEADER.split(',').count()
                    ),
                ));
            }
            let num = |k: usize| -> Result<Option<f64>> {
                if f[k].is_empty() {
                    return Ok(None);
                }
                f[k].parse::<f64>()
                    .ok()
                    .filter(|v| v.is_finite())
                    .map(Some)
                    .ok_or_else(|| {
                        bad(
                            i + 1,
                            format!("field {} is not a number: `{}`", k + 1, f[k]),
                        )
                    })
            };
            let t = num(0)?.ok_or_else(|| bad(i + 1, "no session time".into()))?;
            let values: Vec<Option<f64>> = (cam..cam + 7).map(num).collect::<Result<_>>()?;
            let pose = match values.iter().copied().collect::<Option<Vec<f64>>>() {
                Some(v) => Some(HeadCameraPose {
                    scene_from_cam: Pose::from_parts(
                        nalgebra::Translation3::new(v[0], v[1], v[2]),
                        nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
                            v[6], v[3], v[4], v[5],
                        )),
                    ),
                    sigma_p_m: num(sp)?.unwrap_or(f64::NAN),
                    sigma_r_rad: num(sr)?.unwrap_or(f64::NAN),
                }),
                None => None,
            };
            if samples.last().is_some_and(|(tp, _): &(f64, _)| *tp >= t) {
                return Err(bad(i + 1, format!("session time {t} does not increase")));
            }
            samples.push((t, pose));
        }
        Ok(Self { samples })
    }
}

/// The head stage's record of an episode (`head.json`; the `head` section of `quality.json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct HeadSummary {
    /// Where `marker_from_cam` came from.
    pub mount: String,
    /// Per wrist (`left`, `right`): what became of its rear frames.
    pub wrists: std::collections::BTreeMap<String, SightingCounts>,
    /// Scene observations fused (both wrists).
    pub observations: usize,
    /// Track samples on the session timeline.
    pub samples: usize,
    /// Samples per second.
    pub rate_hz: f64,
    /// Fraction of samples posed.
    pub posed_fraction: f64,
    /// Longest run without a pose (s).
    pub longest_gap_s: f64,
    /// Median position sigma of the posed samples (m; `None` when none is posed).
    pub median_sigma_p_m: Option<f64>,
    /// Median rotation sigma of the posed samples (rad).
    pub median_sigma_r_rad: Option<f64>,
    /// Head camera frames.
    pub camera_frames: usize,
    /// Of those, posed.
    pub camera_frames_posed: usize,
}

/// Header of `head.csv`.
pub const HEAD_HEADER: &str = "t_session,marker_px,marker_py,marker_pz,marker_qx,marker_qy,\
marker_qz,marker_qw,cam_px,cam_py,cam_pz,cam_qx,cam_qy,cam_qz,cam_qw,marker_sigma_p_m,\
marker_sigma_r_rad,cam_sigma_p_m,observations,from_left,from_right,outliers";

/// Header of `head_camera.csv`.
pub const HEAD_CAMERA_HEADER: &str = "frame,t_camera,t_session,cam_px,cam_py,cam_pz,cam_qx,cam_qy,cam_qz,cam_qw,cam_sigma_p_m,\
cam_sigma_r_rad";

/// `head.csv` (every sample; pose fields empty in gaps) and `head.tum` (the head camera at
/// every posed sample, `t x y z qx qy qz qw`).
pub fn track_files(track: &HeadTrack) -> (String, String) {
    let mut csv = String::with_capacity(track.samples.len() * 260 + 256);
    csv.push_str(HEAD_HEADER);
    csv.push('\n');
    let mut tum = String::with_capacity(track.samples.len() * 110);
    for s in &track.samples {
        let _ = write!(csv, "{:.6},", s.t_session);
        match (s.scene_from_marker, track.camera_of(s)) {
            (Some(marker), Some(cam)) => {
                pose_fields(&mut csv, &marker);
                csv.push(',');
                pose_fields(&mut csv, &cam.scene_from_cam);
                let _ = write!(
                    csv,
                    ",{:.3e},{:.3e},{:.3e}",
                    s.sigma_p_m, s.sigma_r_rad, cam.sigma_p_m
                );
                tum_line(&mut tum, s.t_session, &cam.scene_from_cam);
            }
            _ => csv.push_str(",,,,,,,,,,,,,,,,"),
        }
        let _ = writeln!(
            csv,
            ",{},{},{},{}",
            s.observations, s.from_left, s.from_right, s.outliers
        );
    }
    (csv, tum)
}

/// `head_camera.csv`: the head camera's pose at every frame's timestamp (pose fields empty
/// where the track has a gap or the camera is not on the session timeline), and how many
/// frames were posed.
pub fn camera_frames_file(
    track: &HeadTrack,
    frame_times: &[f64],
    clock: Option<&CameraClock>,
) -> (String, usize) {
    let cameras = track.camera_track();
    let mut csv = String::with_capacity(frame_times.len() * 150 + 128);
    csv.push_str(HEAD_CAMERA_HEADER);
    csv.push('\n');
    let mut posed = 0;
    for (i, &t) in frame_times.iter().enumerate() {
        let _ = write!(csv, "{i},{t:.6},");
        let t_session = session_time(clock, t);
        if let Some(ts) = t_session {
            let _ = write!(csv, "{ts:.6}");
        }
        match t_session.and_then(|ts| cameras.at(ts)) {
            Some(cam) => {
                posed += 1;
                csv.push(',');
                pose_fields(&mut csv, &cam.scene_from_cam);
                let _ = writeln!(csv, ",{:.3e},{:.3e}", cam.sigma_p_m, cam.sigma_r_rad);
            }
            None => csv.push_str(",,,,,,,,,\n"),
        }
    }
    (csv, posed)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion, Vector3};

    fn sample(t: f64, x: Option<f64>) -> HeadSample {
        HeadSample {
            t_session: t,
            scene_from_marker: x.map(|x| {
                Pose::from_parts(Translation3::new(x, 0.0, 0.0), UnitQuaternion::identity())
            }),
            observations: 3,
            from_left: 3,
            from_right: 0,
            outliers: 0,
            sigma_p_m: 0.002,
            sigma_r_rad: 0.01,
        }
    }

    #[test]
    fn camera_poses_interpolate_inside_the_track_and_never_across_a_gap() {
        let track = HeadTrack {
            samples: vec![
                sample(0.0, Some(0.0)),
                sample(0.1, Some(1.0)),
                sample(0.2, None),
                sample(0.3, Some(3.0)),
            ],
            marker_from_cam: Pose::from_parts(
                Translation3::new(0.0, -0.08, -0.1),
                UnitQuaternion::from_axis_angle(&Vector3::z_axis(), std::f64::consts::PI),
            ),
        };
        let cameras = track.camera_track();
        let at = |t: f64| cameras.at(t).map(|c| c.scene_from_cam.translation.vector);
        let p = at(0.05).unwrap();
        assert!((p - Vector3::new(0.5, -0.08, -0.1)).norm() < 1e-12, "{p}");
        assert!(at(0.15).is_none() && at(0.25).is_none());
        assert!(at(-0.01).is_none() && at(0.31).is_none());
        assert!(at(0.3).is_some());
        // The lever arm's share of the camera's position sigma.
        let c = cameras.at(0.0).unwrap();
        let lever = (0.08f64).hypot(0.1);
        assert!((c.sigma_p_m - 0.002f64.hypot(0.01 * lever)).abs() < 1e-12);
        assert!((track.posed_fraction() - 0.75).abs() < 1e-12);
        assert!((track.longest_gap_s() - 0.1).abs() < 1e-12);
        assert_eq!(track.median_sigmas(), Some((0.002, 0.01)));
        let (csv, tum) = track_files(&track);
        // head.csv reads back to the same camera track.
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("head.csv"), &csv).unwrap();
        let back = CameraTrack::read_csv(&dir.path().join("head.csv")).unwrap();
        for t in [0.0, 0.05, 0.1, 0.15, 0.3] {
            let (a, b) = (cameras.at(t), back.at(t));
            assert_eq!(a.is_some(), b.is_some());
            if let (Some(a), Some(b)) = (a, b) {
                assert!(
                    (a.scene_from_cam.translation.vector - b.scene_from_cam.translation.vector)
                        .norm()
                        < 1e-6
                );
            }
        }
        assert_eq!(csv.lines().count(), 5);
        assert_eq!(tum.lines().count(), 3);
        let fields = HEAD_HEADER.split(',').count();
        assert!(csv.lines().all(|l| l.split(',').count() == fields), "{csv}");
        let (frames, posed) = camera_frames_file(&track, &[0.0, 0.05, 0.15], None);
        // Without a clock nothing is on the session timeline.
        assert_eq!(posed, 0);
        let n = HEAD_CAMERA_HEADER.split(',').count();
        assert!(
            frames.lines().all(|l| l.split(',').count() == n),
            "{frames}"
        );
    }
}
