//! `kiwi`: reconstruct episodes recorded on certified KIWI camera units.

use std::path::PathBuf;

use anyhow::Result;
use clap::{Parser, Subcommand};

/// Reconstruct KIWI episodes: audio sync, fisheye maps, metric recovery, localization, IMU
/// fusion, gripper opening, head pose, floor height, dataset export.
#[derive(Parser)]
#[command(name = "kiwi", version, about, long_about = None)]
struct Cli {
    /// More log output (repeat for more).
    #[arg(short, long, action = clap::ArgAction::Count, global = true)]
    verbose: u8,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Check a session: session.toml, unit calibrations and every prepared episode's files.
    Inspect {
        /// The session's session.toml.
        session: PathBuf,
        /// Print a machine-readable JSON summary.
        #[arg(long)]
        json: bool,
    },
}

fn main() -> Result<()> {
    let cli = Cli::parse();
    let level = if cli.verbose == 0 { "warn" } else { "info" };
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(level));
    tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .init();
    match cli.command {
        Command::Inspect { session, json } => {
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
        }
    }
    Ok(())
}
