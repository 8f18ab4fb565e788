//! A front frame with its pose at every row (a rolling shutter exposes rows at different times,
//! so a moving camera has a pose per row), and the height histogram both channels vote into.

use nalgebra::{Point2, Point3, Vector3};

use kiwi_core::camera::{Camera, CameraModel};
use kiwi_core::geometry::Pose;

use crate::vision::features::GrayImage;

/// A luma frame posed row by row in the gravity-aligned scene frame.
pub struct PosedView<'a> {
    /// The frame.
    pub image: &'a GrayImage,
    /// The lens model (bearing vectors; the X5 lenses see ~190°).
    pub camera: &'a Camera,
    /// `scene_from_cam` of each row, top row first.
    pub rows: Vec<Pose>,
    /// `cam_from_scene` of each row.
    cam_from_scene: Vec<Pose>,
}

impl<'a> PosedView<'a> {
    /// A view whose rows' poses are `pose_of_row(row fraction in [0, 1])`, or `None` when a
    /// row has no pose (a gap in the trajectory during the frame's readout).
    pub fn new(
        image: &'a GrayImage,
        camera: &'a Camera,
        pose_of_row: impl Fn(f64) -> Option<Pose>,
    ) -> Option<Self> {
        let h = image.height.max(1) as usize;
        let denominator = (h.max(2) - 1) as f64;
        let rows: Vec<Pose> = (0..h)
            .map(|r| pose_of_row(r as f64 / denominator))
            .collect::<Option<_>>()?;
        let cam_from_scene = rows.iter().map(Pose::inverse).collect();
        Some(Self {
            image,
            camera,
            rows,
            cam_from_scene,
        })
    }

    /// Index of the row nearest to `v` (px), clamped to the image.
    fn row(&self, v: f64) -> usize {
        (v.round().max(0.0) as usize).min(self.rows.len() - 1)
    }

    /// `scene_from_cam` of the row nearest to `v`.
    pub fn pose_at(&self, v: f64) -> &Pose {
        &self.rows[self.row(v)]
    }

    /// `scene_from_cam` of the middle row.
    pub fn middle(&self) -> &Pose {
        &self.rows[self.rows.len() / 2]
    }

    /// The scene ray (origin, unit direction) of a pixel, from its row's pose.
    pub fn ray(&self, pixel: &Point2<f64>) -> Option<(Point3<f64>, Vector3<f64>)> {
        let bearing = self.camera.unproject(pixel)?;
        let pose = self.pose_at(pixel.y);
        Some((
            Point3::from(pose.translation.vector),
            pose.rotation * bearing.into_inner(),
        ))
    }

    /// The pixel of a scene point, posed by the row it lands on (one step from the middle
    /// row's projection), or `None` outside the lens's cone or the image.
    pub fn project(&self, p: &Point3<f64>) -> Option<Point2<f64>> {
        let mid = &self.cam_from_scene[self.rows.len() / 2];
        let first = self.camera.project(&(mid * p).coords)?;
        let own = &self.cam_from_scene[self.row(first.y)];
        self.project_in(own, p)
    }

    /// The pixel of `p` seen from a given row's `cam_from_scene`.
    pub fn project_in(&self, cam_from_scene: &Pose, p: &Point3<f64>) -> Option<Point2<f64>> {
        let px = self.camera.project(&(cam_from_scene * p).coords)?;
        self.camera.in_image(&px).then_some(px)
    }

    /// `cam_from_scene` of the row nearest to `v`.
    pub fn cam_from_scene_at(&self, v: f64) -> &Pose {
        &self.cam_from_scene[self.row(v)]
    }

    /// Bilinear luma at `(x, y)`, or `None` within one pixel of the border.
    pub fn sample(&self, x: f64, y: f64) -> Option<f32> {
        sample(self.image, x, y)
    }
}

/// Bilinear luma of `image` at `(x, y)` (pixel centres at integers), or `None` off the image.
pub fn sample(image: &GrayImage, x: f64, y: f64) -> Option<f32> {
    let (w, h) = (image.width as usize, image.height as usize);
    if !(x >= 0.0 && y >= 0.0) {
        return None;
    }
    let (x0, y0) = (x as usize, y as usize);
    if x0 + 1 >= w || y0 + 1 >= h {
        return None;
    }
    let (ax, ay) = ((x - x0 as f64) as f32, (y - y0 as f64) as f32);
    let d = &image.data;
    let at = |xx: usize, yy: usize| f32::from(d[yy * w + xx]);
    let top = at(x0, y0) + (at(x0 + 1, y0) - at(x0, y0)) * ax;
    let bottom = at(x0, y0 + 1) + (at(x0 + 1, y0 + 1) - at(x0, y0 + 1)) * ax;
    Some(top + (bottom - top) * ay)
}

/// Whether a sample is flat: its standard deviation below `min_std`.
pub fn is_flat(values: &[f32], min_std: f32) -> bool {
    let n = values.len() as f32;
    let mean = values.iter().sum::<f32>() / n.max(1.0);
    let var = values.iter().map(|v| (v - mean) * (v - mean)).sum::<f32>() / n.max(1.0);
    var.is_nan() || var < min_std * min_std
}

/// Zero-mean normalized cross-correlation of two equally long samples, or `None` when either
/// is flat (standard deviation below `min_std`).
pub fn zncc(a: &[f32], b: &[f32], min_std: f32) -> Option<f32> {
    let n = a.len().min(b.len()) as f32;
    if n < 2.0 {
        return None;
    }
    let (ma, mb) = (a.iter().sum::<f32>() / n, b.iter().sum::<f32>() / n);
    let (mut sab, mut saa, mut sbb) = (0.0f32, 0.0f32, 0.0f32);
    for (x, y) in a.iter().zip(b) {
        let (dx, dy) = (x - ma, y - mb);
        sab += dx * dy;
        saa += dx * dx;
        sbb += dy * dy;
    }
    let floor = min_std * min_std * n;
    if saa < floor || sbb < floor {
        return None;
    }
    Some(sab / (saa * sbb).sqrt())
}

/// Votes for heights below a reference camera in bins of `bin_m` from `h_min_m`.
#[derive(Debug, Clone)]
pub struct HeightVotes {
    /// Height of bin 0's centre below the reference camera (m).
    pub h_min_m: f64,
    /// Bin width (m).
    pub bin_m: f64,
    /// Votes per bin.
    pub counts: Vec<f64>,
    /// Samples that could vote (the denominator of a surface's support).
    pub voters: usize,
    /// Heights voted, for the refinement of a surface (m below the reference camera).
    pub heights: Vec<f64>,
}

/// A horizontal surface a channel found in one window.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Surface {
    /// Height below the window's reference camera (m).
    pub depth_m: f64,
    /// Scene-frame height (m).
    pub z_m: f64,
    /// Fraction of the channel's voters that voted for it.
    pub support: f64,
    /// Their number.
    pub votes: usize,
    /// Standard error of the height (m).
    pub sigma_m: f64,
}

/// Half width (bins) of a surface's peak: votes within it belong to the surface.
const PEAK_HALF_WIDTH_BINS: usize = 1;
/// Below this many votes no surface is reported, whatever its share (a median of fewer is
/// not a height).
const MIN_SURFACE_VOTES: usize = 25;

impl HeightVotes {
    /// Empty votes over `[h_min_m, h_max_m]`.
    pub fn new(h_min_m: f64, h_max_m: f64, bin_m: f64) -> Self {
        let bins = (((h_max_m - h_min_m) / bin_m).ceil() as usize).max(1) + 1;
        Self {
            h_min_m,
            bin_m,
            counts: vec![0.0; bins],
            voters: 0,
            heights: Vec::new(),
        }
    }

    /// The bin of a height, if inside.
    fn bin(&self, h: f64) -> Option<usize> {
        let b = ((h - self.h_min_m) / self.bin_m).round();
        (b >= 0.0 && (b as usize) < self.counts.len()).then_some(b as usize)
    }

    /// Centre height of a bin.
    pub fn centre(&self, bin: usize) -> f64 {
        self.h_min_m + bin as f64 * self.bin_m
    }

    /// Add one vote for height `h`.
    pub fn vote(&mut self, h: f64) {
        if let Some(b) = self.bin(h) {
            self.counts[b] += 1.0;
            self.heights.push(h);
        }
    }

    /// Support (fraction of voters) per bin centre, for the figure.
    pub fn support_curve(&self) -> Vec<[f64; 2]> {
        let n = self.voters.max(1) as f64;
        self.counts
            .iter()
            .enumerate()
            .map(|(b, c)| [self.centre(b), c / n])
            .collect()
    }

    /// The surfaces: local maxima of the votes (summed over a peak's width) holding at least
    /// `min_support` of the voters, each refined to the median of its votes; `camera_z` is the
    /// reference camera's scene height. Ordered from the lowest (deepest) up.
    pub fn surfaces(&self, min_support: f64, camera_z: f64) -> Vec<Surface> {
        let n = self.counts.len();
        let w = PEAK_HALF_WIDTH_BINS;
        let window = |b: usize| -> f64 {
            self.counts[b.saturating_sub(w)..(b + w + 1).min(n)]
                .iter()
                .sum()
        };
        let summed: Vec<f64> = (0..n).map(window).collect();
        let mut out = Vec::new();
        let mut b = 0;
        while b < n {
            let here = summed[b];
            let left = if b > 0 { summed[b - 1] } else { 0.0 };
            // A plateau counts once, at its first bin.
            let mut end = b;
            while end + 1 < n && summed[end + 1] == here {
                end += 1;
            }
            let right = if end + 1 < n { summed[end + 1] } else { 0.0 };
            if here > left && here > right {
                let centre = self.centre((b + end) / 2);
                let half = (w as f64 + 0.5) * self.bin_m;
                let mut near: Vec<f64> = self
                    .heights
                    .iter()
                    .copied()
                    .filter(|h| (h - centre).abs() <= half)
                    .collect();
                let support = near.len() as f64 / self.voters.max(1) as f64;
                if near.len() >= MIN_SURFACE_VOTES && support >= min_support {
                    let (median, mad) = median_mad(&mut near);
                    let depth = median;
                    out.push(Surface {
                        depth_m: depth,
                        z_m: camera_z - depth,
                        support,
                        votes: near.len(),
                        sigma_m: 1.4826 * mad / (near.len() as f64).sqrt(),
                    });
                }
            }
            b = end + 1;
        }
        out.sort_by(|a, b| b.depth_m.total_cmp(&a.depth_m));
        out
    }
}

/// Median and median absolute deviation (sorts `values`; both 0 when empty).
pub fn median_mad(values: &mut [f64]) -> (f64, f64) {
    if values.is_empty() {
        return (0.0, 0.0);
    }
    values.sort_by(f64::total_cmp);
    let median = values[values.len() / 2];
    let mut dev: Vec<f64> = values.iter().map(|v| (v - median).abs()).collect();
    dev.sort_by(f64::total_cmp);
    (median, dev[dev.len() / 2])
}
