//! `kiwi inspect`: check a session and its prepared episodes before any stage runs.

use std::path::PathBuf;

use anyhow::Result;

/// Arguments of `kiwi inspect`.
#[derive(Debug, clap::Args)]
pub struct InspectArgs {
    /// The session's session.toml.
    pub session: PathBuf,
    /// Decode every frame and the whole audio track (default: image headers and sizes, the WAV
    /// header against the file's size; imu.csv is always read in full).
    #[arg(long)]
    pub deep: bool,
    /// Print a machine-readable JSON summary.
    #[arg(long)]
    pub json: bool,
}

/// Exit status when the session has problems (listed on the output).
const EXIT_PROBLEMS: i32 = 2;

/// Run `kiwi inspect`.
pub fn run_inspect_cmd(args: InspectArgs) -> Result<()> {
    let InspectArgs {
        session,
        deep,
        json,
    } = args;
    let report = kiwi_backend::inspect::inspect_session(
        &session,
        kiwi_backend::inspect::InspectOptions { deep },
    )?;
    if json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        println!(
            "session {} (maps from episode {})",
            report.name, report.map_episode
        );
        for c in &report.cameras {
            let verdict = match c.certified {
                Some(true) => "certified",
                Some(false) => "FAILED certification",
                None => "not certified",
            };
            println!("  camera {:5} unit {} ({verdict})", c.camera, c.unit);
        }
        for e in &report.episodes {
            let lenses: Vec<String> = e
                .lenses
                .iter()
                .map(|(c, l, n)| format!("{c}/{l}: {n} frames"))
                .collect();
            println!("  episode {}: {}", e.name, lenses.join(", "));
        }
        if report.problems.is_empty() {
            println!(
                "every file checked ({}): no problem found",
                if deep {
                    "frames and audio decoded"
                } else {
                    "headers and sizes; --deep decodes every frame"
                }
            );
        }
    }
    if !report.problems.is_empty() {
        for p in &report.problems {
            eprintln!("problem: {p}");
        }
        eprintln!("{} problem(s) found", report.problems.len());
        std::process::exit(EXIT_PROBLEMS);
    }
    Ok(())
}
