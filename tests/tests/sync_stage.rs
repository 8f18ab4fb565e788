//! End to end: a simulated session's episode is synchronised by the `sync` stage, and every
//! camera lands where the simulator put it (within the unmodelled acoustic propagation).

#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

use kiwi_backend::pipeline::runner::{NoProgress, Outcome};
use kiwi_backend::pipeline::{RunOptions, SessionContext, run};
use kiwi_backend::sync::{CameraStatus, SyncResult};
use kiwi_fixtures::session::{SessionOptions, write_session};

fn run_sync(ctx: &SessionContext) -> Outcome {
    let report = run(
        ctx,
        &RunOptions {
            episodes: Some(vec!["ep000".into()]),
            only: Some(vec!["sync".into()]),
            ..Default::default()
        },
        &NoProgress,
    )
    .unwrap();
    report
        .stages
        .iter()
        .find(|s| s.stage == "ep000/sync")
        .unwrap()
        .outcome
        .clone()
}

#[test]
fn sync_stage_places_every_camera_of_a_simulated_episode() {
    let dir = tempfile::tempdir().unwrap();
    let mut o = SessionOptions::new(dir.path().join("s"));
    o.seed = 21;
    o.resolution = 64;
    o.rate_hz = 2.0;
    o.duration_s = 40.0;
    let summary = write_session(&o).unwrap();
    let ctx = SessionContext::load(&summary.session_toml).unwrap();
    assert!(matches!(run_sync(&ctx), Outcome::Ran { .. }));
    let result: SyncResult = serde_json::from_str(
        &std::fs::read_to_string(dir.path().join("s/episodes/ep000/work/sync/sync.json")).unwrap(),
    )
    .unwrap();
    let truth: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(dir.path().join("s/episodes/ep000/truth/clocks.json")).unwrap(),
    )
    .unwrap();
    let clock = |name: &str| {
        let c = truth
            .as_array()
            .unwrap()
            .iter()
            .find(|c| c["camera"] == name)
            .unwrap();
        // The video clock is the device clock less the primary lens's time shift.
        let m = &c["microphone"];
        let drift = m["drift_ppm"].as_f64().unwrap() * 1e-6;
        let offset = m["offset_s"].as_f64().unwrap()
            + m["video_to_device_s"].as_f64().unwrap() * (1.0 + drift);
        (offset, drift, m["propagation_delay_s"].as_f64().unwrap())
    };
    let (o0, d0, p0) = clock(&result.cameras[0].name);
    for cam in &result.cameras[1..] {
        assert_ne!(
            cam.status,
            CameraStatus::Unmatched,
            "{}: {:?}",
            cam.name,
            result.pairs
        );
        let (o, _, p) = clock(&cam.name);
        // The audio path adds the propagation difference, which audio alone cannot see.
        let truth_offset = (o - o0) / (1.0 + d0) - (p - p0);
        let offset = cam.offset_s.expect("a matched camera has an offset");
        assert!(
            (offset - truth_offset).abs() < 1e-3,
            "{}: {} vs {truth_offset}",
            cam.name,
            offset
        );
    }
    // A second run with unchanged inputs is skipped.
    assert_eq!(run_sync(&ctx), Outcome::Current);
}
