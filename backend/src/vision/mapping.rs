//! Incremental monocular mapping on feature tracks (bearings): two-view initialization,
//! keyframe selection, absolute pose per frame, triangulation of new tracks, local bundle
//! adjustment over a sliding window of keyframes, and a final global bundle adjustment.
//!
//! The input is a sequence of frames, each listing the tracks it sees (a track id shared by
//! all observations of one scene point, as produced by KLT tracking or descriptor matching)
//! with their unit bearings. Everything is deterministic: tracks are kept in ordered maps,
//! RANSAC seeds derive from the frame index.
//!
//! The image front-end (ORB + KLT on the episode's frames) and place recognition / loop
//! closure are separate steps still to be connected (docs/vision.md).

use std::collections::BTreeMap;

use nalgebra::{Point2, Point3, Vector3};

use kiwi_core::geometry::Pose;

use crate::error::{BackendError, Result};
use crate::vision::ba::{BaObservation, BaOptions, BaProblem, bundle_adjust, refine_relative_pose};
use crate::vision::geometry::{
    RansacOptions, RayObservation, TriangulationLimits, absolute_pose_ransac, angular_error,
    relative_pose_ransac, triangulate,
};

/// One observation of a track in a frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackObservation {
    /// Track id (one scene point).
    pub track: u64,
    /// Unit bearing in the frame's camera.
    pub bearing: Vector3<f64>,
    /// Pixel position (used to attach keyframe descriptors when a map is exported).
    pub pixel: Point2<f64>,
}

/// A frame's tracks.
#[derive(Debug, Clone, PartialEq)]
pub struct MappingFrame {
    /// Frame index in the episode.
    pub frame: u32,
    /// Frame time (s).
    pub t: f64,
    /// Observations (any order; one per track).
    pub observations: Vec<TrackObservation>,
}

/// Mapper settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MapperOptions {
    /// RANSAC settings (threshold, confidence, minimum inliers; the seed is mixed with the
    /// frame index).
    pub ransac: RansacOptions,
    /// Acceptance of triangulated points.
    pub triangulation: TriangulationLimits,
    /// Median parallax (rad) of the initial pair's triangulated inliers.
    pub init_parallax_rad: f64,
    /// Median rotation-compensated parallax (rad) to the last keyframe that makes a keyframe.
    pub keyframe_parallax_rad: f64,
    /// Keyframes optimized by each local bundle adjustment (older ones held fixed).
    pub local_window: usize,
    /// Bundle-adjustment settings.
    pub ba: BaOptions,
    /// Observations with a larger angular error after local BA are dropped (rad).
    pub max_error_rad: f64,
}

impl Default for MapperOptions {
    fn default() -> Self {
        Self {
            ransac: RansacOptions::default(),
            triangulation: TriangulationLimits::default(),
            // ~3°: enough baseline for a well-conditioned first map.
            init_parallax_rad: 3f64.to_radians(),
            // ~1.5°: keyframes dense enough for tracks to survive, sparse enough to add depth.
            keyframe_parallax_rad: 1.5f64.to_radians(),
            local_window: 8,
            ba: BaOptions::default(),
            max_error_rad: 0.008,
        }
    }
}

/// A keyframe of a reconstruction.
#[derive(Debug, Clone, PartialEq)]
pub struct ReconKeyframe {
    /// Frame index in the episode.
    pub frame: u32,
    /// Frame time (s).
    pub t: f64,
    /// World (map) to camera.
    pub cam_from_world: Pose,
    /// Observations kept (outliers removed), in track order.
    pub observations: Vec<TrackObservation>,
}

/// The result of mapping.
#[derive(Debug, Clone, PartialEq)]
pub struct Reconstruction {
    /// Keyframes in time order.
    pub keyframes: Vec<ReconKeyframe>,
    /// Landmark positions by track id.
    pub landmarks: BTreeMap<u64, Vector3<f64>>,
    /// Pose of every frame that was tracked (frame index, `cam_from_world`), before the final
    /// global adjustment for non-keyframes.
    pub frame_poses: Vec<(u32, Pose)>,
    /// Index of the first frame that could not be tracked, if mapping stopped early.
    pub lost_at: Option<u32>,
}

fn mapping_error(message: String) -> BackendError {
    BackendError::Vision {
        context: "mapping".into(),
        message,
    }
}

/// Pairs of bearings of tracks seen in both observation lists (ordered by track).
fn common(
    a: &[TrackObservation],
    b: &[TrackObservation],
) -> (Vec<u64>, Vec<Vector3<f64>>, Vec<Vector3<f64>>) {
    let ib: BTreeMap<u64, Vector3<f64>> = b.iter().map(|o| (o.track, o.bearing)).collect();
    let mut ids = Vec::new();
    let (mut ba, mut bb) = (Vec::new(), Vec::new());
    let mut sa: Vec<&TrackObservation> = a.iter().collect();
    sa.sort_by_key(|o| o.track);
    for o in sa {
        if let Some(v) = ib.get(&o.track) {
            ids.push(o.track);
            ba.push(o.bearing);
            bb.push(*v);
        }
    }
    (ids, ba, bb)
}

fn median(mut v: Vec<f64>) -> Option<f64> {
    if v.is_empty() {
        return None;
    }
    v.sort_by(f64::total_cmp);
    Some(v[v.len() / 2])
}

fn seeded(options: &RansacOptions, frame: u32) -> RansacOptions {
    RansacOptions {
        seed: options.seed ^ u64::from(frame).wrapping_mul(0x9E37_79B9_7F4A_7C15),
        ..*options
    }
}

/// Build a map from tracked frames. Stops (with `lost_at`) at the first frame whose pose
/// cannot be estimated; fails if no initial pair is found.
pub fn reconstruct(frames: &[MappingFrame], options: &MapperOptions) -> Result<Reconstruction> {
    let first = frames
        .first()
        .ok_or_else(|| mapping_error("expected at least two frames, found none".into()))?;
    // 1. Initialization: the first frame with enough parallax to frame 0.
    let mut init = None;
    for (k, f) in frames.iter().enumerate().skip(1) {
        let (ids, b1, b2) = common(&first.observations, &f.observations);
        if ids.len() < options.ransac.min_inliers {
            break;
        }
        let Some(rel) = relative_pose_ransac(&b1, &b2, &seeded(&options.ransac, f.frame)) else {
            continue;
        };
        let pose = refine_relative_pose(
            &rel.cam2_from_cam1,
            &b1,
            &b2,
            &rel.inliers,
            options.ba.huber_rad,
        )?;
        let mut points = BTreeMap::new();
        let mut parallaxes = Vec::new();
        for i in 0..ids.len() {
            if !rel.inliers[i] {
                continue;
            }
            let obs = [
                RayObservation {
                    cam_from_world: Pose::identity(),
                    bearing: b1[i],
                },
                RayObservation {
                    cam_from_world: pose,
                    bearing: b2[i],
                },
            ];
            if let Some(t) = triangulate(&obs, &options.triangulation) {
                parallaxes.push(t.parallax_rad);
                points.insert(ids[i], t.point);
            }
        }
        let all_parallax: Vec<f64> = (0..ids.len())
            .filter(|&i| rel.inliers[i])
            .map(|i| angular_error(&(pose.rotation * b1[i]), &b2[i]))
            .collect();
        let med = median(all_parallax).unwrap_or(0.0);
        if med >= options.init_parallax_rad && points.len() >= options.ransac.min_inliers {
            init = Some((k, pose, points));
            break;
        }
    }
    let (k1, pose1, points) = init.ok_or_else(|| {
        mapping_error(
            "no pair of frames with enough parallax and inliers to initialize; the mapping \
             episode needs translation, not only rotation, early on"
                .into(),
        )
    })?;
    let mut recon = Reconstruction {
        keyframes: vec![
            ReconKeyframe {
                frame: first.frame,
                t: first.t,
                cam_from_world: Pose::identity(),
                observations: sorted(&first.observations),
            },
            ReconKeyframe {
                frame: frames[k1].frame,
                t: frames[k1].t,
                cam_from_world: pose1,
                observations: sorted(&frames[k1].observations),
            },
        ],
        landmarks: points,
        frame_poses: vec![(first.frame, Pose::identity()), (frames[k1].frame, pose1)],
        lost_at: None,
    };
    local_ba(&mut recon, options, true)?;
    // Frames between the initial pair: poses from the first map.
    let mut between = Vec::new();
    for f in &frames[1..k1] {
        if let Some(pose) = frame_pose(&recon, f, options).map(|a| a.cam_from_world) {
            between.push((f.frame, pose));
        }
    }
    recon.frame_poses.splice(1..1, between);

    // 2. Incremental: pose of every frame, keyframes by parallax.
    for f in &frames[k1 + 1..] {
        let Some(abs) = frame_pose(&recon, f, options) else {
            recon.lost_at = Some(f.frame);
            break;
        };
        let pose = abs.cam_from_world;
        recon.frame_poses.push((f.frame, pose));
        let Some(last) = recon.keyframes.last() else {
            break;
        };
        // Rotation-compensated parallax of shared tracks against the last keyframe.
        let (_, b_last, b_cur) = common(&last.observations, &f.observations);
        let rel_rot = pose.rotation * last.cam_from_world.rotation.inverse();
        let parallax = median(
            b_last
                .iter()
                .zip(&b_cur)
                .map(|(a, b)| angular_error(&(rel_rot * a), b))
                .collect(),
        )
        .unwrap_or(0.0);
        let tracked_ratio = abs.num_inliers as f64 / last.observations.len().max(1) as f64;
        if parallax < options.keyframe_parallax_rad && tracked_ratio > 0.3 {
            continue;
        }
        // Keep the inlier observations of mapped tracks and all unmapped ones.
        let mut observations = Vec::new();
        let mut j = 0;
        for o in &f.observations {
            if recon.landmarks.contains_key(&o.track) {
                if abs.inliers[j] {
                    observations.push(*o);
                }
                j += 1;
            } else {
                observations.push(*o);
            }
        }
        observations.sort_by_key(|o| o.track);
        recon.keyframes.push(ReconKeyframe {
            frame: f.frame,
            t: f.t,
            cam_from_world: pose,
            observations,
        });
        triangulate_new(&mut recon, options);
        local_ba(&mut recon, options, false)?;
    }
    // 3. Global bundle adjustment.
    local_ba(&mut recon, options, true)?;
    Ok(recon)
}

/// Absolute pose of a frame against the current landmarks; inlier flags follow the frame's
/// observations of mapped tracks, in order.
fn frame_pose(
    recon: &Reconstruction,
    f: &MappingFrame,
    options: &MapperOptions,
) -> Option<crate::vision::geometry::AbsolutePose> {
    let mut bearings = Vec::new();
    let mut pts = Vec::new();
    for o in &f.observations {
        if let Some(p) = recon.landmarks.get(&o.track) {
            bearings.push(o.bearing);
            pts.push(*p);
        }
    }
    absolute_pose_ransac(&bearings, &pts, &seeded(&options.ransac, f.frame))
}

fn sorted(obs: &[TrackObservation]) -> Vec<TrackObservation> {
    let mut v = obs.to_vec();
    v.sort_by_key(|o| o.track);
    v
}

/// Triangulate tracks of the newest keyframe that have no landmark yet, from every keyframe
/// that observes them.
fn triangulate_new(recon: &mut Reconstruction, options: &MapperOptions) {
    let Some(newest) = recon.keyframes.last() else {
        return;
    };
    let candidates: Vec<u64> = newest
        .observations
        .iter()
        .map(|o| o.track)
        .filter(|t| !recon.landmarks.contains_key(t))
        .collect();
    let window_start = recon.keyframes.len().saturating_sub(options.local_window);
    for track in candidates {
        let rays: Vec<RayObservation> = recon.keyframes[window_start..]
            .iter()
            .filter_map(|kf| {
                kf.observations
                    .binary_search_by_key(&track, |o| o.track)
                    .ok()
                    .map(|i| RayObservation {
                        cam_from_world: kf.cam_from_world,
                        bearing: kf.observations[i].bearing,
                    })
            })
            .collect();
        if rays.len() < 2 {
            continue;
        }
        if let Some(t) = triangulate(&rays, &options.triangulation) {
            recon.landmarks.insert(track, t.point);
        }
    }
}

/// Bundle adjustment over the last `local_window` keyframes (all keyframes if `global`), with
/// older keyframes that see the same landmarks held fixed, keyframe 0 always fixed; then drop
/// observations whose error exceeds `max_error_rad`.
fn local_ba(recon: &mut Reconstruction, options: &MapperOptions, global: bool) -> Result<()> {
    let n = recon.keyframes.len();
    let start = if global {
        0
    } else {
        n.saturating_sub(options.local_window)
    };
    // Landmarks seen by the window.
    let mut point_index: BTreeMap<u64, usize> = BTreeMap::new();
    let mut problem = BaProblem::default();
    for kf in &recon.keyframes[start..] {
        for o in &kf.observations {
            if let Some(p) = recon.landmarks.get(&o.track)
                && !point_index.contains_key(&o.track)
            {
                point_index.insert(o.track, problem.points.len());
                problem.points.push(*p);
                problem.fixed_point.push(false);
            }
        }
    }
    let mut cam_of_kf = vec![usize::MAX; n];
    for (k, kf) in recon.keyframes.iter().enumerate() {
        let in_window = k >= start;
        let sees = kf
            .observations
            .iter()
            .any(|o| point_index.contains_key(&o.track));
        if !in_window && !sees {
            continue;
        }
        cam_of_kf[k] = problem.cam_from_world.len();
        problem.cam_from_world.push(kf.cam_from_world);
        problem.fixed_camera.push(!in_window || k == 0);
        for o in &kf.observations {
            if let Some(&j) = point_index.get(&o.track) {
                problem.observations.push(BaObservation {
                    camera: cam_of_kf[k],
                    point: j,
                    bearing: o.bearing,
                });
            }
        }
    }
    if problem.observations.is_empty() {
        return Ok(());
    }
    bundle_adjust(&mut problem, &options.ba)?;
    for (k, kf) in recon.keyframes.iter_mut().enumerate() {
        if cam_of_kf[k] != usize::MAX {
            kf.cam_from_world = problem.cam_from_world[cam_of_kf[k]];
        }
    }
    for (track, &j) in &point_index {
        recon.landmarks.insert(*track, problem.points[j]);
    }
    // Drop observations that disagree with the adjusted map.
    for kf in recon.keyframes.iter_mut().skip(start) {
        let pose = kf.cam_from_world;
        kf.observations
            .retain(|o| match recon.landmarks.get(&o.track) {
                Some(p) => {
                    angular_error(&o.bearing, &(pose * Point3::from(*p)).coords)
                        <= options.max_error_rad
                }
                None => true,
            });
    }
    Ok(())
}
