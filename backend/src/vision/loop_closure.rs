//! Loop closure over a finished reconstruction: the mapping sweep's returns to places it has
//! mapped before are found by place recognition, verified geometrically, and used to correct
//! the drift.
//!
//! 1. **Detection.** A bag-of-words vocabulary is learned from the keyframes' ORB descriptors;
//!    each keyframe queries the keyframe database for earlier keyframes at least
//!    [`LoopOptions::min_gap_s`] before it that share few landmarks with it (not already
//!    connected by tracking).
//! 2. **Verification** ([`verify_place`]): the query keyframe's ORB features are matched
//!    (mutual + ratio) to the landmarks of the candidate and its neighbours; P3P RANSAC on the
//!    bearings; the pose is accepted only with many inliers, a high inlier ratio, a wide
//!    angular spread, and a consistent depth ratio between the candidate's landmarks and the
//!    query's own (the scale drift). A loop is closed only when at least
//!    [`LoopOptions::min_consistent`] verified keyframes agree on the correction, so a single
//!    coincidental match never bends the map.
//! 3. **Correction.** A Sim(3) pose graph over the keyframes (odometry edges between each
//!    keyframe and its next few, from the current estimate; loop edges from the verification)
//!    is solved by Gauss–Newton; keyframes take their corrected poses, landmarks move with the
//!    keyframe that first saw them, and non-keyframe poses with their preceding keyframe.
//! 4. **Fusion.** The loop's verified associations merge each query-side landmark into the
//!    candidate-side landmark it matched (every keyframe's observations are renamed), or add an
//!    observation of the candidate's landmark to the query keyframe; the caller then runs a
//!    global bundle adjustment.
//!
//! Everything is sequential and ordered (keyframe order, track order, seeded RANSAC), so the
//! result is bit-identical across runs and thread counts.

use std::collections::{BTreeMap, BTreeSet};

use faer::Mat;
use nalgebra::{Point2, Point3, Vector3};

use kiwi_core::geometry::{Pose, so3_exp, so3_log};

use crate::vision::align::Sim3;
use crate::vision::features::{
    Descriptor, DescriptorMatch, FrameFeatures, MatchOptions, match_descriptors,
};
use crate::vision::geometry::{RansacOptions, absolute_pose_ransac};
use crate::vision::localize::angular_spread;
use crate::vision::map::ASSOCIATION_RADIUS_PX;
use crate::vision::mapping::{Reconstruction, TrackObservation};
use crate::vision::place::{KeyframeDatabase, Vocabulary};

/// Settings of loop detection, verification and correction.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LoopOptions {
    /// A candidate is at least this long (s) before the query keyframe: recent keyframes are
    /// connected by tracking already.
    pub min_gap_s: f64,
    /// A candidate shares fewer than this fraction of the smaller keyframe's landmarks with the
    /// query (more means tracking has connected them already).
    pub max_shared_fraction: f64,
    /// Candidates taken from place recognition per query keyframe.
    pub candidates: usize,
    /// Keyframes on each side of a candidate whose landmarks join the verification.
    pub neighbours: usize,
    /// Fewest P3P inliers of a verified place.
    pub min_inliers: usize,
    /// Smallest inlier ratio among the descriptor matches.
    pub min_inlier_ratio: f64,
    /// Smallest angular spread (rad) of the inlier bearings.
    pub min_spread_rad: f64,
    /// Fewest inliers whose query-side landmark exists (for the scale ratio).
    pub min_scale_pairs: usize,
    /// Largest ratio between the upper and lower quartiles of the depth ratios.
    pub max_scale_spread: f64,
    /// Fewest verified keyframes agreeing on one correction before a loop is closed.
    pub min_consistent: usize,
    /// Largest disagreement of two verified corrections: rotation (rad).
    pub consistency_rotation_rad: f64,
    /// Largest disagreement of two verified corrections: position of the query camera, as a
    /// fraction of the median landmark depth of the query keyframe.
    pub consistency_position: f64,
    /// Descriptor matching of the verification.
    pub matching: MatchOptions,
    /// Whether a candidate that descriptor matching cannot verify is verified again on matches
    /// found around the query's current pose ([`verify_place_guided`]).
    pub guided: bool,
    /// Largest angle (rad) between a query bearing and a candidate landmark projected with the
    /// query's current pose in the guided verification: the drift a guided loop can correct.
    pub guided_radius_rad: f64,
    /// Largest Hamming distance of a guided match.
    pub guided_max_distance: u32,
    /// Odometry edges from each keyframe to this many following keyframes.
    pub odometry_span: usize,
    /// Gauss–Newton iterations of the pose graph.
    pub max_iterations: usize,
}

impl Default for LoopOptions {
    fn default() -> Self {
        Self {
            // A few seconds: the sweep must have left the place and come back.
            min_gap_s: 5.0,
            // Far walls stay tracked for long: a few shared landmarks do not close a loop.
            max_shared_fraction: 0.2,
            candidates: 3,
            neighbours: 2,
            // Well above localization's 40: a loop bends the whole map, a wrong one ruins it.
            min_inliers: 50,
            // A true place explains most matches; a coincidence a small minority.
            min_inlier_ratio: 0.5,
            // Inliers over a wide part of the view constrain the position (as localization).
            min_spread_rad: 0.1,
            // Enough pairs for a robust median of the scale ratio.
            min_scale_pairs: 10,
            // Depth ratios of one rigid scene agree within noise; ±20 % between quartiles is loose.
            max_scale_spread: 1.2,
            // Two views of the same return: one coincidental verification is not enough.
            min_consistent: 2,
            // ~3°: two corrections of one loop agree far better than this.
            consistency_rotation_rad: 3f64.to_radians(),
            // 5 % of the scene depth: far below what a wrong place implies.
            consistency_position: 0.05,
            matching: MatchOptions::default(),
            guided: true,
            // 0.1 rad: a 2 % drift over a 10 m sweep seen at 2 m depth; a pattern repeating
            // every 0.3 m or more at up to 2.5 m puts its next copy beyond it.
            guided_radius_rad: 0.1,
            guided_max_distance: crate::vision::features::GUIDED_MAX_DISTANCE,
            // Each keyframe tied to its next 3: a stiff chain, as tracking connects them.
            odometry_span: 3,
            max_iterations: 30,
        }
    }
}

/// A verified place: the query camera's pose in the candidate's map region and its support.
#[derive(Debug, Clone, PartialEq)]
pub struct PlaceMatch {
    /// `cam_from_world` of the query in the candidate's (drifted) coordinates.
    pub cam_from_world: Pose,
    /// Inlier pairs (query feature index, candidate point index).
    pub inliers: Vec<(usize, usize)>,
    /// Descriptor matches that went into RANSAC.
    pub matches: usize,
    /// Median ratio of the candidate-side depth to the query-side depth (1 without drift).
    pub scale: f64,
}

/// One side of a place verification: the query keyframe's features.
#[derive(Debug, Clone, Copy)]
pub struct QueryFeature {
    /// Unit bearing in the query camera.
    pub bearing: Vector3<f64>,
    /// ORB descriptor.
    pub descriptor: Descriptor,
    /// Position of the query's own landmark at this feature (query coordinates), if any.
    pub own_point: Option<Vector3<f64>>,
}

/// The other side: a described candidate landmark.
#[derive(Debug, Clone, Copy)]
pub struct CandidatePoint {
    /// Position in the candidate's coordinates.
    pub position: Vector3<f64>,
    /// Representative descriptor.
    pub descriptor: Descriptor,
}

/// Why a verification failed (for logs and tests).
#[derive(Debug, Clone, PartialEq)]
pub enum PlaceRejection {
    /// Too few descriptor matches for RANSAC.
    TooFewMatches(usize),
    /// No pose with enough inliers.
    NoPose,
    /// Inlier ratio too low.
    Ratio(f64),
    /// Inliers on one patch.
    Spread(f64),
    /// Too few pairs with a query-side landmark (`pairs`), or inconsistent depth ratios (upper
    /// over lower quartile `spread`).
    Scale {
        /// Inliers with a query-side landmark.
        pairs: usize,
        /// Upper over lower quartile of the depth ratios (0 when not computed).
        spread: f64,
    },
}

/// Verify that the query features view the candidate points: descriptor matching, P3P RANSAC
/// with `ransac` (its `min_inliers` is raised to `options.min_inliers`) and the acceptance
/// rules of [`LoopOptions`]. `query_cam_from_world` is the query's own pose (for the depth ratio).
pub fn verify_place(
    query: &[QueryFeature],
    query_cam_from_world: &Pose,
    candidate: &[CandidatePoint],
    ransac: &RansacOptions,
    options: &LoopOptions,
) -> Result<PlaceMatch, PlaceRejection> {
    let qd: Vec<Descriptor> = query.iter().map(|q| q.descriptor).collect();
    let cd: Vec<Descriptor> = candidate.iter().map(|c| c.descriptor).collect();
    let matches = match_descriptors(&qd, &cd, &options.matching);
    verify_matches(
        query,
        query_cam_from_world,
        candidate,
        &matches,
        ransac,
        options,
    )
}

/// Verify a place as [`verify_place`] does, on matches found around the query's current pose
/// instead of by descriptor alone: each candidate landmark is projected into the query with
/// `query_cam_from_world` (the drifted map's own estimate) and matched to the query feature
/// within [`LoopOptions::guided_radius_rad`] of it whose descriptor is nearest (at most
/// [`LoopOptions::guided_max_distance`] bits), each query feature keeping its nearest landmark.
/// Where a pattern repeats, the ratio test of descriptor matching drops every copy, while a
/// copy one period away lies outside the radius; the loop it closes corrects only drift
/// smaller than the radius.
pub fn verify_place_guided(
    query: &[QueryFeature],
    query_cam_from_world: &Pose,
    candidate: &[CandidatePoint],
    ransac: &RansacOptions,
    options: &LoopOptions,
) -> Result<PlaceMatch, PlaceRejection> {
    let cos_radius = options.guided_radius_rad.cos();
    // Best candidate landmark per query feature: (distance, candidate index).
    let mut best: Vec<Option<(u32, usize)>> = vec![None; query.len()];
    for (c, point) in candidate.iter().enumerate() {
        let in_query = query_cam_from_world * Point3::from(point.position);
        let Some(b) = in_query.coords.try_normalize(f64::EPSILON) else {
            continue;
        };
        let mut nearest: Option<(u32, usize)> = None;
        for (q, feature) in query.iter().enumerate() {
            if feature.bearing.dot(&b) < cos_radius {
                continue;
            }
            let d = feature.descriptor.distance(&point.descriptor);
            if d <= options.guided_max_distance && nearest.is_none_or(|n| d < n.0) {
                nearest = Some((d, q));
            }
        }
        if let Some((d, q)) = nearest
            && best[q].is_none_or(|b| d < b.0)
        {
            best[q] = Some((d, c));
        }
    }
    let matches: Vec<DescriptorMatch> = best
        .iter()
        .enumerate()
        .filter_map(|(q, b)| {
            b.map(|(distance, train)| DescriptorMatch {
                query: q,
                train,
                distance,
            })
        })
        .collect();
    verify_matches(
        query,
        query_cam_from_world,
        candidate,
        &matches,
        ransac,
        options,
    )
}

/// The geometric part of a place verification on given query–candidate matches.
fn verify_matches(
    query: &[QueryFeature],
    query_cam_from_world: &Pose,
    candidate: &[CandidatePoint],
    matches: &[DescriptorMatch],
    ransac: &RansacOptions,
    options: &LoopOptions,
) -> Result<PlaceMatch, PlaceRejection> {
    if matches.len() < options.min_inliers {
        return Err(PlaceRejection::TooFewMatches(matches.len()));
    }
    let bearings: Vec<Vector3<f64>> = matches.iter().map(|m| query[m.query].bearing).collect();
    let points: Vec<Vector3<f64>> = matches
        .iter()
        .map(|m| candidate[m.train].position)
        .collect();
    let ro = RansacOptions {
        min_inliers: ransac.min_inliers.max(options.min_inliers),
        ..*ransac
    };
    let abs = absolute_pose_ransac(&bearings, &points, &ro).ok_or(PlaceRejection::NoPose)?;
    let ratio = abs.num_inliers as f64 / matches.len() as f64;
    if ratio < options.min_inlier_ratio {
        return Err(PlaceRejection::Ratio(ratio));
    }
    let inlier_bearings: Vec<Vector3<f64>> = (0..matches.len())
        .filter(|&i| abs.inliers[i])
        .map(|i| bearings[i])
        .collect();
    let spread = angular_spread(&inlier_bearings);
    if spread < options.min_spread_rad {
        return Err(PlaceRejection::Spread(spread));
    }
    let mut ratios = Vec::new();
    let mut inliers = Vec::new();
    for (i, m) in matches.iter().enumerate() {
        if !abs.inliers[i] {
            continue;
        }
        inliers.push((m.query, m.train));
        if let Some(own) = query[m.query].own_point {
            let d_own = (query_cam_from_world * Point3::from(own)).coords.norm();
            let d_cand = (abs.cam_from_world * Point3::from(points[i])).coords.norm();
            if d_own > 0.0 && d_cand.is_finite() {
                ratios.push(d_cand / d_own);
            }
        }
    }
    if ratios.len() < options.min_scale_pairs {
        return Err(PlaceRejection::Scale {
            pairs: ratios.len(),
            spread: 0.0,
        });
    }
    ratios.sort_by(f64::total_cmp);
    let q = |f: f64| ratios[((ratios.len() - 1) as f64 * f).round() as usize];
    let (q1, med, q3) = (q(0.25), q(0.5), q(0.75));
    if !(q1 > 0.0 && q3 / q1 <= options.max_scale_spread) {
        return Err(PlaceRejection::Scale {
            pairs: ratios.len(),
            spread: q3 / q1,
        });
    }
    Ok(PlaceMatch {
        cam_from_world: abs.cam_from_world,
        inliers,
        matches: matches.len(),
        scale: med,
    })
}

/// A closed loop between two keyframes.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct LoopClosure {
    /// Query keyframe (the later one).
    pub query: usize,
    /// Candidate keyframe (the earlier one).
    pub candidate: usize,
    /// Verified inliers.
    pub inliers: usize,
    /// Scale drift (candidate / query).
    pub scale: f64,
}

/// What [`close_loops`] did.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct LoopReport {
    /// Places verified (before the consistency check).
    pub verified: usize,
    /// Loops used for the correction.
    pub closed: Vec<LoopClosure>,
    /// Query-side landmarks merged into candidate landmarks.
    pub merged_landmarks: usize,
    /// Observations of candidate landmarks added to query keyframes.
    pub added_observations: usize,
}

/// `x ↦ s R x + t` composed: `(a ∘ b)(x) = a(b(x))`.
fn compose(a: &Sim3, b: &Sim3) -> Sim3 {
    Sim3 {
        scale: a.scale * b.scale,
        rotation: a.rotation * b.rotation,
        translation: a.rotation * b.translation * a.scale + a.translation,
    }
}

fn from_pose(p: &Pose) -> Sim3 {
    Sim3 {
        scale: 1.0,
        rotation: p.rotation,
        translation: p.translation.vector,
    }
}

/// A node's Sim(3) `cam_from_world` (camera coordinates in the keyframe's local scale) as the
/// metric-free SE(3) pose of the corrected map: `x ↦ R x + t / s`.
fn to_pose(s: &Sim3) -> Pose {
    Pose::from_parts((s.translation / s.scale).into(), s.rotation)
}

/// 7-vector residual of `z⁻¹ ∘ a ∘ b⁻¹` (rotation vector, translation, log scale).
fn edge_residual(z_inv: &Sim3, a: &Sim3, b: &Sim3) -> [f64; 7] {
    let e = compose(&compose(z_inv, a), &b.inverse());
    let w = so3_log(&e.rotation);
    [
        w.x,
        w.y,
        w.z,
        e.translation.x,
        e.translation.y,
        e.translation.z,
        e.scale.ln(),
    ]
}

/// Left-multiplied update `exp(δ) ∘ s`, `δ = [ω; v; σ]`.
fn perturb(s: &Sim3, d: &[f64]) -> Sim3 {
    let u = Sim3 {
        scale: d[6].exp(),
        rotation: so3_exp(&Vector3::new(d[0], d[1], d[2])),
        translation: Vector3::new(d[3], d[4], d[5]),
    };
    compose(&u, s)
}

/// An edge of the pose graph: `a ∘ b⁻¹ ≈ z` (`cam_a_from_cam_b`), with per-component weights.
struct Edge {
    a: usize,
    b: usize,
    z_inv: Sim3,
    weight: [f64; 7],
}

/// Numeric-derivative step of the pose graph's Jacobians.
const JACOBIAN_STEP: f64 = 1e-6;
/// Stop the pose-graph iterations when the update's largest component falls below this.
const POSE_GRAPH_TOLERANCE: f64 = 1e-10;
/// Rotation standard deviation (rad) of an edge: the tracked odometry's rotation drift.
const EDGE_SIGMA_ROT: f64 = 0.002;
/// Scale standard deviation (log) of an edge.
const EDGE_SIGMA_SCALE: f64 = 0.01;
/// Weight of a verified loop edge relative to an odometry edge: the loop pose rests on 50+
/// verified inliers against the old map; the odometry between the two ends has drifted over
/// dozens of keyframes, so the loop must win.
const LOOP_EDGE_WEIGHT: f64 = 100.0;
/// Translation standard deviation of an edge as a fraction of the median keyframe step.
const EDGE_SIGMA_TRANS_FRACTION: f64 = 0.01;

/// Solve the Sim(3) pose graph (node 0 fixed) by Gauss–Newton with a dense sequential Cholesky.
fn solve_pose_graph(nodes: &mut [Sim3], edges: &[Edge], max_iterations: usize) {
    let n = nodes.len();
    if n < 2 {
        return;
    }
    let dim = 7 * (n - 1);
    for _ in 0..max_iterations {
        let mut h = Mat::<f64>::zeros(dim, dim);
        let mut g = Mat::<f64>::zeros(dim, 1);
        let mut cost = 0.0;
        for e in edges {
            let r0 = edge_residual(&e.z_inv, &nodes[e.a], &nodes[e.b]);
            cost += (0..7).map(|r| e.weight[r] * r0[r] * r0[r]).sum::<f64>();
            // Jacobian columns: 7 for a, 7 for b.
            let mut jac = [[0.0f64; 14]; 7];
            for (side, node) in [(0usize, e.a), (1usize, e.b)] {
                for c in 0..7 {
                    let mut d = [0.0; 7];
                    d[c] = JACOBIAN_STEP;
                    let plus = perturb(&nodes[node], &d);
                    d[c] = -JACOBIAN_STEP;
                    let minus = perturb(&nodes[node], &d);
                    let (rp, rm) = if side == 0 {
                        (
                            edge_residual(&e.z_inv, &plus, &nodes[e.b]),
                            edge_residual(&e.z_inv, &minus, &nodes[e.b]),
                        )
                    } else {
                        (
                            edge_residual(&e.z_inv, &nodes[e.a], &plus),
                            edge_residual(&e.z_inv, &nodes[e.a], &minus),
                        )
                    };
                    for r in 0..7 {
                        jac[r][7 * side + c] = (rp[r] - rm[r]) / (2.0 * JACOBIAN_STEP);
                    }
                }
            }
            let slot = |node: usize| node.checked_sub(1).map(|k| 7 * k);
            let slots = [slot(e.a), slot(e.b)];
            for r in 0..7 {
                let w = e.weight[r];
                for (si, s) in slots.iter().enumerate() {
                    let Some(s) = s else { continue };
                    for c in 0..7 {
                        let jc = jac[r][7 * si + c];
                        g[(s + c, 0)] -= w * jc * r0[r];
                        for (sj, t) in slots.iter().enumerate() {
                            let Some(t) = t else { continue };
                            for c2 in 0..7 {
                                h[(s + c, t + c2)] += w * jc * jac[r][7 * sj + c2];
                            }
                        }
                    }
                }
            }
        }
        for i in 0..dim {
            h[(i, i)] += 1e-9 * h[(i, i)].abs().max(1.0);
        }
        if !crate::vision::ba::solve_spd_system(&mut h, &mut g) {
            tracing::debug!(cost, "pose graph: factorization failed");
            return;
        }
        let mut largest: f64 = 0.0;
        for k in 1..n {
            let d: Vec<f64> = (0..7).map(|c| g[(7 * (k - 1) + c, 0)]).collect();
            largest = d.iter().fold(largest, |m, v| m.max(v.abs()));
            nodes[k] = perturb(&nodes[k], &d);
        }
        if largest < POSE_GRAPH_TOLERANCE {
            break;
        }
    }
}

/// What a query feature stands for: its own track (`None` for a bare ORB feature) and pixel.
type QuerySource = (Option<u64>, Point2<f64>);
/// A loop association: the query's own track (if any), its pixel and bearing, and the
/// candidate landmark track.
type LoopPair = (Option<u64>, Point2<f64>, Vector3<f64>, u64);

/// The query side of keyframe `k`: its mapped observations (with the descriptor of the ORB
/// feature on them, else the track's detection descriptor; `own_point` its landmark), then its
/// ORB features that lie on no mapped observation. Also returns, per query feature, the track
/// it stands for (`None` for a bare ORB feature) and its pixel.
fn query_features(
    recon: &Reconstruction,
    k: usize,
    feats: &FrameFeatures,
    track_descriptors: &BTreeMap<u64, Descriptor>,
) -> (Vec<QueryFeature>, Vec<QuerySource>) {
    let kf = &recon.keyframes[k];
    let r2 = ASSOCIATION_RADIUS_PX * ASSOCIATION_RADIUS_PX;
    let mapped: Vec<TrackObservation> = kf
        .observations
        .iter()
        .filter(|o| recon.landmarks.contains_key(&o.track))
        .copied()
        .collect();
    let mut on_track: BTreeMap<u64, Descriptor> = BTreeMap::new();
    let mut out = Vec::new();
    let mut tracks = Vec::new();
    for (kp, d) in feats.keypoints.iter().zip(&feats.descriptors) {
        match nearest_track(&mapped, kp.pixel, r2) {
            Some(t) => {
                on_track.entry(t).or_insert(*d);
            }
            None => {
                out.push(QueryFeature {
                    bearing: kp.bearing,
                    descriptor: *d,
                    own_point: None,
                });
                tracks.push((None, kp.pixel));
            }
        }
    }
    for o in &mapped {
        let d = on_track
            .get(&o.track)
            .or_else(|| track_descriptors.get(&o.track));
        if let (Some(d), Some(p)) = (d, recon.landmarks.get(&o.track)) {
            out.push(QueryFeature {
                bearing: o.bearing,
                descriptor: *d,
                own_point: Some(*p),
            });
            tracks.push((Some(o.track), o.pixel));
        }
    }
    (out, tracks)
}

/// The mapped-or-not track observed within `sqrt(r2)` px of `pixel` (nearest).
fn nearest_track(obs: &[TrackObservation], pixel: Point2<f64>, r2: f64) -> Option<u64> {
    let mut best: Option<(f64, u64)> = None;
    for o in obs {
        let d2 = (o.pixel - pixel).norm_squared();
        if d2 <= r2 && best.is_none_or(|b| d2 < b.0) {
            best = Some((d2, o.track));
        }
    }
    best.map(|b| b.1)
}

/// The candidate side: landmarks seen by keyframes `lo..=hi`, one descriptor each (from the
/// keyframe nearest to `centre` whose feature lies on it, else the track's detection
/// descriptor), in track order.
fn candidate_points(
    recon: &Reconstruction,
    features: &[FrameFeatures],
    track_descriptors: &BTreeMap<u64, Descriptor>,
    centre: usize,
    lo: usize,
    hi: usize,
) -> (Vec<u64>, Vec<CandidatePoint>) {
    let mut order: Vec<usize> = (lo..=hi).collect();
    order.sort_by_key(|&k| (k.abs_diff(centre), k));
    let r2 = ASSOCIATION_RADIUS_PX * ASSOCIATION_RADIUS_PX;
    let mut chosen: BTreeMap<u64, Descriptor> = BTreeMap::new();
    let mut seen: BTreeSet<u64> = BTreeSet::new();
    for &k in &order {
        let kf = &recon.keyframes[k];
        for o in &kf.observations {
            if recon.landmarks.contains_key(&o.track) {
                seen.insert(o.track);
            }
        }
        let feats = &features[k];
        for (kp, d) in feats.keypoints.iter().zip(&feats.descriptors) {
            if let Some(t) = nearest_track(&kf.observations, kp.pixel, r2)
                && recon.landmarks.contains_key(&t)
            {
                chosen.entry(t).or_insert(*d);
            }
        }
    }
    let mut ids = Vec::new();
    let mut pts = Vec::new();
    for t in seen {
        let d = chosen.get(&t).or_else(|| track_descriptors.get(&t));
        if let (Some(d), Some(p)) = (d, recon.landmarks.get(&t)) {
            ids.push(t);
            pts.push(CandidatePoint {
                position: *p,
                descriptor: *d,
            });
        }
    }
    (ids, pts)
}

/// A verified loop before the consistency check.
struct Verified {
    query: usize,
    candidate: usize,
    /// Corrected `cam_from_world` of the query in the candidate's coordinates, as a Sim(3) in
    /// the query's local scale.
    node: Sim3,
    /// Associations: the query's own track (if the feature stands for one), its pixel and bearing, and
    /// the candidate landmark track.
    pairs: Vec<LoopPair>,
    scale: f64,
}

/// Detect, verify and close loops in `recon` (see the module documentation). `features[k]` are
/// keyframe `k`'s ORB features, `track_descriptors` the tracks' detection descriptors. The
/// caller runs the global bundle adjustment afterwards.
pub fn close_loops(
    recon: &mut Reconstruction,
    features: &[FrameFeatures],
    track_descriptors: &BTreeMap<u64, Descriptor>,
    ransac: &RansacOptions,
    options: &LoopOptions,
) -> LoopReport {
    let mut report = LoopReport::default();
    let n = recon.keyframes.len();
    if n < 3 || features.len() != n {
        return report;
    }
    let docs: Vec<Vec<Descriptor>> = features.iter().map(|f| f.descriptors.clone()).collect();
    let vocabulary = Vocabulary::train(&docs);
    let database = KeyframeDatabase::build(&vocabulary, &docs);
    let landmark_sets: Vec<BTreeSet<u64>> = recon
        .keyframes
        .iter()
        .map(|kf| {
            kf.observations
                .iter()
                .map(|o| o.track)
                .filter(|t| recon.landmarks.contains_key(t))
                .collect()
        })
        .collect();
    let mut verified: Vec<Verified> = Vec::new();
    for k in 0..n {
        let t_k = recon.keyframes[k].t;
        if t_k - recon.keyframes[0].t < options.min_gap_s {
            continue;
        }
        let bow = vocabulary.bow(&docs[k]);
        let candidates: Vec<usize> = database
            .query(&bow, n)
            .into_iter()
            .map(|(_, j)| j)
            .filter(|&j| {
                let shared = landmark_sets[j].intersection(&landmark_sets[k]).count();
                let smaller = landmark_sets[j].len().min(landmark_sets[k].len());
                recon.keyframes[j].t <= t_k - options.min_gap_s
                    && (shared as f64) < options.max_shared_fraction * smaller as f64
            })
            .take(options.candidates)
            .collect();
        if candidates.is_empty() {
            continue;
        }
        let (query, query_tracks) = query_features(recon, k, &features[k], track_descriptors);
        let pose_k = recon.keyframes[k].cam_from_world;
        for j in candidates {
            let lo = j.saturating_sub(options.neighbours);
            let hi = (j + options.neighbours).min(n - 1);
            let (ids, pts) = candidate_points(recon, features, track_descriptors, j, lo, hi);
            let seeded = RansacOptions {
                seed: ransac.seed ^ (k as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ j as u64,
                ..*ransac
            };
            let verified_place =
                verify_place(&query, &pose_k, &pts, &seeded, options).or_else(|why| {
                    if options.guided {
                        verify_place_guided(&query, &pose_k, &pts, &seeded, options).map_err(
                            |guided| {
                                tracing::debug!(?why, ?guided, "guided verification failed too");
                                why
                            },
                        )
                    } else {
                        Err(why)
                    }
                });
            match verified_place {
                Ok(m) => {
                    tracing::debug!(
                        query = k,
                        candidate = j,
                        t_query = t_k,
                        t_candidate = recon.keyframes[j].t,
                        inliers = m.inliers.len(),
                        matches = m.matches,
                        scale = m.scale,
                        "loop verified"
                    );
                    // Query camera in candidate coordinates, camera coordinates in the
                    // query's local scale: x_c = (R x + t) / scale.
                    let mut node = from_pose(&m.cam_from_world);
                    node.scale = 1.0 / m.scale;
                    node.translation /= m.scale;
                    verified.push(Verified {
                        query: k,
                        candidate: j,
                        node,
                        pairs: m
                            .inliers
                            .iter()
                            .map(|&(q, c)| {
                                (
                                    query_tracks[q].0,
                                    query_tracks[q].1,
                                    query[q].bearing,
                                    ids[c],
                                )
                            })
                            .collect(),
                        scale: m.scale,
                    });
                    break;
                }
                Err(why) => {
                    tracing::debug!(
                        query = k,
                        candidate = j,
                        t_query = t_k,
                        t_candidate = recon.keyframes[j].t,
                        ?why,
                        matches_needed = options.min_inliers,
                        "loop candidate rejected"
                    );
                }
            }
        }
    }
    report.verified = verified.len();
    // Consistency: keep a verified loop only when enough others imply the same correction.
    let correction = |v: &Verified| -> Sim3 {
        // world_cand_from_world_query = node⁻¹ ∘ current.
        compose(
            &v.node.inverse(),
            &from_pose(&recon.keyframes[v.query].cam_from_world),
        )
    };
    let depth = |k: usize| -> f64 {
        let kf = &recon.keyframes[k];
        let mut d: Vec<f64> = kf
            .observations
            .iter()
            .filter_map(|o| recon.landmarks.get(&o.track))
            .map(|p| (kf.cam_from_world * Point3::from(*p)).coords.norm())
            .collect();
        d.sort_by(f64::total_cmp);
        d.get(d.len() / 2).copied().unwrap_or(0.0)
    };
    let centre = |k: usize| -> Vector3<f64> {
        recon.keyframes[k]
            .cam_from_world
            .inverse()
            .translation
            .vector
    };
    let corrections: Vec<Sim3> = verified.iter().map(correction).collect();
    let agree = |a: usize, b: usize| -> bool {
        let (ca, cb) = (&corrections[a], &corrections[b]);
        let rot = ca.rotation.angle_to(&cb.rotation);
        let qa = verified[a].query;
        let tol = options.consistency_position * depth(qa);
        let pa = ca.transform_point(&centre(qa));
        let pb = cb.transform_point(&centre(qa));
        // Compare in the candidate side's scale (the corrected one).
        rot <= options.consistency_rotation_rad && (pa - pb).norm() <= tol * ca.scale.max(1e-12)
    };
    let accepted: Vec<usize> = (0..verified.len())
        .filter(|&a| {
            let support = (0..verified.len())
                .filter(|&b| b != a && verified[b].query != verified[a].query && agree(a, b))
                .count();
            support + 1 >= options.min_consistent
        })
        .collect();
    if accepted.is_empty() {
        return report;
    }
    // Pose graph.
    let mut nodes: Vec<Sim3> = recon
        .keyframes
        .iter()
        .map(|kf| from_pose(&kf.cam_from_world))
        .collect();
    let old_nodes = nodes.clone();
    let mut steps: Vec<f64> = (1..n).map(|k| (centre(k) - centre(k - 1)).norm()).collect();
    steps.sort_by(f64::total_cmp);
    let step = steps.get(steps.len() / 2).copied().unwrap_or(1.0).max(1e-9);
    let sigma_t = EDGE_SIGMA_TRANS_FRACTION * step;
    let weight = [
        1.0 / (EDGE_SIGMA_ROT * EDGE_SIGMA_ROT),
        1.0 / (EDGE_SIGMA_ROT * EDGE_SIGMA_ROT),
        1.0 / (EDGE_SIGMA_ROT * EDGE_SIGMA_ROT),
        1.0 / (sigma_t * sigma_t),
        1.0 / (sigma_t * sigma_t),
        1.0 / (sigma_t * sigma_t),
        1.0 / (EDGE_SIGMA_SCALE * EDGE_SIGMA_SCALE),
    ];
    let mut edges = Vec::new();
    for a in 0..n {
        for b in a + 1..(a + 1 + options.odometry_span).min(n) {
            let z = compose(&nodes[a], &nodes[b].inverse());
            edges.push(Edge {
                a,
                b,
                z_inv: z.inverse(),
                weight,
            });
        }
    }
    for &i in &accepted {
        let v = &verified[i];
        // cam_query_from_cam_candidate.
        let z = compose(&v.node, &nodes[v.candidate].inverse());
        edges.push(Edge {
            a: v.query,
            b: v.candidate,
            z_inv: z.inverse(),
            weight: weight.map(|w| w * LOOP_EDGE_WEIGHT),
        });
        report.closed.push(LoopClosure {
            query: v.query,
            candidate: v.candidate,
            inliers: v.pairs.len(),
            scale: v.scale,
        });
    }
    let loop_error = |nodes: &[Sim3]| -> f64 {
        edges
            .iter()
            .skip(edges.len() - report.closed.len())
            .map(|e| {
                let r = edge_residual(&e.z_inv, &nodes[e.a], &nodes[e.b]);
                (r[3] * r[3] + r[4] * r[4] + r[5] * r[5]).sqrt()
            })
            .fold(0.0, f64::max)
    };
    let before = loop_error(&nodes);
    for e in edges.iter().skip(edges.len() - report.closed.len()) {
        let r = edge_residual(&e.z_inv, &nodes[e.a], &nodes[e.b]);
        let z = e.z_inv.inverse();
        // Query centre in the candidate camera's frame, measured and current.
        let meas = z.inverse().transform_point(&Vector3::zeros());
        let cur = compose(&nodes[e.b], &nodes[e.a].inverse()).transform_point(&Vector3::zeros());
        tracing::debug!(query = e.a, candidate = e.b, ?r, ?meas, ?cur, "loop edge");
    }
    solve_pose_graph(&mut nodes, &edges, options.max_iterations);
    tracing::debug!(
        before,
        after = loop_error(&nodes),
        step,
        "pose graph: largest loop translation residual"
    );
    // Landmarks move with the first keyframe that observes them.
    let mut first_kf: BTreeMap<u64, usize> = BTreeMap::new();
    for (k, kf) in recon.keyframes.iter().enumerate() {
        for o in &kf.observations {
            first_kf.entry(o.track).or_insert(k);
        }
    }
    for (track, p) in &mut recon.landmarks {
        let Some(&k) = first_kf.get(track) else {
            continue;
        };
        let local = old_nodes[k].transform_point(p);
        *p = nodes[k].inverse().transform_point(&local);
    }
    // Non-keyframe poses follow their preceding keyframe.
    let kf_frames: Vec<u32> = recon.keyframes.iter().map(|kf| kf.frame).collect();
    for (frame, pose) in &mut recon.frame_poses {
        let k = kf_frames
            .partition_point(|&f| f <= *frame)
            .saturating_sub(1);
        let rel = compose(&from_pose(pose), &old_nodes[k].inverse());
        let fixed = compose(&rel, &nodes[k]);
        *pose = to_pose(&fixed);
    }
    for (kf, node) in recon.keyframes.iter_mut().zip(&nodes) {
        kf.cam_from_world = to_pose(node);
    }
    // Fusion: merge query-side landmarks into the candidate's, or add observations.
    let mut alias: BTreeMap<u64, u64> = BTreeMap::new();
    let mut added: Vec<(usize, TrackObservation)> = Vec::new();
    for &i in &accepted {
        let v = &verified[i];
        for &(own, pixel, bearing, cand_track) in &v.pairs {
            match own {
                Some(own) => {
                    let (a, b) = (resolve(&alias, own), resolve(&alias, cand_track));
                    if a != b {
                        // Keep the older (candidate-side, lower id) landmark.
                        let (keep, drop) = if a < b { (a, b) } else { (b, a) };
                        alias.insert(drop, keep);
                    }
                }
                None => added.push((
                    v.query,
                    TrackObservation {
                        track: cand_track,
                        bearing,
                        pixel,
                    },
                )),
            }
        }
    }
    report.merged_landmarks = alias.len();
    for (k, o) in added {
        let kf = &mut recon.keyframes[k];
        let t = resolve(&alias, o.track);
        if kf
            .observations
            .iter()
            .any(|x| resolve(&alias, x.track) == t)
        {
            continue;
        }
        kf.observations.push(TrackObservation { track: t, ..o });
        report.added_observations += 1;
    }
    for kf in &mut recon.keyframes {
        for o in &mut kf.observations {
            o.track = resolve(&alias, o.track);
        }
        // One observation per landmark and keyframe (the first, in the original order).
        let mut seen = BTreeSet::new();
        kf.observations.retain(|o| seen.insert(o.track));
        kf.observations.sort_by_key(|o| o.track);
    }
    for drop in alias.keys() {
        recon.landmarks.remove(drop);
    }
    report
}

/// Follow merge aliases to the surviving track.
fn resolve(alias: &BTreeMap<u64, u64>, mut t: u64) -> u64 {
    while let Some(&next) = alias.get(&t) {
        t = next;
    }
    t
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn descriptor(i: u64) -> Descriptor {
        let mut x = i.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ 0xD1B5_4A32_D192_ED03;
        let mut words = [0u64; 4];
        for w in &mut words {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            *w = x;
        }
        Descriptor(words)
    }

    /// A landmark of the verification tests' place.
    struct TestPoint {
        /// Unit bearing in the query camera.
        bearing: Vector3<f64>,
        /// Position in the query camera.
        in_camera: Vector3<f64>,
        /// Position in the world.
        world: Vector3<f64>,
    }

    /// The query camera of the verification tests (`cam_from_world`) and 200 landmarks spread
    /// over its view at 2-4 m.
    fn test_place() -> (Pose, Vec<TestPoint>) {
        let cam_from_world = Pose::from_parts(
            Vector3::new(0.1, -0.2, 0.3).into(),
            so3_exp(&Vector3::new(0.1, 0.2, -0.3)),
        );
        let world_from_cam = cam_from_world.inverse();
        let points = (0..200u64)
            .map(|i| {
                let a = i as f64 * 2.399_963;
                let bearing =
                    Vector3::new(a.cos(), a.sin(), 0.6 * ((i % 7) as f64 - 3.0) / 3.0).normalize();
                let in_camera = bearing * (2.0 + (i % 11) as f64 * 0.2);
                TestPoint {
                    bearing,
                    in_camera,
                    world: (world_from_cam * Point3::from(in_camera)).coords,
                }
            })
            .collect();
        (cam_from_world, points)
    }

    /// A true place (query camera viewing the candidate's points, query-side landmarks at a
    /// 0.9 scale drift) is verified with the right pose and scale; the same descriptors on
    /// shuffled positions (a wrong place whose appearance matches) are rejected.
    #[test]
    fn verification_accepts_the_true_place_and_rejects_a_wrong_one() {
        let (cam_from_world, points) = test_place();
        let world_from_cam = cam_from_world.inverse();
        let n = points.len();
        let mut candidate = Vec::new();
        let mut query = Vec::new();
        for (i, p) in (0u64..).zip(&points) {
            candidate.push(CandidatePoint {
                position: p.world,
                descriptor: descriptor(i),
            });
            query.push(QueryFeature {
                bearing: p.bearing,
                descriptor: descriptor(i),
                // The query's own map is 10 % smaller around its camera (identity pose).
                own_point: Some(p.in_camera * 0.9),
            });
        }
        let ransac = RansacOptions::default();
        let options = LoopOptions::default();
        let m = verify_place(&query, &Pose::identity(), &candidate, &ransac, &options).unwrap();
        assert_eq!(m.inliers.len(), n);
        let centre_err = (m.cam_from_world.inverse().translation.vector
            - world_from_cam.translation.vector)
            .norm();
        assert!(centre_err < 1e-6, "{centre_err}");
        assert!((m.scale - 1.0 / 0.9).abs() < 1e-6, "{}", m.scale);
        // Wrong place: same appearance, positions shuffled.
        let mut wrong = candidate.clone();
        for i in 0..wrong.len() {
            wrong[i].position = candidate[(i * 37 + 11) % candidate.len()].position;
        }
        assert!(verify_place(&query, &Pose::identity(), &wrong, &ransac, &options).is_err());
        // Too few matches (a place that shares little): rejected before RANSAC.
        let few: Vec<CandidatePoint> = candidate[..40].to_vec();
        assert_eq!(
            verify_place(&query, &Pose::identity(), &few, &ransac, &options),
            Err(PlaceRejection::TooFewMatches(40))
        );
    }

    /// A place whose appearance repeats (every descriptor on four landmarks, as tiles and
    /// wallpaper give): descriptor matching finds nothing; the guided verification from a pose
    /// that drifted a little (1.7 cm, 1.1°) finds the right landmarks and the true pose, and a
    /// pose that drifted beyond its radius verifies nothing.
    #[test]
    fn a_repeated_place_is_verified_around_the_current_pose() {
        let (cam_from_world, points) = test_place();
        let world_from_cam = cam_from_world.inverse();
        let n = points.len();
        let mut candidate = Vec::new();
        let mut query = Vec::new();
        for (i, p) in (0u64..).zip(&points) {
            candidate.push(CandidatePoint {
                position: p.world,
                descriptor: descriptor(i % 50),
            });
            // One reconstruction: the query's own landmark lies where the candidate's does.
            query.push(QueryFeature {
                bearing: p.bearing,
                descriptor: descriptor(i % 50),
                own_point: Some(p.world),
            });
        }
        let ransac = RansacOptions::default();
        let options = LoopOptions::default();
        // The map's own estimate of the query's pose has drifted a little from the true one.
        assert_eq!(
            verify_place(&query, &cam_from_world, &candidate, &ransac, &options),
            Err(PlaceRejection::TooFewMatches(0))
        );
        let drifted = Pose::from_parts(
            Vector3::new(0.01, 0.01, -0.01).into(),
            so3_exp(&Vector3::new(0.0, 0.02, 0.0)),
        ) * cam_from_world;
        let m = verify_place_guided(&query, &drifted, &candidate, &ransac, &options).unwrap();
        assert_eq!(m.inliers.len(), n);
        assert!(m.inliers.iter().all(|&(q, c)| q == c), "a copy was matched");
        let centre_err = (m.cam_from_world.inverse().translation.vector
            - world_from_cam.translation.vector)
            .norm();
        assert!(centre_err < 1e-6, "{centre_err}");
        let far = Pose::from_parts(
            Vector3::zeros().into(),
            so3_exp(&Vector3::new(0.0, 0.0, 3.0 * options.guided_radius_rad)),
        ) * cam_from_world;
        assert!(verify_place_guided(&query, &far, &candidate, &ransac, &options).is_err());
    }

    /// A square loop of 20 poses whose odometry drifts (scale and heading): the pose graph with
    /// the loop edge to the truth brings the last pose back and spreads the error.
    #[test]
    fn pose_graph_closes_a_drifting_loop() {
        let n = 20;
        let truth: Vec<Sim3> = (0..n)
            .map(|k| {
                let a = 2.0 * std::f64::consts::PI * k as f64 / n as f64;
                let world_from_cam = Pose::from_parts(
                    Vector3::new(a.cos(), a.sin(), 0.1 * a.sin()).into(),
                    so3_exp(&Vector3::new(0.0, 0.0, a)),
                );
                from_pose(&world_from_cam.inverse())
            })
            .collect();
        // Drifted odometry: each step scaled by 1.01 and turned by 0.01 rad more.
        let mut nodes = vec![truth[0]];
        for k in 1..n {
            let step = compose(&truth[k], &truth[k - 1].inverse());
            let drift = Sim3 {
                scale: 1.0,
                rotation: so3_exp(&Vector3::new(0.0, 0.01, 0.01)),
                translation: step.translation * 0.01,
            };
            let prev = nodes[k - 1];
            nodes.push(compose(&compose(&drift, &step), &prev));
        }
        let weight = [1.0; 7];
        let mut edges = Vec::new();
        for a in 0..n {
            for b in a + 1..(a + 3).min(n) {
                let z = compose(&nodes[a], &nodes[b].inverse());
                edges.push(Edge {
                    a,
                    b,
                    z_inv: z.inverse(),
                    weight,
                });
            }
        }
        let z = compose(&truth[n - 1], &truth[0].inverse());
        edges.push(Edge {
            a: n - 1,
            b: 0,
            z_inv: z.inverse(),
            weight: [100.0; 7],
        });
        let err = |nodes: &[Sim3]| {
            let r = edge_residual(&z.inverse(), &nodes[n - 1], &nodes[0]);
            r.iter().map(|v| v * v).sum::<f64>().sqrt()
        };
        let before = err(&nodes);
        solve_pose_graph(&mut nodes, &edges, 30);
        let after = err(&nodes);
        assert!(before > 0.1, "{before}");
        assert!(after < 0.05 * before, "loop residual {before} -> {after}");
    }
}
