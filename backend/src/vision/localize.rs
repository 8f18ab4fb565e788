//! Localization of every frame of an episode against a frozen map (no map update).
//!
//! Per frame:
//! 1. **Tracking** (the previous frame was localized): the previous frame's inlier pixels, each
//!    tied to a map landmark, are followed with pyramidal KLT (pyramids built once per frame,
//!    forward–backward checked) and the pose is estimated by P3P RANSAC + Huber refinement.
//!    When fewer than a share of the target correspondences survive, the frame's ORB features
//!    are extracted and **guided matching** adds landmarks of the keyframes nearest to the
//!    estimated pose: each is projected with the pose and matched to the keypoints within a
//!    few pixels by Hamming distance (ratio-checked); the landmarks left unmatched are looked
//!    for by correlation (`patch_topup`): the map's stored patch of the keyframe view nearest
//!    in direction, against the query image warped to that view through the landmark's surface
//!    plane, within a few pixels of the projection. Then the pose is re-estimated.
//! 2. **Relocalization** (tracking failed or the previous frame was lost): ORB features
//!    (described on rectified patches, see `OrbOptions::rectified`) are quantized into the
//!    map's bag of words; the best-scoring keyframes are candidates; the query is matched
//!    (mutual + ratio) to the landmarks of each candidate and its neighbours — to each
//!    landmark's representative descriptor and to every keyframe view of it in that window.
//!    P3P RANSAC on those matches needs only a *hypothesis* (`relocalization_hypothesis_inliers`,
//!    12): with repeated texture and views from elsewhere few descriptor matches survive the
//!    ratio test, but a right pose projects many landmarks onto their keypoints. Guided
//!    matching then densifies it in rounds, over the candidate's landmarks and then over those
//!    of the keyframes that view the estimated pose's surroundings best (near in centre *and*
//!    in viewing direction), and the candidate with the most inliers wins. While a stream is
//!    lost, relocalization runs on every frame for its first `relocalization_eager_s`, then on
//!    every `relocalization_interval`-th frame; its cost is counted.
//! 3. **Acceptance** (both paths): at least `min_inliers` inliers, an inlier ratio of at least
//!    `min_inlier_ratio` among the correspondences, inlier bearings spread over the sphere
//!    (square root of the middle eigenvalue of their covariance at least `min_spread_rad`), and
//!    the position's uncertainty (`max_position_std`); a relocalized pose must in addition be
//!    supported across the view the map predicts (`min_view_support`: a pose fitted to one copy
//!    of a repeated photo explains that photo only) and rest on landmarks the map does not
//!    repeat elsewhere (`min_unique_inliers`: tiles and wallpaper whose periods nearly agree
//!    make a whole view match one period away), so that a pose resting on a small cluster, a
//!    coincidental minority or a repeated pattern is reported lost rather than output.
//!    An accepted relocalization is then fitted again with the landmarks correlation finds
//!    around it (`refine_relocalized`), so tracking starts from the whole view.
//!
//! Determinism: RANSAC seeds derive from the frame index, OpenCV's ORB and KLT are
//! deterministic, candidates and matches are ordered; one episode runs sequentially, so the
//! output is bit-identical whatever the thread count.

use std::collections::BTreeSet;

use nalgebra::{Matrix2, Matrix3, Point2, Point3, Vector2, Vector3};
use rayon::prelude::*;

use kiwi_core::camera::{Camera, CameraModel};
use kiwi_core::geometry::Pose;

use crate::error::{BackendError, Result};
use crate::vision::features::{
    Descriptor, DescriptorMatch, FrameFeatures, GrayImage, Keypoint, KltOptions, KltPyramid, Mask,
    MatchOptions, OrbExtractor, OrbOptions, TangentPatch, direction_basis, match_descriptor_groups,
    match_descriptor_groups_ambiguous, patch_step, patch_tangent_basis, track_klt_pyramids,
};
use crate::vision::geometry::{
    RansacOptions, absolute_pose_position_std, absolute_pose_ransac, angular_error, dominant_plane,
};
use crate::vision::map::{PATCH_SIDE, VisualMap};
use crate::vision::place::KeyframeDatabase;

/// Outcome of one frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum LocalizationStatus {
    /// Localized by tracking from the previous frame.
    Tracked,
    /// Localized by place recognition.
    Relocalized,
    /// Not localized (no pose output).
    Lost,
}

/// What a relocalized pose was found on.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum RelocalizationSource {
    /// A keyframe window that place recognition proposed, verified against its landmarks.
    Window,
    /// The whole map matched at once, without place recognition (the attempt a look-alike
    /// place in repeated texture can fool).
    WholeMap,
    /// Guided matching around the pose the wrist's other lens gives at the same moment (that
    /// lens localized in its own map, on other walls: independent evidence of the place).
    OtherLens,
}

impl RelocalizationSource {
    /// How the source reads in a lost frame's reason.
    pub fn describe(self) -> &'static str {
        match self {
            Self::Window => "relocalized on a place-recognition window",
            Self::WholeMap => "relocalized by a whole-map match",
            Self::OtherLens => "relocalized around the other lens's pose",
        }
    }
}

impl LocalizationStatus {
    /// Name in `poses.csv`.
    pub fn name(self) -> &'static str {
        match self {
            Self::Tracked => "tracked",
            Self::Relocalized => "relocalized",
            Self::Lost => "lost",
        }
    }
}

/// The result for one frame.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameLocalization {
    /// Frame index in `frames.csv`.
    pub frame: u32,
    /// Frame time (s, camera clock).
    pub t: f64,
    /// Status.
    pub status: LocalizationStatus,
    /// `map_from_cam` when localized.
    pub map_from_cam: Option<Pose>,
    /// Inliers of the accepted (or best rejected) pose.
    pub inliers: usize,
    /// Why the frame is lost (empty when localized).
    pub reason: String,
}

impl FrameLocalization {
    /// A lost frame: no pose, the best rejected inlier count and why.
    pub(crate) fn lost(frame: u32, t: f64, inliers: usize, reason: String) -> Self {
        Self {
            frame,
            t,
            status: LocalizationStatus::Lost,
            map_from_cam: None,
            inliers,
            reason,
        }
    }
}

/// Localizer settings. Angular thresholds are given in pixels at the image centre and converted
/// with the lens's own scale, so the same settings serve 320 px tests and 960 px episodes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LocalizerOptions {
    /// RANSAC inlier threshold (px at the image centre).
    pub threshold_px: f64,
    /// Fewest inliers of an accepted pose.
    pub min_inliers: usize,
    /// Fewest inliers of an accepted relocalization (no motion prior: stricter).
    pub min_inliers_relocalization: usize,
    /// Fewest descriptor-match inliers of a relocalization *hypothesis*: the pose that guided
    /// matching then densifies and the acceptance rules judge (with repeated texture and views
    /// from elsewhere, few descriptor matches survive the ratio test, but a right pose
    /// projects many more landmarks onto their keypoints).
    pub relocalization_hypothesis_inliers: usize,
    /// Rounds of guided densification of a relocalization hypothesis (each re-projects the
    /// landmarks of the keyframes that view the current pose's surroundings best).
    pub relocalization_guided_rounds: usize,
    /// Keyframes viewing a relocalization hypothesis best whose landmarks its densification
    /// projects.
    pub relocalization_guided_keyframes: usize,
    /// A relocalized pose must be supported across the view the map predicts: of the cells of
    /// a `support_grid` × `support_grid` image grid where at least `support_min_predicted` map
    /// landmarks project (from the keyframes viewing that pose best) and the query has
    /// keypoints, at least this share must hold an inlier. A pose fitted to one copy of a
    /// repeated photo explains that photo only.
    pub min_view_support: f64,
    /// When no candidate window gives a pose, the query is matched against the whole map and
    /// each keypoint keeps up to this many look-alike landmarks (0: no whole-map attempt).
    pub relocalization_map_candidates: usize,
    /// RANSAC iterations of the whole-map hypothesis (its share of right matches is low).
    pub relocalization_map_iterations: usize,
    /// Whole-map attempts per run of frames without a pose: after this many failed, only one
    /// attempt in `relocalization_map_interval` is a whole-map one until a pose is found (a
    /// view the map never saw would pay the whole-map matching on every attempt).
    pub relocalization_map_attempts: usize,
    /// After `relocalization_map_attempts`, one attempt in this many is still a whole-map one
    /// (a repeated-texture room may need it long into a lost run; 0 or 1: every attempt).
    pub relocalization_map_interval: usize,
    /// A relocalized pose must rest on at least this many inlier landmarks that the map does
    /// not repeat elsewhere (see `RepeatedEvidence`): in a room whose tiles, wallpaper and
    /// doors repeat with nearly common periods, a view matches the same pattern a period away
    /// as well as here (0: no uniqueness test).
    pub min_unique_inliers: usize,
    /// See `min_view_support`.
    pub support_grid: u32,
    /// See `min_view_support`.
    pub support_min_predicted: usize,
    /// Smallest inlier share among the correspondences of an accepted pose.
    pub min_inlier_ratio: f64,
    /// Smallest angular spread (rad) of the inlier bearings.
    pub min_spread_rad: f64,
    /// Largest standard deviation of the camera position along its least constrained
    /// direction (inlier bearings with 1 px noise, rotation marginalized), as a fraction of the
    /// map's median keyframe-to-landmark distance (the map's scale is arbitrary; that distance
    /// is the room's).
    pub max_position_std: f64,
    /// Correspondences tracked from frame to frame.
    pub target_tracks: usize,
    /// Guided matching tops the correspondences up when fewer than this share of those held
    /// after the last top-up are still carried.
    pub replenish_ratio: f64,
    /// ... or when fewer than this many are carried.
    pub min_carried: usize,
    /// A tracked correspondence is carried to the next frame only while its reprojection error
    /// under the frame's pose stays within this (px at the image centre).
    pub carry_px: f64,
    /// Cells per image side of the top-up grid: ORB runs only in cells that hold fewer than
    /// `cell_min_tracks` carried points but where at least `cell_min_candidates` untracked map
    /// landmarks project.
    pub topup_grid: u32,
    /// See `topup_grid`.
    pub cell_min_tracks: usize,
    /// See `topup_grid`.
    pub cell_min_candidates: usize,
    /// Search radius of guided matching (px).
    pub guided_radius_px: f64,
    /// Keyframes nearest to the pose whose landmarks guided matching projects.
    pub guided_keyframes: usize,
    /// Guided matching compares each keypoint with every keyframe view of a landmark, not only
    /// its representative descriptor.
    pub guided_views: bool,
    /// Tracking's top-up projects the landmarks of the `guided_keyframes` keyframes that view
    /// the pose's surroundings best (centre and viewing direction) as well as those of the ones
    /// nearest in centre.
    pub topup_by_view: bool,
    /// A tracked pose whose position is poorly constrained is matched again over the whole
    /// frame around itself, against the landmarks of the `relocalization_guided_keyframes`
    /// keyframes viewing it best, before it is refused.
    pub densify_uncertain: bool,
    /// Candidate keyframes tried by relocalization.
    pub relocalization_candidates: usize,
    /// Neighbouring keyframes (each side) whose landmarks join a candidate's.
    pub relocalization_neighbours: usize,
    /// After this many frames in a row lost at relocalization, relocalization is tried only on
    /// every `relocalization_interval`-th frame; the frames between are lost ("not tried") and
    /// the backward pass of [`crate::vision::episode::localize_stream`] tracks back into them
    /// from the next success.
    pub relocalization_retries: usize,
    /// See `relocalization_retries`.
    pub relocalization_interval: usize,
    /// While a stream has been lost for less than this (s, frame times), relocalization is
    /// tried on every frame, whatever `relocalization_retries` says: the first second of a
    /// query (the start of every episode after the mapping one) must find the map.
    pub relocalization_eager_s: f64,
    /// KLT settings.
    pub klt: KltOptions,
    /// ORB settings (guided matching and relocalization).
    pub orb: OrbOptions,
    /// Descriptor matching of relocalization.
    pub matching: MatchOptions,
    /// Largest Hamming distance of a guided match.
    pub guided_max_distance: u32,
    /// Tracking's top-up also looks for the landmarks that guided matching left unmatched by
    /// correlating the map's stored keyframe patch of each (its best-aligned view) with the
    /// query image warped to that view through the landmark's surface plane: landmarks found
    /// again where a change of view defeats the descriptors.
    pub patch_topup: bool,
    /// Smallest normalised cross-correlation of a patch match.
    pub patch_min_ncc: f64,
    /// A patch match's peak must exceed every correlation more than one step away from it by
    /// this much (edges and repeated texture correlate along a ridge or at several offsets).
    pub patch_peak_margin: f64,
    /// A relocalized pose is fitted again with the landmarks correlation finds around it (as
    /// `patch_topup` finds them for tracking): the frames tracked from it start from the whole
    /// view instead of the descriptor matches alone.
    pub refine_relocalized: bool,
    /// RANSAC seed (mixed with the frame index).
    pub seed: u64,
    /// Localize in a map whose own check found it not trustworthy ([`VisualMap::quality`]);
    /// off: every frame is lost with the map's reason (a wrong map gives wrong poses).
    pub serve_untrusted_map: bool,
}

impl Default for LocalizerOptions {
    fn default() -> Self {
        Self {
            // ~1.5 px: KLT and ORB keypoints are sub-pixel to 1 px accurate; blur widens it.
            threshold_px: 1.5,
            // P3P on fewer than ~30 spread inliers can fit a wrong pose to a coincidence.
            min_inliers: 30,
            // Without a motion prior, and matching every keyframe view of a landmark: at 40 a
            // relocalization at the edge of a front map's coverage (seed 7 walk start, 41
            // inliers) was 4 cm off and the frames tracked from it up to 5.5 cm.
            min_inliers_relocalization: 45,
            // P3P on 12 consistent matches of one candidate window is a hypothesis worth
            // densifying; it is never output on its own.
            relocalization_hypothesis_inliers: 12,
            // Window, then the best-viewing keyframes twice: the third round rarely adds more.
            relocalization_guided_rounds: 3,
            // A view from elsewhere spans the landmarks of several keyframes of a sweep, each of
            // which sees a part of it (few dozen landmarks each in a texture-poor room).
            relocalization_guided_keyframes: 8,
            // A right pose from elsewhere matched inliers in most predicted cells on the photo
            // room's revisit; one photo copy covers a few of an 8 × 8 grid.
            min_view_support: 0.3,
            // A tile or door corner that recurs more often than this is left out: it cannot
            // tell copies apart, and each kept look-alike dilutes the right matches.
            relocalization_map_candidates: 3,
            // 10 % right matches need ~9 000 P3P draws for 99.99 %; adaptive stopping ends
            // far sooner once a hypothesis with many inliers is found.
            relocalization_map_iterations: 10_000,
            // A third of the eager first second at 30 Hz: the kitchen's revisit found the map on
            // its first whole-map attempt, and each costs ~4 window attempts.
            relocalization_map_attempts: 10,
            // One whole-map attempt costs about four window attempts: past the first ten, at
            // most half of a long lost run's relocalization time goes to the whole map.
            relocalization_map_interval: 4,
            // A hypothesis's worth: poses one pattern period off (kitchen 12, 480 px) kept 0-4
            // inlier landmarks outside the map's copies, right ones (photos 13, studio 14,
            // kitchen 11) 31-79.
            min_unique_inliers: 12,
            // 8 × 8 cells of 120 px at 960 px: a photo or a tile panel covers a few of them.
            support_grid: 8,
            // A cell with fewer predicted landmarks is too thin to expect an inlier in.
            support_min_predicted: 3,
            // A true pose explains most tracked correspondences; a wrong one a minority.
            min_inlier_ratio: 0.5,
            // ~6°: inliers on one small patch constrain the position poorly.
            min_spread_rad: 0.1,
            // 0.5 % of a room's ~3 m median depth is 15 mm: on the 960 px walk (rear lens, far
            // walls only at the walk's far end) accepted poses were off by up to ~3 σ, and every
            // pose over 5 cm had σ above 20 mm.
            max_position_std: 0.005,
            // ~200 well spread points are plenty for P3P; fewer keep KLT cheap.
            target_tracks: 200,
            // Top up once a third of the support is gone (not every frame: ORB is the
            // most expensive step of a tracked frame).
            replenish_ratio: 0.67,
            // Twice the acceptance minimum: keeps a margin before a frame is refused.
            min_carried: 60,
            // KLT drift accumulates over frames; a track more than ~1 px off its landmark's
            // projection is dropped (a fresh guided match replaces it).
            carry_px: 1.0,
            // 4 × 4 cells of 240 px at 960 px: small crops, few of them per top-up.
            topup_grid: 4,
            cell_min_tracks: 8,
            cell_min_candidates: 6,
            // KLT drift plus pose error over one frame at 120 Hz stays within a few pixels.
            guided_radius_px: 6.0,
            guided_keyframes: 4,
            // A landmark seen from 40-60° away (a revisit) looks like its nearest keyframe
            // view, not like the medoid of all of them.
            guided_views: true,
            // A revisit looks elsewhere than the keyframes nearest in centre did (kitchen 3's
            // revisit: 82 -> 89 % localized with this alone, 100 % with `densify_uncertain`).
            topup_by_view: true,
            // The top-up matches only in sparse cells and against eight keyframes at most; a
            // frame at the uncertainty limit has more of the map in view than that.
            densify_uncertain: true,
            relocalization_candidates: 3,
            relocalization_neighbours: 2,
            // Two failures in a row: the view is not in the map (another wrist's view, a part
            // of the room not mapped), and each attempt costs ~6 tracked frames.
            relocalization_retries: 2,
            // Every 4th frame (~0.13 s at 30 Hz): a view that comes into the map is found within
            // a few frames, and the backward pass fills the frames before it.
            relocalization_interval: 4,
            // One second of every frame (~30 attempts at 30 Hz; 50-270 ms each measured at
            // 320 px on a loaded machine): the cost of starting an episode, paid once.
            relocalization_eager_s: 1.0,
            klt: KltOptions {
                // 15 px is enough between consecutive frames and ~2× cheaper than 21.
                window: 15,
                ..KltOptions::default()
            },
            orb: OrbOptions::default(),
            matching: MatchOptions::default(),
            guided_max_distance: crate::vision::features::GUIDED_MAX_DISTANCE,
            patch_topup: true,
            // Right pairs correlate at a median of 0.92-0.97 and a pixel 15 px away at 0.16-0.58
            // (kitchen 11 and photos 13 at 320 px, best over ±2 px): at 0.8, 84-100 % of a
            // frame's right pairs pass and 0-7 of its 25-40 chance ones.
            patch_min_ncc: 0.8,
            // A tenth of the correlation's range above any other offset: a distinct peak.
            patch_peak_margin: 0.1,
            // The worst error of a 320 px revisit fell in 9 of the 12 localized ones (photos 13
            // 24.1 -> 10.6 mm, divided 16 34.8 -> 23.0 mm) and rose in 2 (kitchen 11 14.1 ->
            // 18.2 mm), the same frames localized.
            refine_relocalized: true,
            seed: 0x4C4F_4341,
            serve_untrusted_map: false,
        }
    }
}

/// Angle (rad) subtended by one pixel at the image centre of a lens.
pub fn pixel_angle(camera: &dyn CameraModel) -> f64 {
    let (w, h) = camera.resolution();
    let c = Point2::new(f64::from(w) / 2.0, f64::from(h) / 2.0);
    match (
        camera.unproject(&c),
        camera.unproject(&Point2::new(c.x + 1.0, c.y)),
    ) {
        (Some(a), Some(b)) => a.dot(&b).clamp(-1.0, 1.0).acos(),
        // A lens that does not unproject its centre: fall back to the 190° circle over the width.
        _ => 190f64.to_radians() / f64::from(w.max(1)),
    }
}

/// Square root of the middle eigenvalue of the bearings' covariance (rad): small when the
/// bearings lie in one patch or along one arc.
pub fn angular_spread(bearings: &[Vector3<f64>]) -> f64 {
    if bearings.len() < 3 {
        return 0.0;
    }
    let n = bearings.len() as f64;
    let mean = bearings.iter().sum::<Vector3<f64>>() / n;
    let mut c = Matrix3::zeros();
    for b in bearings {
        let d = b - mean;
        c += d * d.transpose();
    }
    c /= n;
    let mut e: Vec<f64> = c.symmetric_eigenvalues().iter().copied().collect();
    e.sort_by(f64::total_cmp);
    e[1].max(0.0).sqrt()
}

/// Median distance from a keyframe's centre to the landmarks it observes (map units); `None`
/// when no keyframe observes a landmark at a positive distance.
pub fn median_keyframe_depth(map: &VisualMap) -> Option<f64> {
    let mut depths: Vec<f64> = Vec::new();
    for k in &map.keyframes {
        let Some(pose) = k.cam_from_map.to_pose() else {
            continue;
        };
        for l in k.features.iter().filter_map(|f| f.landmark) {
            if let Some(lm) = map.landmarks.get(l as usize) {
                let d = (pose * Point3::from(Vector3::from(lm.position)))
                    .coords
                    .norm();
                if d.is_finite() && d > 0.0 {
                    depths.push(d);
                }
            }
        }
    }
    if depths.is_empty() {
        return None;
    }
    depths.sort_by(f64::total_cmp);
    Some(depths[depths.len() / 2])
}

/// Evenly spread whole-map matches each P3P model is tested on before it is scored on all: at
/// ~8 % right matches a right model has ~4 inliers among 60, a wrong one rarely 2.
const WHOLE_MAP_PREVERIFY: usize = 60;

/// Largest distance of a landmark from a plane it lies on, as a fraction of the map's median
/// depth (1 % of a room's ~3 m is 3 cm: a floor or a wall, not a box on it).
const PLANE_TOLERANCE: f64 = 0.01;

/// How a relocalization refused by the uniqueness rule (`min_unique_inliers`) begins its reason.
pub const REPEATED_VIEW: &str = "the map repeats this view elsewhere";

/// Whether a frame was lost because its best relocalization rested on a pattern the map repeats
/// elsewhere (its reason says so).
pub fn is_refused_as_copy(frame: &FrameLocalization) -> bool {
    frame.status == LocalizationStatus::Lost && frame.reason.contains(REPEATED_VIEW)
}

/// Shortest translational copy the uniqueness test looks for, as a fraction of the map's median
/// depth (5 % of ~3 m: beyond the error of a pose the acceptance rules let through).
const COPY_MIN_SHIFT: f64 = 0.05;

/// Fewest inlier landmarks sharing a shift for it to count as a copy: chance look-alikes
/// (the nearest other landmark of a kitchen keypoint is ~48 bits away) scatter over the whole
/// room's shifts, a handful per tolerance cell at most.
const COPY_MIN_SUPPORT: usize = 8;

/// Tolerance of a copy's shift, as a fraction of the map's median depth (1.5 % of ~3 m is
/// 4.5 cm: landmark error plus periods that agree only nearly, such as a 0.31 m floor tile
/// and a 0.24 m wallpaper motif over 0.9 m).
const COPY_TOLERANCE: f64 = 0.015;

/// A keypoint's pixel as an exact key (keypoints are told apart by position).
fn pixel_key(p: &Point2<f64>) -> (u64, u64) {
    (p.x.to_bits(), p.y.to_bits())
}

/// One relocalization candidate as tried (for diagnostics against the truth).
#[derive(Debug, Clone)]
pub struct CandidateTrace {
    /// The candidate keyframe; for the whole-map attempt, the keyframe viewing its estimate
    /// best (0 without an estimate).
    pub keyframe: usize,
    /// Its place-recognition score; `None` for the whole-map attempt.
    pub score: Option<f64>,
    /// Descriptor matches: (query keypoint index, landmark).
    pub matches: Vec<(usize, u32)>,
    /// Inliers of the candidate's final estimate (0 without one).
    pub inliers: usize,
    /// The final estimate, if RANSAC found one.
    pub cam_from_map: Option<Pose>,
    /// Landmarks of the final estimate's inliers.
    pub inlier_landmarks: Vec<u32>,
    /// Share of those landmarks on their dominant plane (0 without an estimate).
    pub plane_share: f64,
    /// How much of the estimate's evidence the map repeats elsewhere (without an estimate:
    /// the default, nothing).
    pub repeated: RepeatedEvidence,
    /// Empty when accepted, else why not.
    pub rejection: String,
}

/// How much of a pose's evidence the map repeats elsewhere (see the uniqueness rule of
/// relocalization).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct RepeatedEvidence {
    /// Distinct inlier landmarks.
    pub landmarks: usize,
    /// Of those, the ones in a translational copy the map holds elsewhere.
    pub repeated: usize,
    /// The copy shared by the most inlier landmarks: its shift (map units) and that count.
    pub strongest: Option<(Vector3<f64>, usize)>,
}

/// What one relocalization attempt saw: the query's features and every candidate tried.
#[derive(Debug, Clone)]
pub struct RelocalizationTrace {
    /// The query frame's ORB features (keypoint indices of the matches refer to these).
    pub features: FrameFeatures,
    /// Candidates in the order tried.
    pub candidates: Vec<CandidateTrace>,
}

/// A 2-D correspondence: landmark, pixel and bearing in the query frame.
#[derive(Debug, Clone, Copy)]
struct Correspondence {
    landmark: u32,
    pixel: Point2<f64>,
    bearing: Vector3<f64>,
}

/// A pose estimate with its support.
struct Estimate {
    cam_from_map: Pose,
    inliers: Vec<Correspondence>,
    candidates: usize,
}

/// Why tracking did not produce an accepted pose.
enum TrackFailure {
    /// Too few inliers, too low a ratio or too clustered: the reason and the inlier count.
    Rejected(String, usize),
    /// Supported by the tracks but the position is too uncertain: the estimate and the reason.
    Uncertain(Estimate, String),
}

/// What is carried from one localized frame to the next.
struct TrackState {
    pyramid: KltPyramid,
    points: Vec<(u32, Point2<f64>)>,
    cam_from_map: Pose,
    /// Correspondences carried right after the last top-up (or relocalization).
    baseline: usize,
}

/// Localizes the frames of one lens stream, in order, against a frozen map.
pub struct Localizer {
    camera: Camera,
    mask: Mask,
    options: LocalizerOptions,
    threshold_rad: f64,
    /// Angle of one pixel at the image centre (rad): the noise of the pose-uncertainty check.
    pixel_rad: f64,
    /// Median distance from a keyframe to the landmarks it sees (map units): the map's length
    /// scale for the pose-uncertainty check.
    map_depth: f64,
    orb: OrbExtractor,
    database: KeyframeDatabase,
    vocabulary: crate::vision::place::Vocabulary,
    positions: Vec<Vector3<f64>>,
    descriptors: Vec<Descriptor>,
    /// Per keyframe, its linked features' descriptors and landmarks: relocalization matches the
    /// query against these views as well as the landmarks' representative descriptors (a
    /// landmark's views differ a lot across a fisheye image — distortion, scale, rotation — and
    /// one medoid matches a view from elsewhere poorly).
    keyframe_views: Vec<Vec<(Descriptor, u32)>>,
    /// Per landmark, the descriptors of its keyframe views (guided matching takes the nearest
    /// of them and the representative: a view from elsewhere resembles some keyframe's view).
    landmark_views: Vec<Vec<Descriptor>>,
    keyframe_landmarks: Vec<Vec<u32>>,
    keyframe_centres: Vec<Vector3<f64>>,
    /// Each keyframe's optical axis in the map.
    keyframe_axes: Vec<Vector3<f64>>,
    state: Option<TrackState>,
    /// Frames in a row that reached relocalization without a pose.
    failed_run: usize,
    /// Time of the first frame of the current run without a pose.
    lost_since: Option<f64>,
    /// Relocalization attempts so far and their wall time (s): the cost reported per stream.
    attempts: usize,
    attempt_seconds: f64,
    /// Why the map serves no poses (its own check refused it): every frame's lost reason.
    refused: Option<String>,
    /// Whole-map attempts in the current run of frames without a pose.
    map_attempts_in_run: usize,
    /// Window-only attempts since the last whole-map attempt of the current run.
    window_attempts_since_map: usize,
    /// Train descriptors of every landmark and keyframe view with their landmarks, built at the
    /// first whole-map attempt (the map never changes).
    whole_map_train: std::cell::OnceCell<(Vec<Descriptor>, Vec<u32>)>,
    /// What the last relocalized pose was found on.
    last_source: RelocalizationSource,
    /// Per landmark, its keyframe views with a stored patch.
    landmark_patches: Vec<Vec<PatchView>>,
    /// Per keyframe, the map pose of its camera.
    map_from_keyframes: Vec<Pose>,
    /// Per landmark, the normal of the plane through it and its neighbours, when they lie on
    /// one (the patch warp's surface).
    landmark_normals: Vec<Option<Vector3<f64>>>,
}

/// A keyframe's stored patch of one landmark, with what correlating it needs.
#[derive(Debug, Clone)]
struct PatchView {
    /// Keyframe index.
    keyframe: u32,
    /// Angular step of the patch (rad per patch pixel: the view's level).
    step: f64,
    /// The patch ([`PATCH_SIDE`]² samples, row-major).
    values: [f32; PATCH_SIDE * PATCH_SIDE],
    /// Mean of the samples.
    mean: f64,
    /// Sum of squared deviations from the mean.
    energy: f64,
}

/// Neighbours of a landmark that fix its surface normal lie within this many map depths: a few
/// centimetres of wall or floor in a room.
const NORMAL_RADIUS_DEPTHS: f64 = 0.05;
/// Fewest neighbours (the landmark included) a normal is fitted to.
const NORMAL_MIN_POINTS: usize = 6;
/// Flat enough for a normal: the neighbours' smallest spread under this share of the middle one.
const NORMAL_FLATNESS: f64 = 0.25;
/// Largest stretch (ratio of singular values) of a patch warp: a surface seen more obliquely
/// than ~75° from one of the two views is not compared.
const WARP_MAX_STRETCH: f64 = 4.0;
/// Finite-difference step of the warp's Jacobian (rad of tangent plane).
const WARP_EPSILON: f64 = 1e-3;
/// Search radius of a patch match around the landmark's projection (patch pixels, about image
/// pixels at level 0): as far as guided matching looks (`guided_radius_px`).
const PATCH_SEARCH: usize = 6;

/// Per point, the normal of the plane its neighbours within `radius` lie on (when they do).
fn surface_normals(positions: &[Vector3<f64>], radius: f64) -> Vec<Option<Vector3<f64>>> {
    if radius.is_nan() || radius <= 0.0 {
        return vec![None; positions.len()];
    }
    let key = |p: &Vector3<f64>| {
        (
            (p.x / radius).floor() as i64,
            (p.y / radius).floor() as i64,
            (p.z / radius).floor() as i64,
        )
    };
    let mut grid: std::collections::HashMap<(i64, i64, i64), Vec<usize>> =
        std::collections::HashMap::new();
    for (i, p) in positions.iter().enumerate() {
        grid.entry(key(p)).or_default().push(i);
    }
    let mut near: Vec<Vector3<f64>> = Vec::new();
    positions
        .iter()
        .map(|p| {
            let (kx, ky, kz) = key(p);
            near.clear();
            for dz in -1..=1 {
                for dy in -1..=1 {
                    for dx in -1..=1 {
                        if let Some(cell) = grid.get(&(kx + dx, ky + dy, kz + dz)) {
                            near.extend(
                                cell.iter()
                                    .map(|&j| positions[j])
                                    .filter(|q| (q - p).norm() <= radius),
                            );
                        }
                    }
                }
            }
            if near.len() < NORMAL_MIN_POINTS {
                return None;
            }
            let mean = near.iter().sum::<Vector3<f64>>() / near.len() as f64;
            let cov = near
                .iter()
                .map(|q| (q - mean) * (q - mean).transpose())
                .sum::<Matrix3<f64>>();
            let eig = cov.symmetric_eigen();
            let mut order = [0usize, 1, 2];
            order.sort_by(|&a, &b| eig.eigenvalues[a].total_cmp(&eig.eigenvalues[b]));
            let (low, mid) = (eig.eigenvalues[order[0]], eig.eigenvalues[order[1]]);
            (mid > 0.0 && low < NORMAL_FLATNESS * mid)
                .then(|| eig.eigenvectors.column(order[0]).into_owned())
        })
        .collect()
}

/// Normalised cross-correlation of `reference` (zero mean, `reference_energy` its sum of
/// squares) with the `side`-wide window of `area` (row length `stride`) at `(ox, oy)`.
fn window_ncc(
    reference: &[f64],
    reference_energy: f64,
    area: &[f32],
    stride: usize,
    (ox, oy): (usize, usize),
    side: usize,
) -> Option<f64> {
    let n = (side * side) as f64;
    let (mut s1, mut s2, mut sab) = (0.0, 0.0, 0.0);
    for y in 0..side {
        let row = &area[(oy + y) * stride + ox..(oy + y) * stride + ox + side];
        for (v, r) in row.iter().zip(&reference[y * side..(y + 1) * side]) {
            let v = f64::from(*v);
            s1 += v;
            s2 += v * v;
            sab += v * r;
        }
    }
    let energy = s2 - s1 * s1 / n;
    (energy > 1e-3 * n).then(|| sab / (energy * reference_energy).sqrt())
}

fn vision_err(message: String) -> BackendError {
    BackendError::Vision {
        context: "localization".into(),
        message,
    }
}

impl Localizer {
    /// A localizer for `camera` (the query lens's own calibration, checked against the map) with
    /// a static mask (non-zero pixels may hold features).
    pub fn new(
        map: &VisualMap,
        lens: &str,
        camera: Camera,
        mask: Mask,
        options: LocalizerOptions,
    ) -> Result<Self> {
        map.check_query_lens(lens, &camera)?;
        if map.landmarks.is_empty() || map.keyframes.is_empty() {
            return Err(vision_err(
                "the map has no keyframes or landmarks; rebuild it with `kiwi map` on an episode \
                 with texture and motion"
                    .into(),
            ));
        }
        let mut map = map.clone();
        let database = map.keyframe_database();
        let vocabulary = map
            .vocabulary
            .clone()
            .ok_or_else(|| vision_err("the map has no place-recognition vocabulary".into()))?;
        // A keyframe pose the file cannot give stands at the origin looking along z.
        let map_from_keyframes: Vec<Pose> = map
            .keyframes
            .iter()
            .map(|k| {
                k.cam_from_map
                    .to_pose()
                    .map_or_else(Pose::identity, |p| p.inverse())
            })
            .collect();
        let keyframe_centres = map_from_keyframes
            .iter()
            .map(|p| p.translation.vector)
            .collect();
        let keyframe_axes = map_from_keyframes
            .iter()
            .map(|p| p.rotation * Vector3::z())
            .collect();
        let positions: Vec<Vector3<f64>> = map
            .landmarks
            .iter()
            .map(|l| Vector3::from(l.position))
            .collect();
        let keyframe_views: Vec<Vec<(Descriptor, u32)>> = map
            .keyframes
            .iter()
            .map(|k| {
                k.features
                    .iter()
                    .filter_map(|f| f.landmark.map(|l| (f.descriptor, l)))
                    .filter(|(_, l)| (*l as usize) < map.landmarks.len())
                    .collect()
            })
            .collect();
        // Each keyframe's landmarks, once each and sorted.
        let keyframe_landmarks = keyframe_views
            .iter()
            .map(|views| {
                let set: BTreeSet<u32> = views.iter().map(|&(_, l)| l).collect();
                set.into_iter().collect()
            })
            .collect();
        let pixel_rad = pixel_angle(&camera);
        let threshold_rad = options.threshold_px * pixel_rad;
        let map_depth = median_keyframe_depth(&map)
            .ok_or_else(|| vision_err("the map's keyframes see no landmark".into()))?;
        let mut landmark_views: Vec<Vec<Descriptor>> = vec![Vec::new(); map.landmarks.len()];
        if options.guided_views {
            for (d, l) in keyframe_views.iter().flatten() {
                if let Some(views) = landmark_views.get_mut(*l as usize) {
                    views.push(*d);
                }
            }
        }
        let mut landmark_patches: Vec<Vec<PatchView>> = vec![Vec::new(); map.landmarks.len()];
        let scale_factor = f64::from(options.orb.scale_factor);
        if options.patch_topup {
            for (k, kf) in map.keyframes.iter().enumerate() {
                for f in &kf.features {
                    let (Some(l), Some(octave), Some(patch)) = (f.landmark, f.octave, f.patch)
                    else {
                        continue;
                    };
                    if let Some(views) = landmark_patches.get_mut(l as usize) {
                        let Some(step) = patch_step(&camera, &f.keypoint(octave), scale_factor)
                        else {
                            continue;
                        };
                        let values = patch.0.map(f32::from);
                        let n = values.len() as f64;
                        let mean = values.iter().map(|&v| f64::from(v)).sum::<f64>() / n;
                        let energy = values
                            .iter()
                            .map(|&v| {
                                let r = f64::from(v) - mean;
                                r * r
                            })
                            .sum::<f64>();
                        views.push(PatchView {
                            keyframe: k as u32,
                            step,
                            values,
                            mean,
                            energy,
                        });
                    }
                }
            }
        }
        let landmark_normals = if landmark_patches.iter().any(|v| !v.is_empty()) {
            surface_normals(&positions, NORMAL_RADIUS_DEPTHS * map_depth)
        } else {
            vec![None; map.landmarks.len()]
        };
        Ok(Self {
            orb: OrbExtractor::new(&options.orb)?,
            camera,
            mask,
            options,
            threshold_rad,
            pixel_rad,
            map_depth,
            database,
            vocabulary,
            positions,
            descriptors: map.landmarks.iter().map(|l| l.descriptor).collect(),
            keyframe_views,
            landmark_views,
            keyframe_landmarks,
            keyframe_centres,
            keyframe_axes,
            state: None,
            failed_run: 0,
            lost_since: None,
            attempts: 0,
            attempt_seconds: 0.0,
            refused: map
                .quality
                .as_ref()
                .filter(|q| !q.trustworthy && !options.serve_untrusted_map)
                .map(|q| {
                    format!(
                        "the map is not trustworthy: {}; rebuild it from a mapping episode with \
                         more texture or slower motion",
                        q.reason
                    )
                }),
            map_attempts_in_run: 0,
            window_attempts_since_map: 0,
            whole_map_train: std::cell::OnceCell::new(),
            last_source: RelocalizationSource::Window,
            landmark_patches,
            map_from_keyframes,
            landmark_normals,
        })
    }

    /// Why no frame gets a pose in this map (its own check refused it), if so.
    pub fn refusal(&self) -> Option<&str> {
        self.refused.as_deref()
    }

    /// Relocalization attempts so far and their total wall time (s).
    pub fn relocalization_cost(&self) -> (usize, f64) {
        (self.attempts, self.attempt_seconds)
    }

    /// What the last relocalized pose was found on (meaningful after a frame came back
    /// [`LocalizationStatus::Relocalized`]).
    pub fn relocalization_source(&self) -> RelocalizationSource {
        self.last_source
    }

    /// The map's median keyframe-to-landmark depth (map units): its length scale.
    pub fn map_depth(&self) -> f64 {
        self.map_depth
    }

    /// Localize a frame from a pose known for a neighbouring frame (instead of relocalizing:
    /// no place recognition, no descriptor matching against the map): guided matching over the
    /// whole frame around `prior` against the landmarks of the keyframes that view it best,
    /// judged by the tracking rules. `None` when that gives no accepted pose (the frame is then
    /// for [`Self::process`]). The pose is carried to the next frame as after tracking.
    pub fn process_from(
        &mut self,
        frame: u32,
        t: f64,
        image: &GrayImage,
        prior: &Pose,
    ) -> Result<Option<FrameLocalization>> {
        if self.refused.is_some() {
            return Ok(None);
        }
        let mut features = None;
        self.guided_from(frame, t, image, prior, &mut features)
    }

    /// Guided matching over the whole frame around `cam_from_map`, judged by the tracking
    /// rules; an accepted pose is output and carried as after tracking.
    fn guided_from(
        &mut self,
        frame: u32,
        t: f64,
        image: &GrayImage,
        cam_from_map: &Pose,
        features: &mut Option<FrameFeatures>,
    ) -> Result<Option<FrameLocalization>> {
        let Some(e) = self.guided_estimate(frame, image, cam_from_map, Vec::new(), features)?
        else {
            tracing::debug!("frame {frame}: guided matching around the given pose: no pose");
            return Ok(None);
        };
        if let Err(why) = self.accept(&e, self.options.min_inliers) {
            tracing::debug!(
                "frame {frame}: guided matching around the given pose: {} of {} inliers, {why}",
                e.inliers.len(),
                e.candidates
            );
            return Ok(None);
        }
        let pyramid = KltPyramid::new(image, &self.options.klt)?;
        Ok(Some(self.finish(
            frame,
            t,
            &e,
            pyramid,
            LocalizationStatus::Tracked,
            usize::MAX,
        )))
    }

    /// Localize a frame around a pose another source predicts (the wrist's other lens through
    /// the placement), which may be off by up to `radius_rad` in the direction it sees each
    /// landmark: guided matching over the whole frame within that radius gives a first pose (a
    /// hypothesis, held to `relocalization_hypothesis_inliers`), which is matched again around
    /// itself within the usual radius and judged by the tracking rules, as
    /// [`Self::process_from`]. `None` when that gives no accepted pose. The pose is
    /// carried to the next frame as after tracking.
    pub fn process_around(
        &mut self,
        frame: u32,
        t: f64,
        image: &GrayImage,
        prior: &Pose,
        radius_rad: f64,
    ) -> Result<Option<FrameLocalization>> {
        if self.refused.is_some() {
            return Ok(None);
        }
        let feats = self.orb.extract(image, Some(&self.mask), &self.camera)?;
        let radius_px = radius_rad / pixel_angle(&self.camera);
        let grid = KeypointGrid::new(&feats.keypoints, radius_px);
        let candidates =
            self.viewing_landmarks(prior, self.options.relocalization_guided_keyframes);
        let wide = self.guided_matches_within(prior, &candidates, &feats, &grid, radius_px);
        let hypothesis = self.ransac(frame, 5, self.options.relocalization_hypothesis_inliers);
        let first = match self.estimate(&wide, &hypothesis) {
            Ok(e) => e,
            Err(why) => {
                tracing::debug!(
                    "frame {frame}: guided matching within {radius_px:.1} px of the given pose: \
                     {} matches, {why}",
                    wide.len()
                );
                return Ok(None);
            }
        };
        let mut features = Some(feats);
        self.guided_from(frame, t, image, &first.cam_from_map, &mut features)
    }

    /// Forget the motion prior (the next frame relocalizes).
    pub fn reset(&mut self) {
        self.state = None;
    }

    fn ransac(&self, frame: u32, salt: u64, min_inliers: usize) -> RansacOptions {
        RansacOptions {
            threshold_rad: self.threshold_rad,
            min_inliers,
            seed: self.options.seed
                ^ u64::from(frame).wrapping_mul(0x9E37_79B9_7F4A_7C15)
                ^ salt.wrapping_mul(0xD1B5_4A32_D192_ED03),
            ..RansacOptions::default()
        }
    }

    /// Robust pose from correspondences; the inliers are returned in input order.
    fn estimate(
        &self,
        corr: &[Correspondence],
        options: &RansacOptions,
    ) -> std::result::Result<Estimate, String> {
        if corr.len() < options.min_inliers {
            return Err(format!(
                "{} correspondences, fewer than the {} inliers required",
                corr.len(),
                options.min_inliers
            ));
        }
        let b: Vec<Vector3<f64>> = corr.iter().map(|c| c.bearing).collect();
        let p: Vec<Vector3<f64>> = corr
            .iter()
            .map(|c| self.positions[c.landmark as usize])
            .collect();
        let pose = absolute_pose_ransac(&b, &p, options)
            .ok_or_else(|| format!("no pose with {} inliers", options.min_inliers))?;
        Ok(Estimate {
            cam_from_map: pose.cam_from_world,
            inliers: corr
                .iter()
                .zip(&pose.inliers)
                .filter(|(_, ok)| **ok)
                .map(|(c, _)| *c)
                .collect(),
            candidates: corr.len(),
        })
    }

    /// Strict acceptance: inlier count, ratio and spread, then the position's uncertainty.
    fn accept(&self, e: &Estimate, min_inliers: usize) -> std::result::Result<(), String> {
        self.accept_support(e, min_inliers)?;
        self.check_position(e)
    }

    /// Inlier count, ratio and spread.
    fn accept_support(&self, e: &Estimate, min_inliers: usize) -> std::result::Result<(), String> {
        let n = e.inliers.len();
        if n < min_inliers {
            return Err(format!("{n} inliers < {min_inliers}"));
        }
        let ratio = n as f64 / e.candidates.max(1) as f64;
        if ratio < self.options.min_inlier_ratio {
            return Err(format!(
                "inlier ratio {ratio:.2} < {:.2}",
                self.options.min_inlier_ratio
            ));
        }
        let bearings: Vec<Vector3<f64>> = e.inliers.iter().map(|c| c.bearing).collect();
        let spread = angular_spread(&bearings);
        if spread < self.options.min_spread_rad {
            return Err(format!(
                "inliers clustered: spread {spread:.3} rad < {:.3}",
                self.options.min_spread_rad
            ));
        }
        Ok(())
    }

    /// Support of a relocalized pose across the view the map predicts (`min_view_support`).
    fn check_view_support(
        &self,
        e: &Estimate,
        feats: &FrameFeatures,
    ) -> std::result::Result<(), String> {
        let (w, h) = self.camera.resolution();
        let g = self.options.support_grid.max(1);
        let cell = |p: &Point2<f64>| -> Option<usize> {
            if p.x < 0.0 || p.y < 0.0 {
                return None;
            }
            let (cx, cy) = ((p.x as u32) * g / w, (p.y as u32) * g / h);
            (cx < g && cy < g).then_some((cy * g + cx) as usize)
        };
        let cells = (g * g) as usize;
        let (mut predicted, mut textured, mut supported) =
            (vec![0usize; cells], vec![false; cells], vec![false; cells]);
        let cos_max = (0.5 * self.camera.valid_fov()).cos();
        for l in self.viewing_landmarks(&e.cam_from_map, self.options.guided_keyframes) {
            let pc = (e.cam_from_map * Point3::from(self.positions[l as usize])).coords;
            let n = pc.norm();
            if n <= 0.0 || pc.z / n < cos_max {
                continue;
            }
            if let Some(k) = self.camera.project(&pc).as_ref().and_then(cell) {
                predicted[k] += 1;
            }
        }
        for kp in &feats.keypoints {
            if let Some(k) = cell(&kp.pixel) {
                textured[k] = true;
            }
        }
        for c in &e.inliers {
            if let Some(k) = cell(&c.pixel) {
                supported[k] = true;
            }
        }
        let expected: Vec<usize> = (0..cells)
            .filter(|&k| predicted[k] >= self.options.support_min_predicted && textured[k])
            .collect();
        if expected.is_empty() {
            return Ok(());
        }
        let held = expected.iter().filter(|&&k| supported[k]).count();
        let share = held as f64 / expected.len() as f64;
        if share < self.options.min_view_support {
            return Err(format!(
                "inliers in {held} of the {} image cells the map predicts ({:.2} < {:.2})",
                expected.len(),
                share,
                self.options.min_view_support
            ));
        }
        Ok(())
    }

    /// Share of an estimate's inlier landmarks on their dominant plane (within
    /// [`PLANE_TOLERANCE`] of the map's median depth).
    fn plane_share(&self, e: &Estimate) -> f64 {
        let points: Vec<Vector3<f64>> = e
            .inliers
            .iter()
            .map(|c| self.positions[c.landmark as usize])
            .collect();
        dominant_plane(&points, PLANE_TOLERANCE * self.map_depth)
            .map_or(0.0, |(_, _, k)| k as f64 / points.len() as f64)
    }

    /// The uniqueness rule of relocalization (`min_unique_inliers`).
    fn check_unique(&self, r: &RepeatedEvidence) -> std::result::Result<(), String> {
        if self.options.min_unique_inliers == 0 {
            return Ok(());
        }
        let unique = r.landmarks - r.repeated;
        if unique >= self.options.min_unique_inliers {
            return Ok(());
        }
        let strongest = r.strongest.map_or(String::new(), |(d, k)| {
            format!(
                "; the strongest copy, {k} of them, lies {:.0} % of the map's median depth away",
                100.0 * d.norm() / self.map_depth
            )
        });
        Err(format!(
            "{REPEATED_VIEW}: {} of {} inlier landmarks have a look-alike in a copy of the \
             pattern, {unique} unique < {}{strongest}",
            r.repeated, r.landmarks, self.options.min_unique_inliers
        ))
    }

    /// The position's uncertainty against `max_position_std`.
    fn check_position(&self, e: &Estimate) -> std::result::Result<(), String> {
        // Position uncertainty: inliers on far walls fix the rotation but hardly the position,
        // and a bias of a pixel (map error, KLT drift) then moves the pose by centimetres.
        let observations = e
            .inliers
            .iter()
            .map(|c| (c.bearing, self.positions[c.landmark as usize]));
        let limit = self.options.max_position_std * self.map_depth;
        match absolute_pose_position_std(&e.cam_from_map, observations, self.pixel_rad) {
            Some(std) if std <= limit => Ok(()),
            Some(std) => Err(format!(
                "position poorly constrained: σ {:.2} % of the map's median depth > {:.2} %",
                100.0 * std / self.map_depth,
                100.0 * self.options.max_position_std
            )),
            None => Err("position unconstrained (singular information)".into()),
        }
    }

    /// Landmarks seen by the `count` keyframes that view the pose's surroundings best: nearest
    /// in centre (in units of the map's median depth) and in viewing direction (a keyframe
    /// 0.3 m away looking 90° elsewhere shares less than one 0.5 m away looking the same way).
    fn viewing_landmarks(&self, cam_from_map: &Pose, count: usize) -> Vec<u32> {
        let order = self.viewing_order(cam_from_map);
        self.landmarks_of(&order[..count.min(order.len())])
    }

    /// The landmarks seen by any of `keyframes`, sorted, each once.
    fn landmarks_of(&self, keyframes: &[usize]) -> Vec<u32> {
        let set: BTreeSet<u32> = keyframes
            .iter()
            .flat_map(|&k| self.keyframe_landmarks[k].iter().copied())
            .collect();
        set.into_iter().collect()
    }

    /// Keyframes ordered by how well they view the pose's surroundings (see
    /// `viewing_landmarks`).
    fn viewing_order(&self, cam_from_map: &Pose) -> Vec<usize> {
        let map_from_cam = cam_from_map.inverse();
        let c = map_from_cam.translation.vector;
        let axis = map_from_cam.rotation * Vector3::z();
        let mut order: Vec<(f64, usize)> = self
            .keyframe_centres
            .iter()
            .zip(&self.keyframe_axes)
            .enumerate()
            .map(|(k, (x, a))| {
                let d = (x - c).norm() / self.map_depth;
                (d * d + (1.0 - a.dot(&axis)), k)
            })
            .collect();
        order.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        order.into_iter().map(|(_, k)| k).collect()
    }

    /// Keyframes ordered by the distance of their centres to the pose's centre.
    fn nearest_order(&self, cam_from_map: &Pose) -> Vec<usize> {
        let c = cam_from_map.inverse().translation.vector;
        let mut order: Vec<(f64, usize)> = self
            .keyframe_centres
            .iter()
            .enumerate()
            .map(|(k, x)| ((x - c).norm_squared(), k))
            .collect();
        order.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        order.into_iter().map(|(_, k)| k).collect()
    }

    /// Project `landmarks` with the pose and match each to the best keypoint within the guided
    /// radius (Hamming ≤ the guided limit, ratio-checked among the keypoints in reach); each
    /// keypoint serves one landmark (the closest in descriptor distance).
    fn guided_matches(
        &self,
        cam_from_map: &Pose,
        landmarks: &[u32],
        features: &FrameFeatures,
        grid: &KeypointGrid,
    ) -> Vec<Correspondence> {
        self.guided_matches_within(
            cam_from_map,
            landmarks,
            features,
            grid,
            self.options.guided_radius_px,
        )
    }

    /// [`Self::guided_matches`] within `r` px of each projection.
    fn guided_matches_within(
        &self,
        cam_from_map: &Pose,
        landmarks: &[u32],
        features: &FrameFeatures,
        grid: &KeypointGrid,
        r: f64,
    ) -> Vec<Correspondence> {
        let max_off_axis = 0.5 * self.camera.valid_fov();
        let cos_max = max_off_axis.cos();
        // (keypoint, distance, landmark) proposals.
        let mut proposals: Vec<(usize, u32, u32)> = Vec::new();
        let mut near = Vec::new();
        for &l in landmarks {
            let pc = (cam_from_map * Point3::from(self.positions[l as usize])).coords;
            let n = pc.norm();
            if n <= 0.0 || pc.z / n < cos_max {
                continue;
            }
            let Some(px) = self.camera.project(&pc) else {
                continue;
            };
            grid.within(&px, r, &features.keypoints, &mut near);
            let d = &self.descriptors[l as usize];
            let views = &self.landmark_views[l as usize];
            let (mut best, mut second) = ((u32::MAX, usize::MAX), u32::MAX);
            for &k in &near {
                let q = &features.descriptors[k];
                let dist = views
                    .iter()
                    .fold(d.distance(q), |m, v| m.min(v.distance(q)));
                if dist < best.0 {
                    second = best.0;
                    best = (dist, k);
                } else if dist < second {
                    second = dist;
                }
            }
            if best.1 == usize::MAX || best.0 > self.options.guided_max_distance {
                continue;
            }
            if second != u32::MAX && (best.0 as f32) >= self.options.matching.ratio * second as f32
            {
                continue;
            }
            proposals.push((best.1, best.0, l));
        }
        proposals.sort_unstable();
        let mut out = Vec::new();
        let mut last = usize::MAX;
        for (k, _, l) in proposals {
            if k == last {
                continue;
            }
            last = k;
            let kp = &features.keypoints[k];
            out.push(Correspondence {
                landmark: l,
                pixel: kp.pixel,
                bearing: kp.bearing,
            });
        }
        out
    }

    /// The affine map from a keyframe view's stored patch to the query's tangent plane at the
    /// query pixel `at` (its bearing `b_q`): patch pixel `(u, v)` of the view is seen along
    /// `b_q + step_q · (e1, e2) · shape · (u, v)` with the query basis `(e1, e2)` and its level-0
    /// step `step_q`. The surface through landmark `l` is its fitted plane (else one facing the
    /// keyframe). `None` when the plane is seen edge-on or the warp stretches too far.
    fn patch_warp(
        &self,
        l: u32,
        view: &PatchView,
        cam_from_map: &Pose,
        at: &Keypoint,
    ) -> Option<TangentPatch> {
        let x = self.positions[l as usize];
        let map_from_kf = self.map_from_keyframes.get(view.keyframe as usize)?;
        let c_k = map_from_kf.translation.vector;
        let normal = self.landmark_normals[l as usize].unwrap_or_else(|| (c_k - x).normalize());
        let (e1, e2) = patch_tangent_basis(&self.camera, at)?;
        let b_q = at.bearing;
        let tangent = |p_map: &Vector3<f64>| -> Option<Vector2<f64>> {
            let p = (cam_from_map * Point3::from(*p_map)).coords;
            let d = p.dot(&b_q);
            (d > 0.0).then(|| {
                let g = p / d - b_q;
                Vector2::new(g.dot(&e1), g.dot(&e2))
            })
        };
        let t0 = tangent(&x)?;
        // The keyframe's ray through the landmark, as the stored patch was sampled.
        let b = (map_from_kf.rotation.inverse() * (x - c_k)).normalize();
        let (f1, f2) = direction_basis(&b);
        let mut j = Matrix2::zeros();
        for (col, f) in [f1, f2].iter().enumerate() {
            let d = map_from_kf.rotation * (b + f * WARP_EPSILON);
            let denom = normal.dot(&d);
            if denom.abs() < 1e-12 {
                return None;
            }
            let s = normal.dot(&(x - c_k)) / denom;
            if s.is_nan() || s <= 0.0 {
                return None;
            }
            j.set_column(col, &((tangent(&(c_k + d * s))? - t0) / WARP_EPSILON));
        }
        let det = j.determinant();
        if det.is_nan() || det <= 0.0 {
            return None;
        }
        let normalised = j / det.sqrt();
        let f = normalised.norm_squared();
        let stretch = 0.5 * (f + (f * f - 4.0).max(0.0).sqrt());
        if !(stretch.is_finite() && stretch <= WARP_MAX_STRETCH) {
            return None;
        }
        let step_q = patch_step(&self.camera, at, f64::from(self.options.orb.scale_factor))?;
        Some(TangentPatch {
            direction: b_q,
            e1,
            e2,
            step: step_q,
            shape: j * (view.step / step_q),
        })
    }

    /// Landmarks found by correlation (`patch_topup`): each landmark's stored patch of the
    /// keyframe view whose ray to it is nearest the query's, against the query image warped to
    /// that view around the landmark's projection under `cam_from_map`, within
    /// [`PATCH_SEARCH`] patch pixels; a match needs `patch_min_ncc` and a peak
    /// `patch_peak_margin` above every other offset, and is placed at the sub-pixel peak.
    fn patch_matches(
        &self,
        image: &GrayImage,
        cam_from_map: &Pose,
        landmarks: &[u32],
    ) -> Vec<Correspondence> {
        let cos_max = (0.5 * self.camera.valid_fov()).cos();
        let centre = cam_from_map.inverse().translation.vector;
        let side = PATCH_SIDE;
        let region = side + 2 * PATCH_SEARCH;
        let w = 2 * PATCH_SEARCH + 1;
        let mut scores = vec![f64::NEG_INFINITY; w * w];
        let mut reference = vec![0.0f64; side * side];
        let mut out = Vec::new();
        for &l in landmarks {
            if self.landmark_patches[l as usize].is_empty() {
                continue;
            }
            let x = self.positions[l as usize];
            let pc = (cam_from_map * Point3::from(x)).coords;
            let n = pc.norm();
            if n <= 0.0 || pc.z / n < cos_max {
                continue;
            }
            let Some(pixel) = self.camera.project(&pc) else {
                continue;
            };
            let at = Keypoint {
                pixel,
                bearing: pc / n,
                octave: 0,
                response: 0.0,
            };
            let ray = (x - centre).normalize();
            let Some(view) = self.landmark_patches[l as usize]
                .iter()
                .filter_map(|v| {
                    let c_k = self.keyframe_centres.get(v.keyframe as usize)?;
                    Some(((x - c_k).normalize().dot(&ray), v))
                })
                .max_by(|a, b| a.0.total_cmp(&b.0).then(b.1.keyframe.cmp(&a.1.keyframe)))
                .map(|(_, v)| v)
            else {
                continue;
            };
            // A flat patch correlates with nothing.
            if view.energy <= 1e-3 * (side * side) as f64 {
                continue;
            }
            let Some(warped) = self.patch_warp(l, view, cam_from_map, &at) else {
                continue;
            };
            let Some(area) = warped.sample(image, &self.camera, region) else {
                continue;
            };
            for (r, &v) in reference.iter_mut().zip(view.values.iter()) {
                *r = f64::from(v) - view.mean;
            }
            let energy = view.energy;
            for oy in 0..w {
                for ox in 0..w {
                    scores[oy * w + ox] =
                        window_ncc(&reference, energy, &area, region, (ox, oy), side)
                            .unwrap_or(f64::NEG_INFINITY);
                }
            }
            let (peak, best) =
                scores
                    .iter()
                    .enumerate()
                    .fold(
                        (0, f64::NEG_INFINITY),
                        |a, (i, &v)| if v > a.1 { (i, v) } else { a },
                    );
            if best.is_nan() || best < self.options.patch_min_ncc {
                continue;
            }
            let (py, px) = (peak / w, peak % w);
            // A peak on the window's border may be the flank of one outside it.
            if py == 0 || px == 0 || py + 1 == w || px + 1 == w {
                continue;
            }
            let rival = scores
                .iter()
                .enumerate()
                .filter(|(i, _)| (i / w).abs_diff(py) > 1 || (i % w).abs_diff(px) > 1)
                .map(|(_, &v)| v)
                .fold(f64::NEG_INFINITY, f64::max);
            if rival > best - self.options.patch_peak_margin {
                continue;
            }
            // Sub-pixel peak: a parabola through the peak and its neighbours on each axis.
            let vertex = |before: f64, after: f64| {
                let d = before - 2.0 * best + after;
                if before.is_finite() && after.is_finite() && d.abs() > 1e-12 {
                    (0.5 * (before - after) / d).clamp(-0.5, 0.5)
                } else {
                    0.0
                }
            };
            let du = vertex(scores[py * w + px - 1], scores[py * w + px + 1]);
            let dv = vertex(scores[(py - 1) * w + px], scores[(py + 1) * w + px]);
            let offset = Vector2::new(
                px as f64 - PATCH_SEARCH as f64 + du,
                py as f64 - PATCH_SEARCH as f64 + dv,
            );
            let t = warped.shape * offset;
            let bearing =
                (warped.direction + (warped.e1 * t.x + warped.e2 * t.y) * warped.step).normalize();
            let Some(pixel) = self.camera.project(&bearing) else {
                continue;
            };
            out.push(Correspondence {
                landmark: l,
                pixel,
                bearing,
            });
        }
        out
    }

    /// Localize the next frame of the stream.
    pub fn process(&mut self, frame: u32, t: f64, image: &GrayImage) -> Result<FrameLocalization> {
        let (w, h) = self.camera.resolution();
        if (image.width, image.height) != (w, h) {
            return Err(vision_err(format!(
                "frame {frame} is {}x{} but the lens is {w}x{h}; use the calibrated resolution",
                image.width, image.height
            )));
        }
        if let Some(why) = &self.refused {
            return Ok(FrameLocalization::lost(frame, t, 0, why.clone()));
        }
        let pyramid = KltPyramid::new(image, &self.options.klt)?;
        let mut features: Option<FrameFeatures> = None;
        let mut reason = String::new();
        let mut best_rejected = 0;
        if let Some(state) = self.state.take() {
            match self.track(frame, image, &pyramid, &state, &mut features)? {
                Ok((e, baseline)) => {
                    return Ok(self.finish(
                        frame,
                        t,
                        &e,
                        pyramid,
                        LocalizationStatus::Tracked,
                        baseline,
                    ));
                }
                Err(TrackFailure::Rejected(why, n)) => {
                    reason = format!("tracking: {why}");
                    best_rejected = n;
                }
                Err(TrackFailure::Uncertain(e, why)) => {
                    // The correspondences hold but do not pin the position down (far walls
                    // only): no pose is output, and the tracks are carried on so that tracking
                    // resumes once nearer structure comes back into view (relocalization from
                    // the same view would meet the same geometry).
                    let inliers = e.inliers.len();
                    self.carry(&e, pyramid, usize::MAX);
                    return Ok(FrameLocalization::lost(
                        frame,
                        t,
                        inliers,
                        format!("tracking: {why}"),
                    ));
                }
            }
        }
        // The tracking reason (if any) comes first in a lost frame's reason.
        let after_tracking = |why: String| {
            if reason.is_empty() {
                why
            } else {
                format!("{reason}; {why}")
            }
        };
        let (retries, interval) = (
            self.options.relocalization_retries,
            self.options.relocalization_interval.max(1),
        );
        let run = self.failed_run;
        let since = *self.lost_since.get_or_insert(t);
        let eager = t - since < self.options.relocalization_eager_s;
        if !eager && run >= retries && !(run - retries).is_multiple_of(interval) {
            self.failed_run += 1;
            return Ok(FrameLocalization::lost(
                frame,
                t,
                best_rejected,
                after_tracking(format!(
                    "relocalization: not tried ({run} frames in a row without a pose; now \
                     tried on one frame in {interval})"
                )),
            ));
        }
        let feats = match features.take() {
            Some(f) => f,
            None => self.orb.extract(image, Some(&self.mask), &self.camera)?,
        };
        let started = std::time::Instant::now();
        let whole_map = self.map_attempts_in_run < self.options.relocalization_map_attempts
            || self.window_attempts_since_map + 1
                >= self.options.relocalization_map_interval.max(1);
        let relocalized = self.relocalize(frame, &feats, whole_map, None);
        self.attempts += 1;
        self.attempt_seconds += started.elapsed().as_secs_f64();
        self.failed_run = if relocalized.is_ok() {
            0
        } else {
            self.failed_run + 1
        };
        if relocalized.is_ok() {
            self.lost_since = None;
            self.map_attempts_in_run = 0;
            self.window_attempts_since_map = 0;
        } else if whole_map {
            self.map_attempts_in_run += 1;
            self.window_attempts_since_map = 0;
        } else {
            self.window_attempts_since_map += 1;
        }
        match relocalized {
            Ok((e, source)) => {
                self.last_source = source;
                let e = self.refine_by_correlation(frame, image, e);
                Ok(self.finish(
                    frame,
                    t,
                    &e,
                    pyramid,
                    LocalizationStatus::Relocalized,
                    usize::MAX,
                ))
            }
            Err((why, n)) => Ok(FrameLocalization::lost(
                frame,
                t,
                n.max(best_rejected),
                after_tracking(format!("relocalization: {why}")),
            )),
        }
    }

    /// Whether a correspondence's bearing lies within `limit` (rad) of its landmark seen from
    /// `cam_from_map`.
    fn fits(&self, cam_from_map: &Pose, c: &Correspondence, limit: f64) -> bool {
        let pc = cam_from_map * Point3::from(self.positions[c.landmark as usize]);
        angular_error(&c.bearing, &pc.coords) <= limit
    }

    /// A relocalized pose with the landmarks correlation finds around it
    /// (`refine_relocalized`): the landmarks of the keyframes viewing it best that its inliers
    /// leave out are looked for by their stored patches, those that fit the pose as an inlier
    /// would are added, and the pose is fitted again on all. The refit replaces the pose only
    /// when it keeps more inliers and passes the acceptance rules; the frames tracked from it
    /// then start from the whole view instead of the descriptor matches alone.
    fn refine_by_correlation(&self, frame: u32, image: &GrayImage, e: Estimate) -> Estimate {
        if !self.options.refine_relocalized {
            return e;
        }
        let held: BTreeSet<u32> = e.inliers.iter().map(|c| c.landmark).collect();
        let rest: Vec<u32> = self
            .viewing_landmarks(
                &e.cam_from_map,
                self.options.relocalization_guided_keyframes,
            )
            .into_iter()
            .filter(|l| !held.contains(l))
            .collect();
        let found = self.patch_matches(image, &e.cam_from_map, &rest);
        let mut all = e.inliers.clone();
        all.extend(
            found
                .into_iter()
                .filter(|c| self.fits(&e.cam_from_map, c, self.threshold_rad)),
        );
        let added = all.len() - e.inliers.len();
        let min = self.options.min_inliers_relocalization;
        let refit = self
            .estimate(&all, &self.ransac(frame, 4, min))
            .ok()
            .filter(|r| r.inliers.len() > e.inliers.len() && self.accept(r, min).is_ok());
        tracing::debug!(
            frame,
            inliers = e.inliers.len(),
            added,
            refit = refit.as_ref().map_or(0, |r| r.inliers.len()),
            "relocalized pose refined by correlation"
        );
        refit.unwrap_or(e)
    }

    /// Output an accepted pose and carry its well-fitting inliers to the next frame;
    /// `baseline` is the carried count after the last top-up (`usize::MAX`: this frame's).
    fn finish(
        &mut self,
        frame: u32,
        t: f64,
        e: &Estimate,
        pyramid: KltPyramid,
        status: LocalizationStatus,
        baseline: usize,
    ) -> FrameLocalization {
        let inliers = e.inliers.len();
        tracing::debug!(
            frame,
            inliers,
            candidates = e.candidates,
            status = status.name(),
            "pose accepted"
        );
        self.carry(e, pyramid, baseline);
        FrameLocalization {
            frame,
            t,
            status,
            map_from_cam: Some(e.cam_from_map.inverse()),
            inliers,
            reason: String::new(),
        }
    }

    /// Carry the estimate's well-fitting inliers to the next frame as the motion prior.
    fn carry(&mut self, e: &Estimate, pyramid: KltPyramid, baseline: usize) {
        let carry_rad = self.options.carry_px / self.options.threshold_px * self.threshold_rad;
        let points: Vec<(u32, Point2<f64>)> = e
            .inliers
            .iter()
            .filter(|c| self.fits(&e.cam_from_map, c, carry_rad))
            .take(self.options.target_tracks)
            .map(|c| (c.landmark, c.pixel))
            .collect();
        let baseline = if baseline == usize::MAX {
            points.len()
        } else {
            baseline
        };
        self.state = Some(TrackState {
            pyramid,
            points,
            cam_from_map: e.cam_from_map,
            baseline,
        });
    }

    /// Tracking with the motion prior: the estimate and the carried-count baseline, or why it
    /// was not accepted.
    fn track(
        &mut self,
        frame: u32,
        image: &GrayImage,
        pyramid: &KltPyramid,
        state: &TrackState,
        features: &mut Option<FrameFeatures>,
    ) -> Result<std::result::Result<(Estimate, usize), TrackFailure>> {
        let pixels: Vec<Point2<f64>> = state.points.iter().map(|p| p.1).collect();
        let tracks = track_klt_pyramids(
            &state.pyramid,
            pyramid,
            &pixels,
            Some(&self.mask),
            &self.camera,
            &self.options.klt,
        )?;
        let corr: Vec<Correspondence> = state
            .points
            .iter()
            .zip(tracks)
            .filter_map(|((l, _), tr)| {
                tr.map(|tr| Correspondence {
                    landmark: *l,
                    pixel: tr.pixel,
                    bearing: tr.bearing,
                })
            })
            .collect();
        let ransac = self.ransac(frame, 1, self.options.min_inliers);
        let first = self.estimate(&corr, &ransac);
        let enough = (self.options.replenish_ratio * state.baseline as f64)
            .max(self.options.min_carried as f64)
            .min(self.options.replenish_ratio * self.options.target_tracks as f64)
            .ceil();
        let needs_more = match &first {
            Ok(e) => {
                (e.inliers.len() as f64) < enough || self.accept(e, ransac.min_inliers).is_err()
            }
            Err(_) => true,
        };
        if !needs_more && let Ok(e) = first {
            return Ok(Ok((e, state.baseline)));
        }
        // Guided top-up around the estimated pose (or the previous one).
        let pose = match &first {
            Ok(e) => e.cam_from_map,
            Err(_) => state.cam_from_map,
        };
        let tracked: BTreeSet<u32> = corr.iter().map(|c| c.landmark).collect();
        let k = self.options.guided_keyframes;
        let mut keyframes: Vec<usize> = self.nearest_order(&pose).into_iter().take(k).collect();
        if self.options.topup_by_view {
            keyframes.extend(self.viewing_order(&pose).into_iter().take(k));
        }
        let candidates: Vec<u32> = self
            .landmarks_of(&keyframes)
            .into_iter()
            .filter(|l| !tracked.contains(l))
            .collect();
        let feats = match &first {
            // With a pose, ORB runs only where landmarks wait to be matched and few are held.
            Ok(e) => {
                let rects = self.topup_cells(&pose, &candidates, &e.inliers);
                self.orb
                    .extract_in_rects(image, &self.mask, &self.camera, &rects)?
            }
            // Without one the whole frame is described (and reused if relocalization follows).
            Err(_) => self.orb.extract(image, Some(&self.mask), &self.camera)?,
        };
        let grid = KeypointGrid::new(&feats.keypoints, self.options.guided_radius_px);
        let carried = corr.len();
        let mut all = corr;
        all.extend(self.guided_matches(&pose, &candidates, &feats, &grid));
        if self.options.patch_topup {
            let matched: BTreeSet<u32> = all.iter().map(|c| c.landmark).collect();
            let rest: Vec<u32> = candidates
                .iter()
                .copied()
                .filter(|l| !matched.contains(l))
                .collect();
            let mut found = self.patch_matches(image, &pose, &rest);
            // With a pose from the carried tracks, a patch match must fit it as an inlier would:
            // in a finely repeated texture every match can lock one period off together and
            // outvote the tracks (kitchen 7 at 480 px: 72 such matches moved a pose by 5 cm).
            if let Ok(e) = &first {
                found.retain(|c| self.fits(&e.cam_from_map, c, self.threshold_rad));
            }
            tracing::debug!(
                frame,
                candidates = rest.len(),
                found = found.len(),
                "patch top-up"
            );
            all.extend(found);
        }
        if first.is_err() {
            *features = Some(feats);
        }
        let e = match self.estimate(&all, &self.ransac(frame, 2, ransac.min_inliers)) {
            Ok(e) => e,
            Err(why) => return Ok(Err(TrackFailure::Rejected(why, 0))),
        };
        if let Err(why) = self.accept_support(&e, ransac.min_inliers) {
            return Ok(Err(TrackFailure::Rejected(why, e.inliers.len())));
        }
        let why = match self.check_position(&e) {
            Ok(()) => return Ok(Ok((e, usize::MAX))),
            Err(why) => why,
        };
        if self.options.densify_uncertain {
            all.truncate(carried);
            if let Some(dense) =
                self.rematch_uncertain(frame, image, &e, all, features, ransac.min_inliers)?
            {
                return Ok(Ok((dense, usize::MAX)));
            }
        }
        Ok(Err(TrackFailure::Uncertain(e, why)))
    }

    /// Whole-frame guided matching around `pose` against the landmarks of the
    /// `relocalization_guided_keyframes` keyframes that view it best, added to `carried` (KLT
    /// correspondences, whose landmarks are not matched again), and the estimate of them all
    /// (`None` when RANSAC finds none). The whole frame's features are extracted into
    /// `features` unless already there.
    fn guided_estimate(
        &mut self,
        frame: u32,
        image: &GrayImage,
        pose: &Pose,
        carried: Vec<Correspondence>,
        features: &mut Option<FrameFeatures>,
    ) -> Result<Option<Estimate>> {
        let feats = match features {
            Some(f) => &*f,
            None => &*features.insert(self.orb.extract(image, Some(&self.mask), &self.camera)?),
        };
        let grid = KeypointGrid::new(&feats.keypoints, self.options.guided_radius_px);
        let tracked: BTreeSet<u32> = carried.iter().map(|c| c.landmark).collect();
        let candidates: Vec<u32> = self
            .viewing_landmarks(pose, self.options.relocalization_guided_keyframes)
            .into_iter()
            .filter(|l| !tracked.contains(l))
            .collect();
        let mut all = carried;
        all.extend(self.guided_matches(pose, &candidates, feats, &grid));
        Ok(self
            .estimate(&all, &self.ransac(frame, 3, self.options.min_inliers))
            .ok())
    }

    /// A tracked pose whose position is poorly constrained, matched again around itself over
    /// the whole frame (`guided_estimate`, as relocalization densifies a hypothesis): the
    /// accepted estimate, or `None` when the position stays poorly constrained. `carried` are
    /// the frame's KLT correspondences; the whole frame's features land in `features`.
    fn rematch_uncertain(
        &mut self,
        frame: u32,
        image: &GrayImage,
        e: &Estimate,
        carried: Vec<Correspondence>,
        features: &mut Option<FrameFeatures>,
        min_inliers: usize,
    ) -> Result<Option<Estimate>> {
        let Some(dense) = self.guided_estimate(frame, image, &e.cam_from_map, carried, features)?
        else {
            return Ok(None);
        };
        let accepted = dense.inliers.len() > e.inliers.len()
            && self.accept_support(&dense, min_inliers).is_ok()
            && self.check_position(&dense).is_ok();
        Ok(accepted.then_some(dense))
    }

    /// Pixel rectangles of the top-up grid cells that hold fewer than `cell_min_tracks` of the
    /// current inliers and into which at least `cell_min_candidates` untracked landmarks
    /// project (in row-major cell order).
    fn topup_cells(
        &self,
        cam_from_map: &Pose,
        candidates: &[u32],
        inliers: &[Correspondence],
    ) -> Vec<[u32; 4]> {
        let (w, h) = self.camera.resolution();
        let g = self.options.topup_grid.max(1);
        let (cw, ch) = (w.div_ceil(g), h.div_ceil(g));
        let cell = |p: &Point2<f64>| -> Option<usize> {
            if p.x < 0.0 || p.y < 0.0 {
                return None;
            }
            let (cx, cy) = ((p.x as u32) / cw, (p.y as u32) / ch);
            (cx < g && cy < g).then_some((cy * g + cx) as usize)
        };
        let mut held = vec![0usize; (g * g) as usize];
        let mut waiting = vec![0usize; (g * g) as usize];
        for c in inliers {
            if let Some(k) = cell(&c.pixel) {
                held[k] += 1;
            }
        }
        let cos_max = (0.5 * self.camera.valid_fov()).cos();
        for &l in candidates {
            let pc = (cam_from_map * Point3::from(self.positions[l as usize])).coords;
            let n = pc.norm();
            if n <= 0.0 || pc.z / n < cos_max {
                continue;
            }
            if let Some(k) = self.camera.project(&pc).as_ref().and_then(cell) {
                waiting[k] += 1;
            }
        }
        (0..g * g)
            .filter(|&k| {
                held[k as usize] < self.options.cell_min_tracks
                    && waiting[k as usize] >= self.options.cell_min_candidates
            })
            .map(|k| {
                let (cx, cy) = (k % g, k / g);
                [
                    cx * cw,
                    cy * ch,
                    ((cx + 1) * cw).min(w),
                    ((cy + 1) * ch).min(h),
                ]
            })
            .collect()
    }

    /// Relocalize one frame from scratch (no motion prior, no state change) and report every
    /// candidate tried: the diagnostics behind docs/vision.md's relocalization figures.
    pub fn trace_relocalization(
        &mut self,
        frame: u32,
        image: &GrayImage,
    ) -> Result<RelocalizationTrace> {
        let features = self.orb.extract(image, Some(&self.mask), &self.camera)?;
        let mut candidates = Vec::new();
        let _ = self.relocalize(frame, &features, true, Some(&mut candidates));
        Ok(RelocalizationTrace {
            features,
            candidates,
        })
    }

    /// Global relocalization by place recognition; `Err((reason, inliers))` when rejected.
    /// Each candidate tried is appended to `trace` when given. When no candidate window gives
    /// an accepted pose, the query is matched once against the whole map, keeping a few
    /// look-alike landmarks per keypoint (`relocalization_map_candidates`), and RANSAC chooses
    /// (only when `whole_map` is set).
    fn relocalize(
        &self,
        frame: u32,
        feats: &FrameFeatures,
        whole_map: bool,
        mut trace: Option<&mut Vec<CandidateTrace>>,
    ) -> std::result::Result<(Estimate, RelocalizationSource), (String, usize)> {
        if feats.keypoints.len() < self.options.min_inliers_relocalization {
            return Err((
                format!("{} ORB features in the frame", feats.keypoints.len()),
                0,
            ));
        }
        let bow = self.vocabulary.bow(&feats.descriptors);
        let candidates = self
            .database
            .query(&bow, self.options.relocalization_candidates);
        let grid = KeypointGrid::new(&feats.keypoints, self.options.guided_radius_px);
        let mut best: Option<Estimate> = None;
        let mut last_reason = if candidates.is_empty() {
            "no keyframe shares a visual word".to_string()
        } else {
            String::new()
        };
        let mut best_rejected = 0;
        let n_kf = self.keyframe_landmarks.len();
        for (rank, &(score, k)) in candidates.iter().enumerate() {
            let lo = k.saturating_sub(self.options.relocalization_neighbours);
            let hi = (k + self.options.relocalization_neighbours).min(n_kf - 1);
            let set: BTreeSet<u32> = (lo..=hi)
                .flat_map(|j| self.keyframe_landmarks[j].iter().copied())
                .collect();
            let local: Vec<u32> = set.into_iter().collect();
            // Match against every keyframe view of the window's landmarks (plus their
            // representatives), grouped by landmark.
            let (train, groups) = self.train_set(&local, lo..hi + 1);
            let matches = match_descriptor_groups(
                &feats.descriptors,
                &train,
                &groups,
                &self.options.matching,
            );
            let salt = 16 + 4 * rank as u64;
            let attempt = self.densified_hypothesis(
                frame,
                salt,
                &matches,
                feats,
                &grid,
                Some(&local),
                RansacOptions::default().max_iterations,
            );
            self.judge_candidate(
                attempt,
                (Some((k, score)), &matches),
                feats,
                trace.as_deref_mut(),
                &mut best,
                &mut best_rejected,
                &mut last_reason,
            );
        }
        if let Some(e) = best {
            return Ok((e, RelocalizationSource::Window));
        }
        if whole_map && self.options.relocalization_map_candidates > 0 {
            let (train, groups) = self.whole_map_train.get_or_init(|| {
                let all: Vec<u32> = (0..self.positions.len() as u32).collect();
                self.train_set(&all, 0..n_kf)
            });
            let matches = match_descriptor_groups_ambiguous(
                &feats.descriptors,
                train,
                groups,
                &self.options.matching,
                self.options.relocalization_map_candidates,
            );
            let attempt = self.densified_hypothesis(
                frame,
                8,
                &matches,
                feats,
                &grid,
                None,
                self.options.relocalization_map_iterations,
            );
            self.judge_candidate(
                attempt,
                (None, &matches),
                feats,
                trace,
                &mut best,
                &mut best_rejected,
                &mut last_reason,
            );
        }
        best.map(|e| (e, RelocalizationSource::WholeMap))
            .ok_or((last_reason, best_rejected))
    }

    /// Train descriptors of `landmarks` (their representatives) and of every view of theirs in
    /// `keyframes`, with the landmark of each.
    fn train_set(
        &self,
        landmarks: &[u32],
        keyframes: std::ops::Range<usize>,
    ) -> (Vec<Descriptor>, Vec<u32>) {
        let mut train: Vec<Descriptor> = Vec::new();
        let mut groups: Vec<u32> = Vec::new();
        for &l in landmarks {
            train.push(self.descriptors[l as usize]);
            groups.push(l);
        }
        for j in keyframes {
            for (d, l) in self.keyframe_views.get(j).into_iter().flatten() {
                train.push(*d);
                groups.push(*l);
            }
        }
        (train, groups)
    }

    /// A P3P RANSAC hypothesis on descriptor `matches` (at least
    /// `relocalization_hypothesis_inliers`), densified by guided matching: first over
    /// `window` (the candidate window's landmarks) when given, then over the keyframes that
    /// view the estimated pose's surroundings best (a view from elsewhere is often nearest to
    /// keyframes place recognition did not rank first).
    #[allow(clippy::too_many_arguments)]
    fn densified_hypothesis(
        &self,
        frame: u32,
        salt: u64,
        matches: &[DescriptorMatch],
        feats: &FrameFeatures,
        grid: &KeypointGrid,
        window: Option<&[u32]>,
        max_iterations: usize,
    ) -> std::result::Result<Estimate, String> {
        let corr: Vec<Correspondence> = matches
            .iter()
            .map(|m| {
                let kp = &feats.keypoints[m.query];
                Correspondence {
                    landmark: m.train as u32,
                    pixel: kp.pixel,
                    bearing: kp.bearing,
                }
            })
            .collect();
        let hypothesis_min = self
            .options
            .relocalization_hypothesis_inliers
            .clamp(4, self.options.min_inliers_relocalization);
        let ransac = RansacOptions {
            max_iterations,
            preverify: if window.is_none() {
                WHOLE_MAP_PREVERIFY
            } else {
                0
            },
            ..self.ransac(frame, salt, hypothesis_min)
        };
        let first = self.estimate(&corr, &ransac)?;
        let first_inliers = first.inliers.len();
        let mut e = first;
        for round in 0..self.options.relocalization_guided_rounds {
            let viewed;
            let landmarks: &[u32] = match window {
                Some(w) if round == 0 => w,
                _ => {
                    viewed = self.viewing_landmarks(
                        &e.cam_from_map,
                        self.options.relocalization_guided_keyframes,
                    );
                    &viewed
                }
            };
            let mut guided = self.guided_matches(&e.cam_from_map, landmarks, feats, grid);
            if window.is_none() {
                // Guided matching across a 40-60° change of view finds fewer matches than the
                // look-alike descriptor matches the pose already explains: keep those too (one
                // landmark per keypoint).
                let taken: BTreeSet<(u64, u64)> =
                    e.inliers.iter().map(|c| pixel_key(&c.pixel)).collect();
                guided.retain(|c| !taken.contains(&pixel_key(&c.pixel)));
                guided.extend(e.inliers.iter().copied());
            }
            let ransac = self.ransac(frame, salt + 1 + round as u64, hypothesis_min);
            // A whole-map hypothesis's inliers hold look-alikes: its pose is judged on the
            // guided matches it predicts, not on the descriptor matches.
            let replace = |g: &Estimate, e: &Estimate| {
                g.inliers.len() > e.inliers.len() || (round == 0 && window.is_none())
            };
            match self.estimate(&guided, &ransac) {
                Ok(g) if replace(&g, &e) => e = g,
                // The look-alike hypothesis is never judged on its own inliers.
                Err(why) if round == 0 && window.is_none() => {
                    return Err(format!(
                        "guided matching around the look-alike hypothesis gave no pose: {why}"
                    ));
                }
                _ => {
                    if round > 0 || window.is_none() {
                        break;
                    }
                }
            }
        }
        tracing::debug!(
            frame,
            matches = corr.len(),
            hypothesis_inliers = first_inliers,
            inliers = e.inliers.len(),
            candidates = e.candidates,
            "relocalization candidate densified"
        );
        Ok(e)
    }

    /// Guided densification from a pose alone (no descriptor hypothesis): the landmarks of the
    /// keyframes viewing the pose best are projected and matched around their projections,
    /// RANSAC fits a pose, and the rounds repeat from it while the support grows.
    fn densify_from_pose(
        &self,
        frame: u32,
        salt: u64,
        cam_from_map: &Pose,
        feats: &FrameFeatures,
        grid: &KeypointGrid,
    ) -> std::result::Result<Estimate, String> {
        let hypothesis_min = self
            .options
            .relocalization_hypothesis_inliers
            .clamp(4, self.options.min_inliers_relocalization);
        let mut pose = *cam_from_map;
        let mut best: Option<Estimate> = None;
        for round in 0..self.options.relocalization_guided_rounds.max(1) {
            let landmarks =
                self.viewing_landmarks(&pose, self.options.relocalization_guided_keyframes);
            let guided = self.guided_matches(&pose, &landmarks, feats, grid);
            let ransac = self.ransac(frame, salt + round as u64, hypothesis_min);
            match self.estimate(&guided, &ransac) {
                Ok(g)
                    if best
                        .as_ref()
                        .is_none_or(|b| g.inliers.len() > b.inliers.len()) =>
                {
                    pose = g.cam_from_map;
                    best = Some(g);
                }
                Ok(_) => break,
                Err(why) => {
                    if best.is_none() {
                        return Err(why);
                    }
                    break;
                }
            }
        }
        best.ok_or_else(|| "no guided densification round".to_string())
    }

    /// Inliers and pose of guided densification from `cam_from_map` on a traced frame's
    /// features (see [`Self::trace_relocalization`]): how much of the view the map explains
    /// around a given pose, e.g. the true one in a diagnosis.
    pub fn support_at(
        &self,
        frame: u32,
        features: &FrameFeatures,
        cam_from_map: &Pose,
    ) -> Option<(usize, Pose)> {
        let grid = KeypointGrid::new(&features.keypoints, self.options.guided_radius_px);
        self.densify_from_pose(frame, 64, cam_from_map, features, &grid)
            .ok()
            .map(|e| (e.inliers.len(), e.cam_from_map))
    }

    /// How much of an estimate's evidence the map repeats elsewhere. For every inlier landmark
    /// `l`, the map landmarks at least [`COPY_MIN_SHIFT`] of the map depth away whose
    /// descriptors, some view against some view, are within the guided-matching limit give a
    /// shift `d = X_l' - X_l`; a shift (within [`COPY_TOLERANCE`] of the map depth) that at
    /// least [`COPY_MIN_SUPPORT`] inlier landmarks share is a translational copy of that part
    /// of the view (a tiled floor, a papered wall, a row of identical doors). The inliers in
    /// no copy are the pose's unique evidence: a pose that rests on copies alone is as good one
    /// period away, and when the periods of two surfaces nearly agree the whole view repeats.
    fn repeated_evidence(&self, e: &Estimate) -> RepeatedEvidence {
        let min_shift = COPY_MIN_SHIFT * self.map_depth;
        let tolerance = COPY_TOLERANCE * self.map_depth;
        let limit = self.options.guided_max_distance;
        // The localizer holds OpenCV handles and is not `Sync`: the parallel search borrows
        // only the map's arrays.
        let (positions, descriptors, landmark_views) =
            (&self.positions, &self.descriptors, &self.landmark_views);
        let views =
            move |l: usize| std::iter::once(&descriptors[l]).chain(landmark_views[l].iter());
        let mut inlier_landmarks: Vec<u32> = e.inliers.iter().map(|c| c.landmark).collect();
        inlier_landmarks.sort_unstable();
        inlier_landmarks.dedup();
        type Cell = (i64, i64, i64);
        let cell_of = |d: &Vector3<f64>| -> Cell {
            (
                (d.x / tolerance).round() as i64,
                (d.y / tolerance).round() as i64,
                (d.z / tolerance).round() as i64,
            )
        };
        // (shift cell, inlier landmark) of every look-alike pair.
        let mut votes: Vec<(Cell, u32)> = inlier_landmarks
            .par_iter()
            .flat_map_iter(|&l| {
                let x = positions[l as usize];
                positions
                    .iter()
                    .enumerate()
                    .filter(move |(_, y)| (*y - x).norm() >= min_shift)
                    .filter(move |&(other, _)| {
                        views(l as usize).any(|a| views(other).any(|b| a.distance(b) <= limit))
                    })
                    .map(move |(_, y)| (cell_of(&(y - x)), l))
            })
            .collect();
        votes.sort_unstable();
        votes.dedup();
        // Support of a cell: distinct inlier landmarks voting in it or its 26 neighbours.
        let mut cells: Vec<Cell> = votes.iter().map(|v| v.0).collect();
        cells.dedup();
        let mut repeated: BTreeSet<u32> = BTreeSet::new();
        let mut strongest: Option<(Cell, usize)> = None;
        let mut members: Vec<u32> = Vec::new();
        for &c in &cells {
            members.clear();
            for dx in -1..=1 {
                for dy in -1..=1 {
                    for dz in -1..=1 {
                        let n = (c.0 + dx, c.1 + dy, c.2 + dz);
                        let lo = votes.partition_point(|v| v.0 < n);
                        members.extend(votes[lo..].iter().take_while(|v| v.0 == n).map(|v| v.1));
                    }
                }
            }
            members.sort_unstable();
            members.dedup();
            if members.len() >= COPY_MIN_SUPPORT {
                repeated.extend(members.iter().copied());
            }
            if strongest.is_none_or(|(_, k)| members.len() > k) {
                strongest = Some((c, members.len()));
            }
        }
        RepeatedEvidence {
            landmarks: inlier_landmarks.len(),
            repeated: repeated.len(),
            strongest: strongest.map(|(c, k)| {
                (
                    Vector3::new(c.0 as f64, c.1 as f64, c.2 as f64) * tolerance,
                    k,
                )
            }),
        }
    }

    /// Apply the acceptance rules to one candidate's estimate, trace it, and keep the best.
    #[allow(clippy::too_many_arguments)]
    fn judge_candidate(
        &self,
        attempt: std::result::Result<Estimate, String>,
        (candidate, matches): (Option<(usize, f64)>, &[DescriptorMatch]),
        feats: &FrameFeatures,
        trace: Option<&mut Vec<CandidateTrace>>,
        best: &mut Option<Estimate>,
        best_rejected: &mut usize,
        last_reason: &mut String,
    ) {
        let checked = match &attempt {
            Ok(e) => self
                .accept(e, self.options.min_inliers_relocalization)
                .and_then(|()| self.check_view_support(e, feats)),
            Err(why) => Err(why.clone()),
        };
        // The map's copies of the evidence are the dearest figure: found once, only for a
        // candidate that passed the other rules and would replace the best (for every
        // estimate when traced).
        let repeated = attempt.as_ref().ok().and_then(|e| {
            let contends = checked.is_ok()
                && self.options.min_unique_inliers > 0
                && best
                    .as_ref()
                    .is_none_or(|b| e.inliers.len() > b.inliers.len());
            (trace.is_some() || contends).then(|| self.repeated_evidence(e))
        });
        let verdict =
            checked.and_then(|()| repeated.as_ref().map_or(Ok(()), |r| self.check_unique(r)));
        if let Some(t) = trace {
            // A whole-map attempt is traced under the keyframe viewing its estimate best.
            let keyframe = candidate.map_or_else(
                || {
                    attempt
                        .as_ref()
                        .ok()
                        .and_then(|e| self.viewing_order(&e.cam_from_map).first().copied())
                        .unwrap_or(0)
                },
                |(k, _)| k,
            );
            t.push(CandidateTrace {
                keyframe,
                score: candidate.map(|(_, s)| s),
                matches: matches.iter().map(|m| (m.query, m.train as u32)).collect(),
                inliers: attempt.as_ref().map_or(0, |e| e.inliers.len()),
                cam_from_map: attempt.as_ref().ok().map(|e| e.cam_from_map),
                inlier_landmarks: attempt.as_ref().map_or_else(
                    |_| Vec::new(),
                    |e| e.inliers.iter().map(|c| c.landmark).collect(),
                ),
                plane_share: attempt.as_ref().map_or(0.0, |e| self.plane_share(e)),
                repeated: repeated.clone().unwrap_or_default(),
                rejection: verdict.clone().err().unwrap_or_default(),
            });
        }
        match (attempt, verdict) {
            (Ok(e), Ok(())) => {
                if best
                    .as_ref()
                    .is_none_or(|b| e.inliers.len() > b.inliers.len())
                {
                    *best = Some(e);
                }
            }
            (attempt, verdict) => {
                // The frame reports the reason of its strongest refused candidate (a pose
                // refused as a copy says more than a window that gave no pose at all).
                let inliers = attempt.as_ref().map_or(0, |e| e.inliers.len());
                if inliers < *best_rejected && !last_reason.is_empty() {
                    return;
                }
                *best_rejected = inliers;
                let why = verdict.err().unwrap_or_default();
                *last_reason = match candidate {
                    Some((k, _)) => format!("keyframe {k}: {why}"),
                    None => format!("whole map: {why}"),
                };
            }
        }
    }
}

/// Keypoints bucketed on a grid of cells one search radius wide.
struct KeypointGrid {
    cell: f64,
    cols: usize,
    rows: usize,
    cells: Vec<Vec<usize>>,
}

impl KeypointGrid {
    fn new(keypoints: &[Keypoint], radius: f64) -> Self {
        let cell = radius.max(1.0);
        let max_x = keypoints.iter().map(|k| k.pixel.x).fold(0.0, f64::max);
        let max_y = keypoints.iter().map(|k| k.pixel.y).fold(0.0, f64::max);
        let cols = (max_x / cell).floor() as usize + 1;
        let rows = (max_y / cell).floor() as usize + 1;
        let mut cells = vec![Vec::new(); cols * rows];
        for (i, k) in keypoints.iter().enumerate() {
            let (cx, cy) = (
                (k.pixel.x.max(0.0) / cell) as usize,
                (k.pixel.y.max(0.0) / cell) as usize,
            );
            cells[cy.min(rows - 1) * cols + cx.min(cols - 1)].push(i);
        }
        Self {
            cell,
            cols,
            rows,
            cells,
        }
    }

    /// Keypoints within `r` of `p` (in index order).
    fn within(&self, p: &Point2<f64>, r: f64, keypoints: &[Keypoint], out: &mut Vec<usize>) {
        out.clear();
        let lo = |v: f64| ((v - r).max(0.0) / self.cell).floor() as usize;
        let hi = |v: f64, n: usize| (((v + r).max(0.0) / self.cell).floor() as usize).min(n - 1);
        if p.x + r < 0.0 || p.y + r < 0.0 {
            return;
        }
        for cy in lo(p.y)..=hi(p.y, self.rows) {
            for cx in lo(p.x)..=hi(p.x, self.cols) {
                for &i in &self.cells[cy * self.cols + cx] {
                    if (keypoints[i].pixel - p).norm_squared() <= r * r {
                        out.push(i);
                    }
                }
            }
        }
        out.sort_unstable();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn points_on_a_wall_get_its_normal_and_a_corner_none() {
        // A tilted plane z = 0.2 x, points 1 cm apart; its unit normal is (-0.2, 0, 1)/|·|.
        let mut points: Vec<Vector3<f64>> = Vec::new();
        for i in 0..10 {
            for j in 0..10 {
                let (x, y) = (0.01 * f64::from(i), 0.01 * f64::from(j));
                points.push(Vector3::new(x, y, 0.2 * x));
            }
        }
        let normals = surface_normals(&points, 0.025);
        let truth = Vector3::new(-0.2, 0.0, 1.0).normalize();
        let n = normals[55].expect("a normal inside the wall");
        assert!(n.dot(&truth).abs() > 0.999, "{n:?}");
        // Three orthogonal rows through one point are no plane.
        let mut corner: Vec<Vector3<f64>> = Vec::new();
        for k in -3..=3 {
            let d = 0.01 * f64::from(k);
            corner.push(Vector3::new(d, 0.0, 0.0));
            corner.push(Vector3::new(0.0, d, 0.0));
            corner.push(Vector3::new(0.0, 0.0, d));
        }
        assert!(surface_normals(&corner, 0.05)[0].is_none());
    }

    #[test]
    fn correlation_finds_a_shifted_copy_and_ignores_contrast() {
        let side = 5;
        let stride = 9;
        let texture = |x: usize, y: usize| ((x * 37 + y * 91) % 17) as f32;
        let area: Vec<f32> = (0..stride * stride)
            .map(|i| texture(i % stride, i / stride))
            .collect();
        // The reference is the window at (3, 2), at twice the contrast plus an offset.
        let raw: Vec<f64> = (0..side * side)
            .map(|i| 2.0 * f64::from(texture(3 + i % side, 2 + i / side)) + 10.0)
            .collect();
        let mean = raw.iter().sum::<f64>() / raw.len() as f64;
        let reference: Vec<f64> = raw.iter().map(|v| v - mean).collect();
        let energy = reference.iter().map(|v| v * v).sum::<f64>();
        let at = |o| window_ncc(&reference, energy, &area, stride, o, side).unwrap_or(-1.0);
        assert!((at((3, 2)) - 1.0).abs() < 1e-9);
        assert!(at((2, 2)) < 0.9 && at((3, 3)) < 0.9);
        // A flat window has no correlation.
        let flat = vec![7.0f32; stride * stride];
        assert!(window_ncc(&reference, energy, &flat, stride, (0, 0), side).is_none());
    }
}
