//! Relocalization in rooms and along paths the mapping did not take: simulator sessions of a
//! room kind (a mapping scan and a later query path), the map's alignment to the truth, and the
//! diagnosis of relocalization attempts against the truth (are the retrieved keyframes the
//! right ones; how many correct 2D-3D matches exist and how many matching finds).
#![allow(dead_code, clippy::unwrap_used)]

use std::path::{Path, PathBuf};

use kiwi_backend::vision::align::{Sim3, umeyama};
use kiwi_backend::vision::episode::LensStream;
use kiwi_backend::vision::features::{Descriptor, OrbExtractor};
use kiwi_backend::vision::localize::{Localizer, LocalizerOptions, RelocalizationTrace};
use kiwi_backend::vision::map::VisualMap;
use kiwi_core::camera::CameraModel;
use kiwi_core::geometry::Pose;
use kiwi_fixtures::scenario::Scenario;
use kiwi_fixtures::scene::{RoomKind, Scene, SceneOptions};
use kiwi_fixtures::session::{SessionOptions, write_session};
use nalgebra::{Matrix2, Point3, Quaternion, Translation3, UnitQuaternion, Vector3};

/// One simulated episode of a room: which scenario, how long, at what rate and brightness.
#[derive(Debug, Clone, Copy)]
pub struct Take {
    /// Motion.
    pub scenario: Scenario,
    /// Length (s).
    pub seconds: f64,
    /// Frame rate (Hz).
    pub fps: f64,
    /// Lighting gain.
    pub light_gain: f32,
}

/// Write a one-episode session of `room` (seed `seed`, `resolution` px, one lens `lens` as
/// `camera/lens`) into `root/name` unless it is there already; returns the episode folder.
pub fn room_session(
    root: &Path,
    name: &str,
    room: RoomKind,
    seed: u64,
    resolution: u32,
    lens: &str,
    take: Take,
) -> PathBuf {
    let out = root.join(name);
    let episode = out.join("episodes").join("ep000");
    if out.join("session.toml").is_file() {
        return episode;
    }
    let mut o = SessionOptions::new(&out);
    o.seed = seed;
    o.scenario = take.scenario;
    o.duration_s = take.seconds;
    o.resolution = resolution;
    o.rate_hz = take.fps;
    o.head = false;
    o.scene = SceneOptions {
        light_gain: take.light_gain,
        ..SceneOptions::room(room)
    };
    o.only_lenses = vec![lens.to_string()];
    // Diagnosis only: render without rolling shutter (global shutter) to separate its shear.
    if std::env::var("KIWI_RELOC_GLOBAL_SHUTTER").is_ok_and(|v| v == "1") {
        o.rolling_shutter = false;
    }
    write_session(&o).unwrap();
    episode
}

/// `(t, world_from_cam)` rows of a truth pose file.
pub fn truth_poses(episode: &Path, camera: &str, lens: &str) -> Vec<(f64, Pose)> {
    let text =
        std::fs::read_to_string(episode.join(format!("truth/{camera}/{lens}_poses.csv"))).unwrap();
    text.lines()
        .skip(1)
        .map(|l| {
            let v: Vec<f64> = l.split(',').map(|x| x.parse().unwrap()).collect();
            let q = UnitQuaternion::from_quaternion(Quaternion::new(v[8], v[5], v[6], v[7]));
            (
                v[0],
                Pose::from_parts(Translation3::new(v[2], v[3], v[4]), q),
            )
        })
        .collect()
}

/// The truth row nearest in time to `t`.
pub fn pose_at(rows: &[(f64, Pose)], t: f64) -> Pose {
    rows.iter()
        .min_by(|a, b| (a.0 - t).abs().total_cmp(&(b.0 - t).abs()))
        .map(|r| r.1)
        .unwrap()
}

/// The map's Sim(3) to the world, from its keyframe centres and the mapping truth.
pub struct Alignment {
    /// `world = s R map + t`.
    pub sim: Sim3,
}

impl Alignment {
    /// Align `map`'s keyframes to the mapping episode's truth.
    pub fn new(map: &VisualMap, mapping_truth: &[(f64, Pose)]) -> Self {
        let (est, tru): (Vec<Vector3<f64>>, Vec<Vector3<f64>>) = map
            .keyframes
            .iter()
            .map(|k| {
                (
                    keyframe_centre(k),
                    pose_at(mapping_truth, k.t).translation.vector,
                )
            })
            .unzip();
        Self {
            sim: umeyama(&est, &tru, true).unwrap(),
        }
    }

    /// A map point in the world.
    pub fn world_point(&self, p: &Vector3<f64>) -> Vector3<f64> {
        self.sim.transform_point(p)
    }

    /// A world camera pose as `cam_from_map` (map units).
    pub fn cam_from_map(&self, world_from_cam: &Pose) -> Pose {
        let r = self.sim.rotation.inverse() * world_from_cam.rotation;
        let c = self.sim.rotation.inverse()
            * (world_from_cam.translation.vector - self.sim.translation)
            / self.sim.scale;
        Pose::from_parts(Translation3::from(c), r).inverse()
    }

    /// A map pose `map_from_cam` in the world.
    pub fn world_from_cam(&self, map_from_cam: &Pose) -> Pose {
        Pose::from_parts(
            Translation3::from(self.world_point(&map_from_cam.translation.vector)),
            self.sim.rotation * map_from_cam.rotation,
        )
    }
}

/// A keyframe's camera centre in the map frame.
pub fn keyframe_centre(k: &kiwi_backend::vision::map::MapKeyframe) -> Vector3<f64> {
    k.cam_from_map
        .to_pose()
        .unwrap()
        .inverse()
        .translation
        .vector
}

/// Largest distance (px) between a query keypoint and a landmark's true projection for the pair
/// to count as a correct 2D-3D match (map error and keypoint noise at 320-960 px).
pub const CORRECT_MATCH_PX: f64 = 3.0;

/// A landmark is visible from a true pose when the room's first surface along the ray to it is
/// no nearer than this fraction of its distance (map error: a few mm to cm).
const VISIBLE_DEPTH_FRACTION: f64 = 0.97;

/// What one relocalization attempt saw, measured against the truth.
#[derive(Debug, Clone)]
pub struct AttemptDiagnosis {
    /// Frame index.
    pub frame: usize,
    /// Query keypoints.
    pub keypoints: usize,
    /// Query keypoints with a visible map landmark projecting within [`CORRECT_MATCH_PX`]
    /// under the true pose: the correct 2D-3D matches that exist in the whole map.
    pub correct_possible: usize,
    /// Distinct map landmarks visible from the true pose with a query keypoint within
    /// [`CORRECT_MATCH_PX`] of their projection: the most inliers a right pose can have (the
    /// overlap of the view with the map).
    pub landmarks_observable: usize,
    /// Descriptor distances of the correct matches that exist (per keypoint with a correct
    /// landmark: the Hamming distance to the nearest descriptor of that landmark, its
    /// representative or a keyframe view, and the rank of that landmark among all landmarks by
    /// the same distance, 0 = nearest): how many are within the matcher's distance limit, how
    /// many are the nearest landmark, how many among the nearest three; and the median distance
    /// of the correct landmark and of the nearest other one.
    pub correct_descriptors: DescriptorDiagnosis,
    /// The keyframe sharing the most visible landmarks with the query (the right candidate),
    /// its distance (m) and viewing angle (deg) to the query, and that count.
    pub best_keyframe: (usize, f64, f64, usize),
    /// Guided densification from the true pose: inliers and the position error (m) of the pose
    /// it fits (`None` when it fits none): the support a right hypothesis would reach.
    pub true_support: Option<(usize, f64)>,
    /// Per candidate tried: keyframe, distance (m), angle (deg), its rank by shared visible
    /// landmarks (0 = the best), matches found, correct among them, correct possible within its
    /// window's landmarks, inliers, estimate error (m, if any), rejection.
    pub candidates: Vec<CandidateDiagnosis>,
}

/// How the descriptors of the correct matches that exist compare with the rest of the map.
#[derive(Debug, Clone, Default)]
pub struct DescriptorDiagnosis {
    /// Of the keypoints with a correct landmark (`correct_possible`): those whose correct landmark is within the matcher's distance limit.
    pub within_limit: usize,
    /// ... those whose correct landmark is the nearest landmark.
    pub nearest: usize,
    /// ... those whose correct landmark is among the three nearest.
    pub top3: usize,
    /// Median distance to the correct landmark.
    pub median_correct: u32,
    /// Median distance to the nearest other landmark.
    pub median_other: u32,
    /// Keypoints with a landmark projection within reach when every projection is shifted by
    /// [`CHANCE_SHIFT_PX`]: how many of `correct_possible` proximity alone gives.
    pub by_chance: usize,
    /// Every correct pair's surface and viewing geometry with its descriptor distance.
    pub pairs: Vec<PairGeometry>,
}

/// One correct pair, against the truth: on what surface its landmark lies and how the query
/// sees it compared with the map's views.
#[derive(Debug, Clone)]
pub struct PairGeometry {
    /// The surface (room face or object face) the landmark lies on.
    pub surface: String,
    /// Angle (deg) at the landmark between the query's ray and the nearest observing
    /// keyframe's.
    pub angle_deg: f64,
    /// The query's distance to the landmark over that keyframe's (scale change).
    pub distance_ratio: f64,
    /// Pyramid level of the query keypoint.
    pub octave: i32,
    /// Hamming distance to the landmark's nearest descriptor.
    pub distance: u32,
    /// The same with the query keypoint also described on the simulated tilts
    /// ([`SIMULATED_TILTS`]): the least distance over its plain and warped descriptors.
    pub warped_distance: u32,
    /// A pair proximity alone gives (projections shifted by [`CHANCE_SHIFT_PX`]), not a
    /// correct one.
    pub by_chance: bool,
}

/// A short name of the surface a ray hit: a room face, or an object's face with the object's
/// size (so a table top, a carton and a cupboard can be told apart).
fn surface_label(scene: &Scene, hit: &kiwi_fixtures::scene::Hit) -> String {
    const FACES: [&str; 6] = ["-x", "+x", "-y", "+y", "-z", "+z"];
    let face = FACES.get(hit.face).copied().unwrap_or("?");
    match hit.object {
        None => match hit.face {
            4 => "floor".into(),
            5 => "ceiling".into(),
            _ => format!("wall {face}"),
        },
        Some(i) => scene
            .boxes
            .get(i)
            .map_or(format!("object {i} {face}"), |b| {
                format!(
                    "object {i} ({:.2}x{:.2}x{:.2} m) {face}",
                    b.max[0] - b.min[0],
                    b.max[1] - b.min[1],
                    b.max[2] - b.min[2]
                )
            }),
    }
}

/// Tilts (ratio of the axes) of the views simulated on the query's patches: about 45° and 60°
/// of viewing-direction change on a surface seen face-on.
const SIMULATED_TILTS: [f64; 2] = [std::f64::consts::SQRT_2, 2.0];

/// Directions of tilt simulated per tilt (evenly over a half turn).
const SIMULATED_DIRECTIONS: usize = 4;

/// Height above the floor (m) within which a landmark counts as on it (map error).
const FLOOR_BAND_M: f64 = 0.02;

/// Shift of the projections (px, both axes) for the chance count of correct pairs: far beyond
/// the reach of a correct pair, near enough to keep the same keypoint density.
const CHANCE_SHIFT_PX: f64 = 15.0;

/// One candidate of an attempt, against the truth.
#[derive(Debug, Clone)]
pub struct CandidateDiagnosis {
    /// Keyframe.
    pub keyframe: usize,
    /// Distance of its centre to the query's true centre (m).
    pub distance_m: f64,
    /// Angle between its optical axis and the query's (deg).
    pub angle_deg: f64,
    /// Rank among keyframes by shared visible landmarks (0 = most).
    pub overlap_rank: usize,
    /// Descriptor matches.
    pub matches: usize,
    /// Matches whose landmark projects within [`CORRECT_MATCH_PX`] of the keypoint.
    pub correct: usize,
    /// Inliers of its estimate.
    pub inliers: usize,
    /// Position error of its estimate (m), if any.
    pub error_m: Option<f64>,
    /// Share of its inliers' landmarks on their dominant plane (the localizer's figure).
    pub plane_share: f64,
    /// Share of its inliers' landmarks on the floor (within [`FLOOR_BAND_M`] of it, truth).
    pub floor_share: f64,
    /// The map's strongest translational copy of its inliers (world shift, m; inlier landmarks
    /// with a look-alike there).
    pub repeated_shift: Option<(Vector3<f64>, usize)>,
    /// Inlier landmarks, and of those the ones in some copy.
    pub repeated: (usize, usize),
    /// Truth centre minus the estimate's centre (world, m).
    pub offset: Option<Vector3<f64>>,
    /// Empty when accepted.
    pub rejection: String,
}

/// Diagnose a relocalization attempt on `frame` of `stream` against the truth.
pub fn diagnose_attempt(
    map: &VisualMap,
    stream: &LensStream,
    alignment: &Alignment,
    query_truth: &[(f64, Pose)],
    scene: &Scene,
    frame: usize,
    options: &LocalizerOptions,
) -> AttemptDiagnosis {
    let mut localizer = Localizer::new(
        map,
        &stream.lens,
        stream.camera.clone(),
        stream.mask.clone(),
        *options,
    )
    .unwrap();
    let image = stream.load(frame).unwrap();
    let trace: RelocalizationTrace = localizer
        .trace_relocalization(frame as u32, &image)
        .unwrap();
    let world_from_cam = pose_at(query_truth, stream.frames[frame].t);
    let cam_from_map = alignment.cam_from_map(&world_from_cam);
    let camera = &stream.camera;
    // Visible landmarks and their true projections.
    let origin = world_from_cam.translation.vector;
    let surfaces: Vec<Option<kiwi_fixtures::scene::Hit>> = map
        .landmarks
        .iter()
        .map(|l| {
            let p = Vector3::from(l.position);
            let pc = cam_from_map * Point3::from(p);
            let px = camera.project(&pc.coords)?;
            if !camera.in_image(&px) || pc.coords.normalize().z < (0.5 * camera.valid_fov()).cos() {
                return None;
            }
            let w = alignment.world_point(&p);
            let d = w - origin;
            let dist = d.norm();
            let dir = d / dist;
            let hit = scene.intersect(
                [origin.x as f32, origin.y as f32, origin.z as f32],
                [dir.x as f32, dir.y as f32, dir.z as f32],
            );
            (f64::from(hit.distance) >= VISIBLE_DEPTH_FRACTION * dist).then_some(hit)
        })
        .collect();
    let projections: Vec<Option<nalgebra::Point2<f64>>> = map
        .landmarks
        .iter()
        .zip(&surfaces)
        .map(|(l, hit)| {
            hit.as_ref()?;
            camera.project(&(cam_from_map * Point3::from(Vector3::from(l.position))).coords)
        })
        .collect();
    let kps = &trace.features.keypoints;
    let correct_for = |kp: usize, l: u32| -> bool {
        projections[l as usize].is_some_and(|p| (p - kps[kp].pixel).norm() <= CORRECT_MATCH_PX)
    };
    // Per keypoint, the visible landmark projecting nearest to it within reach (shifted by
    // `shift`): with no shift, its correct landmark.
    let nearest_within = |kp: &nalgebra::Point2<f64>, shift: nalgebra::Vector2<f64>| {
        projections
            .iter()
            .enumerate()
            .filter_map(|(l, p)| p.map(|p| ((p + shift - kp).norm(), l)))
            .filter(|(d, _)| *d <= CORRECT_MATCH_PX)
            .min_by(|a, b| a.0.total_cmp(&b.0))
            .map(|(_, l)| l)
    };
    let right: Vec<Option<usize>> = kps
        .iter()
        .map(|kp| nearest_within(&kp.pixel, nalgebra::Vector2::zeros()))
        .collect();
    // Correct matches possible: keypoints with a visible landmark projection within reach.
    let correct_possible = right.iter().flatten().count();
    // Descriptor distances of the correct pairs: every landmark's descriptors (representative
    // and keyframe views).
    let mut views: Vec<Vec<Descriptor>> =
        map.landmarks.iter().map(|l| vec![l.descriptor]).collect();
    // Per landmark, the map-frame centres of the keyframes that observe it.
    let mut observers: Vec<Vec<Vector3<f64>>> = vec![Vec::new(); map.landmarks.len()];
    for kf in &map.keyframes {
        let centre = keyframe_centre(kf);
        for f in &kf.features {
            if let Some(v) = f.landmark.and_then(|l| views.get_mut(l as usize)) {
                v.push(f.descriptor);
            }
            if let Some(o) = f.landmark.and_then(|l| observers.get_mut(l as usize)) {
                o.push(centre);
            }
        }
    }
    let query_centre = cam_from_map.inverse().translation.vector;
    // The query's keypoints described again on patches warped as views tilted against them
    // would see them (ASIFT-style simulated tilts), to measure what simulating the view
    // change would recover.
    let mut extractor = OrbExtractor::new(&options.orb).unwrap();
    let mut warped: Vec<Vec<Option<Descriptor>>> = Vec::new();
    // `KIWI_RELOC_ROTATED_VARIANTS=1`: as many variants, each the plain patch turned by a few
    // degrees instead of tilted (separates what the tilts model from a retry of the
    // orientation and sampling).
    let rotated = std::env::var("KIWI_RELOC_ROTATED_VARIANTS").is_ok_and(|v| v == "1");
    for (t, tilt) in SIMULATED_TILTS.iter().enumerate() {
        for k in 0..SIMULATED_DIRECTIONS {
            let phi = std::f64::consts::PI * k as f64 / SIMULATED_DIRECTIONS as f64;
            let r = nalgebra::Rotation2::new(phi).into_inner();
            let shape = if rotated {
                let i = (t * SIMULATED_DIRECTIONS + k) as f64;
                let degrees = 7.5 * (1.0 + (i / 2.0).floor()) * if k % 2 == 0 { 1.0 } else { -1.0 };
                nalgebra::Rotation2::new(degrees.to_radians()).into_inner()
            } else {
                r * Matrix2::new(tilt.sqrt(), 0.0, 0.0, 1.0 / tilt.sqrt()) * r.transpose()
            };
            if let Some(d) = extractor
                .describe_warped(&image, camera, kps, shape)
                .unwrap()
            {
                warped.push(d);
            }
        }
    }
    let warped_distance = |kp: usize, l: usize| {
        warped
            .iter()
            .filter_map(|w| w[kp].as_ref())
            .flat_map(|q| views[l].iter().map(|d| d.distance(q)))
            .min()
            .unwrap_or(u32::MAX)
    };
    // A pair's geometry: the observing keyframe whose ray to the landmark is nearest the
    // query's, that angle and the distance ratio (query over keyframe), and the surface.
    let pair_geometry = |kp: usize, l: usize, distance: u32, by_chance: bool| {
        let position = Vector3::from(map.landmarks[l].position);
        let to_query = query_centre - position;
        let (angle_deg, distance_ratio) = observers[l]
            .iter()
            .map(|c| {
                let to_kf = c - position;
                (
                    to_kf.angle(&to_query).to_degrees(),
                    to_query.norm() / to_kf.norm().max(1e-9),
                )
            })
            .min_by(|a, b| a.0.total_cmp(&b.0))
            .unwrap_or((f64::NAN, f64::NAN));
        PairGeometry {
            surface: surfaces[l]
                .as_ref()
                .map_or(String::new(), |h| surface_label(scene, h)),
            angle_deg,
            distance_ratio,
            octave: kps[kp].octave,
            distance,
            warped_distance: distance.min(warped_distance(kp, l)),
            by_chance,
        }
    };
    let limit = options.matching.max_distance;
    let mut diag = DescriptorDiagnosis::default();
    let (mut dc, mut dother) = (Vec::new(), Vec::new());
    for (i, right) in right.iter().enumerate() {
        let Some(right) = *right else {
            continue;
        };
        let q = &trace.features.descriptors[i];
        let dist: Vec<u32> = views
            .iter()
            .map(|v| v.iter().map(|d| d.distance(q)).min().unwrap_or(u32::MAX))
            .collect();
        let d_right = dist[right];
        // Landmarks nearer than the right one, and the nearest other.
        let (mut rank, mut other) = (0, u32::MAX);
        for (_, &d) in dist.iter().enumerate().filter(|&(l, _)| l != right) {
            rank += usize::from(d < d_right);
            other = other.min(d);
        }
        diag.pairs.push(pair_geometry(i, right, d_right, false));
        diag.within_limit += usize::from(d_right <= limit);
        diag.nearest += usize::from(rank == 0);
        diag.top3 += usize::from(rank < 3);
        dc.push(d_right);
        dother.push(other);
    }
    let shift = nalgebra::Vector2::new(CHANCE_SHIFT_PX, CHANCE_SHIFT_PX);
    // The pairs proximity alone gives (projections shifted), with their descriptor distance:
    // the baseline the correct pairs' figures are read against.
    for (i, kp) in kps.iter().enumerate() {
        if let Some(l) = nearest_within(&kp.pixel, shift) {
            let q = &trace.features.descriptors[i];
            let d = views[l]
                .iter()
                .map(|d| d.distance(q))
                .min()
                .unwrap_or(u32::MAX);
            diag.pairs.push(pair_geometry(i, l, d, true));
            diag.by_chance += 1;
        }
    }
    dc.sort_unstable();
    dother.sort_unstable();
    diag.median_correct = dc.get(dc.len() / 2).copied().unwrap_or(0);
    diag.median_other = dother.get(dother.len() / 2).copied().unwrap_or(0);
    let landmarks_observable = projections
        .iter()
        .flatten()
        .filter(|p| {
            kps.iter()
                .any(|kp| (*p - kp.pixel).norm() <= CORRECT_MATCH_PX)
        })
        .count();
    // Keyframes by shared visible landmarks.
    let mut overlap: Vec<(usize, usize)> = map
        .keyframes
        .iter()
        .enumerate()
        .map(|(k, kf)| {
            let mut ls: Vec<u32> = kf.features.iter().filter_map(|f| f.landmark).collect();
            ls.sort_unstable();
            ls.dedup();
            (
                ls.iter()
                    .filter(|&&l| projections[l as usize].is_some())
                    .count(),
                k,
            )
        })
        .collect();
    overlap.sort_by(|a, b| b.0.cmp(&a.0).then(a.1.cmp(&b.1)));
    let rank_of = |k: usize| overlap.iter().position(|o| o.1 == k).unwrap_or(usize::MAX);
    let geometry = |k: usize| -> (f64, f64) {
        let kf =
            alignment.world_from_cam(&map.keyframes[k].cam_from_map.to_pose().unwrap().inverse());
        let d = (kf.translation.vector - origin).norm();
        let a = (kf.rotation * Vector3::z())
            .angle(&(world_from_cam.rotation * Vector3::z()))
            .to_degrees();
        (d, a)
    };
    let best = overlap[0];
    let (bd, ba) = geometry(best.1);
    let candidates = trace
        .candidates
        .iter()
        .map(|c| {
            let (d, a) = geometry(c.keyframe);
            CandidateDiagnosis {
                keyframe: c.keyframe,
                distance_m: d,
                angle_deg: a,
                overlap_rank: rank_of(c.keyframe),
                matches: c.matches.len(),
                correct: c
                    .matches
                    .iter()
                    .filter(|(q, l)| correct_for(*q, *l))
                    .count(),
                inliers: c.inliers,
                error_m: c.cam_from_map.map(|p| {
                    (alignment.world_from_cam(&p.inverse()).translation.vector - origin).norm()
                }),
                plane_share: c.plane_share,
                repeated: (c.repeated.landmarks, c.repeated.repeated),
                repeated_shift: c
                    .repeated
                    .strongest
                    .map(|(d, k)| (alignment.sim.rotation * d * alignment.sim.scale, k)),
                offset: c
                    .cam_from_map
                    .map(|p| origin - alignment.world_from_cam(&p.inverse()).translation.vector),
                floor_share: c
                    .inlier_landmarks
                    .iter()
                    .filter(|&&l| {
                        let w = alignment
                            .world_point(&Vector3::from(map.landmarks[l as usize].position));
                        w.z.abs() <= FLOOR_BAND_M
                    })
                    .count() as f64
                    / c.inlier_landmarks.len().max(1) as f64,
                rejection: c.rejection.clone(),
            }
        })
        .collect();
    let true_support = localizer
        .support_at(frame as u32, &trace.features, &cam_from_map)
        .map(|(n, p)| {
            (
                n,
                (alignment.world_from_cam(&p.inverse()).translation.vector - origin).norm(),
            )
        });
    AttemptDiagnosis {
        true_support,
        frame,
        keypoints: kps.len(),
        correct_possible,
        landmarks_observable,
        correct_descriptors: diag,
        best_keyframe: (best.1, bd, ba, best.0),
        candidates,
    }
}

/// One line per attempt.
pub fn describe_attempt(d: &AttemptDiagnosis) -> String {
    let mut s = format!(
        "frame {}: {} keypoints, {} correct matches exist ({} landmarks observable); best keyframe {} ({:.2} m, {:.0}°, {} shared)",
        d.frame,
        d.keypoints,
        d.correct_possible,
        d.landmarks_observable,
        d.best_keyframe.0,
        d.best_keyframe.1,
        d.best_keyframe.2,
        d.best_keyframe.3
    );
    let c = &d.correct_descriptors;
    s.push_str(&format!(
        "\n    correct pairs' descriptors: {} pairs ({} by proximity alone), {} within the limit, {} nearest, {} among the nearest 3; median distance {} (nearest other landmark {})",
        d.correct_possible, c.by_chance, c.within_limit, c.nearest, c.top3, c.median_correct, c.median_other
    ));
    s.push_str(&describe_pairs(&c.pairs));
    s.push_str(&match d.true_support {
        Some((n, e)) => {
            format!("\n    guided densification from the true pose: {n} inliers, error {e:.3} m")
        }
        None => "\n    guided densification from the true pose: no pose".to_string(),
    });
    for c in &d.candidates {
        s.push_str(&format!(
            "\n    kf {} ({:.2} m, {:.0}°, overlap rank {}): {} matches, {} correct, {} inliers ({:.0} % on one plane, {:.0} % on the floor), error {}, {}",
            c.keyframe,
            c.distance_m,
            c.angle_deg,
            c.overlap_rank,
            c.matches,
            c.correct,
            c.inliers,
            100.0 * c.plane_share,
            100.0 * c.floor_share,
            c.error_m.map_or("-".into(), |e| format!("{e:.3} m")),
            if c.rejection.is_empty() { "accepted" } else { &c.rejection }
        ));
        if let Some((d, k)) = c.repeated_shift {
            s.push_str(&format!(
                "; {} of {} inlier landmarks repeated, strongest copy at ({:.2}, {:.2}, {:.2}) m for {k}",
                c.repeated.1, c.repeated.0, d.x, d.y, d.z
            ));
        }
        if let Some(o) = c.offset {
            s.push_str(&format!(
                "; truth at ({:.2}, {:.2}, {:.2}) m",
                o.x, o.y, o.z
            ));
        }
    }
    s
}

/// Correct pairs grouped by surface, by viewing angle and by scale change: count and median
/// descriptor distance per group, beside the same for the pairs proximity alone gives.
pub fn describe_pairs(pairs: &[PairGeometry]) -> String {
    fn group(
        out: &mut String,
        title: &str,
        pairs: &[PairGeometry],
        key: impl Fn(&PairGeometry) -> String,
    ) {
        type Group = (Vec<u32>, Vec<u32>, Vec<u32>, Vec<u32>);
        let mut groups: std::collections::BTreeMap<String, Group> = Default::default();
        for p in pairs {
            let g = groups.entry(key(p)).or_default();
            if p.by_chance {
                g.1.push(p.distance);
                g.3.push(p.warped_distance);
            } else {
                g.0.push(p.distance);
                g.2.push(p.warped_distance);
            }
        }
        let mut rows: Vec<(String, Group)> = groups.into_iter().collect();
        rows.sort_by(|a, b| (b.1).0.len().cmp(&(a.1).0.len()).then(a.0.cmp(&b.0)));
        let median = |d: &mut Vec<u32>| {
            d.sort_unstable();
            d.get(d.len() / 2).map_or("-".to_string(), u32::to_string)
        };
        out.push_str(&format!("\n    by {title}:"));
        let within = |d: &[u32]| d.iter().filter(|&&x| x <= WITHIN_BITS).count();
        for (k, (mut d, mut c, mut dw, mut cw)) in rows.into_iter().take(8) {
            out.push_str(&format!(
                " [{k}: {} pairs, median {} / tilted {}, {} / {} within {WITHIN_BITS}; by chance {}, median {} / {}, {} / {} within]",
                d.len(),
                median(&mut d),
                median(&mut dw),
                within(&d),
                within(&dw),
                c.len(),
                median(&mut c),
                median(&mut cw),
                within(&c),
                within(&cw),
            ));
        }
    }
    /// The matcher's default distance limit (bits of 256).
    const WITHIN_BITS: u32 = 64;
    let mut s = String::new();
    group(&mut s, "surface", pairs, |p| p.surface.clone());
    group(&mut s, "angle to the nearest view", pairs, |p| {
        format!(
            "{:>2}-{:>2} deg",
            15 * (p.angle_deg / 15.0).floor() as i64,
            15 * ((p.angle_deg / 15.0).floor() as i64 + 1)
        )
    });
    group(&mut s, "distance ratio (query / that view)", pairs, |p| {
        let r = p.distance_ratio;
        if r < 0.5 {
            "< 0.5".into()
        } else if r < 0.8 {
            "0.5-0.8".into()
        } else if r <= 1.25 {
            "0.8-1.25".into()
        } else if r <= 2.0 {
            "1.25-2".into()
        } else {
            "> 2".into()
        }
    });
    group(&mut s, "query octave", pairs, |p| {
        format!("octave {}", p.octave)
    });
    s
}
