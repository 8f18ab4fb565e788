#!/usr/bin/env python3
"""Golden data for KIWI's estimation module, produced by GTSAM 4.3 (PyPI `gtsam`).

Usage: python3 backend/tests/golden/make_gtsam_golden.py   (writes the two JSON files next to
this script). Requires `pip install gtsam numpy`.

1. `gtsam_preint.json`: a fixed deterministic IMU sequence integrated by
   `PreintegratedCombinedMeasurements` (ΔR, Δp, Δv, Δt, 15×15 covariance), its bias Jacobians
   (recovered exactly from `predict`, which is linear in the bias for Δp, Δv and in the
   rotation vector for ΔR), and `CombinedImuFactor` residuals, costs and information matrices
   at three states.
2. `gtsam_chain.json`: a 2000-node IMU + noisy pose-prior problem with Huber loss, defined by a
   recipe (analytic trajectory, splitmix64 noise) that the Rust test regenerates bit for bit,
   and GTSAM's Levenberg–Marquardt solution at every node.
"""
import json
import math
import os
import sys

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, V, X

HERE = os.path.dirname(os.path.abspath(__file__))
MASK = (1 << 64) - 1


class SplitMix:
    """splitmix64; `gauss` is an Irwin–Hall(4) unit-variance deviate (bit-reproducible)."""

    def __init__(self, seed):
        self.state = seed & MASK

    def next_u64(self):
        self.state = (self.state + 0x9E3779B97F4A7C15) & MASK
        z = self.state
        z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & MASK
        z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & MASK
        return z ^ (z >> 31)

    def uniform(self):
        return (self.next_u64() >> 11) * (1.0 / 9007199254740992.0)

    def gauss(self):
        s = self.uniform()
        s += self.uniform()
        s += self.uniform()
        s += self.uniform()
        return (s - 2.0) * math.sqrt(3.0)


def hat(v):
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def right_jacobian(phi):
    t = np.linalg.norm(phi)
    k = hat(phi)
    if t < 1e-8:
        return np.eye(3) - 0.5 * k + k @ k / 6.0
    return np.eye(3) - (1 - math.cos(t)) / (t * t) * k + (t - math.sin(t)) / (t ** 3) * (k @ k)


def signal(terms, t):
    """Value, first and second derivative of `lin*t + Σ a sin(w t + p)`."""
    lin, sines = terms
    x, dx, ddx = lin * t, lin, 0.0
    for a, w, p in sines:
        x += a * math.sin(w * t + p)
        dx += a * w * math.cos(w * t + p)
        ddx += -a * w * w * math.sin(w * t + p)
    return x, dx, ddx


def truth(recipe, t):
    rot = [signal(c, t) for c in recipe["rotation"]]
    pos = [signal(c, t) for c in recipe["position"]]
    phi = np.array([r[0] for r in rot])
    dphi = np.array([r[1] for r in rot])
    p = np.array([q[0] for q in pos])
    acc = np.array([q[2] for q in pos])
    vel = np.array([q[1] for q in pos])
    return phi, dphi, p, vel, acc


def imu_params(n):
    p = gtsam.PreintegrationCombinedParams.MakeSharedU(n["gravity"])
    p.setGyroscopeCovariance(np.eye(3) * n["gyro_noise_density"] ** 2)
    p.setAccelerometerCovariance(np.eye(3) * n["accel_noise_density"] ** 2)
    p.setIntegrationCovariance(np.eye(3) * n["integration_sigma"] ** 2)
    p.setBiasAccCovariance(np.eye(3) * n["accel_random_walk"] ** 2)
    p.setBiasOmegaCovariance(np.eye(3) * n["gyro_random_walk"] ** 2)
    return p


def mat(m):
    return [list(map(float, row)) for row in np.asarray(m)]


def vec(v):
    return list(map(float, np.asarray(v).ravel()))


def pose_json(pose):
    q = pose.rotation().toQuaternion()
    return vec(pose.translation()) + [q.x(), q.y(), q.z(), q.w()]


# --------------------------------------------------------------------------------------------
def preint_golden():
    noise = {
        "gravity": 9.81,
        "gyro_noise_density": 1.7e-3,
        "accel_noise_density": 2.0e-2,
        "integration_sigma": 1e-4,
        "gyro_random_walk": 2.0e-4,
        "accel_random_walk": 3.0e-3,
    }
    rng = SplitMix(7)
    samples = []
    for k in range(200):
        t = 0.005 * k
        dt = 0.005 + 0.001 * (rng.uniform() - 0.5)
        omega = [1.5 * math.sin(2.1 * t), -0.8 * math.cos(1.3 * t + 0.4), 2.2 * math.sin(0.7 * t + 1.0)]
        acc = [0.5 + 3.0 * math.sin(3.1 * t), -1.2 * math.cos(2.3 * t), 9.81 + 2.0 * math.sin(1.7 * t)]
        omega = [w + 0.05 * rng.gauss() for w in omega]
        acc = [a + 0.2 * rng.gauss() for a in acc]
        samples.append({"acc": acc, "omega": omega, "dt": dt})
    bias_hat = gtsam.imuBias.ConstantBias(np.array([0.1, -0.2, 0.05]), np.array([0.01, 0.02, -0.03]))
    params = imu_params(noise)
    pim = gtsam.PreintegratedCombinedMeasurements(params, bias_hat)
    for s in samples:
        pim.integrateMeasurement(np.array(s["acc"]), np.array(s["omega"]), s["dt"])

    # Bias Jacobians of the tangent-space preintegrated vector ζ = [θ, p, v] (GTSAM 4.3 wheels
    # use TangentPreintegration): predict() at the identity state returns Exp(ζ_θ + H δb),
    # p + H δb, v + H δb, all exactly linear in δb, so unit differences recover H exactly.
    state0 = gtsam.NavState(gtsam.Rot3(), np.zeros(3), np.zeros(3))

    def zeta(bias):
        s = pim.predict(state0, bias)
        theta = gtsam.Rot3.Logmap(s.attitude())
        assert np.linalg.norm(theta) < 3.0, "keep the golden rotation below pi"
        return np.concatenate([theta, s.position(), s.velocity()])

    base = zeta(bias_hat)
    step = 0.1
    h_bias = np.zeros((9, 6))
    for c in range(6):
        e = np.zeros(6)
        e[c] = step
        b = gtsam.imuBias.ConstantBias(bias_hat.accelerometer() + e[:3], bias_hat.gyroscope() + e[3:])
        h_bias[:, c] = (zeta(b) - base) / step
    gravity_term = 0.5 * np.array([0.0, 0.0, -noise["gravity"]]) * pim.deltaTij() ** 2
    preintegrated = base.copy()
    preintegrated[3:6] -= gravity_term
    preintegrated[6:9] -= np.array([0.0, 0.0, -noise["gravity"]]) * pim.deltaTij()

    factor = gtsam.CombinedImuFactor(X(0), V(0), X(1), V(1), B(0), B(1), pim)
    states = []
    for case in range(3):
        pose_i = gtsam.Pose3(gtsam.Rot3.Expmap(np.array([0.1, 0.2 * case, -0.3])), np.array([1.0, 2.0, 3.0 - case]))
        vel_i = np.array([0.5, -0.2, 0.1 * case])
        bias_i = gtsam.imuBias.ConstantBias(bias_hat.accelerometer() + np.array([0.01, -0.02, 0.03]) * case,
                                            bias_hat.gyroscope() + np.array([-0.002, 0.001, 0.003]) * case)
        pred = pim.predict(gtsam.NavState(pose_i, vel_i), bias_i)
        pose_j = pred.pose().compose(gtsam.Pose3.Expmap(np.array([0.01, -0.02, 0.005, 0.03, 0.01, -0.02]) * case))
        vel_j = pred.velocity() + np.array([0.01, 0.02, -0.03]) * case
        bias_j = gtsam.imuBias.ConstantBias(bias_i.accelerometer() + np.array([0.001, 0.0, -0.002]),
                                            bias_i.gyroscope() + np.array([0.0, 1e-4, 0.0]))
        values = gtsam.Values()
        values.insert(X(0), pose_i)
        values.insert(V(0), vel_i)
        values.insert(X(1), pose_j)
        values.insert(V(1), vel_j)
        values.insert(B(0), bias_i)
        values.insert(B(1), bias_j)
        info = factor.linearize(values).augmentedInformation()
        states.append({
            "pose_i": pose_json(pose_i), "vel_i": vec(vel_i), "bias_i": vec(bias_i.vector()),
            "pose_j": pose_json(pose_j), "vel_j": vec(vel_j), "bias_j": vec(bias_j.vector()),
            "residual": vec(factor.unwhitenedError(values)),
            "cost": float(factor.error(values)),
            "information": mat(info[:30, :30]),
        })
    return {
        "gtsam_version": gtsam.__version__ if hasattr(gtsam, "__version__") else "4.3",
        "noise": noise,
        "bias_hat": vec(bias_hat.vector()),
        "samples": samples,
        "delta_t": float(pim.deltaTij()),
        "delta_r": mat(pim.deltaRij().matrix()),
        "delta_p": vec(pim.deltaPij()),
        "delta_v": vec(pim.deltaVij()),
        "covariance": mat(pim.preintMeasCov()),
        "preintegrated": vec(preintegrated),
        "preintegrated_h_bias": mat(h_bias),
        "states": states,
    }


# --------------------------------------------------------------------------------------------
CHAIN_RECIPE = {
    "nodes": 2000,
    "node_dt": 0.01,
    "imu_per_node": 5,
    "imu_seed": 11,
    "prior_seed": 12,
    "noise": {
        "gravity": 9.81,
        "gyro_noise_density": 1.7e-4,
        "accel_noise_density": 2.0e-3,
        "integration_sigma": 1e-4,
        "gyro_random_walk": 2.0e-5,
        "accel_random_walk": 3.0e-4,
    },
    "true_bias": [0.05, -0.03, 0.02, 0.002, -0.001, 0.003],
    "rotation": [
        [0.0, [[0.3, 0.5, 0.0], [0.1, 1.7, 0.3]]],
        [0.0, [[0.2, 0.7, 1.0], [0.05, 2.3, 0.0]]],
        [0.1, [[0.8, 0.3, 0.0]]],
    ],
    "position": [
        [0.0, [[1.0, 0.4, 0.0], [0.1, 2.0, 0.5]]],
        [0.05, [[0.5, 0.3, 1.5708]]],
        [0.0, [[0.2, 0.9, 0.0], [0.03, 3.1, 0.2]]],
    ],
    "prior_sigma_rot": 0.002,
    "prior_sigma_pos": 0.005,
    "outlier_every": 50,
    "outlier_offset": 25,
    "outlier_tangent": [0.0, 0.0, 0.1, 0.2, 0.0, 0.0],
    "huber_k": 1.345,
    "velocity_prior_sigma": 1.0,
    "bias_prior_sigma_acc": 0.1,
    "bias_prior_sigma_gyro": 0.01,
}


def chain_inputs(recipe):
    """IMU samples per interval and pose priors, exactly as the Rust test regenerates them."""
    n = recipe["noise"]
    h = recipe["node_dt"]
    m = recipe["imu_per_node"]
    dt = h / m
    rate = 1.0 / dt
    sg = n["gyro_noise_density"] * math.sqrt(rate)
    sa = n["accel_noise_density"] * math.sqrt(rate)
    bias = recipe["true_bias"]
    g = np.array([0.0, 0.0, -n["gravity"]])
    rng = SplitMix(recipe["imu_seed"])
    imu = []
    for k in range(recipe["nodes"] - 1):
        for s in range(m):
            t = (k * m + s) * dt + 0.5 * dt
            phi, dphi, _, _, acc = truth(recipe, t)
            rot = gtsam.Rot3.Expmap(phi).matrix()
            omega = right_jacobian(phi) @ dphi
            f = rot.T @ (acc - g)
            meas_w = [omega[i] + bias[3 + i] + sg * rng.gauss() for i in range(3)]
            meas_a = [f[i] + bias[i] + sa * rng.gauss() for i in range(3)]
            imu.append((meas_a, meas_w, dt))
    rng = SplitMix(recipe["prior_seed"])
    priors = []
    for k in range(recipe["nodes"]):
        phi, _, p, _, _ = truth(recipe, k * h)
        xi = [recipe["prior_sigma_rot"] * rng.gauss() for _ in range(3)]
        xi += [recipe["prior_sigma_pos"] * rng.gauss() for _ in range(3)]
        if k % recipe["outlier_every"] == recipe["outlier_offset"]:
            xi = [a + b for a, b in zip(xi, recipe["outlier_tangent"])]
        priors.append(gtsam.Pose3(gtsam.Rot3.Expmap(phi), p).compose(gtsam.Pose3.Expmap(np.array(xi))))
    return imu, priors


def chain_golden():
    import time
    r = CHAIN_RECIPE
    imu, priors = chain_inputs(r)
    params = imu_params(r["noise"])
    m = r["imu_per_node"]
    graph = gtsam.NonlinearFactorGraph()
    initial = gtsam.Values()
    huber = gtsam.noiseModel.mEstimator.Huber.Create(r["huber_k"])
    prior_noise = gtsam.noiseModel.Robust.Create(huber, gtsam.noiseModel.Diagonal.Sigmas(
        np.array([r["prior_sigma_rot"]] * 3 + [r["prior_sigma_pos"]] * 3)))
    for k in range(r["nodes"]):
        graph.add(gtsam.PriorFactorPose3(X(k), priors[k], prior_noise))
        initial.insert(X(k), priors[k])
        initial.insert(V(k), np.zeros(3))
        initial.insert(B(k), gtsam.imuBias.ConstantBias())
        if k > 0:
            pim = gtsam.PreintegratedCombinedMeasurements(params, gtsam.imuBias.ConstantBias())
            for a, w, dt in imu[(k - 1) * m: k * m]:
                pim.integrateMeasurement(np.array(a), np.array(w), dt)
            graph.add(gtsam.CombinedImuFactor(X(k - 1), V(k - 1), X(k), V(k), B(k - 1), B(k), pim))
    graph.add(gtsam.PriorFactorVector(V(0), np.zeros(3), gtsam.noiseModel.Isotropic.Sigma(3, r["velocity_prior_sigma"])))
    graph.add(gtsam.PriorFactorConstantBias(B(0), gtsam.imuBias.ConstantBias(), gtsam.noiseModel.Diagonal.Sigmas(
        np.array([r["bias_prior_sigma_acc"]] * 3 + [r["bias_prior_sigma_gyro"]] * 3))))
    lm = gtsam.LevenbergMarquardtParams()
    lm.setMaxIterations(200)
    lm.setRelativeErrorTol(1e-15)
    lm.setAbsoluteErrorTol(1e-15)
    t0 = time.perf_counter()
    result = gtsam.LevenbergMarquardtOptimizer(graph, initial, lm).optimize()
    seconds = time.perf_counter() - t0
    print(f"chain: initial cost {graph.error(initial):.6g}, final {graph.error(result):.12g}, {seconds:.2f} s",
          file=sys.stderr)
    nodes = []
    for k in range(r["nodes"]):
        pose = result.atPose3(X(k))
        node = {"pose": [float("%.13g" % x) for x in pose_json(pose)]}
        if k % 20 == 0:
            node["velocity"] = [float("%.13g" % x) for x in result.atVector(V(k))]
            node["bias"] = [float("%.13g" % x) for x in result.atConstantBias(B(k)).vector()]
        nodes.append(node)
    checks = {
        "imu": {str(i): {"acc": imu[i][0], "omega": imu[i][1]} for i in (0, 1, 4321, len(imu) - 1)},
        "priors": {str(k): pose_json(priors[k]) for k in (0, 25, 1234, r["nodes"] - 1)},
    }
    return {"recipe": r, "checks": checks, "final_cost": float(graph.error(result)), "nodes": nodes}


def main():
    with open(os.path.join(HERE, "gtsam_preint.json"), "w") as f:
        json.dump(preint_golden(), f)
    with open(os.path.join(HERE, "gtsam_chain.json"), "w") as f:
        json.dump(chain_golden(), f, separators=(",", ":"))


if __name__ == "__main__":
    main()
