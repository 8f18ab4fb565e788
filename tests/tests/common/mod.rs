//! Shared pieces of the end-to-end tests: a certified, simulated session built once per
//! machine (test processes share it through a lock file) and readers of the simulator's truth
//! and of the pipeline's outputs.

#![allow(dead_code)]

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use kiwi_calib::certify::policy::Policy;
use kiwi_calib::certify::{CertifyOptions, certify};
use kiwi_core::geometry::Pose;
use kiwi_core::tool::ToolDefinition;
use kiwi_fixtures::captures::{UnitCaptureOptions, write_unit_captures};
use kiwi_fixtures::scenario::Scenario;
use kiwi_fixtures::session::{CertifiedUnits, Cover, SessionOptions, write_session};
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion, Vector3};

/// Seed of the shared session and its units.
pub const SEED: u64 = 11;
/// Image size of the shared session (px).
pub const RESOLUTION: u32 = 480;
/// Unit ids of the two wrists.
pub const UNITS: [&str; 2] = ["X5-E2E-L", "X5-E2E-R"];

/// The episodes of the shared session: a survey that builds the maps, a tabletop and a walk
/// episode, and a tabletop episode with blind stretches.
pub const SCENARIOS: [Scenario; 4] = [
    Scenario::Survey,
    Scenario::Tabletop,
    Scenario::Walk,
    Scenario::Tabletop,
];
/// Their durations (s).
pub const DURATIONS: [f64; 4] = [20.0, 6.0, 8.0, 6.0];
/// Blind stretch of `ep003` (s into the episode): the left front lens is covered (the rear
/// keeps tracking) and both lenses of the right wrist are covered.
pub const BLIND: (f64, f64) = (2.5, 1.5);

/// What a simulated, certified session is made of.
#[derive(Debug, Clone)]
pub struct SessionSpec {
    /// Seed of the units and the session.
    pub seed: u64,
    /// Per-lens image size (px).
    pub resolution: u32,
    /// Wrist frame rate (Hz).
    pub rate_hz: f64,
    /// Episode motions, the first builds the maps.
    pub scenarios: Vec<Scenario>,
    /// Episode durations (s).
    pub durations: Vec<f64>,
    /// Lenses covered for a while.
    pub covers: Vec<Cover>,
}

impl SessionSpec {
    /// The shared end-to-end session of the tests.
    pub fn shared() -> Self {
        SessionSpec {
            seed: SEED,
            resolution: RESOLUTION,
            rate_hz: 29.97,
            scenarios: SCENARIOS.to_vec(),
            durations: DURATIONS.to_vec(),
            covers: ["left:front", "right:front", "right:rear"]
                .iter()
                .map(|cl| Cover::parse(&format!("3:{cl}:{}:{}", BLIND.0, BLIND.1)).expect("cover"))
                .collect(),
        }
    }
}

/// Certify one simulated unit at the session's resolution (captures as `make demo` makes them).
fn certified_unit(dir: &Path, unit_id: &str, units: &Path, spec: &SessionSpec) {
    let captures = dir.join("captures").join(unit_id);
    let mut o = UnitCaptureOptions::new(&captures, unit_id);
    o.seed = spec.seed;
    o.resolution = spec.resolution;
    o.views = 24;
    o.cam_imu_duration_s = 4.0;
    o.static_duration_s = 4.0 * 3600.0;
    o.static_rate_hz = Some(20.0);
    o.bench_duration_s = 0.0;
    o.rig_duration_s = 20.0;
    o.rig_repeats = 2;
    o.rig_modes = vec!["30fps".into()];
    o.noise_sigma = 1.0;
    write_unit_captures(&o).expect("unit captures");
    let report = certify(&CertifyOptions {
        unit_id: unit_id.into(),
        captures: captures.clone(),
        units_dir: units.to_path_buf(),
        policy: Policy::default(),
        previous: None,
        date: Some("2026-11-30".into()),
        progress: false,
    })
    .expect("certification runs");
    assert!(
        report.failed_checks.is_empty(),
        "{unit_id} did not certify: {:?}",
        report.failed_checks
    );
    std::fs::remove_dir_all(&captures).expect("captures removed");
}

/// Build `dir/session`: two units certified from their simulated captures, then a session
/// recorded with exactly those units. Returns its `session.toml`.
pub fn build_session(dir: &Path, spec: &SessionSpec) -> PathBuf {
    let units = dir.join("units");
    for id in UNITS {
        certified_unit(dir, id, &units, spec);
    }
    let mut o = SessionOptions::new(dir.join("session"));
    o.seed = spec.seed;
    o.resolution = spec.resolution;
    o.rate_hz = spec.rate_hz;
    o.episodes = spec.scenarios.len();
    o.episode_scenarios = spec.scenarios.clone();
    o.episode_durations = spec.durations.clone();
    o.scenario = spec.scenarios[0];
    o.duration_s = spec.durations[0];
    o.blur_samples = 2;
    o.units = Some(CertifiedUnits {
        dir: units,
        left: UNITS[0].into(),
        right: UNITS[1].into(),
        seed: spec.seed,
    });
    o.covers = spec.covers.clone();
    write_session(&o).expect("session").session_toml
}

/// The shared session's `session.toml`, built on first use and reused by every test process
/// of this machine (guarded by a lock file; a finished build leaves a `ready` marker).
pub fn shared_session() -> PathBuf {
    let root =
        PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join(format!("pipeline-e2e-seed{SEED}-v1"));
    std::fs::create_dir_all(&root).expect("tmp dir");
    let lock = std::fs::File::create(root.join(".lock")).expect("lock file");
    lock.lock().expect("lock");
    let toml = root.join("session").join("session.toml");
    if !root.join("ready").is_file() {
        for sub in ["session", "units", "captures"] {
            let _ = std::fs::remove_dir_all(root.join(sub));
        }
        build_session(&root, &SessionSpec::shared());
        std::fs::write(root.join("ready"), b"ok").expect("marker");
    }
    lock.unlock().expect("unlock");
    toml
}

/// Copy a folder tree (hard links for files, so copies of a session are cheap).
pub fn copy_tree(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap().flatten() {
        let (src, dst) = (e.path(), to.join(e.file_name()));
        if src.is_dir() {
            copy_tree(&src, &dst);
        } else if std::fs::hard_link(&src, &dst).is_err() {
            std::fs::copy(&src, &dst).unwrap();
        }
    }
}

/// A pose from position and quaternion fields.
pub fn pose(v: &[f64]) -> Pose {
    Isometry3::from_parts(
        Translation3::new(v[0], v[1], v[2]),
        UnitQuaternion::from_quaternion(Quaternion::new(v[6], v[3], v[4], v[5])),
    )
}

/// A CSV file as header → column values (text).
pub fn read_csv(path: &Path) -> Vec<BTreeMap<String, String>> {
    let text = std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let mut lines = text.lines();
    let header: Vec<String> = lines
        .next()
        .unwrap()
        .split(',')
        .map(str::to_string)
        .collect();
    lines
        .filter(|l| !l.trim().is_empty())
        .map(|l| {
            header
                .iter()
                .cloned()
                .zip(l.split(',').map(str::to_string))
                .collect()
        })
        .collect()
}

/// Numbers of some columns of a row.
pub fn nums(row: &BTreeMap<String, String>, cols: &[&str]) -> Vec<f64> {
    cols.iter()
        .map(|c| row[*c].parse::<f64>().unwrap_or(f64::NAN))
        .collect()
}

/// A frame of the simulator's truth for one lens: camera clock, session clock, `world_from_cam`.
#[derive(Debug, Clone, Copy)]
pub struct TruthFrame {
    /// Camera clock (s).
    pub t: f64,
    /// Session clock (s).
    pub t_session: f64,
    /// `world_from_cam`.
    pub world_from_cam: Pose,
}

/// Truth poses of one lens of an episode.
pub fn truth_frames(session: &Path, episode: &str, camera: &str, lens: &str) -> Vec<TruthFrame> {
    let path = session
        .join("episodes")
        .join(episode)
        .join("truth")
        .join(camera)
        .join(format!("{lens}_poses.csv"));
    read_csv(&path)
        .iter()
        .map(|r| {
            let v = nums(
                r,
                &["t", "t_session", "px", "py", "pz", "qx", "qy", "qz", "qw"],
            );
            TruthFrame {
                t: v[0],
                t_session: v[1],
                world_from_cam: pose(&v[2..]),
            }
        })
        .collect()
}

/// One row of a pipeline output `<wrist>.csv`.
#[derive(Debug, Clone)]
pub struct OutRow {
    /// Session time.
    pub t_session: Option<f64>,
    /// Camera time.
    pub t_camera: f64,
    /// `scene_from_tip`.
    pub tip: Pose,
    /// `scene_from_front_cam`.
    pub cam: Pose,
    /// Support class.
    pub support: String,
    /// Opening (SI) if measured.
    pub opening: Option<f64>,
}

/// Read `episodes/<ep>/out/<camera>.csv`.
pub fn out_rows(session: &Path, episode: &str, camera: &str) -> Vec<OutRow> {
    let path = session
        .join("episodes")
        .join(episode)
        .join("out")
        .join(format!("{camera}.csv"));
    read_csv(&path)
        .iter()
        .map(|r| OutRow {
            t_session: r["t_session"].parse().ok(),
            t_camera: r["t_camera"].parse().unwrap(),
            tip: pose(&nums(
                r,
                &[
                    "tip_px", "tip_py", "tip_pz", "tip_qx", "tip_qy", "tip_qz", "tip_qw",
                ],
            )),
            cam: pose(&nums(
                r,
                &[
                    "cam_px", "cam_py", "cam_pz", "cam_qx", "cam_qy", "cam_qz", "cam_qw",
                ],
            )),
            support: r["support"].clone(),
            opening: r["opening"].parse().ok(),
        })
        .collect()
}

/// Median and 95th percentile.
pub fn median_p95(mut v: Vec<f64>) -> (f64, f64) {
    v.sort_by(f64::total_cmp);
    let at = |p: f64| v[((v.len() - 1) as f64 * p).round() as usize];
    (at(0.5), at(0.95))
}

/// The rigid `world_from_scene` fitted on the front-camera positions of a wrist's outputs.
pub fn fit_world_from_scene(rows: &[OutRow], truth: &[TruthFrame]) -> Pose {
    let mut est = Vec::new();
    let mut tru = Vec::new();
    for r in rows {
        if let Some(f) = truth_at(truth, r.t_camera) {
            est.push(r.cam.translation.vector);
            tru.push(f.world_from_cam.translation.vector);
        }
    }
    let sim = kiwi_backend::vision::align::umeyama(&est, &tru, false).expect("alignment");
    Isometry3::from_parts(Translation3::from(sim.translation), sim.rotation)
}

/// The truth frame with the same camera time (the outputs keep 6 decimals).
pub fn truth_at(truth: &[TruthFrame], t: f64) -> Option<&TruthFrame> {
    let k = truth.partition_point(|f| f.t < t - 1e-6);
    truth.get(k).filter(|f| (f.t - t).abs() < 1e-5)
}

/// Position of a point on a truth trajectory at session time `t` (linear between frames).
pub fn truth_point_at_session(truth: &[TruthFrame], offset: &Pose, t: f64) -> Option<Vector3<f64>> {
    let k = truth.partition_point(|f| f.t_session < t);
    let (a, b) = (truth.get(k.checked_sub(1)?)?, truth.get(k)?);
    let s = (t - a.t_session) / (b.t_session - a.t_session);
    let pa = (a.world_from_cam * offset).translation.vector;
    let pb = (b.world_from_cam * offset).translation.vector;
    Some(pa + (pb - pa) * s)
}

/// The builtin tool's `cam_from_tip` of a wrist (left chopstick, right parallel jaw).
pub fn cam_from_tip(kind: &str) -> Pose {
    let kind = match kind {
        "left" => kiwi_core::layout::ToolKind::Chopstick,
        _ => kiwi_core::layout::ToolKind::ParallelJaw,
    };
    ToolDefinition::builtin(kind).unwrap().cam_from_tip()
}

/// Tool-tip errors of one wrist.
pub struct Errors {
    /// Position errors (m).
    pub position: Vec<f64>,
    /// Rotation errors (deg).
    pub rotation_deg: Vec<f64>,
    /// Frames compared.
    pub frames: usize,
}

/// Tool-tip errors of a wrist in an episode, optionally only for frames whose session time is
/// inside `window` (s into the episode).
pub fn tip_errors(
    session: &Path,
    episode: &str,
    camera: &str,
    world_from_scene: &Pose,
    window: Option<(f64, f64)>,
) -> Errors {
    let rows = out_rows(session, episode, camera);
    let truth = truth_frames(session, episode, camera, "front");
    let tip = cam_from_tip(camera);
    let mut e = Errors {
        position: Vec::new(),
        rotation_deg: Vec::new(),
        frames: 0,
    };
    for r in &rows {
        let Some(f) = truth_at(&truth, r.t_camera) else {
            continue;
        };
        if let Some((a, b)) = window
            && !(a..b).contains(&f.t_session)
        {
            continue;
        }
        e.frames += 1;
        let est = world_from_scene * r.tip;
        let tru = f.world_from_cam * tip;
        e.position
            .push((est.translation.vector - tru.translation.vector).norm());
        e.rotation_deg
            .push(est.rotation.angle_to(&tru.rotation).to_degrees());
    }
    e
}

/// `world_from_scene` fitted on the mapping episode's left front-camera trajectory.
pub fn alignment(session: &Path) -> Pose {
    let map_ep = "ep000";
    fit_world_from_scene(
        &out_rows(session, map_ep, "left"),
        &truth_frames(session, map_ep, "left", "front"),
    )
}

/// The head's errors in an episode: the hat marker's track (`out/head.csv`) against
/// `truth/head_marker_poses.csv`, and the head camera's poses (`out/head_camera.csv`) against
/// its lens truth, both in the truth world through `world_from_scene`.
pub struct HeadErrors {
    /// Track samples, and those posed.
    pub samples: usize,
    /// Posed samples.
    pub posed: usize,
    /// Marker position errors (m).
    pub position: Vec<f64>,
    /// Marker rotation errors (deg).
    pub rotation_deg: Vec<f64>,
    /// Head camera frames, and those posed.
    pub camera_frames: usize,
    /// Posed head camera frames.
    pub camera_posed: usize,
    /// Head camera position errors (m).
    pub camera_position: Vec<f64>,
    /// Head camera rotation errors (deg).
    pub camera_rotation_deg: Vec<f64>,
}

/// A truth pose at session time `t`, interpolated between rows (`None` outside them).
fn truth_pose_at(rows: &[(f64, Pose)], t: f64) -> Option<Pose> {
    let k = rows.partition_point(|r| r.0 <= t);
    let (a, b) = (rows.get(k.checked_sub(1)?)?, rows.get(k)?);
    Some(a.1.lerp_slerp(&b.1, (t - a.0) / (b.0 - a.0)))
}

/// The head's errors of an episode, or `None` when it has no head outputs.
pub fn head_errors(session: &Path, episode: &str, world_from_scene: &Pose) -> Option<HeadErrors> {
    let ep = session.join("episodes").join(episode);
    let track = ep.join("out/head.csv");
    if !track.is_file() {
        return None;
    }
    let fields = ["px", "py", "pz", "qx", "qy", "qz", "qw"];
    let marker_truth: Vec<(f64, Pose)> = read_csv(&ep.join("truth/head_marker_poses.csv"))
        .iter()
        .map(|r| (nums(r, &["t_session"])[0], pose(&nums(r, &fields))))
        .collect();
    let mut e = HeadErrors {
        samples: 0,
        posed: 0,
        position: Vec::new(),
        rotation_deg: Vec::new(),
        camera_frames: 0,
        camera_posed: 0,
        camera_position: Vec::new(),
        camera_rotation_deg: Vec::new(),
    };
    // The pipeline's session timeline starts at its reference camera's clock; the simulator's
    // has its own origin. The left front camera's frames, known on both, give the difference.
    let left = truth_frames(session, episode, "left", "front");
    let mut shifts: Vec<f64> = out_rows(session, episode, "left")
        .iter()
        .filter_map(|r| Some(truth_at(&left, r.t_camera)?.t_session - r.t_session?))
        .collect();
    if shifts.is_empty() {
        return None;
    }
    let (to_truth, _) = median_p95(std::mem::take(&mut shifts));
    let marker_fields = fields.map(|f| format!("marker_{f}"));
    let marker_fields: Vec<&str> = marker_fields.iter().map(String::as_str).collect();
    for r in read_csv(&track) {
        e.samples += 1;
        let v = nums(&r, &marker_fields);
        if v.iter().any(|x| !x.is_finite()) {
            continue;
        }
        e.posed += 1;
        let t = nums(&r, &["t_session"])[0] + to_truth;
        let Some(truth) = truth_pose_at(&marker_truth, t) else {
            continue;
        };
        let est = world_from_scene * pose(&v);
        e.position
            .push((est.translation.vector - truth.translation.vector).norm());
        e.rotation_deg
            .push(est.rotation.angle_to(&truth.rotation).to_degrees());
    }
    // The head camera's frames by their own clock, as the wrists' are compared.
    let camera_truth = truth_frames(session, episode, "head", "main");
    let cam_fields = fields.map(|f| format!("cam_{f}"));
    let cam_fields: Vec<&str> = cam_fields.iter().map(String::as_str).collect();
    for r in read_csv(&ep.join("out/head_camera.csv")) {
        e.camera_frames += 1;
        let v = nums(&r, &cam_fields);
        if v.iter().any(|x| !x.is_finite()) {
            continue;
        }
        e.camera_posed += 1;
        let Some(truth) =
            truth_at(&camera_truth, nums(&r, &["t_camera"])[0]).map(|f| f.world_from_cam)
        else {
            continue;
        };
        let est = world_from_scene * pose(&v);
        e.camera_position
            .push((est.translation.vector - truth.translation.vector).norm());
        e.camera_rotation_deg
            .push(est.rotation.angle_to(&truth.rotation).to_degrees());
    }
    Some(e)
}
