#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]
//! Golden tests against GTSAM 4.3 (`backend/tests/golden/make_gtsam_golden.py`):
//! preintegration, covariance, bias Jacobians and `CombinedImuFactor` residuals to 1e-9
//! relative; a 2000-node IMU + robust pose-prior problem solved to the same trajectory (1e-6 m).

use kiwi_backend::fusion::chain::{ChainProblem, ImuNoiseModel, LmSettings, PoseFactor};
use kiwi_backend::fusion::factors::{NavNode, imu_linearize, rotation_matrix};
use kiwi_backend::fusion::preint::{ImuBias, ImuParams, Matrix15, Preintegrated};
use kiwi_core::geometry::{Pose, se3_exp, so3_right_jacobian};
use nalgebra::{
    DMatrix, Isometry3, Matrix3, Quaternion, Translation3, UnitQuaternion, Vector3, Vector6,
};
use serde_json::Value;

fn load(name: &str) -> Value {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/golden")
        .join(name);
    serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
}

fn f(v: &Value) -> f64 {
    v.as_f64().unwrap()
}
fn v3(v: &Value) -> Vector3<f64> {
    Vector3::new(f(&v[0]), f(&v[1]), f(&v[2]))
}
fn m3(v: &Value) -> Matrix3<f64> {
    Matrix3::from_fn(|r, c| f(&v[r][c]))
}
fn dmat(v: &Value) -> DMatrix<f64> {
    let rows = v.as_array().unwrap();
    DMatrix::from_fn(rows.len(), rows[0].as_array().unwrap().len(), |r, c| {
        f(&v[r][c])
    })
}
fn pose(v: &Value) -> Pose {
    let q =
        UnitQuaternion::from_quaternion(Quaternion::new(f(&v[6]), f(&v[3]), f(&v[4]), f(&v[5])));
    Isometry3::from_parts(Translation3::new(f(&v[0]), f(&v[1]), f(&v[2])), q)
}
fn bias(v: &Value) -> ImuBias {
    ImuBias::from_vector(&Vector6::from_fn(|i, _| f(&v[i])))
}
fn params(n: &Value) -> ImuParams {
    let mut p = ImuParams::from_densities(
        f(&n["gyro_noise_density"]),
        f(&n["gyro_random_walk"]),
        f(&n["accel_noise_density"]),
        f(&n["accel_random_walk"]),
        f(&n["gravity"]),
    );
    let s = f(&n["integration_sigma"]);
    p.integration_cov = Matrix3::identity() * (s * s);
    p
}

/// ‖a − b‖ / ‖b‖ (Frobenius).
fn rel(a: &DMatrix<f64>, b: &DMatrix<f64>) -> f64 {
    (a - b).norm() / b.norm()
}

const PREINT_TOLERANCE: f64 = 1e-9;

#[test]
fn preintegration_matches_gtsam() {
    let g = load("gtsam_preint.json");
    let params = params(&g["noise"]);
    let mut pim = Preintegrated::new(bias(&g["bias_hat"]));
    for s in g["samples"].as_array().unwrap() {
        pim.integrate(&params, &v3(&s["acc"]), &v3(&s["omega"]), f(&s["dt"]));
    }
    let d = |m: Matrix3<f64>| DMatrix::from_column_slice(3, 3, m.as_slice());
    let dv = |v: Vector3<f64>| DMatrix::from_column_slice(3, 1, v.as_slice());
    let checks = [
        (
            "delta_t",
            (pim.dt - f(&g["delta_t"])).abs() / f(&g["delta_t"]),
        ),
        ("delta_r", rel(&d(pim.delta_r()), &d(m3(&g["delta_r"])))),
        ("delta_p", rel(&dv(pim.delta_p), &dv(v3(&g["delta_p"])))),
        ("delta_v", rel(&dv(pim.delta_v), &dv(v3(&g["delta_v"])))),
        (
            "covariance",
            rel(
                &DMatrix::from_column_slice(15, 15, pim.cov.as_slice()),
                &dmat(&g["covariance"]),
            ),
        ),
    ];
    let mut zeta = DMatrix::zeros(9, 1);
    let mut h = DMatrix::zeros(9, 6);
    for r in 0..3 {
        zeta[r] = pim.theta[r];
        zeta[3 + r] = pim.delta_p[r];
        zeta[6 + r] = pim.delta_v[r];
    }
    for r in 0..9 {
        for c in 0..3 {
            h[(r, c)] = pim.h_bias_acc[(r, c)];
            h[(r, 3 + c)] = pim.h_bias_gyro[(r, c)];
        }
    }
    let zeta_gtsam = DMatrix::from_fn(9, 1, |i, _| f(&g["preintegrated"][i]));
    let jac_checks = [
        ("preintegrated [theta, p, v]", rel(&zeta, &zeta_gtsam)),
        (
            "bias Jacobian 9x6",
            rel(&h, &dmat(&g["preintegrated_h_bias"])),
        ),
    ];
    for (name, e) in checks.iter().chain(jac_checks.iter()) {
        eprintln!("{name}: relative difference {e:.2e}");
        assert!(*e < PREINT_TOLERANCE, "{name}: {e:e}");
    }

    // CombinedImuFactor residuals, costs and information (J^T Σ^-1 J) at three states.
    let info = Cholesky15::inverse(&pim.residual_cov());
    let gravity = params.gravity;
    for (case, s) in g["states"].as_array().unwrap().iter().enumerate() {
        let node = |p: &Value, v: &Value, b: &Value| {
            let mut n = NavNode::from_pose(&pose(p), v3(v));
            n.bias = bias(b);
            n
        };
        let xi = node(&s["pose_i"], &s["vel_i"], &s["bias_i"]);
        let xj = node(&s["pose_j"], &s["vel_j"], &s["bias_j"]);
        let lin = imu_linearize(&pim, &gravity, &xi, &xj, true);
        let r_gtsam = DMatrix::from_fn(15, 1, |i, _| f(&s["residual"][i]));
        let r_mine = DMatrix::from_column_slice(15, 1, lin.residual.as_slice());
        let err = (&r_mine - &r_gtsam).norm();
        eprintln!(
            "case {case}: residual |r| {:.3e}, difference {err:.2e}",
            r_gtsam.norm()
        );
        assert!(
            err <= PREINT_TOLERANCE * r_gtsam.norm() + 1e-13,
            "case {case}: {err:e}"
        );
        let cost = 0.5 * (lin.residual.transpose() * info * lin.residual)[0];
        let cost_gtsam = f(&s["cost"]);
        assert!(
            (cost - cost_gtsam).abs() <= 1e-8 * cost_gtsam + 1e-12,
            "case {case}: cost {cost} vs {cost_gtsam}"
        );
        // GTSAM key order: X_i(6) V_i(3) X_j(6) V_j(3) B_i(6) B_j(6).
        let mut jac = DMatrix::zeros(15, 30);
        for r in 0..15 {
            for c in 0..15 {
                let (ci, cj) = match c {
                    0..=8 => (c, 9 + c),
                    _ => (18 + c - 9, 24 + c - 9),
                };
                jac[(r, ci)] = lin.jac_i[(r, c)];
                jac[(r, cj)] = lin.jac_j[(r, c)];
            }
        }
        let info_d = DMatrix::from_column_slice(15, 15, info.as_slice());
        let h = jac.transpose() * info_d * &jac;
        let hg = dmat(&s["information"]);
        for (bi, (r0, rn)) in [(0, 6), (6, 3), (9, 6), (15, 3), (18, 6), (24, 6)]
            .iter()
            .enumerate()
        {
            for (bj, (c0, cn)) in [(0, 6), (6, 3), (9, 6), (15, 3), (18, 6), (24, 6)]
                .iter()
                .enumerate()
            {
                let a = h.view((*r0, *c0), (*rn, *cn)).into_owned();
                let b = hg.view((*r0, *c0), (*rn, *cn)).into_owned();
                let d = (&a - &b).norm() / b.norm().max(1e-300);
                if d > 1e-6 {
                    eprintln!("block {bi},{bj}: {d:.2e} (|b| {:.2e})", b.norm());
                }
            }
        }
        let e = rel(&h, &hg);
        eprintln!("case {case}: information relative difference {e:.2e}");
        assert!(e < 1e-7, "case {case}: information {e:e}");
    }
}

struct Cholesky15;
impl Cholesky15 {
    fn inverse(m: &Matrix15) -> Matrix15 {
        nalgebra::Cholesky::new(*m).unwrap().inverse()
    }
}

/// The recipe's bit-reproducible noise (see the Python script).
struct SplitMix(u64);
impl SplitMix {
    fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    fn uniform(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / 9_007_199_254_740_992.0)
    }
    fn gauss(&mut self) -> f64 {
        let mut s = self.uniform();
        s += self.uniform();
        s += self.uniform();
        s += self.uniform();
        (s - 2.0) * 3f64.sqrt()
    }
}

fn signal(terms: &Value, t: f64) -> (f64, f64, f64) {
    let lin = f(&terms[0]);
    let (mut x, mut dx, mut ddx) = (lin * t, lin, 0.0);
    for s in terms[1].as_array().unwrap() {
        let (a, w, p) = (f(&s[0]), f(&s[1]), f(&s[2]));
        x += a * (w * t + p).sin();
        dx += a * w * (w * t + p).cos();
        ddx += -a * w * w * (w * t + p).sin();
    }
    (x, dx, ddx)
}

struct Truth {
    phi: Vector3<f64>,
    dphi: Vector3<f64>,
    p: Vector3<f64>,
    acc: Vector3<f64>,
}

fn truth(recipe: &Value, t: f64) -> Truth {
    let r: Vec<_> = (0..3).map(|i| signal(&recipe["rotation"][i], t)).collect();
    let p: Vec<_> = (0..3).map(|i| signal(&recipe["position"][i], t)).collect();
    Truth {
        phi: Vector3::new(r[0].0, r[1].0, r[2].0),
        dphi: Vector3::new(r[0].1, r[1].1, r[2].1),
        p: Vector3::new(p[0].0, p[1].0, p[2].0),
        acc: Vector3::new(p[0].2, p[1].2, p[2].2),
    }
}

type ImuMeas = (Vector3<f64>, Vector3<f64>, f64);

fn chain_inputs(r: &Value) -> (Vec<ImuMeas>, Vec<Pose>) {
    let n = &r["noise"];
    let h = f(&r["node_dt"]);
    let m = r["imu_per_node"].as_u64().unwrap() as usize;
    let nodes = r["nodes"].as_u64().unwrap() as usize;
    let dt = h / m as f64;
    let rate = 1.0 / dt;
    let sg = f(&n["gyro_noise_density"]) * rate.sqrt();
    let sa = f(&n["accel_noise_density"]) * rate.sqrt();
    let b: Vec<f64> = (0..6).map(|i| f(&r["true_bias"][i])).collect();
    let g = Vector3::new(0.0, 0.0, -f(&n["gravity"]));
    let mut rng = SplitMix(r["imu_seed"].as_u64().unwrap());
    let mut imu = Vec::new();
    for k in 0..nodes - 1 {
        for s in 0..m {
            let t = (k * m + s) as f64 * dt + 0.5 * dt;
            let tr = truth(r, t);
            let rot = rotation_matrix(&tr.phi);
            let omega = so3_right_jacobian(&tr.phi) * tr.dphi;
            let force = rot.transpose() * (tr.acc - g);
            let w = Vector3::from_fn(|i, _| omega[i] + b[3 + i] + sg * rng.gauss());
            let a = Vector3::from_fn(|i, _| force[i] + b[i] + sa * rng.gauss());
            imu.push((a, w, dt));
        }
    }
    let mut rng = SplitMix(r["prior_seed"].as_u64().unwrap());
    let every = r["outlier_every"].as_u64().unwrap() as usize;
    let offset = r["outlier_offset"].as_u64().unwrap() as usize;
    let mut priors = Vec::new();
    for k in 0..nodes {
        let tr = truth(r, k as f64 * h);
        let sr = f(&r["prior_sigma_rot"]);
        let sp = f(&r["prior_sigma_pos"]);
        let mut xi = Vector6::zeros();
        for i in 0..3 {
            xi[i] = sr * rng.gauss();
        }
        for i in 3..6 {
            xi[i] = sp * rng.gauss();
        }
        if k % every == offset {
            xi += Vector6::from_fn(|i, _| f(&r["outlier_tangent"][i]));
        }
        let truth_pose = Isometry3::from_parts(
            Translation3::from(tr.p),
            kiwi_core::geometry::so3_exp(&tr.phi),
        );
        priors.push(truth_pose * se3_exp(&xi));
    }
    (imu, priors)
}

#[test]
fn chain_solution_matches_gtsam() {
    let g = load("gtsam_chain.json");
    let r = &g["recipe"];
    let (imu, priors) = chain_inputs(r);
    // The recipe reproduces GTSAM's inputs.
    for (i, c) in g["checks"]["imu"].as_object().unwrap() {
        let i: usize = i.parse().unwrap();
        assert!((imu[i].0 - v3(&c["acc"])).norm() < 1e-12, "imu {i}");
        assert!((imu[i].1 - v3(&c["omega"])).norm() < 1e-12, "imu {i}");
    }
    for (k, c) in g["checks"]["priors"].as_object().unwrap() {
        let k: usize = k.parse().unwrap();
        let p = pose(c);
        assert!((priors[k].translation.vector - p.translation.vector).norm() < 1e-12);
        assert!(priors[k].rotation.angle_to(&p.rotation) < 1e-12);
    }
    let params = params(&r["noise"]);
    let m = r["imu_per_node"].as_u64().unwrap() as usize;
    let pims: Vec<Preintegrated> = (1..priors.len())
        .map(|k| {
            let mut pim = Preintegrated::new(ImuBias::default());
            for (a, w, dt) in &imu[(k - 1) * m..k * m] {
                pim.integrate(&params, a, w, *dt);
            }
            pim
        })
        .collect();
    let problem = ChainProblem {
        gravity: params.gravity,
        nodes: priors
            .iter()
            .map(|p| NavNode::from_pose(p, Vector3::zeros()))
            .collect(),
        imu: pims,
        pose_factors: priors
            .iter()
            .enumerate()
            .map(|(k, z)| PoseFactor {
                node: k,
                z: *z,
                sigma_rot: f(&r["prior_sigma_rot"]),
                sigma_pos: f(&r["prior_sigma_pos"]),
                tag: 0,
            })
            .collect(),
        huber_k: Some(f(&r["huber_k"])),
        // GTSAM drops the (tiny) off-diagonal covariances at this rate; compare like for like.
        imu_noise: ImuNoiseModel::GtsamSmart,
        velocity_prior: Some((Vector3::zeros(), f(&r["velocity_prior_sigma"]))),
        bias_prior: Some((
            ImuBias::default(),
            f(&r["bias_prior_sigma_acc"]),
            f(&r["bias_prior_sigma_gyro"]),
        )),
    };
    let settings = LmSettings {
        relative_tolerance: 1e-15,
        absolute_tolerance: 1e-15,
        max_iterations: 200,
        marginals: false,
        ..LmSettings::default()
    };
    let sol = problem.solve_lm(&settings);
    let final_gtsam = f(&g["final_cost"]);
    eprintln!(
        "chain: {} iterations, cost {:.6e} -> {:.12} (GTSAM {final_gtsam:.12})",
        sol.iterations, sol.initial_cost, sol.final_cost
    );
    let (mut worst_p, mut worst_r, mut worst_v, mut worst_b): (f64, f64, f64, f64) =
        (0.0, 0.0, 0.0, 0.0);
    for (k, node) in g["nodes"].as_array().unwrap().iter().enumerate() {
        let p = pose(&node["pose"]);
        let mine = sol.nodes[k].pose();
        worst_p = worst_p.max((mine.translation.vector - p.translation.vector).norm());
        worst_r = worst_r.max(mine.rotation.angle_to(&p.rotation));
        if node.get("velocity").is_some() {
            worst_v = worst_v.max((sol.nodes[k].velocity - v3(&node["velocity"])).norm());
            let b = bias(&node["bias"]).vector();
            worst_b = worst_b.max((sol.nodes[k].bias.vector() - b).norm());
        }
    }
    eprintln!(
        "worst difference to GTSAM over {} nodes: position {worst_p:.2e} m, rotation \
         {worst_r:.2e} rad, velocity {worst_v:.2e} m/s, bias {worst_b:.2e}",
        sol.nodes.len()
    );
    assert!(worst_p < 1e-6, "position differs by {worst_p:e} m");
    assert!(worst_r < 1e-6, "rotation differs by {worst_r:e} rad");
    assert!(worst_v < 1e-5, "velocity differs by {worst_v:e} m/s");
    assert!(worst_b < 1e-5, "bias differs by {worst_b:e}");
    assert!((sol.final_cost - final_gtsam).abs() < 1e-6 * final_gtsam);
}
