//! `kiwi report`: a session's report page (the same page the `report` stage of `kiwi run`
//! writes), made again from what the stages left.

use std::path::PathBuf;

use anyhow::Result;

use kiwi_backend::pipeline::SessionContext;
use kiwi_backend::report::{PAGE_FILE, REPORT_DIR, write_report};

/// Arguments of `kiwi report`.
#[derive(Debug, clap::Args)]
pub struct ReportArgs {
    /// The session's session.toml.
    #[arg(long)]
    pub session: PathBuf,
    /// The HTML file to write [default: SESSION/report/index.html, where `kiwi run` puts it].
    #[arg(long)]
    pub out: Option<PathBuf>,
}

/// Run `kiwi report`.
pub fn run_report_cmd(args: &ReportArgs) -> Result<()> {
    let ctx = SessionContext::load(&args.session)?;
    let out = args
        .out
        .clone()
        .unwrap_or_else(|| ctx.root.join(REPORT_DIR).join(PAGE_FILE));
    let summary = write_report(&ctx, &out)?;
    println!(
        "wrote {} ({} episodes, {} charts, {:.2} MB)",
        out.display(),
        summary.episodes,
        summary.plots,
        summary.bytes as f64 / 1e6
    );
    Ok(())
}
