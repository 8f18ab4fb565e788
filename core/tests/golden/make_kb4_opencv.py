#!/usr/bin/env python3
"""Golden vectors: OpenCV's cv::fisheye::projectPoints for KIWI's KB4 model.

Run from the repository root:  python3 core/tests/golden/make_kb4_opencv.py
Needs: pip install opencv-python-headless numpy. Writes core/tests/golden/kb4_opencv.json,
which core/tests/camera_models.rs compares against to 1e-6 px.
"""
import json
import math
import os

import cv2
import numpy as np

# An X5-like lens at 960x960 and a second, more distorted one.
CAMERAS = [
    {"resolution": [960, 960], "params": [281.3, 280.7, 479.6, 481.2, 0.031, -0.0042, 0.0011, -0.00013]},
    {"resolution": [1920, 1920], "params": [575.0, 576.5, 958.0, 962.5, -0.012, 0.0031, -0.0007, 0.00005]},
]


def main():
    out = {"generator": "OpenCV %s cv2.fisheye.projectPoints" % cv2.__version__, "cameras": []}
    rng = np.random.default_rng(7)
    for cam in CAMERAS:
        fx, fy, cx, cy, k1, k2, k3, k4 = cam["params"]
        K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], dtype=np.float64)
        D = np.array([k1, k2, k3, k4], dtype=np.float64)
        points = []
        # Angles below 80 degrees off-axis (OpenCV divides by z), at several depths.
        for theta_deg in np.linspace(0.0, 79.5, 40):
            for phi in np.linspace(0.0, 2 * math.pi, 12, endpoint=False):
                depth = rng.uniform(0.2, 5.0)
                t = math.radians(theta_deg)
                points.append([depth * math.sin(t) * math.cos(phi), depth * math.sin(t) * math.sin(phi), depth * math.cos(t)])
        obj = np.array(points, dtype=np.float64).reshape(-1, 1, 3)
        img, _ = cv2.fisheye.projectPoints(obj, np.zeros(3), np.zeros(3), K, D)
        img = img.reshape(-1, 2)
        out["cameras"].append({
            "resolution": cam["resolution"],
            "params": cam["params"],
            "points": points,
            "pixels": img.tolist(),
        })
    path = os.path.join(os.path.dirname(os.path.abspath(__file__)), "kb4_opencv.json")
    with open(path, "w") as f:
        json.dump(out, f)
    print("wrote", path)


if __name__ == "__main__":
    main()
