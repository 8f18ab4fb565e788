//! Per-frame jaw opening from the front lens: rectify the dot plane to a fronto-parallel view
//! through the fisheye model, segment the red dots, fit one line per jaw and measure the
//! opening (chopstick: angle between the jaw lines; parallel jaw: gap between the plates).

use kiwi_core::camera::{Camera, CameraModel};
use kiwi_core::layout::ToolKind;
use kiwi_core::tool::ToolDefinition;
use nalgebra::{Point2, Vector3};
use serde::Serialize;

use crate::error::{BackendError, Result};

/// Rectified pixels per source pixel at the window centre: a little oversampling keeps the
/// dot centroids from being quantized by the resampling grid.
const OVERSAMPLE: f64 = 1.5;
/// Bounds on the rectified scale (px/m) and size (px): protect against absurd definitions.
const MIN_PX_PER_M: f64 = 200.0;
const MAX_PX_PER_M: f64 = 20_000.0;
const MAX_RECT_PIXELS: usize = 4_000_000;
/// Redness `(R − (G+B)/2) / (R + G + B + DARK)` above which a pixel belongs to a dot: printed
/// red scores ≈ 0.55, grey jaws and most backgrounds < 0.1; the ratio ignores brightness.
const RED_THRESHOLD: f32 = 0.22;
/// Redness below which a pixel adds nothing to a dot's centroid weight.
const RED_FLOOR: f32 = 0.1;
/// Added to the brightness sum so dark sensor noise does not look saturated.
const DARK: f32 = 30.0;
/// A blob whose area is outside `[MIN_AREA, MAX_AREA] ×` a dot's area is not a single dot.
const MIN_AREA: f64 = 0.2;
const MAX_AREA: f64 = 2.5;
/// A dot further than this fraction of the pitch from every dot ring/slot is not a jaw dot.
const SLOT_TOLERANCE: f64 = 0.3;
/// Fewest dots per jaw for a line fit.
const MIN_DOTS_PER_JAW: usize = 2;
/// A dot further than this many dot radii from its jaw line is an outlier (refit without it).
const OUTLIER_RADII: f64 = 0.8;
/// Dots further than this many dot radii from the line most of their jaw's dots agree on are
/// not that jaw's (looser than [`OUTLIER_RADII`]: it must pass a jaw seen through geometry a few
/// millimetres off, before calibration).
const CONSENSUS_RADII: f64 = 1.5;
/// Least fraction of the rectified window that must fall inside the image.
const MIN_VISIBLE: f64 = 0.5;

/// The dot plane in the front-lens frame and its fronto-parallel sampling grid.
#[derive(Debug, Clone, Serialize)]
pub struct DotPlane {
    /// Origin: the hinge, moved onto the dotted face (m, front-lens frame).
    pub origin: [f64; 3],
    /// In-plane axis along the closed jaws.
    pub e_u: [f64; 3],
    /// In-plane axis across the jaws.
    pub e_v: [f64; 3],
    /// Rectified pixels per metre in the plane.
    pub px_per_m: f64,
    /// Plane coordinate `u` of rectified column 0 (m).
    pub u_min: f64,
    /// Plane coordinate `v` of rectified row 0 (m).
    pub v_min: f64,
    /// Rectified image width (px).
    pub width: usize,
    /// Rectified image height (px).
    pub height: usize,
}

/// Source pixel of every rectified pixel (NaN where the plane point is not imaged).
pub struct Rectifier {
    plane: DotPlane,
    map: Vec<[f32; 2]>,
    visible: f64,
    src: (usize, usize),
}

impl Rectifier {
    /// Build the rectification of a tool's dot plane for a camera.
    pub fn new(camera: &Camera, def: &ToolDefinition) -> Result<Self> {
        if def.kind == ToolKind::BareHand {
            return Err(BackendError::Input {
                path: def.name.clone().into(),
                message: "the bare-hand cuff has no jaws: there is no opening to measure".into(),
            });
        }
        let d0 = def.jaw_direction();
        let n = def.plane_normal();
        let e_v = n.cross(&d0).normalize();
        let origin = def.hinge() - n * def.jaws.half_thickness_m;
        let (r_dot, pos) = (def.dots.radius_m, def.dot_positions_m());
        let mid = def.jaws.offset_m + def.jaws.length_m / 2.0;
        let (first, last) = (
            mid + pos.first().copied().unwrap_or(0.0),
            mid + pos.last().copied().unwrap_or(0.0),
        );
        let margin = 3.0 * r_dot;
        let (u_lo, u_hi, v_half) = match def.kind {
            ToolKind::Chopstick => {
                let half = (def.jaws.max_opening / 2.0).min(std::f64::consts::FRAC_PI_2);
                (
                    (first * half.cos()).min(first) - margin,
                    last + margin,
                    last * half.sin() + margin,
                )
            }
            _ => (
                first - margin,
                last + margin,
                def.jaws.max_opening / 2.0 + def.jaws.half_width_m + margin,
            ),
        };
        // Scale: the source image's pixel density at the window centre, oversampled.
        let centre = origin + d0 * ((u_lo + u_hi) / 2.0);
        let step = 1e-3;
        let p0 = camera.project(&centre);
        let pu = camera.project(&(centre + d0 * step));
        let pv = camera.project(&(centre + e_v * step));
        let density = match (p0, pu, pv) {
            (Some(a), Some(b), Some(c)) => ((b - a).norm().max((c - a).norm())) / step,
            _ => {
                return Err(BackendError::Input {
                    path: def.name.clone().into(),
                    message: "the tool's dot plane is not in the lens's field of view: check \
                              hinge.in_front_m and the lens in the tool definition"
                        .into(),
                });
            }
        };
        let px_per_m = (density * OVERSAMPLE).clamp(MIN_PX_PER_M, MAX_PX_PER_M);
        let width = ((u_hi - u_lo) * px_per_m).ceil() as usize;
        let height = ((2.0 * v_half) * px_per_m).ceil() as usize;
        if width * height > MAX_RECT_PIXELS || width == 0 || height == 0 {
            return Err(BackendError::Input {
                path: def.name.clone().into(),
                message: format!(
                    "rectified window of {width}×{height} px is out of range: check the jaw and \
                     dot dimensions"
                ),
            });
        }
        let plane = DotPlane {
            origin: origin.into(),
            e_u: d0.into(),
            e_v: e_v.into(),
            px_per_m,
            u_min: u_lo,
            v_min: -v_half,
            width,
            height,
        };
        let (sw, sh) = camera.resolution();
        let mut map = Vec::with_capacity(width * height);
        let mut inside = 0usize;
        for j in 0..height {
            for i in 0..width {
                let (u, v) = plane.uv(i as f64, j as f64);
                let x = origin + d0 * u + e_v * v;
                match camera.project(&x) {
                    Some(p)
                        if p.x >= 0.0
                            && p.y >= 0.0
                            && p.x <= f64::from(sw) - 1.0
                            && p.y <= f64::from(sh) - 1.0 =>
                    {
                        inside += 1;
                        map.push([p.x as f32, p.y as f32]);
                    }
                    _ => map.push([f32::NAN, f32::NAN]),
                }
            }
        }
        Ok(Self {
            plane,
            map,
            visible: inside as f64 / (width * height) as f64,
            src: (sw as usize, sh as usize),
        })
    }

    /// The plane and its grid.
    pub fn plane(&self) -> &DotPlane {
        &self.plane
    }

    /// Fraction of the rectified window inside the image.
    pub fn visible_fraction(&self) -> f64 {
        self.visible
    }
}

impl DotPlane {
    /// Plane coordinates (m) of a rectified pixel position.
    pub fn uv(&self, i: f64, j: f64) -> (f64, f64) {
        (
            self.u_min + i / self.px_per_m,
            self.v_min + j / self.px_per_m,
        )
    }

    /// Front-lens point of plane coordinates.
    pub fn point(&self, u: f64, v: f64) -> Vector3<f64> {
        Vector3::from(self.origin) + Vector3::from(self.e_u) * u + Vector3::from(self.e_v) * v
    }
}

/// Channel order of interleaved 8-bit pixels.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ChannelOrder {
    /// R, G, B.
    Rgb,
    /// B, G, R (OpenCV).
    Bgr,
}

/// An interleaved 3-channel 8-bit image.
pub struct ImageView<'a> {
    /// Width (px).
    pub width: usize,
    /// Height (px).
    pub height: usize,
    /// `width × height × 3` bytes, rows top to bottom.
    pub data: &'a [u8],
    /// Channel order.
    pub order: ChannelOrder,
}

/// A red dot found in the rectified view.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct Dot {
    /// Plane coordinate along the jaws (m).
    pub u: f64,
    /// Plane coordinate across the jaws (m).
    pub v: f64,
    /// Area in rectified pixels.
    pub area: usize,
}

/// Red-dot segmentation in the rectified view: connected components of red pixels, centroids
/// weighted by redness.
pub fn find_dots(rect: &Rectifier, image: &ImageView<'_>, dot_radius_m: f64) -> Vec<Dot> {
    let (w, h) = (rect.plane.width, rect.plane.height);
    if image.width != rect.src.0 || image.height != rect.src.1 {
        return vec![];
    }
    let (ri, bi) = match image.order {
        ChannelOrder::Rgb => (0, 2),
        ChannelOrder::Bgr => (2, 0),
    };
    let data = image.data;
    let stride = image.width * 3;
    let mut red = vec![0f32; w * h];
    for (k, m) in rect.map.iter().enumerate() {
        let [x, y] = *m;
        if !x.is_finite() {
            continue;
        }
        let (x0, y0) = (x.floor() as usize, y.floor() as usize);
        let (x1, y1) = (
            (x0 + 1).min(image.width - 1),
            (y0 + 1).min(image.height - 1),
        );
        let (fx, fy) = (x - x0 as f32, y - y0 as f32);
        let px = |xx: usize, yy: usize, c: usize| f32::from(data[yy * stride + xx * 3 + c]);
        let sample = |c: usize| {
            (px(x0, y0, c) * (1.0 - fx) + px(x1, y0, c) * fx) * (1.0 - fy)
                + (px(x0, y1, c) * (1.0 - fx) + px(x1, y1, c) * fx) * fy
        };
        let (r, g, b) = (sample(ri), sample(1), sample(bi));
        red[k] = (r - 0.5 * (g + b)) / (r + g + b + DARK);
    }
    let expected_area = std::f64::consts::PI * (dot_radius_m * rect.plane.px_per_m).powi(2);
    let mut label = vec![false; w * h];
    let mut stack = Vec::new();
    let mut dots = Vec::new();
    for start in 0..w * h {
        if label[start] || red[start] < RED_THRESHOLD {
            continue;
        }
        label[start] = true;
        stack.push(start);
        let (mut sw, mut su, mut sv, mut area) = (0f64, 0f64, 0f64, 0usize);
        while let Some(k) = stack.pop() {
            let (i, j) = (k % w, k / w);
            let wt = f64::from(red[k] - RED_FLOOR);
            sw += wt;
            su += wt * i as f64;
            sv += wt * j as f64;
            area += 1;
            let mut visit = |kk: usize| {
                if !label[kk] && red[kk] >= RED_THRESHOLD {
                    label[kk] = true;
                    stack.push(kk);
                }
            };
            if i > 0 {
                visit(k - 1);
            }
            if i + 1 < w {
                visit(k + 1);
            }
            if j > 0 {
                visit(k - w);
            }
            if j + 1 < h {
                visit(k + w);
            }
        }
        let a = area as f64 / expected_area;
        if !(MIN_AREA..=MAX_AREA).contains(&a) || sw <= 0.0 {
            continue;
        }
        let (u, v) = rect.plane.uv(su / sw, sv / sw);
        dots.push(Dot { u, v, area });
    }
    dots
}

/// Unit of an opening.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum OpeningUnit {
    /// Degrees between the jaw lines (chopstick).
    Deg,
    /// Rectified dot-plane pixels between the plates' inner faces (parallel jaw).
    Px,
}

impl OpeningUnit {
    /// The unit's name in files.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Deg => "deg",
            Self::Px => "px",
        }
    }
}

/// One frame's measurement.
#[derive(Debug, Clone, Serialize)]
pub struct Measurement {
    /// The opening, or `None` when it could not be measured.
    pub opening: Option<f64>,
    /// Unit of `opening`.
    pub unit: OpeningUnit,
    /// 0 (no trust) to 1: dot coverage times line-fit quality.
    pub confidence: f64,
    /// `ok`, or why the frame is missing.
    pub status: String,
    /// Dots used on each jaw.
    pub dots_used: [usize; 2],
    /// RMS distance of the dots from their jaw lines (m).
    pub fit_rms_m: f64,
}

impl Measurement {
    fn missing(unit: OpeningUnit, reason: &str) -> Self {
        Self {
            opening: None,
            unit,
            confidence: 0.0,
            status: format!("missing: {reason}"),
            dots_used: [0, 0],
            fit_rms_m: f64::NAN,
        }
    }
}

/// The per-frame estimator of one tool on one lens.
pub struct GripperEstimator {
    def: ToolDefinition,
    rect: Rectifier,
    /// Distance of each dot slot from the hinge along the jaw (m).
    slots: Vec<f64>,
}

/// The dot chosen for a slot: how far its area is from a dot's, and its plane position.
type SlotPick = (f64, [f64; 2]);

/// A line through the dots of one jaw, in dot-plane coordinates (m): `direction` (unit, along
/// +u) through `point`.
#[derive(Debug, Clone, Copy)]
pub struct JawLine {
    /// A point on the line (the centroid, or the anchor).
    pub point: [f64; 2],
    /// Unit direction, pointing along +u.
    pub direction: [f64; 2],
    /// RMS distance of the dots from the line (m).
    pub rms: f64,
    /// Dots on the line.
    pub n: usize,
}

/// Dots of one frame assigned to each jaw (side of the centre line) and dot slot.
#[derive(Debug, Clone, Default)]
pub struct JawDots {
    /// Per jaw (−v side first): (slot index, plane position (m)).
    pub jaws: [Vec<(usize, [f64; 2])>; 2],
}

/// Total-least-squares line through points; through `anchor` when given (the hinge).
pub fn fit_line(pts: &[[f64; 2]], anchor: Option<[f64; 2]>) -> Option<JawLine> {
    if pts.len() < MIN_DOTS_PER_JAW {
        return None;
    }
    let n = pts.len() as f64;
    let c = anchor.unwrap_or_else(|| {
        let s = pts
            .iter()
            .fold([0.0, 0.0], |a, p| [a[0] + p[0], a[1] + p[1]]);
        [s[0] / n, s[1] / n]
    });
    let (mut suu, mut svv, mut suv) = (0.0, 0.0, 0.0);
    for p in pts {
        let (du, dv) = (p[0] - c[0], p[1] - c[1]);
        suu += du * du;
        svv += dv * dv;
        suv += du * dv;
    }
    let theta = 0.5 * (2.0 * suv).atan2(suu - svv);
    let d = [theta.cos(), theta.sin()];
    let rms = (pts
        .iter()
        .map(|p| ((p[0] - c[0]) * d[1] - (p[1] - c[1]) * d[0]).powi(2))
        .sum::<f64>()
        / n)
        .sqrt();
    Some(JawLine {
        point: c,
        direction: if d[0] < 0.0 { [-d[0], -d[1]] } else { d },
        rms,
        n: pts.len(),
    })
}

/// Fit, drop dots far from the line, refit.
fn robust_line(pts: &[[f64; 2]], anchor: Option<[f64; 2]>, max_dist: f64) -> Option<JawLine> {
    let first = fit_line(pts, anchor)?;
    let keep: Vec<[f64; 2]> = pts
        .iter()
        .copied()
        .filter(|p| {
            ((p[0] - first.point[0]) * first.direction[1]
                - (p[1] - first.point[1]) * first.direction[0])
                .abs()
                <= max_dist
        })
        .collect();
    if keep.len() == pts.len() {
        Some(first)
    } else {
        fit_line(&keep, anchor)
    }
}

impl GripperEstimator {
    /// An estimator for a tool definition seen by a camera.
    pub fn new(camera: &Camera, def: &ToolDefinition) -> Result<Self> {
        let rect = Rectifier::new(camera, def)?;
        let mid = def.jaws.offset_m + def.jaws.length_m / 2.0;
        let slots = def.dot_positions_m().iter().map(|p| mid + p).collect();
        Ok(Self {
            def: def.clone(),
            rect,
            slots,
        })
    }

    /// The rectification (plane pose and scale).
    pub fn rectifier(&self) -> &Rectifier {
        &self.rect
    }

    /// The unit of this tool's openings.
    pub fn unit(&self) -> OpeningUnit {
        match self.def.kind {
            ToolKind::ParallelJaw => OpeningUnit::Px,
            _ => OpeningUnit::Deg,
        }
    }

    /// Measure one frame.
    pub fn measure(&self, image: &ImageView<'_>) -> Measurement {
        let unit = self.unit();
        if image.width != self.rect.src.0 || image.height != self.rect.src.1 {
            return Measurement::missing(
                unit,
                &format!(
                    "frame is {}x{} but the lens calibration is {}x{}",
                    image.width, image.height, self.rect.src.0, self.rect.src.1
                ),
            );
        }
        if self.rect.visible < MIN_VISIBLE {
            return Measurement::missing(
                unit,
                &format!(
                    "jaws out of view: {:.0} % of the dot plane is imaged",
                    100.0 * self.rect.visible
                ),
            );
        }
        let dots = find_dots(&self.rect, image, self.def.dots.radius_m);
        match self.def.kind {
            ToolKind::Chopstick => self.chopstick(&dots),
            _ => self.parallel(&dots),
        }
    }

    /// The slot a distance along the jaw falls in, if close to one.
    fn slot(&self, along: f64) -> Option<usize> {
        let tol = SLOT_TOLERANCE * self.def.dots.pitch_m;
        self.slots
            .iter()
            .enumerate()
            .map(|(k, s)| (k, (along - s).abs()))
            .filter(|(_, d)| *d <= tol)
            .min_by(|a, b| a.1.total_cmp(&b.1))
            .map(|(k, _)| k)
    }

    /// Slot positions along the jaw (m from the hinge).
    pub fn slots(&self) -> &[f64] {
        &self.slots
    }

    /// The frame's dots assigned to jaws and slots (empty when the frame does not fit the
    /// lens or the dot plane is mostly out of view); used by the tool calibration.
    pub fn jaw_dots(&self, image: &ImageView<'_>) -> JawDots {
        if image.width != self.rect.src.0
            || image.height != self.rect.src.1
            || self.rect.visible < MIN_VISIBLE
        {
            return JawDots::default();
        }
        let dots = find_dots(&self.rect, image, self.def.dots.radius_m);
        let jaws = match self.def.kind {
            ToolKind::Chopstick => self.per_jaw_slots(&dots, |d| d.u.hypot(d.v)),
            _ => self.per_jaw_slots(&dots, |d| d.u),
        };
        JawDots { jaws }
    }

    /// Split dots per jaw by side of the centre line, at most one per slot and jaw.
    fn per_jaw(&self, dots: &[Dot], along: impl Fn(&Dot) -> f64) -> [Vec<[f64; 2]>; 2] {
        self.per_jaw_slots(dots, along)
            .map(|j| j.into_iter().map(|(_, p)| p).collect())
    }

    /// [`Self::per_jaw`] with each dot's slot index.
    fn per_jaw_slots(
        &self,
        dots: &[Dot],
        along: impl Fn(&Dot) -> f64,
    ) -> [Vec<(usize, [f64; 2])>; 2] {
        let n = self.slots.len();
        let mut best: [Vec<Option<SlotPick>>; 2] = [vec![None; n], vec![None; n]];
        let expected =
            std::f64::consts::PI * (self.def.dots.radius_m * self.rect.plane.px_per_m).powi(2);
        let candidates: Vec<(usize, &Dot)> = dots
            .iter()
            .filter_map(|d| self.slot(along(d)).map(|k| (k, d)))
            .collect();
        let lines = [0, 1].map(|side| {
            let on_side: Vec<&Dot> = candidates
                .iter()
                .filter(|(_, d)| usize::from(d.v > 0.0) == side)
                .map(|(_, d)| *d)
                .collect();
            self.consensus_line(&on_side)
        });
        for (k, d) in candidates {
            let side = usize::from(d.v > 0.0);
            if lines[side].is_some_and(|l| self.line_distance(l, d) > self.consensus_gate()) {
                continue;
            }
            let score = (d.area as f64 / expected - 1.0).abs();
            if best[side][k].is_none_or(|(s, _)| score < s) {
                best[side][k] = Some((score, [d.u, d.v]));
            }
        }
        best.map(|b| {
            b.into_iter()
                .enumerate()
                .filter_map(|(k, pick)| pick.map(|(_, p)| (k, p)))
                .collect()
        })
    }

    /// Largest distance (m) of a jaw's dot from the line most of that jaw's dots agree on.
    fn consensus_gate(&self) -> f64 {
        CONSENSUS_RADII * self.def.dots.radius_m
    }

    /// Distance (m) of a dot from a candidate jaw line: chopstick, a ray from the hinge at an
    /// angle (rad) from `u`; parallel jaw, a line along `u` at an offset `v` (m).
    fn line_distance(&self, line: f64, d: &Dot) -> f64 {
        match self.def.kind {
            ToolKind::Chopstick => {
                let (s, c) = line.sin_cos();
                if d.u * c + d.v * s <= 0.0 {
                    f64::INFINITY
                } else {
                    (d.u * s - d.v * c).abs()
                }
            }
            _ => (d.v - line).abs(),
        }
    }

    /// The jaw line (see [`Self::line_distance`]) through one of the dots that the most dots
    /// lie near, so a red blob elsewhere in the window (background, a reflection) can neither
    /// take a real dot's slot nor pull the line; `None` for fewer than two dots.
    fn consensus_line(&self, dots: &[&Dot]) -> Option<f64> {
        if dots.len() < MIN_DOTS_PER_JAW {
            return None;
        }
        let gate = self.consensus_gate();
        dots.iter()
            .map(|d| match self.def.kind {
                ToolKind::Chopstick => d.v.atan2(d.u),
                _ => d.v,
            })
            .map(|line| {
                let (mut support, mut spread) = (0usize, 0.0);
                for d in dots {
                    let e = self.line_distance(line, d);
                    if e <= gate {
                        support += 1;
                        spread += e;
                    }
                }
                (line, support, spread)
            })
            .max_by(|a, b| a.1.cmp(&b.1).then(b.2.total_cmp(&a.2)))
            .map(|(line, _, _)| line)
    }

    fn confidence(&self, lines: [&JawLine; 2]) -> f64 {
        let coverage = lines[0].n.min(lines[1].n) as f64 / self.slots.len().max(1) as f64;
        let rms = lines[0].rms.max(lines[1].rms);
        coverage * (-rms / (0.25 * self.def.dots.radius_m)).exp()
    }

    fn chopstick(&self, dots: &[Dot]) -> Measurement {
        let unit = OpeningUnit::Deg;
        let jaws = self.per_jaw(dots, |d| d.u.hypot(d.v));
        let max_dist = OUTLIER_RADII * self.def.dots.radius_m;
        let lines: Vec<Option<JawLine>> = jaws
            .iter()
            .map(|pts| robust_line(pts, Some([0.0, 0.0]), max_dist))
            .collect();
        let (Some(a), Some(b)) = (lines[0], lines[1]) else {
            return Measurement::missing(
                unit,
                &format!(
                    "jaw dots not found ({} and {} of {} per jaw, need {MIN_DOTS_PER_JAW})",
                    jaws[0].len(),
                    jaws[1].len(),
                    self.slots.len()
                ),
            );
        };
        let angle = |l: &JawLine| l.direction[1].atan2(l.direction[0]);
        let opening = (angle(&b) - angle(&a)).to_degrees();
        Measurement {
            opening: Some(opening),
            unit,
            confidence: self.confidence([&a, &b]),
            status: "ok".into(),
            dots_used: [a.n, b.n],
            fit_rms_m: a.rms.max(b.rms),
        }
    }

    fn parallel(&self, dots: &[Dot]) -> Measurement {
        let unit = OpeningUnit::Px;
        let jaws = self.per_jaw(dots, |d| d.u);
        let max_dist = OUTLIER_RADII * self.def.dots.radius_m;
        let lines: Vec<Option<JawLine>> = jaws
            .iter()
            .map(|pts| robust_line(pts, None, max_dist))
            .collect();
        let (Some(a), Some(b)) = (lines[0], lines[1]) else {
            return Measurement::missing(
                unit,
                &format!(
                    "plate dots not found ({} and {} of {} per plate, need {MIN_DOTS_PER_JAW})",
                    jaws[0].len(),
                    jaws[1].len(),
                    self.slots.len()
                ),
            );
        };
        // Gap between the two dot lines at the middle of the plates, minus the plates' faces.
        let u_mid = (self.slots.first().copied().unwrap_or(0.0)
            + self.slots.last().copied().unwrap_or(0.0))
            / 2.0;
        let v_at = |l: &JawLine| {
            if l.direction[0].abs() < 1e-9 {
                l.point[1]
            } else {
                l.point[1] + (u_mid - l.point[0]) * l.direction[1] / l.direction[0]
            }
        };
        let gap_m = (v_at(&b) - v_at(&a)) - 2.0 * self.def.jaws.half_width_m;
        Measurement {
            opening: Some(gap_m * self.rect.plane.px_per_m),
            unit,
            confidence: self.confidence([&a, &b]),
            status: "ok".into(),
            dots_used: [a.n, b.n],
            fit_rms_m: a.rms.max(b.rms),
        }
    }

    /// Where a plane point appears in the source image (for overlays).
    pub fn project(&self, camera: &Camera, u: f64, v: f64) -> Option<Point2<f64>> {
        camera.project(&self.rect.plane.point(u, v))
    }
}
