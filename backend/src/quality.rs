//! Episode quality: the figures that say how far to trust an episode's outputs, and the verdict
//! `usable | suspect | unusable` with its reasons. Every threshold is here, with its reason;
//! docs/pipeline.md lists them for users.
//!
//! A frame is *supported* (paper §5) when a valid front observation, or a rear observation
//! within a tracked run of at most 50 ms, is available at its timestamp; frames without one are
//! carried by the IMU alone (`imu-only`), and their uncertainty grows with the gap.

use serde::{Deserialize, Serialize};

/// Verdict of an episode.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Verdict {
    /// Every check passed.
    Usable,
    /// Outputs exist but a check failed: look at the reasons before training on it.
    Suspect,
    /// Outputs are missing or cannot be trusted.
    Unusable,
}

impl Verdict {
    /// `usable`, `suspect` or `unusable`.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Usable => "usable",
            Self::Suspect => "suspect",
            Self::Unusable => "unusable",
        }
    }
}

/// Below this supported fraction a wrist is suspect: the paper's pipeline supports more than
/// 99.9 % of frames; a percent of IMU-only frames means long or frequent visual loss.
pub const SUSPECT_SUPPORTED_FRACTION: f64 = 0.99;
/// Below this supported fraction a wrist's trajectory is mostly inertial dead reckoning.
pub const UNUSABLE_SUPPORTED_FRACTION: f64 = 0.8;
/// An IMU-only run longer than this (s) is suspect: consumer IMU drift reaches centimetres
/// within about a second of double integration.
pub const SUSPECT_UNSUPPORTED_RUN_S: f64 = 0.5;
/// An IMU-only run longer than this (s) makes the episode unusable: drift reaches decimetres.
pub const UNUSABLE_UNSUPPORTED_RUN_S: f64 = 5.0;
/// A tool-tip position sigma above this (m) anywhere is suspect (twice the accuracy target).
pub const SUSPECT_POSITION_SIGMA_M: f64 = 0.02;
/// A tool-tip position sigma above this (m) anywhere is unusable for manipulation data.
pub const UNUSABLE_POSITION_SIGMA_M: f64 = 0.1;
/// Fusion residuals of the front or rear observations above this 95th percentile (m) mean the
/// maps, placement or calibration disagree with the IMU: suspect.
pub const SUSPECT_RESIDUAL_P95_M: f64 = 0.02;
/// Placement inlier fraction below this: the front map sits in the scene on a minority of
/// pairs, so the placement is doubtful.
pub const SUSPECT_PLACEMENT_INLIER_FRACTION: f64 = 0.5;
/// Gripper openings measured on fewer than this fraction of frames are suspect.
pub const SUSPECT_GRIPPER_FRACTION: f64 = 0.9;
/// A head track posed on less than this fraction of the episode is suspect: the operator's
/// head was out of both rear views (or the marker unreadable) most of the time.
pub const SUSPECT_HEAD_TRACKED_FRACTION: f64 = 0.5;
/// A head track whose median position sigma exceeds this (m) is suspect: the head-pose accuracy
/// target (1 cm).
pub const SUSPECT_HEAD_SIGMA_P_M: f64 = 0.01;
/// ... or whose median rotation sigma exceeds this (rad): the target (1°). A hat marker that
/// spans too few pixels (rear lenses below 960 px) scatters its rotation by degrees.
pub const SUSPECT_HEAD_SIGMA_R_RAD: f64 = 0.017_453_292_519_943_295;

/// The thresholds, as recorded in every `quality.json`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Thresholds {
    /// [`SUSPECT_SUPPORTED_FRACTION`].
    pub suspect_supported_fraction: f64,
    /// [`UNUSABLE_SUPPORTED_FRACTION`].
    pub unusable_supported_fraction: f64,
    /// [`SUSPECT_UNSUPPORTED_RUN_S`].
    pub suspect_unsupported_run_s: f64,
    /// [`UNUSABLE_UNSUPPORTED_RUN_S`].
    pub unusable_unsupported_run_s: f64,
    /// [`SUSPECT_POSITION_SIGMA_M`].
    pub suspect_position_sigma_m: f64,
    /// [`UNUSABLE_POSITION_SIGMA_M`].
    pub unusable_position_sigma_m: f64,
    /// [`SUSPECT_RESIDUAL_P95_M`].
    pub suspect_residual_p95_m: f64,
    /// [`SUSPECT_PLACEMENT_INLIER_FRACTION`].
    pub suspect_placement_inlier_fraction: f64,
    /// [`SUSPECT_GRIPPER_FRACTION`].
    pub suspect_gripper_fraction: f64,
    /// [`SUSPECT_HEAD_TRACKED_FRACTION`].
    #[serde(default = "default_head_fraction")]
    pub suspect_head_tracked_fraction: f64,
    /// [`SUSPECT_HEAD_SIGMA_P_M`].
    #[serde(default = "default_head_sigma_p")]
    pub suspect_head_sigma_p_m: f64,
    /// [`SUSPECT_HEAD_SIGMA_R_RAD`].
    #[serde(default = "default_head_sigma_r")]
    pub suspect_head_sigma_r_rad: f64,
}

fn default_head_fraction() -> f64 {
    SUSPECT_HEAD_TRACKED_FRACTION
}

fn default_head_sigma_p() -> f64 {
    SUSPECT_HEAD_SIGMA_P_M
}

fn default_head_sigma_r() -> f64 {
    SUSPECT_HEAD_SIGMA_R_RAD
}

impl Default for Thresholds {
    fn default() -> Self {
        Self {
            suspect_supported_fraction: SUSPECT_SUPPORTED_FRACTION,
            unusable_supported_fraction: UNUSABLE_SUPPORTED_FRACTION,
            suspect_unsupported_run_s: SUSPECT_UNSUPPORTED_RUN_S,
            unusable_unsupported_run_s: UNUSABLE_UNSUPPORTED_RUN_S,
            suspect_position_sigma_m: SUSPECT_POSITION_SIGMA_M,
            unusable_position_sigma_m: UNUSABLE_POSITION_SIGMA_M,
            suspect_residual_p95_m: SUSPECT_RESIDUAL_P95_M,
            suspect_placement_inlier_fraction: SUSPECT_PLACEMENT_INLIER_FRACTION,
            suspect_gripper_fraction: SUSPECT_GRIPPER_FRACTION,
            suspect_head_tracked_fraction: SUSPECT_HEAD_TRACKED_FRACTION,
            suspect_head_sigma_p_m: SUSPECT_HEAD_SIGMA_P_M,
            suspect_head_sigma_r_rad: SUSPECT_HEAD_SIGMA_R_RAD,
        }
    }
}

/// A verdict being assembled: the worst finding wins, every finding is a reason.
#[derive(Debug, Clone, Default)]
pub struct VerdictBuilder {
    worst: Option<Verdict>,
    reasons: Vec<String>,
}

impl VerdictBuilder {
    /// Record a finding that makes the episode at best `level`.
    pub fn add(&mut self, level: Verdict, reason: impl Into<String>) {
        self.worst = Some(self.worst.map_or(level, |w| w.max(level)));
        self.reasons
            .push(format!("{}: {}", level.as_str(), reason.into()));
    }

    /// Grade a value where larger is worse.
    pub fn check_at_most(&mut self, what: &str, value: f64, suspect: f64, unusable: f64) {
        if value > unusable {
            self.add(Verdict::Unusable, format!("{what} {value:.4} > {unusable}"));
        } else if value > suspect {
            self.add(Verdict::Suspect, format!("{what} {value:.4} > {suspect}"));
        }
    }

    /// Grade a value where smaller is worse.
    pub fn check_at_least(&mut self, what: &str, value: f64, suspect: f64, unusable: f64) {
        if value < unusable {
            self.add(Verdict::Unusable, format!("{what} {value:.4} < {unusable}"));
        } else if value < suspect {
            self.add(Verdict::Suspect, format!("{what} {value:.4} < {suspect}"));
        }
    }

    /// The verdict and its reasons.
    pub fn finish(self) -> (Verdict, Vec<String>) {
        (self.worst.unwrap_or(Verdict::Usable), self.reasons)
    }
}

/// A lost-frame reason with its numbers replaced by `#`, so that reasons group:
/// `inlier ratio 0.39 < 0.50` → `inlier ratio # < #`.
pub fn reason_class(reason: &str) -> String {
    let mut out = String::with_capacity(reason.len());
    let mut in_number = false;
    for c in reason.chars() {
        if c.is_ascii_digit() || (in_number && c == '.') {
            if !in_number {
                out.push('#');
                in_number = true;
            }
        } else {
            in_number = false;
            out.push(c);
        }
    }
    out
}

/// `<name> has a pose at <n> of <m> frames`, and when frames were lost, how many were lost for
/// the commonest reason and that reason (up to its first `;`).
pub fn describe_outcome(name: &str, record: &crate::outputs::LocalizationRecord) -> String {
    let mut text = format!(
        "{name} has a pose at {} of {} frames",
        record.localized, record.frames
    );
    // `max_by_key` keeps the last of equals: reversed, the first reason in order among them.
    let commonest = record.lost_reasons.iter().rev().max_by_key(|(_, n)| **n);
    if let Some((why, n)) = commonest {
        let lost = record.frames.saturating_sub(record.localized);
        let short = why.split(';').next().unwrap_or(why).trim();
        text += &format!(" ({lost} lost; {n} of them: \"{short}\")");
    }
    text
}

/// Length (s) of the longest run of consecutive unsupported frames, measured from the last
/// supported frame before the run to the first one after it (or the stream's ends).
pub fn longest_unsupported_run(times: &[f64], supported: &[bool]) -> f64 {
    let mut longest: f64 = 0.0;
    let mut start: Option<usize> = None;
    for (k, &s) in supported.iter().enumerate() {
        match (s, start) {
            (false, None) => start = Some(k),
            (true, Some(a)) => {
                let from = if a > 0 { times[a - 1] } else { times[a] };
                longest = longest.max(times[k] - from);
                start = None;
            }
            _ => {}
        }
    }
    if let (Some(a), Some(&last)) = (start, times.last()) {
        let from = if a > 0 { times[a - 1] } else { times[a] };
        longest = longest.max(last - from);
    }
    longest
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reasons_group_without_their_numbers() {
        assert_eq!(
            reason_class("inlier ratio 0.39 < 0.50"),
            "inlier ratio # < #"
        );
        assert_eq!(
            reason_class("keyframe 110: no pose with 45 inliers"),
            "keyframe #: no pose with # inliers"
        );
    }

    /// A stage that had too little to work with says how much of the lens had a pose and why
    /// the rest was lost.
    #[test]
    fn a_lens_outcome_names_the_commonest_reason() {
        let mut record = crate::outputs::LocalizationRecord {
            frames: 689,
            localized: 0,
            ..Default::default()
        };
        assert_eq!(
            describe_outcome("the right rear lens", &record),
            "the right rear lens has a pose at 0 of 689 frames"
        );
        record.lost_reasons.insert(
            "tracking: position poorly constrained: σ #% > #%".into(),
            26,
        );
        record.lost_reasons.insert(
            "withdrawn: the run that began at frame # does not join the stream's other poses; \
             frames # and # are # map depths apart"
                .into(),
            663,
        );
        assert_eq!(
            describe_outcome("the right rear lens", &record),
            "the right rear lens has a pose at 0 of 689 frames (689 lost; 663 of them: \
             \"withdrawn: the run that began at frame # does not join the stream's other poses\")"
        );
    }

    #[test]
    fn the_longest_gap_spans_from_the_last_supported_frame() {
        let t: Vec<f64> = (0..10).map(f64::from).collect();
        let s = [
            true, true, false, false, false, true, true, false, true, true,
        ];
        assert!((longest_unsupported_run(&t, &s) - 4.0).abs() < 1e-12);
        assert_eq!(longest_unsupported_run(&t, &[true; 10]), 0.0);
    }

    #[test]
    fn the_worst_finding_decides() {
        let mut v = VerdictBuilder::default();
        v.check_at_least("supported", 0.995, 0.99, 0.8);
        assert_eq!(v.clone().finish().0, Verdict::Usable);
        v.check_at_most("gap", 1.0, 0.5, 5.0);
        v.check_at_least("supported", 0.5, 0.99, 0.8);
        let (verdict, reasons) = v.finish();
        assert_eq!(verdict, Verdict::Unusable);
        assert_eq!(reasons.len(), 2);
    }
}
