//! The image front-end of mapping: turns a sequence of fisheye frames into bearing tracks.
//!
//! Points are followed from frame to frame with pyramidal KLT (cheap at 120 Hz, where
//! consecutive frames are nearly identical); when fewer than the target number survive, or when
//! part of the image holds no track, ORB keypoints are detected away from the surviving tracks
//! (inside the static mask) and start new tracks, empty parts of the image first. Each frame
//! yields a [`MappingFrame`] for [`crate::vision::mapping::reconstruct`].
//!
//! Coverage matters on a fisheye: points on a far wall live for hundreds of frames while the
//! floor and the side walls near the lens rush past the image edge in a few. Kept by count
//! alone, the tracks end up all on the far structure (measured on a rear lens walking down a
//! room: 0-14 of 535 tracks beyond 70° off-axis, where ORB finds ~40 % of its keypoints), and the
//! map has nothing near to fix a position with.

use std::collections::BTreeMap;

use nalgebra::Point2;

use kiwi_core::camera::CameraModel;

use crate::error::Result;
use crate::vision::features::{
    Descriptor, GrayImage, Keypoint, KltOptions, Mask, OrbExtractor, OrbOptions, track_klt,
};
use crate::vision::mapping::{MappingFrame, TrackObservation};

/// Front-end settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackerOptions {
    /// Tracks to keep alive; new ones are detected when fewer survive.
    pub target_tracks: usize,
    /// Below this fraction of the target, new features are detected.
    pub replenish_ratio: f64,
    /// Smallest distance (px) between a new feature and any other track.
    pub min_distance_px: f64,
    /// Cells per image side of the coverage grid.
    pub grid_cells: u32,
    /// Frames between detections made only because a usable grid cell holds no track.
    pub coverage_interval: u32,
    /// KLT settings.
    pub klt: KltOptions,
    /// ORB settings of detection.
    pub orb: OrbOptions,
}

impl Default for TrackerOptions {
    fn default() -> Self {
        Self {
            target_tracks: 600,
            // Detect again once a fifth of the tracks are gone.
            replenish_ratio: 0.8,
            min_distance_px: 10.0,
            // 8 × 8: cells of 120 px at 960 px, a few degrees of view each on a 190° lens.
            grid_cells: 8,
            // Every 3rd frame: near points live ~10 frames at walking speed, and a detection
            // costs as much as a tracked frame.
            coverage_interval: 3,
            klt: KltOptions::default(),
            orb: OrbOptions::default(),
        }
    }
}

/// Frame-to-frame tracker.
pub struct FrameTracker {
    options: TrackerOptions,
    orb: OrbExtractor,
    /// Describes the keypoints that start tracks (see `FrameTracker::new`).
    describer: OrbExtractor,
    mask: Mask,
    next_track: u64,
    previous: Option<GrayImage>,
    active: Vec<(u64, Point2<f64>)>,
    births: BTreeMap<u64, Descriptor>,
    /// Per grid cell: whether enough of it is inside the mask to hold tracks.
    usable_cells: Vec<bool>,
    /// Per grid cell: tracks in it (reused from frame to frame).
    counts: Vec<usize>,
    /// A usable cell's fair share of the target: `target_tracks` / usable cells.
    share: usize,
}

/// A grid cell holds tracks when at least this fraction of its pixels is inside the mask.
const USABLE_CELL_FRACTION: f64 = 0.25;

impl FrameTracker {
    /// A tracker with a static mask (non-zero pixels may hold features).
    pub fn new(options: TrackerOptions, mask: Mask) -> Result<Self> {
        let n = options.grid_cells.max(1);
        let mut inside = vec![0usize; (n * n) as usize];
        for y in 0..mask.height {
            for x in 0..mask.width {
                if mask.data[(y * mask.width + x) as usize] != 0 {
                    inside[cell_of(&mask, n, f64::from(x), f64::from(y))] += 1;
                }
            }
        }
        let cell_area = f64::from(mask.width) * f64::from(mask.height) / f64::from(n * n);
        let usable_cells: Vec<bool> = inside
            .iter()
            .map(|&c| c as f64 >= USABLE_CELL_FRACTION * cell_area)
            .collect();
        let usable = usable_cells.iter().filter(|&&u| u).count().max(1);
        Ok(Self {
            // Detection describes on the raw image (cheap); the few keypoints that start tracks
            // are then described as the options ask (rectified patches by default).
            orb: OrbExtractor::new(&OrbOptions {
                rectified: false,
                ..options.orb
            })?,
            describer: OrbExtractor::new(&options.orb)?,
            share: options.target_tracks.div_ceil(usable).max(1),
            options,
            counts: vec![0; usable_cells.len()],
            usable_cells,
            mask,
            next_track: 0,
            previous: None,
            active: Vec::new(),
            births: BTreeMap::new(),
        })
    }

    /// The ORB descriptor of each track where it was detected (its first frame): lets the map
    /// describe landmarks that no keyframe keypoint lands on.
    pub fn track_descriptors(&self) -> &BTreeMap<u64, Descriptor> {
        &self.births
    }

    /// Track into the next image and top up the tracks; returns the frame's observations.
    pub fn process(
        &mut self,
        frame: u32,
        t: f64,
        image: GrayImage,
        camera: &dyn CameraModel,
    ) -> Result<MappingFrame> {
        let mut observations = Vec::new();
        let mut survivors = Vec::new();
        if let Some(prev) = &self.previous {
            let pixels: Vec<Point2<f64>> = self.active.iter().map(|a| a.1).collect();
            let tracks = track_klt(
                prev,
                &image,
                &pixels,
                Some(&self.mask),
                camera,
                &self.options.klt,
            )?;
            for ((id, _), tr) in self.active.iter().zip(tracks) {
                if let Some(tr) = tr {
                    survivors.push((*id, tr.pixel));
                    observations.push(TrackObservation {
                        track: *id,
                        bearing: tr.bearing,
                        pixel: tr.pixel,
                    });
                }
            }
        }
        let wanted = self.options.target_tracks;
        let n = self.options.grid_cells.max(1);
        let few = (survivors.len() as f64) < self.options.replenish_ratio * wanted as f64;
        // Coverage is checked only when it could trigger a detection of its own.
        let coverage_due = !few && frame.is_multiple_of(self.options.coverage_interval.max(1)) && {
            self.counts.fill(0);
            for s in &survivors {
                self.counts[cell_of(&self.mask, n, s.1.x, s.1.y)] += 1;
            }
            self.counts
                .iter()
                .zip(&self.usable_cells)
                .any(|(&c, &u)| u && c == 0)
        };
        if few || coverage_due {
            let mut detect_mask = self.mask.clone();
            let r = self.options.min_distance_px;
            block_disks(&mut detect_mask, survivors.iter().map(|s| s.1), r);
            let found = self.orb.extract(&image, Some(&detect_mask), camera)?;
            // Too few tracks: the strongest keypoints anywhere, up to the target. Coverage only:
            // first the cells below a fair share (even past the target), then up to the target.
            // (A fair share on every replenishment took weak-texture points over strong ones: a
            // 320 px tabletop localized with a worst error of 53 mm instead of 24 mm.) A taken
            // keypoint blocks its own pixel in `detect_mask`, so the second pass skips it.
            let first_pass = if coverage_due { 0 } else { 1 };
            let born_from = observations.len();
            let mut born: Vec<Keypoint> = Vec::new();
            for pass in first_pass..2 {
                for (kp, desc) in found.keypoints.iter().zip(&found.descriptors) {
                    if pass == 1 && survivors.len() >= wanted {
                        break;
                    }
                    let c = cell_of(&self.mask, n, kp.pixel.x, kp.pixel.y);
                    if pass == 0 && self.counts[c] >= self.share {
                        continue;
                    }
                    let (x, y) = (kp.pixel.x.round() as i64, kp.pixel.y.round() as i64);
                    if detect_mask.get(x, y) == 0 {
                        continue;
                    }
                    block_disks(&mut detect_mask, std::iter::once(kp.pixel), r);
                    if pass == 0 {
                        self.counts[c] += 1;
                    }
                    let id = self.next_track;
                    self.next_track += 1;
                    self.births.insert(id, *desc);
                    survivors.push((id, kp.pixel));
                    observations.push(TrackObservation {
                        track: id,
                        bearing: kp.bearing,
                        pixel: kp.pixel,
                    });
                    born.push(*kp);
                }
            }
            if let Some(described) = self.describer.describe(&image, camera, &born)? {
                for (o, d) in observations[born_from..].iter().zip(described) {
                    match d {
                        Some(d) => {
                            self.births.insert(o.track, d);
                        }
                        None => {
                            self.births.remove(&o.track);
                        }
                    }
                }
            }
        }
        self.active = survivors;
        self.previous = Some(image);
        Ok(MappingFrame {
            frame,
            t,
            observations,
        })
    }
}

/// The coverage-grid cell (row-major, `n` per side) of a pixel, clamped to the image.
fn cell_of(mask: &Mask, n: u32, x: f64, y: f64) -> usize {
    let cx = ((x / f64::from(mask.width.max(1))) * f64::from(n)).floor();
    let cy = ((y / f64::from(mask.height.max(1))) * f64::from(n)).floor();
    let clamp = |v: f64| (v.max(0.0) as u32).min(n - 1);
    (clamp(cy) * n + clamp(cx)) as usize
}

/// Zero the mask in disks of radius `r` around the given pixels.
fn block_disks(mask: &mut Mask, centres: impl Iterator<Item = Point2<f64>>, r: f64) {
    let (w, h) = (i64::from(mask.width), i64::from(mask.height));
    let ri = r.ceil() as i64;
    for c in centres {
        let (cx, cy) = (c.x.round() as i64, c.y.round() as i64);
        for y in (cy - ri).max(0)..=(cy + ri).min(h - 1) {
            for x in (cx - ri).max(0)..=(cx + ri).min(w - 1) {
                let (dx, dy) = ((x - cx) as f64, (y - cy) as f64);
                if dx * dx + dy * dy <= r * r {
                    mask.data[(y * w + x) as usize] = 0;
                }
            }
        }
    }
}
