//! Command-line front ends of `kiwi-calib certify` and `kiwi-calib units`.

use std::fmt::Write as _;
use std::path::PathBuf;

use super::policy::Policy;
use super::report::{
    clean_leftovers, latest_set, leftovers_text, list_leftovers, list_text, list_units, show_text,
};
use super::{CertifyOptions, CertifyReport, certify};
use crate::error::{CalibError, Result};

/// Exit status of `certify` when the unit did not certify (the set is written all the same).
pub const EXIT_NOT_CERTIFIED: i32 = 2;

/// Arguments of `kiwi-calib certify`.
#[derive(Debug, clap::Args)]
pub struct CertifyArgs {
    /// The unit's id (as in the captures' unit.toml).
    #[arg(long, required_unless_present = "print_policy")]
    pub unit: Option<String>,
    /// The capture folder (unit.toml, target.yaml, intrinsics/<lens>/, imu_static/imu.csv,
    /// cam_imu/, qr_rig/...; docs/certify.md).
    #[arg(long, required_unless_present = "print_policy")]
    pub captures: Option<PathBuf>,
    /// The units folder; the set goes to OUT/ID/YYYY-MM-DD[-N]/.
    #[arg(long, default_value = "units")]
    pub out: PathBuf,
    /// Thresholds (TOML; missing fields keep the defaults of `--print-policy`).
    #[arg(long)]
    pub policy: Option<PathBuf>,
    /// An earlier set of this unit (its folder) to compare with.
    #[arg(long)]
    pub previous: Option<PathBuf>,
    /// Certification date YYYY-MM-DD (default: today, UTC).
    #[arg(long)]
    pub date: Option<String>,
    /// Print the result as JSON (no progress display).
    #[arg(long)]
    pub json: bool,
    /// Print the default policy as TOML and exit.
    #[arg(long)]
    pub print_policy: bool,
}

/// `kiwi-calib units`.
#[derive(Debug, clap::Subcommand)]
pub enum UnitsCommand {
    /// Every unit under a units folder, with its sets' dates and verdicts.
    List {
        /// The units folder.
        #[arg(default_value = "units")]
        units: PathBuf,
        /// Print JSON.
        #[arg(long)]
        json: bool,
    },
    /// A unit's latest set in readable form.
    Show {
        /// The unit's folder (units/ID); a set folder (units/ID/DATE) shows that set.
        unit: PathBuf,
        /// Print JSON (the set's certification.json).
        #[arg(long)]
        json: bool,
    },
    /// Remove what killed certifications left behind (work folders, empty set folders);
    /// finished sets are never touched.
    Clean {
        /// The units folder.
        #[arg(default_value = "units")]
        units: PathBuf,
    },
}

/// The readable summary printed by `certify`.
pub fn summary_text(report: &CertifyReport) -> String {
    let mut s = String::new();
    if report.passed {
        let _ = writeln!(
            s,
            "unit {}: CERTIFIED ({} checks passed) in {:.1} s",
            report.unit_id,
            report.checks.len(),
            report.seconds
        );
    } else {
        let _ = writeln!(
            s,
            "unit {}: NOT CERTIFIED — failed: {}",
            report.unit_id,
            report.failed_checks.join(", ")
        );
        for c in report.checks.iter().filter(|c| !c.check.passed) {
            let _ = writeln!(
                s,
                "  {}: {} {} {} {}{}",
                c.check.name,
                c.check.value,
                if c.check.comparison == "at_most" {
                    "> limit"
                } else {
                    "< limit"
                },
                c.check.threshold,
                c.unit,
                c.note
                    .as_ref()
                    .map_or_else(String::new, |n| format!(" — {n}"))
            );
        }
    }
    if let Some(c) = &report.comparison {
        if c.significant.is_empty() {
            let _ = writeln!(s, "compared with {}: no significant change", c.previous);
        } else {
            let _ = writeln!(
                s,
                "compared with {}: CHANGED {} ({})",
                c.previous,
                c.changed_groups.join(", "),
                c.significant.join(", ")
            );
        }
    }
    let _ = writeln!(s, "set: {}", report.folder.display());
    let _ = writeln!(
        s,
        "report: {}",
        report.folder.join("report").join("index.md").display()
    );
    s
}

/// Run `kiwi-calib certify`: prints the summary (or JSON) and returns the report.
pub fn run_certify(args: &CertifyArgs) -> Result<CertifyReport> {
    if args.print_policy {
        print!("{}", Policy::default().to_toml()?);
        std::process::exit(0);
    }
    let (Some(unit), Some(captures)) = (&args.unit, &args.captures) else {
        return Err(CalibError::Input {
            path: PathBuf::from("."),
            message: "certify needs --unit ID and --captures DIR".into(),
        });
    };
    let policy = match &args.policy {
        Some(p) => Policy::load(p)?,
        None => Policy::default(),
    };
    let report = certify(&CertifyOptions {
        unit_id: unit.clone(),
        captures: captures.clone(),
        units_dir: args.out.clone(),
        policy,
        previous: args.previous.clone(),
        date: args.date.clone(),
        progress: !args.json && std::io::IsTerminal::is_terminal(&std::io::stderr()),
    })?;
    if args.json {
        let json = serde_json::to_string_pretty(&report)
            .map_err(|e| CalibError::Internal(format!("the report does not serialize: {e}")))?;
        println!("{json}");
    } else {
        print!("{}", summary_text(&report));
    }
    Ok(report)
}

/// Run `kiwi-calib units`; returns the text to print.
pub fn run_units(cmd: &UnitsCommand) -> Result<String> {
    match cmd {
        UnitsCommand::List {
            units,
            json: as_json,
        } => {
            let sets = list_units(units)?;
            let leftovers = list_leftovers(units)?;
            if *as_json {
                if !leftovers.is_empty() {
                    eprint!("{}", leftovers_text(&leftovers));
                }
                serde_json::to_string_pretty(&sets)
                    .map(|s| format!("{s}\n"))
                    .map_err(|e| CalibError::Internal(format!("does not serialize: {e}")))
            } else {
                Ok(format!(
                    "{}{}",
                    list_text(&sets),
                    leftovers_text(&leftovers)
                ))
            }
        }
        UnitsCommand::Clean { units } => {
            let removed = clean_leftovers(units)?;
            let mut s = String::new();
            for l in &removed {
                let _ = writeln!(s, "removed {} ({})", l.path.display(), l.what);
            }
            if removed.is_empty() {
                s.push_str("nothing to clean\n");
            }
            Ok(s)
        }
        UnitsCommand::Show {
            unit,
            json: as_json,
        } => {
            let set = match unit.file_name().and_then(|n| n.to_str()) {
                // A set folder: show that set.
                Some(name) if kiwi_core::io::parse_set_name(name).is_some() => {
                    let parent = unit.parent().unwrap_or(std::path::Path::new("."));
                    super::report::unit_sets(parent)?
                        .into_iter()
                        .find(|s| s.name == name)
                        .ok_or_else(|| CalibError::Input {
                            path: unit.clone(),
                            message: "is a set folder without calibration.json or \
                                      certification.json (an unfinished or killed run?); see \
                                      `kiwi-calib units list`"
                                .into(),
                        })?
                }
                _ => latest_set(unit)?,
            };
            if *as_json {
                let path = set.folder.join("certification.json");
                kiwi_core::io::read_text(&path)
                    .map(|t| format!("{t}\n"))
                    .map_err(CalibError::from)
            } else {
                show_text(&set)
            }
        }
    }
}
