//! Fisheye camera models that work on unit bearing vectors over the whole ~190° field of view.
//!
//! A [`CameraModel`] maps a 3-D direction in the camera frame (x right, y down, z along the
//! optical axis) to a pixel and back. No function here divides by `z`: directions up to and
//! beyond 90° off-axis are first-class, which is what the Insta360 X5 lenses need.
//!
//! Two models are provided:
//! - [`Kb4`], Kannala–Brandt with four radial terms, parameters `[fx, fy, cx, cy, k1, k2, k3, k4]`
//!   (OpenCV `cv::fisheye`, Kalibr `pinhole`/`equidistant`, Basalt `kb4`);
//! - [`DoubleSphere`], Usenko et al. 2018, parameters `[fx, fy, cx, cy, xi, alpha]`
//!   (Kalibr `ds`/`none`, Basalt `ds`).
//!
//! Pixel centres are at integer coordinates. Failure (a direction outside the model's valid
//! cone, a pixel outside its image circle, a Newton solve that does not converge) is `None`,
//! never a garbage value.

use nalgebra::{Matrix2x3, Matrix2xX, Point2, Unit, Vector3};
use serde::{Deserialize, Serialize};

use crate::error::{CoreError, Result};

/// Which projection a camera uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CameraModelKind {
    /// Kannala–Brandt with four radial coefficients.
    Kb4,
    /// Double Sphere (Usenko, Demmel, Cremers 2018).
    DoubleSphere,
}

impl std::fmt::Display for CameraModelKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::Kb4 => "kb4",
            Self::DoubleSphere => "double_sphere",
        })
    }
}

/// A central camera: projects directions to pixels and pixels back to unit bearings.
pub trait CameraModel: Send + Sync {
    /// The projection this camera uses.
    fn kind(&self) -> CameraModelKind;

    /// Image size in pixels `(width, height)`.
    fn resolution(&self) -> (u32, u32);

    /// The model's parameters in their documented order.
    fn params(&self) -> &[f64];

    /// Replace the parameters (same order as [`CameraModel::params`]); validated.
    fn set_params(&mut self, params: &[f64]) -> Result<()>;

    /// Full apex angle (rad) of the cone of directions that project validly and one-to-one.
    fn valid_fov(&self) -> f64;

    /// Project a direction (any non-zero length) to a pixel, or `None` outside the valid cone.
    /// Models override it to skip the derivatives; the pixel is the one
    /// [`CameraModel::project_with_jacobians`] gives, to the bit.
    fn project(&self, point: &Vector3<f64>) -> Option<Point2<f64>> {
        self.project_with_jacobians(point, None).map(|(p, _)| p)
    }

    /// Project and return `d pixel / d point` (2×3); if `d_params` is given (2 × number of
    /// parameters, allocated once by the caller), also fill `d pixel / d params`.
    fn project_with_jacobians(
        &self,
        point: &Vector3<f64>,
        d_params: Option<&mut Matrix2xX<f64>>,
    ) -> Option<(Point2<f64>, Matrix2x3<f64>)>;

    /// The unit bearing vector of a pixel, or `None` outside the image circle.
    fn unproject(&self, pixel: &Point2<f64>) -> Option<Unit<Vector3<f64>>>;

    /// Whether a pixel lies inside the image rectangle (pixel centres at integers).
    fn in_image(&self, pixel: &Point2<f64>) -> bool {
        let (w, h) = self.resolution();
        pixel.x >= -0.5
            && pixel.y >= -0.5
            && pixel.x < f64::from(w) - 0.5
            && pixel.y < f64::from(h) - 0.5
    }
}

/// True for a finite number greater than zero (false for NaN).
fn positive_finite(x: f64) -> bool {
    x.is_finite() && x > 0.0
}

/// Check the resolution and the four pinhole-like parameters shared by both models.
fn validate_common(
    model: &str,
    width: u32,
    height: u32,
    params: &[f64],
    names: &[&str],
) -> Result<()> {
    if params.len() != names.len() {
        return Err(CoreError::invalid_value(
            format!("{model}.params"),
            format!("{} values ({})", names.len(), names.join(", ")),
            format!("{} values", params.len()),
            "pass the parameters in the documented order",
        ));
    }
    if width == 0 || height == 0 {
        return Err(CoreError::invalid_value(
            format!("{model}.resolution"),
            "a positive width and height in pixels",
            format!("{width}x{height}"),
            "set the lens image size",
        ));
    }
    for (value, name) in params.iter().zip(names) {
        if !value.is_finite() {
            return Err(CoreError::invalid_value(
                format!("{model}.{name}"),
                "a finite number",
                value.to_string(),
                "re-run the calibration or fix the file",
            ));
        }
    }
    for (i, name) in names.iter().enumerate().take(2) {
        if params[i] <= 0.0 {
            return Err(CoreError::invalid_value(
                format!("{model}.{name}"),
                "a positive focal length in pixels",
                params[i].to_string(),
                "focal lengths are in pixels and must be > 0; check the sign and units",
            ));
        }
    }
    Ok(())
}

// ---------------------------------------------------------------------------------------------
// Kannala–Brandt (KB4)
// ---------------------------------------------------------------------------------------------

/// Parameter names of [`Kb4`] in order.
pub const KB4_PARAM_NAMES: [&str; 8] = ["fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4"];

/// Below this ratio of off-axis radius to norm a direction counts as on the axis, where the
/// KB4 formulas switch to their pinhole limit (x/r is undefined at r = 0).
const KB4_ON_AXIS: f64 = 1e-10;
/// Step (rad) of the scan for the first stationary point of the KB4 radial polynomial.
const KB4_MONOTONIC_SCAN_STEP: f64 = 1e-3;
/// Newton iterations allowed when inverting the KB4 radial polynomial; it converges in < 10.
const KB4_NEWTON_MAX_ITERATIONS: usize = 50;
/// Residual (normalized image radius) at which the KB4 Newton solve has converged.
const KB4_NEWTON_TOLERANCE: f64 = 1e-14;

/// Kannala–Brandt fisheye with four radial terms: `r(θ) = θ (1 + k1 θ² + k2 θ⁴ + k3 θ⁶ + k4 θ⁸)`,
/// with `θ = atan2(√(x²+y²), z)` so directions beyond 90° off-axis project correctly.
#[derive(Debug, Clone, PartialEq)]
pub struct Kb4 {
    params: [f64; 8],
    width: u32,
    height: u32,
    /// Largest θ (rad) where `r(θ)` is still increasing: beyond it the model is not one-to-one.
    max_theta: f64,
}

impl Kb4 {
    /// A KB4 camera with parameters `[fx, fy, cx, cy, k1, k2, k3, k4]`; validated.
    pub fn new(width: u32, height: u32, params: [f64; 8]) -> Result<Self> {
        let mut camera = Self {
            params,
            width,
            height,
            max_theta: 0.0,
        };
        camera.set_params(&params)?;
        Ok(camera)
    }

    fn radial(&self, theta: f64) -> (f64, f64) {
        let k = &self.params[4..8];
        let t2 = theta * theta;
        let poly = self.radial_poly(theta);
        let d_poly =
            1.0 + t2 * (3.0 * k[0] + t2 * (5.0 * k[1] + t2 * (7.0 * k[2] + t2 * 9.0 * k[3])));
        (theta * poly, d_poly)
    }

    /// `1 + k1 θ² + k2 θ⁴ + k3 θ⁶ + k4 θ⁸` (the radius is θ times this).
    #[inline]
    fn radial_poly(&self, theta: f64) -> f64 {
        let k = &self.params[4..8];
        let t2 = theta * theta;
        1.0 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3])))
    }

    /// Where a direction lies for projection: on the axis (a pinhole to first order), or off it
    /// at angle `theta`; `None` when it does not project (zero or non-finite, straight behind,
    /// or beyond the valid cone).
    #[inline]
    fn ray_angle(&self, point: &Vector3<f64>) -> Option<Kb4Ray> {
        let (x, y, z) = (point.x, point.y, point.z);
        let r2 = x * x + y * y;
        let r = r2.sqrt();
        let norm = (r2 + z * z).sqrt();
        if !positive_finite(norm) {
            return None;
        }
        if r < KB4_ON_AXIS * norm {
            // On the axis: the model is a pinhole to first order. Straight behind is invalid.
            return (z > 0.0).then_some(Kb4Ray::OnAxis);
        }
        let theta = r.atan2(z);
        (theta <= self.max_theta).then_some(Kb4Ray::OffAxis { r2, r, theta })
    }

    /// The first θ in `(0, π]` where `dr/dθ` stops being positive (π if it never does).
    fn monotonic_limit(&self) -> f64 {
        let pi = std::f64::consts::PI;
        let mut prev = 0.0;
        let mut theta = KB4_MONOTONIC_SCAN_STEP;
        while theta <= pi {
            if self.radial(theta).1 <= 0.0 {
                // Bisect the sign change between prev and theta.
                let (mut lo, mut hi) = (prev, theta);
                for _ in 0..60 {
                    let mid = 0.5 * (lo + hi);
                    if self.radial(mid).1 > 0.0 {
                        lo = mid;
                    } else {
                        hi = mid;
                    }
                }
                return lo;
            }
            prev = theta;
            theta += KB4_MONOTONIC_SCAN_STEP;
        }
        pi
    }
}

/// A direction's place for [`Kb4`] projection (see [`Kb4::ray_angle`]).
#[derive(Debug, Clone, Copy)]
enum Kb4Ray {
    /// Within [`KB4_ON_AXIS`] of the axis, in front.
    OnAxis,
    /// Off the axis: `r² = x² + y²`, `r`, and the angle from the axis `theta` (rad).
    OffAxis { r2: f64, r: f64, theta: f64 },
}

impl CameraModel for Kb4 {
    fn kind(&self) -> CameraModelKind {
        CameraModelKind::Kb4
    }

    fn resolution(&self) -> (u32, u32) {
        (self.width, self.height)
    }

    fn params(&self) -> &[f64] {
        &self.params
    }

    fn set_params(&mut self, params: &[f64]) -> Result<()> {
        validate_common("kb4", self.width, self.height, params, &KB4_PARAM_NAMES)?;
        self.params.copy_from_slice(params);
        self.max_theta = self.monotonic_limit();
        if self.max_theta < 0.1 {
            return Err(CoreError::invalid_value(
                "kb4.k1..k4",
                "coefficients whose radial polynomial increases over the field of view",
                format!(
                    "a polynomial that turns back at θ = {:.3} rad",
                    self.max_theta
                ),
                "re-run the calibration; the coefficients are not a valid lens",
            ));
        }
        Ok(())
    }

    fn valid_fov(&self) -> f64 {
        2.0 * self.max_theta
    }

    fn project(&self, point: &Vector3<f64>) -> Option<Point2<f64>> {
        let [fx, fy, cx, cy, ..] = self.params;
        let (x, y, z) = (point.x, point.y, point.z);
        match self.ray_angle(point)? {
            Kb4Ray::OnAxis => Some(Point2::new(fx * x / z + cx, fy * y / z + cy)),
            Kb4Ray::OffAxis { r, theta, .. } => {
                let d = theta * self.radial_poly(theta);
                let (ux, uy) = (x / r, y / r);
                Some(Point2::new(fx * (d * ux) + cx, fy * (d * uy) + cy))
            }
        }
    }

    fn project_with_jacobians(
        &self,
        point: &Vector3<f64>,
        d_params: Option<&mut Matrix2xX<f64>>,
    ) -> Option<(Point2<f64>, Matrix2x3<f64>)> {
        let [fx, fy, cx, cy, ..] = self.params;
        let (x, y, z) = (point.x, point.y, point.z);
        let (r2, r, theta) = match self.ray_angle(point)? {
            Kb4Ray::OffAxis { r2, r, theta } => (r2, r, theta),
            Kb4Ray::OnAxis => {
                let pixel = Point2::new(fx * x / z + cx, fy * y / z + cy);
                let j = Matrix2x3::new(
                    fx / z,
                    0.0,
                    -fx * x / (z * z),
                    0.0,
                    fy / z,
                    -fy * y / (z * z),
                );
                if let Some(dp) = d_params {
                    dp.fill(0.0);
                    dp[(0, 0)] = x / z;
                    dp[(1, 1)] = y / z;
                    dp[(0, 2)] = 1.0;
                    dp[(1, 3)] = 1.0;
                }
                return Some((pixel, j));
            }
        };
        let (d, d_prime) = self.radial(theta);
        let (ux, uy) = (x / r, y / r);
        let mx = d * ux;
        let my = d * uy;
        let pixel = Point2::new(fx * mx + cx, fy * my + cy);

        let rho2 = r2 + z * z;
        let dtheta = Vector3::new(z * ux / rho2, z * uy / rho2, -r / rho2);
        let r3 = r2 * r;
        let dmx = Vector3::new(
            d_prime * dtheta.x * ux + d * y * y / r3,
            d_prime * dtheta.y * ux - d * x * y / r3,
            d_prime * dtheta.z * ux,
        );
        let dmy = Vector3::new(
            d_prime * dtheta.x * uy - d * x * y / r3,
            d_prime * dtheta.y * uy + d * x * x / r3,
            d_prime * dtheta.z * uy,
        );
        let j = Matrix2x3::new(
            fx * dmx.x,
            fx * dmx.y,
            fx * dmx.z,
            fy * dmy.x,
            fy * dmy.y,
            fy * dmy.z,
        );
        if let Some(dp) = d_params {
            dp.fill(0.0);
            dp[(0, 0)] = mx;
            dp[(1, 1)] = my;
            dp[(0, 2)] = 1.0;
            dp[(1, 3)] = 1.0;
            let mut power = theta * theta * theta;
            for k in 0..4 {
                dp[(0, 4 + k)] = fx * power * ux;
                dp[(1, 4 + k)] = fy * power * uy;
                power *= theta * theta;
            }
        }
        Some((pixel, j))
    }

    fn unproject(&self, pixel: &Point2<f64>) -> Option<Unit<Vector3<f64>>> {
        let [fx, fy, cx, cy, ..] = self.params;
        let mx = (pixel.x - cx) / fx;
        let my = (pixel.y - cy) / fy;
        let rho = (mx * mx + my * my).sqrt();
        if !rho.is_finite() {
            return None;
        }
        if rho < KB4_ON_AXIS {
            return Some(Unit::new_normalize(Vector3::new(mx, my, 1.0)));
        }
        // Safeguarded Newton on [0, max_theta], where r(θ) is increasing.
        let (r_max, _) = self.radial(self.max_theta);
        if rho > r_max {
            return None;
        }
        let (mut lo, mut hi) = (0.0, self.max_theta);
        let mut theta = rho.min(self.max_theta);
        let mut converged = false;
        for _ in 0..KB4_NEWTON_MAX_ITERATIONS {
            let (d, d_prime) = self.radial(theta);
            let f = d - rho;
            if f.abs() <= KB4_NEWTON_TOLERANCE * (1.0 + rho) {
                converged = true;
                break;
            }
            if f > 0.0 {
                hi = theta;
            } else {
                lo = theta;
            }
            let newton = theta - f / d_prime;
            theta = if d_prime > 0.0 && newton > lo && newton < hi {
                newton
            } else {
                0.5 * (lo + hi)
            };
        }
        if !converged {
            return None;
        }
        let (s, c) = theta.sin_cos();
        Some(Unit::new_normalize(Vector3::new(
            s * mx / rho,
            s * my / rho,
            c,
        )))
    }
}

// ---------------------------------------------------------------------------------------------
// Double Sphere
// ---------------------------------------------------------------------------------------------

/// Parameter names of [`DoubleSphere`] in order.
pub const DS_PARAM_NAMES: [&str; 6] = ["fx", "fy", "cx", "cy", "xi", "alpha"];

/// Double Sphere model (Usenko, Demmel, Cremers, 3DV 2018), parameters `[fx, fy, cx, cy, ξ, α]`.
#[derive(Debug, Clone, PartialEq)]
pub struct DoubleSphere {
    params: [f64; 6],
    width: u32,
    height: u32,
}

impl DoubleSphere {
    /// A Double Sphere camera with parameters `[fx, fy, cx, cy, xi, alpha]`; validated.
    pub fn new(width: u32, height: u32, params: [f64; 6]) -> Result<Self> {
        let mut camera = Self {
            params,
            width,
            height,
        };
        camera.set_params(&params)?;
        Ok(camera)
    }

    /// The paper's `w2`: a direction is valid when `z > −w2 · |p|`.
    fn w2(&self) -> f64 {
        let xi = self.params[4];
        let alpha = self.params[5];
        let w1 = if alpha <= 0.5 {
            alpha / (1.0 - alpha)
        } else {
            (1.0 - alpha) / alpha
        };
        (w1 + xi) / (2.0 * w1 * xi + xi * xi + 1.0).sqrt()
    }
}

/// The intermediate terms of a [`DoubleSphere`] projection.
#[derive(Debug, Clone, Copy)]
struct DsTerms {
    /// Distance of the point from the first sphere's centre.
    d1: f64,
    /// `xi d1 + z`.
    zz: f64,
    /// Distance from the second sphere's centre.
    d2: f64,
    /// The projection's denominator.
    den: f64,
}

impl DoubleSphere {
    /// The projection's terms, or `None` when the direction does not project.
    #[inline]
    fn terms(&self, point: &Vector3<f64>) -> Option<DsTerms> {
        let [.., xi, alpha] = self.params;
        let (x, y, z) = (point.x, point.y, point.z);
        let d1 = (x * x + y * y + z * z).sqrt();
        if !positive_finite(d1) || z <= -self.w2() * d1 {
            return None;
        }
        let zz = xi * d1 + z;
        let d2 = (x * x + y * y + zz * zz).sqrt();
        let den = alpha * d2 + (1.0 - alpha) * zz;
        positive_finite(den).then_some(DsTerms { d1, zz, d2, den })
    }
}

impl CameraModel for DoubleSphere {
    fn kind(&self) -> CameraModelKind {
        CameraModelKind::DoubleSphere
    }

    fn resolution(&self) -> (u32, u32) {
        (self.width, self.height)
    }

    fn params(&self) -> &[f64] {
        &self.params
    }

    fn set_params(&mut self, params: &[f64]) -> Result<()> {
        validate_common(
            "double_sphere",
            self.width,
            self.height,
            params,
            &DS_PARAM_NAMES,
        )?;
        let alpha = params[5];
        if !(0.0..1.0).contains(&alpha) {
            return Err(CoreError::invalid_value(
                "double_sphere.alpha",
                "a value in [0, 1)",
                alpha.to_string(),
                "re-run the calibration; alpha outside [0, 1) is not a valid double-sphere lens",
            ));
        }
        let xi = params[4];
        if !(-1.0..=2.0).contains(&xi) {
            return Err(CoreError::invalid_value(
                "double_sphere.xi",
                "a value in [-1, 2]",
                xi.to_string(),
                "re-run the calibration; typical fisheye lenses have xi in [-0.5, 1]",
            ));
        }
        self.params.copy_from_slice(params);
        Ok(())
    }

    fn valid_fov(&self) -> f64 {
        2.0 * (-self.w2()).clamp(-1.0, 1.0).acos()
    }

    fn project(&self, point: &Vector3<f64>) -> Option<Point2<f64>> {
        let [fx, fy, cx, cy, ..] = self.params;
        let (x, y) = (point.x, point.y);
        let DsTerms { den, .. } = self.terms(point)?;
        Some(Point2::new(fx * x / den + cx, fy * y / den + cy))
    }

    fn project_with_jacobians(
        &self,
        point: &Vector3<f64>,
        d_params: Option<&mut Matrix2xX<f64>>,
    ) -> Option<(Point2<f64>, Matrix2x3<f64>)> {
        let [fx, fy, cx, cy, xi, alpha] = self.params;
        let (x, y) = (point.x, point.y);
        let DsTerms { d1, zz, d2, den } = self.terms(point)?;
        let pixel = Point2::new(fx * x / den + cx, fy * y / den + cy);

        let dd1 = point / d1;
        let dzz = dd1 * xi + Vector3::z();
        let dd2 = (Vector3::new(x, y, 0.0) + dzz * zz) / d2;
        let dden = dd2 * alpha + dzz * (1.0 - alpha);
        let den2 = den * den;
        let j = Matrix2x3::new(
            fx * (den - x * dden.x) / den2,
            -fx * x * dden.y / den2,
            -fx * x * dden.z / den2,
            -fy * y * dden.x / den2,
            fy * (den - y * dden.y) / den2,
            -fy * y * dden.z / den2,
        );
        if let Some(dp) = d_params {
            dp.fill(0.0);
            dp[(0, 0)] = x / den;
            dp[(1, 1)] = y / den;
            dp[(0, 2)] = 1.0;
            dp[(1, 3)] = 1.0;
            let dden_dxi = alpha * zz * d1 / d2 + (1.0 - alpha) * d1;
            let dden_dalpha = d2 - zz;
            dp[(0, 4)] = -fx * x * dden_dxi / den2;
            dp[(1, 4)] = -fy * y * dden_dxi / den2;
            dp[(0, 5)] = -fx * x * dden_dalpha / den2;
            dp[(1, 5)] = -fy * y * dden_dalpha / den2;
        }
        Some((pixel, j))
    }

    fn unproject(&self, pixel: &Point2<f64>) -> Option<Unit<Vector3<f64>>> {
        let [fx, fy, cx, cy, xi, alpha] = self.params;
        let mx = (pixel.x - cx) / fx;
        let my = (pixel.y - cy) / fy;
        let r2 = mx * mx + my * my;
        if !r2.is_finite() {
            return None;
        }
        let radicand = 1.0 - (2.0 * alpha - 1.0) * r2;
        if radicand < 0.0 {
            return None;
        }
        let mz = (1.0 - alpha * alpha * r2) / (alpha * radicand.sqrt() + 1.0 - alpha);
        let inner = mz * mz + (1.0 - xi * xi) * r2;
        if inner < 0.0 {
            return None;
        }
        let k = (mz * xi + inner.sqrt()) / (mz * mz + r2);
        let bearing = Vector3::new(k * mx, k * my, k * mz - xi);
        let n = bearing.norm();
        if !positive_finite(n) || bearing.z <= -self.w2() * n {
            return None;
        }
        Some(Unit::new_unchecked(bearing / n))
    }
}

// ---------------------------------------------------------------------------------------------
// A concrete camera of either model
// ---------------------------------------------------------------------------------------------

/// A camera of either supported model, for code that reads the model from a file.
#[derive(Debug, Clone, PartialEq)]
pub enum Camera {
    /// Kannala–Brandt.
    Kb4(Kb4),
    /// Double Sphere.
    DoubleSphere(DoubleSphere),
}

impl Camera {
    fn inner(&self) -> &dyn CameraModel {
        match self {
            Self::Kb4(c) => c,
            Self::DoubleSphere(c) => c,
        }
    }

    fn inner_mut(&mut self) -> &mut dyn CameraModel {
        match self {
            Self::Kb4(c) => c,
            Self::DoubleSphere(c) => c,
        }
    }
}

impl CameraModel for Camera {
    fn kind(&self) -> CameraModelKind {
        self.inner().kind()
    }
    fn resolution(&self) -> (u32, u32) {
        self.inner().resolution()
    }
    fn params(&self) -> &[f64] {
        self.inner().params()
    }
    fn set_params(&mut self, params: &[f64]) -> Result<()> {
        self.inner_mut().set_params(params)
    }
    fn valid_fov(&self) -> f64 {
        self.inner().valid_fov()
    }
    fn project(&self, point: &Vector3<f64>) -> Option<Point2<f64>> {
        self.inner().project(point)
    }
    fn project_with_jacobians(
        &self,
        point: &Vector3<f64>,
        d_params: Option<&mut Matrix2xX<f64>>,
    ) -> Option<(Point2<f64>, Matrix2x3<f64>)> {
        self.inner().project_with_jacobians(point, d_params)
    }
    fn unproject(&self, pixel: &Point2<f64>) -> Option<Unit<Vector3<f64>>> {
        self.inner().unproject(pixel)
    }
}

/// The unit direction at angle `theta` off the optical axis and azimuth `phi` (rad).
pub fn bearing_from_angles(theta: f64, phi: f64) -> Unit<Vector3<f64>> {
    let (st, ct) = theta.sin_cos();
    let (sp, cp) = phi.sin_cos();
    Unit::new_normalize(Vector3::new(st * cp, st * sp, ct))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn project_gives_the_pixel_of_project_with_jacobians_to_the_bit() {
        let kb4 = Kb4::new(
            960,
            960,
            [301.5, 300.9, 479.2, 481.7, -0.021, 0.0013, -0.0004, 0.00002],
        )
        .unwrap();
        let ds = DoubleSphere::new(960, 960, [310.0, 309.0, 480.5, 479.5, -0.2, 0.57]).unwrap();
        let cameras: [(&str, &dyn CameraModel); 4] = [
            ("kb4", &kb4),
            ("ds", &ds),
            ("camera kb4", &Camera::Kb4(kb4.clone())),
            ("camera ds", &Camera::DoubleSphere(ds.clone())),
        ];
        // Directions over the whole sphere (a spiral), the axis and next to it, behind, zero.
        let mut directions: Vec<Vector3<f64>> = (0..4000)
            .map(|i| {
                let z = 1.0 - 2.0 * (f64::from(i) + 0.5) / 4000.0;
                let phi = f64::from(i) * 2.399_963_229_728_653;
                let r = (1.0 - z * z).sqrt();
                Vector3::new(r * phi.cos(), r * phi.sin(), z) * (0.3 + f64::from(i % 7))
            })
            .collect();
        directions.extend([
            Vector3::new(0.0, 0.0, 2.0),
            Vector3::new(1e-12, -1e-12, 1.0),
            Vector3::new(0.0, 0.0, -1.0),
            Vector3::zeros(),
            Vector3::new(f64::NAN, 0.0, 1.0),
        ]);
        for (name, cam) in cameras {
            let mut projected = 0;
            for d in &directions {
                let fast = cam.project(d);
                let full = cam.project_with_jacobians(d, None).map(|(p, _)| p);
                match (fast, full) {
                    (Some(a), Some(b)) => {
                        assert!(
                            a.x.to_bits() == b.x.to_bits() && a.y.to_bits() == b.y.to_bits(),
                            "{name} {d:?}: {a:?} vs {b:?}"
                        );
                        projected += 1;
                    }
                    (None, None) => {}
                    other => panic!("{name} {d:?}: {other:?}"),
                }
            }
            assert!(
                projected > 2000,
                "{name}: only {projected} directions projected"
            );
        }
    }

    #[test]
    fn kb4_rejects_bad_parameters() {
        assert!(Kb4::new(960, 960, [-300.0, 300.0, 480.0, 480.0, 0.0, 0.0, 0.0, 0.0]).is_err());
        assert!(
            Kb4::new(
                960,
                960,
                [300.0, f64::NAN, 480.0, 480.0, 0.0, 0.0, 0.0, 0.0]
            )
            .is_err()
        );
        assert!(Kb4::new(0, 960, [300.0, 300.0, 480.0, 480.0, 0.0, 0.0, 0.0, 0.0]).is_err());
        // A polynomial that turns back almost at once is not a lens.
        assert!(Kb4::new(960, 960, [300.0, 300.0, 480.0, 480.0, -50.0, 0.0, 0.0, 0.0]).is_err());
    }

    #[test]
    fn kb4_reports_failure_outside_its_cone() {
        let cam = Kb4::new(
            960,
            960,
            [300.0, 300.0, 480.0, 480.0, -0.02, 0.001, 0.0, 0.0],
        )
        .unwrap();
        assert!(cam.project(&Vector3::new(0.0, 0.0, -1.0)).is_none());
        assert!(cam.project(&Vector3::zeros()).is_none());
        assert!(cam.unproject(&Point2::new(1e9, 480.0)).is_none());
        assert!(cam.unproject(&Point2::new(f64::NAN, 480.0)).is_none());
    }

    #[test]
    fn ds_rejects_bad_parameters_and_directions() {
        assert!(DoubleSphere::new(960, 960, [300.0, 300.0, 480.0, 480.0, -0.2, 1.5]).is_err());
        let cam = DoubleSphere::new(960, 960, [300.0, 300.0, 480.0, 480.0, -0.2, 0.6]).unwrap();
        assert!(cam.project(&Vector3::new(0.0, 0.0, -1.0)).is_none());
        assert!(cam.unproject(&Point2::new(1e6, 1e6)).is_none());
    }
}
