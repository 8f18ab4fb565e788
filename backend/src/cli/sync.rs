//! `kiwi sync`: place an episode's cameras on one timeline from their audio (paper §4.1).

use std::path::PathBuf;

use anyhow::Result;

use super::named;

/// Arguments of `kiwi sync`.
#[derive(Debug, clap::Args)]
pub struct SyncArgs {
    /// A camera's audio: NAME=path.wav (repeat; the first is the reference).
    #[arg(long = "audio", value_name = "NAME=FILE")]
    pub audio: Vec<String>,
    /// A camera's A/V delay in seconds: NAME=SECONDS.
    #[arg(long = "av-delay", value_name = "NAME=SECONDS")]
    pub av_delay: Vec<String>,
    /// A camera's unit calibration (its A/V delay is used): NAME=calibration.json.
    #[arg(long = "calibration", value_name = "NAME=FILE")]
    pub calibration: Vec<String>,
    /// A camera's recording mode, to pick the A/V delay from its calibration: NAME=MODE.
    #[arg(long = "mode", value_name = "NAME=MODE")]
    pub mode: Vec<String>,
    /// Run as a stage on this session's episode (with --episode).
    #[arg(long, conflicts_with = "audio")]
    pub session: Option<PathBuf>,
    /// The episode to synchronise (with --session).
    #[arg(long, requires = "session")]
    pub episode: Option<String>,
    /// Re-run the stage even if its inputs are unchanged.
    #[arg(long)]
    pub force: bool,
    /// Print the full JSON result.
    #[arg(long)]
    pub json: bool,
}

/// Run `kiwi sync`.
pub fn run_sync_cmd(args: SyncArgs) -> Result<()> {
    let SyncArgs {
        audio,
        av_delay,
        calibration,
        mode,
        session,
        episode,
        force,
        json,
    } = args;
    let result = if let Some(session) = session {
        let episode = episode.ok_or_else(|| anyhow::anyhow!("--session needs --episode NAME"))?;
        let ctx = kiwi_backend::pipeline::SessionContext::load(&session)?;
        let report = kiwi_backend::pipeline::run(
            &ctx,
            &kiwi_backend::pipeline::RunOptions {
                episodes: Some(vec![episode.clone()]),
                only: Some(vec!["sync".into()]),
                force: if force {
                    vec!["sync".into()]
                } else {
                    Vec::new()
                },
                ..Default::default()
            },
            &kiwi_backend::pipeline::runner::NoProgress,
        )?;
        let id = kiwi_backend::pipeline::stage::StageId::episode(&episode, "sync");
        let label = id.label();
        match report
            .stages
            .iter()
            .find(|s| s.stage == label)
            .map(|s| &s.outcome)
        {
            Some(kiwi_backend::pipeline::runner::Outcome::Failed { reason }) => {
                anyhow::bail!("{reason}")
            }
            Some(kiwi_backend::pipeline::runner::Outcome::Current) if !json => {
                println!(
                    "{} is up to date (inputs unchanged; --force re-runs)",
                    id.dir(&ctx.root).join("sync.json").display()
                );
                return Ok(());
            }
            _ => {}
        }
        let path = id.dir(&ctx.root).join("sync.json");
        let text = std::fs::read_to_string(&path)?;
        eprintln!("wrote {}", path.display());
        serde_json::from_str::<kiwi_backend::sync::SyncResult>(&text)?
    } else {
        sync_files(&audio, &av_delay, &calibration, &mode)?
    };
    if json {
        println!("{}", serde_json::to_string_pretty(&result)?);
    } else {
        for c in &result.cameras {
            match c.offset_s {
                Some(offset) => println!(
                    "{:10} offset {offset:+12.6} s  drift {:+7.2} ppm  ({:?})",
                    c.name, c.drift_ppm, c.status
                ),
                None => println!(
                    "{:10} not placed on the timeline ({:?}: no accepted audio match)",
                    c.name, c.status
                ),
            }
        }
        for p in &result.pairs {
            let detail = p.reason.clone().unwrap_or_else(|| {
                format!(
                    "{} windows, {}",
                    p.windows,
                    p.class.clone().unwrap_or_default()
                )
            });
            println!(
                "pair {}-{}: {} (votes {}, ratio {:.1}) {detail}",
                p.a, p.b, p.status, p.votes, p.peak_ratio
            );
        }
    }
    Ok(())
}

fn sync_files(
    audio: &[String],
    av_delay: &[String],
    calibration: &[String],
    mode: &[String],
) -> Result<kiwi_backend::sync::SyncResult> {
    use anyhow::Context;
    if audio.len() < 2 {
        anyhow::bail!(
            "name at least two cameras with --audio NAME=FILE (or use --session and --episode)"
        );
    }
    let names: Vec<String> = audio
        .iter()
        .map(|a| named(a, "--audio").map(|(n, _)| n))
        .collect::<Result<_>>()?;
    for (flag, values) in [
        ("--av-delay", av_delay),
        ("--calibration", calibration),
        ("--mode", mode),
    ] {
        for v in values {
            let (n, _) = named(v, flag)?;
            if !names.contains(&n) {
                anyhow::bail!(
                    "{flag} {v}: there is no camera `{n}` (cameras given with --audio: {}); \
                     check the name",
                    names.join(", ")
                );
            }
        }
    }
    if let Some(d) = names
        .iter()
        .enumerate()
        .find_map(|(i, n)| names[..i].contains(n).then_some(n))
    {
        anyhow::bail!("--audio names camera `{d}` twice; give each camera once");
    }
    let mut inputs = Vec::new();
    for a in audio {
        let (name, file) = named(a, "--audio")?;
        let path = PathBuf::from(&file);
        let decoded = kiwi_backend::sync::audio::read_audio(&path)
            .with_context(|| format!("camera {name}"))?;
        let mut delay = 0.0;
        for d in av_delay {
            let (n, v) = named(d, "--av-delay")?;
            if n == name {
                delay = v
                    .parse::<f64>()
                    .with_context(|| format!("--av-delay {d}: expected seconds"))?;
            }
        }
        for c in calibration {
            let (n, f) = named(c, "--calibration")?;
            if n == name {
                let cal = kiwi_core::artifact::UnitCalibration::load(std::path::Path::new(&f))?;
                let m = mode
                    .iter()
                    .filter_map(|m| named(m, "--mode").ok())
                    .find(|(n, _)| *n == name)
                    .map(|(_, m)| m);
                delay =
                    kiwi_backend::sync::av_delay_for(&cal, m.as_deref(), std::path::Path::new(&f))?;
            }
        }
        inputs.push(kiwi_backend::sync::SyncInput {
            name,
            audio: decoded,
            av_delay_s: delay,
        });
    }
    Ok(kiwi_backend::sync::synchronise(&inputs))
}
