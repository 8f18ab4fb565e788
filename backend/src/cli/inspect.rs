//! `kiwi inspect`: check a session and its prepared episodes before any stage runs.

use std::path::PathBuf;

use anyhow::Result;

/// Arguments of `kiwi inspect`.
#[derive(Debug, clap::Args)]
pub struct InspectArgs {
    /// The session's session.toml.
    pub session: PathBuf,
    /// Print a machine-readable JSON summary.
    #[arg(long)]
    pub json: bool,
}

/// Run `kiwi inspect`.
pub fn run_inspect_cmd(args: InspectArgs) -> Result<()> {
    let InspectArgs { session, json } = args;
    let report = kiwi_backend::inspect::inspect_session(&session)?;
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
    }
    Ok(())
}
