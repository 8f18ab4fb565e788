//! Uniform cubic B-splines for a continuous-time IMU trajectory: rotation as a cumulative
//! B-spline on SO(3) (Kim et al. 1995; Lovegrove et al. 2013) and position as an ordinary cubic
//! B-spline in R³, with the same knots (the SO(3)×R³ split Kalibr's and Basalt's batch
//! estimators use), plus an R³ spline for slowly drifting biases.
//!
//! Segment `i` covers `[t0 + i·h, t0 + (i+1)·h)` and depends on control points `i..i+4`.
//! `R(t) = R_i · Π_{j=1..3} exp(B̃_j(u)·log(R_{i+j−1}ᵀ R_{i+j}))`, `p(t) = Σ_j B_j(u)·p_{i+j}`,
//! with `u = (t − t0)/h − i`.

use nalgebra::{Matrix3, SMatrix, UnitQuaternion, Vector3};

use kiwi_core::geometry::{so3_exp, so3_log};

/// Step (rad) of the numerical rotation Jacobians: small enough for 1e-7 relative accuracy,
/// large enough to stay clear of round-off.
const JACOBIAN_STEP: f64 = 1e-6;

/// Uniform cubic B-spline basis at `u` (weights of control points `i..i+4`).
pub fn basis(u: f64) -> [f64; 4] {
    let v = 1.0 - u;
    [
        v * v * v / 6.0,
        (3.0 * u * u * u - 6.0 * u * u + 4.0) / 6.0,
        (-3.0 * u * u * u + 3.0 * u * u + 3.0 * u + 1.0) / 6.0,
        u * u * u / 6.0,
    ]
}

/// First derivative of [`basis`] with respect to `u`.
pub fn basis_d1(u: f64) -> [f64; 4] {
    [
        -(1.0 - u) * (1.0 - u) / 2.0,
        (3.0 * u * u - 4.0 * u) / 2.0,
        (-3.0 * u * u + 2.0 * u + 1.0) / 2.0,
        u * u / 2.0,
    ]
}

/// Second derivative of [`basis`] with respect to `u`.
pub fn basis_d2(u: f64) -> [f64; 4] {
    [1.0 - u, 3.0 * u - 2.0, 1.0 - 3.0 * u, u]
}

/// Cumulative basis `B̃_1..B̃_3` and their `u` derivatives.
fn cumulative(u: f64) -> ([f64; 3], [f64; 3]) {
    (
        [
            (5.0 + 3.0 * u - 3.0 * u * u + u * u * u) / 6.0,
            (1.0 + 3.0 * u + 3.0 * u * u - 2.0 * u * u * u) / 6.0,
            u * u * u / 6.0,
        ],
        [
            (3.0 - 6.0 * u + 3.0 * u * u) / 6.0,
            (3.0 + 6.0 * u - 6.0 * u * u) / 6.0,
            3.0 * u * u / 6.0,
        ],
    )
}

/// Where a time falls on a uniform knot grid: segment index and fraction.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Knot {
    /// Segment index: control points `segment..segment + 4` apply.
    pub segment: usize,
    /// Fraction of the segment, in `[0, 1)`.
    pub u: f64,
}

/// Locate `t` on a grid starting at `t0` with spacing `h` and `count` control points.
pub fn locate(t0: f64, h: f64, count: usize, t: f64) -> Option<Knot> {
    let s = (t - t0) / h;
    if !s.is_finite() || s < 0.0 {
        return None;
    }
    let i = s.floor() as usize;
    if i + 4 > count {
        return None;
    }
    Some(Knot {
        segment: i,
        u: s - i as f64,
    })
}

/// Rotation and body angular rate (per unit `u`) of a cumulative SO(3) spline segment.
fn rotation_segment(
    ctrl: &[UnitQuaternion<f64>; 4],
    u: f64,
) -> (UnitQuaternion<f64>, Vector3<f64>) {
    let (b, db) = cumulative(u);
    let mut r = ctrl[0];
    let mut w = Vector3::zeros();
    for j in 0..3 {
        let omega = so3_log(&(ctrl[j].inverse() * ctrl[j + 1]));
        let a = so3_exp(&(omega * b[j]));
        r *= a;
        w = a.inverse() * w + omega * db[j];
    }
    (r, w)
}

/// The trajectory `world_from_imu(t)`: rotation and position control points on one grid.
#[derive(Debug, Clone)]
pub struct TrajectorySpline {
    /// Time of the first knot (s, IMU clock).
    pub t0: f64,
    /// Knot spacing (s).
    pub h: f64,
    /// Rotation control points (`world_from_imu` rotations).
    pub rotations: Vec<UnitQuaternion<f64>>,
    /// Position control points (m, world frame).
    pub positions: Vec<Vector3<f64>>,
}

/// The trajectory at one instant.
#[derive(Debug, Clone, Copy)]
pub struct TrajectoryState {
    /// Where on the grid.
    pub knot: Knot,
    /// Rotation `world_from_imu`.
    pub rotation: UnitQuaternion<f64>,
    /// Body angular rate (rad/s, IMU frame).
    pub omega: Vector3<f64>,
    /// Position (m, world).
    pub position: Vector3<f64>,
    /// Velocity (m/s, world).
    pub velocity: Vector3<f64>,
    /// Acceleration (m/s², world).
    pub acceleration: Vector3<f64>,
}

impl TrajectorySpline {
    /// Number of control points.
    pub fn len(&self) -> usize {
        self.rotations.len()
    }

    /// True without control points.
    pub fn is_empty(&self) -> bool {
        self.rotations.is_empty()
    }

    /// Last time the spline is defined at (exclusive).
    pub fn t_end(&self) -> f64 {
        self.t0 + (self.len().saturating_sub(3)) as f64 * self.h
    }

    /// Where `t` falls, if inside the spline.
    pub fn locate(&self, t: f64) -> Option<Knot> {
        locate(self.t0, self.h, self.len(), t)
    }

    fn ctrl_rotations(&self, i: usize) -> [UnitQuaternion<f64>; 4] {
        [
            self.rotations[i],
            self.rotations[i + 1],
            self.rotations[i + 2],
            self.rotations[i + 3],
        ]
    }

    /// The state at `t`, or `None` outside the spline.
    pub fn state(&self, t: f64) -> Option<TrajectoryState> {
        let knot = self.locate(t)?;
        let i = knot.segment;
        let (rotation, w) = rotation_segment(&self.ctrl_rotations(i), knot.u);
        let (b, d1, d2) = (basis(knot.u), basis_d1(knot.u), basis_d2(knot.u));
        let mut position = Vector3::zeros();
        let mut velocity = Vector3::zeros();
        let mut acceleration = Vector3::zeros();
        for j in 0..4 {
            let p = self.positions[i + j];
            position += p * b[j];
            velocity += p * d1[j];
            acceleration += p * d2[j];
        }
        Some(TrajectoryState {
            knot,
            rotation,
            omega: w / self.h,
            position,
            velocity: velocity / self.h,
            acceleration: acceleration / (self.h * self.h),
        })
    }

    /// Rotation and position only (cheaper), or `None` outside the spline.
    pub fn pose(&self, t: f64) -> Option<(UnitQuaternion<f64>, Vector3<f64>)> {
        let knot = self.locate(t)?;
        let i = knot.segment;
        let (b, _) = cumulative(knot.u);
        let mut r = self.rotations[i];
        for j in 0..3 {
            let omega = so3_log(&(self.rotations[i + j].inverse() * self.rotations[i + j + 1]));
            r *= so3_exp(&(omega * b[j]));
        }
        let w = basis(knot.u);
        let p = (0..4).fold(Vector3::zeros(), |a, j| a + self.positions[i + j] * w[j]);
        Some((r, p))
    }

    /// Jacobians of the rotation (right perturbation) and of the body rate at `knot` with respect
    /// to right perturbations of the segment's four rotation control points (3 × 12 each).
    pub fn rotation_jacobians(&self, knot: Knot) -> (SMatrix<f64, 3, 12>, SMatrix<f64, 3, 12>) {
        let ctrl = self.ctrl_rotations(knot.segment);
        let (r0, w0) = rotation_segment(&ctrl, knot.u);
        let mut jr = SMatrix::<f64, 3, 12>::zeros();
        let mut jw = SMatrix::<f64, 3, 12>::zeros();
        let r0_inv = r0.inverse();
        for k in 0..4 {
            for a in 0..3 {
                let mut c = ctrl;
                let mut e = Vector3::zeros();
                e[a] = JACOBIAN_STEP;
                c[k] *= so3_exp(&e);
                let (r, w) = rotation_segment(&c, knot.u);
                let dr = so3_log(&(r0_inv * r)) / JACOBIAN_STEP;
                let dw = (w - w0) / (JACOBIAN_STEP * self.h);
                jr.fixed_view_mut::<3, 1>(0, 3 * k + a).copy_from(&dr);
                jw.fixed_view_mut::<3, 1>(0, 3 * k + a).copy_from(&dw);
            }
        }
        (jr, jw)
    }
}

/// A slowly varying 3-vector (a bias) as a uniform cubic B-spline.
#[derive(Debug, Clone)]
pub struct VectorSpline {
    /// Time of the first knot (s).
    pub t0: f64,
    /// Knot spacing (s).
    pub h: f64,
    /// Control points.
    pub values: Vec<Vector3<f64>>,
}

impl VectorSpline {
    /// A constant spline covering `[t0, t1]` with knots `h` apart.
    pub fn constant(t0: f64, t1: f64, h: f64, value: Vector3<f64>) -> Self {
        let count = ((t1 - t0) / h).floor().max(0.0) as usize + 4;
        Self {
            t0,
            h,
            values: vec![value; count],
        }
    }

    /// Value and the weights of control points `knot.segment..+4`, clamped to the ends.
    pub fn weights(&self, t: f64) -> (usize, [f64; 4]) {
        let count = self.values.len();
        let last = count.saturating_sub(4);
        match locate(self.t0, self.h, count, t) {
            Some(k) => (k.segment, basis(k.u)),
            None if t < self.t0 => (0, basis(0.0)),
            None => (last, basis(1.0)),
        }
    }

    /// Value at `t` (clamped to the ends).
    pub fn value(&self, t: f64) -> Vector3<f64> {
        let (i, w) = self.weights(t);
        (0..4).fold(Vector3::zeros(), |a, j| a + self.values[i + j] * w[j])
    }
}

/// `[v]×` as a 3 × 3 matrix (re-exported for the solver's readability).
pub fn skew(v: &Vector3<f64>) -> Matrix3<f64> {
    kiwi_core::geometry::hat(v)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spline() -> TrajectorySpline {
        let rotations = (0..10)
            .map(|k| so3_exp(&Vector3::new(0.1 * k as f64, -0.05 * k as f64, 0.3)))
            .collect();
        let positions = (0..10)
            .map(|k| Vector3::new((k as f64).sin(), 0.1 * k as f64, 0.0))
            .collect();
        TrajectorySpline {
            t0: 1.0,
            h: 0.1,
            rotations,
            positions,
        }
    }

    #[test]
    fn derivatives_match_finite_differences() {
        let s = spline();
        let t = 1.337;
        let dt = 1e-6;
        let a = s.state(t).unwrap();
        let b = s.state(t + dt).unwrap();
        let w = so3_log(&(a.rotation.inverse() * b.rotation)) / dt;
        assert!((w - a.omega).norm() < 1e-4, "{w} {}", a.omega);
        let v = (b.position - a.position) / dt;
        assert!((v - a.velocity).norm() < 1e-4);
        let acc = (b.velocity - a.velocity) / dt;
        assert!((acc - a.acceleration).norm() < 1e-3);
        let (r, p) = s.pose(t).unwrap();
        assert!((r.inverse() * a.rotation).angle() < 1e-12 && (p - a.position).norm() < 1e-12);
        // Continuity across a knot.
        let l = s.state(1.2 - 1e-9).unwrap();
        let r = s.state(1.2).unwrap();
        assert!((l.rotation.inverse() * r.rotation).angle() < 1e-7);
        assert!((l.omega - r.omega).norm() < 1e-5);
    }

    #[test]
    fn basis_sums_to_one() {
        for u in [0.0, 0.3, 0.99] {
            assert!((basis(u).iter().sum::<f64>() - 1.0).abs() < 1e-15);
            assert!(basis_d1(u).iter().sum::<f64>().abs() < 1e-15);
            assert!(basis_d2(u).iter().sum::<f64>().abs() < 1e-15);
        }
    }
}
