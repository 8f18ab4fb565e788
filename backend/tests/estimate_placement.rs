#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]
//! Placement acceptance on a simulated mapping episode: `scene_from_front_map` within 1 mm /
//! 0.05° of the truth despite noisy localizations and 10 % failed relocalizations, and on the
//! right pairs when most are at a look-alike place.

use kiwi_backend::placement::{Placement, PlacementConfig, PlacementPair, place};
use kiwi_core::geometry::{Pose, rotation_angle_between, se3_exp};
use kiwi_fixtures::rng::{SimRng, normal, stream, uniform};
use kiwi_fixtures::scenario::{Scenario, episode_motion};
use kiwi_fixtures::unit::{LensModel, SimUnit};
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector6};

/// A 40 s simulated mapping episode of unit `seed`'s left wrist, localized every 0.1 s in an
/// arbitrary rigid front map and in the scene (2 mm / 2 mrad noise on each pose);
/// `spoil(k, t, front, rear, rng)` makes pair `k` wrong. The placement fitted to the pairs, and
/// its distance from the truth (m, rad).
fn placement_of(
    seed: u64,
    front_map_from_scene: Pose,
    mut spoil: impl FnMut(usize, f64, &mut Pose, &mut Pose, &mut SimRng),
) -> (Placement, f64, f64) {
    let motion = episode_motion(Scenario::Mapping, seed, 0, 40.0);
    let unit = SimUnit::x5("PLACE", seed, 96, LensModel::Kb4).unwrap();
    let front_from_imu = unit.lens("front").unwrap().cam_from_imu;
    let rear_from_imu = unit.lens("rear").unwrap().cam_from_imu;
    let rear_from_front = rear_from_imu * front_from_imu.inverse();
    let mut rng = stream(seed, "placement");
    let mut pairs = Vec::new();
    for k in 0..400 {
        let t = k as f64 * 0.1;
        let scene_from_imu = motion.left.pose(t);
        let noisy = |pose: Pose, rng: &mut SimRng| {
            let xi = Vector6::from_fn(|_, _| normal(rng, 2e-3));
            pose * se3_exp(&xi)
        };
        let mut front = noisy(
            front_map_from_scene * scene_from_imu * front_from_imu.inverse(),
            &mut rng,
        );
        let mut rear = noisy(scene_from_imu * rear_from_imu.inverse(), &mut rng);
        spoil(k, t, &mut front, &mut rear, &mut rng);
        pairs.push(PlacementPair {
            t,
            front_map_from_front: front,
            scene_from_rear: rear,
        });
    }
    let p = place(&pairs, &rear_from_front, &PlacementConfig::default()).unwrap();
    let truth = front_map_from_scene.inverse();
    let dp = (p.scene_from_front_map.translation.vector - truth.translation.vector).norm();
    let dr = rotation_angle_between(&p.scene_from_front_map.rotation, &truth.rotation);
    eprintln!(
        "placement: {:.3} mm, {:.4} deg from truth; {} of {} inliers, RMS {:.2} mm / {:.3} deg",
        dp * 1e3,
        dr.to_degrees(),
        p.inliers,
        p.pairs,
        p.rms_position_m * 1e3,
        p.rms_rotation_rad.to_degrees()
    );
    (p, dp, dr)
}

#[test]
fn placement_recovers_scene_from_front_map() {
    // The front map is an arbitrary rigid frame (metric after metric recovery).
    let front_map_from_scene: Pose = Isometry3::from_parts(
        Translation3::new(0.7, -1.3, 0.4),
        UnitQuaternion::from_euler_angles(0.3, -0.2, 1.1),
    );
    let (p, dp, dr) = placement_of(6, front_map_from_scene, |_, _, front, _, rng| {
        if uniform(rng, 0.0, 1.0) < 0.1 {
            // A failed relocalization: off by decimetres and degrees.
            *front *= se3_exp(&Vector6::new(0.1, -0.05, 0.08, 0.3, -0.2, 0.25));
        }
    });
    assert!(dp < 1e-3, "position {dp}");
    assert!(dr < 0.05f64.to_radians(), "rotation {dr}");
    assert!(p.inliers >= 340 && p.inliers <= 370);
}

/// The rear lens relocalizes at a look-alike place a third of the way in and tracks it to the
/// end (0.4 m off, its offset wandering by ±5 cm as tracking at the wrong place drifts): most
/// pairs are wrong, but fewer of them agree with any one placement than the right third does.
/// The placement rests on the largest group that agrees (a fit started from the median would
/// settle among the wrong pairs).
#[test]
fn placement_rests_on_the_largest_group_of_pairs_that_agree() {
    let front_map_from_scene: Pose = Isometry3::from_parts(
        Translation3::new(-0.4, 0.9, 0.2),
        UnitQuaternion::from_euler_angles(-0.1, 0.4, -0.7),
    );
    let (p, dp, dr) = placement_of(7, front_map_from_scene, |k, t, _, rear, _| {
        if k >= 140 {
            let wander = 0.05 * (t * 0.7).sin();
            let look_alike = Isometry3::translation(0.4 + wander, 0.05 * (t * 0.3).cos(), 0.0);
            *rear = look_alike * *rear;
        }
    });
    assert!(dp < 2e-3, "position {dp}");
    assert!(dr < 0.1f64.to_radians(), "rotation {dr}");
    assert!(p.inliers >= 130 && p.inliers <= 150, "{}", p.inliers);
}

/// The wrist that did not build the rear map: its rear stream saw only the first 15 s, in a
/// part of the scene map 4 cm off (a distorted stretch of map), so the rear pairs alone put
/// the front map 4 cm off. Its front lens seen in the other wrist's front map (an unscaled map
/// with its own metric similarity and placement, 2 mm noise) over the whole episode pools 400
/// pairs more into the one fit, which then lands within millimetres of the truth.
#[test]
fn the_other_wrists_front_map_outvotes_a_rear_stream_on_a_distorted_map() {
    use kiwi_backend::formats::calibration::LensImuCalibration;
    use kiwi_backend::formats::results::{FrontWitness, apply, placement_from_localizations};
    use kiwi_backend::formats::tables::Localization;
    use kiwi_backend::vision::align::Sim3;
    use nalgebra::Vector3;

    let seed = 8;
    let motion = episode_motion(Scenario::Mapping, seed, 0, 40.0);
    let unit = SimUnit::x5("PLACE", seed, 96, LensModel::Kb4).unwrap();
    let calibration = |lens: &str| LensImuCalibration {
        cam_from_imu: unit.lens(lens).unwrap().cam_from_imu,
        time_shift_s: 0.0,
        imu_noise: None,
    };
    let (front_cal, rear_cal) = (calibration("front"), calibration("rear"));
    let scene_from_front_map: Pose = Isometry3::from_parts(
        Translation3::new(0.7, -1.3, 0.4),
        UnitQuaternion::from_euler_angles(0.3, -0.2, 1.1),
    );
    let other_sim = Sim3 {
        scale: 0.25,
        rotation: UnitQuaternion::from_euler_angles(-0.4, 0.1, 0.6),
        translation: Vector3::new(0.3, 0.2, -0.1),
    };
    let scene_from_other_map: Pose = Isometry3::from_parts(
        Translation3::new(-0.5, 0.8, 0.1),
        UnitQuaternion::from_euler_angles(0.05, 0.1, -0.9),
    );
    let mut rng = stream(seed, "witness placement");
    let mut noisy = |pose: Pose| pose * se3_exp(&Vector6::from_fn(|_, _| normal(&mut rng, 2e-3)));
    let row = |t: f64, valid: bool, map_from_cam: Pose| Localization {
        t,
        valid,
        map_from_cam,
    };
    let (mut front, mut rear, mut witness) = (Vec::new(), Vec::new(), Vec::new());
    for k in 0..400 {
        let t = k as f64 * 0.1;
        let scene_from_imu = motion.left.pose(t);
        let scene_from_front = scene_from_imu * front_cal.cam_from_imu.inverse();
        front.push(row(
            t,
            true,
            noisy(scene_from_front_map.inverse() * scene_from_front),
        ));
        let off_map = Isometry3::translation(0.04, 0.0, 0.0);
        let scene_from_rear = off_map * scene_from_imu * rear_cal.cam_from_imu.inverse();
        rear.push(row(t, t < 15.0, noisy(scene_from_rear)));
        let metric_from_front = scene_from_other_map.inverse() * scene_from_front;
        witness.push(row(
            t,
            true,
            apply(&other_sim.inverse(), &noisy(metric_from_front)),
        ));
    }
    let error = |file: &kiwi_backend::formats::results::PlacementFile| {
        let g = file.scene_from_front_map.translation_m;
        (Vector3::from(g) - scene_from_front_map.translation.vector).norm()
    };
    let identity = Sim3::identity();
    let config = PlacementConfig::default();
    let alone = placement_from_localizations(
        &front, &rear, &front_cal, &rear_cal, &identity, &identity, None, &config,
    )
    .unwrap();
    let pooled = placement_from_localizations(
        &front,
        &rear,
        &front_cal,
        &rear_cal,
        &identity,
        &identity,
        Some(FrontWitness {
            rows: &witness,
            other_front_sim: other_sim,
            scene_from_other_front_map: scene_from_other_map,
        }),
        &config,
    )
    .unwrap();
    eprintln!(
        "rear alone {:.1} mm off ({} pairs); pooled {:.2} mm off ({} of {} pairs inliers, {} \
         from the witness)",
        1e3 * error(&alone),
        alone.pairs,
        1e3 * error(&pooled),
        pooled.inliers,
        pooled.pairs,
        pooled.witness_pairs
    );
    assert!(error(&alone) > 0.03, "{}", error(&alone));
    assert!(error(&pooled) < 3e-3, "{}", error(&pooled));
    assert_eq!((pooled.pairs, pooled.witness_pairs), (550, 400));
}
