//! Runs of a localized stream, and whether they fit together: a hand-held camera cannot jump.
//!
//! A stream's poses come in runs. Each run starts with a relocalization (or, in the backward
//! pass, from the pose of a later run) and goes on by tracking, every frame consistent with the
//! one before. In a room with repeated texture (tiles, wallpaper, the same poster twice) a
//! relocalization can fit the view to a look-alike place, the pattern shifted by a period, and
//! tracking then carries that wrong pose on: each frame on its own passes every acceptance rule.
//! Where two runs meet, their poses must be reachable from one another at a hand's speed; where
//! they are not, at least one of them is wrong. This module finds such meetings and withdraws
//! the run whose start rests on less: a run begun by matching the whole map at once (no place
//! recognition, the attempt a look-alike fools) before one begun on a keyframe window that place
//! recognition proposed; both when their starts are alike (nothing tells which is right, and a
//! frame without a pose is better than a wrong one).
//!
//! Two tests judge a meeting. The speed bound alone must allow a hand's fastest motion over the
//! time between the two frames, plus noise, which over one frame interval is more than a
//! look-alike's offset in a finely repeated room. So where both runs hold two poses next to a
//! meeting of consecutive frames, the motion on either side is also carried across it: one
//! constant acceleration through both runs' poses, with an offset for the later run, leaves a
//! step that is noise for runs at the same place and the look-alike's offset for runs at two.

use std::collections::BTreeSet;

use kiwi_core::geometry::Pose;
use nalgebra::{Matrix4, Matrix4x3, Vector3};

use crate::vision::localize::{FrameLocalization, LocalizationStatus, RelocalizationSource};

/// Fastest a hand-held camera moves, in the map's median keyframe-to-landmark depths per
/// second: 3 depths/s is 4.5 m/s in a room seen at 1.5 m (above a hand's fastest reach), while
/// a look-alike place one pattern period away is several times farther than a frame interval
/// allows.
pub const MAX_SPEED_DEPTHS_PER_S: f64 = 3.0;
/// What two runs' localization noise may add to their apparent jump where they meet (median
/// depths): centimetres in a room, ~10x the localizer's worst accepted error.
pub const JUMP_ALLOWANCE_DEPTHS: f64 = 0.1;
/// Fastest rotation of a hand-held camera (rad/s): ~1000 °/s, above a wrist's flick.
pub const MAX_ANGULAR_RATE_RAD_PER_S: f64 = 17.0;
/// What localization noise may add to the rotation between two runs where they meet (rad, 10°).
pub const ROTATION_ALLOWANCE_RAD: f64 = 0.175;
/// Longest interval between the poses a meeting is judged on, the meeting's own included (s):
/// consecutive frames at 30 Hz (0.033 s) or one lost frame at 60 Hz. Over one interval a
/// change of acceleration leaves a fast reach under 0.015 median depths (unit test); over three
/// about nine times as much (simulated), too close to a look-alike's offset.
pub const MAX_STEP_INTERVAL_S: f64 = 0.05;
/// Largest step one smooth motion may leave between two runs (median depths): under half the
/// smallest look-alike offset measured where a look-alike run met a right one (0.13 depths, a
/// kitchen's tiles), and above what a run's own localization noise leaves (measured: docs/vision.md).
pub const STEP_ALLOWANCE_DEPTHS: f64 = 0.06;
/// Slack on every comparison of a time between frames with a bound (s): frame times are
/// multiples of a frame interval up to rounding (six intervals at 30 Hz compute as
/// 0.20000000000000007 s from frames 17 and 23), and a microsecond is far below any interval,
/// so a decision never flips on how a time was rounded.
pub const TIME_ROUNDING_S: f64 = 1e-6;

/// How far apart two poses are where two runs meet.
#[derive(Debug, Clone, Copy)]
struct Separation {
    /// Camera-centre distance (median map depths).
    jump_depths: f64,
    /// Rotation between them (rad).
    rotation_rad: f64,
    /// Whether a hand-held camera covers both within the time between them.
    reachable: bool,
}

/// The separation of two poses `dt` seconds apart in a map of median depth `depth`.
fn separation(a: &Pose, b: &Pose, dt: f64, depth: f64) -> Separation {
    let jump_depths = (b.translation.vector - a.translation.vector).norm() / depth;
    let rotation_rad = a.rotation.angle_to(&b.rotation);
    Separation {
        jump_depths,
        rotation_rad,
        reachable: jump_depths <= MAX_SPEED_DEPTHS_PER_S * dt + JUMP_ALLOWANCE_DEPTHS
            && rotation_rad <= MAX_ANGULAR_RATE_RAD_PER_S * dt + ROTATION_ALLOWANCE_RAD,
    }
}

/// Whether a frame's pose was withdrawn by [`withdraw`] (its lost reason says so).
pub fn is_withdrawn(frame: &FrameLocalization) -> bool {
    frame.status == LocalizationStatus::Lost && frame.reason.starts_with("withdrawn")
}

/// How a run's first pose was found.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Run {
    /// Frame the run started at (its relocalization, or the later frame a backward pass
    /// started from).
    pub start: usize,
    /// What that start rests on.
    pub source: RelocalizationSource,
}

/// The run each frame's pose belongs to (`None` for a frame without a pose).
#[derive(Debug, Clone, Default)]
pub struct RunBook {
    /// Per frame, an index into `runs`.
    pub frame_run: Vec<Option<usize>>,
    /// Every run so far.
    pub runs: Vec<Run>,
}

impl RunBook {
    /// A book for `n` frames, none localized.
    pub fn new(n: usize) -> Self {
        Self {
            frame_run: vec![None; n],
            runs: Vec::new(),
        }
    }

    /// Start a run at frame `start`; returns its index.
    pub fn open(&mut self, start: usize, source: RelocalizationSource) -> usize {
        self.runs.push(Run { start, source });
        self.runs.len() - 1
    }

    /// The run a localizer is in after producing `result` for frame `frame`: a relocalization
    /// opens a new one (from `source`), tracking stays in `current`.
    pub fn follow(
        &mut self,
        frame: usize,
        result: &FrameLocalization,
        source: RelocalizationSource,
        current: Option<usize>,
    ) -> Option<usize> {
        match result.status {
            LocalizationStatus::Relocalized => Some(self.open(frame, source)),
            LocalizationStatus::Tracked | LocalizationStatus::Lost => current,
        }
    }
}

/// Two consecutive posed frames of different runs whose poses no hand could join.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Conflict {
    /// The earlier frame.
    pub before: usize,
    /// The later frame.
    pub after: usize,
    /// Distance between their camera centres (median map depths).
    pub jump_depths: f64,
    /// Rotation between them (rad).
    pub rotation_rad: f64,
    /// The step the runs' motion, carried across the meeting, leaves between them (median
    /// depths), when that is what showed the conflict.
    pub step_depths: Option<f64>,
}

/// A timed camera centre (s, median map depths).
pub type TimedCentre = (f64, Vector3<f64>);

/// The step one smooth motion leaves between two runs: the camera centre over time as one
/// quadratic (constant acceleration) through the earlier run's last two poses `a` (`a[1]`
/// before `a[0]`) and the later run's first two `b` (`b[0]` before `b[1]`), plus an offset for
/// the later run. Four poses, four unknowns per axis: the offset is what no constant
/// acceleration explains. `None` when the poses are not in time order or any interval between
/// them exceeds [`MAX_STEP_INTERVAL_S`].
pub fn step_between(a: [TimedCentre; 2], b: [TimedCentre; 2]) -> Option<f64> {
    let times = [a[1].0, a[0].0, b[0].0, b[1].0];
    let in_order = |w: &[f64]| {
        let dt = w[1] - w[0];
        dt > 0.0 && dt <= MAX_STEP_INTERVAL_S + TIME_ROUNDING_S
    };
    if !times.windows(2).all(in_order) {
        return None;
    }
    let mid = 0.5 * (a[0].0 + b[0].0);
    // Time in units of the span, so the columns are of one size.
    let scale = times[3] - times[0];
    let row = |t: f64, later: f64| {
        let tau = (t - mid) / scale;
        [1.0, tau, tau * tau, later]
    };
    let rows = [
        row(times[0], 0.0),
        row(times[1], 0.0),
        row(times[2], 1.0),
        row(times[3], 1.0),
    ];
    let design = Matrix4::from_fn(|r, c| rows[r][c]);
    let centres = [a[1].1, a[0].1, b[0].1, b[1].1];
    let rhs = Matrix4x3::from_fn(|r, c| centres[r][c]);
    let coefficients = design.lu().solve(&rhs)?;
    Some(coefficients.row(3).norm())
}

/// The two poses of `run` nearest frame `from` (itself first), walking backwards or forwards.
fn run_pair(
    results: &[FrameLocalization],
    book: &RunBook,
    from: usize,
    run: usize,
    forward: bool,
    depth: f64,
) -> Option<[TimedCentre; 2]> {
    let next = |k: &usize| {
        if forward {
            (k + 1 < results.len()).then_some(k + 1)
        } else {
            k.checked_sub(1)
        }
    };
    let t0 = results[from].t;
    // `from` is the first pose; [`step_between`] takes a second only one interval from it.
    let mut found = std::iter::successors(Some(from), next)
        .take_while(|&k| (results[k].t - t0).abs() <= MAX_STEP_INTERVAL_S + TIME_ROUNDING_S)
        .filter_map(|k| {
            let p = results[k].map_from_cam?;
            (book.frame_run[k] == Some(run)).then(|| (results[k].t, p.translation.vector / depth))
        });
    Some([found.next()?, found.next()?])
}

/// The step the motion of two runs, carried across their meeting at frames `before` (run
/// `run_a`) and `after` (run `run_b`), leaves between them ([`step_between`], median depths);
/// `None` when either run has no second pose next to the meeting or the poses are too far
/// apart in time to carry the motion.
pub fn carried_step(
    results: &[FrameLocalization],
    book: &RunBook,
    (before, after): (usize, usize),
    (run_a, run_b): (usize, usize),
    depth: f64,
) -> Option<f64> {
    if depth.is_nan() || depth <= 0.0 {
        return None;
    }
    let a = run_pair(results, book, before, run_a, false, depth)?;
    let b = run_pair(results, book, after, run_b, true, depth)?;
    step_between(a, b)
}

/// Meetings of runs that no hand-held motion explains: consecutive posed frames (lost frames
/// between them allowed) of different runs whose camera centres are farther apart than
/// [`MAX_SPEED_DEPTHS_PER_S`] over the time between them plus [`JUMP_ALLOWANCE_DEPTHS`], whose
/// orientations differ by more than the rotation bounds allow, or, across a meeting of
/// consecutive frames, whose motion carried across it ([`carried_step`]) leaves a step over
/// [`STEP_ALLOWANCE_DEPTHS`]. `depth` is the map's median keyframe-to-landmark depth (map units).
pub fn conflicts(results: &[FrameLocalization], book: &RunBook, depth: f64) -> Vec<Conflict> {
    let posed: Vec<(usize, Pose, usize)> = (results.iter().zip(&book.frame_run).enumerate())
        .filter_map(|(i, (r, run))| Some((i, r.map_from_cam?, (*run)?)))
        .collect();
    let mut out = Vec::new();
    for w in posed.windows(2) {
        let ((i, a, run_a), (j, b, run_b)) = (w[0], w[1]);
        if run_a == run_b {
            continue;
        }
        let dt = (results[j].t - results[i].t).abs();
        let Separation {
            jump_depths,
            rotation_rad,
            reachable,
        } = separation(&a, &b, dt, depth);
        let carried = carried_step(results, book, (i, j), (run_a, run_b), depth);
        tracing::debug!(
            "runs meet at frames {i} and {j}: {jump_depths:.3} depths (median depth {depth:.4}), \
             {:.1}° in {dt:.3} s; carried step {}",
            rotation_rad.to_degrees(),
            carried.map_or_else(|| "not judged".to_string(), |c| format!("{c:.3} depths"))
        );
        let step_depths = carried.filter(|&c| c > STEP_ALLOWANCE_DEPTHS);
        if !reachable || step_depths.is_some() {
            out.push(Conflict {
                before: i,
                after: j,
                jump_depths,
                rotation_rad,
                step_depths: if reachable { step_depths } else { None },
            });
        }
    }
    out
}

/// How much a run's start rests on: a whole-map match (which a look-alike place can fool) least,
/// a place-recognition window more, the other lens's independent pose most.
fn start_weight(source: RelocalizationSource) -> u8 {
    match source {
        RelocalizationSource::WholeMap => 0,
        RelocalizationSource::Window => 1,
        RelocalizationSource::OtherLens => 2,
    }
}

/// Farthest a run's poses may lie from where an independent witness places the lens (median
/// over the frames they share, in median map depths) and still agree with it: half the smallest
/// look-alike offset measured where a look-alike run met a right one (0.13 depths, a kitchen's
/// tiles); about 0.1 m in a room seen at 1.5 m, five times the witness's worst error measured
/// (19 mm, kitchen 79: docs/vision.md, "The other wrist as a witness").
pub const WITNESS_ALLOWANCE_DEPTHS: f64 = 0.065;
/// Fewest frames a run must share with the witness to be judged by it: one or two frames of a
/// witness can themselves be a stray pose; five at 30 Hz are a sixth of a second of agreement.
pub const MIN_WITNESS_FRAMES: usize = 5;

/// How a run compares with an independent witness of the lens's pose (another localization of
/// the same wrist that neither shares the run's map nor its look-alikes).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WitnessJudgement {
    /// Frames where both the run and the witness hold a pose.
    pub frames: usize,
    /// Median camera-centre distance between them over those frames (median map depths).
    pub median_depths: f64,
}

impl WitnessJudgement {
    /// Whether the run stands where the witness places the lens
    /// ([`WITNESS_ALLOWANCE_DEPTHS`]).
    pub fn agrees(&self) -> bool {
        self.median_depths <= WITNESS_ALLOWANCE_DEPTHS
    }
}

/// Each run's [`WitnessJudgement`] against `witness` (per frame `map_from_cam`, `None` where the
/// witness has none); `None` for a run sharing fewer than [`MIN_WITNESS_FRAMES`] frames with it
/// (or without one at all). `depth` is the map's median keyframe-to-landmark depth.
pub fn judge_runs(
    results: &[FrameLocalization],
    book: &RunBook,
    witness: &[Option<Pose>],
    depth: f64,
) -> Vec<Option<WitnessJudgement>> {
    let mut distances: Vec<Vec<f64>> = vec![Vec::new(); book.runs.len()];
    for ((r, run), w) in results.iter().zip(&book.frame_run).zip(witness) {
        if let (Some(p), Some(run), Some(w)) = (r.map_from_cam, run, w)
            && let Some(d) = distances.get_mut(*run)
        {
            d.push((p.translation.vector - w.translation.vector).norm() / depth);
        }
    }
    distances
        .into_iter()
        .map(|mut d| {
            if d.len() < MIN_WITNESS_FRAMES || !depth.is_finite() || depth <= 0.0 {
                return None;
            }
            d.sort_by(f64::total_cmp);
            Some(WitnessJudgement {
                frames: d.len(),
                median_depths: d[d.len() / 2],
            })
        })
        .collect()
}

/// Whether the witness places run `run` where it stands (`None`: not judged).
pub fn witness_agrees(judged: &[Option<WitnessJudgement>], run: usize) -> Option<bool> {
    judged.get(run).copied().flatten().map(|j| j.agrees())
}

/// The runs to withdraw for `conflicts`: of two runs that cannot both be right, the one a
/// witness does not place where it stands when the witness places the other there (`judged`,
/// per run, from [`judge_runs`]; empty without a witness); else the one whose start rests on
/// less ([`start_weight`]); both when their starts are alike.
pub fn runs_to_withdraw(
    conflicts: &[Conflict],
    book: &RunBook,
    judged: &[Option<WitnessJudgement>],
) -> BTreeSet<usize> {
    let mut out = BTreeSet::new();
    for c in conflicts {
        let (Some(ra), Some(rb)) = (book.frame_run[c.before], book.frame_run[c.after]) else {
            continue;
        };
        match (witness_agrees(judged, ra), witness_agrees(judged, rb)) {
            (Some(true), Some(true)) | (Some(false) | None, Some(false) | None) => {}
            (Some(true), _) => {
                out.insert(rb);
                continue;
            }
            (_, Some(true)) => {
                out.insert(ra);
                continue;
            }
        }
        let (wa, wb) = (
            start_weight(book.runs[ra].source),
            start_weight(book.runs[rb].source),
        );
        if wa <= wb {
            out.insert(ra);
        }
        if wb <= wa {
            out.insert(rb);
        }
    }
    out
}

/// Why the runs of a conflict are withdrawn: the meeting that showed them wrong.
pub fn conflict_reason(
    results: &[FrameLocalization],
    book: &RunBook,
    conflicts: &[Conflict],
    run: usize,
) -> String {
    let start = book.runs[run];
    let meeting = conflicts
        .iter()
        .find(|c| book.frame_run[c.before] == Some(run) || book.frame_run[c.after] == Some(run))
        .map_or_else(String::new, |c| {
            let dt = (results[c.after].t - results[c.before].t).abs();
            match c.step_depths {
                Some(step) => format!(
                    "; frames {} and {} are {:.2} map depths apart in {dt:.3} s, and the motion \
                     on either side leaves a {step:.2}-depth step between them",
                    c.before, c.after, c.jump_depths
                ),
                None => format!(
                    "; frames {} and {} are {:.2} map depths and {:.0}° apart in {dt:.3} s, \
                     farther than a hand moves",
                    c.before,
                    c.after,
                    c.jump_depths,
                    c.rotation_rad.to_degrees()
                ),
            }
        });
    format!(
        "withdrawn: the run that began at frame {} ({}) does not join the stream's other \
         poses{meeting} (a look-alike place in repeated texture)",
        start.start,
        start.source.describe()
    )
}

/// Why a run the witness does not place where it stands is withdrawn.
pub fn witness_reason(
    book: &RunBook,
    judged: &[Option<WitnessJudgement>],
    run: usize,
) -> Option<String> {
    let j = judged.get(run).copied().flatten().filter(|j| !j.agrees())?;
    let start = book.runs[run];
    Some(format!(
        "withdrawn: the run that began at frame {} ({}) does not join the stream's other poses \
         and lies {:.2} map depths (median over {} frames) from where the other wrist's front \
         map places this lens (a look-alike place in repeated texture)",
        start.start,
        start.source.describe(),
        j.median_depths,
        j.frames
    ))
}

/// Longest time across frames without a pose over which a pose can be said to join a withdrawn
/// one (s): a few frame intervals, where the motion bound is still tighter than a pattern period.
pub const MAX_JOIN_GAP_S: f64 = 0.2;
/// Farthest a pose may be from a withdrawn one and still be said to join it (median depths):
/// half the distance a look-alike one period away is seen at, whatever the time between them.
pub const MAX_JOIN_DEPTHS: f64 = 0.25;

/// Runs that agree with a withdrawn pose: a posed frame whose nearest frame with a pose or a
/// withdrawn pose, on either side (or the frame itself), is a withdrawn one within
/// [`MAX_JOIN_GAP_S`], within the motion a hand makes between them (at most
/// [`MAX_JOIN_DEPTHS`]). A pose that joins a place shown to be a look-alike is at that
/// look-alike too — unless a witness places the run where it stands (`judged`, per run, from
/// [`judge_runs`]; empty without a witness).
pub fn runs_joining_withdrawn(
    results: &[FrameLocalization],
    book: &RunBook,
    withdrawn: &[Option<Pose>],
    depth: f64,
    judged: &[Option<WitnessJudgement>],
) -> BTreeSet<usize> {
    let n = results.len();
    let joins = |i: usize, j: usize, p: &Pose| -> bool {
        let Some(w) = withdrawn.get(j).copied().flatten() else {
            return false;
        };
        let dt = (results[j].t - results[i].t).abs();
        let sep = separation(p, &w, dt, depth);
        dt <= MAX_JOIN_GAP_S + TIME_ROUNDING_S
            && sep.reachable
            && sep.jump_depths <= MAX_JOIN_DEPTHS
    };
    // The nearest frame from `i`, forwards or backwards, that holds a pose or a withdrawn pose.
    let nearest = |i: usize, forward: bool| -> Option<usize> {
        let mut j = i;
        loop {
            j = if forward {
                (j + 1 < n).then_some(j + 1)?
            } else {
                j.checked_sub(1)?
            };
            if results[j].map_from_cam.is_some() || withdrawn[j].is_some() {
                return Some(j);
            }
        }
    };
    let mut out = BTreeSet::new();
    for (i, r) in results.iter().enumerate() {
        let (Some(p), Some(run)) = (r.map_from_cam, book.frame_run[i]) else {
            continue;
        };
        if witness_agrees(judged, run) == Some(true) {
            continue;
        }
        let candidates = [Some(i), nearest(i, false), nearest(i, true)];
        if candidates.into_iter().flatten().any(|j| joins(i, j, &p)) {
            out.insert(run);
        }
    }
    out
}

/// Withdraw every pose of `runs`: the frames become lost with the reason `why(run)` gives, and
/// each withdrawn pose is kept in `withdrawn` (per frame). Returns how many frames were
/// withdrawn.
pub fn withdraw(
    results: &mut [FrameLocalization],
    book: &mut RunBook,
    runs: &BTreeSet<usize>,
    why: impl Fn(&[FrameLocalization], &RunBook, usize) -> String,
    withdrawn: &mut [Option<Pose>],
) -> usize {
    let mut count = 0;
    for &r in runs {
        let reason = why(results, book, r);
        for i in 0..results.len() {
            if book.frame_run[i] != Some(r) {
                continue;
            }
            if let Some(p) = results[i].map_from_cam {
                withdrawn[i] = Some(p);
                let inliers = results[i].inliers;
                results[i] = FrameLocalization::lost(
                    results[i].frame,
                    results[i].t,
                    inliers,
                    reason.clone(),
                );
                count += 1;
            }
            book.frame_run[i] = None;
        }
    }
    count
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion, Vector3};

    const RATE: f64 = 30.0;

    fn posed(i: usize, x: f64, status: LocalizationStatus) -> FrameLocalization {
        FrameLocalization {
            frame: i as u32,
            t: i as f64 / RATE,
            status,
            map_from_cam: Some(Pose::from_parts(
                Translation3::new(x, 0.0, 0.0),
                UnitQuaternion::identity(),
            )),
            inliers: 60,
            reason: String::new(),
        }
    }

    /// Frames 0..n moving 1 cm a frame; run A covers `0..split`, run B `split..n`, and B's
    /// poses are shifted by `offset` (map units, depth 1).
    fn two_runs(
        n: usize,
        split: usize,
        offset: f64,
        a: RelocalizationSource,
        b: RelocalizationSource,
    ) -> (Vec<FrameLocalization>, RunBook) {
        let mut book = RunBook::new(n);
        let ra = book.open(0, a);
        let rb = book.open(split, b);
        let results = (0..n)
            .map(|i| {
                let shift = if i >= split { offset } else { 0.0 };
                let status = if i == 0 || i == split {
                    LocalizationStatus::Relocalized
                } else {
                    LocalizationStatus::Tracked
                };
                book.frame_run[i] = Some(if i < split { ra } else { rb });
                posed(i, 0.01 * i as f64 + shift, status)
            })
            .collect();
        (results, book)
    }

    #[test]
    fn runs_that_join_smoothly_are_kept() {
        use RelocalizationSource::{WholeMap, Window};
        let (results, book) = two_runs(60, 30, 0.02, WholeMap, Window);
        assert!(conflicts(&results, &book, 1.0).is_empty());
    }

    #[test]
    fn a_whole_map_run_that_jumps_from_a_window_run_is_withdrawn() {
        use RelocalizationSource::{WholeMap, Window};
        let (mut results, mut book) = two_runs(60, 30, 0.9, WholeMap, Window);
        let found = conflicts(&results, &book, 1.0);
        assert_eq!(found.len(), 1);
        assert_eq!((found[0].before, found[0].after), (29, 30));
        assert!((found[0].jump_depths - 0.91).abs() < 1e-9);
        let runs = runs_to_withdraw(&found, &book, &[]);
        assert_eq!(runs, BTreeSet::from([0]));
        let mut gone = vec![None; 60];
        let why = |r: &[FrameLocalization], b: &RunBook, run| conflict_reason(r, b, &found, run);
        assert_eq!(withdraw(&mut results, &mut book, &runs, why, &mut gone), 30);
        assert!(gone[..30].iter().all(Option::is_some) && gone[30..].iter().all(Option::is_none));
        assert!(
            results[..30]
                .iter()
                .all(|r| is_withdrawn(r) && r.reason.contains("whole-map"))
        );
        assert!(results[30..].iter().all(|r| r.map_from_cam.is_some()));
        assert!(conflicts(&results, &book, 1.0).is_empty());
    }

    #[test]
    fn runs_with_alike_starts_are_both_withdrawn() {
        use RelocalizationSource::Window;
        let (mut results, mut book) = two_runs(40, 10, -0.5, Window, Window);
        let found = conflicts(&results, &book, 1.0);
        let runs = runs_to_withdraw(&found, &book, &[]);
        assert_eq!(runs, BTreeSet::from([0, 1]));
        let mut gone = vec![None; 40];
        let why = |r: &[FrameLocalization], b: &RunBook, run| conflict_reason(r, b, &found, run);
        assert_eq!(withdraw(&mut results, &mut book, &runs, why, &mut gone), 40);
    }

    /// [`two_runs`] of 60 frames whose whole-map first run (frames 0..30) jumps 0.9 depths to
    /// the window run and is withdrawn; with the withdrawn poses.
    fn first_run_withdrawn() -> (Vec<FrameLocalization>, RunBook, Vec<Option<Pose>>) {
        use RelocalizationSource::{WholeMap, Window};
        let (mut results, mut book) = two_runs(60, 30, 0.9, WholeMap, Window);
        let found = conflicts(&results, &book, 1.0);
        let runs = runs_to_withdraw(&found, &book, &[]);
        let mut gone = vec![None; 60];
        let why = |r: &[FrameLocalization], b: &RunBook, run| conflict_reason(r, b, &found, run);
        withdraw(&mut results, &mut book, &runs, why, &mut gone);
        (results, book, gone)
    }

    #[test]
    fn a_run_that_joins_a_withdrawn_place_is_found() {
        use RelocalizationSource::{WholeMap, Window};
        let (mut results, mut book, gone) = first_run_withdrawn();
        // Later, frames 0..5 are posed at the same place again and frames 10..20 elsewhere.
        let again = book.open(5, WholeMap);
        let other = book.open(20, Window);
        for i in 0..5 {
            results[i] = posed(i, 0.01 * i as f64 + 0.03, LocalizationStatus::Tracked);
            book.frame_run[i] = Some(again);
        }
        for i in 10..20 {
            results[i] = posed(i, 0.01 * i as f64 + 0.9, LocalizationStatus::Tracked);
            book.frame_run[i] = Some(other);
        }
        assert_eq!(
            runs_joining_withdrawn(&results, &book, &gone, 1.0, &[]),
            BTreeSet::from([again])
        );
    }

    /// A witness at `x = 0.01 i + offset` for frames `range` (none elsewhere).
    fn witness_over(n: usize, range: std::ops::Range<usize>, offset: f64) -> Vec<Option<Pose>> {
        (0..n)
            .map(|i| {
                range.contains(&i).then(|| {
                    Pose::from_parts(
                        Translation3::new(0.01 * i as f64 + offset, 0.0, 0.0),
                        UnitQuaternion::identity(),
                    )
                })
            })
            .collect()
    }

    #[test]
    fn a_witness_keeps_the_run_it_places_and_withdraws_the_other() {
        use RelocalizationSource::Window;
        // Alike starts: without a witness both runs go (see above).
        let (mut results, mut book) = two_runs(40, 10, -0.5, Window, Window);
        let found = conflicts(&results, &book, 1.0);
        // The witness, 1 cm off the first run's place, sees both runs' frames.
        let judged = judge_runs(&results, &book, &witness_over(40, 0..40, 0.01), 1.0);
        assert!(judged[0].is_some_and(|j| j.agrees() && j.frames == 10));
        assert!(judged[1].is_some_and(|j| !j.agrees() && (j.median_depths - 0.51).abs() < 1e-9));
        let runs = runs_to_withdraw(&found, &book, &judged);
        assert_eq!(runs, BTreeSet::from([1]));
        let mut gone = vec![None; 40];
        let why = |r: &[FrameLocalization], b: &RunBook, run| {
            witness_reason(b, &judged, run).unwrap_or_else(|| conflict_reason(r, b, &found, run))
        };
        assert_eq!(withdraw(&mut results, &mut book, &runs, why, &mut gone), 30);
        assert!(results[10..].iter().all(
            |r| is_withdrawn(r) && r.reason.contains("0.51 map depths (median over 30 frames)")
        ));
        assert!(results[..10].iter().all(|r| r.map_from_cam.is_some()));
        // The witness placing the second run keeps it instead, even against a run begun by the
        // other lens (which rests on more).
        let (results, mut book) = two_runs(40, 10, -0.5, Window, Window);
        book.runs[0].source = RelocalizationSource::OtherLens;
        let judged = judge_runs(&results, &book, &witness_over(40, 0..40, -0.5), 1.0);
        let found = conflicts(&results, &book, 1.0);
        assert_eq!(
            runs_to_withdraw(&found, &book, &judged),
            BTreeSet::from([0])
        );
    }

    #[test]
    fn a_witness_decides_nothing_without_enough_frames_or_where_it_places_neither() {
        use RelocalizationSource::Window;
        let (results, book) = two_runs(40, 10, -0.5, Window, Window);
        let found = conflicts(&results, &book, 1.0);
        // Four frames of the witness on the first run: not judged, so the starts decide.
        let few = witness_over(40, 2..6, 0.0);
        let judged = judge_runs(&results, &book, &few, 1.0);
        assert_eq!(judged[0], None);
        assert_eq!(
            runs_to_withdraw(&found, &book, &judged),
            BTreeSet::from([0, 1])
        );
        // A witness 0.25 depths from both places neither.
        let judged = judge_runs(&results, &book, &witness_over(40, 0..40, -0.25), 1.0);
        assert!(judged.iter().all(|j| j.is_some_and(|j| !j.agrees())));
        assert_eq!(
            runs_to_withdraw(&found, &book, &judged),
            BTreeSet::from([0, 1])
        );
    }

    #[test]
    fn a_run_the_witness_places_is_not_withdrawn_for_joining_a_withdrawn_pose() {
        use RelocalizationSource::WholeMap;
        let (mut results, mut book, gone) = first_run_withdrawn();
        let again = book.open(5, WholeMap);
        for i in 0..5 {
            results[i] = posed(i, 0.01 * i as f64 + 0.03, LocalizationStatus::Tracked);
            book.frame_run[i] = Some(again);
        }
        let judged = judge_runs(&results, &book, &witness_over(60, 0..60, 0.02), 1.0);
        assert!(runs_joining_withdrawn(&results, &book, &gone, 1.0, &judged).is_empty());
    }

    #[test]
    fn a_run_the_join_gap_away_from_a_withdrawn_place_joins_it() {
        use RelocalizationSource::{WholeMap, Window};
        let (mut results, mut book) = two_runs(60, 18, 0.9, WholeMap, Window);
        let found = conflicts(&results, &book, 1.0);
        let runs = runs_to_withdraw(&found, &book, &[]);
        assert_eq!(runs, BTreeSet::from([0]));
        let mut gone = vec![None; 60];
        let why = |r: &[FrameLocalization], b: &RunBook, run| conflict_reason(r, b, &found, run);
        withdraw(&mut results, &mut book, &runs, why, &mut gone);
        // Frames 18..23 lost, then a run at the withdrawn place from frame 23: six intervals
        // after the last withdrawn pose (frame 17), exactly the join gap at 30 Hz, though the
        // frame times' difference rounds above it.
        assert!(results[23].t - results[17].t > MAX_JOIN_GAP_S);
        for r in &mut results[18..23] {
            *r = FrameLocalization::lost(r.frame, r.t, 0, "lost".into());
        }
        for run in &mut book.frame_run[18..23] {
            *run = None;
        }
        let again = book.open(23, WholeMap);
        for i in 23..30 {
            results[i] = posed(i, 0.01 * i as f64, LocalizationStatus::Tracked);
            book.frame_run[i] = Some(again);
        }
        assert_eq!(
            runs_joining_withdrawn(&results, &book, &gone, 1.0, &[]),
            BTreeSet::from([again])
        );
    }

    #[test]
    fn the_allowed_jump_grows_with_the_time_between_the_runs() {
        use RelocalizationSource::{WholeMap, Window};
        // 0.5 depths apart: a conflict across one frame interval, not across a second of lost
        // frames (a hand can move that far in a second).
        let (mut results, book) = two_runs(60, 40, 0.5, WholeMap, Window);
        assert_eq!(conflicts(&results, &book, 1.0).len(), 1);
        for r in &mut results[10..40] {
            *r = FrameLocalization::lost(r.frame, r.t, 0, "lost".into());
        }
        assert!(conflicts(&results, &book, 1.0).is_empty());
    }

    #[test]
    fn a_turn_no_wrist_makes_is_a_conflict() {
        use RelocalizationSource::{WholeMap, Window};
        let (mut results, book) = two_runs(20, 10, 0.0, WholeMap, Window);
        let turned = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 1.5);
        if let Some(p) = results[10].map_from_cam.as_mut() {
            p.rotation = turned;
        }
        let found = conflicts(&results, &book, 1.0);
        assert_eq!(found.len(), 1);
        assert!((found[0].rotation_rad - 1.5).abs() < 1e-9);
    }

    #[test]
    fn a_look_alike_one_frame_away_is_found_by_its_step() {
        use RelocalizationSource::{WholeMap, Window};
        // 0.13 depths: within what the speed bound allows over one frame (0.2 depths at 30 Hz),
        // the smallest look-alike offset measured in a tiled kitchen.
        let (results, book) = two_runs(60, 30, 0.13, WholeMap, Window);
        let found = conflicts(&results, &book, 1.0);
        assert_eq!(found.len(), 1);
        assert_eq!((found[0].before, found[0].after), (29, 30));
        let step = found[0].step_depths.unwrap_or(f64::NAN);
        assert!((step - 0.13).abs() < 1e-9, "step {step}");
        assert_eq!(runs_to_withdraw(&found, &book, &[]), BTreeSet::from([0]));
        let reason = conflict_reason(&results, &book, &found, 0);
        assert!(reason.contains("0.13-depth step"), "{reason}");
    }

    #[test]
    fn a_fast_reach_leaves_no_step() {
        // A minimum-jerk reach of 0.4 m in 0.3 s (peak 2.5 m/s) seen at 0.6 m, at 29.97 Hz: the
        // carried motion's step at every meeting stays under a quarter of the allowance.
        let (distance, duration, depth, rate) = (0.4, 0.3, 0.6, 29.97);
        let centre = |t: f64| {
            let s = (t / duration).clamp(0.0, 1.0);
            let x = distance * s.powi(3) * (10.0 - 15.0 * s + 6.0 * s * s);
            (t, Vector3::new(x, 0.3 * x, 0.0) / depth)
        };
        let at = |k: i32| centre(f64::from(k) / rate);
        let mut worst: f64 = 0.0;
        for k in -6..15 {
            let step = step_between([at(k), at(k - 1)], [at(k + 1), at(k + 2)]);
            worst = worst.max(step.unwrap_or(f64::INFINITY));
        }
        assert!(worst < 0.25 * STEP_ALLOWANCE_DEPTHS, "worst step {worst}");
    }

    #[test]
    fn no_step_is_judged_across_lost_frames() {
        use RelocalizationSource::{WholeMap, Window};
        let (mut results, book) = two_runs(60, 30, 0.13, WholeMap, Window);
        // Two lost frames before the meeting: 0.1 s, too long to carry the motion across; the
        // speed bound alone judges it, and 0.16 depths over 0.1 s is within it.
        for r in &mut results[28..30] {
            *r = FrameLocalization::lost(r.frame, r.t, 0, "lost".into());
        }
        assert_eq!(carried_step(&results, &book, (27, 30), (0, 1), 1.0), None);
        assert!(conflicts(&results, &book, 1.0).is_empty());
        // Nor when the later run has a single pose.
        let (results, book) = two_runs(31, 30, 0.13, WholeMap, Window);
        assert_eq!(carried_step(&results, &book, (29, 30), (0, 1), 1.0), None);
    }
}
