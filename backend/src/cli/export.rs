//! `kiwi export`: write a session's episodes as a dataset (LeRobot v3.0, UMI, KIWI sidecar) or
//! as a scene-reconstruction input (COLMAP, nerfstudio).

use std::path::PathBuf;

use anyhow::Result;

use kiwi_backend::export::{ExportFormat, ExportOptions, export};

/// Arguments of `kiwi export`.
#[derive(Debug, clap::Args)]
pub struct ExportArgs {
    /// The session's session.toml (its episodes must have been through `kiwi run`).
    #[arg(long)]
    pub session: PathBuf,
    /// lerobot (LeRobot v3.0: parquet + mp4), umi (dataset.zarr.zip), sidecar (every output
    /// at full rate, without loss), colmap (a COLMAP text model of posed wrist images, for
    /// 3DGUT and gsplat) or nerfstudio (transforms.json, for nerfstudio and brush).
    #[arg(long)]
    pub format: ExportFormat,
    /// Output rate in Hz (lerobot, umi) [default: the slowest trajectory or view]; at most
    /// what every source supplies.
    #[arg(long)]
    pub fps: Option<f64>,
    /// Views as camera.lens, comma-separated (lerobot, umi) [default: each wrist's front lens
    /// and the head camera].
    #[arg(long, value_delimiter = ',')]
    pub views: Option<Vec<String>>,
    /// Images per second and lens stream (colmap, nerfstudio) [default: 1].
    #[arg(long)]
    pub rate: Option<f64>,
    /// Episodes, comma-separated [default: all]; unusable ones are left out with the reason.
    #[arg(long, value_delimiter = ',')]
    pub episodes: Option<Vec<String>>,
    /// Output folder (must not exist or be empty).
    #[arg(long)]
    pub out: PathBuf,
}

/// Run `kiwi export`.
pub fn run_export_cmd(args: &ExportArgs) -> Result<()> {
    let options = ExportOptions {
        fps: args.fps,
        rate: args.rate,
        views: args.views.clone(),
        episodes: args.episodes.clone(),
    };
    let started = std::time::Instant::now();
    let report = export(&args.session, args.format, &options, &args.out)?;
    for (name, reason) in &report.skipped {
        eprintln!("left out {name}: {reason}");
    }
    for note in &report.notes {
        println!("{note}");
    }
    let rate = report
        .fps
        .map(|f| format!(" at {f:.4} Hz"))
        .unwrap_or_default();
    println!(
        "exported {} episode(s), {} frames{rate}, into {} in {:.1} s",
        report.exported.len(),
        report.frames,
        args.out.display(),
        started.elapsed().as_secs_f64()
    );
    if report.max_frame_offset_s > 0.0 {
        println!(
            "largest distance between a row and its video frame's capture time: {:.2} ms",
            report.max_frame_offset_s * 1e3
        );
    }
    Ok(())
}
