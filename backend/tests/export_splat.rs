//! `kiwi export --format colmap|nerfstudio` on small synthetic episode outputs with known
//! trajectories, calibrations (a KB4 and a Double Sphere unit) and maps, read back
//! independently: pycolmap (`backend/tests/python/read_colmap.py`) for the COLMAP model —
//! cameras, rigs, frames, image poses, the exported cameras' pixels for truth rays, the
//! reprojection of the map points — and the nerfstudio `transforms.json` against the COLMAP
//! poses. pycolmap is installed by `make deps`; when it is missing its checks are skipped with a
//! message on stderr.

#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

#[path = "support/export_session.rs"]
mod synthetic;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use nalgebra::{Matrix4, Point2, Quaternion, UnitQuaternion, Vector3, Vector4};
use serde_json::Value;

use kiwi_backend::export::mask::{IGNORE, KEEP, LensMasker};
use kiwi_backend::export::splat::{
    COLMAP_MODEL_DIR, MASK_SUFFIX, PIXEL_CENTRE_OFFSET, SPLIT_EVERY, TEST_LIST,
};
use kiwi_backend::export::{ExportFormat, ExportOptions, WristTrajectory, export, read_trajectory};
use kiwi_backend::formats::calibration::readout_for;
use kiwi_core::camera::CameraModel;
use kiwi_core::geometry::Pose;
use kiwi_core::layout::{Side, ToolKind};
use kiwi_core::tool::ToolDefinition;

use synthetic::{FEATURE_NOISE_PX, LANDMARKS_PER_KEYFRAME, Synthetic, camera_time, f64s};

/// 10 s per camera at 64×64 px per lens: 20 time groups at 2 Hz.
const SPEC: Synthetic = Synthetic {
    frames: 300,
    width: 64,
    height: 64,
    rear_lens: true,
};
/// Images per second and lens.
const RATE: f64 = 2.0;
/// Poses are written with 17 significant digits: equal to the outputs' to rounding.
const POSE_TOL: f64 = 1e-9;
/// The bound for a truth ray through the exported camera (px).
const RAY_TOL_PX: f64 = 0.05;
/// The bound on the median reprojection error of the exported points (px).
const MEDIAN_REPROJECTION_PX: f64 = 1.0;
/// Beyond the features' own noise (at most `FEATURE_NOISE_PX` along each axis), what an
/// exported point may be off (px): far below the half pixel a wrong pixel-centre convention
/// adds.
const REPROJECTION_SLACK_PX: f64 = 0.01;
/// Keep truth rays this far in front of the camera: COLMAP's OPENCV_FISHEYE divides by z.
const MIN_RAY_Z: f64 = 0.05;
/// The views, in camera-id order.
const VIEWS: [(&str, &str); 4] = [
    ("left", "front"),
    ("left", "rear"),
    ("right", "front"),
    ("right", "rear"),
];

fn scene_session(root: &Path) -> PathBuf {
    let session = synthetic::make_session(&SPEC, root);
    synthetic::add_scene_inputs(&SPEC, root, RATE);
    session
}

fn options() -> ExportOptions {
    ExportOptions {
        rate: Some(RATE),
        ..ExportOptions::default()
    }
}

/// Run the pycolmap reader; `None` (and a loud message) when pycolmap is missing.
fn read_colmap(export: &Path, queries: &Value) -> Option<Value> {
    let qpath = export.with_file_name("queries.json");
    std::fs::write(&qpath, queries.to_string()).unwrap();
    synthetic::python_reader("read_colmap.py", &[&export.join(COLMAP_MODEL_DIR), &qpath])
}

fn pose_from_json(v: &Value) -> Pose {
    let q = f64s(&v["q_wxyz"]);
    let t = f64s(&v["t"]);
    Pose::from_parts(
        Vector3::new(t[0], t[1], t[2]).into(),
        UnitQuaternion::from_quaternion(Quaternion::new(q[0], q[1], q[2], q[3])),
    )
}

fn assert_pose_eq(a: &Pose, b: &Pose, tol: f64, what: &str) {
    let dr = a.rotation.angle_to(&b.rotation);
    let dt = (a.translation.vector - b.translation.vector).norm();
    assert!(
        dr <= tol && dt <= tol,
        "{what}: rotation {dr:e} rad, translation {dt:e} m apart"
    );
}

/// `ep0/left_rear/000016.png` → (camera index, lens, frame).
fn parse_name(name: &str) -> (usize, String, usize) {
    let mut parts = name.split('/');
    let (_ep, view, file) = (
        parts.next().unwrap(),
        parts.next().unwrap(),
        parts.next().unwrap(),
    );
    let (camera, lens) = view.split_once('_').unwrap();
    let c = usize::from(camera == "right");
    (
        c,
        lens.to_string(),
        file.trim_end_matches(".png").parse().unwrap(),
    )
}

/// The pipeline outputs' pose of an exported image: its front frame's trajectory at the
/// frame's centre-row exposure (half the recording mode's readout after the row's time; the
/// rear lens is exposed with it), through the unit's `front_from_rear` for a rear image.
fn expected_scene_from_cam(root: &Path, name: &str) -> Pose {
    let cals = synthetic::scene_calibrations(SPEC.width);
    let (c, lens, frame) = parse_name(name);
    let camera = ["left", "right"][c];
    let rows = read_trajectory(&root.join(format!("episodes/ep0/out/{camera}.csv"))).unwrap();
    let row = &rows[frame];
    assert!((row.t_camera - camera_time(c, frame)).abs() < 1e-6);
    let readout = readout_for(&cals[c], synthetic::MODE, synthetic::RATE).unwrap();
    assert!(
        readout > 0.01,
        "the simulated X5 reads a 30 fps frame out in ~15 ms"
    );
    let t = row.t_session.unwrap() + readout / 2.0;
    let wrist = WristTrajectory {
        side: [Side::Left, Side::Right][c],
        tool: ToolKind::Chopstick,
        rows,
    };
    let front = wrist.sample(t).unwrap().scene_from_front_cam;
    match lens.as_str() {
        "front" => front,
        _ => front * synthetic::front_from_rear(&cals[c]),
    }
}

/// A pixel (KIWI's convention) and its truth bearing.
type PixelRay = (Point2<f64>, Vector3<f64>);

/// Pixels on a grid of each lens (KIWI's convention) and their truth bearings, in front of the
/// camera.
fn truth_rays() -> BTreeMap<u32, Vec<PixelRay>> {
    let cals = synthetic::scene_calibrations(SPEC.width);
    let mut rays = BTreeMap::new();
    for (id, (camera, lens)) in VIEWS.iter().enumerate() {
        let cal = &cals[usize::from(*camera == "right")];
        let model = cal.lens(lens).unwrap().camera().unwrap();
        let mut v = Vec::new();
        for y in (0..SPEC.height).step_by(4) {
            for x in (0..SPEC.width).step_by(4) {
                let p = Point2::new(f64::from(x) + 0.25, f64::from(y) + 0.75);
                if let Some(b) = model.unproject(&p)
                    && b.z > MIN_RAY_Z
                {
                    v.push((p, b.into_inner()));
                }
            }
        }
        assert!(v.len() > 50, "{camera}.{lens}: {} rays", v.len());
        rays.insert(id as u32 + 1, v);
    }
    rays
}

#[test]
fn colmap_export_reads_back_with_pycolmap() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    let session = scene_session(root);
    let out = root.join("colmap");
    let started = std::time::Instant::now();
    let report = export(&session, ExportFormat::Colmap, &options(), &out).unwrap();
    eprintln!(
        "colmap export: {:.2} s, {:?}",
        started.elapsed().as_secs_f64(),
        report.notes
    );
    assert_eq!(report.exported, vec!["ep0".to_string()]);
    assert_eq!(report.skipped.len(), 1, "the unusable ep1 is left out");
    // The Double Sphere lenses were refitted and said so.
    assert!(
        report
            .notes
            .iter()
            .filter(|n| n.contains("Double Sphere"))
            .count()
            == 2,
        "{:?}",
        report.notes
    );
    let (_, rows) = synthetic::expected_grid(&SPEC, RATE);
    assert_eq!(report.frames, rows * VIEWS.len());
    for f in [
        "cameras.txt",
        "images.txt",
        "points3D.txt",
        "rigs.txt",
        "frames.txt",
    ] {
        assert!(out.join(COLMAP_MODEL_DIR).join(f).is_file(), "{f}");
    }
    // Held-out split: every eighth time group, all four lenses of it.
    let test = std::fs::read_to_string(out.join(TEST_LIST)).unwrap();
    let groups = rows.div_ceil(SPLIT_EVERY);
    assert_eq!(test.lines().count(), groups * VIEWS.len(), "{test}");

    let rays = truth_rays();
    let queries: BTreeMap<String, Vec<[f64; 3]>> = rays
        .iter()
        .map(|(id, v)| {
            (
                id.to_string(),
                v.iter().map(|(_, b)| [b.x, b.y, b.z]).collect(),
            )
        })
        .collect();
    let Some(model) = read_colmap(&out, &serde_json::to_value(&queries).unwrap()) else {
        return;
    };
    // Cameras: OPENCV_FISHEYE, the KB4 lenses' parameters with the principal point moved by
    // half a pixel; every lens rebuilds its truth rays within RAY_TOL_PX.
    let cals = synthetic::scene_calibrations(SPEC.width);
    for (id, (camera, lens)) in VIEWS.iter().enumerate() {
        let cam = &model["cameras"][(id + 1).to_string()];
        assert_eq!(cam["model"], "OPENCV_FISHEYE");
        assert_eq!(cam["width"], SPEC.width);
        let params = f64s(&cam["params"]);
        if *camera == "left" {
            let mut want = cals[0].lens(lens).unwrap().intrinsics.params();
            want[2] += PIXEL_CENTRE_OFFSET;
            want[3] += PIXEL_CENTRE_OFFSET;
            assert_eq!(params, want, "{camera}.{lens}");
        }
        let projected = cam["projected"].as_array().unwrap();
        let mut worst = 0.0f64;
        for ((pixel, _), got) in rays[&(id as u32 + 1)].iter().zip(projected) {
            let got = f64s(got);
            let err = ((got[0] - pixel.x - PIXEL_CENTRE_OFFSET).powi(2)
                + (got[1] - pixel.y - PIXEL_CENTRE_OFFSET).powi(2))
            .sqrt();
            worst = worst.max(err);
        }
        eprintln!("{camera}.{lens}: truth rays within {worst:.4} px");
        assert!(
            worst < RAY_TOL_PX,
            "{camera}.{lens}: a truth ray is {worst} px off"
        );
    }
    // Every image pose equals the pipeline outputs'.
    let images = model["images"].as_object().unwrap();
    assert_eq!(images.len(), rows * VIEWS.len());
    for (name, img) in images {
        let (c, lens, _) = parse_name(name);
        let want = expected_scene_from_cam(root, name).inverse();
        assert_pose_eq(
            &pose_from_json(&img["cam_from_world"]),
            &want,
            POSE_TOL,
            name,
        );
        let view = VIEWS
            .iter()
            .position(|v| v.0 == ["left", "right"][c] && v.1 == lens);
        assert_eq!(
            img["camera_id"].as_u64().unwrap() as usize,
            view.unwrap() + 1
        );
    }
    // One rig per unit whose rear sensor sits at the calibration's rear_from_front; each
    // frame holds both lenses' images.
    for (r, cal) in cals.iter().enumerate() {
        let rig = &model["rigs"][(r + 1).to_string()];
        assert_eq!(rig["ref_camera"], 2 * r + 1);
        let sensor = pose_from_json(&rig["sensors"][(2 * r + 2).to_string()]);
        let want = synthetic::front_from_rear(cal).inverse();
        assert_pose_eq(&sensor, &want, POSE_TOL, "rear_from_front");
    }
    let frames = model["frames"].as_object().unwrap();
    assert_eq!(frames.len(), rows * 2);
    assert!(
        frames
            .values()
            .all(|f| f["images"].as_array().unwrap().len() == 2)
    );
    // The map points project into the images that observe them.
    let mut errors: Vec<f64> = model["errors"]
        .as_array()
        .unwrap()
        .iter()
        .map(|e| e.as_f64().expect("every observed point projects"))
        .collect();
    assert_eq!(errors.len(), rows * LANDMARKS_PER_KEYFRAME);
    errors.sort_by(f64::total_cmp);
    let median = errors[errors.len() / 2];
    eprintln!(
        "reprojection: median {median:.3} px, worst {:.3} px",
        errors[errors.len() - 1]
    );
    assert!(median < MEDIAN_REPROJECTION_PX, "median {median} px");
    // Each point takes the colour its exported images show at its observations (the synthetic
    // rear frames are one grey level each); a point no exported image observes stays grey.
    let mut coloured = 0;
    for (pid, p) in model["colours"].as_object().unwrap() {
        let rgb = f64s(&p["rgb"]);
        let seen: Vec<f64> = p["images"]
            .as_array()
            .unwrap()
            .iter()
            .map(|n| {
                let (c, lens, frame) = parse_name(n.as_str().unwrap());
                assert_eq!(lens, "rear");
                f64::from(synthetic::grey(c, frame).wrapping_add(1))
            })
            .collect();
        let want = if seen.is_empty() {
            128.0
        } else {
            coloured += 1;
            (seen.iter().sum::<f64>() / seen.len() as f64).round()
        };
        assert_eq!(rgb, vec![want; 3], "point {pid}");
    }
    assert_eq!(coloured, rows * LANDMARKS_PER_KEYFRAME);
    let worst = errors[errors.len() - 1];
    let bound = FEATURE_NOISE_PX * std::f64::consts::SQRT_2 + REPROJECTION_SLACK_PX;
    assert!(
        worst <= bound,
        "worst {worst} px > the features' noise ({bound} px)"
    );
}

/// images.txt by image name: `scene_from_cam` and the camera id.
fn colmap_images(dir: &Path) -> BTreeMap<String, (Pose, String)> {
    let text = std::fs::read_to_string(dir.join(COLMAP_MODEL_DIR).join("images.txt")).unwrap();
    let mut images = BTreeMap::new();
    let mut lines = text.lines().filter(|l| !l.starts_with('#'));
    while let Some(line) = lines.next() {
        let f: Vec<&str> = line.split_whitespace().collect();
        let v: Vec<f64> = f[1..8].iter().map(|x| x.parse().unwrap()).collect();
        let cam_from_world = Pose::from_parts(
            Vector3::new(v[4], v[5], v[6]).into(),
            UnitQuaternion::from_quaternion(Quaternion::new(v[0], v[1], v[2], v[3])),
        );
        images.insert(
            f[9].to_string(),
            (cam_from_world.inverse(), f[8].to_string()),
        );
        lines.next();
    }
    images
}

/// cameras.txt parameters by camera id.
fn colmap_cameras(dir: &Path) -> BTreeMap<String, Vec<f64>> {
    let text = std::fs::read_to_string(dir.join(COLMAP_MODEL_DIR).join("cameras.txt")).unwrap();
    text.lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .map(|l| {
            let f: Vec<&str> = l.split_whitespace().collect();
            (
                f[0].to_string(),
                f[4..].iter().map(|x| x.parse().unwrap()).collect(),
            )
        })
        .collect()
}

#[test]
fn nerfstudio_transforms_round_trip_to_the_colmap_poses() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    let session = scene_session(root);
    let colmap = root.join("colmap");
    let ns = root.join("nerfstudio");
    export(&session, ExportFormat::Colmap, &options(), &colmap).unwrap();
    export(&session, ExportFormat::Nerfstudio, &options(), &ns).unwrap();
    let images = colmap_images(&colmap);
    let cameras = colmap_cameras(&colmap);
    let doc: Value =
        serde_json::from_str(&std::fs::read_to_string(ns.join("transforms.json")).unwrap())
            .unwrap();
    assert_eq!(doc["camera_model"], "OPENCV_FISHEYE");
    assert_eq!(doc["ply_file_path"], "points3D.ply");
    let frames = doc["frames"].as_array().unwrap();
    assert_eq!(frames.len(), images.len());
    let gl_to_cv = Matrix4::from_diagonal(&Vector4::new(1.0, -1.0, -1.0, 1.0));
    for f in frames {
        let path = f["file_path"].as_str().unwrap();
        assert!(ns.join(path).is_file(), "{path}");
        let name = path.trim_start_matches("images/");
        // The lenses differ, so each frame carries its intrinsics: its camera's in cameras.txt.
        let camera = &cameras[&images[name].1];
        for (i, key) in ["fl_x", "fl_y", "cx", "cy", "k1", "k2", "k3", "k4"]
            .iter()
            .enumerate()
        {
            let got = f[*key].as_f64().unwrap();
            assert!(
                (got - camera[i]).abs() < 1e-9,
                "{name} {key}: {got} vs {}",
                camera[i]
            );
        }
        let rows: Vec<Vec<f64>> = f["transform_matrix"]
            .as_array()
            .unwrap()
            .iter()
            .map(f64s)
            .collect();
        let m = Matrix4::from_fn(|r, c| rows[r][c]) * gl_to_cv;
        let rotation = UnitQuaternion::from_matrix(&m.fixed_view::<3, 3>(0, 0).into_owned());
        let scene_from_cam = Pose::from_parts(
            Vector3::new(m[(0, 3)], m[(1, 3)], m[(2, 3)]).into(),
            rotation,
        );
        assert_pose_eq(&scene_from_cam, &images[name].0, POSE_TOL, name);
    }
    let test = doc["test_filenames"].as_array().unwrap().len();
    let train = doc["train_filenames"].as_array().unwrap().len();
    assert_eq!(test + train, frames.len());
    let ply = std::fs::read_to_string(ns.join("points3D.ply")).unwrap();
    let (_, rows) = synthetic::expected_grid(&SPEC, RATE);
    // The rear map's landmarks and the two front maps' five each.
    let points = rows * LANDMARKS_PER_KEYFRAME + 10;
    assert!(
        ply.contains(&format!("element vertex {points}\n")),
        "{ply:.300}"
    );
}

/// Every exported image has a mask beside it, named where 3DGUT and nerfstudio look; a front
/// mask covers the tool as its definition places it at the frame's gripper opening, and no
/// more than the tool over its whole range.
#[test]
fn every_image_gets_a_mask_of_its_tool_at_its_opening() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    let session = scene_session(root);
    let ns = root.join("nerfstudio");
    export(&session, ExportFormat::Nerfstudio, &options(), &ns).unwrap();
    let doc: Value =
        serde_json::from_str(&std::fs::read_to_string(ns.join("transforms.json")).unwrap())
            .unwrap();
    let cals = synthetic::scene_calibrations(SPEC.width);
    let tools =
        [ToolKind::Chopstick, ToolKind::ParallelJaw].map(|k| ToolDefinition::builtin(k).unwrap());
    let mut narrower_than_the_range = 0;
    let frames = doc["frames"].as_array().unwrap();
    for f in frames {
        let image = f["file_path"].as_str().unwrap();
        let mask_path = f["mask_path"].as_str().unwrap();
        assert_eq!(
            mask_path,
            image.replace(".png", MASK_SUFFIX),
            "3DGUT's name"
        );
        let mask = image::open(ns.join(mask_path)).unwrap();
        assert_eq!(mask.color(), image::ColorType::L8, "{mask_path}");
        let mask = mask.to_luma8();
        assert_eq!(mask.dimensions(), (SPEC.width, SPEC.height));
        assert!(mask.pixels().all(|p| p.0[0] == KEEP || p.0[0] == IGNORE));
        let name = image.trim_start_matches("images/");
        let (c, lens, frame) = parse_name(name);
        let lens_cal = cals[c].lens(&lens).unwrap();
        let camera = lens_cal.camera().unwrap();
        let lens_from_front = match lens.as_str() {
            "front" => Pose::identity(),
            _ => synthetic::front_from_rear(&cals[c]).inverse(),
        };
        let masker = LensMasker::new(&camera, lens_cal.valid_fov_rad, lens_from_front);
        let row =
            &read_trajectory(&root.join(format!("episodes/ep0/out/{}.csv", ["left", "right"][c])))
                .unwrap()[frame];
        // The synthetic parallel jaw opens past the tool's 0.1 m near the end; the plates stop
        // there.
        let truth =
            synthetic::truth_opening(c, row.t_session.unwrap()).min(tools[c].jaws.max_opening);
        let at_truth = masker.mask(&tools[c].solids(truth));
        let swept: Vec<_> = tools[c]
            .sweep_openings()
            .iter()
            .flat_map(|&o| tools[c].solids(o))
            .collect();
        let swept = masker.mask(&swept);
        for ((m, t), s) in mask.pixels().zip(at_truth.pixels()).zip(swept.pixels()) {
            if t.0[0] == IGNORE {
                assert_eq!(
                    m.0[0], IGNORE,
                    "{mask_path}: the tool at its opening is kept"
                );
            }
            if s.0[0] == KEEP {
                assert_eq!(m.0[0], KEEP, "{mask_path}: beyond the tool's whole range");
            }
        }
        let ignored = |m: &image::GrayImage| m.pixels().filter(|p| p.0[0] == IGNORE).count();
        if ignored(&mask) < ignored(&swept) {
            narrower_than_the_range += 1;
        }
    }
    // The measured opening narrows the front masks (the jaws' sweep is wider than the band).
    assert!(
        narrower_than_the_range >= frames.len() / 4,
        "{narrower_than_the_range} of {} masks narrower than the tool's range",
        frames.len()
    );
}

#[test]
fn scene_exports_refuse_bad_input() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    let session = scene_session(root);
    let fail = |name: &str| {
        let out = root.join(name);
        let err = export(&session, ExportFormat::Colmap, &options(), &out)
            .unwrap_err()
            .to_string();
        assert!(!out.exists(), "a failed export leaves no folder");
        err
    };
    // A Double Sphere lens KB4 cannot follow within 0.1 px (0.35 px off over its 200° field).
    let set = root.join("units/X5-R/2026-01-01/calibration.json");
    let good = std::fs::read_to_string(&set).unwrap();
    let mut cal = kiwi_core::artifact::UnitCalibration::from_json(&good, &set).unwrap();
    for l in &mut cal.lenses {
        if l.name == "rear" {
            l.intrinsics = kiwi_core::artifact::Intrinsics::DoubleSphere {
                fx: 40.0,
                fy: 40.0,
                cx: 32.0,
                cy: 32.0,
                xi: -0.6,
                alpha: 0.5,
            };
            l.valid_fov_rad = 200f64.to_radians();
        }
    }
    std::fs::write(&set, cal.to_json().unwrap()).unwrap();
    let err = fail("refit");
    assert!(
        err.contains("rear") && err.contains("cannot be written as OPENCV_FISHEYE"),
        "{err}"
    );
    std::fs::write(&set, good).unwrap();
    // No visually supported pose in the episode.
    let mut kept = Vec::new();
    for camera in ["left", "right"] {
        let path = root.join(format!("episodes/ep0/out/{camera}.csv"));
        let text = std::fs::read_to_string(&path).unwrap();
        std::fs::write(&path, text.replace(",front,front,", ",imu-only,front,")).unwrap();
        kept.push((path, text));
    }
    let err = fail("unposed");
    assert!(
        err.contains("ep0") && err.contains("has a visually supported pose"),
        "{err}"
    );
    for (path, text) in kept {
        std::fs::write(path, text).unwrap();
    }
    // The maps are missing.
    std::fs::remove_dir_all(root.join("work/map-rear")).unwrap();
    let err = fail("nomap");
    assert!(
        err.contains("map.kmap") && err.contains("kiwi run"),
        "{err}"
    );
}

/// The head camera's images: posed from the outputs' `head.csv` at their centre row's
/// exposure on the head camera's clock, left out inside the track's gap, masked at the rim of
/// the lens only, and a rig of their own.
#[test]
fn head_camera_images_are_posed_from_the_head_track() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    let session = scene_session(root);
    let head_cal = synthetic::add_head_camera(&SPEC, root);
    let out = root.join("colmap");
    let report = export(&session, ExportFormat::Colmap, &options(), &out).unwrap();
    let track =
        kiwi_backend::head::episode::CameraTrack::read_csv(&root.join("episodes/ep0/out/head.csv"))
            .unwrap();
    let readout = readout_for(&head_cal, synthetic::HEAD_MODE, synthetic::RATE).unwrap();
    assert!(readout > 0.01, "the GO 3 reads a frame out in 20 ms");
    let images = colmap_images(&out);
    let head: Vec<(&String, &(Pose, String))> = images
        .iter()
        .filter(|(n, _)| n.starts_with("ep0/head_main/"))
        .collect();
    let (mut expected, mut in_gap) = (0, 0);
    let (t_first, rows) = synthetic::expected_grid(&SPEC, RATE);
    for k in 0..rows {
        let t = t_first + k as f64 / RATE;
        let frame = (0..SPEC.frames)
            .min_by(|&a, &b| {
                (synthetic::head_session_time(a) - t)
                    .abs()
                    .total_cmp(&(synthetic::head_session_time(b) - t).abs())
            })
            .unwrap();
        let centre = synthetic::head_session_time(frame) + readout / 2.0;
        match track.at(centre) {
            Some(_) => expected += 1,
            None => in_gap += 1,
        }
    }
    assert!(in_gap > 0, "the grid crosses the track's gap");
    assert_eq!(head.len(), expected, "{in_gap} head frames in the gap");
    let cameras = colmap_cameras(&out);
    for (name, (pose, camera)) in &head {
        let frame: usize = name
            .rsplit('/')
            .next()
            .unwrap()
            .trim_end_matches(".png")
            .parse()
            .unwrap();
        let t = synthetic::head_session_time(frame) + readout / 2.0;
        // Exactly the track's pose at the centre row's time, and the truth to interpolation.
        assert_pose_eq(pose, &track.at(t).unwrap().scene_from_cam, 1e-6, name);
        assert_pose_eq(pose, &synthetic::truth_head(t), 1e-4, name);
        assert_eq!(
            cameras[camera].len(),
            8,
            "OPENCV_FISHEYE: fx fy cx cy k1-k4"
        );
        let mask = image::open(out.join("images").join(name.replace(".png", MASK_SUFFIX)))
            .unwrap()
            .to_luma8();
        // The rim beyond the lens field is ignored, the centre kept: no tool on the head.
        let (w, h) = mask.dimensions();
        assert_eq!(mask.get_pixel(w / 2, h / 2).0[0], KEEP);
    }
    let rigs = std::fs::read_to_string(out.join(COLMAP_MODEL_DIR).join("rigs.txt")).unwrap();
    let head_camera = &head[0].1.1;
    assert!(
        rigs.lines()
            .filter(|l| !l.starts_with('#'))
            .any(|l| l.split_whitespace().nth(3) == Some(head_camera.as_str())),
        "the head camera is a rig's reference: {rigs}"
    );
    assert!(
        report.notes.iter().any(|n| n.contains("left out")),
        "{:?}",
        report.notes
    );
}
