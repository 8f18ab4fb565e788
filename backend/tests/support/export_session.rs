//! A synthetic session for the export tests and benchmark: two wrists with known analytic
//! tool-tip trajectories and gripper openings, front-lens frames whose grey level names the
//! frame, a right camera 37 ms late with 40 ppm drift, a usable episode `ep0` and an unusable
//! one `ep1`. Only `out/`, `quality.json`, `meta.json`, the frames and `sync.json` exist: what
//! the exporters read.

#![allow(dead_code, clippy::unwrap_used, clippy::expect_used, missing_docs)]

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use nalgebra::{Translation3, Vector3};

use kiwi_backend::outputs::{TRAJECTORY_HEADER, failed_record};
use kiwi_backend::quality::Verdict;
use kiwi_backend::sync::{CameraClock, CameraStatus, SyncResult};
use kiwi_core::geometry::{Pose, so3_exp};
use kiwi_core::layout::{CameraMeta, FrameRecord, write_frames_csv};

/// Size of a synthetic session.
#[derive(Debug, Clone, Copy)]
pub struct Synthetic {
    /// Front-lens frames per camera.
    pub frames: usize,
    /// Image width (px, even as yuv420p needs).
    pub width: u32,
    /// Image height (px, even).
    pub height: u32,
}

/// Front-lens rate of the synthetic cameras (Hz).
pub const RATE: f64 = 30000.0 / 1001.0;
/// Camera clocks: (name, first frame time on the camera clock, offset, drift ppm).
pub const CAMERAS: [(&str, f64, f64, f64); 2] =
    [("left", 0.005, 0.0, 0.0), ("right", 0.011, 0.0371, 40.0)];
/// Left frames with no visual support.
pub const IMU_ONLY: std::ops::Range<usize> = 10..13;
/// The right frame whose opening was not measured.
pub const UNMEASURED: usize = 20;
/// Linear interpolation of the truth between frames 33 ms apart is this close (m, rad).
pub const RESAMPLE_TOL: f64 = 1e-4;
/// LeRobot's timestamp tolerance (s).
pub const LEROBOT_TOL_S: f64 = 1e-4;

pub fn truth_tip(side: usize, t: f64) -> Pose {
    let s = side as f64;
    let p = Vector3::new(0.1 * t + 0.2 * s, 0.05 * (2.0 * t).sin(), 0.8 + 0.01 * t);
    let r = so3_exp(&Vector3::new(0.2 * t, -0.1 * t + 0.3 * s, 0.05));
    Pose::from_parts(Translation3::from(p), r)
}

pub fn truth_opening(side: usize, t: f64) -> f64 {
    if side == 0 {
        0.1 + 0.05 * t
    } else {
        0.02 + 0.01 * t
    }
}

pub fn session_time(camera: usize, t_cam: f64) -> f64 {
    let (_, _, offset, drift) = CAMERAS[camera];
    t_cam * (1.0 + drift * 1e-6) + offset
}

pub fn camera_time(camera: usize, i: usize) -> f64 {
    CAMERAS[camera].1 + i as f64 / RATE
}

/// Grey level of a camera's frame `i` (so a decoded video frame names its source frame).
pub fn grey(camera: usize, i: usize) -> u8 {
    (20 + 3 * i + 5 * camera) as u8
}

fn write_episode(spec: &Synthetic, root: &Path, name: &str, verdict: Verdict) {
    let ep = root.join("episodes").join(name);
    let out = ep.join("out");
    std::fs::create_dir_all(&out).unwrap();
    for (c, (camera, ..)) in CAMERAS.iter().enumerate() {
        let cam_dir = ep.join(camera);
        let lens = cam_dir.join("front");
        std::fs::create_dir_all(lens.join("frames")).unwrap();
        let meta = CameraMeta {
            camera: camera.to_string(),
            unit_id: format!("X5-{camera}"),
            camera_model: "Insta360 X5".into(),
            mode: "30fps".into(),
            fps: RATE,
            lenses: vec!["front".into()],
            audio_rate_hz: 48000,
            source: "test".into(),
            recording: None,
        };
        std::fs::write(
            cam_dir.join("meta.json"),
            serde_json::to_string_pretty(&meta).unwrap(),
        )
        .unwrap();
        let mut frames = Vec::new();
        let mut csv = format!("{TRAJECTORY_HEADER}\n");
        for i in 0..spec.frames {
            let file = format!("frames/{i:06}.png");
            image::GrayImage::from_pixel(spec.width, spec.height, image::Luma([grey(c, i)]))
                .save(lens.join(&file))
                .unwrap();
            let t_cam = camera_time(c, i);
            frames.push(FrameRecord { t: t_cam, file });
            let ts = session_time(c, t_cam);
            let tip = truth_tip(c, ts);
            let p = tip.translation.vector;
            let q = tip.rotation.coords;
            let support = if c == 0 && IMU_ONLY.contains(&i) {
                "imu-only"
            } else {
                "front"
            };
            let (unit, opening) = if c == 0 {
                ("rad", truth_opening(c, ts))
            } else {
                ("m", truth_opening(c, ts))
            };
            let opening = if c == 1 && i == UNMEASURED {
                String::new()
            } else {
                format!("{opening:.6}")
            };
            let pose = format!(
                "{:.6},{:.6},{:.6},{:.9},{:.9},{:.9},{:.9}",
                p.x, p.y, p.z, q.x, q.y, q.z, q.w
            );
            writeln!(
                csv,
                "{ts:.6},{t_cam:.6},{pose},{pose},1.000e-3,2.000e-3,1.500e-3,2.500e-3,{support},front,{opening},{unit},0.900"
            )
            .unwrap();
        }
        write_frames_csv(&lens.join("frames.csv"), &frames).unwrap();
        std::fs::write(out.join(format!("{camera}.csv")), csv).unwrap();
    }
    let mut record = failed_record(name, "ep0", vec!["test reason".into()]);
    record.verdict = verdict;
    if verdict != Verdict::Unusable {
        record.reasons.clear();
    }
    record.sync = Some(SyncResult {
        cameras: CAMERAS
            .iter()
            .enumerate()
            .map(|(i, (name, _, offset, drift))| CameraClock {
                name: name.to_string(),
                offset_s: Some(*offset),
                drift_ppm: *drift,
                offset_std_s: 1e-5,
                status: if i == 0 {
                    CameraStatus::Reference
                } else {
                    CameraStatus::OffsetAndDrift
                },
            })
            .collect(),
        pairs: Vec::new(),
        closures: Vec::new(),
    });
    std::fs::write(
        out.join("quality.json"),
        serde_json::to_string_pretty(&record).unwrap(),
    )
    .unwrap();
    let sync = ep.join("work/sync");
    std::fs::create_dir_all(&sync).unwrap();
    std::fs::write(
        sync.join("sync.json"),
        serde_json::to_string_pretty(record.sync.as_ref().unwrap()).unwrap(),
    )
    .unwrap();
}

/// A session with a usable episode `ep0` and an unusable one `ep1`.
pub fn make_session(spec: &Synthetic, root: &Path) -> PathBuf {
    for unit in ["L", "R"] {
        let set = root.join(format!("units/X5-{unit}/2026-01-01"));
        std::fs::create_dir_all(&set).unwrap();
        std::fs::write(
            set.join("calibration.json"),
            format!("{{\"unit\": \"X5-{unit}\"}}\n"),
        )
        .unwrap();
    }
    let toml = r#"schema_version = 1
name = "export-test"
map_episode = "ep0"

[wrists.left]
unit = "X5-L"
calibration = "units/X5-L/2026-01-01"
tool = "chopstick"

[wrists.right]
unit = "X5-R"
calibration = "units/X5-R/2026-01-01"
tool = "parallel_jaw"

[[episodes]]
name = "ep0"
description = "pick up the cup"

[[episodes]]
name = "ep1"
description = "covered lenses"
"#;
    let path = root.join("session.toml");
    std::fs::write(&path, toml).unwrap();
    write_episode(spec, root, "ep0", Verdict::Usable);
    write_episode(spec, root, "ep1", Verdict::Unusable);
    path
}

/// The expected grid: first row, rows.
pub fn expected_grid(spec: &Synthetic, fps: f64) -> (f64, usize) {
    let starts = (0..2).map(|c| session_time(c, camera_time(c, 0)));
    let ends = (0..2).map(|c| session_time(c, camera_time(c, spec.frames - 1)));
    let t0 = starts.fold(f64::NEG_INFINITY, f64::max);
    let t1 = ends.fold(f64::INFINITY, f64::min);
    (t0, ((t1 - t0) * fps + 1e-9).floor() as usize + 1)
}

/// The frame of a camera captured nearest session time `t`.
pub fn nearest_frame(spec: &Synthetic, camera: usize, t: f64) -> usize {
    (0..spec.frames)
        .min_by(|&a, &b| {
            let da = (session_time(camera, camera_time(camera, a)) - t).abs();
            let db = (session_time(camera, camera_time(camera, b)) - t).abs();
            da.total_cmp(&db)
        })
        .unwrap()
}
