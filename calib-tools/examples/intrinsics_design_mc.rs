#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]
//! Monte Carlo of intrinsics capture designs (board layout, distance, off-axis spread, tilt):
//! exact corners of 40 views of the simulator's X5 lens (960 px) plus 0.3 px noise, no
//! rendering; prints per design the principal point's std from the fit and the projection error
//! over the field of view (95°) across noise and view draws. Figures: docs/intrinsics.md.
//!
//! `SEEDS=48 MODEL=kb4|ds DESIGNS=current,g10_20_40_th80_s03 cargo run --release -p kiwi-calib
//! --example intrinsics_design_mc`

use kiwi_calib::detect::{Corner, CornerSet, ImageCorners};
use kiwi_calib::intrinsics::{IntrinsicsOptions, calibrate};
use kiwi_calib::target::AprilGridTarget;
use kiwi_core::camera::{Camera, CameraModel, CameraModelKind};
use kiwi_fixtures::unit::{LensModel, SimUnit};
use nalgebra::{Isometry3, Matrix3, Point2, Translation3, Unit, UnitQuaternion, Vector3};

struct Rng(u64);
impl Rng {
    fn u(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^= z >> 31;
        ((z >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    }
    fn r(&mut self, a: f64, b: f64) -> f64 {
        a + (b - a) * self.u()
    }
    fn n(&mut self, s: f64) -> f64 {
        let (u1, u2) = (self.u(), self.u());
        s * (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    }
}

#[derive(Clone, Copy, Debug)]
struct Design {
    name: &'static str,
    cols: usize,
    rows: usize,
    tag: f64,
    dmin: f64,
    dmax: f64,
    tilt: f64,
    max_theta_deg: f64,
    /// exponent of stratification: 0.5 = uniform in area (sqrt), 1 = uniform in theta
    strat: f64,
}

fn pose(rng: &mut Rng, d: &Design, t: &AprilGridTarget, k: usize, n: usize) -> Isometry3<f64> {
    let max_theta = d.max_theta_deg.to_radians();
    let theta = max_theta * ((k as f64 + rng.u()) / n as f64).powf(d.strat).min(1.0);
    let phi = rng.r(0.0, std::f64::consts::TAU);
    let dir = Vector3::new(
        theta.sin() * phi.cos(),
        theta.sin() * phi.sin(),
        theta.cos(),
    );
    let distance = rng.r(d.dmin, d.dmax);
    let tilt_axis = dir
        .cross(&Vector3::new(rng.n(1.0), rng.n(1.0), rng.n(1.0)))
        .normalize();
    let tilt =
        UnitQuaternion::from_axis_angle(&Unit::new_normalize(tilt_axis), rng.r(-d.tilt, d.tilt));
    let z = tilt * -dir;
    let spin = rng.r(0.0, std::f64::consts::TAU);
    let x0 = z.cross(&Vector3::new(0.3, 1.0, 0.1)).normalize();
    let x = UnitQuaternion::from_axis_angle(&Unit::new_normalize(z), spin) * x0;
    let y = z.cross(&x);
    let r = UnitQuaternion::from_matrix(&Matrix3::from_columns(&[x, y, z]));
    let pitch = t.pitch_m();
    let g = pitch - d.tag;
    let c = Vector3::new(
        (d.cols as f64 * pitch - g) / 2.0,
        (d.rows as f64 * pitch - g) / 2.0,
        0.0,
    );
    let tr = dir * distance - r * c;
    Isometry3::from_parts(Translation3::from(tr), r)
}

fn projection_rms(truth: &Camera, fitted: &Camera, max_theta: f64) -> f64 {
    let (w, h) = truth.resolution();
    let (mut sum, mut n) = (0.0, 0usize);
    for y in (0..h).step_by(8) {
        for x in (0..w).step_by(8) {
            let p = Point2::new(f64::from(x), f64::from(y));
            let Some(b) = truth.unproject(&p) else {
                continue;
            };
            if b.z.clamp(-1.0, 1.0).acos() > max_theta {
                continue;
            }
            let q = fitted.project(&b).unwrap();
            sum += (q - p).norm_squared();
            n += 1;
        }
    }
    (sum / n as f64).sqrt()
}

fn run(d: &Design, model: LensModel, kind: CameraModelKind, seed: u64) -> (f64, f64, f64, usize) {
    let unit = SimUnit::x5("X5-IT", 11 + seed % 3, 960, model).unwrap();
    let cam = unit.lenses[0].camera.clone();
    let t = AprilGridTarget::new(d.cols, d.rows, d.tag, 0.3).unwrap();
    let mut rng = Rng(seed * 7919 + 13);
    let n = 40;
    let mut set = CornerSet::new(Some(t));
    let mut total = 0;
    for k in 0..n {
        let p = pose(&mut rng, d, &t, k, n);
        let normal = p.rotation * Vector3::z();
        let mut corners = Vec::new();
        for i in 0..t.point_count() {
            let b = t.point(i);
            let pc = p * nalgebra::Point3::from(b);
            if normal.dot(&-pc.coords) <= 0.0 {
                continue;
            }
            if let Some(px) = cam.project(&pc.coords)
                && cam.in_image(&px)
            {
                corners.push(Corner {
                    id: i as u32,
                    board: [b.x, b.y, b.z],
                    pixel: [px.x + rng.n(0.3), px.y + rng.n(0.3)],
                });
            }
        }
        if corners.len() >= 8 {
            total += corners.len();
            set.images.push(ImageCorners {
                name: format!("{k:06}.png"),
                width: 960,
                height: 960,
                tags: Vec::new(),
                corners,
            });
        }
    }
    let o = IntrinsicsOptions {
        model: kind,
        ..IntrinsicsOptions::default()
    };
    let r = match calibrate(&set, &o) {
        Ok(r) => r,
        Err(e) => {
            eprintln!("{} seed {seed}: {e}", d.name);
            return (f64::NAN, f64::NAN, f64::NAN, total);
        }
    };
    let pe = projection_rms(&cam, &r.camera, 95f64.to_radians());
    let pp = r.param_std[2].hypot(r.param_std[3]);
    if pe > 0.05 {
        println!(
            "  seed {seed}: pe {pe:.4} rms {:.4} views {} corners {} rejected {} params {:?} truth {:?}",
            r.rms_px,
            r.n_views,
            r.n_corners,
            r.n_rejected,
            r.camera.params(),
            cam.params()
        );
    }
    (pe, pp, r.rms_px, total)
}

fn main() {
    let seeds: u64 = std::env::var("SEEDS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(8);
    let which = std::env::var("DESIGNS").unwrap_or_default();
    let kinds: Vec<(LensModel, CameraModelKind)> = match std::env::var("MODEL").as_deref() {
        Ok("kb4") => vec![(LensModel::Kb4, CameraModelKind::Kb4)],
        Ok("ds") => vec![(LensModel::Ds, CameraModelKind::DoubleSphere)],
        _ => vec![
            (LensModel::Kb4, CameraModelKind::Kb4),
            (LensModel::Ds, CameraModelKind::DoubleSphere),
        ],
    };
    let base = Design {
        name: "current",
        cols: 6,
        rows: 6,
        tag: 0.088,
        dmin: 0.35,
        dmax: 0.9,
        tilt: 0.6,
        max_theta_deg: 92.0,
        strat: 0.5,
    };
    let g10 = Design {
        name: "g10",
        cols: 10,
        rows: 10,
        tag: 0.055,
        ..base
    };
    let designs = vec![
        base,
        Design {
            name: "g10_15_35",
            dmin: 0.15,
            dmax: 0.35,
            ..g10
        },
        Design {
            name: "g10_20_40",
            dmin: 0.2,
            dmax: 0.4,
            ..g10
        },
        Design {
            name: "g10_20_40_th80",
            dmin: 0.2,
            dmax: 0.4,
            max_theta_deg: 80.0,
            ..g10
        },
        Design {
            name: "g10_20_40_s08",
            dmin: 0.2,
            dmax: 0.4,
            strat: 0.8,
            ..g10
        },
        Design {
            name: "g10_20_40_s03",
            dmin: 0.2,
            dmax: 0.4,
            strat: 0.3,
            ..g10
        },
        Design {
            name: "g12_045_20_40",
            cols: 12,
            rows: 12,
            tag: 0.045,
            dmin: 0.2,
            dmax: 0.4,
            ..base
        },
        Design {
            name: "g6_12_30_s03",
            dmin: 0.12,
            dmax: 0.3,
            strat: 0.3,
            ..base
        },
        Design {
            name: "g6_15_35_s03",
            dmin: 0.15,
            dmax: 0.35,
            strat: 0.3,
            ..base
        },
        Design {
            name: "g6_15_35_th80_s03",
            dmin: 0.15,
            dmax: 0.35,
            strat: 0.3,
            max_theta_deg: 80.0,
            ..base
        },
        Design {
            name: "g10_15_35_s03",
            dmin: 0.15,
            dmax: 0.35,
            strat: 0.3,
            ..g10
        },
        Design {
            name: "g10_20_40_th80_s03",
            dmin: 0.2,
            dmax: 0.4,
            strat: 0.3,
            max_theta_deg: 80.0,
            ..g10
        },
        Design {
            name: "g6_20_40_th80_s03",
            dmin: 0.2,
            dmax: 0.4,
            strat: 0.3,
            max_theta_deg: 80.0,
            ..base
        },
        Design {
            name: "g12_20_40_th80_s03",
            cols: 12,
            rows: 12,
            tag: 0.045,
            dmin: 0.2,
            dmax: 0.4,
            strat: 0.3,
            max_theta_deg: 80.0,
            ..base
        },
        Design {
            name: "g6_15_35",
            dmin: 0.15,
            dmax: 0.35,
            ..base
        },
        Design {
            name: "g6_15_35_t0",
            dmin: 0.15,
            dmax: 0.35,
            tilt: 0.2,
            ..base
        },
        Design {
            name: "close",
            dmin: 0.25,
            dmax: 0.5,
            ..base
        },
        Design {
            name: "closer",
            dmin: 0.2,
            dmax: 0.4,
            ..base
        },
        Design {
            name: "tilt1",
            tilt: 1.0,
            ..base
        },
        Design {
            name: "close_tilt",
            dmin: 0.25,
            dmax: 0.5,
            tilt: 1.0,
            ..base
        },
        Design {
            name: "theta100",
            max_theta_deg: 100.0,
            ..base
        },
        Design {
            name: "uniform_theta",
            strat: 1.0,
            ..base
        },
        Design {
            name: "close_th100",
            dmin: 0.25,
            dmax: 0.5,
            max_theta_deg: 100.0,
            ..base
        },
        Design {
            name: "big8x8",
            cols: 8,
            rows: 8,
            ..base
        },
        Design {
            name: "grid10_055",
            cols: 10,
            rows: 10,
            tag: 0.055,
            ..base
        },
        Design {
            name: "grid10_055_close",
            cols: 10,
            rows: 10,
            tag: 0.055,
            dmin: 0.25,
            dmax: 0.5,
            ..base
        },
        Design {
            name: "grid10_055_close_tilt",
            cols: 10,
            rows: 10,
            tag: 0.055,
            dmin: 0.25,
            dmax: 0.5,
            tilt: 1.0,
            ..base
        },
        Design {
            name: "8x8_close_tilt",
            cols: 8,
            rows: 8,
            dmin: 0.25,
            dmax: 0.5,
            tilt: 1.0,
            ..base
        },
    ];
    for d in designs
        .iter()
        .filter(|d| which.is_empty() || which.split(',').any(|w| w == d.name))
    {
        for &(model, kind) in &kinds {
            let t0 = std::time::Instant::now();
            let mut pes = Vec::new();
            let mut pps = Vec::new();
            let mut ncs = Vec::new();
            for s in 0..seeds {
                let (pe, pp, _rms, nc) = run(d, model, kind, s);
                pes.push(pe);
                pps.push(pp);
                ncs.push(nc);
            }
            let ok = pes.iter().filter(|&&p| p <= 0.05).count();
            let mut sorted = pes.clone();
            sorted.sort_by(f64::total_cmp);
            let pp_mean = pps.iter().sum::<f64>() / pps.len() as f64;
            println!(
                "{:24} {kind:?}: pp std |σ| {:.4} px; proj median {:.4} max {:.4} ≤0.05 in {ok}/{seeds}; corners {:.0}; {:.1}s",
                d.name,
                pp_mean,
                sorted[sorted.len() / 2],
                sorted[sorted.len() - 1],
                ncs.iter().sum::<usize>() as f64 / ncs.len() as f64,
                t0.elapsed().as_secs_f64()
            );
        }
    }
}
