//! The map-sharing ablation (paper §5, `tab:eval-map-sharing`): on the right wrist's front
//! frames of each episode (the frames of its published trajectory), the share a front-only
//! system supports — the right front lens localized in the left wrist's front map, cross-hand,
//! with no shared rear map — against the share KIWI's outputs support (a front, rear or
//! interpolated rear observation at the frame).

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use kiwi_core::layout::Side;

use crate::error::{BackendError, Result};
use crate::outputs::{SupportClass, read_quality};
use crate::pipeline::SessionContext;
use crate::pipeline::graph::{MapName, StageKind, id_of};
use crate::pipeline::stages::{MAP_FILE, PUBLISHED_DIR};
use crate::vision::episode::{LensStream, localize_stream};
use crate::vision::localize::{LocalizationStatus, LocalizerOptions};
use crate::vision::map::VisualMap;

/// The outputs keep frame times to the microsecond: a localization and an output row closer
/// than this are the same frame (s).
const FRAME_MATCH_S: f64 = 2e-6;

/// File of the ablation's record in the session's `evaluation/`.
pub const ABLATION_FILE: &str = "ablation.json";

/// One episode's row of the table.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AblationEpisode {
    /// Episode name.
    pub episode: String,
    /// Query frames: the right wrist's front frames in the episode's outputs.
    pub frames: usize,
    /// Of those, localized in the left front map (front-only, cross-hand).
    pub cross_hand_supported: usize,
    /// Of those, supported in KIWI's outputs.
    pub kiwi_supported: usize,
    /// Why the cross-hand localizations of the other frames failed (figures as `#`), with
    /// counts.
    pub cross_hand_lost: BTreeMap<String, usize>,
    /// The right wrist's supported fraction in the episode's `quality.json`.
    pub reported_fraction: f64,
}

impl AblationEpisode {
    /// Share of the query frames the front-only system supports.
    pub fn cross_hand_fraction(&self) -> f64 {
        self.cross_hand_supported as f64 / self.frames.max(1) as f64
    }

    /// Share of the query frames KIWI supports.
    pub fn kiwi_fraction(&self) -> f64 {
        self.kiwi_supported as f64 / self.frames.max(1) as f64
    }
}

/// The ablation of a session.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AblationReport {
    /// The map the query frames were localized in.
    pub map: String,
    /// Episodes evaluated.
    pub episodes: Vec<AblationEpisode>,
    /// Episodes left out, each with the reason.
    pub skipped: BTreeMap<String, String>,
    /// Query frames over all episodes.
    pub frames: usize,
    /// Of those, supported front-only.
    pub cross_hand_supported: usize,
    /// Of those, supported by KIWI.
    pub kiwi_supported: usize,
}

fn input(path: &std::path::Path, message: String) -> BackendError {
    BackendError::Input {
        path: path.to_path_buf(),
        message,
    }
}

/// Run the ablation on `episodes` of the session (each needs its outputs from `kiwi run`);
/// `progress(episode, done, total)` reports the cross-hand localization.
pub fn ablation(
    ctx: &SessionContext,
    episodes: &[String],
    progress: &mut dyn FnMut(&str, usize, usize),
) -> Result<AblationReport> {
    let (Some(_), Some(right)) = (ctx.wrists.get(&Side::Left), ctx.wrists.get(&Side::Right)) else {
        return Err(input(
            &ctx.toml,
            "the ablation localizes the right front lens in the left front map: the session \
             needs both [wrists.left] and [wrists.right]"
                .into(),
        ));
    };
    let map_path = id_of(&StageKind::Map {
        map: MapName::Front(Side::Left),
    })
    .dir(&ctx.root)
    .join(MAP_FILE);
    if !map_path.is_file() {
        return Err(input(
            &map_path,
            "missing: the left front map is built by `kiwi run` on the session; run it first"
                .into(),
        ));
    }
    let map = VisualMap::load(&map_path)?;
    let mut report = AblationReport {
        map: ctx.relative(&map_path),
        episodes: Vec::new(),
        skipped: BTreeMap::new(),
        frames: 0,
        cross_hand_supported: 0,
        kiwi_supported: 0,
    };
    for episode in episodes {
        let layout = ctx.episode(episode);
        let out = layout.root().join(PUBLISHED_DIR);
        let trajectory = out.join(format!("{}.csv", right.camera));
        let quality = out.join("quality.json");
        if !trajectory.is_file() || !quality.is_file() {
            report.skipped.insert(
                episode.clone(),
                format!(
                    "no outputs ({} missing): the episode was not reconstructed; see its \
                     quality.json or run `kiwi run`",
                    ctx.relative(&trajectory)
                ),
            );
            continue;
        }
        let reported_fraction = read_quality(&quality)?
            .wrists
            .get(right.camera)
            .map(|w| w.supported_fraction)
            .ok_or_else(|| {
                input(
                    &quality,
                    format!(
                        "has no `wrists.{}` section: re-run `kiwi run --force outputs`",
                        right.camera
                    ),
                )
            })?;
        let rows = crate::export::read_trajectory(&trajectory)?;
        let stream = LensStream::open(
            layout.root(),
            right.camera,
            "front",
            Some(&right.calibration_path),
            None,
        )?;
        let (localized, _) = localize_stream(
            &map,
            &stream,
            &LocalizerOptions::default(),
            &mut |done, total| progress(episode, done, total),
        )?;
        let mut row = AblationEpisode {
            episode: episode.clone(),
            frames: rows.len(),
            cross_hand_supported: 0,
            kiwi_supported: 0,
            cross_hand_lost: BTreeMap::new(),
            reported_fraction,
        };
        for r in &rows {
            row.kiwi_supported += usize::from(r.support != SupportClass::ImuOnly);
            let k = localized.partition_point(|l| l.t < r.t_camera - FRAME_MATCH_S);
            match localized
                .get(k)
                .filter(|l| (l.t - r.t_camera).abs() <= FRAME_MATCH_S)
            {
                Some(l) if l.status != LocalizationStatus::Lost => {
                    row.cross_hand_supported += 1;
                }
                Some(l) => {
                    *row.cross_hand_lost
                        .entry(reason_kind(&l.reason))
                        .or_insert(0) += 1;
                }
                None => {
                    *row.cross_hand_lost
                        .entry("the frame is not in the front stream".into())
                        .or_insert(0) += 1;
                }
            }
        }
        report.frames += row.frames;
        report.cross_hand_supported += row.cross_hand_supported;
        report.kiwi_supported += row.kiwi_supported;
        report.episodes.push(row);
    }
    Ok(report)
}

/// A lost frame's reason with its figures replaced by `#`, so that frames lost for one reason
/// count together.
fn reason_kind(reason: &str) -> String {
    let mut out = String::with_capacity(reason.len());
    let mut in_number = false;
    for c in reason.chars() {
        let numeric = c.is_ascii_digit() || (in_number && c == '.');
        if numeric {
            if !in_number {
                out.push('#');
            }
        } else {
            out.push(c);
        }
        in_number = numeric;
    }
    out
}

/// The table as text: per episode and in total, frames and both systems' supported shares.
pub fn table(report: &AblationReport) -> String {
    use std::fmt::Write as _;
    let pct = |n: usize, d: usize| 100.0 * n as f64 / d.max(1) as f64;
    let mut s = format!(
        "right front frames: front-only cross-hand (right front in {}) vs KIWI\n\
         {:<16} {:>8} {:>12} {:>12} {:>12}\n",
        report.map, "episode", "frames", "front-only", "KIWI", "unsupported"
    );
    for e in &report.episodes {
        let _ = writeln!(
            s,
            "{:<16} {:>8} {:>11.1}% {:>11.1}% {:>11.1}%",
            e.episode,
            e.frames,
            pct(e.cross_hand_supported, e.frames),
            pct(e.kiwi_supported, e.frames),
            100.0 - pct(e.cross_hand_supported, e.frames)
        );
    }
    let _ = writeln!(
        s,
        "{:<16} {:>8} {:>11.1}% {:>11.1}% {:>11.1}%",
        "total",
        report.frames,
        pct(report.cross_hand_supported, report.frames),
        pct(report.kiwi_supported, report.frames),
        100.0 - pct(report.cross_hand_supported, report.frames)
    );
    for (episode, why) in &report.skipped {
        let _ = writeln!(s, "{episode}: left out: {why}");
    }
    s
}

#[cfg(test)]
mod tests {
    use super::reason_kind;

    #[test]
    fn reasons_count_together_whatever_their_figures() {
        assert_eq!(
            reason_kind("keyframe 110: no pose with 45 inliers, ratio 0.39 < 0.50"),
            "keyframe #: no pose with # inliers, ratio # < #"
        );
        assert_eq!(reason_kind("lost."), "lost.");
    }
}
