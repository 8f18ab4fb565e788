//! `kiwi metric` and `kiwi place`: metric recovery and scene placement from localizer
//! `poses.csv` files, for experts who run the stages one by one.

use std::path::PathBuf;

use anyhow::Result;

use anyhow::Context;
use kiwi_backend::formats::calibration::{exposure_centre_delay, imu_params, lens_calibration};
use kiwi_backend::formats::results::{
    FrontWitness, metric_from_localizations, metric_of, placement_from_localizations,
    read_placement, write_json,
};
use kiwi_backend::formats::tables::read_localizations;
use kiwi_backend::metric::MetricConfig;
use kiwi_backend::placement::PlacementConfig;
use kiwi_core::artifact::UnitCalibration;
use kiwi_core::imu::ImuSeries;
use kiwi_core::layout::CameraMeta;
use nalgebra::{Isometry3, Translation3};

/// Arguments of `kiwi metric`.
#[derive(Debug, clap::Args)]
pub struct MetricArgs {
    /// The localizer's poses.csv of the mapping episode against the map
    /// (`t,status,px,py,pz,qx,qy,qz,qw,...`; lost rows are skipped).
    #[arg(long)]
    pub poses: PathBuf,
    /// The IMU log (imu.csv) of the same recording.
    #[arg(long)]
    pub imu: PathBuf,
    /// Unit calibration.json (cam_from_imu and time shift of --lens, IMU noise).
    #[arg(long)]
    pub calibration: PathBuf,
    /// The lens the map was built from.
    #[arg(long, default_value = "rear")]
    pub lens: String,
    /// IMU noise GN,GW,AN,AW overriding the calibration's (SI continuous-time densities).
    #[arg(long, value_name = "GN,GW,AN,AW")]
    pub imu_noise: Option<String>,
    /// Rolling-shutter readout of a whole frame (s; 0 for a global shutter) [default: the
    /// calibration's readout of the recording mode named in the `meta.json` beside --imu].
    #[arg(long, value_name = "SECONDS")]
    pub readout: Option<f64>,
    /// Visual noise once metric: METRES,RADIANS [default: 0.002,0.00349].
    #[arg(long, value_name = "M,RAD")]
    pub pose_sigma: Option<String>,
    /// Huber threshold on the whitened 6-dof visual residual [default: 3.55].
    #[arg(long)]
    pub huber: Option<f64>,
    /// Output metric.json (world_from_map, scale, gravity, biases, conditioning).
    #[arg(long)]
    pub out: PathBuf,
    /// Print the result as JSON.
    #[arg(long)]
    pub json: bool,
}

/// Arguments of `kiwi place`.
#[derive(Debug, clap::Args)]
pub struct PlaceArgs {
    /// Front-lens poses.csv of the mapping episode in the front map.
    #[arg(long)]
    pub front: PathBuf,
    /// Rear-lens poses.csv of the same episode in the scene (rear) map.
    #[arg(long)]
    pub rear: PathBuf,
    /// Unit calibration.json (cam_from_imu and time shift of both lenses).
    #[arg(long)]
    pub calibration: PathBuf,
    /// metric.json of the front map, applied to the front poses first.
    #[arg(long)]
    pub front_metric: Option<PathBuf>,
    /// metric.json of the scene map, applied to the rear poses first.
    #[arg(long)]
    pub rear_metric: Option<PathBuf>,
    /// The same front stream's poses.csv in another wrist's front map: pooled into the fit as
    /// a witness of where the front camera stands in the scene (what `kiwi run` does for the
    /// wrist that did not build the scene map). Needs --witness-metric and --witness-placement.
    #[arg(long, requires_all = ["witness_metric", "witness_placement"])]
    pub witness: Option<PathBuf>,
    /// metric.json of the other wrist's front map (for --witness).
    #[arg(long, requires = "witness")]
    pub witness_metric: Option<PathBuf>,
    /// placement.json of the other wrist's front map (for --witness).
    #[arg(long, requires = "witness")]
    pub witness_placement: Option<PathBuf>,
    /// Output placement.json (scene_from_front_map and inlier statistics).
    #[arg(long)]
    pub out: PathBuf,
    /// Print the result as JSON.
    #[arg(long)]
    pub json: bool,
}

/// Parse `A,B,...` into exactly `N` positive finite numbers.
pub fn positive_numbers<const N: usize>(flag: &str, text: &str, what: &str) -> Result<[f64; N]> {
    let values: Vec<f64> = text
        .split(',')
        .map(|v| v.trim().parse::<f64>())
        .collect::<std::result::Result<_, _>>()
        .map_err(|_| anyhow::anyhow!("{flag} {text}: expected {what}"))?;
    let out: [f64; N] = values
        .try_into()
        .map_err(|_| anyhow::anyhow!("{flag} {text}: expected {what}"))?;
    if out.iter().any(|x| !(*x > 0.0 && x.is_finite())) {
        anyhow::bail!("{flag} {text}: values must be positive (SI units)");
    }
    Ok(out)
}

/// Time from a frame's timestamp to its exposure centre (s): half of `--readout`, else of the
/// calibration's readout of the mode in the camera's `meta.json` beside the IMU log, else 0
/// with a warning.
fn exposure_centre_of(args: &MetricArgs, unit: &UnitCalibration) -> Result<f64> {
    if let Some(r) = args.readout {
        if !(r.is_finite() && r >= 0.0) {
            anyhow::bail!("--readout {r}: expected the readout time in seconds, 0 or more");
        }
        return Ok(0.5 * r);
    }
    let meta_path = args.imu.with_file_name("meta.json");
    if !meta_path.is_file() {
        eprintln!(
            "warning: no {} beside the IMU log and no --readout: the frames are taken as \
             global-shutter exposures (give --readout for a rolling-shutter camera)",
            meta_path.display()
        );
        return Ok(0.0);
    }
    let meta = CameraMeta::load(&meta_path)?;
    Ok(
        exposure_centre_delay(unit, &meta.mode, meta.fps).unwrap_or_else(|| {
            eprintln!(
                "warning: {} knows no readout for recording mode {} ({} fps): the frames are \
                 taken as global-shutter exposures (give --readout to set it)",
                args.calibration.display(),
                meta.mode,
                meta.fps
            );
            0.0
        }),
    )
}

/// Run `kiwi metric`.
pub fn run_metric_cmd(args: &MetricArgs) -> Result<()> {
    let mut config = MetricConfig::default();
    if let Some(s) = &args.pose_sigma {
        let [p, r] = positive_numbers::<2>("--pose-sigma", s, "METRES,RADIANS")?;
        config.sigma_position_m = p;
        config.sigma_rotation_rad = r;
    }
    if let Some(k) = args.huber {
        if !(k > 0.0 && k.is_finite()) {
            anyhow::bail!("--huber {k}: expected a positive threshold");
        }
        config.huber_k = k;
    }
    let imu_noise = args
        .imu_noise
        .as_deref()
        .map(|s| positive_numbers::<4>("--imu-noise", s, "four numbers GN,GW,AN,AW"))
        .transpose()?;
    let started = std::time::Instant::now();
    let unit = UnitCalibration::load(&args.calibration)?;
    let cal = lens_calibration(&unit, &args.calibration, &args.lens)?;
    let params = imu_params(imu_noise, Some((&args.calibration, &cal)))?;
    let rows = read_localizations(&args.poses)?;
    let imu = ImuSeries::read_csv(&args.imu)?;
    let centre = exposure_centre_of(args, &unit)?;
    let file = metric_from_localizations(
        &rows, &imu, &args.lens, &cal, &params, centre, &config, started,
    )
    .with_context(|| format!("{}", args.poses.display()))?;
    write_json(&args.out, &file)?;
    if args.json {
        println!("{}", serde_json::to_string(&file)?);
    } else {
        let c = &file.conditioning;
        println!(
            "scale {:.5} m/unit (±{:.2} %), gravity ±{:.3}°, accel bias [{:.4}, {:.4}, {:.4}] \
             m/s², excitation {:.3} m/s² RMS; {} frames ({} lost, {} outliers) -> {}",
            file.scale_m_per_map_unit,
            c.scale_sigma * 100.0,
            c.gravity_sigma_deg,
            file.accel_bias_m_s2[0],
            file.accel_bias_m_s2[1],
            file.accel_bias_m_s2[2],
            c.excitation_rms_m_s2,
            file.frames_used,
            file.frames_lost,
            file.outliers_downweighted,
            args.out.display()
        );
    }
    Ok(())
}

/// Run `kiwi place`.
pub fn run_place_cmd(args: &PlaceArgs) -> Result<()> {
    let unit = UnitCalibration::load(&args.calibration)?;
    let front_cal = lens_calibration(&unit, &args.calibration, "front")?;
    let rear_cal = lens_calibration(&unit, &args.calibration, "rear")?;
    let front = read_localizations(&args.front)?;
    let rear = read_localizations(&args.rear)?;
    let front_sim = metric_of(args.front_metric.as_deref())?;
    let rear_sim = metric_of(args.rear_metric.as_deref())?;
    let witness = match (&args.witness, &args.witness_metric, &args.witness_placement) {
        (Some(rows), Some(metric), Some(placement)) => {
            let g = read_placement(placement)?;
            let g = g.scene_from_front_map.to_sim3(placement)?;
            Some((
                read_localizations(rows)?,
                metric_of(Some(metric))?,
                Isometry3::from_parts(Translation3::from(g.translation), g.rotation),
            ))
        }
        _ => None,
    };
    let file = placement_from_localizations(
        &front,
        &rear,
        &front_cal,
        &rear_cal,
        &front_sim,
        &rear_sim,
        witness.as_ref().map(|(rows, sim, g)| FrontWitness {
            rows,
            other_front_sim: *sim,
            scene_from_other_front_map: *g,
        }),
        &PlacementConfig::default(),
    )
    .with_context(|| format!("{}", args.front.display()))?;
    write_json(&args.out, &file)?;
    if args.json {
        println!("{}", serde_json::to_string(&file)?);
    } else {
        println!(
            "placed the front map: {} of {} pairs inliers ({} from the witness), RMS {:.2} mm / \
             {:.3}° -> {}",
            file.inliers,
            file.pairs,
            file.witness_pairs,
            file.rms_position_m * 1e3,
            file.rms_rotation_deg,
            args.out.display()
        );
    }
    Ok(())
}
