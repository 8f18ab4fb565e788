//! `kiwi status`: where every stage of a session stands — current, stale (with the changed
//! input named), failed (with its reason) or not run — without running anything.

use std::collections::BTreeMap;

use serde::Serialize;

use super::context::SessionContext;
use super::graph::build;
use super::runner::{fingerprint_of, selected_episodes};
use super::stage::{Manifest, StageId, StageState, state_of};
use crate::error::Result;

/// One stage's state.
#[derive(Debug, Clone, Serialize)]
pub struct StageStatus {
    /// `session` or the episode.
    pub scope: String,
    /// Stage name.
    pub stage: String,
    /// `current`, `stale`, `failed`, `not run` or `blocked`.
    pub state: String,
    /// The changed inputs, the failure reason, or what blocks it.
    pub detail: String,
    /// Wall time of its last run (s).
    pub seconds: Option<f64>,
}

/// The state of every stage of the session's graph for `episodes` (all when `None`).
pub fn status(ctx: &SessionContext, episodes: Option<&[String]>) -> Result<Vec<StageStatus>> {
    let episodes = selected_episodes(ctx, episodes)?;
    let graph = build(ctx, &episodes);
    let mut digests: BTreeMap<StageId, String> = BTreeMap::new();
    let mut out = Vec::new();
    for node in &graph {
        let dir = node.id.dir(&ctx.root);
        let manifest = Manifest::read(&dir);
        if let Some(m) = &manifest {
            digests.insert(node.id.clone(), m.output_digest.clone());
        }
        let (state, detail) = match fingerprint_of(ctx, node, &digests) {
            Err(e) => ("blocked".to_string(), e.to_string()),
            Ok(fp) => match state_of(&dir, &fp) {
                StageState::Current => ("current".into(), String::new()),
                StageState::NotRun => ("not run".into(), String::new()),
                StageState::Stale { changed } => ("stale".into(), changed.join(", ")),
                StageState::Failed { reason } => ("failed".into(), reason),
            },
        };
        out.push(StageStatus {
            scope: node.id.scope.label().to_string(),
            stage: node.id.name.clone(),
            state,
            detail,
            seconds: manifest.map(|m| m.seconds),
        });
    }
    ctx.digests.save();
    Ok(out)
}
