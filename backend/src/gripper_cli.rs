//! `kiwi gripper`: jaw opening per front-lens frame of a wrist camera.

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use clap::Args;
use kiwi_core::artifact::UnitCalibration;
use kiwi_core::layout::ToolKind;
use kiwi_core::tool::ToolDefinition;

/// `kiwi gripper` options.
#[derive(Args, Debug)]
pub struct GripperArgs {
    /// The lens folder (frames.csv + frames/), e.g. episodes/ep000/left/front. Or use
    /// --episode with --camera.
    #[arg(long, conflicts_with = "episode")]
    pub lens: Option<PathBuf>,
    /// A prepared episode folder (with --camera): reads <episode>/<camera>/<lens-name>.
    #[arg(long, requires = "camera")]
    pub episode: Option<PathBuf>,
    /// Camera of the episode (left or right).
    #[arg(long)]
    pub camera: Option<String>,
    /// The unit's calibration.json.
    #[arg(long)]
    pub calibration: PathBuf,
    /// Lens that sees the tool.
    #[arg(long, default_value = "front")]
    pub lens_name: String,
    /// Tool: chopstick, parallel_jaw, or a tool definition file (.toml, see hardware/tools).
    #[arg(long)]
    pub tool: String,
    /// Output folder (default: <episode>/work/gripper/<camera>).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Print the summary as JSON.
    #[arg(long)]
    pub json: bool,
}

/// Run `kiwi gripper`.
pub fn run_gripper(args: &GripperArgs) -> Result<()> {
    let def = match args.tool.as_str() {
        "chopstick" => ToolDefinition::builtin(ToolKind::Chopstick)?,
        "parallel_jaw" | "parallel-jaw" => ToolDefinition::builtin(ToolKind::ParallelJaw)?,
        "bare_hand" | "bare-hand" => bail!(
            "the bare-hand cuff has no jaws, so there is no opening to measure; use --tool \
             chopstick, parallel_jaw or a definition file"
        ),
        path => ToolDefinition::load(std::path::Path::new(path))?,
    };
    let (lens_dir, default_out) = match (&args.lens, &args.episode, &args.camera) {
        (Some(l), _, _) => (l.clone(), None),
        (None, Some(e), Some(c)) => (
            e.join(c).join(&args.lens_name),
            Some(e.join("work").join("gripper").join(c)),
        ),
        _ => bail!("give --lens DIR, or --episode DIR with --camera NAME"),
    };
    let out = match (&args.out, default_out) {
        (Some(o), _) => o.clone(),
        (None, Some(o)) => o,
        (None, None) => bail!("give --out DIR for the opening files"),
    };
    let cal = UnitCalibration::load(&args.calibration)?;
    let lens = cal
        .lenses
        .iter()
        .find(|l| l.name == args.lens_name)
        .with_context(|| {
            format!(
                "{}: no lens named `{}` (lenses: {}); pass --lens-name",
                args.calibration.display(),
                args.lens_name,
                cal.lenses
                    .iter()
                    .map(|l| l.name.as_str())
                    .collect::<Vec<_>>()
                    .join(", ")
            )
        })?;
    let camera = lens.camera()?;
    let n = kiwi_core::layout::read_frames_csv(&lens_dir.join("frames.csv"))?.len();
    let bar = indicatif::ProgressBar::new(n as u64);
    if let Ok(style) = indicatif::ProgressStyle::with_template(
        "gripper {bar:40} {pos}/{len} frames [{elapsed_precise}<{eta_precise}]",
    ) {
        bar.set_style(style);
    }
    let (summary, files) =
        kiwi_backend::gripper::run(&camera, &def, &lens_dir, &out, &|| bar.inc(1))?;
    bar.finish_and_clear();
    if args.json {
        println!("{}", serde_json::to_string_pretty(&summary)?);
    } else {
        println!(
            "{} of {} frames measured ({}), median confidence {:.2}, {:.0} frames/s; wrote {}, {}, {}",
            summary.measured,
            summary.frames,
            summary.unit.as_str(),
            summary.median_confidence,
            summary.frames_per_s,
            files.csv.display(),
            files.plot.display(),
            files.tool.display()
        );
        for (reason, count) in &summary.missing {
            println!("  {count} frames {reason}");
        }
    }
    Ok(())
}
