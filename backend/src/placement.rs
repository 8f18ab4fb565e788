//! Scene placement (paper eq. 2): from synchronized localizations of the mapping episode in the
//! front map (`front_map_from_front`) and in the rear/scene map (`scene_from_rear`), and the
//! unit's fixed `rear_from_front` = `E_a`, fit `scene_from_front_map` robustly.
//!
//! Each synchronized pair gives a candidate rotation from
//! `scene_from_rear · E_a · front_map_from_front⁻¹` and a point correspondence: the front camera
//! centre in the front map `p_k` and, through the rear localization and `E_a`, in the scene `q_k`.
//! The rotation is a weighted geodesic L1 mean of the candidates; the translation is fitted to
//! the camera centres (`t = mean(q_k − R p_k)`), which keeps rotation noise from being amplified
//! by the lever arm to the map origin. The fit starts from the candidate most pairs agree with
//! within the inlier thresholds (maximum consensus, as RANSAC's): where a lens was localized at
//! a look-alike place of a repeated room for part of the episode, the pairs form two groups and
//! the larger one that holds together is taken; which of two such groups is right is not
//! decided here (the placement's inlier share reports it). From there, iteratively
//! reweighted least squares uses a Huber weight on the residual whitened by
//! [`PlacementConfig`]'s scales, and pairs outside the inlier thresholds no weight. Inliers are
//! pairs whose residual is within the inlier thresholds; statistics are reported over them.

use kiwi_core::geometry::{Pose, average_rotations, rotation_angle_between};
use nalgebra::{Isometry3, Translation3, Vector3};

use crate::error::{BackendError, Result};

/// One synchronized pair of localizations.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlacementPair {
    /// Time (s), for reporting.
    pub t: f64,
    /// Front camera pose in the front map.
    pub front_map_from_front: Pose,
    /// Rear camera pose in the scene (rear) map.
    pub scene_from_rear: Pose,
}

/// Robust-fit settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlacementConfig {
    /// Position scale of the Huber loss (m).
    pub sigma_position_m: f64,
    /// Rotation scale of the Huber loss (rad).
    pub sigma_rotation_rad: f64,
    /// Huber threshold on the whitened residual.
    pub huber_k: f64,
    /// Pairs with a larger position residual are outliers (m).
    pub inlier_position_m: f64,
    /// Pairs with a larger rotation residual are outliers (rad).
    pub inlier_rotation_rad: f64,
}

impl Default for PlacementConfig {
    fn default() -> Self {
        Self {
            // Visual localization noise on metric maps: a few mm, a few tenths of a degree.
            sigma_position_m: 3e-3,
            sigma_rotation_rad: 0.3f64.to_radians(),
            huber_k: 2.0,
            // Well outside the noise: a relocalization this far off is a failure.
            inlier_position_m: 0.03,
            inlier_rotation_rad: 2f64.to_radians(),
        }
    }
}

/// The fitted placement and its inlier statistics.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Placement {
    /// `scene_from_front_map`.
    pub scene_from_front_map: Pose,
    /// Pairs used.
    pub pairs: usize,
    /// Pairs within the inlier thresholds.
    pub inliers: usize,
    /// RMS position residual of the inliers (m).
    pub rms_position_m: f64,
    /// RMS rotation residual of the inliers (rad).
    pub rms_rotation_rad: f64,
}

/// IRLS rounds: the fit settles in a handful; more is cheap.
const IRLS_ROUNDS: usize = 20;
/// Most candidates tried for the consensus start, evenly spread over the pairs: a run of a
/// second or more holds several even in a 60 s episode at 120 Hz, and the count stays
/// linear in the pairs.
const MAX_CONSENSUS_CANDIDATES: usize = 500;
/// Fewest pairs that make a placement trustworthy.
pub const MIN_PAIRS: usize = 3;

/// Fit `scene_from_front_map` from synchronized pairs and `rear_from_front` (`E_a`).
pub fn place(
    pairs: &[PlacementPair],
    rear_from_front: &Pose,
    config: &PlacementConfig,
) -> Result<Placement> {
    if pairs.len() < MIN_PAIRS {
        return Err(BackendError::Estimation(format!(
            "placement needs at least {MIN_PAIRS} synchronized front/rear localizations, found {}; \
             relocalize more of the mapping episode",
            pairs.len()
        )));
    }
    let candidates: Vec<Pose> = pairs
        .iter()
        .map(|p| p.scene_from_rear * rear_from_front * p.front_map_from_front.inverse())
        .collect();
    // Front camera centres in the front map and (via the rear localization) in the scene.
    let p_front: Vec<Vector3<f64>> = pairs
        .iter()
        .map(|p| p.front_map_from_front.translation.vector)
        .collect();
    let q_scene: Vec<Vector3<f64>> = pairs
        .iter()
        .map(|p| (p.scene_from_rear * rear_from_front).translation.vector)
        .collect();
    let rotations: Vec<_> = candidates.iter().map(|c| c.rotation).collect();
    let offsets = |r: &nalgebra::UnitQuaternion<f64>| -> Vec<Vector3<f64>> {
        p_front
            .iter()
            .zip(&q_scene)
            .map(|(p, q)| q - r * p)
            .collect()
    };
    let residuals = |est: &Pose| -> Vec<(f64, f64)> {
        candidates
            .iter()
            .zip(p_front.iter().zip(&q_scene))
            .map(|(c, (p, q))| {
                (
                    (est * nalgebra::Point3::from(*p) - nalgebra::Point3::from(*q)).norm(),
                    rotation_angle_between(&c.rotation, &est.rotation),
                )
            })
            .collect()
    };
    let is_inlier =
        |(p, r): &(f64, f64)| *p <= config.inlier_position_m && *r <= config.inlier_rotation_rad;
    let stride = candidates.len().div_ceil(MAX_CONSENSUS_CANDIDATES).max(1);
    let mut start: Option<(usize, Pose)> = None;
    for candidate in candidates.iter().step_by(stride) {
        let support = residuals(candidate).iter().filter(|r| is_inlier(r)).count();
        if start.is_none_or(|(best, _)| support > best) {
            start = Some((support, *candidate));
        }
    }
    let (_, mut estimate) = start
        .ok_or_else(|| BackendError::Estimation("placement: no candidate to start from".into()))?;
    let huber = |(p, r): &(f64, f64)| {
        let s = ((p / config.sigma_position_m).powi(2) + (r / config.sigma_rotation_rad).powi(2))
            .sqrt();
        if s <= config.huber_k {
            1.0
        } else {
            config.huber_k / s
        }
    };
    for _ in 0..IRLS_ROUNDS {
        let res = residuals(&estimate);
        let mut weights: Vec<f64> = res
            .iter()
            .map(|r| if is_inlier(r) { huber(r) } else { 0.0 })
            .collect();
        if weights.iter().sum::<f64>() <= 0.0 {
            // No pair within the thresholds: every pair by its Huber weight.
            weights = res.iter().map(huber).collect();
        }
        let total: f64 = weights.iter().sum();
        let r = average_rotations(&rotations, Some(&weights)).unwrap_or(estimate.rotation);
        let t = offsets(&r)
            .iter()
            .zip(&weights)
            .fold(Vector3::zeros(), |acc, (o, w)| acc + o * *w)
            / total;
        estimate = Isometry3::from_parts(Translation3::from(t), r);
    }
    let res = residuals(&estimate);
    let inl: Vec<&(f64, f64)> = res.iter().filter(|r| is_inlier(r)).collect();
    let n = inl.len().max(1) as f64;
    Ok(Placement {
        scene_from_front_map: estimate,
        pairs: pairs.len(),
        inliers: inl.len(),
        rms_position_m: (inl.iter().map(|(p, _)| p * p).sum::<f64>() / n).sqrt(),
        rms_rotation_rad: (inl.iter().map(|(_, r)| r * r).sum::<f64>() / n).sqrt(),
    })
}
