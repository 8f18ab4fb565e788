//! `kiwi gripper`: jaw opening per front-lens frame of a wrist camera.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use clap::Args;
use kiwi_backend::gripper::calibrate::{CalibrateOptions, calibrate_tool};
use kiwi_core::artifact::UnitCalibration;
use kiwi_core::io::write_atomic;
use kiwi_core::layout::ToolKind;
use kiwi_core::tool::{ToolCalibration, ToolDefinition, default_tool_calibration_path};

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
    /// Output folder (default: <episode>/work/gripper/<camera>); with --calibrate, the
    /// artifact file (default: units/<unit>/tools/tool_<name>_<lens>.json beside the unit's
    /// dated sets, or beside --calibration when that is not in a dated set).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Print the summary as JSON.
    #[arg(long)]
    pub json: bool,
    /// Calibrate the tool instead of measuring: the dot plane from the body ArUco tag and the
    /// hinge from the jaw dots, written as `tool_<name>_<lens>.json` in the unit's `tools/`
    /// folder (or to --out FILE.json); never into a dated calibration set.
    #[arg(long)]
    pub calibrate: bool,
    /// With --calibrate: frames searched, spread over the recording.
    #[arg(long, default_value_t = 60)]
    pub calibration_frames: usize,
    /// Replace earlier outputs (the opening files, or with --calibrate the tool calibration).
    #[arg(long)]
    pub overwrite: bool,
    /// Tool calibration to measure with (default: the --calibrate output for this unit, tool
    /// and lens when it exists).
    #[arg(long, conflicts_with = "nominal")]
    pub tool_calibration: Option<PathBuf>,
    /// Measure with the tool definition's CAD geometry even if a tool calibration exists.
    #[arg(long)]
    pub nominal: bool,
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
        path => ToolDefinition::load(Path::new(path))?,
    };
    let (lens_dir, default_out) = match (&args.lens, &args.episode, &args.camera) {
        (Some(l), _, _) => (l.clone(), None),
        (None, Some(e), Some(c)) => (
            e.join(c).join(&args.lens_name),
            Some(e.join("work").join("gripper").join(c)),
        ),
        _ => bail!("give --lens DIR, or --episode DIR with --camera NAME"),
    };
    let cal = UnitCalibration::load(&args.calibration)?;
    check_recorded_by(&lens_dir, &cal, &args.calibration)?;
    let default_tool_cal =
        default_tool_calibration_path(&args.calibration, &def.name, &args.lens_name);
    if args.calibrate {
        let out = args.out.clone().unwrap_or(default_tool_cal);
        kiwi_core::io::ensure_outside_dated_set(&out)?;
        return calibrate(args, &def, &cal, &lens_dir, &out);
    }
    let out = match (&args.out, default_out) {
        (Some(o), _) => o.clone(),
        (None, Some(o)) => o,
        (None, None) => bail!("give --out DIR for the opening files"),
    };
    kiwi_core::io::ensure_outside_dated_set(&out)?;
    if !args.overwrite {
        for name in kiwi_backend::gripper::OUTPUT_FILES {
            let existing = out.join(name);
            if existing.exists() {
                bail!(
                    "{} exists from an earlier run: outputs are never replaced silently; pass \
                     --overwrite or choose another --out",
                    existing.display()
                );
            }
        }
    }
    // A tool calibration written beside calibration.json by earlier versions is still read.
    let legacy_tool_cal =
        args.calibration
            .with_file_name(kiwi_core::tool::tool_calibration_file_name(
                &def.name,
                &args.lens_name,
            ));
    let tool_cal = match (&args.tool_calibration, args.nominal) {
        (Some(p), _) => Some(ToolCalibration::load(p)?),
        (None, false) if default_tool_cal.exists() => {
            Some(ToolCalibration::load(&default_tool_cal)?)
        }
        (None, false) if legacy_tool_cal.exists() => Some(ToolCalibration::load(&legacy_tool_cal)?),
        _ => None,
    };
    if let Some(tc) = &tool_cal {
        if tc.unit_id != cal.unit_id || tc.lens != args.lens_name {
            bail!(
                "the tool calibration is for unit {} lens {}, but --calibration is unit {} and \
                 the lens is {}: calibrate this unit's tool with --calibrate",
                tc.unit_id,
                tc.lens,
                cal.unit_id,
                args.lens_name
            );
        }
        if tc.definition.name != def.name {
            bail!(
                "the tool calibration is for tool `{}`, not `{}`",
                tc.definition.name,
                def.name
            );
        }
    }
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
    let (summary, files) = match &tool_cal {
        Some(tc) => kiwi_backend::gripper::run_calibrated(&camera, tc, &lens_dir, &out, &|| {
            bar.inc(1);
        })?,
        None => kiwi_backend::gripper::run(&camera, &def, &lens_dir, &out, &|| bar.inc(1))?,
    };
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
        match &tool_cal {
            Some(tc) => println!(
                "  tool geometry from the tool calibration of unit {} ({} frames with the tag)",
                tc.unit_id, tc.quality.frames_with_tag
            ),
            None => println!(
                "  tool geometry from the definition's CAD numbers (no tool calibration; run \
                 with --calibrate once)"
            ),
        }
    }
    Ok(())
}

/// The recording's `meta.json` (in the camera folder above the lens folder) must name the unit
/// the calibration is of: the other wrist's calibration measures with the wrong lens.
fn check_recorded_by(lens_dir: &Path, cal: &UnitCalibration, cal_path: &Path) -> Result<()> {
    let Some(camera_dir) = lens_dir.parent() else {
        return Ok(());
    };
    let meta_path = camera_dir.join("meta.json");
    if !meta_path.is_file() {
        return Ok(());
    }
    let (Some(root), Some(camera)) = (camera_dir.parent(), camera_dir.file_name()) else {
        return Ok(());
    };
    let meta = kiwi_core::layout::EpisodeLayout::new(root).read_meta(&camera.to_string_lossy())?;
    if meta.unit_id != cal.unit_id {
        bail!(
            "{} was recorded by unit {}, but --calibration {} is of unit {}: pass that unit's \
             calibration (the other wrist's?)",
            meta_path.display(),
            meta.unit_id,
            cal_path.display(),
            cal.unit_id
        );
    }
    Ok(())
}

/// `kiwi gripper --calibrate`: write the tool calibration artifact.
fn calibrate(
    args: &GripperArgs,
    def: &ToolDefinition,
    cal: &UnitCalibration,
    lens_dir: &Path,
    out: &Path,
) -> Result<()> {
    if out.extension().and_then(|e| e.to_str()) != Some("json") {
        bail!(
            "{}: with --calibrate, --out is the artifact file to write (ending in .json)",
            out.display()
        );
    }
    if out.exists() && !args.overwrite {
        bail!(
            "{} exists: a tool calibration is never replaced silently; pass --overwrite or \
             --out another file",
            out.display()
        );
    }
    let lens = cal.lens(&args.lens_name).with_context(|| {
        format!(
            "{}: no lens named `{}`; pass --lens-name",
            args.calibration.display(),
            args.lens_name
        )
    })?;
    let camera = lens.camera()?;
    let frames = kiwi_core::layout::read_frames_csv(&lens_dir.join("frames.csv"))?;
    let n = args.calibration_frames.min(frames.len());
    let bar = indicatif::ProgressBar::new(n as u64);
    if let Ok(style) = indicatif::ProgressStyle::with_template(
        "tool calibration {bar:40} {pos}/{len} frames [{elapsed_precise}]",
    ) {
        bar.set_style(style);
    }
    let options = CalibrateOptions {
        max_frames: args.calibration_frames,
        unit_id: cal.unit_id.clone(),
        lens: args.lens_name.clone(),
        unit_calibration_date: cal.date.clone(),
    };
    let tc = calibrate_tool(&camera, def, lens_dir, &frames, &options, &|| bar.inc(1))?;
    bar.finish_and_clear();
    write_atomic(out, tc.to_json()?.as_bytes())?;
    if args.json {
        println!("{}", serde_json::to_string_pretty(&tc)?);
    } else {
        let q = &tc.quality;
        println!(
            "tool {} on unit {} lens {}: body tag in {} of {} frames (corner RMS {:.2} px, \
             normal scatter {:.2} deg), hinge from {} jaw lines (dot RMS {} mm); plane tilted \
             {:.2} deg, jaws turned {:.2} deg, hinge moved {:.2} mm from the definition; wrote {}",
            def.name,
            tc.unit_id,
            tc.lens,
            q.frames_with_tag,
            q.frames_searched,
            q.tag_rms_px,
            q.tag_normal_spread_deg,
            q.jaw_lines,
            q.dot_line_rms_m
                .map_or_else(|| "-".to_string(), |v| format!("{:.2}", v * 1e3)),
            q.plane_tilt_from_definition_deg,
            q.jaw_direction_from_definition_deg,
            q.hinge_shift_from_definition_m * 1e3,
            out.display()
        );
    }
    Ok(())
}
