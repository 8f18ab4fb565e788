//! `kiwi ingest`: a camera's own files into a prepared episode of a session.

use std::path::PathBuf;

use anyhow::{Result, bail};

use kiwi_backend::ingest::imu::{AxisMap, ImuCsvOptions, TimeUnit, parse_columns};
use kiwi_backend::ingest::{CameraInput, IngestOptions, LensOutput, ingest_episode};
use kiwi_core::video::VideoCodec;

/// Arguments of `kiwi ingest`.
#[derive(Debug, clap::Args)]
pub struct IngestArgs {
    /// The session's session.toml (the episode is written under its episodes/ and added to it).
    #[arg(long)]
    pub session: PathBuf,
    /// Episode name (a new folder: an existing episode is never overwritten).
    #[arg(long)]
    pub episode: String,
    /// The left wrist camera's files: an Insta360 .insv (both lenses as tracks), its
    /// _00_/_10_ pair, or every segment of a split recording (comma-separated or repeated);
    /// or any video with both lenses as tracks (or one file per lens, front first) plus
    /// --left-imu.
    #[arg(long, value_delimiter = ',', required = true)]
    pub left: Vec<PathBuf>,
    /// The right wrist camera's files (as --left).
    #[arg(long, value_delimiter = ',')]
    pub right: Vec<PathBuf>,
    /// The head camera's files (an Insta360 GO 3 recording, or any one-lens video plus
    /// --head-imu).
    #[arg(long, value_delimiter = ',')]
    pub head: Vec<PathBuf>,
    /// IMU CSV of the left camera (generic path, or a recording whose file has no IMU).
    #[arg(long)]
    pub left_imu: Option<PathBuf>,
    /// IMU CSV of the right camera.
    #[arg(long)]
    pub right_imu: Option<PathBuf>,
    /// IMU CSV of the head camera.
    #[arg(long)]
    pub head_imu: Option<PathBuf>,
    /// IMU CSV column names of time, gyro x y z, accel x y z.
    #[arg(long, default_value = "t,gx,gy,gz,ax,ay,az")]
    pub imu_columns: String,
    /// Unit of the IMU CSV's time column: s, ms, us or ns.
    #[arg(long, default_value = "s")]
    pub imu_time_unit: String,
    /// Unit of the IMU CSV's gyroscope columns: rad/s or deg/s.
    #[arg(long, default_value = "rad/s")]
    pub gyro_unit: String,
    /// Unit of the IMU CSV's accelerometer columns: m/s2 or g.
    #[arg(long, default_value = "m/s2")]
    pub accel_unit: String,
    /// The IMU CSV's time of video time 0 (s, after unit conversion): subtracted from its times.
    #[arg(long, default_value_t = 0.0, allow_negative_numbers = true)]
    pub imu_time_offset: f64,
    /// Axis map: KIWI's IMU x, y, z as signed axes of the device (e.g. -y,-z,+x). Applies to
    /// IMU CSVs (default +x,+y,+z) and to Insta360 models KIWI's table does not know.
    #[arg(long)]
    pub imu_axes: Option<String>,
    /// Processing width of each lens (px); a lens no wider keeps its native size.
    #[arg(long, default_value_t = kiwi_backend::ingest::DEFAULT_RESOLUTION)]
    pub resolution: u32,
    /// How lens frames are stored: a video codec (h264 or h264:CRF near-lossless, utvideo or
    /// ffv1 lossless) or png (one file per frame).
    #[arg(long, default_value = "h264:12")]
    pub frames: String,
    /// Which source lens is a wrist's front lens: 0 (first video track, or the _00_ file) or 1.
    #[arg(long, default_value_t = 0)]
    pub front_lens: usize,
    /// Recording mode name (default: the unit calibration's mode with the recording's frame
    /// rate).
    #[arg(long)]
    pub mode: Option<String>,
    /// Print a JSON summary.
    #[arg(long)]
    pub json: bool,
}

/// Run `kiwi ingest`.
pub fn run_ingest_cmd(args: &IngestArgs) -> Result<()> {
    let gyro_deg_s = match args.gyro_unit.as_str() {
        "rad/s" => false,
        "deg/s" => true,
        other => bail!("--gyro-unit {other}: expected rad/s or deg/s"),
    };
    let accel_g = match args.accel_unit.as_str() {
        "m/s2" | "m/s^2" | "m/s²" => false,
        "g" => true,
        other => bail!("--accel-unit {other}: expected m/s2 or g"),
    };
    let axes = match &args.imu_axes {
        Some(text) => Some(AxisMap::parse(text).map_err(|e| anyhow::anyhow!("--imu-axes {e}"))?),
        None => None,
    };
    let imu_csv = ImuCsvOptions {
        columns: parse_columns(&args.imu_columns)
            .map_err(|e| anyhow::anyhow!("--imu-columns {e}"))?,
        time_unit: TimeUnit::parse(&args.imu_time_unit)
            .map_err(|e| anyhow::anyhow!("--imu-time-unit {e}"))?,
        gyro_deg_s,
        accel_g,
        axes: axes.unwrap_or(AxisMap::IDENTITY),
        time_offset_s: -args.imu_time_offset,
    };
    let output = match args.frames.as_str() {
        "png" => LensOutput::Images,
        other => LensOutput::Video(
            VideoCodec::parse(other).map_err(|e| anyhow::anyhow!("--frames {e} or png"))?,
        ),
    };
    let options = IngestOptions {
        resolution: args.resolution,
        output,
        front_lens: args.front_lens,
        mode: args.mode.clone(),
        imu_csv,
        imu_axes: axes,
    };
    let mut inputs = vec![CameraInput {
        camera: "left".into(),
        files: args.left.clone(),
        imu_csv: args.left_imu.clone(),
    }];
    for (camera, files, imu) in [
        ("right", &args.right, &args.right_imu),
        ("head", &args.head, &args.head_imu),
    ] {
        if !files.is_empty() {
            inputs.push(CameraInput {
                camera: camera.into(),
                files: files.clone(),
                imu_csv: imu.clone(),
            });
        }
    }
    let report = ingest_episode(&args.session, &args.episode, &inputs, &options)?;
    if args.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        println!("ingested {}", report.episode_dir.display());
        for c in &report.cameras {
            let lenses: Vec<String> = c
                .lenses
                .iter()
                .map(|(l, n)| format!("{l} {n} frames"))
                .collect();
            println!(
                "  {}: {} mode {} at {:.3} Hz: {}; {} IMU samples; {} audio samples",
                c.camera,
                c.camera_model,
                c.mode,
                c.fps,
                lenses.join(", "),
                c.imu_samples,
                c.audio_samples
            );
        }
    }
    Ok(())
}
