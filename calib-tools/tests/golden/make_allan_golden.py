#!/usr/bin/env python3
"""Golden overlapping Allan deviations from allantools (pip install allantools numpy).

The input is regenerated bit for bit by the Rust test (calib-tools/tests/allan_noise.rs,
`golden_series`): a xorshift64 stream turned into uniforms with integer arithmetic, summed into
white noise plus a bias random walk plus a slow sine-free drift. Run from the repo root:

    python3 calib-tools/tests/golden/make_allan_golden.py
"""
import json
import math
import os

import allantools
import numpy as np

N = 200_000
RATE = 100.0
MASK = (1 << 64) - 1


def uniforms(seed, count):
    x = seed
    out = []
    for _ in range(count):
        x ^= (x << 13) & MASK
        x ^= x >> 7
        x ^= (x << 17) & MASK
        out.append((x >> 11) * (1.0 / 9007199254740992.0))
    return out


def series(axis):
    u = uniforms(0x9E3779B97F4A7C15 + axis, 5 * N)
    rw = 0.0
    y = np.empty(N)
    for k in range(N):
        a, b, c, d, e = u[5 * k : 5 * k + 5]
        rw = rw + 1e-6 * (e - 0.5)
        y[k] = 1e-3 * (((a + b) + (c + d)) - 2.0) + rw + 0.05 * axis
    return y


def averaging_factors(n, per_decade, max_fraction):
    max_m = max(math.floor(n * max_fraction), 1.0)
    steps = math.floor(math.log10(max_m) * per_decade)
    ms = []
    for k in range(steps + 1):
        m = round(10 ** (k / per_decade))
        if 1 <= m <= max_m and (not ms or ms[-1] != m):
            ms.append(m)
    return ms


def main():
    ms = averaging_factors(N, 20, 0.3)
    taus = np.array(ms, dtype=float) / RATE
    out = {"n": N, "rate": RATE, "m": ms, "axes": []}
    for axis in range(2):
        y = series(axis)
        t2, ad, ade, ns = allantools.oadev(y, rate=RATE, data_type="freq", taus=taus)
        assert len(t2) == len(ms), (len(t2), len(ms))
        out["axes"].append({"axis": axis, "taus": list(t2), "adev": list(ad), "n": [int(v) for v in ns]})
    out["allantools_version"] = allantools.__version__
    path = os.path.join(os.path.dirname(__file__), "allan_oadev.json")
    with open(path, "w") as f:
        json.dump(out, f, indent=1)
    print("wrote", path)


if __name__ == "__main__":
    main()
