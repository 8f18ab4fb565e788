//! Shared helpers of the intrinsics tests: simulator captures, truth corners, noise.
#![allow(dead_code)]

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use kiwi_calib::detect::{Corner, CornerSet, ImageCorners};
use kiwi_calib::target::AprilGridTarget;
use kiwi_core::artifact::UnitCalibration;
use kiwi_core::camera::{Camera, CameraModel};
use kiwi_fixtures::captures::{IntrinsicsDesign, UnitCaptureOptions, write_unit_captures};
use kiwi_fixtures::unit::LensModel;

/// A unit capture with only the intrinsics views, of Kalibr's board (the detector tests).
pub fn capture(dir: &Path, model: LensModel, views: usize, resolution: u32, seed: u64) -> PathBuf {
    capture_with(
        dir,
        model,
        views,
        resolution,
        seed,
        IntrinsicsDesign::kalibr(),
    )
}

/// A unit capture with only the intrinsics views, in a given capture design.
pub fn capture_with(
    dir: &Path,
    model: LensModel,
    views: usize,
    resolution: u32,
    seed: u64,
    design: IntrinsicsDesign,
) -> PathBuf {
    let out = dir.join(format!(
        "unit-{model:?}-{views}-{resolution}-{seed}-{}x{}",
        design.grid.cols, design.grid.rows
    ));
    let mut o = UnitCaptureOptions::new(&out, "X5-IT");
    o.intrinsics_design = design;
    o.seed = seed;
    o.resolution = resolution;
    o.lens_model = model;
    o.views = views;
    o.cam_imu_duration_s = 0.0;
    o.static_duration_s = 0.0;
    o.bench_duration_s = 0.0;
    o.rig_duration_s = 0.0;
    write_unit_captures(&o).unwrap();
    out
}

/// The unit's exact camera for a lens.
pub fn truth_camera(capture: &Path, lens: &str) -> Camera {
    let cal = UnitCalibration::load(&capture.join("truth/calibration.json")).unwrap();
    cal.lens(lens).unwrap().camera().unwrap()
}

/// Exact corners per view: view → [(point id, u, v)].
pub fn truth_corners(capture: &Path, lens: &str) -> BTreeMap<usize, Vec<(u32, f64, f64)>> {
    let text =
        std::fs::read_to_string(capture.join(format!("truth/intrinsics/{lens}_corners.csv")))
            .unwrap();
    let mut out: BTreeMap<usize, Vec<(u32, f64, f64)>> = BTreeMap::new();
    for line in text.lines().skip(1) {
        let f: Vec<&str> = line.split(',').collect();
        out.entry(f[0].parse().unwrap()).or_default().push((
            f[1].parse().unwrap(),
            f[2].parse().unwrap(),
            f[3].parse().unwrap(),
        ));
    }
    out
}

/// Deterministic Gaussian noise (SplitMix64 + Box–Muller).
pub struct Noise(u64);

impl Noise {
    pub fn new(seed: u64) -> Self {
        Self(seed)
    }
    pub fn uniform(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^= z >> 31;
        ((z >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    }
    pub fn normal(&mut self, sigma: f64) -> f64 {
        let (u1, u2) = (self.uniform(), self.uniform());
        sigma * (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    }
}

/// A corners set from the truth corners plus Gaussian pixel noise.
pub fn noisy_corner_set(
    truth: &BTreeMap<usize, Vec<(u32, f64, f64)>>,
    target: &AprilGridTarget,
    resolution: u32,
    sigma: f64,
    seed: u64,
) -> CornerSet {
    let mut noise = Noise::new(seed);
    let mut set = CornerSet::new(Some(*target));
    for (view, corners) in truth {
        set.images.push(ImageCorners {
            name: format!("{view:06}.png"),
            width: resolution,
            height: resolution,
            tags: Vec::new(),
            corners: corners
                .iter()
                .map(|&(id, u, v)| {
                    let b = target.point(id as usize);
                    Corner {
                        id,
                        board: [b.x, b.y, b.z],
                        pixel: [u + noise.normal(sigma), v + noise.normal(sigma)],
                    }
                })
                .collect(),
        });
    }
    set
}

/// Largest angle off-axis (rad) of the truth corners, through the true camera.
pub fn max_truth_theta(truth_cam: &Camera, truth: &BTreeMap<usize, Vec<(u32, f64, f64)>>) -> f64 {
    truth
        .values()
        .flatten()
        .filter_map(|&(_, u, v)| truth_cam.unproject(&nalgebra::Point2::new(u, v)))
        .map(|b| b.z.clamp(-1.0, 1.0).acos())
        .fold(0.0, f64::max)
}

/// RMS (px) over the whole imaged field of view of how far `fitted` projects the directions
/// `truth` sees: every 4th pixel of the image that `truth` unprojects, up to `max_theta` off-axis.
pub fn projection_rms(truth: &Camera, fitted: &Camera, max_theta: f64) -> f64 {
    let (w, h) = truth.resolution();
    let (mut sum, mut n) = (0.0, 0usize);
    for y in (0..h).step_by(4) {
        for x in (0..w).step_by(4) {
            let p = nalgebra::Point2::new(f64::from(x), f64::from(y));
            let Some(b) = truth.unproject(&p) else {
                continue;
            };
            if b.z.clamp(-1.0, 1.0).acos() > max_theta {
                continue;
            }
            let q = fitted
                .project(&b)
                .unwrap_or_else(|| panic!("pixel {x},{y} does not project in the fitted model"));
            sum += (q - p).norm_squared();
            n += 1;
        }
    }
    (sum / n as f64).sqrt()
}

/// The default Kalibr aprilgrid the simulator draws.
pub fn sim_target() -> AprilGridTarget {
    AprilGridTarget::new(6, 6, 0.088, 0.3).unwrap()
}

/// The aprilgrid a capture design holds up.
pub fn design_target(design: &IntrinsicsDesign) -> AprilGridTarget {
    let g = design.grid;
    AprilGridTarget::new(g.cols, g.rows, g.tag_size_m, g.spacing).unwrap()
}
