//! Masks of what moves with a wrist camera, for the scene exports: the tool's jaws and body tag
//! (from the tool definition, at the frame's gripper opening) and the camera's own body at the
//! rim of the lens field. A splat trainer that fits them would grow floaters near every lens,
//! so each exported image gets a mask that tells it which pixels to ignore.
//!
//! A mask is an 8-bit grey image of the frame's size: [`KEEP`] (255) where the pixel sees the
//! scene, [`IGNORE`] (0) where it sees the tool or the camera body — the convention of 3DGUT
//! (`<image>_mask.png`) and nerfstudio (`mask_path`).

use image::GrayImage;
use nalgebra::{Point2, Vector3};
use rayon::prelude::*;

use kiwi_core::camera::{Camera, CameraModel};
use kiwi_core::geometry::Pose;
use kiwi_core::tool::{ToolDefinition, ToolSolid};

/// Mask value of a pixel that sees the scene.
pub const KEEP: u8 = 255;
/// Mask value of a pixel a trainer ignores (tool, jaws, camera body).
pub const IGNORE: u8 = 0;
/// Grown onto every tool part (m): a printed tool deviates from its definition by about a
/// millimetre, and a part seen 5 cm away shifts by as much under a 1° calibration error.
pub const SOLID_MARGIN_M: f64 = 0.002;
/// Pixels grown around the masked area: a pixel only partly covered by the tool blends both,
/// and lens blur spreads an edge over about a pixel.
pub const DILATE_PX: usize = 2;
/// A measured opening is masked with the jaws anywhere within this fraction of the tool's
/// range of it: the estimate's error and the jaws' motion between the measured frames.
pub const OPENING_TOLERANCE_FRACTION: f64 = 0.05;
/// Below this opening confidence the measurement is not trusted and the jaws are masked over
/// their whole range (the estimator's confidence is dot coverage times a fit-quality factor;
/// under 0.3 fewer than a third of the dots carried it).
pub const MIN_OPENING_CONFIDENCE: f64 = 0.3;

/// The openings whose jaws a frame's mask covers: the measured opening with its tolerance band
/// when it is trusted, else the tool's whole range.
pub fn mask_openings(def: &ToolDefinition, opening: Option<f64>, confidence: f64) -> Vec<f64> {
    let sweep = def.sweep_openings();
    let range = def.jaws.max_opening.max(0.0);
    let Some(o) = opening.filter(|o| o.is_finite() && confidence >= MIN_OPENING_CONFIDENCE) else {
        return sweep;
    };
    let step = match sweep.as_slice() {
        [a, b, ..] => b - a,
        _ => return vec![o.clamp(0.0, range)],
    };
    let tolerance = OPENING_TOLERANCE_FRACTION * range;
    let lo = (o - tolerance).clamp(0.0, range);
    let hi = (o + tolerance).clamp(0.0, range);
    let steps = (((hi - lo) / step).ceil() as usize).max(1);
    (0..=steps)
        .map(|k| lo + (hi - lo) * k as f64 / steps as f64)
        .collect()
}

/// A tool part in a lens's frame, grown by the margin, with a cone that bounds it.
struct LensSolid {
    /// `solid_from_lens`.
    solid_from_lens: Pose,
    half: Vector3<f64>,
    /// Unit direction from the lens centre to the part's centre.
    axis: Vector3<f64>,
    /// Cosine of the bounding cone's half angle; -1 when the lens sits inside the bounding
    /// sphere.
    cos_half_angle: f64,
}

/// Per-pixel rays of one lens, built once and used for every frame's mask.
pub struct LensMasker {
    width: usize,
    height: usize,
    /// Unit ray per pixel centre (KIWI's pixel convention), `None` where the pixel is outside
    /// the lens's valid field: the camera body, or no ray at all.
    rays: Vec<Option<Vector3<f32>>>,
    /// `lens_from_front`: where the tool (defined in the front-lens frame) sits for this lens.
    lens_from_front: Pose,
}

impl LensMasker {
    /// Rays of every pixel of `camera`; pixels more than half of `valid_fov_rad` off the axis
    /// see the camera body and are always ignored. `lens_from_front` is the identity for the
    /// front lens.
    pub fn new(camera: &Camera, valid_fov_rad: f64, lens_from_front: Pose) -> Self {
        let (w, h) = camera.resolution();
        let (width, height) = (w as usize, h as usize);
        let cos_limit = (valid_fov_rad / 2.0).cos();
        let rays = (0..height)
            .into_par_iter()
            .flat_map_iter(|y| {
                (0..width).map(move |x| {
                    camera
                        .unproject(&Point2::new(x as f64, y as f64))
                        .map(|b| b.normalize())
                        .filter(|b| b.z >= cos_limit)
                        .map(nalgebra::Matrix::cast::<f32>)
                })
            })
            .collect();
        Self {
            width,
            height,
            rays,
            lens_from_front,
        }
    }

    /// Image width and height (px).
    pub fn size(&self) -> (usize, usize) {
        (self.width, self.height)
    }

    /// The mask of a frame whose tool parts are `solids` (front-lens frame).
    pub fn mask(&self, solids: &[ToolSolid]) -> GrayImage {
        let parts: Vec<LensSolid> = solids.iter().map(|s| self.in_lens(s)).collect();
        let mut ignore: Vec<bool> = self
            .rays
            .par_iter()
            .map(|ray| match ray {
                None => true,
                Some(r) => {
                    let r = r.cast::<f64>();
                    parts.iter().any(|p| hits(p, &r))
                }
            })
            .collect();
        dilate(&mut ignore, self.width, self.height, DILATE_PX);
        let pixels = ignore
            .iter()
            .map(|&i| if i { IGNORE } else { KEEP })
            .collect();
        // One value per pixel of this lens, so the buffer always fits; the fallback (everything
        // ignored) is never taken.
        GrayImage::from_raw(self.width as u32, self.height as u32, pixels)
            .unwrap_or_else(|| GrayImage::new(self.width as u32, self.height as u32))
    }

    fn in_lens(&self, solid: &ToolSolid) -> LensSolid {
        let lens_from_solid = self.lens_from_front * solid.front_from_solid;
        let half = solid.half_m.add_scalar(SOLID_MARGIN_M);
        let centre = lens_from_solid.translation.vector;
        let distance = centre.norm();
        let radius = half.norm();
        let (axis, cos_half_angle) = if distance > radius {
            (
                centre / distance,
                (1.0 - (radius / distance).powi(2)).sqrt(),
            )
        } else {
            (Vector3::z(), -1.0)
        };
        LensSolid {
            solid_from_lens: lens_from_solid.inverse(),
            half,
            axis,
            cos_half_angle,
        }
    }
}

/// Whether the unit ray `r` from the lens centre meets the box (slab test in the box's frame).
fn hits(p: &LensSolid, r: &Vector3<f64>) -> bool {
    if r.dot(&p.axis) < p.cos_half_angle {
        return false;
    }
    let o = p.solid_from_lens.translation.vector;
    let d = p.solid_from_lens.rotation * r;
    let mut near = f64::NEG_INFINITY;
    let mut far = f64::INFINITY;
    for k in 0..3 {
        if d[k].abs() < 1e-12 {
            if o[k].abs() > p.half[k] {
                return false;
            }
            continue;
        }
        let a = (-p.half[k] - o[k]) / d[k];
        let b = (p.half[k] - o[k]) / d[k];
        near = near.max(a.min(b));
        far = far.min(a.max(b));
    }
    near <= far && far > 0.0
}

/// Grow the `true` area by `radius` pixels (a square window, rows then columns).
fn dilate(mask: &mut [bool], width: usize, height: usize, radius: usize) {
    if radius == 0 || width == 0 || height == 0 {
        return;
    }
    let mut tmp = vec![false; mask.len()];
    for y in 0..height {
        let row = &mask[y * width..(y + 1) * width];
        // Distance back to the last set pixel, forwards and backwards.
        let mut last: Option<usize> = None;
        for x in 0..width {
            if row[x] {
                last = Some(x);
            }
            tmp[y * width + x] = last.is_some_and(|l| x - l <= radius);
        }
        last = None;
        for x in (0..width).rev() {
            if row[x] {
                last = Some(x);
            }
            if last.is_some_and(|l| l - x <= radius) {
                tmp[y * width + x] = true;
            }
        }
    }
    for x in 0..width {
        let mut last: Option<usize> = None;
        for y in 0..height {
            if tmp[y * width + x] {
                last = Some(y);
            }
            mask[y * width + x] = last.is_some_and(|l| y - l <= radius);
        }
        last = None;
        for y in (0..height).rev() {
            if tmp[y * width + x] {
                last = Some(y);
            }
            if last.is_some_and(|l| l - y <= radius) {
                mask[y * width + x] = true;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]

    use super::*;
    use kiwi_core::layout::ToolKind;
    use kiwi_fixtures::render::{Extras, LensRays, RenderOptions, render};
    use kiwi_fixtures::scene::{Scene, SceneOptions};
    use kiwi_fixtures::tools::ToolGeometry;
    use kiwi_fixtures::unit::{LensModel, SimUnit};

    /// The pixels the simulator draws the tool on (a render with the tool against one without).
    fn tool_pixels(kind: ToolKind, opening: f64, rays: &LensRays, scene: &Scene) -> Vec<bool> {
        let tool = ToolGeometry::nominal(kind).unwrap();
        let texture = tool.tag_texture().unwrap();
        let pose = |_t: f64| Pose::identity();
        let options = RenderOptions::default();
        let with = Extras {
            items: tool.items(opening, &texture),
            hide_room: true,
            ..Extras::default()
        };
        let without = Extras {
            hide_room: true,
            ..Extras::default()
        };
        let a = render(scene, rays, &pose, 0.0, &with, &options);
        let b = render(scene, rays, &pose, 0.0, &without, &options);
        a.pixels().zip(b.pixels()).map(|(p, q)| p != q).collect()
    }

    #[test]
    fn masks_cover_every_tool_pixel_the_simulator_draws_and_little_else() {
        let scene = Scene::new(1, SceneOptions::default());
        let cases = [
            (ToolKind::Chopstick, [0.05, 0.4, 0.75]),
            (ToolKind::ParallelJaw, [0.003, 0.04, 0.085]),
        ];
        for model in [LensModel::Kb4, LensModel::Ds] {
            let unit = SimUnit::x5("M", 7, 320, model).unwrap();
            let camera = &unit.lenses[0].camera;
            let rays = LensRays::new(camera);
            let masker = LensMasker::new(camera, 195f64.to_radians(), Pose::identity());
            let body = masker.mask(&[]);
            for (kind, openings) in cases {
                let def = ToolDefinition::builtin(kind).unwrap();
                let mut unknown_opening_union = vec![false; masker.rays.len()];
                let swept = masker.mask(
                    &mask_openings(&def, None, 0.0)
                        .iter()
                        .flat_map(|&o| def.solids(o))
                        .collect::<Vec<_>>(),
                );
                for opening in openings {
                    let tool = tool_pixels(kind, opening, &rays, &scene);
                    let solids: Vec<ToolSolid> = mask_openings(&def, Some(opening), 1.0)
                        .iter()
                        .flat_map(|&o| def.solids(o))
                        .collect();
                    let mask = masker.mask(&solids);
                    let drawn = tool.iter().filter(|&&t| t).count();
                    assert!(
                        drawn > 500,
                        "{kind:?} at {opening}: only {drawn} tool pixels"
                    );
                    let mut missed = 0;
                    let mut extra = 0;
                    for (i, (&t, (m, b))) in tool
                        .iter()
                        .zip(mask.pixels().zip(body.pixels()))
                        .enumerate()
                    {
                        if t {
                            unknown_opening_union[i] = true;
                            missed += usize::from(m.0[0] != IGNORE);
                        } else if m.0[0] == IGNORE && b.0[0] == KEEP {
                            extra += 1;
                        }
                    }
                    assert_eq!(
                        missed, 0,
                        "{model:?} {kind:?} at {opening}: tool pixels kept"
                    );
                    // The margins (2 mm on parts 3–24 mm across, 2 px) and the opening band grow
                    // the mask by about the tool's own area at this size (0.8–1.05 times
                    // measured; the fixed 2 px dominate at 320 px).
                    assert!(
                        2 * extra <= 3 * drawn,
                        "{model:?} {kind:?} at {opening}: {extra} extra pixels for {drawn} tool \
                         pixels"
                    );
                }
                // Unknown opening: the swept mask holds every opening's jaws.
                let missed = unknown_opening_union
                    .iter()
                    .zip(swept.pixels())
                    .filter(|(t, m)| **t && m.0[0] != IGNORE)
                    .count();
                assert_eq!(missed, 0, "{model:?} {kind:?}: swept mask misses jaws");
            }
        }
    }

    #[test]
    fn the_camera_body_ring_and_the_bare_hand() {
        let unit = SimUnit::x5("M", 7, 160, LensModel::Kb4).unwrap();
        let camera = &unit.lenses[0].camera;
        let masker = LensMasker::new(camera, 170f64.to_radians(), Pose::identity());
        let def = ToolDefinition::builtin(ToolKind::BareHand).unwrap();
        assert!(def.solids(0.0).is_empty());
        let mask = masker.mask(&def.solids(0.0));
        // A pixel is ignored exactly when a pixel within the dilation sees beyond 85° off the
        // axis (or has no ray).
        let (w, h) = camera.resolution();
        let beyond = |x: u32, y: u32| {
            camera
                .unproject(&Point2::new(f64::from(x), f64::from(y)))
                .is_none_or(|r| r.normalize().z.acos() > 85f64.to_radians())
        };
        let r = DILATE_PX as u32;
        let mut ring = 0;
        for (x, y, p) in mask.enumerate_pixels() {
            let expected = (y.saturating_sub(r)..=(y + r).min(h - 1))
                .any(|v| (x.saturating_sub(r)..=(x + r).min(w - 1)).any(|u| beyond(u, v)));
            assert_eq!(p.0[0] == IGNORE, expected, "({x}, {y})");
            ring += usize::from(expected);
        }
        assert!(ring > 0 && ring < (w * h) as usize / 2);
    }

    #[test]
    fn dilation_grows_by_the_radius() {
        let (w, h) = (9, 7);
        let mut m = vec![false; w * h];
        m[3 * w + 4] = true;
        dilate(&mut m, w, h, 2);
        for y in 0..h {
            for x in 0..w {
                let inside = x.abs_diff(4) <= 2 && y.abs_diff(3) <= 2;
                assert_eq!(m[y * w + x], inside, "({x}, {y})");
            }
        }
    }

    #[test]
    fn a_trusted_opening_gets_a_band_and_an_untrusted_one_the_range() {
        let def = ToolDefinition::builtin(ToolKind::ParallelJaw).unwrap();
        let band = mask_openings(&def, Some(0.05), 0.9);
        let tol = OPENING_TOLERANCE_FRACTION * def.jaws.max_opening;
        assert!((band[0] - (0.05 - tol)).abs() < 1e-12);
        assert!((band[band.len() - 1] - (0.05 + tol)).abs() < 1e-12);
        let range = mask_openings(&def, Some(0.05), 0.1);
        assert_eq!(range, def.sweep_openings());
        assert_eq!(range[0], 0.0);
        assert!((range[range.len() - 1] - def.jaws.max_opening).abs() < 1e-12);
        assert_eq!(mask_openings(&def, Some(f64::NAN), 1.0), range);
    }
}
