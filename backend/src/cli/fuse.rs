//! `kiwi fuse`: fuse a wrist's IMU with visual pose observations from CSV files (paper eq. 4),
//! for experts who run the stages one by one.

use std::path::PathBuf;

use anyhow::Result;

use kiwi_backend::formats::calibration::{imu_params, load_lens_calibration};
use kiwi_backend::formats::tables::{
    TrajectoryRow, read_frames, read_observations, write_trajectory,
};
use kiwi_backend::fusion::{FusionConfig, PoseSigma, fuse};
use kiwi_core::geometry::Pose;
use kiwi_core::imu::ImuSeries;

use super::named;

/// Arguments of `kiwi fuse`.
#[derive(Debug, clap::Args)]
pub struct FuseArgs {
    /// The IMU log (imu.csv).
    #[arg(long)]
    pub imu: PathBuf,
    /// Node timestamps (first column `t`).
    #[arg(long)]
    pub frames: PathBuf,
    /// Visual pose observations.
    #[arg(long)]
    pub observations: PathBuf,
    /// Unit calibration.json (IMU noise, cam_from_imu and time shift of --lens).
    #[arg(long)]
    pub calibration: Option<PathBuf>,
    /// The lens whose frames are the nodes.
    #[arg(long, default_value = "front")]
    pub lens: String,
    /// IMU noise GN,GW,AN,AW: gyro noise (rad/s/√Hz), gyro random walk (rad/s²/√Hz),
    /// accel noise (m/s²/√Hz), accel random walk (m/s³/√Hz).
    #[arg(long, value_name = "GN,GW,AN,AW")]
    pub imu_noise: Option<String>,
    /// Pose noise of a source: SOURCE=METRES,RADIANS [defaults: front=0.001,0.001745,
    /// rear=0.002,0.00349].
    #[arg(long = "pose-sigma", value_name = "SOURCE=M,RAD")]
    pub pose_sigma: Vec<String>,
    /// Huber threshold on the whitened 6-dof residual norm; 0 disables it [default: 3.55].
    #[arg(long, value_parser = kiwi_core::args::finite)]
    pub huber: Option<f64>,
    /// Keep at most this many visual factors per second and source (every frame stays a
    /// node) [default: all].
    #[arg(long, value_parser = kiwi_core::args::positive)]
    pub visual_rate: Option<f64>,
    /// Output trajectory CSV.
    #[arg(long)]
    pub out: PathBuf,
    /// Print a JSON summary.
    #[arg(long)]
    pub json: bool,
}

/// Run `kiwi fuse`.
pub fn run_fuse_cmd(args: FuseArgs) -> Result<()> {
    let FuseArgs {
        imu,
        frames,
        observations,
        calibration,
        lens,
        imu_noise,
        pose_sigma,
        huber,
        visual_rate,
        out,
        json,
    } = args;
    let mut config = FusionConfig::default();
    for arg in &pose_sigma {
        let (name, value) = named(arg, "--pose-sigma")?;
        let parts: Vec<f64> = value
            .split(',')
            .map(|v| v.trim().parse::<f64>())
            .collect::<std::result::Result<_, _>>()
            .map_err(|_| anyhow::anyhow!("--pose-sigma {arg}: expected SOURCE=METRES,RADIANS"))?;
        let [p, r] = parts[..] else {
            anyhow::bail!("--pose-sigma {arg}: expected SOURCE=METRES,RADIANS");
        };
        if !(p > 0.0 && r > 0.0 && p.is_finite() && r.is_finite()) {
            anyhow::bail!("--pose-sigma {arg}: sigmas must be positive");
        }
        let sigma = PoseSigma {
            position_m: p,
            rotation_rad: r,
        };
        match name.as_str() {
            "front" => config.front_sigma = sigma,
            "rear" => config.rear_sigma = sigma,
            other => anyhow::bail!("--pose-sigma {arg}: unknown source `{other}` (front or rear)"),
        }
    }
    if let Some(k) = huber {
        if !(k >= 0.0 && k.is_finite()) {
            anyhow::bail!("--huber {k}: expected a non-negative threshold (0 disables)");
        }
        config.huber_k = (k > 0.0).then_some(k);
    }
    config.visual_rate_hz = visual_rate;
    let imu_noise = imu_noise
        .as_deref()
        .map(|s| super::metric::positive_numbers::<4>("--imu-noise", s, "four numbers GN,GW,AN,AW"))
        .transpose()?;
    let summary = run_fuse(&FuseOptions {
        imu,
        frames,
        observations,
        calibration,
        lens,
        imu_noise,
        config,
        out: out.clone(),
    })?;
    if json {
        println!("{}", serde_json::to_string(&summary)?);
    } else {
        println!(
            "fused {} nodes from {} observations ({} downweighted) in {} iterations, \
             {:.2} s -> {}",
            summary.nodes,
            summary.observations_used,
            summary.outliers_downweighted,
            summary.iterations,
            summary.seconds,
            out.display()
        );
    }
    Ok(())
}

/// Inputs of `kiwi fuse`.
#[derive(Debug, Clone)]
pub struct FuseOptions {
    /// `imu.csv`.
    pub imu: PathBuf,
    /// `frames.csv`.
    pub frames: PathBuf,
    /// `obs.csv`.
    pub observations: PathBuf,
    /// Unit `calibration.json` (IMU noise, `cam_from_imu`, time shift).
    pub calibration: Option<PathBuf>,
    /// Lens whose frames are the nodes.
    pub lens: String,
    /// IMU noise densities `[gn, gw, an, aw]` (required without a calibration).
    pub imu_noise: Option<[f64; 4]>,
    /// Fusion settings.
    pub config: FusionConfig,
    /// Output `traj.csv`.
    pub out: PathBuf,
}

/// Summary printed by `kiwi fuse --json`.
#[derive(Debug, Clone, serde::Serialize)]
pub struct FuseSummary {
    /// Nodes written.
    pub nodes: usize,
    /// Visual factors used.
    pub observations_used: usize,
    /// Visual factors downweighted by the Huber loss.
    pub outliers_downweighted: usize,
    /// Solver iterations.
    pub iterations: usize,
    /// Final cost.
    pub final_cost: f64,
    /// Wall time (s).
    pub seconds: f64,
}

/// Run `kiwi fuse`.
fn run_fuse(opts: &FuseOptions) -> Result<FuseSummary> {
    let start = std::time::Instant::now();
    let lens_cal = opts
        .calibration
        .as_deref()
        .map(|path| load_lens_calibration(path, &opts.lens).map(|c| (path, c)))
        .transpose()?;
    let time_shift = lens_cal.as_ref().map_or(0.0, |(_, c)| c.time_shift_s);
    let cam_from_imu = lens_cal.as_ref().map(|(_, c)| c.cam_from_imu);
    let params = imu_params(opts.imu_noise, lens_cal.as_ref().map(|(p, c)| (*p, c)))?;
    let imu = ImuSeries::read_csv(&opts.imu)?;
    let frames = read_frames(&opts.frames)?;
    let observations = read_observations(&opts.observations)?;
    // Kalibr convention: t_imu = t_cam + time_shift_s.
    let node_times: Vec<f64> = frames.iter().map(|t| t + time_shift).collect();
    let result = fuse(
        imu.samples(),
        &params,
        &node_times,
        &observations,
        &opts.config,
    )?;
    let rows: Vec<TrajectoryRow> = result
        .nodes
        .iter()
        .zip(&frames)
        .map(|(n, &t)| {
            let (pose, sigma_p, sigma_r) =
                n.camera_pose(&cam_from_imu.unwrap_or_else(Pose::identity));
            TrajectoryRow {
                t,
                pose,
                sigma_p,
                sigma_r,
                support: n.support,
            }
        })
        .collect();
    write_trajectory(&opts.out, &rows)?;
    Ok(FuseSummary {
        nodes: rows.len(),
        observations_used: result.observations_used,
        outliers_downweighted: result.outliers_downweighted,
        iterations: result.iterations,
        final_cost: result.final_cost,
        seconds: start.elapsed().as_secs_f64(),
    })
}
