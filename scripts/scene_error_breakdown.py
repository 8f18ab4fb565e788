#!/usr/bin/env python3
"""Where a simulated session's pose error lives: compares a `kiwi run` result with the
simulator's truth (episodes/<ep>/truth/) and prints, per episode and wrist,

- front-camera position errors after one SE(3) alignment fitted on the mapping episode's left
  wrist (as tests/tests/pipeline.rs measures them),
- the tilt of that position-fitted alignment and of an alignment fitted on orientations only
  (a scene whose positions and orientations disagree shows as different tilts),
- each wrist's own Sim(3) scale (a wrist whose positions carry another scale),
- per stream, the angle between a position-fitted and an orientation-fitted alignment of the
  raw map localizations (work/localize-*/poses.csv) — a map whose structure is rotated against
  its own camera orientations.

Usage: scripts/scene_error_breakdown.py SESSION_DIR [MAP_EPISODE]
(the session folder holding session.toml after `kiwi run`; needs numpy and scipy).
"""
import csv
import os
import sys

import numpy as np
from scipy.spatial.transform import Rotation as R


def umeyama(a, b, scale):
    ma, mb = a.mean(0), b.mean(0)
    A, B = a - ma, b - mb
    U, S, Vt = np.linalg.svd(B.T @ A / len(a))
    D = np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))])
    rot = U @ D @ Vt
    s = (S * np.diag(D)).sum() / ((A ** 2).sum() / len(a)) if scale else 1.0
    return s, rot, mb - s * rot @ ma


def read(path, time_col, p_cols, q_cols, keep=lambda r: True):
    rows = [r for r in csv.DictReader(open(path)) if keep(r)]
    t = np.array([float(r[time_col]) for r in rows])
    p = np.array([[float(r[k]) for k in p_cols] for r in rows])
    q = np.array([[float(r[k]) for k in q_cols] for r in rows])
    return t, p, q


def paired(est, tru):
    (te, pe, qe), (tt, pt, qt) = est, tru
    idx = np.minimum(np.searchsorted(tt, te - 1e-6), len(tt) - 1)
    ok = np.abs(tt[idx] - te) < 1e-5
    return pe[ok], qe[ok], pt[idx[ok]], qt[idx[ok]]


def tilt_deg(rot):
    return np.degrees(np.arccos(np.clip(rot[2, 2], -1, 1)))


def main():
    root = sys.argv[1]
    map_ep = sys.argv[2] if len(sys.argv) > 2 else "ep000"
    xyz, quat = ["px", "py", "pz"], ["qx", "qy", "qz", "qw"]

    def output(ep, wrist):
        est = read(f"{root}/episodes/{ep}/out/{wrist}.csv", "t_camera",
                   ["cam_px", "cam_py", "cam_pz"], ["cam_qx", "cam_qy", "cam_qz", "cam_qw"])
        tru = read(f"{root}/episodes/{ep}/truth/{wrist}/front_poses.csv", "t", xyz, quat)
        return paired(est, tru)

    pe, qe, pt, qt = output(map_ep, "left")
    _, rot, t = umeyama(pe, pt, False)
    orient = (R.from_quat(qt) * R.from_quat(qe).inv()).mean().as_matrix()
    print(f"alignment on {map_ep} left: position-fitted tilt {tilt_deg(rot):.3f} deg, "
          f"orientation-fitted tilt {tilt_deg(orient):.3f} deg")
    episodes = sorted(os.listdir(f"{root}/episodes"))
    for ep in episodes:
        for wrist in ["left", "right"]:
            try:
                pe, qe, pt, qt = output(ep, wrist)
            except FileNotFoundError:
                continue
            if len(pe) < 3:
                continue
            err = np.linalg.norm(pe @ rot.T + t - pt, axis=1)
            s3, _, _ = umeyama(pe, pt, True)
            print(f"{ep} {wrist}: camera position error median {np.median(err) * 1e3:.1f} mm, "
                  f"p95 {np.percentile(err, 95) * 1e3:.1f} mm; own Sim(3) scale {s3:.4f}; "
                  f"extent {np.ptp(pt, 0).round(2)} m")
            for lens in ["front", "rear"]:
                try:
                    est = read(f"{root}/episodes/{ep}/work/localize-{wrist}-{lens}/poses.csv", "t",
                               xyz, quat, lambda r: r["status"] in ("tracked", "relocalized"))
                    tru = read(f"{root}/episodes/{ep}/truth/{wrist}/{lens}_poses.csv", "t",
                               xyz, quat)
                except FileNotFoundError:
                    continue
                pe2, qe2, pt2, qt2 = paired(est, tru)
                if len(pe2) < 3:
                    continue
                _, rp, _ = umeyama(pe2, pt2, True)
                ro = (R.from_quat(qt2) * R.from_quat(qe2).inv()).mean()
                ang = (R.from_matrix(rp) * ro.inv()).magnitude() * 180 / np.pi
                print(f"    {lens} in its map: position-fitted vs orientation-fitted "
                      f"alignment {ang:.3f} deg over {len(pe2)} frames")


if __name__ == "__main__":
    main()
