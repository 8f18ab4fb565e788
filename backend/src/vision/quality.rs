//! The mapper's own check of a map, without ground truth: is the map consistent enough that a
//! pose localized in it can be trusted?
//!
//! A monocular map can drift (scale and position) where the view holds few landmarks: every
//! keyframe is then posed on a few dozen points and the error of each link accumulates.
//! Bundle adjustment cannot see such drift (a drifted map fits its own observations), so the
//! check maps the same tracks a second time in the **reverse frame order** and compares the two
//! trajectories after a similarity alignment: the forward run's error grows from the first
//! frame, the reversed run's from the last, so two consistent maps agree and a drifted one does
//! not. The disagreement (RMS distance of the keyframe centres after the Sim(3), over the map's
//! median keyframe-to-landmark depth) is what a pose localized in the map inherits: a
//! localized camera is placed relative to landmarks at about that depth.
//!
//! A map is refused ([`MapQuality::trustworthy`] false, with the reason) when the two runs
//! disagree by more than [`MAX_DIRECTION_DISAGREEMENT`], or when the reversed run cannot
//! confirm enough of the forward keyframes ([`MIN_REVERSED_COVERAGE`]). The localizer outputs
//! no pose in a refused map: every frame is lost with the reason.

use std::collections::BTreeMap;

use nalgebra::{Point3, Vector3};
use serde::{Deserialize, Serialize};

use kiwi_core::geometry::Pose;

use crate::vision::align::align_and_measure;
use crate::vision::mapping::{MapperOptions, MappingFrame, Reconstruction, reconstruct};

/// Largest disagreement of the forward and reversed reconstructions (RMS keyframe-centre
/// distance after a Sim(3), over the median keyframe-to-landmark depth) of a trusted map.
/// An empirical bound: over the 17 maps of docs/vision.md the maps whose revisits stayed within
/// 5 cm disagreed by 0.18-0.86 % and the drifted ones by 2.3-4.9 %; 1.5 % sits in that gap.
pub const MAX_DIRECTION_DISAGREEMENT: f64 = 0.015;

/// Smallest share of the forward keyframes the reversed run must pose for the check to
/// confirm the map: a map only one direction can build is too fragile to vouch for.
pub const MIN_REVERSED_COVERAGE: f64 = 0.5;

/// A keyframe whose forward and reversed positions lie more than this many times the median
/// distance of the others apart (after a fit on the others) is one the reversed run did not
/// confirm: a run that breaks at one place (kitchen 41's right front map, at the fast turn that
/// ends its survey) is off there by ~150 times its median, while drift, growing smoothly along
/// the path, leaves no keyframe beyond 4-5 times it (scale and rotation creep and random walks,
/// simulated; the workshop's drifted maps: none).
pub const UNCONFIRMED_FACTOR: f64 = 10.0;

/// At most this share of the keyframes may be left unconfirmed for the map to be judged on the
/// others: a break of one stretch, not a map that disagrees everywhere.
pub const MAX_UNCONFIRMED_SHARE: f64 = 0.1;

/// Refits of the disagreement without the unconfirmed keyframes (each judges every keyframe
/// by the previous fit; two or three settle it).
const UNCONFIRMED_ROUNDS: usize = 5;

/// The mapper's consistency figures for a map and the verdict (`.kmap` field `quality`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MapQuality {
    /// Whether poses may be localized in the map.
    pub trustworthy: bool,
    /// Why the map is not trustworthy (empty when it is).
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub reason: String,
    /// RMS distance between the forward and the reversed reconstruction's keyframe centres
    /// after a Sim(3), over the median keyframe-to-landmark depth, over the keyframes the
    /// reversed run confirms (all but `unconfirmed_keyframes`); `None` when the reversed run
    /// posed fewer than three of the keyframes.
    pub direction_disagreement: Option<f64>,
    /// The same over every keyframe both runs posed (equal to `direction_disagreement` when
    /// every keyframe is confirmed).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub whole_disagreement: Option<f64>,
    /// Frames of the keyframes the reversed run places far off the forward run
    /// ([`UNCONFIRMED_FACTOR`]), left out of `direction_disagreement` when they are at most
    /// [`MAX_UNCONFIRMED_SHARE`] of the keyframes (one run broke there; which one the check
    /// cannot tell).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub unconfirmed_keyframes: Vec<u32>,
    /// Share of the forward keyframes the reversed run posed.
    pub reversed_coverage: f64,
    /// Median number of landmarks a keyframe observes.
    pub landmarks_per_keyframe: f64,
    /// Tenth percentile of the landmarks shared by consecutive keyframes (what carries the
    /// scale from one keyframe to the next).
    pub shared_landmarks_p10: f64,
    /// Keyframes per posed frame.
    pub keyframes_per_frame: f64,
}

/// Why a map with these figures is not trustworthy, or an empty string when it is: the reversed
/// run must pose at least [`MIN_REVERSED_COVERAGE`] of the keyframes and agree with the forward
/// run within [`MAX_DIRECTION_DISAGREEMENT`] (`None`: the two could not be aligned).
pub fn verdict(reversed_coverage: f64, direction_disagreement: Option<f64>) -> String {
    match direction_disagreement {
        _ if reversed_coverage.is_nan() || reversed_coverage < MIN_REVERSED_COVERAGE => format!(
            "mapping the episode in reverse order posed only {:.0} % of the keyframes (at least \
             {:.0} % needed to confirm the map)",
            100.0 * reversed_coverage,
            100.0 * MIN_REVERSED_COVERAGE
        ),
        Some(d) if d.is_nan() || d > MAX_DIRECTION_DISAGREEMENT => format!(
            "mapping the episode forward and in reverse order gives trajectories {:.1} % of the \
             scene depth apart (at most {:.1} %): the map has drifted",
            100.0 * d,
            100.0 * MAX_DIRECTION_DISAGREEMENT
        ),
        Some(_) => String::new(),
        None => "the reversed mapping could not be aligned with the map".into(),
    }
}

impl std::fmt::Display for MapQuality {
    /// One line: the verdict (with the reason) and every figure.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        if self.trustworthy {
            write!(f, "trustworthy")?;
        } else {
            write!(f, "NOT trustworthy ({})", self.reason)?;
        }
        write!(
            f,
            "; forward/reversed disagreement {} of the depth, reversed coverage {:.0} %, {:.0} \
             landmarks per keyframe, p10 shared by consecutive keyframes {:.0}, {:.2} keyframes \
             per frame",
            self.direction_disagreement
                .map_or("-".into(), |d| format!("{:.2} %", 100.0 * d)),
            100.0 * self.reversed_coverage,
            self.landmarks_per_keyframe,
            self.shared_landmarks_p10,
            self.keyframes_per_frame
        )?;
        if !self.unconfirmed_keyframes.is_empty() {
            write!(
                f,
                "; {} keyframes not confirmed by the reversed run (frames {}-{}; over every \
                 keyframe {})",
                self.unconfirmed_keyframes.len(),
                self.unconfirmed_keyframes.first().copied().unwrap_or(0),
                self.unconfirmed_keyframes.last().copied().unwrap_or(0),
                self.whole_disagreement
                    .map_or("-".into(), |d| format!("{:.2} %", 100.0 * d)),
            )?;
        }
        Ok(())
    }
}

/// Which keyframes the reversed run confirms. A first Sim(3) fit on every keyframe, a second
/// on the [`MAX_UNCONFIRMED_SHARE`] nearest-fitting ones left out (so that a broken stretch
/// does not bend the fit it is judged by); then keyframes farther than [`UNCONFIRMED_FACTOR`]
/// times the median distance are left out and the fit repeated on the rest until nothing
/// changes (at most [`UNCONFIRMED_ROUNDS`] refits). All confirmed when no fit is possible.
fn confirmed_keyframes(fwd: &[Vector3<f64>], bwd: &[Vector3<f64>]) -> Vec<bool> {
    let all = vec![true; fwd.len()];
    let distances = |keep: &[bool]| -> Option<Vec<f64>> {
        let pick = |v: &[Vector3<f64>]| -> Vec<Vector3<f64>> {
            v.iter()
                .zip(keep)
                .filter(|(_, k)| **k)
                .map(|(x, _)| *x)
                .collect()
        };
        let sim = crate::vision::align::umeyama(&pick(bwd), &pick(fwd), true)?;
        Some(
            (bwd.iter().zip(fwd))
                .map(|(b, f)| (sim.transform_point(b) - f).norm())
                .collect(),
        )
    };
    let Some(first) = distances(&all) else {
        return all;
    };
    let Some(cut) = percentile(first.clone(), 1.0 - MAX_UNCONFIRMED_SHARE) else {
        return all;
    };
    let mut keep: Vec<bool> = first.iter().map(|&d| d <= cut).collect();
    for _ in 0..UNCONFIRMED_ROUNDS {
        let Some(d) = distances(&keep) else {
            return all;
        };
        let Some(median) = percentile(d.clone(), 0.5) else {
            return all;
        };
        let limit = (UNCONFIRMED_FACTOR * median).max(f64::MIN_POSITIVE);
        let next: Vec<bool> = d.iter().map(|&x| x <= limit).collect();
        if next == keep {
            break;
        }
        keep = next;
    }
    keep
}

/// The disagreement of the two runs' keyframe centres, over `depth`.
#[derive(Debug, Clone, PartialEq)]
struct Judged {
    /// Over every keyframe both runs posed.
    whole: Option<f64>,
    /// Over the keyframes the map is judged on (all, or all but `unconfirmed`).
    confirmed: Option<f64>,
    /// Indices (into the centres) left out of `confirmed`.
    unconfirmed: Vec<usize>,
}

/// Judge the forward and reversed centres `fwd` and `bwd` (same keyframes, same order) of a
/// map of `keyframes` keyframes: without the keyframes the reversed run does not confirm when
/// they are at most [`MAX_UNCONFIRMED_SHARE`] of the map, else on all of them.
fn judge(
    fwd: &[Vector3<f64>],
    bwd: &[Vector3<f64>],
    keyframes: usize,
    depth: Option<f64>,
) -> Judged {
    let measure = |b: &[Vector3<f64>], f: &[Vector3<f64>]| {
        align_and_measure(b, f)
            .zip(depth)
            .map(|((_, err), depth)| err.rmse / depth)
    };
    let whole = measure(bwd, fwd);
    let confirmed = confirmed_keyframes(fwd, bwd);
    let unconfirmed: Vec<usize> = (0..confirmed.len()).filter(|&i| !confirmed[i]).collect();
    if unconfirmed.is_empty() || unconfirmed.len() as f64 > MAX_UNCONFIRMED_SHARE * keyframes as f64
    {
        return Judged {
            whole,
            confirmed: whole,
            unconfirmed: Vec::new(),
        };
    }
    let keep = |v: &[Vector3<f64>]| -> Vec<Vector3<f64>> {
        (v.iter().zip(&confirmed))
            .filter(|(_, c)| **c)
            .map(|(x, _)| *x)
            .collect()
    };
    Judged {
        whole,
        confirmed: measure(&keep(bwd), &keep(fwd)),
        unconfirmed,
    }
}

/// Median keyframe-to-landmark distance of a reconstruction (its units); `None` without any.
fn median_depth(recon: &Reconstruction) -> Option<f64> {
    let mut d: Vec<f64> = Vec::new();
    for kf in &recon.keyframes {
        for o in &kf.observations {
            if let Some(p) = recon.landmarks.get(&o.track) {
                let z = (kf.cam_from_world * Point3::from(*p)).coords.norm();
                if z.is_finite() && z > 0.0 {
                    d.push(z);
                }
            }
        }
    }
    percentile(d, 0.5)
}

fn percentile(mut v: Vec<f64>, q: f64) -> Option<f64> {
    if v.is_empty() {
        return None;
    }
    v.sort_by(f64::total_cmp);
    let i = ((v.len() - 1) as f64 * q).round() as usize;
    v.get(i).copied()
}

fn centre(cam_from_world: &Pose) -> Vector3<f64> {
    cam_from_world.inverse().translation.vector
}

/// Check `recon` (the forward reconstruction of `frames`, possibly corrected by loop closure)
/// by mapping `frames` again in reverse order with the same `options`.
pub fn assess(
    frames: &[MappingFrame],
    recon: &Reconstruction,
    options: &MapperOptions,
) -> MapQuality {
    let mapped = |kf: &crate::vision::mapping::ReconKeyframe| {
        kf.observations
            .iter()
            .filter(|o| recon.landmarks.contains_key(&o.track))
            .count() as f64
    };
    let landmarks_per_keyframe =
        percentile(recon.keyframes.iter().map(mapped).collect(), 0.5).unwrap_or(0.0);
    let shared: Vec<f64> = recon
        .keyframes
        .windows(2)
        .map(|w| {
            let ids: std::collections::BTreeSet<u64> = w[0]
                .observations
                .iter()
                .filter(|o| recon.landmarks.contains_key(&o.track))
                .map(|o| o.track)
                .collect();
            w[1].observations
                .iter()
                .filter(|o| ids.contains(&o.track))
                .count() as f64
        })
        .collect();
    let shared_landmarks_p10 = percentile(shared, 0.1).unwrap_or(0.0);
    let keyframes_per_frame = recon.keyframes.len() as f64 / recon.frame_poses.len().max(1) as f64;

    // The same tracks in reverse order (times negated so that they still increase).
    let posed: std::collections::BTreeSet<u32> = recon.frame_poses.iter().map(|p| p.0).collect();
    let reversed: Vec<MappingFrame> = frames
        .iter()
        .rev()
        .filter(|f| posed.contains(&f.frame))
        .map(|f| MappingFrame {
            frame: f.frame,
            t: -f.t,
            observations: f.observations.clone(),
        })
        .collect();
    let back = reconstruct(&reversed, options);
    let mut back_poses: BTreeMap<u32, Pose> = BTreeMap::new();
    if let Ok(b) = &back {
        back_poses.extend(b.frame_poses.iter().copied());
        back_poses.extend(b.keyframes.iter().map(|k| (k.frame, k.cam_from_world)));
    }
    let both: Vec<&crate::vision::mapping::ReconKeyframe> = recon
        .keyframes
        .iter()
        .filter(|k| back_poses.contains_key(&k.frame))
        .collect();
    let frames_both: Vec<u32> = both.iter().map(|k| k.frame).collect();
    let fwd: Vec<Vector3<f64>> = both.iter().map(|k| centre(&k.cam_from_world)).collect();
    let bwd: Vec<Vector3<f64>> = (frames_both.iter())
        .filter_map(|f| back_poses.get(f).map(centre))
        .collect();
    let reversed_coverage = fwd.len() as f64 / recon.keyframes.len().max(1) as f64;
    let judged = judge(&fwd, &bwd, recon.keyframes.len(), median_depth(recon));
    let (whole_disagreement, direction_disagreement) = (judged.whole, judged.confirmed);
    let unconfirmed_keyframes: Vec<u32> = (judged.unconfirmed.iter())
        .filter_map(|&i| frames_both.get(i).copied())
        .collect();
    if !unconfirmed_keyframes.is_empty() {
        tracing::warn!(
            "the reversed mapping run does not confirm {} of {} keyframes (frames {:?}): the \
             map is judged on the others ({}; all: {})",
            unconfirmed_keyframes.len(),
            recon.keyframes.len(),
            unconfirmed_keyframes,
            direction_disagreement.map_or("-".into(), |d| format!("{:.2} %", 100.0 * d)),
            whole_disagreement.map_or("-".into(), |d| format!("{:.2} %", 100.0 * d)),
        );
    }
    let mut reason = verdict(reversed_coverage, direction_disagreement);
    if let Err(e) = &back {
        reason = format!("{reason} ({e})");
    }
    MapQuality {
        trustworthy: reason.is_empty(),
        reason,
        direction_disagreement,
        whole_disagreement: whole_disagreement.filter(|_| !unconfirmed_keyframes.is_empty()),
        unconfirmed_keyframes,
        reversed_coverage,
        landmarks_per_keyframe,
        shared_landmarks_p10,
        keyframes_per_frame,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn both_rules_decide_at_their_bounds() {
        let d = MAX_DIRECTION_DISAGREEMENT;
        let c = MIN_REVERSED_COVERAGE;
        assert!(verdict(c, Some(d)).is_empty());
        assert!(verdict(1.0, Some(0.0)).is_empty());
        assert!(verdict(1.0, Some(d * 1.01)).contains("has drifted"));
        assert!(verdict(1.0, Some(f64::NAN)).contains("has drifted"));
        assert!(verdict(c * 0.99, Some(0.0)).contains("posed only"));
        assert!(verdict(f64::NAN, Some(0.0)).contains("posed only"));
        assert!(verdict(1.0, None).contains("could not be aligned"));
    }

    /// A path of `n` keyframe centres along a curve (map units).
    fn path(n: usize) -> Vec<Vector3<f64>> {
        (0..n)
            .map(|i| {
                let a = i as f64 / n as f64 * std::f64::consts::TAU;
                Vector3::new(3.0 * a.cos(), 2.0 * a.sin(), 0.3 * (2.0 * a).sin())
            })
            .collect()
    }

    /// A 1 cm wobble along the path, different at every keyframe.
    fn wobble(i: usize) -> Vector3<f64> {
        Vector3::new(
            0.01 * (i as f64 * 1.7).sin(),
            0.01 * (i as f64 * 0.9).cos(),
            0.0,
        )
    }

    /// The path of 100 keyframes and a second run of it with the wobble and the stretch
    /// `broken` 0.23 units off.
    fn broken_over(broken: std::ops::Range<usize>) -> (Vec<Vector3<f64>>, Vec<Vector3<f64>>) {
        let fwd = path(100);
        let bwd = (fwd.iter().enumerate())
            .map(|(i, p)| {
                let jump = if broken.contains(&i) {
                    Vector3::new(0.2, -0.1, 0.05)
                } else {
                    Vector3::zeros()
                };
                p + wobble(i) + jump
            })
            .collect();
        (fwd, bwd)
    }

    /// A run that breaks over 7 of 100 keyframes (the reversed run off there by 0.23 units, about
    /// 20 times its 1 cm wobble elsewhere) leaves those 7 unconfirmed; smooth drift (a scale that
    /// creeps along the path) leaves none, however large.
    #[test]
    fn a_break_of_one_stretch_is_left_out_and_drift_is_not() {
        let (fwd, broken) = broken_over(60..67);
        let keep = confirmed_keyframes(&fwd, &broken);
        let left_out: Vec<usize> = (0..100).filter(|&i| !keep[i]).collect();
        assert_eq!(left_out, (60..67).collect::<Vec<_>>());

        let drifted: Vec<Vector3<f64>> = (fwd.iter().enumerate())
            .map(|(i, p)| p * (1.0 + 0.002 * i as f64) + wobble(i))
            .collect();
        assert!(confirmed_keyframes(&fwd, &drifted).iter().all(|&k| k));
    }

    /// A map is judged without a break of at most a tenth of its keyframes, and on all of them
    /// when the break is longer: a run that disagrees over more is not one stretch gone wrong.
    #[test]
    fn only_a_tenth_of_the_keyframes_may_be_left_out() {
        let depth = Some(2.0);
        let (fwd, bwd) = broken_over(60..67);
        let short = judge(&fwd, &bwd, 100, depth);
        assert_eq!(short.unconfirmed, (60..67).collect::<Vec<_>>());
        let (whole, confirmed) = (short.whole.unwrap(), short.confirmed.unwrap());
        assert!(confirmed < MAX_DIRECTION_DISAGREEMENT, "{confirmed}");
        assert!(whole > MAX_DIRECTION_DISAGREEMENT, "{whole}");

        // The same break is at most a tenth of a map of 70 keyframes, not of one of 69.
        assert_eq!(judge(&fwd, &bwd, 70, depth).unconfirmed.len(), 7);
        let capped = judge(&fwd, &bwd, 69, depth);
        assert!(capped.unconfirmed.is_empty());
        assert_eq!(capped.confirmed, capped.whole);

        let (fwd, bwd) = broken_over(50..65);
        let long = judge(&fwd, &bwd, 100, depth);
        assert!(long.unconfirmed.is_empty());
        assert_eq!(long.confirmed, long.whole);
        assert!(long.whole.unwrap() > MAX_DIRECTION_DISAGREEMENT);
    }
}
