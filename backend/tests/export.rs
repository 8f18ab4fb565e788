//! `kiwi export` on small synthetic episode outputs with known trajectories, read back with
//! independent readers: pyarrow for the LeRobot parquet files and their schemas, ffprobe and
//! ffmpeg for every video frame's presentation time and content, zarr-python for the UMI
//! store. The Python readers are installed by `make deps`; when one is missing locally its
//! checks are skipped with a message on stderr (ffmpeg is required).

#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

#[path = "support/export_session.rs"]
mod synthetic;

use std::collections::BTreeMap;
use std::path::Path;
use std::process::Command;

use nalgebra::Vector3;
use serde_json::Value;

use kiwi_backend::export::{ExportFormat, ExportOptions, export};
use kiwi_core::geometry::{so3_exp, so3_log};

use synthetic::{
    IMU_ONLY, LEROBOT_TOL_S, RATE, RESAMPLE_TOL, Synthetic, camera_time, f64s, grey, python_reader,
    session_time, truth_opening, truth_tip,
};

/// 2 s per camera at 64×48 px: seconds to export and read back.
const SPEC: Synthetic = Synthetic {
    frames: 60,
    width: 64,
    height: 48,
    rear_lens: false,
};
const FRAMES: usize = SPEC.frames;
const W: u32 = SPEC.width;
const H: u32 = SPEC.height;

fn make_session(root: &Path) -> std::path::PathBuf {
    synthetic::make_session(&SPEC, root)
}

fn expected_grid(fps: f64) -> (f64, usize) {
    synthetic::expected_grid(&SPEC, fps)
}

fn nearest_frame(camera: usize, t: f64) -> usize {
    synthetic::nearest_frame(&SPEC, camera, t)
}

/// Every frame's presentation time, by ffprobe.
fn ffprobe_times(video: &Path) -> Vec<f64> {
    let out = Command::new("ffprobe")
        .args([
            "-v",
            "error",
            "-select_streams",
            "v:0",
            "-show_entries",
            "frame=pts_time",
        ])
        .args(["-of", "csv=p=0"])
        .arg(video)
        .output()
        .expect("ffprobe runs (make deps installs ffmpeg)");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout)
        .lines()
        .filter(|l| !l.trim().is_empty())
        .map(|l| l.trim().trim_end_matches(',').parse::<f64>().unwrap())
        .collect()
}

/// Every frame's mean grey level, decoded by ffmpeg.
fn ffmpeg_frame_means(video: &Path) -> Vec<f64> {
    let out = Command::new("ffmpeg")
        .args(["-v", "error", "-i"])
        .arg(video)
        .args(["-f", "rawvideo", "-pix_fmt", "gray", "-"])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    out.stdout
        .chunks_exact((W * H) as usize)
        .map(|f| f.iter().map(|&v| f64::from(v)).sum::<f64>() / f.len() as f64)
        .collect()
}

#[test]
fn lerobot_export_reads_back_with_pyarrow_and_ffprobe() {
    let dir = tempfile::tempdir().unwrap();
    let session = make_session(dir.path());
    let out = dir.path().join("lerobot");
    let fps = 15.0;
    let options = ExportOptions {
        fps: Some(fps),
        ..ExportOptions::default()
    };
    let report = export(&session, ExportFormat::LeRobot, &options, &out).unwrap();
    assert_eq!(report.exported, vec!["ep0".to_string()]);
    assert_eq!(
        report.skipped.len(),
        1,
        "the unusable episode is left out with its reason"
    );
    assert!(
        report.skipped[0].1.contains("unusable"),
        "{:?}",
        report.skipped
    );
    let (t0, rows) = expected_grid(fps);
    assert_eq!(report.frames, rows);

    let info: Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("meta/info.json")).unwrap())
            .unwrap();
    assert_eq!(info["codebase_version"], "v3.0");
    assert_eq!(info["fps"], 15);
    assert_eq!(info["total_frames"], rows);
    assert_eq!(info["total_episodes"], 1);
    let names = info["features"]["observation.state"]["names"]
        .as_array()
        .unwrap();
    assert_eq!(names.len(), 16);
    assert_eq!(names[0], "left_tip_x");
    assert_eq!(names[15], "right_gripper");
    for key in [
        "observation.images.left_front",
        "observation.images.right_front",
    ] {
        assert_eq!(info["features"][key]["dtype"], "video");
        assert_eq!(info["features"][key]["shape"], serde_json::json!([H, W, 3]));
    }
    let stats: Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("meta/stats.json")).unwrap())
            .unwrap();
    assert_eq!(
        stats["observation.state"]["mean"].as_array().unwrap().len(),
        16
    );
    assert_eq!(
        stats["observation.state"]["count"],
        serde_json::json!([rows])
    );
    // Image statistics per RGB channel, shaped (3, 1, 1), of pixel values scaled to 0..1, over
    // every row's source frame (a short episode's frames are all sampled); each frame is one
    // grey level.
    for (c, camera) in ["left", "right"].iter().enumerate() {
        let s = &stats[format!("observation.images.{camera}_front")];
        let greys: Vec<f64> = (0..rows)
            .map(|k| f64::from(grey(c, nearest_frame(c, t0 + k as f64 / fps))) / 255.0)
            .collect();
        let mean = greys.iter().sum::<f64>() / rows as f64;
        let std = (greys.iter().map(|g| (g - mean).powi(2)).sum::<f64>() / rows as f64).sqrt();
        let min = greys.iter().copied().fold(f64::INFINITY, f64::min);
        let max = greys.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        assert_eq!(s["count"], serde_json::json!([rows]), "{camera}");
        for (name, want) in [("mean", mean), ("std", std), ("min", min), ("max", max)] {
            let channels = s[name].as_array().unwrap();
            assert_eq!(channels.len(), 3, "{camera} {name}: three channels");
            for ch in channels {
                let v = ch[0][0].as_f64().unwrap();
                assert!((v - want).abs() < 1e-9, "{camera} {name}: {v}, want {want}");
            }
        }
    }

    // Videos: every frame presented at its row's timestamp, showing the nearest source frame.
    for (c, camera) in ["left", "right"].iter().enumerate() {
        let video = out.join(format!(
            "videos/observation.images.{camera}_front/chunk-000/file-000.mp4"
        ));
        let times = ffprobe_times(&video);
        assert_eq!(times.len(), rows, "{camera}: one video frame per row");
        for (k, t) in times.iter().enumerate() {
            assert!(
                (t - k as f64 / fps).abs() <= LEROBOT_TOL_S,
                "{camera} frame {k} at {t}"
            );
        }
        let means = ffmpeg_frame_means(&video);
        assert_eq!(means.len(), rows);
        for (k, m) in means.iter().enumerate() {
            let want = f64::from(grey(c, nearest_frame(c, t0 + k as f64 / fps)));
            assert!(
                (m - want).abs() < 1.5,
                "{camera} row {k}: grey {m}, source frame grey {want}"
            );
        }
    }

    let data = out.join("data/chunk-000/file-000.parquet");
    let tasks = out.join("meta/tasks.parquet");
    let episodes = out.join("meta/episodes/chunk-000/file-000.parquet");
    let Some(read) = python_reader("read_parquet.py", &[&data, &tasks, &episodes]) else {
        return;
    };
    let d = &read[data.to_str().unwrap()];
    let schema = &d["schema"];
    assert_eq!(
        schema["observation.state"],
        "fixed_size_list<item: float>[16]"
    );
    assert_eq!(schema["action"], "fixed_size_list<item: float>[16]");
    assert_eq!(schema["timestamp"], "float");
    for key in ["frame_index", "episode_index", "index", "task_index"] {
        assert_eq!(schema[key], "int64", "{key}");
    }
    assert_eq!(schema["kiwi.support"], "fixed_size_list<item: int64>[2]");
    let cols = &d["columns"];
    let ts = f64s(&cols["timestamp"]);
    assert_eq!(ts.len(), rows);
    let states: Vec<Vec<f64>> = cols["observation.state"]
        .as_array()
        .unwrap()
        .iter()
        .map(f64s)
        .collect();
    let actions: Vec<Vec<f64>> = cols["action"]
        .as_array()
        .unwrap()
        .iter()
        .map(f64s)
        .collect();
    let support: Vec<Vec<f64>> = cols["kiwi.support"]
        .as_array()
        .unwrap()
        .iter()
        .map(f64s)
        .collect();
    let t_session = f64s(&cols["kiwi.t_session"]);
    for k in 0..rows {
        assert!(
            (ts[k] - k as f64 / fps).abs() < 1e-6,
            "timestamp {k}: {}",
            ts[k]
        );
        assert_eq!(cols["frame_index"][k], k);
        assert_eq!(cols["index"][k], k);
        let t = t0 + k as f64 / fps;
        assert!((t_session[k] - t).abs() < 1e-9);
        for c in 0..2 {
            let s = &states[k][c * 8..(c + 1) * 8];
            let truth = truth_tip(c, t);
            let p = truth.translation.vector;
            let dp = (Vector3::new(s[0], s[1], s[2]) - p).norm();
            assert!(dp < RESAMPLE_TOL, "row {k} wrist {c}: position off by {dp}");
            let q = nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
                s[6], s[3], s[4], s[5],
            ));
            let dr = so3_log(&(q.inverse() * truth.rotation)).norm();
            assert!(dr < RESAMPLE_TOL, "row {k} wrist {c}: rotation off by {dr}");
            let g = s[7];
            assert!(
                (g - truth_opening(c, t)).abs() < 2e-4,
                "row {k} wrist {c}: opening {g}"
            );
        }
        let next = (k + 1).min(rows - 1);
        assert_eq!(
            actions[k], states[next],
            "action {k} is the next row's state"
        );
        // Rows whose bracketing left frames include an IMU-only one carry code 3.
        let i = (0..FRAMES)
            .rev()
            .find(|&i| session_time(0, camera_time(0, i)) <= t)
            .unwrap();
        let imu_only = IMU_ONLY.contains(&i)
            || (IMU_ONLY.contains(&(i + 1)) && session_time(0, camera_time(0, i)) < t);
        assert_eq!(
            support[k][0],
            if imu_only { 3.0 } else { 0.0 },
            "row {k} support"
        );
        assert_eq!(support[k][1], 0.0);
    }
    let tk = &read[tasks.to_str().unwrap()];
    assert_eq!(tk["columns"]["task_index"], serde_json::json!([0]));
    if let Some(index) = tk.get("pandas_index") {
        assert_eq!(
            index,
            &serde_json::json!(["pick up the cup"]),
            "pandas reads the task as the index"
        );
    }
    let ep = &read[episodes.to_str().unwrap()];
    let ec = &ep["columns"];
    assert_eq!(ec["length"], serde_json::json!([rows]));
    assert_eq!(ec["tasks"], serde_json::json!([["pick up the cup"]]));
    assert_eq!(ec["dataset_to_index"], serde_json::json!([rows]));
    assert_eq!(
        ec["videos/observation.images.left_front/from_timestamp"],
        serde_json::json!([0.0])
    );
    assert_eq!(ec["kiwi/episode"], serde_json::json!(["ep0"]));
    // Per-episode statistics, as LeRobot stores them: numeric features as lists, views as
    // (3, 1, 1) nested lists; with one episode they equal the dataset's.
    let es = &ep["schema"];
    assert_eq!(es["stats/observation.state/mean"], "list<item: double>");
    assert_eq!(es["stats/observation.state/count"], "list<item: int64>");
    assert_eq!(
        es["stats/observation.images.left_front/mean"],
        "list<item: list<item: list<item: double>>>"
    );
    for key in [
        "observation.state",
        "action",
        "timestamp",
        "kiwi.support",
        "observation.images.left_front",
        "observation.images.right_front",
    ] {
        for stat in ["min", "max", "mean", "std", "count"] {
            let column = &ec[format!("stats/{key}/{stat}")];
            assert_eq!(
                &column[0], &stats[key][stat],
                "stats/{key}/{stat} of the episode equals the dataset's"
            );
        }
    }
}

#[test]
fn bad_requests_get_clear_errors() {
    let dir = tempfile::tempdir().unwrap();
    let session = make_session(dir.path());
    let run = |options: ExportOptions, name: &str| {
        let out = dir.path().join(name);
        let err = export(&session, ExportFormat::LeRobot, &options, &out)
            .unwrap_err()
            .to_string();
        assert!(!out.exists(), "a failed export leaves no folder");
        err
    };
    let err = run(
        ExportOptions {
            fps: Some(60.0),
            ..Default::default()
        },
        "fast",
    );
    assert!(
        // The right camera runs 40 ppm slow on the session timeline: 29.969 Hz there, for its
        // trajectory and its front view alike (the error names the first of the two).
        err.contains("cannot supply")
            && (err.contains("right trajectory") || err.contains("right.front"))
            && err.contains("29.969"),
        "{err}"
    );
    let err = run(
        ExportOptions {
            views: Some(vec!["left.rear".into()]),
            ..Default::default()
        },
        "view",
    );
    assert!(
        err.contains("unknown view `left.rear`") && err.contains("left.front"),
        "{err}"
    );
    let err = run(
        ExportOptions {
            episodes: Some(vec!["nope".into()]),
            ..Default::default()
        },
        "ep",
    );
    assert!(err.contains("no episode `nope`"), "{err}");
    let err = run(
        ExportOptions {
            episodes: Some(vec!["ep1".into()]),
            ..Default::default()
        },
        "unusable",
    );
    assert!(err.contains("ep1: verdict unusable: test reason"), "{err}");
    // An existing, non-empty output folder is never overwritten.
    let busy = dir.path().join("busy");
    std::fs::create_dir_all(&busy).unwrap();
    std::fs::write(busy.join("x"), "keep").unwrap();
    let err = export(
        &session,
        ExportFormat::Sidecar,
        &ExportOptions::default(),
        &busy,
    )
    .unwrap_err()
    .to_string();
    assert!(err.contains("not empty"), "{err}");
    assert_eq!(std::fs::read_to_string(busy.join("x")).unwrap(), "keep");
}

#[test]
fn umi_export_reads_back_with_zarr() {
    let dir = tempfile::tempdir().unwrap();
    let session = make_session(dir.path());
    let out = dir.path().join("umi");
    let report = export(&session, ExportFormat::Umi, &ExportOptions::default(), &out).unwrap();
    let fps = RATE;
    assert!(
        (report.fps.unwrap() - fps).abs() < 1e-9,
        "default rate is the cameras' own"
    );
    let (t0, rows) = expected_grid(fps);
    assert_eq!(report.frames, rows);
    let store = out.join("dataset.zarr.zip");
    let Some(read) = python_reader("read_zarr.py", &[&store]) else {
        return;
    };
    let arrays = &read["arrays"];
    let mut shapes = BTreeMap::new();
    for (k, v) in arrays.as_object().unwrap() {
        shapes.insert(
            k.clone(),
            (v["dtype"].as_str().unwrap().to_string(), v["shape"].clone()),
        );
    }
    for i in 0..2 {
        for (name, width) in [
            ("eef_pos", 3),
            ("eef_rot_axis_angle", 3),
            ("gripper_width", 1),
            ("demo_start_pose", 6),
            ("demo_end_pose", 6),
        ] {
            let key = format!("data/robot{i}_{name}");
            assert_eq!(
                shapes[&key],
                ("float32".to_string(), serde_json::json!([rows, width])),
                "{key}"
            );
        }
        let key = format!("data/camera{i}_rgb");
        assert_eq!(
            shapes[&key],
            ("uint8".to_string(), serde_json::json!([rows, H, W, 3])),
            "{key}"
        );
    }
    assert_eq!(arrays["meta/episode_ends"]["dtype"], "int64");
    assert_eq!(
        arrays["meta/episode_ends"]["values"],
        serde_json::json!([rows])
    );
    assert_eq!(arrays["data/robot1_gripper_width"]["attrs"]["unit"], "m");
    for c in 0..2 {
        let pos: Vec<Vec<f64>> = arrays[format!("data/robot{c}_eef_pos")]["values"]
            .as_array()
            .unwrap()
            .iter()
            .map(f64s)
            .collect();
        let rot: Vec<Vec<f64>> = arrays[format!("data/robot{c}_eef_rot_axis_angle")]["values"]
            .as_array()
            .unwrap()
            .iter()
            .map(f64s)
            .collect();
        let start: Vec<Vec<f64>> = arrays[format!("data/robot{c}_demo_start_pose")]["values"]
            .as_array()
            .unwrap()
            .iter()
            .map(f64s)
            .collect();
        let means = f64s(&arrays[format!("data/camera{c}_rgb")]["frame_means"]);
        for k in 0..rows {
            let t = t0 + k as f64 / fps;
            let truth = truth_tip(c, t);
            let dp =
                (Vector3::new(pos[k][0], pos[k][1], pos[k][2]) - truth.translation.vector).norm();
            assert!(dp < RESAMPLE_TOL, "row {k} robot{c}: position off by {dp}");
            let r = so3_exp(&Vector3::new(rot[k][0], rot[k][1], rot[k][2]));
            let dr = so3_log(&(r.inverse() * truth.rotation)).norm();
            assert!(dr < RESAMPLE_TOL, "row {k} robot{c}: rotation off by {dr}");
            assert_eq!(
                start[k][..3],
                pos[0][..],
                "demo_start_pose repeats the first pose"
            );
            // Lossless: the stored frame is the nearest source frame exactly.
            let want = f64::from(grey(c, nearest_frame(c, t)));
            assert!(
                (means[k] - want).abs() < 1e-9,
                "camera{c} row {k}: {} vs {want}",
                means[k]
            );
        }
    }
}

#[test]
fn sidecar_carries_every_output_and_clock() {
    let dir = tempfile::tempdir().unwrap();
    let session = make_session(dir.path());
    let out = dir.path().join("sidecar");
    let report = export(
        &session,
        ExportFormat::Sidecar,
        &ExportOptions::default(),
        &out,
    )
    .unwrap();
    assert_eq!(report.exported, vec!["ep0".to_string()]);
    let index: Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("sidecar.json")).unwrap()).unwrap();
    let files: Vec<&str> = index["files"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| f["path"].as_str().unwrap())
        .collect();
    for f in [
        "session.toml",
        "calibration/left/calibration.json",
        "calibration/right/calibration.json",
        "episodes/ep0/out/left.csv",
        "episodes/ep0/out/right.csv",
        "episodes/ep0/out/quality.json",
        "episodes/ep0/work/sync/sync.json",
        "episodes/ep0/left/meta.json",
        "episodes/ep0/right/front/frames.csv",
        "episodes/ep0/right/front/timestamps.csv",
    ] {
        assert!(files.contains(&f), "{f} missing from {files:?}");
        assert!(out.join(f).is_file(), "{f}");
    }
    assert!(
        !files.iter().any(|f| f.contains("ep1")),
        "the unusable episode is left out"
    );
    // Copies are byte-identical.
    let a = std::fs::read(dir.path().join("episodes/ep0/out/left.csv")).unwrap();
    assert_eq!(
        std::fs::read(out.join("episodes/ep0/out/left.csv")).unwrap(),
        a
    );
    let text =
        std::fs::read_to_string(out.join("episodes/ep0/right/front/timestamps.csv")).unwrap();
    let mut lines = text.lines();
    assert_eq!(lines.next(), Some("frame,t_camera,t_session"));
    for (i, line) in lines.enumerate() {
        let v: Vec<f64> = line.split(',').map(|x| x.parse().unwrap()).collect();
        assert_eq!(v[0] as usize, i);
        assert!((v[1] - camera_time(1, i)).abs() < 1e-9);
        assert!((v[2] - session_time(1, camera_time(1, i))).abs() < 1e-9);
    }
}
