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
//!
//! **The two lenses check each other.** Both lenses of a wrist camera see the same body pose at
//! the same moment, each through its own map. A lens's poses come in runs (consecutive
//! localized frames; a lost frame ends one), each begun by a relocalization and carried on by
//! tracking. In a room whose texture repeats, a relocalization can fit the view to a look-alike
//! place a pattern period away, and tracking carries that wrong pose on with every frame
//! passing the localizer's rules; the other lens, localized in another map on other walls, is
//! the independent evidence. Where a front run and a rear run overlap and disagree by more than
//! [`RUN_DISAGREEMENT_M`] (median over their common moments), the run that no other run of
//! the other lens vouches for is withdrawn: a run confirmed by an independent relocalization of
//! the other lens stands. When neither or both are vouched for, the pipeline's [`RunArbiter`]
//! is asked. First each lens's frames are localized only around where the other lens places
//! the wrist: the true place fits both lenses' views, a look-alike place only the view that
//! repeats, so a lens whose frames fit both places (at least [`CROSS_FIT_FRACTION`] of the
//! moments tried) while the other's fit only its own loses its run. Then a witness, if there
//! is one (the wrist's front lens seen in the other wrist's front map, carried to the scene
//! through that wrist's placement): the run it places where it stands (within
//! [`RUN_DISAGREEMENT_M`]) is kept and the other withdrawn. When nothing decides, both are
//! withdrawn (a frame without a pose is better than a wrong one). Withdrawn runs are listed in
//! the summary, with the arbitration's counts.

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

/// Largest time (s) between a front and a rear observation compared as one moment: the
/// dual-lens camera exposes both lenses together, so the two differ only by the lenses' time
/// shifts (well under a millisecond); half a frame interval at 120 Hz.
pub const PAIR_TOLERANCE_S: f64 = 0.004;

/// Median position disagreement (m) of two overlapping runs of the two lenses above which they
/// are taken to be at different places: runs at the right place agree within 1-3 cm (the
/// localizers' and the placement's errors), a run relocalized at a look-alike place is a
/// pattern period away (tiles, wallpaper, cupboard doors: 0.3-0.9 m).
pub const RUN_DISAGREEMENT_M: f64 = 0.1;

/// Fewest common moments for two runs to be compared: a few frames do not judge a run.
pub const MIN_RUN_PAIRS: usize = 5;

/// A run of one lens withdrawn because the other lens disagrees with it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct WithdrawnRun {
    /// `front` or `rear`.
    pub lens: String,
    /// First observation of the run (IMU clock, s).
    pub start_s: f64,
    /// Last observation of the run (IMU clock, s).
    pub end_s: f64,
    /// Observations withdrawn.
    pub observations: usize,
    /// Median position disagreement with the other lens's run it contradicts (m).
    pub disagreement_m: f64,
    /// Why it was withdrawn.
    pub reason: String,
}

/// Evidence asked only where a front run and a rear run of the wrist disagree and no other run
/// of the wrist tells which is right (module docs). Every answer costs a localization, so none
/// is asked before it is needed.
pub trait RunArbiter {
    /// `lens`'s frames at the moments of `at` (the other lens's observations of the wrist, IMU
    /// clock), localized only around where `at` places the wrist (guided matching, then
    /// tracking): its observations of the wrist there, in time order; none where its view does
    /// not fit that place.
    fn localize_at(&mut self, lens: Source, at: &[PoseObservation]) -> Vec<PoseObservation>;

    /// Observations of the wrist independent of both lenses' maps (the pipeline's: its front
    /// lens seen in the other wrist's front map, [`observations_in_other_front_map`]), or
    /// `None` when there is no such witness.
    fn witness(&mut self) -> Option<Vec<PoseObservation>>;
}

/// Fewest of the moments tried at which a lens must fit the other lens's place to be said to
/// fit there: at the right place guided matching finds nearly every frame (a few are lost to
/// blur or a covered lens), at a wrong one it finds few or none.
pub const CROSS_FIT_FRACTION: f64 = 0.5;

/// What the arbitration between disagreeing runs did, when it was needed.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Arbitration {
    /// Disagreeing pairs of runs decided because one lens's frames also fit where the other
    /// lens places the wrist and not the reverse (the view that fits both places repeats).
    pub decided_by_cross_fit: usize,
    /// Pairs the witness decided (it placed the wrist where one lens does, not the other).
    pub decided_by_witness: usize,
    /// Pairs nothing decided: both runs withdrawn.
    pub undecided: usize,
    /// Observations the witness gave, when it was asked.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub witness_observations: Option<usize>,
}

/// How many localizations became observations, per lens.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct ObservationCounts {
    /// Front frames in the episode.
    pub front_frames: usize,
    /// Front observations made.
    pub front_observations: usize,
    /// Rear frames in the episode.
    pub rear_frames: usize,
    /// Rear observations made.
    pub rear_observations: usize,
    /// Runs withdrawn because the other lens contradicts them (their observations are not
    /// counted above).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub withdrawn_runs: Vec<WithdrawnRun>,
    /// What decided between disagreeing runs, when nothing of the wrist's own runs could
    /// ([`RunArbiter`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub arbitration: Option<Arbitration>,
}

/// Eq. 3 for one wrist: front and rear localizations (`map_from_cam` on the camera clock) to
/// `scene_from_imu` observations on the IMU clock, sorted by time, after the two lenses have
/// checked each other's runs (module docs). `exposure_centre_s` is the time from a frame's
/// timestamp to its exposure centre (half the rolling readout; 0 for a global shutter).
pub fn body_observations(
    front: &[Localization],
    rear: &[Localization],
    reference: &SceneReference,
    front_calibration: &LensImuCalibration,
    rear_calibration: &LensImuCalibration,
    exposure_centre_s: f64,
) -> (Vec<PoseObservation>, ObservationCounts) {
    body_observations_arbitrated(
        front,
        rear,
        reference,
        front_calibration,
        rear_calibration,
        exposure_centre_s,
        None,
    )
}

/// [`body_observations`], with a [`RunArbiter`] asked when a front run and a rear run
/// disagree and nothing of the wrist's own runs tells which is right.
pub fn body_observations_arbitrated(
    front: &[Localization],
    rear: &[Localization],
    reference: &SceneReference,
    front_calibration: &LensImuCalibration,
    rear_calibration: &LensImuCalibration,
    exposure_centre_s: f64,
    arbiter: Option<&mut dyn RunArbiter>,
) -> (Vec<PoseObservation>, ObservationCounts) {
    let front_obs = lens_observations(front, |f| PoseObservation {
        t: f.t + front_calibration.time_shift_s + exposure_centre_s,
        source: Source::Front,
        scene_from_imu: reference.scene_from_front_map
            * apply(&reference.front_metric, &f.map_from_cam)
            * front_calibration.cam_from_imu,
    });
    let rear_obs = lens_observations(rear, |r| PoseObservation {
        t: r.t + rear_calibration.time_shift_s + exposure_centre_s,
        source: Source::Rear,
        scene_from_imu: apply(&reference.rear_metric, &r.map_from_cam)
            * rear_calibration.cam_from_imu,
    });
    let (withdrawn, arbitration) = cross_check(&front_obs, &rear_obs, arbiter);
    let kept = |obs: &[RunObservation], source: Source| -> Vec<PoseObservation> {
        obs.iter()
            .filter(|o| !withdrawn.contains_key(&(source, o.run)))
            .map(|o| o.observation)
            .collect()
    };
    let mut out = kept(&front_obs, Source::Front);
    let front_observations = out.len();
    out.extend(kept(&rear_obs, Source::Rear));
    let counts = ObservationCounts {
        front_frames: front.len(),
        front_observations,
        rear_frames: rear.len(),
        rear_observations: out.len() - front_observations,
        withdrawn_runs: withdrawn.values().cloned().collect(),
        arbitration,
    };
    out.sort_by(|a, b| a.t.total_cmp(&b.t));
    (out, counts)
}

/// Eq. 3 solved for the front lens: its `map_from_cam` in its own (unscaled) front map at each
/// of `front_times` (camera clock, s), as the rear lens's localization at the same moment (the
/// rear frame nearest on the IMU clock, within [`PAIR_TOLERANCE_S`]) places the wrist; `None`
/// where the rear has no pose. Both lenses share the frame's exposure, so its centre cancels.
pub fn front_poses_from_rear(
    front_times: &[f64],
    rear: &[Localization],
    reference: &SceneReference,
    front_calibration: &LensImuCalibration,
    rear_calibration: &LensImuCalibration,
) -> Vec<Option<Pose>> {
    let rear_obs = lens_observations(rear, |r| PoseObservation {
        t: r.t + rear_calibration.time_shift_s,
        source: Source::Rear,
        scene_from_imu: apply(&reference.rear_metric, &r.map_from_cam)
            * rear_calibration.cam_from_imu,
    });
    let rear_obs: Vec<PoseObservation> = rear_obs.into_iter().map(|o| o.observation).collect();
    lens_poses_at(
        front_times,
        &rear_obs,
        Source::Front,
        reference,
        front_calibration,
        0.0,
    )
}

/// Eq. 3 solved for either lens: its `map_from_cam` in its own (unscaled) map at each of
/// `times` (camera clock, s) where `at` (observations of the wrist, IMU clock, time order)
/// places the wrist (the observation nearest on the IMU clock, within [`PAIR_TOLERANCE_S`]);
/// `None` where `at` has none. `exposure_centre_s` is the one `at` was made with.
pub fn lens_poses_at(
    times: &[f64],
    at: &[PoseObservation],
    lens: Source,
    reference: &SceneReference,
    calibration: &LensImuCalibration,
    exposure_centre_s: f64,
) -> Vec<Option<Pose>> {
    let at: Vec<RunObservation> = (at.iter())
        .map(|&observation| RunObservation {
            run: 0,
            observation,
        })
        .collect();
    let imu_from_cam = calibration.cam_from_imu.inverse();
    let (map_from_metric, metric_from_scene) = match lens {
        Source::Front => (
            reference.front_metric.inverse(),
            reference.scene_from_front_map.inverse(),
        ),
        Source::Rear => (reference.rear_metric.inverse(), Pose::identity()),
    };
    let mut j = 0usize;
    times
        .iter()
        .map(|&t_cam| {
            let t = t_cam + calibration.time_shift_s + exposure_centre_s;
            let nearest = nearest_at(&at, &mut j, t)?;
            let metric_from_cam =
                metric_from_scene * nearest.observation.scene_from_imu * imu_from_cam;
            Some(apply(&map_from_metric, &metric_from_cam))
        })
        .collect()
}

/// A wrist's rear lens placed through its front lens seen in another wrist's front map: its
/// `map_from_cam` in the (unscaled) rear map at each of `rear_times` (camera clock, s), from the
/// front frame nearest on the IMU clock (within [`PAIR_TOLERANCE_S`]) localized in the map
/// wrist's front map (`front_in_other_map`, `map_from_cam` of this wrist's front lens), carried
/// to the scene by that map's metric recovery and placement (`other`, the map wrist's
/// reference) and to the rear lens by this wrist's calibration; `None` where the front has no
/// pose. Eq. 3 with the other wrist's `G_a`: the scene frame is one for both wrists.
pub fn rear_poses_from_other_front_map(
    rear_times: &[f64],
    front_in_other_map: &[Localization],
    other: &SceneReference,
    front_calibration: &LensImuCalibration,
    rear_calibration: &LensImuCalibration,
) -> Vec<Option<Pose>> {
    let front_obs =
        observations_in_other_front_map(front_in_other_map, other, front_calibration, 0.0);
    lens_poses_at(
        rear_times,
        &front_obs,
        Source::Rear,
        other,
        rear_calibration,
        0.0,
    )
}

/// Eq. 3 for a wrist's front lens seen in another wrist's front map (`front_in_other_map`,
/// `map_from_cam` of this wrist's front lens in that map): `scene_from_imu` observations on the
/// IMU clock through that map's metric recovery and placement (`other`, the map's wrist's
/// reference) and this wrist's calibration, in time order. The [`RunArbiter::witness`] of the
/// pipeline: another map, another placement, the same scene frame.
pub fn observations_in_other_front_map(
    front_in_other_map: &[Localization],
    other: &SceneReference,
    front_calibration: &LensImuCalibration,
    exposure_centre_s: f64,
) -> Vec<PoseObservation> {
    lens_observations(front_in_other_map, |r| PoseObservation {
        t: r.t + front_calibration.time_shift_s + exposure_centre_s,
        source: Source::Front,
        scene_from_imu: other.scene_from_front_map
            * apply(&other.front_metric, &r.map_from_cam)
            * front_calibration.cam_from_imu,
    })
    .into_iter()
    .map(|o| o.observation)
    .collect()
}

/// The observation of `obs` (sorted by time) nearest `t` within [`PAIR_TOLERANCE_S`]; `j` is
/// the search's start, advanced past everything too early (queries must come in time order).
fn nearest_at<'a>(obs: &'a [RunObservation], j: &mut usize, t: f64) -> Option<&'a RunObservation> {
    while *j < obs.len() && obs[*j].observation.t < t - PAIR_TOLERANCE_S {
        *j += 1;
    }
    obs[*j..]
        .iter()
        .take_while(|r| r.observation.t <= t + PAIR_TOLERANCE_S)
        .min_by(|a, b| {
            (a.observation.t - t)
                .abs()
                .total_cmp(&(b.observation.t - t).abs())
        })
}

/// An observation and the run of its lens it belongs to.
#[derive(Debug, Clone, Copy)]
struct RunObservation {
    run: usize,
    observation: PoseObservation,
}

/// The observations of one lens's valid localizations, numbered by run (a lost frame ends a
/// run), in time order.
fn lens_observations(
    rows: &[Localization],
    observe: impl Fn(&Localization) -> PoseObservation,
) -> Vec<RunObservation> {
    let mut out: Vec<RunObservation> = Vec::with_capacity(rows.len());
    let mut run = 0usize;
    let mut in_run = false;
    for row in rows {
        if !row.valid {
            in_run = false;
            continue;
        }
        if !in_run && !out.is_empty() {
            run += 1;
        }
        in_run = true;
        out.push(RunObservation {
            run,
            observation: observe(row),
        });
    }
    out.sort_by(|a, b| a.observation.t.total_cmp(&b.observation.t));
    out
}

/// Median distance (m) from the observations of `run` in `obs` to the witness's observation of
/// the same moment, over at least [`MIN_RUN_PAIRS`] moments; `None` with fewer.
fn distance_to_witness(
    obs: &[RunObservation],
    run: usize,
    witness: &[RunObservation],
) -> Option<f64> {
    let mut j = 0usize;
    let mut d: Vec<f64> = (obs.iter().filter(|o| o.run == run))
        .filter_map(|o| {
            let w = nearest_at(witness, &mut j, o.observation.t)?;
            let d = (o.observation.scene_from_imu.translation.vector
                - w.observation.scene_from_imu.translation.vector)
                .norm();
            d.is_finite().then_some(d)
        })
        .collect();
    if d.len() < MIN_RUN_PAIRS {
        return None;
    }
    d.sort_by(f64::total_cmp);
    Some(d[d.len() / 2])
}

/// Whether a lens's frames, localized around where the other lens places the wrist
/// ([`RunArbiter::localize_at`]), fit that place.
#[derive(Debug, Clone, Copy)]
struct CrossFit {
    /// Moments tried.
    tried: usize,
    /// Moments the lens was localized within [`RUN_DISAGREEMENT_M`] of the other lens's place.
    found: usize,
}

impl CrossFit {
    /// Compare `found` (the lens's observations) with `at` (the other lens's, tried).
    fn of(found: &[PoseObservation], at: &[PoseObservation]) -> Self {
        let at: Vec<RunObservation> = (at.iter())
            .map(|&observation| RunObservation {
                run: 0,
                observation,
            })
            .collect();
        let mut j = 0usize;
        let near = (found.iter())
            .filter(|o| {
                nearest_at(&at, &mut j, o.t).is_some_and(|a| {
                    (o.scene_from_imu.translation.vector
                        - a.observation.scene_from_imu.translation.vector)
                        .norm()
                        <= RUN_DISAGREEMENT_M
                })
            })
            .count();
        Self {
            tried: at.len(),
            found: near,
        }
    }

    fn fits(self) -> bool {
        self.found >= MIN_RUN_PAIRS && self.found as f64 >= CROSS_FIT_FRACTION * self.tried as f64
    }
}

/// The observations of `run` in `obs` between `start` and `end` (IMU clock, s).
fn run_between(
    obs: &[RunObservation],
    run: usize,
    (start, end): (f64, f64),
) -> Vec<PoseObservation> {
    (obs.iter())
        .filter(|o| o.run == run && (start..=end).contains(&o.observation.t))
        .map(|o| o.observation)
        .collect()
}

/// The runs to withdraw, keyed by (lens, run), with why, and what the arbiter did if it was
/// asked (module docs).
fn cross_check(
    front: &[RunObservation],
    rear: &[RunObservation],
    mut arbiter: Option<&mut dyn RunArbiter>,
) -> (
    std::collections::BTreeMap<(Source, usize), WithdrawnRun>,
    Option<Arbitration>,
) {
    use std::collections::{BTreeMap, BTreeSet};
    // Position disagreements of every front–rear pair of one moment, per pair of runs.
    let mut distances: BTreeMap<(usize, usize), Vec<f64>> = BTreeMap::new();
    let mut j = 0usize;
    for f in front {
        if let Some(r) = nearest_at(rear, &mut j, f.observation.t) {
            let d = (f.observation.scene_from_imu.translation.vector
                - r.observation.scene_from_imu.translation.vector)
                .norm();
            if d.is_finite() {
                distances.entry((f.run, r.run)).or_default().push(d);
            }
        }
    }
    let medians: BTreeMap<(usize, usize), f64> = distances
        .into_iter()
        .filter(|(_, d)| d.len() >= MIN_RUN_PAIRS)
        .map(|(k, mut d)| {
            d.sort_by(f64::total_cmp);
            (k, d[d.len() / 2])
        })
        .collect();
    let agree: BTreeSet<(usize, usize)> = medians
        .iter()
        .filter(|(_, m)| **m <= RUN_DISAGREEMENT_M)
        .map(|(k, _)| *k)
        .collect();
    let span = |obs: &[RunObservation], run: usize| -> (f64, f64, usize) {
        let times: Vec<f64> = obs
            .iter()
            .filter(|o| o.run == run)
            .map(|o| o.observation.t)
            .collect();
        (
            times.first().copied().unwrap_or(f64::NAN),
            times.last().copied().unwrap_or(f64::NAN),
            times.len(),
        )
    };
    let mut out = BTreeMap::new();
    // The witness's observations (numbered as one run), once asked.
    let mut witnessed: Option<Vec<RunObservation>> = None;
    let mut arbitration: Option<Arbitration> = None;
    for (&(f, r), &median) in &medians {
        if median <= RUN_DISAGREEMENT_M {
            continue;
        }
        let front_vouched = agree.iter().any(|&(af, ar)| af == f && ar != r);
        let rear_vouched = agree.iter().any(|&(af, ar)| ar == r && af != f);
        let mut withdraw = |source: Source, run: usize, obs: &[RunObservation], why: String| {
            let (start_s, end_s, n) = span(obs, run);
            out.entry((source, run)).or_insert(WithdrawnRun {
                lens: source.name().to_string(),
                start_s,
                end_s,
                observations: n,
                disagreement_m: median,
                reason: why,
            });
        };
        let other = |source: Source| match source {
            Source::Front => "rear",
            Source::Rear => "front",
        };
        let vouched_against = |source: Source| {
            format!(
                "the {} lens disagrees with it by {median:.3} m (median) where a run of the {} \
                 lens that another run of the {} lens confirms places the wrist: it was \
                 localized at a look-alike place",
                other(source),
                other(source),
                source.name()
            )
        };
        let undecided = format!(
            "the front and rear lenses disagree by {median:.3} m (median) and no other run tells \
             which is right: one of them was localized at a look-alike place"
        );
        // Withdraw this pair's run of `source`.
        let mut withdraw_lens = |source: Source, why: String| match source {
            Source::Front => withdraw(Source::Front, f, front, why),
            Source::Rear => withdraw(Source::Rear, r, rear, why),
        };
        match (front_vouched, rear_vouched) {
            (false, true) => withdraw_lens(Source::Front, vouched_against(Source::Front)),
            (true, false) => withdraw_lens(Source::Rear, vouched_against(Source::Rear)),
            _ => {
                let Some(arbiter) = arbiter.as_deref_mut() else {
                    withdraw_lens(Source::Front, undecided.clone());
                    withdraw_lens(Source::Rear, undecided);
                    continue;
                };
                let record = arbitration.get_or_insert_with(Arbitration::default);
                // First each lens at the other's place: the true place fits both lenses' views,
                // a look-alike place only the view that repeats.
                let (front_span, rear_span) = (span(front, f), span(rear, r));
                let at_front = run_between(front, f, (rear_span.0, rear_span.1));
                let at_rear = run_between(rear, r, (front_span.0, front_span.1));
                let rear_there =
                    CrossFit::of(&arbiter.localize_at(Source::Rear, &at_front), &at_front);
                let front_there =
                    CrossFit::of(&arbiter.localize_at(Source::Front, &at_rear), &at_rear);
                let fits_both = |source: Source, kept: CrossFit, withdrawn: CrossFit| {
                    format!(
                        "the {} lens disagrees with it by {median:.3} m (median); this lens's own \
                         frames also fit where the {} lens places the wrist ({} of {} moments \
                         tried), the {} lens's do not fit where this run places it ({} of {}): \
                         this lens's view repeats and the run was localized at a look-alike place",
                        other(source),
                        other(source),
                        withdrawn.found,
                        withdrawn.tried,
                        other(source),
                        kept.found,
                        kept.tried,
                    )
                };
                // The lens that fits both places loses, with (kept, withdrawn) evidence.
                let repeats = match (front_there.fits(), rear_there.fits()) {
                    (false, true) => Some((Source::Rear, front_there, rear_there)),
                    (true, false) => Some((Source::Front, rear_there, front_there)),
                    _ => None,
                };
                if let Some((lens, kept, withdrawn)) = repeats {
                    record.decided_by_cross_fit += 1;
                    withdraw_lens(lens, fits_both(lens, kept, withdrawn));
                    continue;
                }
                // Then the witness, asked once, as the third vote.
                if witnessed.is_none() {
                    let obs: Vec<RunObservation> = (arbiter.witness().into_iter().flatten())
                        .map(|observation| RunObservation {
                            run: 0,
                            observation,
                        })
                        .collect();
                    record.witness_observations = Some(obs.len());
                    witnessed = Some(obs);
                }
                let placed = |obs: &[RunObservation], run: usize| {
                    let d = distance_to_witness(obs, run, witnessed.as_deref()?)?;
                    Some((d, d <= RUN_DISAGREEMENT_M))
                };
                let placed_by_witness = |source: Source, d_kept: f64, d_withdrawn: f64| {
                    format!(
                        "the {} lens disagrees with it by {median:.3} m (median) and the wrist's \
                         front lens seen in the other wrist's front map places the wrist \
                         {d_withdrawn:.3} m from it and {d_kept:.3} m from the {} lens: it was \
                         localized at a look-alike place",
                        other(source),
                        other(source)
                    )
                };
                // The lens the witness does not place loses, with (kept, withdrawn) distances.
                let (df, dr) = (placed(front, f), placed(rear, r));
                let unplaced = match (df, dr) {
                    (Some((df, true)), Some((dr, false))) => Some((Source::Rear, df, dr)),
                    (Some((df, false)), Some((dr, true))) => Some((Source::Front, dr, df)),
                    _ => None,
                };
                match unplaced {
                    Some((lens, d_kept, d_withdrawn)) => {
                        record.decided_by_witness += 1;
                        withdraw_lens(lens, placed_by_witness(lens, d_kept, d_withdrawn));
                    }
                    None => {
                        record.undecided += 1;
                        let show = |d: Option<(f64, bool)>| match d {
                            Some((d, _)) => format!("{d:.3} m"),
                            None => "too few common frames".into(),
                        };
                        let why = format!(
                            "{undecided} (each lens's frames fit the other's place or neither \
                             does: front {} of {}, rear {} of {} moments; the wrist's front lens \
                             seen in the other wrist's front map does not tell either: front {}, \
                             rear {})",
                            front_there.found,
                            front_there.tried,
                            rear_there.found,
                            rear_there.tried,
                            show(df),
                            show(dr)
                        );
                        withdraw_lens(Source::Front, why.clone());
                        withdraw_lens(Source::Rear, why);
                    }
                }
            }
        }
    }
    (out, arbitration)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    const RATE_HZ: f64 = 30.0;

    fn identity_reference() -> SceneReference {
        SceneReference {
            front_metric: Sim3::identity(),
            rear_metric: Sim3::identity(),
            scene_from_front_map: Pose::identity(),
        }
    }

    fn calibration() -> LensImuCalibration {
        LensImuCalibration {
            cam_from_imu: Pose::identity(),
            time_shift_s: 0.0,
            imu_noise: None,
        }
    }

    /// A wrist moving along x at 0.5 m/s, seen for `n` frames; `offset(i)` moves frame `i`'s
    /// pose (a look-alike place) and `None` loses the frame.
    fn stream(n: usize, offset: impl Fn(usize) -> Option<Vector3<f64>>) -> Vec<Localization> {
        (0..n)
            .map(|i| {
                let t = i as f64 / RATE_HZ;
                match offset(i) {
                    Some(o) => Localization {
                        t,
                        valid: true,
                        map_from_cam: Pose::from_parts(
                            (Vector3::new(0.5 * t, 0.0, 1.0) + o).into(),
                            nalgebra::UnitQuaternion::identity(),
                        ),
                    },
                    None => Localization {
                        t,
                        valid: false,
                        map_from_cam: Pose::identity(),
                    },
                }
            })
            .collect()
    }

    fn observe(front: &[Localization], rear: &[Localization]) -> ObservationCounts {
        let c = calibration();
        body_observations(front, rear, &identity_reference(), &c, &c, 0.0).1
    }

    /// The rear lens placed through the front lens seen in the other wrist's front map lands
    /// where the rear lens truly is in the rear map, through every frame change (scaled maps,
    /// a placement, both lenses' calibrations and time shifts); a lost front frame gives none.
    #[test]
    fn the_other_wrists_front_map_places_the_rear_lens() {
        use nalgebra::{Translation3, UnitQuaternion};
        let rot = |x: f64, y: f64, z: f64| UnitQuaternion::from_euler_angles(x, y, z);
        let other = SceneReference {
            front_metric: Sim3 {
                scale: 0.3,
                rotation: rot(0.1, -0.2, 0.4),
                translation: Vector3::new(0.5, -1.0, 0.2),
            },
            rear_metric: Sim3 {
                scale: 2.5,
                rotation: rot(-0.3, 0.05, 1.1),
                translation: Vector3::new(-0.2, 0.3, 1.4),
            },
            scene_from_front_map: Pose::from_parts(
                Translation3::new(0.1, 0.2, -0.3),
                rot(0.02, 0.3, -0.5),
            ),
        };
        let front_cal = LensImuCalibration {
            cam_from_imu: Pose::from_parts(Translation3::new(0.01, 0.02, 0.03), rot(0.0, 1.5, 0.1)),
            time_shift_s: 0.0004,
            imu_noise: None,
        };
        let rear_cal = LensImuCalibration {
            cam_from_imu: Pose::from_parts(
                Translation3::new(-0.01, 0.0, -0.03),
                rot(0.0, -1.6, 0.0),
            ),
            time_shift_s: -0.0003,
            imu_noise: None,
        };
        let scene_from_imu = |t: f64| {
            Pose::from_parts(
                Translation3::new(0.5 * t, 0.2 * t.sin(), 1.0),
                rot(0.3 * t, 0.1, -0.2 * t),
            )
        };
        let times: Vec<f64> = (0..30).map(|i| i as f64 / RATE_HZ).collect();
        let front: Vec<Localization> = times
            .iter()
            .enumerate()
            .map(|(i, &t)| {
                let moment = t + front_cal.time_shift_s;
                let metric_from_cam = other.scene_from_front_map.inverse()
                    * scene_from_imu(moment)
                    * front_cal.cam_from_imu.inverse();
                Localization {
                    t,
                    valid: i != 7,
                    map_from_cam: apply(&other.front_metric.inverse(), &metric_from_cam),
                }
            })
            .collect();
        // The rear frames are exposed with the front ones (their lens shifts differ by 0.7 ms).
        let rear = rear_poses_from_other_front_map(&times, &front, &other, &front_cal, &rear_cal);
        assert!(rear[7].is_none());
        for (i, (&t, pose)) in times.iter().zip(&rear).enumerate().filter(|(i, _)| *i != 7) {
            let moment = t + front_cal.time_shift_s;
            let truth = apply(
                &other.rear_metric.inverse(),
                &(scene_from_imu(moment) * rear_cal.cam_from_imu.inverse()),
            );
            let d = truth.inverse() * pose.unwrap_or_else(Pose::identity);
            assert!(d.translation.vector.norm() < 1e-9, "frame {i}: {d:?}");
            assert!(d.rotation.angle() < 1e-9, "frame {i}: {d:?}");
        }
    }

    /// Two lenses that agree (within a centimetre of noise) keep every observation.
    #[test]
    fn lenses_that_agree_keep_every_run() {
        let front = stream(90, |i| {
            Some(Vector3::new(0.0, 0.01 * ((i % 3) as f64 - 1.0), 0.0))
        });
        let rear = stream(90, |i| (i % 20 != 7).then(Vector3::zeros));
        let counts = observe(&front, &rear);
        assert!(
            counts.withdrawn_runs.is_empty(),
            "{:?}",
            counts.withdrawn_runs
        );
        assert_eq!(counts.front_observations, 90);
        assert_eq!(counts.rear_observations, 90 - 5);
    }

    /// The rear lens loses the view at frame 40 and relocalizes at frame 43 at a look-alike
    /// place 0.4 m away; the front lens tracks throughout and agreed with the rear's first run:
    /// the rear's second run is withdrawn, the rest kept.
    #[test]
    fn a_run_at_a_look_alike_place_is_withdrawn_where_the_other_lens_is_confirmed() {
        let front = stream(90, |_| Some(Vector3::zeros()));
        let rear = stream(90, |i| match i {
            0..40 => Some(Vector3::zeros()),
            40..43 => None,
            _ => Some(Vector3::new(0.4, 0.0, 0.0)),
        });
        let counts = observe(&front, &rear);
        assert_eq!(
            counts.withdrawn_runs.len(),
            1,
            "{:?}",
            counts.withdrawn_runs
        );
        let w = &counts.withdrawn_runs[0];
        assert_eq!(w.lens, "rear");
        assert_eq!(w.observations, 47);
        assert!((w.start_s - 43.0 / RATE_HZ).abs() < 1e-9, "{}", w.start_s);
        assert!(
            (w.disagreement_m - 0.4).abs() < 1e-9,
            "{}",
            w.disagreement_m
        );
        assert!(w.reason.contains("look-alike"), "{}", w.reason);
        assert_eq!(counts.front_observations, 90);
        assert_eq!(counts.rear_observations, 40);
    }

    /// The same with the lenses swapped: the front run at the look-alike place is withdrawn.
    #[test]
    fn a_front_run_at_a_look_alike_place_is_withdrawn_too() {
        let rear = stream(90, |_| Some(Vector3::zeros()));
        let front = stream(90, |i| match i {
            0..30 | 70..90 => Some(Vector3::zeros()),
            30..32 | 68..70 => None,
            _ => Some(Vector3::new(0.0, -0.6, 0.0)),
        });
        let counts = observe(&front, &rear);
        assert_eq!(
            counts.withdrawn_runs.len(),
            1,
            "{:?}",
            counts.withdrawn_runs
        );
        assert_eq!(counts.withdrawn_runs[0].lens, "front");
        assert_eq!(counts.front_observations, 50);
        assert_eq!(counts.rear_observations, 90);
    }

    /// Two lenses that disagree over the whole episode, with nothing to tell which is right:
    /// both runs are withdrawn.
    #[test]
    fn lenses_that_disagree_throughout_withdraw_both() {
        let front = stream(60, |_| Some(Vector3::zeros()));
        let rear = stream(60, |_| Some(Vector3::new(0.0, 0.0, 0.5)));
        let counts = observe(&front, &rear);
        assert_eq!(counts.withdrawn_runs.len(), 2);
        assert_eq!(counts.front_observations + counts.rear_observations, 0);
    }

    /// An arbiter over the test's streams (identity references: a pose is the scene's): each
    /// lens's view fits the places `front_fits` / `rear_fits` (sideways offsets from the
    /// wrist's path), and the witness is `witness` seen as a front stream.
    struct Arbiter<'a> {
        front_fits: Vec<Vector3<f64>>,
        rear_fits: Vec<Vector3<f64>>,
        witness: Option<&'a [Localization]>,
        localized: usize,
        witnessed: usize,
    }

    impl<'a> Arbiter<'a> {
        fn new(front_fits: &[f64], rear_fits: &[f64], witness: Option<&'a [Localization]>) -> Self {
            let places = |v: &[f64]| v.iter().map(|&y| Vector3::new(0.0, y, 0.0)).collect();
            Self {
                front_fits: places(front_fits),
                rear_fits: places(rear_fits),
                witness,
                localized: 0,
                witnessed: 0,
            }
        }
    }

    impl RunArbiter for Arbiter<'_> {
        fn localize_at(&mut self, lens: Source, at: &[PoseObservation]) -> Vec<PoseObservation> {
            self.localized += 1;
            let fits = match lens {
                Source::Front => &self.front_fits,
                Source::Rear => &self.rear_fits,
            };
            (at.iter())
                .filter(|o| {
                    let offset =
                        o.scene_from_imu.translation.vector - Vector3::new(0.5 * o.t, 0.0, 1.0);
                    fits.iter().any(|p| (offset - p).norm() < 0.05)
                })
                .map(|o| PoseObservation { source: lens, ..*o })
                .collect()
        }

        fn witness(&mut self) -> Option<Vec<PoseObservation>> {
            self.witnessed += 1;
            let c = calibration();
            (self.witness)
                .map(|w| observations_in_other_front_map(w, &identity_reference(), &c, 0.0))
        }
    }

    /// Check that `counts` withdrew exactly one run, of `lens`, with a reason holding `why`,
    /// and kept the other lens's 60 observations.
    fn assert_one_run_withdrawn(counts: &ObservationCounts, lens: &str, why: &str) {
        assert_eq!(
            counts.withdrawn_runs.len(),
            1,
            "{:?}",
            counts.withdrawn_runs
        );
        let run = &counts.withdrawn_runs[0];
        assert_eq!(run.lens, lens);
        assert!(run.reason.contains(why), "{}", run.reason);
        assert_eq!(counts.front_observations + counts.rear_observations, 60);
    }

    fn arbitrate(
        front: &[Localization],
        rear: &[Localization],
        arbiter: &mut Arbiter<'_>,
    ) -> ObservationCounts {
        let c = calibration();
        let arbiter: &mut dyn RunArbiter = arbiter;
        body_observations_arbitrated(
            front,
            rear,
            &identity_reference(),
            &c,
            &c,
            0.0,
            Some(arbiter),
        )
        .1
    }

    /// Two lenses that disagree over the whole episode, where one lens's view repeats (it fits
    /// both places) and the other's does not: the run of the lens that repeats is withdrawn,
    /// whichever lens it is, without asking the witness.
    #[test]
    fn the_lens_whose_view_fits_both_places_is_withdrawn() {
        let right = stream(60, |_| Some(Vector3::zeros()));
        let look_alike = stream(60, |_| Some(Vector3::new(0.0, 0.3, 0.0)));
        let (unique, repeating) = ([0.0].as_slice(), [0.0, 0.3].as_slice());
        for repeats in [Source::Rear, Source::Front] {
            let (front, rear, mut arbiter) = match repeats {
                Source::Rear => (&right, &look_alike, Arbiter::new(unique, repeating, None)),
                Source::Front => (&look_alike, &right, Arbiter::new(repeating, unique, None)),
            };
            let counts = arbitrate(front, rear, &mut arbiter);
            assert_one_run_withdrawn(&counts, repeats.name(), "(60 of 60 moments");
            let record = counts.arbitration.expect("arbitrated");
            assert_eq!((record.decided_by_cross_fit, record.undecided), (1, 0));
            assert_eq!((arbiter.localized, arbiter.witnessed), (2, 0));
            assert_eq!(record.witness_observations, None);
        }
    }

    /// Where both views repeat (or neither fits the other's place), the witness, which places
    /// the wrist where one of them does (within a few centimetres), keeps that lens's run and
    /// withdraws the other's.
    #[test]
    fn a_witness_keeps_the_lens_it_places() {
        let right = stream(60, |_| Some(Vector3::zeros()));
        let look_alike = stream(60, |_| Some(Vector3::new(0.0, 0.3, 0.0)));
        let witness = stream(60, |i| {
            (i % 10 != 3).then(|| Vector3::new(0.02, -0.01 * (i % 2) as f64, 0.0))
        });
        for (front, rear, withdrawn) in [
            (&right, &look_alike, "rear"),
            (&look_alike, &right, "front"),
        ] {
            for fits in [[0.0, 0.3].as_slice(), &[]] {
                let mut arbiter = Arbiter::new(fits, fits, Some(&witness));
                let counts = arbitrate(front, rear, &mut arbiter);
                assert_one_run_withdrawn(&counts, withdrawn, "other wrist's front map");
                let record = counts.arbitration.expect("arbitrated");
                assert_eq!(record.witness_observations, Some(54));
                assert_eq!((record.decided_by_witness, record.undecided), (1, 0));
                assert_eq!(arbiter.witnessed, 1);
            }
        }
    }

    /// A witness that places neither lens, places both, or has nothing to say leaves both runs
    /// withdrawn, and the reason says what was found.
    #[test]
    fn a_witness_that_places_neither_or_both_decides_nothing() {
        let front = stream(60, |_| Some(Vector3::zeros()));
        let rear = stream(60, |_| Some(Vector3::new(0.0, 0.3, 0.0)));
        let between = stream(60, |_| Some(Vector3::new(0.0, 0.15, 0.0)));
        let elsewhere = stream(60, |_| Some(Vector3::new(1.0, 0.0, 0.0)));
        let lost = stream(60, |i| (i < 3).then(Vector3::zeros));
        for witness in [
            Some(&elsewhere[..]),
            Some(&lost[..]),
            Some(&between[..]),
            None,
        ] {
            let mut arbiter = Arbiter::new(&[0.0, 0.3], &[0.0, 0.3], witness);
            let counts = arbitrate(&front, &rear, &mut arbiter);
            assert_eq!(
                counts.withdrawn_runs.len(),
                2,
                "{:?}",
                counts.withdrawn_runs
            );
            let why = &counts.withdrawn_runs[0].reason;
            assert!(
                why.contains("does not tell either") && why.contains("front 60 of 60"),
                "{why}"
            );
            assert_eq!(counts.arbitration.map(|u| u.undecided), Some(1));
        }
    }

    /// Lenses that agree never ask the arbiter: every answer costs a localization.
    #[test]
    fn lenses_that_agree_do_not_ask_the_arbiter() {
        let front = stream(60, |_| Some(Vector3::zeros()));
        let rear = stream(60, |_| Some(Vector3::new(0.01, 0.0, 0.0)));
        let mut arbiter = Arbiter::new(&[0.0], &[0.0], Some(&front));
        let counts = arbitrate(&front, &rear, &mut arbiter);
        assert_eq!((arbiter.localized, arbiter.witnessed), (0, 0));
        assert!(counts.arbitration.is_none() && counts.withdrawn_runs.is_empty());
    }

    /// A disagreement below the bound (a few centimetres: map and placement errors) withdraws
    /// nothing.
    #[test]
    fn a_few_centimetres_do_not_withdraw_a_run() {
        let front = stream(60, |_| Some(Vector3::zeros()));
        let rear = stream(60, |_| Some(Vector3::new(0.03, 0.02, 0.0)));
        assert!(observe(&front, &rear).withdrawn_runs.is_empty());
    }

    /// The front poses predicted from the rear (eq. 3 solved for the front) give, through eq. 3,
    /// the rear's body observations back, through scaled maps, a placement, different
    /// camera–IMU calibrations and time shifts; a rear frame lost leaves the front frame of its
    /// moment without a pose.
    #[test]
    fn front_poses_from_the_rear_observe_the_body_where_the_rear_does() {
        use nalgebra::{Translation3, UnitQuaternion};
        let turn = |x: f64, y: f64, z: f64| UnitQuaternion::from_euler_angles(x, y, z);
        let reference = SceneReference {
            front_metric: Sim3 {
                scale: 0.37,
                rotation: turn(0.1, -0.3, 0.7),
                translation: Vector3::new(0.2, -1.0, 0.4),
            },
            rear_metric: Sim3 {
                scale: 2.4,
                rotation: turn(-0.5, 0.2, 0.1),
                translation: Vector3::new(-0.3, 0.1, 1.2),
            },
            scene_from_front_map: Pose::from_parts(
                Translation3::new(0.5, 0.2, -0.1),
                turn(0.3, 0.0, -1.1),
            ),
        };
        let front_cal = LensImuCalibration {
            cam_from_imu: Pose::from_parts(
                Translation3::new(0.01, 0.02, 0.03),
                turn(3.1, 0.0, 0.1),
            ),
            time_shift_s: 0.0012,
            imu_noise: None,
        };
        let rear_cal = LensImuCalibration {
            cam_from_imu: Pose::from_parts(
                Translation3::new(-0.01, 0.0, 0.02),
                turn(0.0, 0.1, 0.0),
            ),
            time_shift_s: 0.0009,
            imu_noise: None,
        };
        let rear: Vec<Localization> = stream(30, |i| (i != 12).then(Vector3::zeros))
            .into_iter()
            .map(|mut r| {
                r.map_from_cam.rotation = turn(0.02 * r.t, 0.5, -0.01 * r.t);
                r
            })
            .collect();
        let times: Vec<f64> = rear.iter().map(|r| r.t).collect();
        let predicted = front_poses_from_rear(&times, &rear, &reference, &front_cal, &rear_cal);
        assert!(predicted[12].is_none());
        assert_eq!(predicted.iter().filter(|p| p.is_some()).count(), 29);
        let front: Vec<Localization> = (times.iter().zip(&predicted))
            .map(|(&t, p)| Localization {
                t,
                valid: p.is_some(),
                map_from_cam: p.unwrap_or_else(Pose::identity),
            })
            .collect();
        let (obs, counts) =
            body_observations(&front, &rear, &reference, &front_cal, &rear_cal, 0.0);
        assert!(counts.withdrawn_runs.is_empty());
        let (f, r): (Vec<&PoseObservation>, Vec<&PoseObservation>) =
            obs.iter().partition(|o| o.source == Source::Front);
        assert_eq!((f.len(), r.len()), (29, 29));
        for (a, b) in f.iter().zip(&r) {
            let d = a.scene_from_imu.inverse() * b.scene_from_imu;
            assert!(d.translation.vector.norm() < 1e-9, "{d:?}");
            assert!(d.rotation.angle() < 1e-9, "{d:?}");
        }
    }
}
