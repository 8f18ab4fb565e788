//! Feature statistics as LeRobot keeps them: per episode (columns `stats/<feature>/<stat>` of
//! `meta/episodes`) and for the whole dataset (`meta/stats.json`), each with `min`, `max`,
//! `mean`, `std` and `count`. Numeric features have one value per element; a video feature has
//! one per colour channel (red, green, blue), of pixel values scaled to 0..1, shaped
//! `(3, 1, 1)`, computed on a sample of the episode's frames as LeRobot samples them.

use serde_json::{Value, json};

use crate::formats::video::ColorImage;

/// Fewest frames sampled per episode for image statistics (all of them in a shorter episode).
const MIN_IMAGE_SAMPLES: usize = 100;
/// Most frames sampled per episode for image statistics.
const MAX_IMAGE_SAMPLES: usize = 10_000;
/// Samples grow as the frame count to this power: 177 of 1000 frames, 1000 of 10 000.
const IMAGE_SAMPLE_POWER: f64 = 0.75;
/// Images at least this wide or high (px) are thinned before their statistics are taken.
const THIN_ABOVE_PX: usize = 300;
/// Thinned images keep about this many pixels along their longer side.
const THIN_TARGET_PX: usize = 150;

/// Which of an episode's `n` rows have their images in the statistics: evenly spread, rounded,
/// as many as LeRobot's heuristic takes.
pub fn image_sample_rows(n: usize) -> Vec<usize> {
    if n == 0 {
        return Vec::new();
    }
    let grown = ((n as f64).powf(IMAGE_SAMPLE_POWER) as usize).min(MAX_IMAGE_SAMPLES);
    let count = grown.max(MIN_IMAGE_SAMPLES.min(n));
    if count == 1 {
        return vec![0];
    }
    let step = (n - 1) as f64 / (count - 1) as f64;
    let mut rows: Vec<usize> = (0..count)
        .map(|i| (i as f64 * step).round_ties_even() as usize)
        .collect();
    rows.dedup();
    rows
}

/// Running per-element statistics of a numeric feature.
#[derive(Debug, Clone, Default)]
pub struct Stats {
    min: Vec<f64>,
    max: Vec<f64>,
    sum: Vec<f64>,
    sum_sq: Vec<f64>,
    count: u64,
}

impl Stats {
    /// Add one row.
    pub fn add(&mut self, row: &[f64]) {
        if self.min.is_empty() {
            self.min = vec![f64::INFINITY; row.len()];
            self.max = vec![f64::NEG_INFINITY; row.len()];
            self.sum = vec![0.0; row.len()];
            self.sum_sq = vec![0.0; row.len()];
        }
        for (i, &v) in row.iter().enumerate() {
            self.min[i] = self.min[i].min(v);
            self.max[i] = self.max[i].max(v);
            self.sum[i] += v;
            self.sum_sq[i] += v * v;
        }
        self.count += 1;
    }

    /// Add everything `other` holds (the statistics of both sets together).
    pub fn merge(&mut self, other: &Stats) {
        if other.count == 0 {
            return;
        }
        if self.count == 0 {
            *self = other.clone();
            return;
        }
        for i in 0..self.min.len().min(other.min.len()) {
            self.min[i] = self.min[i].min(other.min[i]);
            self.max[i] = self.max[i].max(other.max[i]);
            self.sum[i] += other.sum[i];
            self.sum_sq[i] += other.sum_sq[i];
        }
        self.count += other.count;
    }

    /// `min`, `max`, `mean`, `std` (population) per element.
    pub fn summary(&self) -> Summary {
        let n = self.count.max(1) as f64;
        let mean: Vec<f64> = self.sum.iter().map(|s| s / n).collect();
        let std = self
            .sum_sq
            .iter()
            .zip(&mean)
            .map(|(sq, m)| (sq / n - m * m).max(0.0).sqrt())
            .collect();
        Summary {
            min: self.min.clone(),
            max: self.max.clone(),
            mean,
            std,
            count: self.count,
            per_channel: false,
        }
    }
}

/// Running per-channel statistics of a video feature's sampled images.
#[derive(Debug, Clone, Default)]
pub struct ImageStats {
    /// Per channel (red, green, blue) pixel statistics, 0..255.
    pixels: Stats,
    /// Images added.
    images: u64,
}

impl ImageStats {
    /// Add one image (thinned as LeRobot thins images before taking their statistics).
    pub fn add(&mut self, image: &ColorImage) {
        let (w, h) = (image.width, image.height);
        let step = if w.max(h) < THIN_ABOVE_PX {
            1
        } else {
            (w.max(h) / THIN_TARGET_PX).max(1)
        };
        if w == 0 {
            return;
        }
        for row in image.bgr.chunks_exact(w * 3).take(h).step_by(step) {
            for px in row.chunks_exact(3).step_by(step) {
                self.pixels
                    .add(&[f64::from(px[2]), f64::from(px[1]), f64::from(px[0])]);
            }
        }
        self.images += 1;
    }

    /// Add everything `other` holds.
    pub fn merge(&mut self, other: &ImageStats) {
        self.pixels.merge(&other.pixels);
        self.images += other.images;
    }

    /// Per channel statistics of pixel values scaled to 0..1; `count` is the images sampled.
    pub fn summary(&self) -> Summary {
        let s = self.pixels.summary();
        let scale = |v: Vec<f64>| v.into_iter().map(|x| x / 255.0).collect();
        Summary {
            min: scale(s.min),
            max: scale(s.max),
            mean: scale(s.mean),
            std: scale(s.std),
            count: self.images,
            per_channel: true,
        }
    }
}

/// A feature's statistics, ready to write.
#[derive(Debug, Clone, PartialEq)]
pub struct Summary {
    /// Smallest value per element (channel).
    pub min: Vec<f64>,
    /// Largest value per element (channel).
    pub max: Vec<f64>,
    /// Mean per element (channel).
    pub mean: Vec<f64>,
    /// Population standard deviation per element (channel).
    pub std: Vec<f64>,
    /// Rows (images for a video feature) the statistics are over.
    pub count: u64,
    /// Values are per colour channel, shaped `(channels, 1, 1)`.
    pub per_channel: bool,
}

impl Summary {
    /// The four value statistics by their LeRobot names.
    pub fn values(&self) -> [(&'static str, &[f64]); 4] {
        [
            ("min", &self.min),
            ("max", &self.max),
            ("mean", &self.mean),
            ("std", &self.std),
        ]
    }

    /// As `stats.json` holds it.
    pub fn to_json(&self) -> Value {
        let shape = |v: &[f64]| -> Value {
            if self.per_channel {
                json!(v.iter().map(|x| json!([[x]])).collect::<Vec<_>>())
            } else {
                json!(v)
            }
        };
        let mut out = serde_json::Map::new();
        for (name, v) in self.values() {
            out.insert(name.into(), shape(v));
        }
        out.insert("count".into(), json!([self.count]));
        Value::Object(out)
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use super::*;

    #[test]
    fn samples_follow_the_episode_length() {
        assert!(image_sample_rows(0).is_empty());
        assert_eq!(image_sample_rows(1), vec![0]);
        assert_eq!(image_sample_rows(50), (0..50).collect::<Vec<_>>());
        let r = image_sample_rows(1000);
        assert_eq!((r.len(), r[0], r[r.len() - 1]), (177, 0, 999));
        assert_eq!(image_sample_rows(10_000).len(), 1000);
        assert_eq!(image_sample_rows(1_000_000).len(), MAX_IMAGE_SAMPLES);
    }

    #[test]
    fn merged_statistics_equal_those_of_all_rows() {
        let rows: Vec<[f64; 2]> = (0..40)
            .map(|i| [f64::from(i).sin(), f64::from(i * i) * 0.01])
            .collect();
        let (mut all, mut a, mut b) = (Stats::default(), Stats::default(), Stats::default());
        for (i, r) in rows.iter().enumerate() {
            all.add(r);
            if i < 13 { a.add(r) } else { b.add(r) }
        }
        a.merge(&b);
        let (x, y) = (all.summary(), a.summary());
        assert_eq!((x.min, x.max, x.count), (y.min, y.max, y.count));
        for (p, q) in x.mean.iter().chain(&x.std).zip(y.mean.iter().chain(&y.std)) {
            assert!((p - q).abs() < 1e-12);
        }
    }

    #[test]
    fn image_statistics_are_per_rgb_channel_scaled_to_one() {
        // 2×1 image: pixels (r, g, b) = (255, 0, 10) and (0, 0, 30), stored blue first.
        let image = ColorImage {
            width: 2,
            height: 1,
            bgr: vec![10, 0, 255, 30, 0, 0],
        };
        let mut s = ImageStats::default();
        s.add(&image);
        s.add(&image);
        let m = s.summary();
        assert_eq!(m.count, 2);
        assert_eq!(m.min, vec![0.0, 0.0, 10.0 / 255.0]);
        assert_eq!(m.max, vec![1.0, 0.0, 30.0 / 255.0]);
        assert!((m.mean[0] - 0.5).abs() < 1e-12 && (m.std[0] - 0.5).abs() < 1e-12);
        assert!((m.mean[2] - 20.0 / 255.0).abs() < 1e-12);
        let j = m.to_json();
        assert_eq!(j["mean"][0][0][0].as_f64().unwrap(), m.mean[0]);
        assert_eq!(j["count"], json!([2]));
    }
}
