//! Command-line front ends of the lens steps: `target`, `detect`, `intrinsics`, and the
//! `bench-intrinsics` benchmark. `main.rs` only forwards to these.

use std::path::{Path, PathBuf};
use std::time::Instant;

use kiwi_core::camera::CameraModelKind;
use kiwi_core::io::write_atomic;

use crate::detect::{CornerSet, DetectOptions, detect_folder};
use crate::error::{CalibError, Result};
use crate::intrinsics::{IntrinsicsOptions, calibrate, report::write_outputs};
use crate::target::{AprilGridTarget, aruco_svg};

/// `kiwi-calib target`: print-ready targets.
#[derive(Debug, clap::Subcommand)]
pub enum TargetCommand {
    /// A Kalibr aprilgrid board (SVG and PDF, 1 : 1) and its Kalibr target yaml (same name,
    /// .yaml).
    Aprilgrid {
        /// Tags along the board's x axis.
        #[arg(long, default_value_t = 6)]
        cols: usize,
        /// Tags along the board's y axis.
        #[arg(long, default_value_t = 6)]
        rows: usize,
        /// Edge of a tag's black square (m).
        #[arg(long, default_value_t = 0.088, value_parser = kiwi_core::args::positive)]
        tag_size: f64,
        /// Gap between tags divided by the tag size.
        #[arg(long, default_value_t = 0.3, value_parser = kiwi_core::args::non_negative)]
        spacing: f64,
        /// The SVG to write (a PDF and the target yaml go beside it); a `.pdf` name writes
        /// only the PDF and the yaml.
        #[arg(long)]
        out: PathBuf,
    },
    /// A single ArUco marker (tool and head markers).
    Aruco {
        /// Dictionary (4x4_50).
        #[arg(long, default_value = "4x4_50")]
        dict: String,
        /// Marker id.
        #[arg(long)]
        id: usize,
        /// Edge of the black square (m).
        #[arg(long, value_parser = kiwi_core::args::positive)]
        size: f64,
        /// The SVG to write.
        #[arg(long)]
        out: PathBuf,
    },
}

/// Arguments of `kiwi-calib detect`.
#[derive(Debug, clap::Args)]
pub struct DetectArgs {
    /// Folder of calibration images of one lens (or its parent with frames/).
    #[arg(long)]
    pub images: PathBuf,
    /// Kalibr target yaml (aprilgrid).
    #[arg(long)]
    pub target: PathBuf,
    /// The corners file to write.
    #[arg(long)]
    pub out: PathBuf,
    /// Print `{"images": [{"name", "tags", "corners"}], "total_corners"}`.
    #[arg(long)]
    pub json: bool,
}

/// Projection model choice on the command line.
#[derive(Debug, Clone, Copy, clap::ValueEnum)]
pub enum ModelArg {
    /// Kannala–Brandt, 4 radial terms.
    Kb4,
    /// Double Sphere.
    Ds,
}

/// Arguments of `kiwi-calib intrinsics`.
#[derive(Debug, clap::Args)]
pub struct IntrinsicsArgs {
    /// Folder of calibration images (detects first; needs --target).
    #[arg(long, conflicts_with = "corners")]
    pub images: Option<PathBuf>,
    /// A corners file from `kiwi-calib detect` (or converted from another tool).
    #[arg(long)]
    pub corners: Option<PathBuf>,
    /// Kalibr target yaml (needed with --images).
    #[arg(long)]
    pub target: Option<PathBuf>,
    /// Projection model.
    #[arg(long, value_enum, default_value = "kb4")]
    pub model: ModelArg,
    /// Lens name in the artifact (front, rear, main).
    #[arg(long, default_value = "front")]
    pub lens: String,
    /// Result folder: lens.json, summary.json, rejected_corners.csv, report plots (SVG).
    #[arg(long)]
    pub out: PathBuf,
    /// Print the JSON summary.
    #[arg(long)]
    pub json: bool,
}

/// Arguments of `kiwi-calib bench-intrinsics`.
#[derive(Debug, clap::Args)]
pub struct BenchIntrinsicsArgs {
    /// Folder of images (e.g. a `kiwi-sim unit` capture's intrinsics/front).
    #[arg(long)]
    pub images: PathBuf,
    /// Kalibr target yaml.
    #[arg(long)]
    pub target: PathBuf,
    /// Projection model.
    #[arg(long, value_enum, default_value = "kb4")]
    pub model: ModelArg,
}

fn svg_yaml_path(out: &Path) -> PathBuf {
    out.with_extension("yaml")
}

/// Run `kiwi-calib target`; returns the files written.
pub fn run_target(cmd: &TargetCommand) -> Result<Vec<PathBuf>> {
    match cmd {
        TargetCommand::Aprilgrid {
            cols,
            rows,
            tag_size,
            spacing,
            out,
        } => {
            let t = AprilGridTarget::new(*cols, *rows, *tag_size, *spacing)?;
            let is_pdf = out
                .extension()
                .is_some_and(|e| e.eq_ignore_ascii_case("pdf"));
            let mut files = Vec::new();
            if !is_pdf {
                write_atomic(out, t.to_svg()?.as_bytes())?;
                files.push(out.clone());
            }
            let pdf = out.with_extension("pdf");
            write_atomic(&pdf, &t.to_pdf()?)?;
            files.push(pdf);
            let yaml = svg_yaml_path(out);
            write_atomic(&yaml, t.to_kalibr_yaml().as_bytes())?;
            files.push(yaml);
            Ok(files)
        }
        TargetCommand::Aruco {
            dict,
            id,
            size,
            out,
        } => {
            write_atomic(out, aruco_svg(dict, *id, *size)?.as_bytes())?;
            Ok(vec![out.clone()])
        }
    }
}

/// Run `kiwi-calib detect`; returns the corners.
pub fn run_detect(args: &DetectArgs) -> Result<CornerSet> {
    let target = AprilGridTarget::load(&args.target)?;
    let set = detect_folder(
        &args.images,
        &target,
        &DetectOptions {
            progress: true,
            ..DetectOptions::default()
        },
    )?;
    set.save(&args.out)?;
    Ok(set)
}

fn model_kind(m: ModelArg) -> CameraModelKind {
    match m {
        ModelArg::Kb4 => CameraModelKind::Kb4,
        ModelArg::Ds => CameraModelKind::DoubleSphere,
    }
}

/// Run `kiwi-calib intrinsics`; returns the JSON summary.
pub fn run_intrinsics(args: &IntrinsicsArgs) -> Result<serde_json::Value> {
    let set = match (&args.images, &args.corners) {
        (Some(images), None) => {
            let Some(target) = &args.target else {
                return Err(CalibError::Input {
                    path: images.clone(),
                    message: "--images needs --target (the Kalibr target yaml of the board)".into(),
                });
            };
            let target = AprilGridTarget::load(target)?;
            let set = detect_folder(
                images,
                &target,
                &DetectOptions {
                    progress: true,
                    ..DetectOptions::default()
                },
            )?;
            std::fs::create_dir_all(&args.out).map_err(|e| CalibError::Input {
                path: args.out.clone(),
                message: format!("cannot create the output folder: {e}"),
            })?;
            set.save(&args.out.join("corners.json"))?;
            set
        }
        (None, Some(corners)) => CornerSet::load(corners)?,
        _ => {
            return Err(CalibError::Input {
                path: args.out.clone(),
                message: "give either --images DIR --target target.yaml, or --corners \
                          corners.json"
                    .into(),
            });
        }
    };
    let options = IntrinsicsOptions {
        model: model_kind(args.model),
        lens_name: args.lens.clone(),
        check_coverage: true,
    };
    let result = calibrate(&set, &options)?;
    let files = write_outputs(&result, &args.lens, &args.out)?;
    let mut summary = result.summary_json();
    if let Some(map) = summary.as_object_mut() {
        map.insert(
            "files".into(),
            serde_json::to_value(&files)
                .map_err(|e| CalibError::Internal(format!("paths do not serialize: {e}")))?,
        );
    }
    Ok(summary)
}

/// Run the detection + fit benchmark; returns a printable report.
pub fn run_bench(args: &BenchIntrinsicsArgs) -> Result<String> {
    let target = AprilGridTarget::load(&args.target)?;
    let t0 = Instant::now();
    let set = detect_folder(&args.images, &target, &DetectOptions::default())?;
    let t_detect = t0.elapsed().as_secs_f64();
    let t1 = Instant::now();
    let options = IntrinsicsOptions {
        model: model_kind(args.model),
        ..IntrinsicsOptions::default()
    };
    let result = calibrate(&set, &options)?;
    let t_fit = t1.elapsed().as_secs_f64();
    let n_images = crate::detect::list_images(&args.images)?.len();
    Ok(format!(
        "{n_images} images ({} with the target, {} corners): detection {t_detect:.2} s, fit \
         {t_fit:.2} s ({} iterations, rms {:.3} px, {} rejected), total {:.2} s on {} threads",
        set.images.len(),
        set.total_corners(),
        result.iterations,
        result.rms_px,
        result.n_rejected,
        t_detect + t_fit,
        rayon::current_num_threads()
    ))
}
