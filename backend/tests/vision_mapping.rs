//! Incremental mapping on synthetic tracks in a room: a camera walks an arc, sees wall points
//! up to 95° off-axis with noise and outliers; after Sim(3) alignment the keyframe trajectory
//! error must stay below 0.5 % of the trajectory extent (the mapping criterion).
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

use kiwi_backend::vision::align::{TrajectoryError, align_and_measure};
use kiwi_backend::vision::mapping::{
    MapperOptions, MappingFrame, Reconstruction, TrackObservation, reconstruct,
};
use kiwi_core::geometry::{Pose, so3_exp};
use nalgebra::{Point3, Translation3, UnitQuaternion, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

const MAX_OFF_AXIS: f64 = 95.0 * std::f64::consts::PI / 180.0;

fn random_unit(rng: &mut ChaCha8Rng) -> Vector3<f64> {
    loop {
        let v = Vector3::new(
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
        );
        let n = v.norm();
        if n > 0.1 && n <= 1.0 {
            return v / n;
        }
    }
}

/// Points on the walls, floor and ceiling of a 6 × 5 × 2.7 m room centred on the origin.
fn room_points(rng: &mut ChaCha8Rng, n: usize) -> Vec<Vector3<f64>> {
    (0..n)
        .map(|_| {
            let mut p = Vector3::new(
                rng.random_range(-3.0..3.0),
                rng.random_range(-2.5..2.5),
                rng.random_range(0.0..2.7),
            );
            match rng.random_range(0..6) {
                0 => p.x = -3.0,
                1 => p.x = 3.0,
                2 => p.y = -2.5,
                3 => p.y = 2.5,
                4 => p.z = 0.0,
                _ => p.z = 2.7,
            }
            p
        })
        .collect()
}

/// `world_from_cam` along an arc, camera looking roughly forward and swaying.
fn trajectory(i: usize, n: usize) -> Pose {
    let s = i as f64 / n as f64;
    let a = 1.6 * s;
    let centre = Vector3::new(
        1.2 * a.cos() - 1.2,
        1.2 * a.sin(),
        1.2 + 0.1 * (3.0 * a).sin(),
    );
    // Camera z along the walking direction (tangent), y down.
    let forward = Vector3::new(-a.sin(), a.cos(), 0.0);
    let down = Vector3::new(0.0, 0.0, -1.0);
    let right = down.cross(&forward);
    let base = UnitQuaternion::from_basis_unchecked(&[right, down, forward]);
    let sway = so3_exp(&Vector3::new(
        0.1 * (5.0 * a).sin(),
        0.15 * (4.0 * a).cos(),
        0.05 * a,
    ));
    Pose::from_parts(Translation3::from(centre), base * sway)
}

#[test]
fn mapping_recovers_the_keyframe_trajectory() {
    let mut rng = ChaCha8Rng::seed_from_u64(21);
    let points = room_points(&mut rng, 900);
    let n = 90;
    let truth: Vec<Pose> = (0..n).map(|i| trajectory(i, n)).collect();
    let mut frames = Vec::new();
    let mut outliers = 0;
    for (i, world_from_cam) in truth.iter().enumerate() {
        let cam_from_world = world_from_cam.inverse();
        let mut observations = Vec::new();
        for (j, p) in points.iter().enumerate() {
            let pc = (cam_from_world * Point3::from(*p)).coords;
            let b = pc.normalize();
            if b.z.acos() > MAX_OFF_AXIS {
                continue;
            }
            let bearing = if rng.random_range(0.0..1.0) < 0.02 {
                outliers += 1;
                (b + random_unit(&mut rng) * 0.1).normalize()
            } else {
                // ~0.5 mrad: about 0.15 px at the centre of a 960 px X5 lens.
                (b + random_unit(&mut rng) * 0.0005 * rng.random_range(0.0..1.0)).normalize()
            };
            observations.push(TrackObservation {
                track: j as u64,
                bearing,
                pixel: nalgebra::Point2::origin(),
            });
        }
        frames.push(MappingFrame {
            frame: i as u32,
            t: i as f64 / 30.0,
            observations,
        });
    }
    assert!(outliers > 100);
    let recon = reconstruct(&frames, &MapperOptions::default()).unwrap();
    assert_eq!(recon.lost_at, None);
    assert!(
        recon.keyframes.len() >= 8,
        "{} keyframes",
        recon.keyframes.len()
    );
    let err = keyframe_ate(&recon, &truth);
    eprintln!(
        "{} keyframes, {} landmarks, {} frames tracked; keyframe ATE {:.2} mm rmse, {:.2} mm max, \
         extent {:.2} m, {:.4} % of extent",
        recon.keyframes.len(),
        recon.landmarks.len(),
        recon.frame_poses.len(),
        err.rmse * 1e3,
        err.max * 1e3,
        err.extent,
        100.0 * err.relative_rmse()
    );
    assert!(err.relative_rmse() < 0.005, "{err:?}");
    // Every frame is tracked, in order.
    assert_eq!(recon.frame_poses.len(), n);
    assert!(recon.frame_poses.windows(2).all(|w| w[0].0 < w[1].0));
    // Deterministic.
    let again = reconstruct(&frames, &MapperOptions::default()).unwrap();
    assert_eq!(recon, again);
}

/// `world_from_cam` near the table, looking along +y and down, sliding sideways.
fn table_pose(i: usize, n: usize) -> Pose {
    let s = i as f64 / n as f64;
    let base = nalgebra::Matrix3::new(1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, -1.0, 0.0);
    let tilt = so3_exp(&Vector3::new(-0.35, 0.0, 0.0));
    let sway = so3_exp(&Vector3::new(0.0, 0.0, 0.15 * (3.0 * s).sin()));
    let r = sway
        * tilt
        * UnitQuaternion::from_rotation_matrix(&nalgebra::Rotation3::from_matrix_unchecked(base));
    let c = Vector3::new(-0.3 + 0.6 * s, -0.6 + 0.1 * s, 1.3 + 0.05 * (2.0 * s).sin());
    Pose::from_parts(Translation3::from(c), r)
}

#[test]
fn mapping_from_rendered_fisheye_frames() {
    use kiwi_backend::vision::features::{
        FOV_MASK_MARGIN_RAD, GrayImage, MatchOptions, OrbExtractor, OrbOptions, fov_mask,
        match_descriptors,
    };
    use kiwi_backend::vision::frontend::{FrameTracker, TrackerOptions};
    use kiwi_backend::vision::geometry::{RansacOptions, absolute_pose_ransac};
    use kiwi_backend::vision::map::VisualMap;
    use kiwi_fixtures::render::{Extras, LensRays, RenderOptions, render};
    use kiwi_fixtures::scene::{Scene, SceneOptions};
    use kiwi_fixtures::unit::{LensModel, SimUnit};

    let size = 320;
    let unit = SimUnit::x5("X5-MAP", 4, size, LensModel::Kb4).unwrap();
    let camera = unit.lenses[0].camera.clone();
    let rays = LensRays::new(&camera);
    let scene = Scene::new(8, SceneOptions::default());
    let n = 40;
    let truth: Vec<Pose> = (0..n).map(|i| table_pose(i, n)).collect();
    let mask = fov_mask(&camera, FOV_MASK_MARGIN_RAD);
    let mut tracker = FrameTracker::new(TrackerOptions::default(), mask.clone()).unwrap();
    let mut frames = Vec::new();
    let mut images = Vec::new();
    for (i, pose) in truth.iter().enumerate() {
        let options = RenderOptions {
            noise_key: i as u64,
            ..RenderOptions::default()
        };
        let img = render(
            &scene,
            &rays,
            &|_t| *pose,
            0.0,
            &Extras::default(),
            &options,
        );
        let gray = GrayImage::from_rgb(img.width(), img.height(), img.as_raw()).unwrap();
        images.push(gray.clone());
        frames.push(
            tracker
                .process(i as u32, i as f64 / 30.0, gray, &camera)
                .unwrap(),
        );
    }
    // 1 px ≈ 10 mrad at 320 px: thresholds scaled from the 960 px defaults.
    let mut options = MapperOptions::default();
    options.ransac.threshold_rad = 0.012;
    options.triangulation.max_error_rad = 0.012;
    options.ba.huber_rad = 0.012;
    options.max_error_rad = 0.02;
    let recon = reconstruct(&frames, &options).unwrap();
    let est: Vec<Vector3<f64>> = recon
        .frame_poses
        .iter()
        .map(|(_, p)| p.inverse().translation.vector)
        .collect();
    let tru: Vec<Vector3<f64>> = recon
        .frame_poses
        .iter()
        .map(|(f, _)| truth[*f as usize].translation.vector)
        .collect();
    let (_, err) = align_and_measure(&est, &tru).unwrap();
    eprintln!(
        "rendered {size} px: {} keyframes, {} landmarks, {} of {n} frames tracked; ATE {:.2} mm \
         rmse, {:.2} mm max, extent {:.3} m, {:.3} % of extent",
        recon.keyframes.len(),
        recon.landmarks.len(),
        recon.frame_poses.len(),
        err.rmse * 1e3,
        err.max * 1e3,
        err.extent,
        100.0 * err.relative_rmse()
    );
    assert_eq!(recon.lost_at, None);
    assert_eq!(recon.frame_poses.len(), n);
    assert!(err.relative_rmse() < 0.005, "{err:?}");

    // Export the map with ORB descriptors at the keyframes, through the file.
    let mut orb = OrbExtractor::new(&OrbOptions::default()).unwrap();
    let kf_features: Vec<_> = recon
        .keyframes
        .iter()
        .map(|k| {
            orb.extract(&images[k.frame as usize], Some(&mask), &camera)
                .unwrap()
        })
        .collect();
    let map =
        VisualMap::from_reconstruction(&recon, &kf_features, "left", "front", "ep000", &camera)
            .unwrap();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("front.kmap");
    map.save(&path).unwrap();
    let map = VisualMap::load(&path).unwrap();
    map.check_query_lens("front", &camera).unwrap();
    assert!(
        map.landmarks.len() > 100,
        "{} described landmarks",
        map.landmarks.len()
    );

    // Localize non-keyframes against the frozen map by descriptor matching + P3P RANSAC and
    // compare with the truth through the map's Sim(3).
    let (sim, _) = align_and_measure(&est, &tru).unwrap();
    let descs: Vec<_> = map.landmarks.iter().map(|l| l.descriptor).collect();
    let positions: Vec<Vector3<f64>> = map
        .landmarks
        .iter()
        .map(|l| Vector3::from(l.position))
        .collect();
    let mut errors = Vec::new();
    for i in (3..n).step_by(6) {
        let q = orb.extract(&images[i], Some(&mask), &camera).unwrap();
        let m = match_descriptors(&q.descriptors, &descs, &MatchOptions::default());
        let b: Vec<Vector3<f64>> = m.iter().map(|x| q.keypoints[x.query].bearing).collect();
        let p: Vec<Vector3<f64>> = m.iter().map(|x| positions[x.train]).collect();
        let ro = RansacOptions {
            threshold_rad: 0.012,
            ..RansacOptions::default()
        };
        let pose = absolute_pose_ransac(&b, &p, &ro).expect("localized");
        let centre = sim.transform_point(&pose.cam_from_world.inverse().translation.vector);
        let e = (centre - truth[i].translation.vector).norm();
        eprintln!(
            "frame {i}: {} matches, {} inliers, position error {:.2} mm",
            m.len(),
            pose.num_inliers,
            e * 1e3
        );
        errors.push(e);
    }
    // At 320 px one pixel is ~10 mrad (~15 mm at 1.5 m): the 1 cm median / 5 cm worst
    // at 960 px are checked here at this coarser resolution as 1 cm median / 3 cm worst.
    errors.sort_by(f64::total_cmp);
    let median = errors[errors.len() / 2];
    let worst = errors[errors.len() - 1];
    assert!(
        median < 0.01 && worst < 0.03,
        "localization errors {errors:?} m"
    );
}

/// Observations of `points` from each pose: 0.5 mrad noise, 2 % gross outliers, rays to 95°.
/// Keyframe positions against the truth after the Sim(3) that aligns them.
fn keyframe_ate(recon: &Reconstruction, truth: &[Pose]) -> TrajectoryError {
    let est: Vec<Vector3<f64>> = recon
        .keyframes
        .iter()
        .map(|k| k.cam_from_world.inverse().translation.vector)
        .collect();
    let tru: Vec<Vector3<f64>> = recon
        .keyframes
        .iter()
        .map(|k| truth[k.frame as usize].translation.vector)
        .collect();
    align_and_measure(&est, &tru).unwrap().1
}

fn observe(truth: &[Pose], points: &[Vector3<f64>], rng: &mut ChaCha8Rng) -> Vec<MappingFrame> {
    let mut frames = Vec::new();
    for (i, world_from_cam) in truth.iter().enumerate() {
        let cam_from_world = world_from_cam.inverse();
        let mut observations = Vec::new();
        for (j, p) in points.iter().enumerate() {
            let b = (cam_from_world * Point3::from(*p)).coords.normalize();
            if b.z.acos() > MAX_OFF_AXIS {
                continue;
            }
            let bearing = if rng.random_range(0.0..1.0) < 0.02 {
                (b + random_unit(rng) * 0.1).normalize()
            } else {
                (b + random_unit(rng) * 0.0005 * rng.random_range(0.0..1.0)).normalize()
            };
            observations.push(TrackObservation {
                track: j as u64,
                bearing,
                pixel: nalgebra::Point2::origin(),
            });
        }
        frames.push(MappingFrame {
            frame: i as u32,
            t: i as f64 / 30.0,
            observations,
        });
    }
    frames
}

/// A long, slow sweep fed at 30 Hz, every frame (docs/vision.md: this used to make a keyframe
/// of nearly every frame): 15 s that start almost still (2 cm in the first 3 s, so frame 0 has
/// no partner with enough parallax for seconds) and end 0.5 m along the arc. The mapper must
/// initialize later, pose every frame, keep at most a few dozen keyframes and stay within the
/// 0.5 % ATE criterion.
#[test]
fn slow_sweep_at_30_hz_keeps_few_keyframes() {
    let mut rng = ChaCha8Rng::seed_from_u64(22);
    let points = room_points(&mut rng, 900);
    let n = 450;
    // Ease-in along the arc of `trajectory`: s = 0.25 u².
    let truth: Vec<Pose> = (0..n)
        .map(|i| {
            let u = i as f64 / n as f64;
            trajectory((0.25 * u * u * 100_000.0) as usize, 100_000)
        })
        .collect();
    let frames = observe(&truth, &points, &mut rng);
    let recon = reconstruct(&frames, &MapperOptions::default()).unwrap();
    let err = keyframe_ate(&recon, &truth);
    eprintln!(
        "slow sweep: {} keyframes (first at frame {}, second at {}), {} landmarks, {} of {n} \
         frames posed; keyframe ATE {:.2} mm rmse, extent {:.3} m, {:.4} % of extent",
        recon.keyframes.len(),
        recon.keyframes[0].frame,
        recon.keyframes[1].frame,
        recon.landmarks.len(),
        recon.frame_poses.len(),
        err.rmse * 1e3,
        err.extent,
        100.0 * err.relative_rmse()
    );
    assert_eq!(recon.lost_at, None);
    assert_eq!(recon.frame_poses.len(), n);
    assert!(recon.frame_poses.windows(2).all(|w| w[0].0 < w[1].0));
    // Synthetic tracks never die, so once the view is mapped only rotation and support make
    // keyframes: a handful here (real KLT tracks give ~20 on the 20 s rendered sweep).
    assert!(
        (3..=60).contains(&recon.keyframes.len()),
        "{} keyframes for {n} frames",
        recon.keyframes.len()
    );
    assert!(recon.keyframes.windows(2).all(|w| w[0].t < w[1].t));
    assert!(err.relative_rmse() < 0.005, "{err:?}");
}
