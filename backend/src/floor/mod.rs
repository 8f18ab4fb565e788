//! The floor reference (paper §4.3.3, eq. 6): short windows of a wrist's front video that look
//! down while the camera moves sideways; in each, a photometric plane sweep ([`sweep`]) and
//! rectified motion stereo ([`stereo`]) propose horizontal surfaces, each channel picks the
//! lowest well-supported one inside the camera-to-floor band, agreeing channels are combined
//! and conflicting ones reject the window; windows that stray from their neighbours are
//! rejected, and a weighted median over both wrists gives the episode's floor height. The other
//! supported surfaces (a table) are reported beside it.

pub mod figure;
pub mod stereo;
pub mod sweep;
pub mod view;

use serde::{Deserialize, Serialize};

use kiwi_core::camera::{Camera, CameraModel};
use kiwi_core::geometry::Pose;
use kiwi_core::layout::Side;

use crate::error::Result;
use crate::frames::FrameSource;
use crate::fusion::FusedNode;
use crate::head::episode::imu_pose_at;
use crate::sync::CameraClock;

use stereo::{StereoOptions, stereo};
use sweep::{SweepOptions, sweep};
use view::{PosedView, Surface};

/// How the floor is sought.
#[derive(Debug, Clone, Copy, Serialize, Deserialize)]
pub struct FloorOptions {
    /// Camera-to-floor heights the floor may be at (m): the lowest supported surface inside
    /// is the floor.
    pub camera_height_m: [f64; 2],
    /// Length of a window of front video (s).
    pub window_s: f64,
    /// Most windows per wrist (spread over the episode; bounds the cost).
    pub max_windows: usize,
    /// The plane sweep channel.
    pub sweep: SweepOptions,
    /// The motion stereo channel.
    pub stereo: StereoOptions,
}

impl Default for FloorOptions {
    fn default() -> Self {
        Self {
            camera_height_m: DEFAULT_CAMERA_HEIGHT_M,
            window_s: 1.0,
            max_windows: 16,
            sweep: SweepOptions::default(),
            stereo: StereoOptions::default(),
        }
    }
}

/// Default camera-to-floor band (m): a standing operator's wrist from a low reach to arms
/// raised. The lower bound keeps out a worktop the wrist works over (0.15-0.45 m below it);
/// a session that works near the floor configures its own band.
pub const DEFAULT_CAMERA_HEIGHT_M: [f64; 2] = [0.5, 2.2];
/// A window needs this share of its reference frame's directions looking within the sweep's
/// nadir angle (a frame looking level or up sees the floor only at grazing angles).
const MIN_DOWNWARD_SHARE: f64 = 0.1;
/// Frames whose camera moved less than this sideways from the reference give no depth (m).
const MIN_BASELINE_M: f64 = 0.03;
/// Baseline sought for the stereo pair (m): wide enough for sub-centimetre heights at 1 m,
/// short enough that the two views still overlap on the ground.
const STEREO_BASELINE_M: f64 = 0.12;
/// Other frames the sweep compares with the reference.
const SWEEP_VIEWS: usize = 4;
/// Two channels agree when their floors are this close, or within three joint sigmas (m).
const CHANNELS_AGREE_M: f64 = 0.02;
/// A channel's height sigma is at least this (m): the votes' spread understates the model's
/// own error (calibration, pose).
const MIN_SIGMA_M: f64 = 0.002;
/// A window strays when its floor is this far from the median of its neighbours (m).
const OUTLIER_M: f64 = 0.03;
/// Neighbours on each side a window's floor is compared with.
const NEIGHBOURS: usize = 3;
/// Surfaces of different windows within this of each other are one surface (m).
const SURFACE_CLUSTER_M: f64 = 0.03;
/// A surface above the floor is reported when this share of the accepted windows saw it.
const MIN_SURFACE_WINDOWS_SHARE: f64 = 0.2;
/// Surfaces closer than this above the floor are the floor itself (m).
const MIN_ABOVE_FLOOR_M: f64 = 0.05;
/// The floor is the lowest height that at least this share of the windows with a candidate
/// found: a wrist over a table may see the floor in only a few windows, while a single
/// window's low surface is not evidence enough.
const MIN_FLOOR_WINDOWS_SHARE: f64 = 0.2;
/// Heights of different windows within this of a level's centre belong to it (m): the
/// windows' own spread, and less than the smallest object on a table is tall.
const LEVEL_HALF_WIDTH_M: f64 = 0.02;
/// The floor needs at least this many windows too (unless only one window had a candidate).
const MIN_FLOOR_WINDOWS: usize = 2;

/// A wrist's front lens on its fused trajectory.
#[derive(Debug, Clone, Copy)]
pub struct FrontLens<'a> {
    /// Which wrist.
    pub side: Side,
    /// Fused nodes in time order (IMU clock).
    pub nodes: &'a [FusedNode],
    /// The front lens's `cam_from_imu`.
    pub cam_from_imu: Pose,
    /// The front lens's frame time shift to the IMU clock (s).
    pub time_shift_s: f64,
    /// Rolling readout of the recording mode (s; 0 for a global shutter).
    pub readout_s: f64,
    /// The lens model.
    pub camera: &'a Camera,
    /// The wrist camera's clock on the session timeline.
    pub clock: Option<&'a CameraClock>,
}

impl FrontLens<'_> {
    /// `scene_from_cam` of a frame taken at camera time `t` at row fraction `row`.
    fn pose(&self, t: f64, row: f64) -> Option<Pose> {
        let imu = imu_pose_at(self.nodes, t + self.time_shift_s + self.readout_s * row)?;
        Some(imu * self.cam_from_imu.inverse())
    }
}

/// What became of a window.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum WindowStatus {
    /// It gave a floor height.
    Accepted,
    /// Neither channel found a supported surface in the band.
    NoSurface,
    /// The two channels found different floors.
    Conflict,
    /// Its floor strayed from its neighbours', or lay below the episode's floor.
    Outlier,
    /// It saw only surfaces above the episode's floor (a table filled its view).
    AboveFloor,
}

/// One window's result.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct WindowEstimate {
    /// Which wrist.
    pub side: Side,
    /// Reference frame index.
    pub frame: usize,
    /// Its time on the camera clock (s).
    pub t_camera: f64,
    /// Its time on the session timeline (s), when the camera is on it.
    pub t_session: Option<f64>,
    /// The reference camera's scene height (m).
    pub camera_z_m: f64,
    /// Sideways baseline of the widest frame compared (m).
    pub baseline_m: f64,
    /// The sweep's surfaces, lowest first.
    pub sweep: Vec<Surface>,
    /// The stereo pair's surfaces, lowest first.
    pub stereo: Vec<Surface>,
    /// The sweep's support per camera-to-plane distance (m, share), for the figure.
    #[serde(skip)]
    pub sweep_support: Vec<[f64; 2]>,
    /// The window's floor height (scene z, m) and its sigma, when accepted.
    pub floor_z_m: Option<f64>,
    /// Sigma of `floor_z_m` (m).
    pub sigma_m: Option<f64>,
    /// What became of it.
    pub status: WindowStatus,
}

/// Why a wrist's windows were too few.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct WindowCounts {
    /// Windows the episode has.
    pub windows: usize,
    /// Of those, without a fused pose.
    pub unposed: usize,
    /// Not looking down.
    pub not_looking_down: usize,
    /// Without sideways motion.
    pub no_baseline: usize,
    /// Swept (the others beyond the window budget were skipped).
    pub swept: usize,
}

/// A window of frames chosen for the channels.
struct Window {
    reference: usize,
    sweep_views: Vec<usize>,
    stereo_view: usize,
    baseline_m: f64,
}

/// Share of the lens's directions (on a coarse pixel grid) within `max_nadir` of straight down
/// from `scene_from_cam`.
fn downward_share(camera: &Camera, scene_from_cam: &Pose, max_nadir: f64) -> f64 {
    const GRID: u32 = 16;
    let (w, h) = camera.resolution();
    let (mut inside, mut down) = (0usize, 0usize);
    for j in 0..GRID {
        for i in 0..GRID {
            let p = nalgebra::Point2::new(
                (f64::from(i) + 0.5) * f64::from(w) / f64::from(GRID),
                (f64::from(j) + 0.5) * f64::from(h) / f64::from(GRID),
            );
            if let Some(b) = camera.unproject(&p) {
                inside += 1;
                if (scene_from_cam.rotation * b.into_inner()).z < -max_nadir.cos() {
                    down += 1;
                }
            }
        }
    }
    down as f64 / inside.max(1) as f64
}

/// The windows of a wrist's front stream worth sweeping, at most `max_windows` spread evenly.
fn choose_windows(
    lens: &FrontLens<'_>,
    times: &[f64],
    o: &FloorOptions,
    counts: &mut WindowCounts,
) -> Vec<Window> {
    let mut out = Vec::new();
    let mut start = 0;
    while start < times.len() {
        let end = times.partition_point(|&t| t < times[start] + o.window_s);
        let frames: Vec<usize> = (start..end.max(start + 1)).collect();
        start = end.max(start + 1);
        counts.windows += 1;
        let reference = frames[frames.len() / 2];
        let centre = |i: usize| lens.pose(times[i], 0.5);
        let Some(ref_pose) = centre(reference) else {
            counts.unposed += 1;
            continue;
        };
        if downward_share(lens.camera, &ref_pose, o.sweep.max_nadir_rad) < MIN_DOWNWARD_SHARE {
            counts.not_looking_down += 1;
            continue;
        }
        let moved: Vec<(usize, f64)> = frames
            .iter()
            .filter(|&&i| i != reference)
            .filter_map(|&i| {
                let p = centre(i)?;
                let b = (p.translation.vector - ref_pose.translation.vector)
                    .xy()
                    .norm();
                (b >= MIN_BASELINE_M).then_some((i, b))
            })
            .collect();
        if moved.len() < 2 {
            counts.no_baseline += 1;
            continue;
        }
        let sweep_views: Vec<usize> = if moved.len() <= SWEEP_VIEWS {
            moved.iter().map(|m| m.0).collect()
        } else {
            (0..SWEEP_VIEWS)
                .map(|k| moved[k * (moved.len() - 1) / (SWEEP_VIEWS - 1)].0)
                .collect()
        };
        let Some(&(stereo_view, _)) = moved.iter().min_by(|a, b| {
            (a.1 - STEREO_BASELINE_M)
                .abs()
                .total_cmp(&(b.1 - STEREO_BASELINE_M).abs())
        }) else {
            continue;
        };
        let baseline_m = moved.iter().map(|m| m.1).fold(0.0, f64::max);
        out.push(Window {
            reference,
            sweep_views,
            stereo_view,
            baseline_m,
        });
    }
    if out.len() > o.max_windows {
        let n = out.len();
        let keep: Vec<usize> = (0..o.max_windows)
            .map(|k| (2 * k + 1) * n / (2 * o.max_windows))
            .collect();
        out = out
            .into_iter()
            .enumerate()
            .filter(|(i, _)| keep.contains(i))
            .map(|(_, w)| w)
            .collect();
    }
    counts.swept = out.len();
    out
}

/// The lowest surface of a channel inside the camera-to-floor band.
fn floor_of(surfaces: &[Surface], band: [f64; 2]) -> Option<Surface> {
    surfaces
        .iter()
        .find(|s| s.depth_m >= band[0] && s.depth_m <= band[1])
        .copied()
}

/// Combine the channels' floors: agreeing ones by inverse variance, a single one as it is.
fn combine(
    a: Option<Surface>,
    b: Option<Surface>,
) -> std::result::Result<(f64, f64), WindowStatus> {
    let sigma = |s: &Surface| s.sigma_m.max(MIN_SIGMA_M);
    match (a, b) {
        (None, None) => Err(WindowStatus::NoSurface),
        (Some(s), None) | (None, Some(s)) => Ok((s.z_m, sigma(&s))),
        (Some(s), Some(t)) => {
            let (vs, vt) = (sigma(&s).powi(2), sigma(&t).powi(2));
            if (s.z_m - t.z_m).abs() > CHANNELS_AGREE_M.max(3.0 * (vs + vt).sqrt()) {
                return Err(WindowStatus::Conflict);
            }
            let (ws, wt) = (1.0 / vs, 1.0 / vt);
            Ok((
                (ws * s.z_m + wt * t.z_m) / (ws + wt),
                (1.0 / (ws + wt)).sqrt(),
            ))
        }
    }
}

/// Sweep and match a wrist's windows; `tick(done, total)` reports progress.
pub fn wrist_windows(
    source: &FrameSource,
    lens: &FrontLens<'_>,
    o: &FloorOptions,
    tick: &dyn Fn(usize, usize),
) -> Result<(Vec<WindowEstimate>, WindowCounts)> {
    let times: Vec<f64> = source.frames().iter().map(|f| f.t).collect();
    let mut counts = WindowCounts::default();
    let windows = choose_windows(lens, &times, o, &mut counts);
    let mut out = Vec::with_capacity(windows.len());
    for (k, w) in windows.iter().enumerate() {
        tick(k, windows.len());
        let mut indices: Vec<usize> = w.sweep_views.clone();
        indices.push(w.reference);
        indices.push(w.stereo_view);
        indices.sort_unstable();
        indices.dedup();
        let mut images = std::collections::BTreeMap::new();
        for &i in &indices {
            images.insert(i, source.load_gray(i)?);
        }
        let view = |i: usize| -> Option<PosedView<'_>> {
            let t = times[i];
            PosedView::new(images.get(&i)?, lens.camera, |row| lens.pose(t, row))
        };
        let (Some(reference), Some(pair)) = (view(w.reference), view(w.stereo_view)) else {
            // A gap in the trajectory during one of the two frames' readout.
            counts.unposed += 1;
            counts.swept -= 1;
            continue;
        };
        let others: Vec<PosedView<'_>> = w.sweep_views.iter().filter_map(|&i| view(i)).collect();
        let swept = sweep(&reference, &others, &o.sweep);
        let matched = stereo(&reference, &pair, &o.stereo)?;
        let stereo_surfaces = matched.map(|m| m.surfaces).unwrap_or_default();
        let band = o.camera_height_m;
        let combined = combine(
            floor_of(&swept.surfaces, band),
            floor_of(&stereo_surfaces, band),
        );
        let (floor_z_m, sigma_m, status) = match combined {
            Ok((z, s)) => (Some(z), Some(s), WindowStatus::Accepted),
            Err(status) => (None, None, status),
        };
        out.push(WindowEstimate {
            side: lens.side,
            frame: w.reference,
            t_camera: times[w.reference],
            t_session: crate::outputs::session_time(lens.clock, times[w.reference]),
            camera_z_m: reference.middle().translation.vector.z,
            baseline_m: w.baseline_m,
            sweep_support: swept.votes.support_curve(),
            sweep: swept.surfaces,
            stereo: stereo_surfaces,
            floor_z_m,
            sigma_m,
            status,
        });
    }
    tick(windows.len(), windows.len());
    reject_strays(&mut out);
    Ok((out, counts))
}

/// Temporal outlier rejection: a window whose floor is more than [`OUTLIER_M`] from most of its
/// accepted neighbours' (up to [`NEIGHBOURS`] on each side, at least two) is rejected. Agreeing
/// with half of them is enough: two neighbours that disagree with each other say nothing.
fn reject_strays(windows: &mut [WindowEstimate]) {
    let accepted: Vec<(usize, f64)> = windows
        .iter()
        .enumerate()
        .filter_map(|(i, w)| w.floor_z_m.map(|z| (i, z)))
        .collect();
    let mut strays = Vec::new();
    for (k, &(i, z)) in accepted.iter().enumerate() {
        let lo = k.saturating_sub(NEIGHBOURS);
        let hi = (k + NEIGHBOURS + 1).min(accepted.len());
        let near: Vec<f64> = accepted[lo..hi]
            .iter()
            .filter(|(j, _)| *j != i)
            .map(|(_, z)| *z)
            .collect();
        if near.len() < 2 {
            continue;
        }
        let agreeing = near.iter().filter(|n| (z - *n).abs() <= OUTLIER_M).count();
        if 2 * agreeing < near.len() {
            strays.push(i);
        }
    }
    for i in strays {
        let w = &mut windows[i];
        w.status = WindowStatus::Outlier;
    }
}

/// Each channel's floor candidate of a window (the lowest surface in the band), when the window
/// is neither without a surface nor a temporal stray.
fn candidates(w: &WindowEstimate, band: [f64; 2]) -> [Option<Surface>; 2] {
    if matches!(w.status, WindowStatus::NoSurface | WindowStatus::Outlier) {
        return [None, None];
    }
    [floor_of(&w.sweep, band), floor_of(&w.stereo, band)]
}

/// Heights found by windows: one per window and level, with the window's index.
type WindowHeights = Vec<(f64, usize)>;

/// The heights within [`LEVEL_HALF_WIDTH_M`] of `z`, and how many distinct windows found them.
fn level_members(heights: &WindowHeights, z: f64) -> (Vec<f64>, usize) {
    let near: Vec<&(f64, usize)> = heights
        .iter()
        .filter(|h| (h.0 - z).abs() <= LEVEL_HALF_WIDTH_M)
        .collect();
    let mut seen: Vec<usize> = near.iter().map(|h| h.1).collect();
    seen.sort_unstable();
    seen.dedup();
    (near.iter().map(|h| h.0).collect(), seen.len())
}

/// The centre of the level around `z`: the median of its members, taken twice so a seed at the
/// level's edge moves to its middle.
fn level_centre(heights: &WindowHeights, z: f64) -> f64 {
    let mut centre = z;
    for _ in 0..2 {
        let (mut members, _) = level_members(heights, centre);
        if members.is_empty() {
            break;
        }
        centre = view::median_mad(&mut members).0;
    }
    centre
}

/// One height per window and level from `surfaces` of each window (levels closer than
/// [`SURFACE_CLUSTER_M`] within a window count once, the first given wins), and how many
/// windows gave any.
fn window_heights<'a, I>(per_window: impl Iterator<Item = (usize, I)>) -> (WindowHeights, usize)
where
    I: Iterator<Item = &'a Surface>,
{
    let mut heights = Vec::new();
    let mut windows = 0;
    for (i, surfaces) in per_window {
        let mut mine: Vec<f64> = Vec::new();
        for s in surfaces {
            if mine.iter().all(|m| (m - s.z_m).abs() > SURFACE_CLUSTER_M) {
                mine.push(s.z_m);
            }
        }
        windows += usize::from(!mine.is_empty());
        heights.extend(mine.into_iter().map(|z| (z, i)));
    }
    heights.sort_by(|a, b| a.0.total_cmp(&b.0));
    (heights, windows)
}

/// The episode's floor level by consensus: the windows' candidates (both channels', one height
/// per window and level); the lowest height that enough windows found within
/// [`LEVEL_HALF_WIDTH_M`] ([`MIN_FLOOR_WINDOWS_SHARE`], [`MIN_FLOOR_WINDOWS`]) is the floor.
/// Its centre, or `None` when no level is found by enough windows.
fn floor_level(windows: &[WindowEstimate], band: [f64; 2]) -> Option<f64> {
    let per_window: Vec<(usize, [Option<Surface>; 2])> = windows
        .iter()
        .enumerate()
        .map(|(i, w)| (i, candidates(w, band)))
        .collect();
    let (heights, with_candidate) =
        window_heights(per_window.iter().map(|(i, c)| (*i, c.iter().flatten())));
    let needed = if with_candidate == 1 {
        1
    } else {
        ((with_candidate as f64 * MIN_FLOOR_WINDOWS_SHARE).ceil() as usize).max(MIN_FLOOR_WINDOWS)
    };
    heights
        .iter()
        .find(|h| level_members(&heights, h.0).1 >= needed)
        .map(|h| level_centre(&heights, h.0))
}

/// Re-judge every window against the episode's floor level: the channels whose candidate lies
/// within [`OUTLIER_M`] of it are combined (a channel that saw only the table no longer
/// conflicts with one that saw the floor); a window without one there saw only surfaces above
/// the floor (some too near the camera to be a candidate at all), or a spurious one below it.
/// Temporal strays stay rejected.
fn judge(windows: &mut [WindowEstimate], level: f64, band: [f64; 2]) {
    for w in windows.iter_mut() {
        if w.status == WindowStatus::Outlier {
            continue;
        }
        let [a, b] = candidates(w, band);
        let near = |s: Option<Surface>| s.filter(|s| (s.z_m - level).abs() <= OUTLIER_M);
        if let Ok((z, sigma)) = combine(near(a), near(b)) {
            w.floor_z_m = Some(z);
            w.sigma_m = Some(sigma);
            w.status = WindowStatus::Accepted;
            continue;
        }
        let mut seen = w.sweep.iter().chain(&w.stereo).peekable();
        if seen.peek().is_none() {
            continue;
        }
        let above = seen.all(|s| s.z_m - level >= MIN_ABOVE_FLOOR_M);
        w.floor_z_m = None;
        w.sigma_m = None;
        w.status = if above {
            WindowStatus::AboveFloor
        } else if a.is_some() || b.is_some() {
            WindowStatus::Outlier
        } else {
            w.status
        };
    }
}

/// A horizontal surface of the episode above the floor (a table).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct EpisodeSurface {
    /// Scene height (m).
    pub z_m: f64,
    /// Height above the floor (m), when there is one.
    pub above_floor_m: Option<f64>,
    /// Accepted windows that saw it.
    pub windows: usize,
}

/// The episode's floor: found, or not with the reason.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "status", rename_all = "snake_case")]
pub enum Floor {
    /// A floor height.
    Found {
        /// Scene height of the floor (m).
        z_m: f64,
        /// Spread of the windows' heights about it (m, 1.4826 × weighted MAD).
        spread_m: f64,
        /// Accepted windows pooled.
        windows: usize,
    },
    /// No floor: why.
    NoFloor {
        /// What was missing.
        reason: String,
    },
}

impl Floor {
    /// The floor's scene height, when found.
    pub fn z_m(&self) -> Option<f64> {
        match self {
            Self::Found { z_m, .. } => Some(*z_m),
            Self::NoFloor { .. } => None,
        }
    }
}

/// Weighted median of `(value, weight)` pairs (none when empty).
fn weighted_median(mut pairs: Vec<(f64, f64)>) -> Option<f64> {
    pairs.retain(|(v, w)| v.is_finite() && *w > 0.0);
    if pairs.is_empty() {
        return None;
    }
    pairs.sort_by(|a, b| a.0.total_cmp(&b.0));
    let total: f64 = pairs.iter().map(|p| p.1).sum();
    let mut acc = 0.0;
    for (v, w) in &pairs {
        acc += w;
        if acc >= 0.5 * total {
            return Some(*v);
        }
    }
    pairs.last().map(|p| p.0)
}

/// Pool the windows of both wrists: the floor level by consensus ([`floor_level`]), every
/// window re-judged against it, and the floor by a weighted median (weights 1/sigma²) of the
/// accepted ones; or no floor with the reason drawn from the wrists' counts.
pub fn pool(windows: &mut [WindowEstimate], counts: &[WindowCounts], band: [f64; 2]) -> Floor {
    let level = floor_level(windows, band);
    if let Some(level) = level {
        judge(windows, level, band);
    }
    // Without a level that enough windows found, the windows' floors disagree: no guess.
    let accepted: Vec<(f64, f64)> = windows
        .iter()
        .filter(|w| level.is_some() && w.status == WindowStatus::Accepted)
        .filter_map(|w| Some((w.floor_z_m?, 1.0 / w.sigma_m?.max(MIN_SIGMA_M).powi(2))))
        .collect();
    let Some(z_m) = weighted_median(accepted.clone()) else {
        let total: WindowCounts =
            counts
                .iter()
                .fold(WindowCounts::default(), |a, c| WindowCounts {
                    windows: a.windows + c.windows,
                    unposed: a.unposed + c.unposed,
                    not_looking_down: a.not_looking_down + c.not_looking_down,
                    no_baseline: a.no_baseline + c.no_baseline,
                    swept: a.swept + c.swept,
                });
        let conflicts = windows
            .iter()
            .filter(|w| w.status == WindowStatus::Conflict)
            .count();
        let reason = if total.windows == 0 {
            "the front lenses recorded no frames".to_string()
        } else if total.unposed == total.windows {
            "no front frame has a fused pose".to_string()
        } else if total.swept == 0 && total.not_looking_down >= total.no_baseline {
            format!(
                "the front lenses never looked down: in none of {} one-second windows did {:.0} % \
                 of a frame's view lie within {:.0}° of straight down",
                total.windows,
                100.0 * MIN_DOWNWARD_SHARE,
                SweepOptions::default().max_nadir_rad.to_degrees()
            )
        } else if total.swept == 0 {
            format!(
                "the cameras never moved sideways by {MIN_BASELINE_M} m within a window while \
                 looking down"
            )
        } else if conflicts > 0 && conflicts == total.swept {
            "the plane sweep and the motion stereo disagreed in every window".to_string()
        } else if level.is_none() && windows.iter().any(|w| candidates(w, band) != [None, None]) {
            format!(
                "no floor height was found by {MIN_FLOOR_WINDOWS} windows or {:.0} % of those \
                 with a candidate: the windows' lowest surfaces disagreed",
                100.0 * MIN_FLOOR_WINDOWS_SHARE
            )
        } else {
            format!(
                "no horizontal surface {:.2}-{:.2} m below the cameras was supported in any of \
                 {} windows that looked down (a floor without texture, or out of view)",
                band[0], band[1], total.swept
            )
        };
        return Floor::NoFloor { reason };
    };
    let deviations: Vec<(f64, f64)> = accepted
        .iter()
        .map(|(v, w)| ((v - z_m).abs(), *w))
        .collect();
    let spread_m = 1.4826 * weighted_median(deviations).unwrap_or(0.0);
    Floor::Found {
        z_m,
        spread_m,
        windows: accepted.len(),
    }
}

/// The supported surfaces above the floor (or all, without one) seen by enough of the windows
/// that saw the floor or only surfaces above it: repeatedly the height found by the most windows
/// within [`LEVEL_HALF_WIDTH_M`] (the sweep's height first where both channels saw a level: it
/// poses every row), while at least [`MIN_SURFACE_WINDOWS_SHARE`] of those windows found it.
pub fn surfaces_above(windows: &[WindowEstimate], floor: &Floor) -> Vec<EpisodeSurface> {
    let floor_z = floor.z_m();
    let seeing: Vec<&WindowEstimate> = windows
        .iter()
        .filter(|w| matches!(w.status, WindowStatus::Accepted | WindowStatus::AboveFloor))
        .collect();
    let above = |s: &&Surface| floor_z.is_none_or(|f| s.z_m - f >= MIN_ABOVE_FLOOR_M);
    let (mut heights, _) = window_heights(
        seeing
            .iter()
            .enumerate()
            .map(|(i, w)| (i, w.sweep.iter().chain(&w.stereo).filter(above))),
    );
    let min_windows = ((seeing.len() as f64 * MIN_SURFACE_WINDOWS_SHARE).ceil() as usize).max(2);
    let mut out = Vec::new();
    loop {
        let best = heights
            .iter()
            .map(|h| (h.0, level_members(&heights, h.0).1))
            .max_by(|a, b| a.1.cmp(&b.1).then(b.0.total_cmp(&a.0)));
        let Some((seed, count)) = best else { break };
        if count < min_windows {
            break;
        }
        let z = level_centre(&heights, seed);
        let (_, windows) = level_members(&heights, z);
        out.push(EpisodeSurface {
            z_m: z,
            above_floor_m: floor_z.map(|f| z - f),
            windows: windows.max(count),
        });
        heights.retain(|h| {
            (h.0 - z).abs() > LEVEL_HALF_WIDTH_M && (h.0 - seed).abs() > LEVEL_HALF_WIDTH_M
        });
    }
    out.sort_by(|a, b| a.z_m.total_cmp(&b.z_m));
    out
}

/// The floor stage's record (`floor.json`, and `quality.json`'s `floor` section).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FloorSummary {
    /// The episode's floor, or why there is none.
    pub floor: Floor,
    /// Horizontal surfaces above it (a table), lowest first.
    pub surfaces: Vec<EpisodeSurface>,
    /// The camera-to-floor band searched (m).
    pub camera_height_m: [f64; 2],
    /// Per wrist camera: the windows and why some were not swept.
    pub wrists: std::collections::BTreeMap<String, WindowCounts>,
    /// Swept windows per outcome (`accepted`, `no_surface`, `conflict`, `outlier`,
    /// `above_floor`).
    pub outcomes: std::collections::BTreeMap<String, usize>,
}

impl FloorSummary {
    /// The record of `windows` pooled into `floor` with `surfaces`.
    pub fn new(
        floor: Floor,
        surfaces: Vec<EpisodeSurface>,
        camera_height_m: [f64; 2],
        wrists: std::collections::BTreeMap<String, WindowCounts>,
        windows: &[WindowEstimate],
    ) -> Self {
        let mut outcomes = std::collections::BTreeMap::new();
        for w in windows {
            *outcomes.entry(w.status.name().to_string()).or_insert(0) += 1;
        }
        Self {
            floor,
            surfaces,
            camera_height_m,
            wrists,
            outcomes,
        }
    }
}

impl WindowStatus {
    /// The outcome's name in files.
    pub fn name(self) -> &'static str {
        match self {
            Self::Accepted => "accepted",
            Self::NoSurface => "no_surface",
            Self::Conflict => "conflict",
            Self::Outlier => "outlier",
            Self::AboveFloor => "above_floor",
        }
    }
}

/// Header of `floor_windows.csv`.
pub const WINDOWS_HEADER: &str = "wrist,frame,t_camera,t_session,camera_z_m,baseline_m,\
sweep_floor_z_m,stereo_floor_z_m,floor_z_m,sigma_m,status,sweep_surfaces_z_m,stereo_surfaces_z_m";

/// `floor_windows.csv`: one row per swept window, its channels' floor candidates in `band`,
/// its floor and outcome, and every surface each channel found (`;`-separated scene heights).
pub fn windows_csv(windows: &[WindowEstimate], band: [f64; 2]) -> String {
    use std::fmt::Write as _;
    let opt = |v: Option<f64>| v.map(|v| format!("{v:.5}")).unwrap_or_default();
    let list = |s: &[Surface]| {
        s.iter()
            .map(|s| format!("{:.4}", s.z_m))
            .collect::<Vec<_>>()
            .join(";")
    };
    let mut out = format!("{WINDOWS_HEADER}\n");
    for w in windows {
        let _ = writeln!(
            out,
            "{},{},{:.6},{},{:.4},{:.4},{},{},{},{},{},{},{}",
            w.side.camera_name(),
            w.frame,
            w.t_camera,
            w.t_session.map(|t| format!("{t:.6}")).unwrap_or_default(),
            w.camera_z_m,
            w.baseline_m,
            opt(floor_of(&w.sweep, band).map(|s| s.z_m)),
            opt(floor_of(&w.stereo, band).map(|s| s.z_m)),
            opt(w.floor_z_m),
            opt(w.sigma_m),
            w.status.name(),
            list(&w.sweep),
            list(&w.stereo),
        );
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A surface `z` in the scene seen from a camera at `camera_z`.
    fn surface(z: f64, camera_z: f64) -> Surface {
        Surface {
            depth_m: camera_z - z,
            z_m: z,
            support: 0.2,
            votes: 100,
            sigma_m: 0.003,
        }
    }

    /// A swept window of the left wrist whose sweep saw `sweep` and whose stereo saw `stereo`,
    /// judged as `wrist_windows` judges it.
    fn window(frame: usize, sweep: &[f64], stereo: &[f64]) -> WindowEstimate {
        let camera_z = 1.0;
        let sweep: Vec<Surface> = sweep.iter().map(|&z| surface(z, camera_z)).collect();
        let stereo: Vec<Surface> = stereo.iter().map(|&z| surface(z, camera_z)).collect();
        let band = DEFAULT_CAMERA_HEIGHT_M;
        let (floor_z_m, sigma_m, status) =
            match combine(floor_of(&sweep, band), floor_of(&stereo, band)) {
                Ok((z, s)) => (Some(z), Some(s), WindowStatus::Accepted),
                Err(status) => (None, None, status),
            };
        WindowEstimate {
            side: Side::Left,
            frame,
            t_camera: frame as f64,
            t_session: None,
            camera_z_m: camera_z,
            baseline_m: 0.1,
            sweep,
            stereo,
            sweep_support: Vec::new(),
            floor_z_m,
            sigma_m,
            status,
        }
    }

    fn counts(n: usize) -> Vec<WindowCounts> {
        vec![WindowCounts {
            windows: n,
            swept: n,
            ..WindowCounts::default()
        }]
    }

    #[test]
    fn the_floor_is_the_lowest_level_enough_windows_found() {
        // Six windows see the floor, two see only a low platform, and one channel of another
        // window sees only the platform while the other sees the floor.
        let mut windows: Vec<WindowEstimate> = (0..6)
            .map(|k| window(k, &[0.001 * k as f64], &[]))
            .collect();
        windows.push(window(6, &[0.2], &[0.2]));
        windows.push(window(7, &[0.2], &[]));
        windows.push(window(8, &[0.002], &[0.2]));
        assert_eq!(windows[8].status, WindowStatus::Conflict);
        let floor = pool(&mut windows, &counts(9), DEFAULT_CAMERA_HEIGHT_M);
        let z = floor.z_m().expect("a floor");
        assert!(z.abs() < 0.005, "{floor:?}");
        assert_eq!(windows[6].status, WindowStatus::AboveFloor);
        assert_eq!(windows[8].status, WindowStatus::Accepted);
        let surfaces = surfaces_above(&windows, &floor);
        assert!(
            surfaces.iter().any(|s| (s.z_m - 0.2).abs() < 0.01),
            "{surfaces:?}"
        );
    }

    #[test]
    fn windows_that_all_disagree_give_no_floor_with_the_reason() {
        let mut windows = vec![
            window(0, &[0.0], &[]),
            window(1, &[0.12], &[]),
            window(2, &[0.24], &[]),
            window(3, &[0.36], &[]),
        ];
        let floor = pool(&mut windows, &counts(4), DEFAULT_CAMERA_HEIGHT_M);
        let Floor::NoFloor { reason } = floor else {
            panic!("expected no floor, got {floor:?}");
        };
        assert!(reason.contains("disagreed"), "{reason}");
    }
}
