//! The simulator's truth pose files (`t_session,px,...,qw` with the clock's own `t`) and a
//! wrist's true IMU trajectory as fused nodes, for the tests developed on truth poses.

use std::path::Path;

use nalgebra::{Quaternion, Translation3, UnitQuaternion};

use kiwi_backend::fusion::FusedNode;
use kiwi_core::geometry::Pose;

/// A truth row: the clock's own time (`t`, when the file has it), session time, pose.
pub struct TruthRow {
    pub t: f64,
    pub t_session: f64,
    pub pose: Pose,
}

/// Rows of a truth CSV whose columns include `t_session,px,py,pz,qx,qy,qz,qw` (and `t`).
pub fn truth_rows(path: &Path) -> Vec<TruthRow> {
    let text = std::fs::read_to_string(path).unwrap();
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    let col = |name: &str| header.iter().position(|h| *h == name);
    let (ts, px, t) = (col("t_session").unwrap(), col("px").unwrap(), col("t"));
    lines
        .map(|l| {
            let v: Vec<f64> = l.split(',').map(|x| x.parse().unwrap()).collect();
            let q = UnitQuaternion::from_quaternion(Quaternion::new(
                v[px + 6],
                v[px + 3],
                v[px + 4],
                v[px + 5],
            ));
            TruthRow {
                t: t.map_or(f64::NAN, |i| v[i]),
                t_session: v[ts],
                pose: Pose::from_parts(Translation3::new(v[px], v[px + 1], v[px + 2]), q),
            }
        })
        .collect()
}

/// Truth rows (on their own clock `t`) as fused nodes: the truth trajectory where a stage
/// reads the fusion's.
pub fn truth_nodes(rows: &[TruthRow]) -> Vec<FusedNode> {
    rows.iter()
        .map(|r| FusedNode {
            t: r.t,
            scene_from_imu: r.pose,
            velocity: nalgebra::Vector3::zeros(),
            bias: Default::default(),
            pose_cov: nalgebra::Matrix6::zeros(),
            support: Default::default(),
        })
        .collect()
}

/// A wrist's floor windows on the simulator's truth: its front lens with the exact calibration
/// the simulator keeps beside its truth (`truth/units/<unit>/`), posed on the wrist's true IMU
/// trajectory, through the floor stage's own window function.
pub fn truth_floor_windows(
    root: &Path,
    episode: &kiwi_core::layout::EpisodeLayout,
    unit: &str,
    side: kiwi_core::layout::Side,
    options: &kiwi_backend::floor::FloorOptions,
) -> (
    Vec<kiwi_backend::floor::WindowEstimate>,
    kiwi_backend::floor::WindowCounts,
) {
    let camera = side.camera_name();
    let cal = kiwi_core::artifact::UnitCalibration::load(
        &root.join("truth/units").join(unit).join("calibration.json"),
    )
    .unwrap();
    let front = cal.lens("front").unwrap();
    let meta = episode.read_meta(camera).unwrap();
    let readout = 2.0
        * kiwi_backend::formats::calibration::exposure_centre_delay(&cal, &meta.mode, meta.fps)
            .unwrap();
    let nodes = truth_nodes(&truth_rows(
        &episode.truth_dir().join(camera).join("imu_states.csv"),
    ));
    let model = front.camera().unwrap();
    let lens = kiwi_backend::floor::FrontLens {
        side,
        nodes: &nodes,
        cam_from_imu: front.cam_from_imu().unwrap(),
        time_shift_s: front.time_shift_s.unwrap(),
        readout_s: readout,
        camera: &model,
        clock: None,
    };
    let source =
        kiwi_backend::frames::FrameSource::open(&episode.lens_dir(camera, "front")).unwrap();
    kiwi_backend::floor::wrist_windows(&source, &lens, options, &|_, _| {}).unwrap()
}
