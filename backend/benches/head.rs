//! Head-pose cost: seconds of hat-marker work (finding it in a rear frame, refining its corners,
//! IPPE) per minute of recording, for the two wrists' rear streams at 29.97 Hz, on simulator
//! renders at `KIWI_BENCH_RESOLUTION` px (default 960): frames with the marker at 0.4-0.7 m and
//! frames without it.

#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use std::sync::Arc;
use std::time::Instant;

use nalgebra::{Rotation3, Translation3, UnitQuaternion, Vector3};

use kiwi_backend::frames::ColorImage;
use kiwi_backend::head::marker::{MarkerFinder, resolve, square_poses};
use kiwi_core::geometry::Pose;
use kiwi_fixtures::markers::{aruco_texture, aruco_texture_side};
use kiwi_fixtures::render::{Extras, LensRays, RenderOptions, Rigid32, WorldQuad, render};
use kiwi_fixtures::scene::{Scene, SceneOptions};
use kiwi_fixtures::unit::{LensModel, SimUnit};

const FRAMES: usize = 40;

fn main() {
    let size = std::env::var("KIWI_BENCH_RESOLUTION")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(960u32);
    let unit = SimUnit::x5("B", 3, size, LensModel::Kb4).unwrap();
    let camera = unit.lenses[1].camera.clone();
    let rays = LensRays::new(&camera);
    let scene = Scene::new(2, SceneOptions::default());
    let texture = Arc::new(aruco_texture(3, 0.08, 0.0004).unwrap());
    let side = aruco_texture_side(0.08);
    // The room around the lens, so the detector sees clutter as in a real frame.
    let world_from_cam = Pose::from_parts(
        Translation3::new(2.0, 2.0, 1.2),
        UnitQuaternion::from_scaled_axis(Vector3::new(1.4, 0.0, 0.0)),
    );
    let frames: Vec<(bool, image::RgbImage)> = (0..FRAMES)
        .map(|k| {
            let with_marker = k % 2 == 0;
            let theta = 0.1 + 0.05 * k as f64;
            let b = kiwi_core::camera::bearing_from_angles(theta, 0.7 * k as f64).into_inner();
            let z = -b;
            let x = if z.x.abs() < 0.9 {
                Vector3::x()
            } else {
                Vector3::y()
            }
            .cross(&z)
            .normalize();
            let r = Rotation3::from_matrix_unchecked(nalgebra::Matrix3::from_columns(&[
                x,
                z.cross(&x),
                z,
            ])) * Rotation3::from_axis_angle(&Vector3::x_axis(), 0.4);
            let cam_from_marker = Pose::from_parts(
                Translation3::from(b * (0.4 + 0.3 * (k % 5) as f64 / 4.0)),
                r.into(),
            );
            let corner = Pose::from_parts(
                Translation3::new(-side / 2.0, -side / 2.0, 0.0),
                UnitQuaternion::identity(),
            );
            let extras = Extras {
                quads: if with_marker {
                    vec![WorldQuad {
                        world_from_quad: Rigid32::from_pose(
                            &(world_from_cam * cam_from_marker * corner),
                        ),
                        width: side as f32,
                        height: side as f32,
                        texture: Arc::clone(&texture),
                    }]
                } else {
                    Vec::new()
                },
                ..Extras::default()
            };
            let options = RenderOptions {
                noise_key: k as u64,
                ..RenderOptions::default()
            };
            let img = render(
                &scene,
                &rays,
                &|_t: f64| world_from_cam,
                0.0,
                &extras,
                &options,
            );
            (with_marker, img)
        })
        .collect();
    let finder = MarkerFinder::new(camera, "4x4_50", 3).unwrap();
    let mut timings = [(0.0f64, 0usize, 0usize); 2];
    for (with_marker, img) in &frames {
        let frame = ColorImage::from_rgb(img.width() as usize, img.height() as usize, img.as_raw())
            .unwrap();
        let t = Instant::now();
        let posed = finder
            .find(&frame)
            .unwrap()
            .and_then(|c| square_poses(&c, 0.08).unwrap())
            .is_some_and(|p| resolve(&p, None).pose().is_some());
        let s = t.elapsed().as_secs_f64();
        let slot = &mut timings[usize::from(*with_marker)];
        slot.0 += s;
        slot.1 += 1;
        slot.2 += usize::from(posed);
    }
    let per_minute = |ms: f64| ms * 1e-3 * 29.97 * 60.0 * 2.0;
    for (name, (s, n, posed)) in ["without the marker", "with the marker"]
        .iter()
        .zip(timings)
    {
        let ms = 1e3 * s / n.max(1) as f64;
        println!(
            "{size} px, {name:>18}: {ms:6.1} ms per rear frame ({posed} of {n} posed) = {:6.1} s \
             per minute of recording (two rear streams at 29.97 Hz, one thread)",
            per_minute(ms)
        );
    }
}
