//! Per-wrist visual–inertial fusion (paper eq. 4, `eq:state-objective`): one node per
//! front-camera frame with state
//! `scene_from_imu`, velocity and biases; IMU preintegration between consecutive nodes; robust
//! unary pose factors from front and rear observations `Z = scene_from_cam · cam_from_imu`.
//!
//! - Observations of a source are attached to a node when one lies within
//!   [`FusionConfig::match_tolerance_s`] of it, or else interpolated (SO(3) geodesic + linear
//!   translation) between the two neighbouring observations of that source only when they are
//!   at most [`FusionConfig::max_interpolation_gap_s`] apart (a contiguous tracked run).
//! - Visual factors may be thinned per source to [`FusionConfig::visual_rate_hz`]; every frame
//!   stays a node.
//! - The first node has a velocity prior and a zero-centred bias prior.
//! - IMU samples are integrated between node times piecewise: each sub-interval between
//!   consecutive breakpoints (node times and sample times) uses the linearly interpolated
//!   measurement at its midpoint.

pub mod chain;
pub mod factors;
pub mod preint;

use kiwi_core::geometry::{Pose, interpolate_pose, se3_adjoint};
use kiwi_core::imu::ImuSample;
use nalgebra::{Matrix6, Vector3};

use self::chain::{ChainProblem, ImuNoiseModel, LmSettings, PoseFactor, pose_sigmas};
use self::factors::NavNode;
use self::preint::{ImuBias, ImuParams, Preintegrated};
use crate::error::{BackendError, Result};

/// Which camera an observation comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Source {
    /// The front lens (native node clock).
    Front,
    /// The rear lens (scene map), interpolated to node times.
    Rear,
}

impl Source {
    /// Name used in files.
    pub fn name(self) -> &'static str {
        match self {
            Self::Front => "front",
            Self::Rear => "rear",
        }
    }

    fn index(self) -> usize {
        match self {
            Self::Front => 0,
            Self::Rear => 1,
        }
    }
}

/// A visual body observation: `scene_from_imu` at IMU-clock time `t`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PoseObservation {
    /// Time on the IMU clock (s).
    pub t: f64,
    /// The camera that produced it.
    pub source: Source,
    /// Observed `scene_from_imu`.
    pub scene_from_imu: Pose,
}

/// Noise of one observation source.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PoseSigma {
    /// Position sigma (m).
    pub position_m: f64,
    /// Rotation sigma (rad).
    pub rotation_rad: f64,
}

/// Fusion settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FusionConfig {
    /// Noise of front observations.
    pub front_sigma: PoseSigma,
    /// Noise of rear observations.
    pub rear_sigma: PoseSigma,
    /// Huber threshold on the whitened 6-dof residual norm (`None`: no robust loss).
    pub huber_k: Option<f64>,
    /// Longest gap between two observations of a source that may be interpolated (s).
    pub max_interpolation_gap_s: f64,
    /// An observation this close to a node is used as is (s).
    pub match_tolerance_s: f64,
    /// Keep at most this many visual factors per second and source (`None`: all).
    pub visual_rate_hz: Option<f64>,
    /// Sigma of the zero-mean prior on the first node's velocity (m/s).
    pub velocity_prior_sigma: f64,
    /// Sigma of the zero prior on the first node's accelerometer bias (m/s²).
    pub bias_prior_sigma_acc: f64,
    /// Sigma of the zero prior on the first node's gyro bias (rad/s).
    pub bias_prior_sigma_gyro: f64,
    /// IMU noise model.
    pub imu_noise: ImuNoiseModel,
    /// Solver settings.
    pub lm: LmSettings,
}

/// Default Huber threshold: √χ²₆(0.95), so 95 % of inlier 6-dof residuals stay quadratic.
pub const DEFAULT_HUBER_K: f64 = 3.55;
/// Default front noise: 1 mm, 0.1° (visual localization on a metric map).
pub const DEFAULT_FRONT_SIGMA: PoseSigma = PoseSigma {
    position_m: 1e-3,
    rotation_rad: 1.745e-3,
};
/// Default rear noise: 2 mm, 0.2° (scene map, interpolated).
pub const DEFAULT_REAR_SIGMA: PoseSigma = PoseSigma {
    position_m: 2e-3,
    rotation_rad: 3.49e-3,
};
/// Smallest visual position noise taken from the lenses' disagreement (m): below a millimetre
/// one frame's localization does not resolve it, and a zero noise would overrule the IMU.
pub const MIN_VISUAL_SIGMA_POSITION_M: f64 = 1e-3;
/// Smallest visual rotation noise taken from the lenses' disagreement (rad): 0.05°.
pub const MIN_VISUAL_SIGMA_ROTATION_RAD: f64 = 8.7e-4;

/// The visual noise of each lens of a wrist from how much its two lenses disagree about the
/// same rigid body: the placement's RMS residuals (eq. 2) over the mapping episode.
///
/// The two lenses localize in maps built the same way from the same kind of images, and their
/// errors (mostly each map's own distortion, which is correlated over seconds) are independent,
/// so the disagreement's RMS is √2 times each lens's noise and both get the same share. The
/// fixed defaults, which trust the front lens twice as much, are for inputs with no placement.
pub fn visual_sigma_from_disagreement(rms_position_m: f64, rms_rotation_rad: f64) -> PoseSigma {
    let share = |rms: f64, floor: f64| {
        if rms.is_finite() {
            (rms / std::f64::consts::SQRT_2).max(floor)
        } else {
            floor
        }
    };
    PoseSigma {
        position_m: share(rms_position_m, MIN_VISUAL_SIGMA_POSITION_M),
        rotation_rad: share(rms_rotation_rad, MIN_VISUAL_SIGMA_ROTATION_RAD),
    }
}

/// Longest interpolated gap: the 50 ms contiguous-run limit.
pub const DEFAULT_MAX_INTERPOLATION_GAP_S: f64 = 0.05;
/// Same-frame tolerance: well below one frame period at 120 fps (8.3 ms).
pub const DEFAULT_MATCH_TOLERANCE_S: f64 = 1e-3;

impl FusionConfig {
    /// The noise of `source`'s observations.
    pub fn sigma(&self, source: Source) -> PoseSigma {
        match source {
            Source::Front => self.front_sigma,
            Source::Rear => self.rear_sigma,
        }
    }
}

impl Default for FusionConfig {
    fn default() -> Self {
        Self {
            front_sigma: DEFAULT_FRONT_SIGMA,
            rear_sigma: DEFAULT_REAR_SIGMA,
            huber_k: Some(DEFAULT_HUBER_K),
            max_interpolation_gap_s: DEFAULT_MAX_INTERPOLATION_GAP_S,
            match_tolerance_s: DEFAULT_MATCH_TOLERANCE_S,
            visual_rate_hz: None,
            // A hand moves at most a few m/s; the prior only fixes the gauge before data.
            velocity_prior_sigma: 1.0,
            // Consumer MEMS turn-on biases are a few 0.01 m/s² and 0.1°/s.
            bias_prior_sigma_acc: 0.2,
            bias_prior_sigma_gyro: 0.02,
            imu_noise: ImuNoiseModel::Full,
            lm: LmSettings::default(),
        }
    }
}

/// Which factors constrain a node: the final Huber weight per source (if any).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Support {
    /// Weight of the front factor (1 = inlier).
    pub front: Option<f64>,
    /// Weight of the rear factor.
    pub rear: Option<f64>,
    /// Whether the rear factor was interpolated between two rear observations of a tracked run
    /// (rather than taken at the node's own time).
    pub rear_interpolated: bool,
}

impl Support {
    /// `front`, `rear`, `front+rear` or `imu`; a Huber-downweighted factor carries a `*`.
    pub fn label(&self) -> String {
        let tag = |name: &str, w: f64| {
            if w < 1.0 {
                format!("{name}*")
            } else {
                name.to_string()
            }
        };
        match (self.front, self.rear) {
            (Some(f), Some(r)) => format!("{}+{}", tag("front", f), tag("rear", r)),
            (Some(f), None) => tag("front", f),
            (None, Some(r)) => tag("rear", r),
            (None, None) => "imu".to_string(),
        }
    }
}

/// One fused node.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FusedNode {
    /// Node time on the IMU clock (s).
    pub t: f64,
    /// Estimated `scene_from_imu`.
    pub scene_from_imu: Pose,
    /// Velocity in the scene (m/s).
    pub velocity: Vector3<f64>,
    /// IMU biases.
    pub bias: ImuBias,
    /// Marginal 6×6 covariance of the pose (`[rot; trans]`, body-frame perturbation).
    pub pose_cov: Matrix6<f64>,
    /// Factors that supported the node.
    pub support: Support,
}

impl FusedNode {
    /// `scene_from_cam` for a lens with `cam_from_imu`, and its position and rotation sigmas.
    pub fn camera_pose(&self, cam_from_imu: &Pose) -> (Pose, f64, f64) {
        let ad = se3_adjoint(cam_from_imu);
        let cov = ad * self.pose_cov * ad.transpose();
        let (sp, sr) = pose_sigmas(&cov);
        (self.scene_from_imu * cam_from_imu.inverse(), sp, sr)
    }
}

impl FusedNode {
    /// The node carried `dt` seconds along the IMU (negative: earlier), e.g. from a
    /// rolling-shutter frame's exposure centre, where its visual observations are exact, back to
    /// the frame's timestamp (its first row). Constant angular rate and acceleration over `dt`
    /// (a few milliseconds): rotation by the bias-corrected gyro, position and velocity by the
    /// velocity and the gravity-compensated acceleration. The covariance is kept.
    pub fn carried(&self, imu: &ImuSample, gravity: &Vector3<f64>, dt: f64) -> FusedNode {
        let rotation = self.scene_from_imu.rotation;
        let omega = imu.gyro - self.bias.gyro;
        let acceleration = rotation * (imu.accel - self.bias.acc) + gravity;
        let position = self.scene_from_imu.translation.vector
            + self.velocity * dt
            + 0.5 * acceleration * dt * dt;
        let mut node = *self;
        node.t = self.t + dt;
        node.scene_from_imu = Pose::from_parts(
            nalgebra::Translation3::from(position),
            rotation * kiwi_core::geometry::so3_exp(&(omega * dt)),
        );
        node.velocity = self.velocity + acceleration * dt;
        node
    }
}

/// The fused trajectory and solver statistics.
#[derive(Debug, Clone)]
pub struct FusionResult {
    /// One entry per node.
    pub nodes: Vec<FusedNode>,
    /// Visual factors in the graph.
    pub observations_used: usize,
    /// Visual factors whose final Huber weight is below one.
    pub outliers_downweighted: usize,
    /// Solver iterations.
    pub iterations: usize,
    /// Cost at the initial values.
    pub initial_cost: f64,
    /// Cost at the solution.
    pub final_cost: f64,
}

fn err(message: String) -> BackendError {
    BackendError::Estimation(message)
}

/// Largest spacing of IMU samples integrated across (s): ten samples at 200 Hz, far above any
/// jitter of a healthy log, far below the time in which hand motion stops being interpolable.
pub const MAX_IMU_GAP_S: f64 = 0.05;

/// Linear interpolation of IMU samples at `t`, with `samples[i].t <= t <= samples[i+1].t`.
fn imu_at(samples: &[ImuSample], i: usize, t: f64) -> (Vector3<f64>, Vector3<f64>) {
    let a = &samples[i];
    let Some(b) = samples.get(i + 1) else {
        return (a.accel, a.gyro);
    };
    let span = b.t - a.t;
    let s = if span > 0.0 {
        ((t - a.t) / span).clamp(0.0, 1.0)
    } else {
        0.0
    };
    (
        a.accel + (b.accel - a.accel) * s,
        a.gyro + (b.gyro - a.gyro) * s,
    )
}

/// Preintegrate the IMU between consecutive node times.
pub fn preintegrate_nodes(
    samples: &[ImuSample],
    params: &ImuParams,
    node_times: &[f64],
    bias_hat: ImuBias,
) -> Result<Vec<Preintegrated>> {
    let (Some(first), Some(last)) = (samples.first(), samples.last()) else {
        return Err(err("the IMU log is empty".into()));
    };
    let (Some(&t0), Some(&tn)) = (node_times.first(), node_times.last()) else {
        return Err(err("no node timestamps".into()));
    };
    if t0 < first.t || tn > last.t {
        return Err(err(format!(
            "frames span {t0:.6}..{tn:.6} s but the IMU covers only {:.6}..{:.6} s on the same \
             clock; check the time shift or trim the frame list",
            first.t, last.t
        )));
    }
    // Refuse to invent IMU data across a dropout inside the span the nodes use.
    let first_used = samples.partition_point(|s| s.t <= t0).saturating_sub(1);
    let last_used = samples.partition_point(|s| s.t < tn).min(samples.len() - 1);
    if let Some(w) = samples[first_used..=last_used]
        .windows(2)
        .find(|w| w[1].t - w[0].t > MAX_IMU_GAP_S)
    {
        return Err(err(format!(
            "the IMU log has a gap of {:.1} ms between {:.6} s and {:.6} s (limit {:.0} ms), \
             inside the frames' span; integrating across it would invent motion. Split the \
             episode at the gap or drop the frames around it",
            (w[1].t - w[0].t) * 1e3,
            w[0].t,
            w[1].t,
            MAX_IMU_GAP_S * 1e3
        )));
    }
    let mut out = Vec::with_capacity(node_times.len().saturating_sub(1));
    let mut i = 0;
    for w in node_times.windows(2) {
        let (ta, tb) = (w[0], w[1]);
        while i + 1 < samples.len() && samples[i + 1].t <= ta {
            i += 1;
        }
        let mut pim = Preintegrated::new(bias_hat);
        let mut cur = ta;
        let mut j = i;
        while cur < tb {
            let next = samples.get(j + 1).map_or(tb, |s| s.t.min(tb));
            let next = if next <= cur { tb } else { next };
            let (acc, gyro) = imu_at(samples, j, 0.5 * (cur + next));
            // GTSAM rotates a step's specific force by the attitude at the step's start: a lag
            // of half a step that biases Δv by ½|ω|·dt·|a| per step along ω × a (gravity
            // included), ~2.5e-3 m/s² at 0.5 rad/s and 1 kHz, enough to shift a recovered map
            // scale by 0.1 %. Turning the sample by half the step's rotation evaluates it at the
            // step's midpoint instead (second order); `integrate` itself stays GTSAM's.
            let half_turn =
                factors::rotation_matrix(&((gyro - bias_hat.gyro) * (0.5 * (next - cur))));
            let acc = half_turn * (acc - bias_hat.acc) + bias_hat.acc;
            pim.integrate(params, &acc, &gyro, next - cur);
            cur = next;
            if j + 1 < samples.len() && samples[j + 1].t <= cur {
                j += 1;
            }
        }
        out.push(pim);
    }
    Ok(out)
}

/// The observation of a source at node time `t`: one within the match tolerance, else one
/// interpolated between its neighbours when they are close enough (`true` = interpolated).
fn observation_at(obs: &[PoseObservation], t: f64, config: &FusionConfig) -> Option<(Pose, bool)> {
    let k = obs.partition_point(|o| o.t < t);
    let after = obs.get(k);
    let before = k.checked_sub(1).and_then(|i| obs.get(i));
    let close = |o: &&PoseObservation| (o.t - t).abs() <= config.match_tolerance_s;
    match (before, after) {
        (_, Some(a)) if close(&a) => Some((a.scene_from_imu, false)),
        (Some(b), _) if close(&b) => Some((b.scene_from_imu, false)),
        (Some(b), Some(a)) if a.t - b.t <= config.max_interpolation_gap_s => {
            let s = (t - b.t) / (a.t - b.t);
            Some((
                interpolate_pose(&b.scene_from_imu, &a.scene_from_imu, s),
                true,
            ))
        }
        _ => None,
    }
}

fn check_times(times: &[f64], what: &str) -> Result<()> {
    for (k, w) in times.windows(2).enumerate() {
        if w[1].partial_cmp(&w[0]) != Some(std::cmp::Ordering::Greater) {
            return Err(err(format!(
                "{what}: time {} at row {} does not increase after {}; sort the rows and drop \
                 duplicates",
                w[1],
                k + 2,
                w[0]
            )));
        }
    }
    if let Some(t) = times.iter().find(|t| !t.is_finite()) {
        return Err(err(format!("{what}: non-finite time {t}")));
    }
    Ok(())
}

/// Fuse IMU and visual pose observations at the node times (all on the IMU clock).
pub fn fuse(
    imu: &[ImuSample],
    params: &ImuParams,
    node_times: &[f64],
    observations: &[PoseObservation],
    config: &FusionConfig,
) -> Result<FusionResult> {
    if node_times.len() < 2 {
        return Err(err(format!(
            "need at least 2 nodes, found {}",
            node_times.len()
        )));
    }
    check_times(node_times, "frames")?;
    let mut per_source: [Vec<PoseObservation>; 2] = [Vec::new(), Vec::new()];
    for o in observations {
        let finite = o.t.is_finite()
            && o.scene_from_imu
                .translation
                .vector
                .iter()
                .all(|v| v.is_finite())
            && o.scene_from_imu
                .rotation
                .coords
                .iter()
                .all(|v| v.is_finite());
        if !finite {
            return Err(err(format!("observation at t = {} is not finite", o.t)));
        }
        per_source[o.source.index()].push(*o);
    }
    for list in &mut per_source {
        list.sort_by(|a, b| a.t.total_cmp(&b.t));
    }
    let pims = preintegrate_nodes(imu, params, node_times, ImuBias::default())?;

    // Visual factors per node, thinned per source.
    let mut factors = Vec::new();
    let mut interpolated_rear = Vec::new();
    let mut last_kept = [f64::NEG_INFINITY; 2];
    let min_spacing = config
        .visual_rate_hz
        .filter(|r| *r > 0.0)
        .map_or(0.0, |r| 1.0 / r);
    for (k, &t) in node_times.iter().enumerate() {
        for source in [Source::Front, Source::Rear] {
            let s = source.index();
            // Half a node period of slack so a 30 Hz rate keeps every fourth 120 Hz frame.
            if t - last_kept[s] < min_spacing - config.match_tolerance_s {
                continue;
            }
            if let Some((z, interpolated)) = observation_at(&per_source[s], t, config) {
                if source == Source::Rear && interpolated {
                    interpolated_rear.push(k);
                }
                let sigma = config.sigma(source);
                factors.push(PoseFactor {
                    node: k,
                    z,
                    sigma_rot: sigma.rotation_rad,
                    sigma_pos: sigma.position_m,
                    tag: s as u8,
                });
                last_kept[s] = t;
            }
        }
    }
    if factors.is_empty() {
        return Err(err(
            "no visual observation falls on or between node times; check that frames.csv and \
             obs.csv use the same clock"
                .into(),
        ));
    }

    // Initial poses: the node's own observation, else interpolated between observed nodes.
    let n = node_times.len();
    let mut init: Vec<Option<Pose>> = vec![None; n];
    for f in factors.iter().rev() {
        init[f.node] = Some(f.z);
    }
    let observed: Vec<usize> = (0..n).filter(|&k| init[k].is_some()).collect();
    let mut poses = Vec::with_capacity(n);
    let mut next = 0;
    for k in 0..n {
        while next < observed.len() && observed[next] < k {
            next += 1;
        }
        let pose = match init[k] {
            Some(p) => p,
            None => {
                let after = observed.get(next).copied();
                let before = next.checked_sub(1).and_then(|i| observed.get(i)).copied();
                match (before, after) {
                    (Some(b), Some(a)) => {
                        let (Some(pb), Some(pa)) = (init[b], init[a]) else {
                            return Err(err("internal: missing initial pose".into()));
                        };
                        let s = (node_times[k] - node_times[b]) / (node_times[a] - node_times[b]);
                        interpolate_pose(&pb, &pa, s)
                    }
                    (Some(i), None) | (None, Some(i)) => {
                        init[i].ok_or_else(|| err("internal: missing initial pose".into()))?
                    }
                    (None, None) => return Err(err("internal: no observed node".into())),
                }
            }
        };
        poses.push(pose);
    }
    let nodes: Vec<NavNode> = (0..n)
        .map(|k| {
            let (a, b) = (k.saturating_sub(1), (k + 1).min(n - 1));
            let v = (poses[b].translation.vector - poses[a].translation.vector)
                / (node_times[b] - node_times[a]);
            NavNode::from_pose(&poses[k], v)
        })
        .collect();
    let v0 = Vector3::zeros();
    let problem = ChainProblem {
        gravity: params.gravity,
        nodes,
        imu: pims,
        pose_factors: factors,
        huber_k: config.huber_k,
        imu_noise: config.imu_noise,
        velocity_prior: Some((v0, config.velocity_prior_sigma)),
        bias_prior: Some((
            ImuBias::default(),
            config.bias_prior_sigma_acc,
            config.bias_prior_sigma_gyro,
        )),
    };
    let sol = problem.solve_lm(&config.lm);
    let mut support = vec![Support::default(); n];
    for &k in &interpolated_rear {
        support[k].rear_interpolated = true;
    }
    let mut outliers = 0;
    for (f, &w) in problem.pose_factors.iter().zip(&sol.pose_weights) {
        if w < 1.0 {
            outliers += 1;
        }
        if f.tag == 0 {
            support[f.node].front = Some(w);
        } else {
            support[f.node].rear = Some(w);
        }
    }
    let nodes = sol
        .nodes
        .iter()
        .enumerate()
        .map(|(k, x)| FusedNode {
            t: node_times[k],
            scene_from_imu: x.pose(),
            velocity: x.velocity,
            bias: x.bias,
            pose_cov: sol
                .marginals
                .get(k)
                .map_or_else(Matrix6::zeros, |m| m.fixed_view::<6, 6>(0, 0).into_owned()),
            support: support[k],
        })
        .collect();
    Ok(FusionResult {
        nodes,
        observations_used: problem.pose_factors.len(),
        outliers_downweighted: outliers,
        iterations: sol.iterations,
        initial_cost: sol.initial_cost,
        final_cost: sol.final_cost,
    })
}

/// How well the fused trajectory agrees with one source's observations.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SourceResiduals {
    /// Nodes with an observation of this source.
    pub observations: usize,
    /// Of those, interpolated between two observations of a tracked run.
    pub interpolated: usize,
    /// Down-weighted by the Huber loss.
    pub downweighted: usize,
    /// Median position residual (m).
    pub median_position_m: f64,
    /// 95th-percentile position residual (m).
    pub p95_position_m: f64,
    /// Median rotation residual (rad).
    pub median_rotation_rad: f64,
    /// 95th-percentile rotation residual (rad).
    pub p95_rotation_rad: f64,
    /// Position noise the graph gave this source (m).
    #[serde(default)]
    pub sigma_position_m: f64,
    /// Rotation noise the graph gave this source (rad).
    #[serde(default)]
    pub sigma_rotation_rad: f64,
}

/// Solver and residual statistics of a fusion run, for the quality record.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct FusionStatistics {
    /// Nodes (front frames).
    pub nodes: usize,
    /// Visual factors in the graph.
    pub observations_used: usize,
    /// Visual factors down-weighted by the Huber loss.
    pub outliers_downweighted: usize,
    /// Solver iterations.
    pub iterations: usize,
    /// Cost at the initial values.
    pub initial_cost: f64,
    /// Cost at the solution.
    pub final_cost: f64,
    /// Front-lens observations against the solution.
    pub front: SourceResiduals,
    /// Rear-lens observations against the solution.
    pub rear: SourceResiduals,
}

fn percentile(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return 0.0;
    }
    let k = ((sorted.len() - 1) as f64 * p).round() as usize;
    sorted[k.min(sorted.len() - 1)]
}

/// Residuals of each source's observations (taken at the node as the graph took them) against
/// the fused poses.
pub fn residual_statistics(
    result: &FusionResult,
    observations: &[PoseObservation],
    config: &FusionConfig,
) -> FusionStatistics {
    let mut per_source: [Vec<PoseObservation>; 2] = [Vec::new(), Vec::new()];
    for o in observations {
        per_source[o.source.index()].push(*o);
    }
    for list in &mut per_source {
        list.sort_by(|a, b| a.t.total_cmp(&b.t));
    }
    let mut stats = [SourceResiduals::default(); 2];
    for source in [Source::Front, Source::Rear] {
        let s = source.index();
        let (mut pos, mut rot) = (Vec::new(), Vec::new());
        for node in &result.nodes {
            let weight = match source {
                Source::Front => node.support.front,
                Source::Rear => node.support.rear,
            };
            let Some(w) = weight else { continue };
            let Some((z, interpolated)) = observation_at(&per_source[s], node.t, config) else {
                continue;
            };
            let e = z.inverse() * node.scene_from_imu;
            pos.push(e.translation.vector.norm());
            rot.push(e.rotation.angle());
            stats[s].observations += 1;
            stats[s].interpolated += usize::from(interpolated);
            stats[s].downweighted += usize::from(w < 1.0);
        }
        pos.sort_by(f64::total_cmp);
        rot.sort_by(f64::total_cmp);
        stats[s].median_position_m = percentile(&pos, 0.5);
        stats[s].p95_position_m = percentile(&pos, 0.95);
        stats[s].median_rotation_rad = percentile(&rot, 0.5);
        stats[s].p95_rotation_rad = percentile(&rot, 0.95);
        let sigma = config.sigma(source);
        stats[s].sigma_position_m = sigma.position_m;
        stats[s].sigma_rotation_rad = sigma.rotation_rad;
    }
    FusionStatistics {
        nodes: result.nodes.len(),
        observations_used: result.observations_used,
        outliers_downweighted: result.outliers_downweighted,
        iterations: result.iterations,
        initial_cost: result.initial_cost,
        final_cost: result.final_cost,
        front: stats[0],
        rear: stats[1],
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn log_with_hole(hole: (f64, f64)) -> Vec<ImuSample> {
        (0..2000)
            .map(|k| k as f64 * 1e-3)
            .filter(|t| !(hole.0..hole.1).contains(t))
            .map(|t| ImuSample::new(t, Vector3::zeros(), Vector3::new(0.0, 0.0, 9.81)))
            .collect()
    }

    #[test]
    fn imu_gaps_inside_the_frames_are_refused_not_bridged() {
        let params = ImuParams::from_densities(1e-3, 1e-5, 1e-2, 1e-4, 9.81);
        let samples = log_with_hole((1.0, 1.1));
        let nodes: Vec<f64> = (1..19).map(|k| k as f64 * 0.1).collect();
        let e = preintegrate_nodes(&samples, &params, &nodes, ImuBias::default())
            .err()
            .map(|e| e.to_string())
            .unwrap_or_default();
        assert!(
            e.contains("gap of 101.0 ms") && e.contains("0.999000"),
            "{e}"
        );
        // Frames that stay clear of the hole integrate normally.
        let before: Vec<f64> = (1..9).map(|k| k as f64 * 0.1).collect();
        assert!(preintegrate_nodes(&samples, &params, &before, ImuBias::default()).is_ok());
    }

    #[test]
    fn visual_noise_is_the_lenses_disagreement_shared_equally() {
        let s = visual_sigma_from_disagreement(8e-3, 0.2f64.to_radians());
        assert!((s.position_m - 8e-3 / 2f64.sqrt()).abs() < 1e-12);
        assert!((s.rotation_rad - 0.2f64.to_radians() / 2f64.sqrt()).abs() < 1e-12);
        // Agreement below what a frame resolves, or no figure at all: the floors.
        let tiny = visual_sigma_from_disagreement(1e-5, 1e-6);
        assert_eq!(tiny.position_m, MIN_VISUAL_SIGMA_POSITION_M);
        assert_eq!(tiny.rotation_rad, MIN_VISUAL_SIGMA_ROTATION_RAD);
        let none = visual_sigma_from_disagreement(f64::NAN, f64::INFINITY);
        assert_eq!(none.position_m, MIN_VISUAL_SIGMA_POSITION_M);
        assert_eq!(none.rotation_rad, MIN_VISUAL_SIGMA_ROTATION_RAD);
    }
}
