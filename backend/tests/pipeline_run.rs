//! `kiwi run` as a command: a run killed during localization resumes and ends byte-identical to
//! an uninterrupted run (with another thread count, datasets included), `kiwi status` says where stages stand, and
//! a map episode that cannot be mapped gives every episode an `unusable` verdict naming the
//! stream, with exit status 2; a wrist whose stream is missing in one episode leaves that episode
//! `unusable` with the other wrist published.

#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant};

use kiwi_fixtures::session::{SessionOptions, write_session};

#[path = "support/pipeline_sessions.rs"]
mod sessions;
use sessions::{
    copy_inputs, files, localizing, small_session, small_session_with_head, unmappable_session,
};

const KIWI: &str = env!("CARGO_BIN_EXE_kiwi");
/// Longest the killed run may take to reach localization before the test gives up.
const REACH_LOCALIZE: Duration = Duration::from_secs(600);

/// What the pipeline wrote: every stage folder and every episode's `out/`.
fn results(session: &Path) -> Vec<(String, Vec<u8>)> {
    let mut all: Vec<(String, Vec<u8>)> = files(&session.join("work"))
        .into_iter()
        .map(|(p, b)| (format!("work/{p}"), b))
        .collect();
    all.extend(files(&session.join("exports")).into_iter().map(|(p, b)| {
        // The sidecar's index holds every carried file's digest; the manifests hold wall times.
        let b = if p.ends_with("sidecar.json") {
            let mut index: serde_json::Value = serde_json::from_slice(&b).unwrap();
            index["files"]
                .as_array_mut()
                .unwrap()
                .retain(|f| !f["path"].as_str().unwrap().ends_with("manifest.json"));
            index.to_string().into_bytes()
        } else {
            b
        };
        (format!("exports/{p}"), b)
    }));
    for ep in ["ep000", "ep001"] {
        for sub in ["work", "out"] {
            let dir = session.join("episodes").join(ep).join(sub);
            all.extend(
                files(&dir)
                    .into_iter()
                    .map(|(p, b)| (format!("{ep}/{sub}/{p}"), b)),
            );
        }
    }
    all
}

/// The bound on the cameras' heights above the floor on fused poses (m): the floor's own
/// accuracy goal (1 cm) plus the fused trajectory's height error at this session's 320 px.
const MAX_HEIGHT_ERROR_M: f64 = 0.02;

/// An episode's published floor: `floor.json`, its windows and figure, the `floor` section of
/// `quality.json`; when a floor was found, every front camera's `cam_height_m` against the
/// simulator's camera height (its world's floor is at z = 0 and the scene frame is level).
/// Whether a floor was found (and its heights checked).
fn floor_heights_match_the_truth(root: &Path, ep: &str, quality: &serde_json::Value) -> bool {
    let episode = root.join("episodes").join(ep);
    let out = episode.join("out");
    for file in ["floor.json", "floor_windows.csv", "floor.svg"] {
        assert!(out.join(file).is_file(), "{ep}: no {file}");
    }
    let floor = &quality["floor"];
    println!("{ep} floor: {floor}");
    let status = floor["floor"]["status"].as_str().unwrap();
    if status != "found" {
        assert!(
            !floor["floor"]["reason"].as_str().unwrap().is_empty(),
            "{floor}"
        );
        return false;
    }
    for wrist in ["left", "right"] {
        let mut reader = csv::Reader::from_path(out.join(format!("{wrist}.csv"))).unwrap();
        let header = reader.headers().unwrap().clone();
        let col = |name: &str| header.iter().position(|h| h == name).unwrap();
        let (tc, height) = (col("t_camera"), col("cam_height_m"));
        let truth: Vec<(f64, f64)> =
            std::fs::read_to_string(episode.join("truth").join(wrist).join("front_poses.csv"))
                .unwrap()
                .lines()
                .skip(1)
                .map(|l| {
                    let v: Vec<f64> = l.split(',').map(|x| x.parse().unwrap()).collect();
                    // `t` (the camera's clock, as the outputs' `t_camera`) and `pz`.
                    (v[0], v[4])
                })
                .collect();
        let mut errors: Vec<f64> = reader
            .records()
            .map(|r| r.unwrap())
            .filter_map(|r| {
                let t: f64 = r.get(tc)?.parse().ok()?;
                let h: f64 = r.get(height)?.parse().ok()?;
                let k = truth.partition_point(|x| x.0 < t);
                let (a, b) = (truth.get(k.checked_sub(1)?)?, truth.get(k)?);
                let z = a.1 + (b.1 - a.1) * (t - a.0) / (b.0 - a.0);
                Some((h - z).abs())
            })
            .collect();
        assert!(!errors.is_empty(), "{ep} {wrist}: no heights");
        errors.sort_by(f64::total_cmp);
        let median = errors[errors.len() / 2];
        println!("{ep} {wrist}: camera height above the floor, median error {median:.4} m");
        assert!(
            median < MAX_HEIGHT_ERROR_M,
            "{ep} {wrist}: median height error {median:.4} m"
        );
    }
    true
}

#[test]
fn a_killed_run_resumes_to_byte_identical_results() {
    let tmp = tempfile::tempdir().unwrap();
    // With the head camera: its stage runs and resumes like the others.
    let a = small_session_with_head(&tmp.path().join("a"), 2);
    // With the datasets on: their stages run last, and resume like the others.
    let mut text = std::fs::read_to_string(&a).unwrap();
    text.push_str("\n[export]\nformats = [\"lerobot\", \"sidecar\", \"colmap\"]\n");
    std::fs::write(&a, text).unwrap();
    let b_dir = tmp.path().join("b");
    copy_inputs(a.parent().unwrap(), &b_dir);
    let b = b_dir.join("session.toml");

    let out = Command::new(KIWI)
        .args(["run", "--threads", "1", "--json", "--session"])
        .arg(&a)
        .output()
        .unwrap();
    let report: serde_json::Value = serde_json::from_slice(&out.stdout)
        .unwrap_or_else(|e| panic!("{e}: {}", String::from_utf8_lossy(&out.stderr)));
    println!("uninterrupted: {}", report["counts"]);
    let stages = report["stages"].as_array().unwrap();
    let usable: Vec<&str> = ["ep000", "ep001"]
        .into_iter()
        .filter(|ep| {
            let q = a
                .parent()
                .unwrap()
                .join(format!("episodes/{ep}/out/quality.json"));
            let q: serde_json::Value =
                serde_json::from_str(&std::fs::read_to_string(q).unwrap()).unwrap();
            q["verdict"] != "unusable"
        })
        .collect();
    assert!(
        !usable.is_empty(),
        "some episode is usable: {}",
        report["counts"]
    );
    // The head stage ran per episode and the outputs publish its files and record.
    for ep in ["ep000", "ep001"] {
        let s = stages
            .iter()
            .find(|s| s["stage"] == format!("{ep}/head"))
            .unwrap_or_else(|| panic!("no head stage for {ep}: {stages:?}"));
        assert_eq!(s["outcome"], "ran", "{s}");
    }
    let mut floors_checked = 0;
    for ep in &usable {
        let out = a.parent().unwrap().join(format!("episodes/{ep}/out"));
        for file in ["head.csv", "head.tum", "head_camera.csv"] {
            assert!(out.join(file).is_file(), "{ep}: no {file}");
        }
        let q: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("quality.json")).unwrap())
                .unwrap();
        let head = &q["head"];
        for wrist in ["left", "right"] {
            assert!(
                head["wrists"][wrist]["frames"].as_u64().unwrap() > 0,
                "{head}"
            );
        }
        assert!(head["samples"].as_u64().unwrap() > 0, "{head}");
        println!("{ep} head: {head}");
        floors_checked += usize::from(floor_heights_match_the_truth(a.parent().unwrap(), ep, &q));
    }
    assert!(floors_checked > 0, "no usable episode found its floor");
    // The floor stage ran per episode and the outputs publish its files.
    for ep in ["ep000", "ep001"] {
        let s = stages
            .iter()
            .find(|s| s["stage"] == format!("{ep}/floor"))
            .unwrap_or_else(|| panic!("no floor stage for {ep}: {stages:?}"));
        assert_eq!(s["outcome"], "ran", "{s}");
    }
    for name in [
        "session/export-lerobot",
        "session/export-sidecar",
        "session/export-colmap",
    ] {
        let s = stages.iter().find(|s| s["stage"] == name).unwrap();
        assert_eq!(s["outcome"], "ran", "{s}");
    }
    // The scene export posed images of the usable episodes, each with its mask.
    let colmap = a.parent().unwrap().join("exports/colmap");
    let images = std::fs::read_to_string(colmap.join("sparse/0/images.txt")).unwrap();
    let names: Vec<&str> = images
        .lines()
        .filter(|l| !l.starts_with('#'))
        .step_by(2)
        .filter_map(|l| l.split_whitespace().nth(9))
        .collect();
    assert!(!names.is_empty(), "{images:.400}");
    for name in &names {
        assert!(usable.iter().any(|ep| name.starts_with(ep)), "{name}");
        let mask = colmap
            .join("images")
            .join(name.replace(".png", "_mask.png"));
        assert!(mask.is_file(), "{}", mask.display());
    }
    let info: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(a.parent().unwrap().join("exports/lerobot/meta/info.json"))
            .unwrap(),
    )
    .unwrap();
    assert_eq!(info["total_episodes"], usable.len(), "{info}");

    // Kill a second run (another thread count) as soon as it localizes.
    let mut child = Command::new(KIWI)
        .args(["run", "--threads", "2", "--json", "--session"])
        .arg(&b)
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let start = Instant::now();
    while !["ep000", "ep001"].iter().any(|ep| localizing(&b_dir, ep)) {
        assert!(
            start.elapsed() < REACH_LOCALIZE,
            "never reached localization"
        );
        if child.try_wait().unwrap().is_some() {
            panic!("the run ended before localization");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    child.kill().unwrap();
    child.wait().unwrap();
    let status = Command::new(KIWI)
        .args(["status", "--session"])
        .arg(&b)
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&status.stdout).into_owned();
    println!("status after the kill:\n{text}");
    assert!(text.contains("map-rear") && text.contains("current"));
    assert!(text.contains("not run"));

    let resumed = Command::new(KIWI)
        .args(["run", "--threads", "2", "--json", "--session"])
        .arg(&b)
        .output()
        .unwrap();
    let report: serde_json::Value = serde_json::from_slice(&resumed.stdout).unwrap();
    println!("resumed: {}", report["counts"]);
    // The finished maps were not built again.
    let map_stage = report["stages"]
        .as_array()
        .unwrap()
        .iter()
        .find(|s| s["stage"] == "session/map-rear")
        .unwrap();
    assert_eq!(map_stage["outcome"], "current", "{map_stage}");
    let (ra, rb) = (results(a.parent().unwrap()), results(&b_dir));
    let names = |r: &[(String, Vec<u8>)]| r.iter().map(|(n, _)| n.clone()).collect::<Vec<_>>();
    assert_eq!(names(&ra), names(&rb));
    for ((name, x), (_, y)) in ra.iter().zip(&rb) {
        assert!(
            x == y,
            "{name} differs between the uninterrupted and the resumed run"
        );
    }
    assert!(
        !b_dir
            .join("work")
            .read_dir()
            .unwrap()
            .flatten()
            .any(|e| { e.file_name().to_string_lossy().starts_with(".tmp-") })
    );

    // The map-sharing ablation on the finished session: KIWI's column is the pipeline's own
    // supported fraction of the right wrist, on the same frames.
    let out = Command::new(KIWI)
        .args(["evaluate", "ablation", "--json", "--session"])
        .arg(&a)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let ablation: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    println!("ablation: {ablation}");
    let rows = ablation["episodes"].as_array().unwrap();
    assert!(!rows.is_empty(), "{ablation}");
    for row in rows {
        let frames = row["frames"].as_u64().unwrap() as f64;
        let kiwi = row["kiwi_supported"].as_u64().unwrap() as f64 / frames;
        let reported = row["reported_fraction"].as_f64().unwrap();
        assert!((kiwi - reported).abs() < 1e-12, "{row}");
        assert!(row["cross_hand_supported"].as_u64().unwrap() as f64 <= frames);
    }
    assert!(
        a.parent()
            .unwrap()
            .join("evaluation/ablation.json")
            .is_file()
    );
}

/// `kiwi run --json` on `toml`, which must exit with status 2 (an episode unusable): its JSON
/// report.
fn run_json_with_unusable(toml: &Path) -> serde_json::Value {
    let out = Command::new(KIWI)
        .args(["run", "--json", "--session"])
        .arg(toml)
        .output()
        .unwrap();
    assert_eq!(
        out.status.code(),
        Some(2),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).unwrap()
}

/// A wrist whose stages fail in one episode (its front stream is missing) does not take the
/// other wrist with it: the episode is `unusable`, says which stream is missing, and publishes
/// the other wrist's trajectory; the other episode is untouched.
#[test]
fn a_missing_stream_of_one_wrist_publishes_the_other_wrist() {
    let tmp = tempfile::tempdir().unwrap();
    let toml = small_session(tmp.path(), 2);
    let root = toml.parent().unwrap();
    let ep1 = root.join("episodes/ep001");
    std::fs::remove_dir_all(ep1.join("right/front")).unwrap();
    let report = run_json_with_unusable(&toml);
    let episodes = report["episodes"].as_array().unwrap();
    assert_ne!(episodes[0]["verdict"], "unusable", "{}", episodes[0]);
    assert_eq!(episodes[1]["verdict"], "unusable");
    let reasons = episodes[1]["reasons"].to_string();
    assert!(
        reasons.contains("right: no trajectory") && reasons.contains("right/front"),
        "{reasons}"
    );
    let published = ep1.join("out");
    assert!(
        published.join("left.csv").is_file() && published.join("left_tip.tum").is_file(),
        "{reasons}"
    );
    assert!(!published.join("right.csv").exists());
    let quality: serde_json::Value =
        serde_json::from_slice(&std::fs::read(published.join("quality.json")).unwrap()).unwrap();
    let wrists: Vec<&String> = quality["wrists"].as_object().unwrap().keys().collect();
    assert_eq!(wrists, ["left"]);
    assert!(root.join("episodes/ep000/out/right.csv").is_file());
}

#[test]
fn an_unmappable_map_episode_makes_every_episode_unusable_and_says_why() {
    let tmp = tempfile::tempdir().unwrap();
    let toml = unmappable_session(tmp.path());
    let report = run_json_with_unusable(&toml);
    for e in report["episodes"].as_array().unwrap() {
        assert_eq!(e["verdict"], "unusable");
        let reasons = e["reasons"].to_string();
        assert!(
            reasons.contains("map-rear") && reasons.contains("left/rear"),
            "{reasons}"
        );
    }
    // The text summary counts them.
    let out = Command::new(KIWI)
        .args(["run", "--session"])
        .arg(&toml)
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(text.contains("2 unusable"), "{text}");
}

#[test]
fn the_export_stage_follows_every_episode_and_names_the_ones_it_leaves_out() {
    let tmp = tempfile::tempdir().unwrap();
    // Cheap and fast: the map episode cannot be mapped, so every episode is unusable.
    let toml = unmappable_session(tmp.path());
    let mut text = std::fs::read_to_string(&toml).unwrap();
    text.push_str("\n[export]\nformats = [\"lerobot\", \"sidecar\"]\n");
    std::fs::write(&toml, text).unwrap();
    let stage = |report: &serde_json::Value, name: &str| {
        report["stages"]
            .as_array()
            .unwrap()
            .iter()
            .find(|s| s["stage"] == name)
            .cloned()
    };

    // A run of some episodes does not rewrite the session's datasets.
    let out = Command::new(KIWI)
        .args(["run", "--json", "--episodes", "ep001", "--session"])
        .arg(&toml)
        .output()
        .unwrap();
    let report: serde_json::Value = serde_json::from_slice(&out.stdout)
        .unwrap_or_else(|e| panic!("{e}: {}", String::from_utf8_lossy(&out.stderr)));
    assert!(stage(&report, "session/export-lerobot").is_none());

    // A run of every episode: the exports run (failed episodes do not block them), leave each
    // unusable episode out with its reason, and fail as nothing is left.
    let out = Command::new(KIWI)
        .args(["run", "--json", "--session"])
        .arg(&toml)
        .output()
        .unwrap();
    let report: serde_json::Value = serde_json::from_slice(&out.stdout)
        .unwrap_or_else(|e| panic!("{e}: {}", String::from_utf8_lossy(&out.stderr)));
    for name in ["session/export-lerobot", "session/export-sidecar"] {
        let s = stage(&report, name).unwrap_or_else(|| panic!("no {name} in {report}"));
        let reason = s.to_string();
        assert!(
            reason.contains("failed")
                && reason.contains("no episode")
                && reason.contains("ep000: verdict unusable")
                && reason.contains("ep001: verdict unusable")
                && reason.contains("map-rear"),
            "{name}: {s}"
        );
    }
    assert!(
        !toml.parent().unwrap().join("exports/lerobot").exists(),
        "a failed export publishes nothing"
    );
    // A session.toml naming an unknown format is refused, naming the field.
    let mut text = std::fs::read_to_string(&toml).unwrap();
    text = text.replace("\"sidecar\"", "\"rlds\"");
    std::fs::write(&toml, text).unwrap();
    let out = Command::new(KIWI)
        .args(["run", "--session"])
        .arg(&toml)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        err.contains("export.formats[1]") && err.contains("rlds"),
        "{err}"
    );
}

#[test]
fn run_refuses_unknown_stages_and_episodes_naming_them() {
    let tmp = tempfile::tempdir().unwrap();
    let mut o = SessionOptions::new(tmp.path().join("s"));
    o.resolution = 64;
    o.rate_hz = 2.0;
    o.duration_s = 2.0;
    o.episodes = 2;
    o.head = false;
    let toml = write_session(&o).unwrap().session_toml;
    for (args, expect) in [
        (vec!["--from", "mapping"], "--from mapping: unknown stage"),
        (vec!["--force", "fuse"], "--force fuse: unknown stage"),
        (
            vec!["--force", "localize-left-middle"],
            "--force localize-left-middle: unknown stage",
        ),
        (
            vec!["--from", "ep009/sync"],
            "--from ep009/sync: unknown stage",
        ),
        (vec!["--episodes", "ep009"], "no episode `ep009`"),
    ] {
        let out = Command::new(KIWI)
            .args(["run", "--session"])
            .arg(&toml)
            .args(&args)
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(1));
        assert!(err.contains(expect), "{err}");
    }
    let out = Command::new(KIWI)
        .args(["run", "--session"])
        .arg(toml.parent().unwrap())
        .output()
        .unwrap();
    assert!(String::from_utf8_lossy(&out.stderr).contains("expected the session's session.toml"));

    // A stage named as `kiwi status` lists it, with its episode: only that one re-runs.
    let sync_outcomes = |extra: &[&str]| -> Vec<(String, String)> {
        let out = Command::new(KIWI)
            .args(["run", "--json", "--only", "sync", "--session"])
            .arg(&toml)
            .args(extra)
            .output()
            .unwrap();
        let report: serde_json::Value = serde_json::from_slice(&out.stdout)
            .unwrap_or_else(|e| panic!("{e}: {}", String::from_utf8_lossy(&out.stderr)));
        report["stages"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|s| s["stage"].as_str().unwrap().ends_with("/sync"))
            .map(|s| {
                (
                    s["stage"].as_str().unwrap().to_string(),
                    s["outcome"].as_str().unwrap().to_string(),
                )
            })
            .collect()
    };
    let first = sync_outcomes(&[]);
    assert!(first.len() >= 2, "{first:?}");
    assert!(first.iter().all(|(_, o)| o == "ran"), "{first:?}");
    let again = sync_outcomes(&["--force", "ep000/sync"]);
    for (stage, outcome) in &again {
        let expected = if stage == "ep000/sync" {
            "ran"
        } else {
            "current"
        };
        assert_eq!(outcome, expected, "{again:?}");
    }
}
