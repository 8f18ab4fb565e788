#!/usr/bin/env python3
"""Time GTSAM 4.3 on the problem of `cargo bench -p kiwi-backend --bench fuse`.

Usage: fuse_gtsam.py DIR GN,GW,AN,AW  (DIR holds imu.csv, frames.csv, obs.csv written by the
bench). Builds the graph KIWI builds with its defaults: a node per frame, CombinedImuFactor
between nodes with the same midpoint-interpolated sub-intervals, Huber (k = 3.55) pose priors
with sigmas 1 mm / 1.745e-3 rad, velocity prior N(0, 1), zero bias prior (0.2, 0.02), the same
initial values; prints `gtsam_seconds S` for LevenbergMarquardtOptimizer.optimize() alone
(graph construction and preintegration are not timed, which favours GTSAM).
"""
import sys
import time

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, V, X


def main():
    folder, noise = sys.argv[1], [float(x) for x in sys.argv[2].split(",")]
    imu = np.loadtxt(f"{folder}/imu.csv", delimiter=",", skiprows=1)
    times = np.loadtxt(f"{folder}/frames.csv", delimiter=",", skiprows=1, ndmin=1)
    obs = np.genfromtxt(f"{folder}/obs.csv", delimiter=",", skip_header=1, dtype=None, encoding=None)
    gn, gw, an, aw = noise
    p = gtsam.PreintegrationCombinedParams.MakeSharedU(9.81)
    p.setGyroscopeCovariance(np.eye(3) * gn * gn)
    p.setAccelerometerCovariance(np.eye(3) * an * an)
    p.setIntegrationCovariance(np.eye(3) * 1e-8)
    p.setBiasAccCovariance(np.eye(3) * aw * aw)
    p.setBiasOmegaCovariance(np.eye(3) * gw * gw)
    t_imu = imu[:, 0]

    def at(i, t):
        a, b = imu[i], imu[min(i + 1, len(imu) - 1)]
        span = b[0] - a[0]
        s = min(max((t - a[0]) / span, 0.0), 1.0) if span > 0 else 0.0
        m = a + (b - a) * s
        return m[4:7], m[1:4]

    poses = []
    for row in obs:
        t, _, px, py, pz, qx, qy, qz, qw = row
        poses.append(gtsam.Pose3(gtsam.Rot3.Quaternion(qw, qx, qy, qz), np.array([px, py, pz])))
    n = len(times)
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    huber = gtsam.noiseModel.mEstimator.Huber.Create(3.55)
    prior = gtsam.noiseModel.Robust.Create(huber, gtsam.noiseModel.Diagonal.Sigmas(
        np.array([1.745e-3] * 3 + [1e-3] * 3)))
    build = time.perf_counter()
    i = 0
    for k in range(n):
        a, b = max(k - 1, 0), min(k + 1, n - 1)
        vel = (poses[b].translation() - poses[a].translation()) / (times[b] - times[a])
        values.insert(X(k), poses[k])
        values.insert(V(k), vel)
        values.insert(B(k), gtsam.imuBias.ConstantBias())
        graph.add(gtsam.PriorFactorPose3(X(k), poses[k], prior))
        if k + 1 < n:
            ta, tb = times[k], times[k + 1]
            while i + 1 < len(imu) and t_imu[i + 1] <= ta:
                i += 1
            pim = gtsam.PreintegratedCombinedMeasurements(p, gtsam.imuBias.ConstantBias())
            cur, j = ta, i
            while cur < tb:
                nxt = min(t_imu[j + 1], tb) if j + 1 < len(imu) else tb
                if nxt <= cur:
                    nxt = tb
                acc, gyro = at(j, 0.5 * (cur + nxt))
                pim.integrateMeasurement(acc, gyro, nxt - cur)
                cur = nxt
                if j + 1 < len(imu) and t_imu[j + 1] <= cur:
                    j += 1
            graph.add(gtsam.CombinedImuFactor(X(k), V(k), X(k + 1), V(k + 1), B(k), B(k + 1), pim))
    graph.add(gtsam.PriorFactorVector(V(0), np.zeros(3), gtsam.noiseModel.Isotropic.Sigma(3, 1.0)))
    graph.add(gtsam.PriorFactorConstantBias(B(0), gtsam.imuBias.ConstantBias(),
                                            gtsam.noiseModel.Diagonal.Sigmas(np.array([0.2] * 3 + [0.02] * 3))))
    print(f"gtsam graph build + preintegration (Python loop, not timed): {time.perf_counter() - build:.1f} s")
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-10)
    params.setMaxIterations(100)
    start = time.perf_counter()
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    result = optimizer.optimize()
    seconds = time.perf_counter() - start
    print(f"gtsam: {n} nodes, {optimizer.iterations()} iterations, final cost {graph.error(result):.6g}")
    print(f"gtsam_seconds {seconds:.3f}")


if __name__ == "__main__":
    main()
