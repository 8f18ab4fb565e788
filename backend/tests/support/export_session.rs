//! A synthetic session for the export tests and benchmark: two wrists with known analytic
//! tool-tip trajectories and gripper openings, front-lens frames whose grey level names the
//! frame, a right camera 37 ms late with 40 ppm drift, a usable episode `ep0` and an unusable
//! one `ep1`. Only `out/`, `quality.json`, `meta.json`, the frames and `sync.json` exist: what
//! the exporters read. [`add_scene_inputs`] adds what the scene exports read besides: the units'
//! calibrations (left KB4, right Double Sphere) and the session's maps with their metric and
//! placement files, the rear map's keyframes observing its landmarks at exported frames.

#![allow(dead_code, clippy::unwrap_used, clippy::expect_used, missing_docs)]

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::process::Command;

use serde_json::Value;

use nalgebra::{Translation3, Vector3};

use kiwi_backend::outputs::{TRAJECTORY_HEADER, failed_record};

/// The floor lies this far below the scene origin in the written outputs (m).
const FLOOR_DEPTH_M: f64 = 1.0;
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
    /// Whether each camera also has a rear lens (same frame times, as an X5's two lenses).
    pub rear_lens: bool,
}

/// Front-lens rate of the synthetic cameras (Hz).
pub const RATE: f64 = 30000.0 / 1001.0;
/// The cameras' recording mode in `meta.json` (the calibration's 29.97 Hz mode by its rate).
pub const MODE: &str = "30fps";
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
        let lenses: Vec<String> = if spec.rear_lens {
            vec!["front".into(), "rear".into()]
        } else {
            vec!["front".into()]
        };
        let meta = CameraMeta {
            camera: camera.to_string(),
            unit_id: format!("X5-{camera}"),
            camera_model: "Insta360 X5".into(),
            mode: MODE.into(),
            fps: RATE,
            lenses: lenses.clone(),
            audio_rate_hz: 48000,
            source: "test".into(),
            recording: None,
        };
        kiwi_core::layout::EpisodeLayout::new(&ep)
            .write_meta(&meta)
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
                "{ts},{t_cam},{pose},{pose},1.000e-3,2.000e-3,1.500e-3,2.500e-3,{support},front,{opening},{unit},0.900,{:.6},{:.6}",
                p.z + FLOOR_DEPTH_M,
                p.z + FLOOR_DEPTH_M
            )
            .unwrap();
        }
        write_frames_csv(&lens.join("frames.csv"), &frames).unwrap();
        if spec.rear_lens {
            let rear = cam_dir.join("rear");
            std::fs::create_dir_all(rear.join("frames")).unwrap();
            for (i, f) in frames.iter().enumerate() {
                image::GrayImage::from_pixel(
                    spec.width,
                    spec.height,
                    image::Luma([grey(c, i).wrapping_add(1)]),
                )
                .save(rear.join(&f.file))
                .unwrap();
            }
            write_frames_csv(&rear.join("frames.csv"), &frames).unwrap();
        }
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

/// Rear-map landmarks seen from each of its keyframes.
pub const LANDMARKS_PER_KEYFRAME: usize = 24;
/// Detection noise on the keyframes' feature pixels (px, deterministic).
pub const FEATURE_NOISE_PX: f64 = 0.3;
/// Rear lens time shift after the front lens's (s): inside one rig exposure.
pub const REAR_SHIFT_S: f64 = 1e-4;

/// `world_from_map` of the rear map's metric recovery (the scene frame from the raw map).
pub fn rear_metric() -> kiwi_backend::vision::align::Sim3 {
    kiwi_backend::vision::align::Sim3 {
        scale: 2.0,
        rotation: so3_exp(&Vector3::new(0.1, 0.2, -0.3)),
        translation: Vector3::new(0.5, -0.2, 0.1),
    }
}

fn sim_json(s: &kiwi_backend::vision::align::Sim3) -> Value {
    let q = s.rotation.coords;
    serde_json::json!({
        "scale": s.scale,
        "rotation_xyzw": [q.x, q.y, q.z, q.w],
        "translation_m": [s.translation.x, s.translation.y, s.translation.z],
    })
}

fn write_metric(root: &Path, map: &str, sim: &kiwi_backend::vision::align::Sim3) {
    let dir = root.join("work").join(format!("metric-{map}"));
    std::fs::create_dir_all(&dir).unwrap();
    let json = serde_json::json!({
        "schema_version": 1, "lens": map, "world_from_map": sim_json(sim),
        "scale_m_per_map_unit": sim.scale, "gravity_in_map": [0.0, 0.0, -1.0],
        "accel_bias_m_s2": [0.0, 0.0, 0.0], "accel_bias_sigma_m_s2": [0.0, 0.0, 0.0],
        "gyro_bias_rad_s": [0.0, 0.0, 0.0],
        "conditioning": {"excitation_rms_m_s2": 1.0, "scale_sigma": 0.01,
                         "gravity_sigma_deg": 0.1, "variance_factor": 1.0},
        "frames_used": 100, "frames_lost": 0, "outliers_downweighted": 0,
        "rms_position_m": 0.001, "rms_rotation_deg": 0.1, "iterations": 5,
    });
    std::fs::write(dir.join("metric.json"), json.to_string()).unwrap();
}

/// The units' calibrations: `X5-L` with KB4 lenses, `X5-R` with Double Sphere lenses, each lens
/// `size` px square; the rear lens's time shift [`REAR_SHIFT_S`] after the front's.
pub fn scene_calibrations(size: u32) -> [kiwi_core::artifact::UnitCalibration; 2] {
    use kiwi_fixtures::unit::{LensModel, SimUnit};
    [("L", 11, LensModel::Kb4), ("R", 12, LensModel::Ds)].map(|(u, seed, model)| {
        let unit = SimUnit::x5(&format!("X5-{u}"), seed, size, model).unwrap();
        let mut cal = unit.true_calibration("2026-01-01");
        let front_shift = cal.lens("front").unwrap().time_shift_s.unwrap();
        for l in &mut cal.lenses {
            if l.name == "rear" {
                l.time_shift_s = Some(front_shift + REAR_SHIFT_S);
            }
        }
        cal
    })
}

/// `front_from_rear` of a unit's calibration.
pub fn front_from_rear(cal: &kiwi_core::artifact::UnitCalibration) -> Pose {
    let f = cal.lens("front").unwrap().cam_from_imu().unwrap();
    let r = cal.lens("rear").unwrap().cam_from_imu().unwrap();
    f * r.inverse()
}

/// Add the scene exports' inputs to a session made by [`make_session`] with `rear_lens`: the
/// calibrations of [`scene_calibrations`], and the maps. The rear map (built from the left
/// rear lens of `ep0`) has a keyframe at the left camera's frame nearest each row of the
/// `rate` grid, observing [`LANDMARKS_PER_KEYFRAME`] landmarks of its own with
/// [`FEATURE_NOISE_PX`] of noise; the front maps have landmarks and no observations.
pub fn add_scene_inputs(spec: &Synthetic, root: &Path, rate: f64) {
    use kiwi_backend::vision::features::Descriptor;
    use kiwi_backend::vision::map::{MapFeature, MapKeyframe, MapLandmark, MapPose, VisualMap};
    use kiwi_core::camera::{CameraModel, bearing_from_angles};
    assert!(spec.rear_lens && spec.width == spec.height);
    let cals = scene_calibrations(spec.width);
    for (u, cal) in ["L", "R"].iter().zip(&cals) {
        let set = root.join(format!("units/X5-{u}/2026-01-01"));
        std::fs::write(set.join("calibration.json"), cal.to_json().unwrap()).unwrap();
    }
    let descriptor = |k: u64| Descriptor([k.wrapping_mul(0x9E37_79B9_7F4A_7C15), k, !k, k << 7]);
    // Rear map of the left unit.
    let left = &cals[0];
    let rear_cam = left.lens("rear").unwrap().camera().unwrap();
    let front_from_rear = front_from_rear(left);
    let metric = rear_metric();
    let mut map = VisualMap::new("left", "rear", "ep0", &rear_cam);
    let (t0, rows) = expected_grid(spec, rate);
    let centre_delay =
        kiwi_backend::formats::calibration::exposure_centre_delay(left, MODE, RATE).unwrap();
    for k in 0..rows {
        let frame = nearest_frame(spec, 0, t0 + k as f64 / rate);
        let t_cam = camera_time(0, frame);
        // Seen as the export poses the image: at its centre row's exposure.
        let t = session_time(0, t_cam) + centre_delay;
        let scene_from_rear = truth_tip(0, t) * front_from_rear;
        let mut features = Vec::new();
        for j in 0..LANDMARKS_PER_KEYFRAME {
            let theta = 0.2 + 1.2 * (j as f64 / LANDMARKS_PER_KEYFRAME as f64);
            let phi = 2.4 * j as f64;
            let bearing = bearing_from_angles(theta, phi);
            let depth = 1.0 + 0.1 * j as f64;
            let p_scene = scene_from_rear * nalgebra::Point3::from(bearing.into_inner() * depth);
            let p_map =
                metric.rotation.inverse() * ((p_scene.coords - metric.translation) / metric.scale);
            let id = map.landmarks.len() as u32;
            map.landmarks.push(MapLandmark {
                position: p_map.into(),
                descriptor: descriptor(u64::from(id)),
            });
            let px = rear_cam.project(&bearing).unwrap();
            let noise = FEATURE_NOISE_PX * ((j + k) as f64 * 1.7).sin();
            features.push(MapFeature {
                pixel: [px.x + noise, px.y - noise],
                bearing: bearing.into_inner().into(),
                descriptor: descriptor(u64::from(id)),
                landmark: Some(id),
                octave: None,
                patch: None,
            });
        }
        // `cam_from_map` in map units: the scene pose moved into the map frame.
        let map_from_rear = Pose::from_parts(
            Translation3::from(
                metric.rotation.inverse()
                    * ((scene_from_rear.translation.vector - metric.translation) / metric.scale),
            ),
            metric.rotation.inverse() * scene_from_rear.rotation,
        );
        map.keyframes.push(MapKeyframe {
            frame: frame as u32,
            t: t_cam,
            cam_from_map: MapPose::from_pose(&map_from_rear.inverse()),
            features,
        });
    }
    map.train_vocabulary();
    let dir = root.join("work/map-rear");
    std::fs::create_dir_all(&dir).unwrap();
    map.save(&dir.join("map.kmap")).unwrap();
    write_metric(root, "rear", &metric);
    // Front maps: landmarks only, and one keyframe that is no exported frame.
    for (s, side) in ["left", "right"].iter().enumerate() {
        let cam = cals[s].lens("front").unwrap().camera().unwrap();
        let mut map = VisualMap::new(side, "front", "ep0", &cam);
        let mut features = Vec::new();
        for j in 0..5u32 {
            map.landmarks.push(MapLandmark {
                position: [0.1 * f64::from(j), 0.2, 1.0],
                descriptor: descriptor(1000 + u64::from(j)),
            });
            features.push(MapFeature {
                pixel: [10.0, 10.0],
                bearing: [0.0, 0.0, 1.0],
                descriptor: descriptor(1000 + u64::from(j)),
                landmark: Some(j),
                octave: None,
                patch: None,
            });
        }
        map.keyframes.push(MapKeyframe {
            frame: 1_000_000,
            t: 0.0,
            cam_from_map: MapPose::from_pose(&Pose::identity()),
            features,
        });
        map.train_vocabulary();
        let dir = root.join(format!("work/map-front-{side}"));
        std::fs::create_dir_all(&dir).unwrap();
        map.save(&dir.join("map.kmap")).unwrap();
        let sim = kiwi_backend::vision::align::Sim3 {
            scale: 1.5,
            rotation: so3_exp(&Vector3::new(0.0, 0.0, 0.3 * s as f64)),
            translation: Vector3::new(0.0, 0.1, 0.0),
        };
        write_metric(root, &format!("front-{side}"), &sim);
        let g = kiwi_backend::vision::align::Sim3 {
            scale: 1.0,
            rotation: so3_exp(&Vector3::new(0.05, 0.0, 0.0)),
            translation: Vector3::new(0.2, 0.0, 0.0),
        };
        let dir = root.join(format!("work/placement-{side}"));
        std::fs::create_dir_all(&dir).unwrap();
        let json = serde_json::json!({
            "schema_version": 1, "scene_from_front_map": sim_json(&g), "pairs": 10,
            "inliers": 10, "rms_position_m": 0.001, "rms_rotation_deg": 0.1,
        });
        std::fs::write(dir.join("placement.json"), json.to_string()).unwrap();
    }
}

/// Run a Python reader; `None` (and a loud message) when its module is not installed.
pub fn python_reader(script: &str, args: &[&Path]) -> Option<Value> {
    let script = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/python")
        .join(script);
    let out = Command::new("python3").arg(&script).args(args).output();
    let out = match out {
        Ok(o) => o,
        Err(e) => {
            eprintln!("SKIPPED: python3 not available ({e}); run `make deps`");
            return None;
        }
    };
    if out.status.code() == Some(3) {
        eprintln!(
            "SKIPPED independent read-back with {}: {} — run `make deps`",
            script.display(),
            String::from_utf8_lossy(&out.stderr).trim()
        );
        return None;
    }
    assert!(
        out.status.success(),
        "{} failed: {}",
        script.display(),
        String::from_utf8_lossy(&out.stderr)
    );
    Some(serde_json::from_slice(&out.stdout).unwrap())
}

/// A JSON array of numbers.
pub fn f64s(v: &Value) -> Vec<f64> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_f64().unwrap())
        .collect()
}

/// The head camera's clock: first frame on its own clock, offset, drift (ppm).
pub const HEAD_CLOCK: (f64, f64, f64) = (0.017, 0.0213, -15.0);
/// Head camera frames: the GO 3's 29.97 Hz mode.
pub const HEAD_MODE: &str = "go3-30fps";
/// Samples of the head's track (30 Hz on the session timeline) that are a gap.
pub const HEAD_GAP: std::ops::Range<usize> = 60..75;

/// The head camera's true pose at session time `t`.
pub fn truth_head(t: f64) -> Pose {
    let p = Vector3::new(0.05 * t, 1.4 + 0.02 * (1.5 * t).sin(), 0.3);
    let r = so3_exp(&Vector3::new(0.1 * t, 0.5 + 0.05 * t, -0.02));
    Pose::from_parts(Translation3::from(p), r)
}

/// The head camera's session time of its frame `i`.
pub fn head_session_time(i: usize) -> f64 {
    let (first, offset, drift) = HEAD_CLOCK;
    (first + i as f64 / RATE) * (1.0 + drift * 1e-6) + offset
}

/// Add a head camera (a simulated GO 3, `size` px) to a session made by [`make_session`]:
/// `[head]` in `session.toml`, its calibration, in every episode its frames, `meta.json` and
/// clock, and in `ep0` the outputs' `head.csv` (the head camera's truth on a 30 Hz grid, with
/// the samples of [`HEAD_GAP`] a gap). Returns the head camera's calibration.
pub fn add_head_camera(spec: &Synthetic, root: &Path) -> kiwi_core::artifact::UnitCalibration {
    use kiwi_backend::head::episode::{HEAD_HEADER, HeadTrack};
    use kiwi_backend::head::track::HeadSample;
    let unit = kiwi_fixtures::unit::SimUnit::go3("GO3-H", 13, spec.width).unwrap();
    let cal = unit.true_calibration("2026-01-01");
    let set = root.join("units/GO3-H/2026-01-01");
    std::fs::create_dir_all(&set).unwrap();
    std::fs::write(set.join("calibration.json"), cal.to_json().unwrap()).unwrap();
    let toml = root.join("session.toml");
    let text = std::fs::read_to_string(&toml).unwrap().replacen(
        "\n[[episodes]]",
        "\n[head]\nunit = \"GO3-H\"\ncalibration = \"units/GO3-H/2026-01-01\"\nmarker_id = 3\n\
         marker_size_m = 0.08\n\n[[episodes]]",
        1,
    );
    std::fs::write(&toml, text).unwrap();
    let mount = kiwi_core::head::HeadMount::builtin()
        .unwrap()
        .marker_from_cam();
    // The GO 3's frames are 4:3.
    let (width, height) = {
        use kiwi_core::camera::CameraModel;
        cal.lens("main").unwrap().camera().unwrap().resolution()
    };
    for name in ["ep0", "ep1"] {
        let ep = root.join("episodes").join(name);
        let cam_dir = ep.join("head");
        let lens = cam_dir.join("main");
        std::fs::create_dir_all(lens.join("frames")).unwrap();
        let meta = CameraMeta {
            camera: "head".into(),
            unit_id: "GO3-H".into(),
            camera_model: "Insta360 GO 3".into(),
            mode: HEAD_MODE.into(),
            fps: RATE,
            lenses: vec!["main".into()],
            audio_rate_hz: 48000,
            source: "test".into(),
            recording: None,
        };
        kiwi_core::layout::EpisodeLayout::new(&ep)
            .write_meta(&meta)
            .unwrap();
        let mut frames = Vec::new();
        for i in 0..spec.frames {
            let file = format!("frames/{i:06}.png");
            image::GrayImage::from_pixel(width, height, image::Luma([grey(1, i) / 2]))
                .save(lens.join(&file))
                .unwrap();
            frames.push(FrameRecord {
                t: HEAD_CLOCK.0 + i as f64 / RATE,
                file,
            });
        }
        write_frames_csv(&lens.join("frames.csv"), &frames).unwrap();
        // The head camera's clock beside the wrists'.
        let clock = CameraClock {
            name: "head".into(),
            offset_s: Some(HEAD_CLOCK.1),
            drift_ppm: HEAD_CLOCK.2,
            offset_std_s: 1e-5,
            status: CameraStatus::OffsetAndDrift,
        };
        let quality = ep.join("out/quality.json");
        let mut record: kiwi_backend::outputs::QualityRecord =
            serde_json::from_str(&std::fs::read_to_string(&quality).unwrap()).unwrap();
        if let Some(sync) = record.sync.as_mut() {
            sync.cameras.push(clock);
            std::fs::write(
                ep.join("work/sync/sync.json"),
                serde_json::to_string_pretty(sync).unwrap(),
            )
            .unwrap();
        }
        if name == "ep0" {
            let samples: Vec<HeadSample> = (0..(spec.frames as f64 / RATE * 30.0) as usize)
                .map(|k| {
                    let t = k as f64 / 30.0;
                    HeadSample {
                        t_session: t,
                        scene_from_marker: (!HEAD_GAP.contains(&k))
                            .then(|| truth_head(t) * mount.inverse()),
                        observations: 6,
                        from_left: 3,
                        from_right: 3,
                        outliers: 0,
                        sigma_p_m: 0.002,
                        sigma_r_rad: 0.005,
                    }
                })
                .collect();
            let (csv, tum) = kiwi_backend::head::episode::track_files(&HeadTrack {
                samples,
                marker_from_cam: mount,
            });
            assert!(csv.starts_with(HEAD_HEADER));
            std::fs::write(ep.join("out/head.csv"), csv).unwrap();
            std::fs::write(ep.join("out/head.tum"), tum).unwrap();
        }
        std::fs::write(&quality, serde_json::to_string_pretty(&record).unwrap()).unwrap();
    }
    cal
}
