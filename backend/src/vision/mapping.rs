//! Incremental monocular mapping on feature tracks (bearings): two-view initialization,
//! keyframe selection, absolute pose per frame, triangulation of new tracks, local bundle
//! adjustment over a sliding window of keyframes, and a final global bundle adjustment.
//!
//! The input is a sequence of frames, each listing the tracks it sees (a track id shared by
//! all observations of one scene point, as produced by KLT tracking or descriptor matching)
//! with their unit bearings. Everything is deterministic: tracks are kept in ordered maps,
//! RANSAC seeds derive from the frame index.
//!
//! The image front-end (ORB + KLT on the episode's frames) is `vision::frontend`; loop closure
//! runs on the finished reconstruction ([`crate::vision::loop_closure`], [`global_adjustment`]).

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
    /// Rotation (rad) from the last keyframe that makes a keyframe (with new tracks): the view,
    /// and with it the descriptors a query will be matched to, has changed.
    pub keyframe_rotation_rad: f64,
    /// A keyframe is also made when the frame's inliers fall below this fraction of the
    /// landmarks the last keyframe observes (the map is losing its hold on the view).
    pub keyframe_support_ratio: f64,
    /// Smallest time (s) between keyframes, unless the support is about to be lost.
    pub min_keyframe_interval_s: f64,
    /// Smallest number of unmapped tracks shared with the last keyframe for a parallax-driven
    /// keyframe (it must bring something new to triangulate).
    pub keyframe_min_new_tracks: usize,
    /// The initial pair's first frame moves forward when fewer than this fraction of its tracks
    /// survive to the candidate partner (no partner with enough parallax before them).
    pub init_min_shared_ratio: f64,
    /// Consecutive frames without a pose after which mapping stops (`lost_at`); isolated
    /// failures (a blurred frame) are skipped while KLT keeps the tracks.
    pub max_consecutive_failures: usize,
    /// Keyframes optimized by each local bundle adjustment (older ones held fixed).
    pub local_window: usize,
    /// Bundle-adjustment settings.
    pub ba: BaOptions,
    /// Observations with a larger angular error after local BA are dropped (rad).
    pub max_error_rad: f64,
    /// A mapped track that is an outlier of a frame's pose continues under a new id from that
    /// frame on (see [`Reconstruction::split_from`]).
    pub split_outlier_tracks: bool,
}

impl Default for MapperOptions {
    fn default() -> Self {
        Self {
            ransac: RansacOptions::default(),
            triangulation: TriangulationLimits::default(),
            // ~3°: enough baseline for a well-conditioned first map.
            init_parallax_rad: 3f64.to_radians(),
            // ~1°: keyframes dense enough for tracks to survive and to cover the sweep, sparse
            // enough to add depth (the triangulation limit is 1° over all keyframes of a track).
            keyframe_parallax_rad: 1.0f64.to_radians(),
            // ~8°: a wrist sweep turns 5-10°/s; descriptors of a view stay matchable that far.
            keyframe_rotation_rad: 8f64.to_radians(),
            // Half the support gone: the next frames would soon rest on too few landmarks.
            keyframe_support_ratio: 0.5,
            // ~4 frames at 30 Hz: a slow sweep must not make a keyframe of every frame.
            min_keyframe_interval_s: 0.12,
            // A few dozen new points make a keyframe worth its bundle-adjustment cost.
            keyframe_min_new_tracks: 30,
            // Half the tracks gone: the pair would share too few points to start a good map.
            init_min_shared_ratio: 0.5,
            // A few blurred frames in a row are tolerated; more means the view is gone.
            max_consecutive_failures: 5,
            local_window: 8,
            ba: BaOptions::default(),
            max_error_rad: 0.008,
            // KLT tracks drift (measured against the truth on the 320 px survey: tracks
            // followed for 300+ frames end tens of mrad off any single point).
            split_outlier_tracks: true,
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
    /// Tracks split by the mapper (new id → the front-end track it continues): a track that
    /// stopped agreeing with its landmark (KLT drift) continues under a new id from that frame
    /// on, so its later observations never pull on the old landmark.
    pub split_from: BTreeMap<u64, u64>,
}

/// First id given to split tracks: far above any front-end track id.
pub const SPLIT_TRACK_BASE: u64 = 1 << 48;

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

/// A two-view initialization: the second frame's pose relative to the first and the
/// triangulated inliers.
struct InitialPair {
    second: usize,
    cam2_from_cam1: Pose,
    points: BTreeMap<u64, Vector3<f64>>,
}

/// Outcome of one initialization attempt.
enum PairTrial {
    /// The frames share too few tracks: the pair's first frame must move forward.
    TooFewShared,
    /// Not enough parallax or inliers yet.
    NotYet,
    /// A usable pair.
    Found(InitialPair),
}

/// Try to initialize from `frames[first]` and `frames[second]`.
fn try_initial_pair(
    frames: &[MappingFrame],
    first: usize,
    second: usize,
    options: &MapperOptions,
) -> Result<PairTrial> {
    let (a, f) = (&frames[first], &frames[second]);
    let (ids, b1, b2) = common(&a.observations, &f.observations);
    let needed = (options.init_min_shared_ratio * a.observations.len() as f64).ceil() as usize;
    if ids.len() < options.ransac.min_inliers.max(needed) {
        return Ok(PairTrial::TooFewShared);
    }
    let Some(rel) = relative_pose_ransac(&b1, &b2, &seeded(&options.ransac, f.frame)) else {
        return Ok(PairTrial::NotYet);
    };
    // Cheap test before the refinement: rotation-compensated parallax of the inliers.
    let rough: Vec<f64> = (0..ids.len())
        .filter(|&i| rel.inliers[i])
        .map(|i| angular_error(&(rel.cam2_from_cam1.rotation * b1[i]), &b2[i]))
        .collect();
    if median(rough).unwrap_or(0.0) < 0.8 * options.init_parallax_rad {
        return Ok(PairTrial::NotYet);
    }
    let pose = refine_relative_pose(
        &rel.cam2_from_cam1,
        &b1,
        &b2,
        &rel.inliers,
        options.ba.huber_rad,
    )?;
    let mut points = BTreeMap::new();
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
            points.insert(ids[i], t.point);
        }
    }
    let all_parallax: Vec<f64> = (0..ids.len())
        .filter(|&i| rel.inliers[i])
        .map(|i| angular_error(&(pose.rotation * b1[i]), &b2[i]))
        .collect();
    let med = median(all_parallax).unwrap_or(0.0);
    if med < options.init_parallax_rad || points.len() < options.ransac.min_inliers {
        return Ok(PairTrial::NotYet);
    }
    Ok(PairTrial::Found(InitialPair {
        second,
        cam2_from_cam1: pose,
        points,
    }))
}

/// Build a map from tracked frames.
///
/// Initialization looks for the first pair with enough parallax: frame 0 against each later
/// frame; when frame 0's tracks have thinned out without such a partner (a slow start, or
/// rotation only), the pair's first frame moves forward. Mapping then continues frame by
/// frame; isolated frames without a pose are skipped, and mapping stops (with `lost_at`) after
/// `max_consecutive_failures` in a row. Fails if no initial pair is found.
pub fn reconstruct(frames: &[MappingFrame], options: &MapperOptions) -> Result<Reconstruction> {
    if frames.len() < 2 {
        return Err(mapping_error(format!(
            "expected at least two frames, found {}",
            frames.len()
        )));
    }
    // 1. Initialization: the first pair (k0, k1) with enough parallax.
    let mut init = None;
    let mut k0 = 0;
    let mut k = 1;
    while k < frames.len() {
        match try_initial_pair(frames, k0, k, options)? {
            PairTrial::TooFewShared => {
                // Too few shared tracks: start again from the previous frame (which still
                // shares enough with the current one), or this one.
                k0 = if k - 1 > k0 { k - 1 } else { k };
                if k0 == k {
                    k += 1;
                }
            }
            PairTrial::NotYet => k += 1,
            PairTrial::Found(pair) => {
                init = Some(pair);
                break;
            }
        }
    }
    let pair = init.ok_or_else(|| {
        mapping_error(
            "no pair of frames with enough parallax and inliers to initialize; the mapping \
             episode needs translation, not only rotation"
                .into(),
        )
    })?;
    let k1 = pair.second;
    tracing::debug!(
        first = frames[k0].frame,
        second = frames[k1].frame,
        points = pair.points.len(),
        "mapping initialized"
    );
    let (f0, f1) = (&frames[k0], &frames[k1]);
    let mut recon = Reconstruction {
        keyframes: vec![
            ReconKeyframe {
                frame: f0.frame,
                t: f0.t,
                cam_from_world: Pose::identity(),
                observations: sorted(&f0.observations),
            },
            ReconKeyframe {
                frame: f1.frame,
                t: f1.t,
                cam_from_world: pair.cam2_from_cam1,
                observations: sorted(&f1.observations),
            },
        ],
        landmarks: pair.points,
        frame_poses: Vec::new(),
        lost_at: None,
        split_from: BTreeMap::new(),
    };
    local_ba(&mut recon, options, true)?;
    // Frames before the initial pair: poses from the first map where possible.
    for f in &frames[..k0] {
        if let Some(abs) = frame_pose(&recon, f, options) {
            recon.frame_poses.push((f.frame, abs.cam_from_world));
        }
    }
    recon
        .frame_poses
        .push((f0.frame, recon.keyframes[0].cam_from_world));
    // Frames between the pair: poses, and keyframes inserted before the pair's second frame
    // by the same rules as later (a slow start must not leave its views out of the map).
    let mut last_kf = 0;
    for f in &frames[k0 + 1..k1] {
        let Some(abs) = frame_pose(&recon, f, options) else {
            continue;
        };
        recon.frame_poses.push((f.frame, abs.cam_from_world));
        if needs_keyframe(&recon, &recon.keyframes[last_kf], f, &abs, options) {
            last_kf += 1;
            let kf = keyframe_from(&recon, f, &abs);
            recon.keyframes.insert(last_kf, kf);
            triangulate_new(&mut recon, last_kf, options);
        }
    }
    recon
        .frame_poses
        .push((f1.frame, recon.keyframes[last_kf + 1].cam_from_world));
    if last_kf > 0 {
        local_ba(&mut recon, options, true)?;
    }

    // 2. Incremental: pose of every frame, keyframes by parallax and support. A mapped track
    // that is an outlier of its frame's pose has drifted off its landmark (KLT slides along
    // texture under scale change): it continues under a new id (`alias`), unmapped.
    let mut failures = 0;
    let mut alias: BTreeMap<u64, u64> = BTreeMap::new();
    let mut next_split = SPLIT_TRACK_BASE;
    for f in &frames[k1 + 1..] {
        let mut f = f.clone();
        for o in &mut f.observations {
            if let Some(&a) = alias.get(&o.track) {
                o.track = a;
            }
        }
        let Some(abs) = frame_pose(&recon, &f, options) else {
            failures += 1;
            if failures >= options.max_consecutive_failures.max(1) {
                recon.lost_at = Some(f.frame);
                break;
            }
            continue;
        };
        failures = 0;
        let pose = abs.cam_from_world;
        recon.frame_poses.push((f.frame, pose));
        if options.split_outlier_tracks {
            let mut j = 0;
            for o in &mut f.observations {
                if !recon.landmarks.contains_key(&o.track) {
                    continue;
                }
                if !abs.inliers[j] {
                    let origin = recon.split_from.get(&o.track).copied().unwrap_or(o.track);
                    alias.insert(origin, next_split);
                    recon.split_from.insert(next_split, origin);
                    o.track = next_split;
                    next_split += 1;
                }
                j += 1;
            }
        }
        let Some(last) = recon.keyframes.last() else {
            break;
        };
        if !needs_keyframe(&recon, last, &f, &abs, options) {
            continue;
        }
        let kf = if options.split_outlier_tracks {
            // Outliers were renamed: every mapped observation left is an inlier.
            ReconKeyframe {
                frame: f.frame,
                t: f.t,
                cam_from_world: pose,
                observations: sorted(&f.observations),
            }
        } else {
            keyframe_from(&recon, &f, &abs)
        };
        recon.keyframes.push(kf);
        let newest = recon.keyframes.len() - 1;
        triangulate_new(&mut recon, newest, options);
        local_ba(&mut recon, options, false)?;
    }
    // 3. Global bundle adjustment.
    local_ba(&mut recon, options, true)?;
    Ok(recon)
}

/// A keyframe from a posed frame: the inlier observations of mapped tracks and all unmapped
/// ones, in track order.
fn keyframe_from(
    recon: &Reconstruction,
    f: &MappingFrame,
    abs: &crate::vision::geometry::AbsolutePose,
) -> ReconKeyframe {
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
    ReconKeyframe {
        frame: f.frame,
        t: f.t,
        cam_from_world: abs.cam_from_world,
        observations,
    }
}

/// Keyframe decision for a frame with pose `abs` after keyframe `last`: a keyframe when the
/// map's support has dropped to `keyframe_support_ratio` of what the last keyframe saw, or when
/// the rotation-compensated parallax reaches `keyframe_parallax_rad` and there are new tracks
/// to triangulate, or the view has turned by `keyframe_rotation_rad`; never closer than `min_keyframe_interval_s` to the last keyframe unless the
/// support is nearly gone.
fn needs_keyframe(
    recon: &Reconstruction,
    last: &ReconKeyframe,
    f: &MappingFrame,
    abs: &crate::vision::geometry::AbsolutePose,
    options: &MapperOptions,
) -> bool {
    let last_mapped = last
        .observations
        .iter()
        .filter(|o| recon.landmarks.contains_key(&o.track))
        .count();
    let support = abs.num_inliers as f64 / last_mapped.max(1) as f64;
    // Critical: a few more lost points and the next frame cannot be posed.
    if abs.num_inliers < 4 * options.ransac.min_inliers {
        return true;
    }
    if f.t - last.t < options.min_keyframe_interval_s {
        return false;
    }
    if support < options.keyframe_support_ratio {
        return true;
    }
    let (ids, b_last, b_cur) = common(&last.observations, &f.observations);
    let new_tracks = ids
        .iter()
        .filter(|t| !recon.landmarks.contains_key(t))
        .count();
    if new_tracks < options.keyframe_min_new_tracks {
        return false;
    }
    let rel_rot = abs.cam_from_world.rotation * last.cam_from_world.rotation.inverse();
    if rel_rot.angle() >= options.keyframe_rotation_rad {
        return true;
    }
    let parallax = median(
        b_last
            .iter()
            .zip(&b_cur)
            .map(|(a, b)| angular_error(&(rel_rot * a), b))
            .collect(),
    )
    .unwrap_or(0.0);
    parallax >= options.keyframe_parallax_rad
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

/// Triangulate tracks of keyframe `index` that have no landmark yet, from every keyframe that
/// observes them.
fn triangulate_new(recon: &mut Reconstruction, index: usize, options: &MapperOptions) {
    let Some(newest) = recon.keyframes.get(index) else {
        return;
    };
    let candidates: Vec<u64> = newest
        .observations
        .iter()
        .map(|o| o.track)
        .filter(|t| !recon.landmarks.contains_key(t))
        .collect();
    // Every keyframe that saw the track (not only the window): a slow sweep needs the oldest
    // view for parallax.
    for track in candidates {
        let rays: Vec<RayObservation> = recon
            .keyframes
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
pub(crate) fn local_ba(
    recon: &mut Reconstruction,
    options: &MapperOptions,
    global: bool,
) -> Result<()> {
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

/// Global bundle adjustment of a reconstruction (keyframe 0 fixed), dropping observations whose
/// error then exceeds `options.max_error_rad`: run after loop closure has corrected and merged
/// the map.
pub fn global_adjustment(recon: &mut Reconstruction, options: &MapperOptions) -> Result<()> {
    local_ba(recon, options, true)
}
