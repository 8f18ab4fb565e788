//! The image front-end of mapping: turns a sequence of fisheye frames into bearing tracks.
//!
//! Points are followed from frame to frame with pyramidal KLT (cheap at 120 Hz, where
//! consecutive frames are nearly identical); when fewer than the target number survive, ORB
//! keypoints are detected away from the surviving tracks (inside the static mask) and start new
//! tracks. Each frame yields a [`MappingFrame`] for [`crate::vision::mapping::reconstruct`].

use std::collections::BTreeMap;

use nalgebra::Point2;

use kiwi_core::camera::CameraModel;

use crate::error::Result;
use crate::vision::features::{
    Descriptor, GrayImage, KltOptions, Mask, OrbExtractor, OrbOptions, track_klt,
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
            klt: KltOptions::default(),
            orb: OrbOptions::default(),
        }
    }
}

/// Frame-to-frame tracker.
pub struct FrameTracker {
    options: TrackerOptions,
    orb: OrbExtractor,
    mask: Mask,
    next_track: u64,
    previous: Option<GrayImage>,
    active: Vec<(u64, Point2<f64>)>,
    births: BTreeMap<u64, Descriptor>,
}

impl FrameTracker {
    /// A tracker with a static mask (non-zero pixels may hold features).
    pub fn new(options: TrackerOptions, mask: Mask) -> Result<Self> {
        Ok(Self {
            orb: OrbExtractor::new(&options.orb)?,
            options,
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
        if (survivors.len() as f64) < self.options.replenish_ratio * wanted as f64 {
            let mut detect_mask = self.mask.clone();
            let r = self.options.min_distance_px;
            block_disks(&mut detect_mask, survivors.iter().map(|s| s.1), r);
            let found = self.orb.extract(&image, Some(&detect_mask), camera)?;
            for (kp, desc) in found.keypoints.into_iter().zip(found.descriptors) {
                if survivors.len() >= wanted {
                    break;
                }
                let (x, y) = (kp.pixel.x.round() as i64, kp.pixel.y.round() as i64);
                if detect_mask.get(x, y) == 0 {
                    continue;
                }
                block_disks(&mut detect_mask, std::iter::once(kp.pixel), r);
                let id = self.next_track;
                self.next_track += 1;
                self.births.insert(id, desc);
                survivors.push((id, kp.pixel));
                observations.push(TrackObservation {
                    track: id,
                    bearing: kp.bearing,
                    pixel: kp.pixel,
                });
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
