//! The head's track from both wrists' sightings of the hat marker (paper §4.3.2, eq. 5): each
//! sighting becomes a scene-frame observation `scene_from_marker = scene_from_rear(t) ·
//! rear_from_marker`, and the observations of both wrists are fused into one smoothed track on
//! a time grid, with per-sample support and sigma. Where no wrist saw the marker the track has
//! a gap: nothing is made up.

use nalgebra::{Matrix2, Vector2, Vector3};

use kiwi_core::geometry::Pose;
use kiwi_core::layout::Side;

/// One wrist's sighting of the hat marker, in the scene frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HeadObservation {
    /// Session time of the sighting's exposure (s).
    pub t_session: f64,
    /// The wrist whose rear lens saw the marker.
    pub side: Side,
    /// `scene_from_marker`.
    pub scene_from_marker: Pose,
}

/// `scene_from_marker` of a sighting: the rear lens's scene pose (the fused front pose at the
/// sighting's time composed with the unit's `front_from_rear`) composed with the sighting's
/// `rear_from_marker`.
pub fn observe(scene_from_front: &Pose, front_from_rear: &Pose, rear_from_marker: &Pose) -> Pose {
    scene_from_front * front_from_rear * rear_from_marker
}

/// How the observations are smoothed.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackOptions {
    /// Samples per second of the track.
    pub rate_hz: f64,
    /// Observations within this much of a sample's time (s) shape it; a sample with none is a
    /// gap.
    pub half_window_s: f64,
    /// An observation further than this many robust spreads from the local fit is an outlier.
    pub outlier_spreads: f64,
    /// Smallest spread used for outlier rejection (m and rad): the sightings' own noise, so a
    /// run of near-identical observations does not make every small deviation an outlier.
    pub min_spread_m: f64,
    /// Smallest rotation spread (rad), as [`Self::min_spread_m`].
    pub min_spread_rad: f64,
    /// Fewest observations that make a sample; fewer is a gap. One or two cannot outvote a
    /// misdetection among them.
    pub min_observations: usize,
}

impl Default for TrackOptions {
    fn default() -> Self {
        Self {
            // The wrist outputs' rate.
            rate_hz: 30.0,
            // A head turns at up to ~2 rad/s; a local line over ±0.1 s follows it to within a
            // few millimetres while averaging ~6 sightings per wrist at 30 Hz.
            half_window_s: 0.1,
            // Misdetections and wrong IPPE branches land decimetres or tens of degrees off.
            outlier_spreads: 4.0,
            // The marker's IPPE pose at 0.3-0.7 m: a few millimetres, a few tenths of a degree.
            min_spread_m: 0.005,
            min_spread_rad: 0.01,
            min_observations: 3,
        }
    }
}

/// One sample of the head's track.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HeadSample {
    /// Session time (s).
    pub t_session: f64,
    /// `scene_from_marker`; `None` in a gap.
    pub scene_from_marker: Option<Pose>,
    /// Observations that shaped the sample (after outlier rejection); in a gap, those too few
    /// to make one.
    pub observations: usize,
    /// Of those, from the left wrist.
    pub from_left: usize,
    /// Of those, from the right wrist.
    pub from_right: usize,
    /// Observations rejected as outliers in the window.
    pub outliers: usize,
    /// Position sigma (m): the local fit's residual spread over √n, at least the sightings'
    /// noise over √n.
    pub sigma_p_m: f64,
    /// Rotation sigma (rad), as the position's.
    pub sigma_r_rad: f64,
}

/// Fuse observations (any order, both wrists) into a track over `[t0, t1]` at the options'
/// rate.
pub fn fuse(
    observations: &[HeadObservation],
    t0: f64,
    t1: f64,
    o: &TrackOptions,
) -> Vec<HeadSample> {
    let mut obs: Vec<&HeadObservation> = observations
        .iter()
        .filter(|h| h.t_session.is_finite())
        .collect();
    obs.sort_by(|a, b| a.t_session.total_cmp(&b.t_session));
    if !(o.rate_hz > 0.0 && t1 >= t0) {
        return Vec::new();
    }
    let n = ((t1 - t0) * o.rate_hz).floor() as usize + 1;
    (0..n)
        .map(|k| {
            let t = t0 + k as f64 / o.rate_hz;
            let lo = obs.partition_point(|h| h.t_session < t - o.half_window_s);
            let hi = obs.partition_point(|h| h.t_session <= t + o.half_window_s);
            sample_at(t, &obs[lo..hi], o)
        })
        .collect()
}

/// Weight of an observation `dt` from the sample within the half window `h` (tricube).
fn weight(dt: f64, h: f64) -> f64 {
    let u = (dt / h).abs();
    if u >= 1.0 {
        0.0
    } else {
        (1.0 - u.powi(3)).powi(3)
    }
}

/// A weighted local line `a + b·dt` through values: `(a, b)`. Falls back to the weighted mean
/// (no slope) when the times do not span a line.
fn local_line(
    dts: &[f64],
    weights: &[f64],
    values: &[Vector3<f64>],
) -> (Vector3<f64>, Vector3<f64>) {
    let (mut s0, mut s1, mut s2) = (0.0, 0.0, 0.0);
    let (mut v0, mut v1) = (Vector3::zeros(), Vector3::zeros());
    for ((&dt, &w), v) in dts.iter().zip(weights).zip(values) {
        s0 += w;
        s1 += w * dt;
        s2 += w * dt * dt;
        v0 += v * w;
        v1 += v * (w * dt);
    }
    let m = Matrix2::new(s0, s1, s1, s2);
    match m.try_inverse() {
        Some(inv) if m.determinant().abs() > 1e-12 * s0.max(1e-300).powi(2) => {
            let a: Vector2<f64> = inv.row(0).transpose();
            let b: Vector2<f64> = inv.row(1).transpose();
            (v0 * a[0] + v1 * a[1], v0 * b[0] + v1 * b[1])
        }
        _ if s0 > 0.0 => (v0 / s0, Vector3::zeros()),
        _ => (Vector3::zeros(), Vector3::zeros()),
    }
}

fn sample_at(t: f64, window: &[&HeadObservation], o: &TrackOptions) -> HeadSample {
    let gap = HeadSample {
        t_session: t,
        scene_from_marker: None,
        observations: 0,
        from_left: 0,
        from_right: 0,
        outliers: 0,
        sigma_p_m: f64::NAN,
        sigma_r_rad: f64::NAN,
    };
    if window.len() < o.min_observations.max(1) {
        return HeadSample {
            observations: window.len(),
            ..gap
        };
    }
    let dts: Vec<f64> = window.iter().map(|h| h.t_session - t).collect();
    // Rotations in the tangent space of the observation nearest in time.
    let reference = window
        .iter()
        .min_by(|a, b| (a.t_session - t).abs().total_cmp(&(b.t_session - t).abs()))
        .map(|h| h.scene_from_marker.rotation)
        .unwrap_or_default();
    let positions: Vec<Vector3<f64>> = window
        .iter()
        .map(|h| h.scene_from_marker.translation.vector)
        .collect();
    let rotations: Vec<Vector3<f64>> = window
        .iter()
        .map(|h| (reference.inverse() * h.scene_from_marker.rotation).scaled_axis())
        .collect();
    // Robust start: the median of each coordinate (no line yet), then outliers from it.
    let median3 = |vs: &[Vector3<f64>]| {
        Vector3::from_fn(|i, _| {
            let mut c: Vec<f64> = vs.iter().map(|v| v[i]).collect();
            c.sort_by(f64::total_cmp);
            c[c.len() / 2]
        })
    };
    let median = |mut d: Vec<f64>| {
        d.sort_by(f64::total_cmp);
        d[d.len() / 2]
    };
    let p_med = median3(&positions);
    let r_med = median3(&rotations);
    let p_dev: Vec<f64> = positions.iter().map(|p| (p - p_med).norm()).collect();
    let r_dev: Vec<f64> = rotations.iter().map(|r| (r - r_med).norm()).collect();
    // Spread from the median deviation (1.4826·MAD for a normal coordinate), floored by the
    // sightings' own noise; the motion within the window adds to it.
    let p_spread = (1.4826 * median(p_dev.clone())).max(o.min_spread_m);
    let r_spread = (1.4826 * median(r_dev.clone())).max(o.min_spread_rad);
    let keep: Vec<bool> = p_dev
        .iter()
        .zip(&r_dev)
        .map(|(dp, dr)| *dp <= o.outlier_spreads * p_spread && *dr <= o.outlier_spreads * r_spread)
        .collect();
    let pick = |v: &[f64]| -> Vec<f64> {
        v.iter()
            .zip(&keep)
            .filter(|(_, k)| **k)
            .map(|(x, _)| *x)
            .collect()
    };
    let pick3 = |v: &[Vector3<f64>]| -> Vec<Vector3<f64>> {
        v.iter()
            .zip(&keep)
            .filter(|(_, k)| **k)
            .map(|(x, _)| *x)
            .collect()
    };
    let kept_dts = pick(&dts);
    if kept_dts.len() < o.min_observations.max(1) {
        return HeadSample {
            observations: kept_dts.len(),
            outliers: window.len() - kept_dts.len(),
            ..gap
        };
    }
    let weights: Vec<f64> = kept_dts
        .iter()
        .map(|dt| weight(*dt, o.half_window_s * (1.0 + 1e-9)).max(1e-6))
        .collect();
    let kept_p = pick3(&positions);
    let kept_r = pick3(&rotations);
    let (p, p_rate) = local_line(&kept_dts, &weights, &kept_p);
    let (r, r_rate) = local_line(&kept_dts, &weights, &kept_r);
    let n = kept_dts.len();
    // Residual spread about the line.
    let rms = |vals: &[Vector3<f64>], a: &Vector3<f64>, b: &Vector3<f64>| {
        (vals
            .iter()
            .zip(&kept_dts)
            .map(|(v, dt)| (v - a - b * *dt).norm_squared())
            .sum::<f64>()
            / n as f64)
            .sqrt()
    };
    let root_n = (n as f64).sqrt();
    let sides = |side: Side| {
        window
            .iter()
            .zip(&keep)
            .filter(|(h, k)| **k && h.side == side)
            .count()
    };
    HeadSample {
        t_session: t,
        scene_from_marker: Some(Pose::from_parts(
            p.into(),
            reference * nalgebra::UnitQuaternion::from_scaled_axis(r),
        )),
        observations: n,
        from_left: sides(Side::Left),
        from_right: sides(Side::Right),
        outliers: window.len() - n,
        sigma_p_m: rms(&kept_p, &p, &p_rate).max(o.min_spread_m) / root_n,
        sigma_r_rad: rms(&kept_r, &r, &r_rate).max(o.min_spread_rad) / root_n,
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]

    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};

    /// A head nodding and turning while walking slowly.
    fn truth(t: f64) -> Pose {
        Pose::from_parts(
            Translation3::new(
                0.3 * t,
                0.05 * (1.3 * t).sin(),
                1.6 + 0.02 * (2.1 * t).sin(),
            ),
            UnitQuaternion::from_scaled_axis(Vector3::new(
                0.2 * (0.9 * t).sin(),
                0.15 * (1.7 * t).cos(),
                0.6 * (0.5 * t).sin(),
            )),
        )
    }

    /// A deterministic pseudo-random number in [-1, 1].
    fn noise(k: usize, salt: usize) -> f64 {
        let x = ((k * 7919 + salt * 104_729) as f64 * 0.618_033_988_75).fract();
        2.0 * x - 1.0
    }

    #[test]
    fn both_wrists_fuse_to_the_truth_outliers_are_dropped_and_gaps_stay_gaps() {
        let mut obs = Vec::new();
        // Left sees the marker in [0, 4] s, right in [3, 6] s and [8, 10] s: a gap in (6, 8).
        for (side, spans, offset) in [
            (Side::Left, vec![(0.0, 4.0)], 0.004),
            (Side::Right, vec![(3.0, 6.0), (8.0, 10.0)], 0.019),
        ] {
            for (a, b) in spans {
                let mut k = 0;
                loop {
                    let t = a + offset + k as f64 / 29.97;
                    if t > b {
                        break;
                    }
                    let mut pose = truth(t);
                    // 3 mm and 0.3° of noise; every 23rd a misdetection 15 cm and 30° off.
                    let p_noise = Vector3::new(noise(k, 1), noise(k, 2), noise(k, 3));
                    let r_noise = Vector3::new(noise(k, 4), noise(k, 5), noise(k, 6));
                    let (dp, dr) = if k % 23 == 11 {
                        (p_noise.normalize() * 0.15, r_noise.normalize() * 0.5)
                    } else {
                        (p_noise * 0.003, r_noise * 0.005)
                    };
                    pose.translation.vector += dp;
                    pose.rotation *= UnitQuaternion::from_scaled_axis(dr);
                    obs.push(HeadObservation {
                        t_session: t,
                        side,
                        scene_from_marker: pose,
                    });
                    k += 1;
                }
            }
        }
        let o = TrackOptions::default();
        let track = fuse(&obs, 0.0, 10.0, &o);
        assert_eq!(track.len(), 301);
        let (mut worst_p, mut worst_r, mut outliers) = (0.0f64, 0.0f64, 0);
        for s in &track {
            let t = s.t_session;
            let hw = o.half_window_s;
            let spans = [(0.0, 4.0), (3.0, 6.0), (8.0, 10.0)];
            // Within a half window of a span: may have a pose; well inside one: must.
            let near = spans.iter().any(|(a, b)| t >= a - hw && t <= b + hw);
            let inside = spans.iter().any(|(a, b)| t >= a + hw && t <= b - hw);
            match s.scene_from_marker {
                Some(p) => {
                    assert!(near, "a pose at {t} s, in the gap");
                    let truth = truth(t);
                    worst_p = worst_p.max((p.translation.vector - truth.translation.vector).norm());
                    worst_r = worst_r.max(p.rotation.angle_to(&truth.rotation));
                    assert!(
                        s.sigma_p_m > 0.0 && s.sigma_p_m < 0.01,
                        "{t} s: sigma {} m from {} observations",
                        s.sigma_p_m,
                        s.observations
                    );
                    outliers += s.outliers;
                }
                None => assert!(!inside, "no pose at {t} s"),
            }
        }
        eprintln!(
            "worst {:.2} mm, {:.3} deg; {outliers} outlier rejections",
            worst_p * 1e3,
            worst_r.to_degrees()
        );
        assert!(worst_p < 0.01 && worst_r < 1f64.to_radians());
        assert!(outliers > 0);
        // Both wrists shape the overlap.
        let overlap = track
            .iter()
            .find(|s| (s.t_session - 3.5).abs() < 1e-9)
            .unwrap();
        assert!(overlap.from_left > 0 && overlap.from_right > 0);
    }

    #[test]
    fn too_few_sightings_are_a_gap_and_three_agreeing_ones_a_sample() {
        let pose = truth(1.0);
        let at = |t: f64| HeadObservation {
            t_session: t,
            side: Side::Left,
            scene_from_marker: pose,
        };
        let o = TrackOptions::default();
        let sample = |obs: &[HeadObservation]| {
            *fuse(obs, 0.9, 1.1, &o)
                .iter()
                .find(|s| (s.t_session - 1.0).abs() < 1e-9)
                .unwrap()
        };
        let lone = sample(&[at(1.0), at(1.01)]);
        assert_eq!(lone.scene_from_marker, None);
        assert_eq!(lone.observations, 2);
        let three = sample(&[at(0.98), at(1.0), at(1.02)]);
        let p = three.scene_from_marker.unwrap();
        assert!((p.translation.vector - pose.translation.vector).norm() < 1e-12);
        assert!((three.sigma_p_m - o.min_spread_m / 3f64.sqrt()).abs() < 1e-15);
        assert!(
            fuse(&[], 0.0, 1.0, &o)
                .iter()
                .all(|s| s.scene_from_marker.is_none())
        );
    }

    #[test]
    fn an_observation_composes_the_rear_pose_and_the_sighting() {
        let scene_from_front = truth(0.5);
        let front_from_rear = Pose::from_parts(
            Translation3::new(0.0, 0.0, -0.03),
            UnitQuaternion::from_scaled_axis(Vector3::new(0.0, std::f64::consts::PI, 0.0)),
        );
        let rear_from_marker = Pose::from_parts(
            Translation3::new(0.1, -0.2, 0.5),
            UnitQuaternion::from_scaled_axis(Vector3::new(0.1, 0.2, 0.3)),
        );
        let got = observe(&scene_from_front, &front_from_rear, &rear_from_marker);
        let p = got * nalgebra::Point3::origin();
        let want =
            scene_from_front * (front_from_rear * (rear_from_marker * nalgebra::Point3::origin()));
        assert!((p - want).norm() < 1e-12);
    }
}
