//! Compare the jaw opening measured from the video with the bench encoder: find the offset
//! between the host clock (encoder) and the video clock by cross-correlation, map encoder
//! counts to the opening's unit, and report RMSE, max error and bias with a plot of one cycle.

use std::path::{Path, PathBuf};

use rustfft::FftPlanner;
use rustfft::num_complex::Complex;
use serde::Serialize;

use kiwi_core::layout::ToolKind;
use kiwi_core::tool::ToolDefinition;

use super::error::BenchError;
use super::protocol::COUNTS_PER_REV;
use kiwi_plot::{Axis, Chart, Mark, Series};

/// Grid step of the coarse cross-correlation (s); the refinement goes below it.
const GRID_S: f64 = 0.001;
/// Half-width of the residual search around the correlation peak (s): the raw-sum peak can
/// sit several ms off on a short recording (its overlap term), so search wide, then fine.
const REFINE_HALF_S: f64 = 0.03;
/// Step of the wide residual search (s).
const REFINE_COARSE_STEP_S: f64 = 0.000_5;
/// Step of the fine search, within one wide step either side of the wide minimum (s).
const REFINE_STEP_S: f64 = 0.000_05;
/// Encoder samples further apart than this many median periods are a gap (no interpolation).
const GAP_PERIODS: f64 = 3.0;
/// Least fraction of the shorter recording that must overlap at a candidate offset.
const MIN_OVERLAP: f64 = 0.5;
/// Fewest matched samples for a meaningful comparison.
const MIN_MATCHED: usize = 20;

/// Unit of the vision opening.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum OpeningUnit {
    /// Chopstick: angle between the jaws in degrees.
    Deg,
    /// Parallel jaw: gap in rectified dot-plane pixels.
    Px,
}

/// One encoder row.
#[derive(Debug, Clone, Copy)]
pub struct EncoderSample {
    /// Host time (s).
    pub t: f64,
    /// Raw count.
    pub raw: f64,
    /// Horn angle (rad) as recorded.
    pub angle_rad: f64,
}

/// One vision row that was measured.
#[derive(Debug, Clone, Copy)]
pub struct VisionSample {
    /// Video time (s).
    pub t: f64,
    /// Opening in the file's unit.
    pub opening: f64,
}

/// How encoder readings become openings.
#[derive(Debug, Clone)]
pub struct EncoderMap {
    /// Count at a closed jaw; `None` uses the `angle_rad` column as recorded.
    pub zero_count: Option<f64>,
    /// Encoder counts per horn revolution.
    pub counts_per_rev: f64,
    /// Opening per horn radian: jaw rad per horn rad for the chopstick (1 when the horn sits
    /// on the hinge; −1 when it turns the other way), m per rad for the parallel jaw.
    pub scale: f64,
    /// Rectified pixels per metre of the parallel jaw's gap (`kiwi gripper`'s `tool.json`):
    /// with a metric `scale` it fixes the px map; without, gain and intercept are fitted.
    pub px_per_m: Option<f64>,
    /// Where the map came from (reported in `compare.json`).
    pub source: String,
}

impl Default for EncoderMap {
    fn default() -> Self {
        Self {
            zero_count: None,
            counts_per_rev: f64::from(COUNTS_PER_REV),
            scale: 1.0,
            px_per_m: None,
            source: "angle_rad column as recorded".into(),
        }
    }
}

impl EncoderMap {
    fn angle_rad(&self, s: &EncoderSample) -> f64 {
        let horn = match self.zero_count {
            Some(z) => (s.raw - z) / self.counts_per_rev * std::f64::consts::TAU,
            None => s.angle_rad,
        };
        horn * self.scale
    }

    /// The map of a tool definition's `[encoder]` section; `px_per_m` from the gripper's
    /// `tool.json` when known. Without the section, the recorded `angle_rad` is used.
    pub fn from_tool(def: &ToolDefinition, px_per_m: Option<f64>, source: &str) -> Self {
        match &def.encoder {
            Some(e) => Self {
                zero_count: Some(e.zero_count),
                counts_per_rev: e.counts_per_rev,
                scale: e.opening_per_horn_rad,
                px_per_m,
                source: format!("{source} (encoder section of tool `{}`)", def.name),
            },
            None => Self {
                px_per_m,
                source: format!(
                    "angle_rad column as recorded (tool `{}` in {source} has no [encoder] section)",
                    def.name
                ),
                ..Self::default()
            },
        }
    }
}

/// The tool behind a comparison: a built-in name (`chopstick`, `parallel_jaw`), a definition
/// (`.toml`), or a JSON artifact holding one (`kiwi gripper`'s `tool.json`, a tool
/// calibration); also the rectified px/m when the artifact records it.
pub fn load_tool(spec: &str) -> Result<(ToolDefinition, Option<f64>), BenchError> {
    let core = |path: &Path, e: kiwi_core::error::CoreError| file_err(path, e.to_string());
    match spec {
        "chopstick" | "parallel_jaw" | "parallel-jaw" => {
            let kind = if spec == "chopstick" {
                ToolKind::Chopstick
            } else {
                ToolKind::ParallelJaw
            };
            let def = ToolDefinition::builtin(kind).map_err(|e| core(Path::new(spec), e))?;
            Ok((def, None))
        }
        path => {
            let path = Path::new(path);
            if path.extension().and_then(|e| e.to_str()) == Some("toml") {
                let def = ToolDefinition::load(path).map_err(|e| core(path, e))?;
                return Ok((def, None));
            }
            let text = std::fs::read_to_string(path)
                .map_err(|e| file_err(path, format!("cannot read the tool file: {e}")))?;
            let v: serde_json::Value = serde_json::from_str(&text)
                .map_err(|e| file_err(path, format!("expected a JSON tool artifact: {e}")))?;
            let def_value = v.get("definition").cloned().ok_or_else(|| {
                file_err(
                    path,
                    "no `definition` field: pass kiwi gripper's tool.json, a tool calibration \
                     or a .toml definition"
                        .into(),
                )
            })?;
            let def: ToolDefinition = serde_json::from_value(def_value)
                .map_err(|e| file_err(path, format!("field `definition`: {e}")))?;
            def.validate().map_err(|e| core(path, e))?;
            let px_per_m = v
                .get("plane")
                .and_then(|p| p.get("px_per_m"))
                .and_then(serde_json::Value::as_f64)
                .filter(|p| p.is_finite() && *p > 0.0);
            Ok((def, px_per_m))
        }
    }
}

/// The comparison's result.
#[derive(Debug, Clone, Serialize)]
pub struct Comparison {
    /// Root-mean-square error of vision against encoder.
    pub rmse: f64,
    /// Unit of the errors.
    pub unit: OpeningUnit,
    /// `host_time = video_time + offset_s`.
    pub offset_s: f64,
    /// Matched samples.
    pub n: usize,
    /// Largest absolute error.
    pub max_error: f64,
    /// Mean error (vision − encoder).
    pub bias: f64,
    /// Pearson correlation of the aligned series.
    pub correlation: f64,
    /// Opening per encoder radian (1 rad→deg for the chopstick; fitted px/rad for the
    /// parallel jaw, whose pixel scale depends on the rectification).
    pub gain: f64,
    /// Opening at encoder angle 0 (0 for the chopstick; fitted for the parallel jaw).
    pub intercept: f64,
    /// Vision rows that were measured / all rows.
    pub vision_measured: usize,
    /// All vision rows.
    pub vision_rows: usize,
    /// Dominant period of the motion (s), used for the one-cycle plot.
    pub cycle_s: f64,
    /// Where the encoder-to-opening map came from.
    pub map_source: String,
}

/// Aligned samples behind a comparison (video time, vision, encoder as opening).
#[derive(Debug, Clone, Default)]
pub struct Aligned {
    /// Video times (s).
    pub t: Vec<f64>,
    /// Vision openings.
    pub vision: Vec<f64>,
    /// Encoder openings at the same instants.
    pub encoder: Vec<f64>,
}

fn file_err(path: &Path, detail: String) -> BenchError {
    BenchError::File {
        path: path.to_path_buf(),
        detail,
    }
}

fn header_index(path: &Path, header: &str, name: &str) -> Result<usize, BenchError> {
    header
        .split(',')
        .position(|h| h.trim() == name)
        .ok_or_else(|| {
            file_err(
                path,
                format!("line 1: expected a column `{name}` in the header, found `{header}`"),
            )
        })
}

fn parse_f64(path: &Path, line: usize, field: &str, s: &str) -> Result<f64, BenchError> {
    let v: f64 = s.trim().parse().map_err(|_| {
        file_err(
            path,
            format!("line {line}: field `{field}` should be a number, found `{s}`"),
        )
    })?;
    if !v.is_finite() {
        return Err(file_err(
            path,
            format!("line {line}: field `{field}` is not finite"),
        ));
    }
    Ok(v)
}

/// Read an encoder log (`t,raw,angle_rad`, times strictly increasing).
pub fn read_encoder(path: &Path) -> Result<Vec<EncoderSample>, BenchError> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| file_err(path, format!("cannot read the encoder log: {e}")))?;
    let mut lines = text.lines();
    let header = lines.next().unwrap_or_default();
    let (it, ir, ia) = (
        header_index(path, header, "t")?,
        header_index(path, header, "raw")?,
        header_index(path, header, "angle_rad")?,
    );
    let mut out: Vec<EncoderSample> = Vec::new();
    for (k, line) in lines.enumerate() {
        let ln = k + 2;
        if line.trim().is_empty() {
            continue;
        }
        let f: Vec<&str> = line.split(',').collect();
        let get = |i: usize, name: &str| {
            f.get(i)
                .ok_or_else(|| file_err(path, format!("line {ln}: missing field `{name}`")))
        };
        let s = EncoderSample {
            t: parse_f64(path, ln, "t", get(it, "t")?)?,
            raw: parse_f64(path, ln, "raw", get(ir, "raw")?)?,
            angle_rad: parse_f64(path, ln, "angle_rad", get(ia, "angle_rad")?)?,
        };
        if let Some(prev) = out.last()
            && s.t <= prev.t
        {
            return Err(file_err(
                path,
                format!(
                    "line {ln}: time {} does not increase (previous {}); was the log edited?",
                    s.t, prev.t
                ),
            ));
        }
        out.push(s);
    }
    if out.len() < MIN_MATCHED {
        return Err(file_err(
            path,
            format!(
                "{} encoder samples; record at least {MIN_MATCHED}",
                out.len()
            ),
        ));
    }
    Ok(out)
}

/// Read a vision opening file (`t,opening,unit,confidence,status`); rows whose status is not
/// `ok` are skipped. Returns the measured rows, the unit and the count of all rows.
pub fn read_vision(path: &Path) -> Result<(Vec<VisionSample>, OpeningUnit, usize), BenchError> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| file_err(path, format!("cannot read the opening file: {e}")))?;
    let mut lines = text.lines();
    let header = lines.next().unwrap_or_default();
    let (it, io, iu, is) = (
        header_index(path, header, "t")?,
        header_index(path, header, "opening")?,
        header_index(path, header, "unit")?,
        header_index(path, header, "status")?,
    );
    let mut unit = None;
    let mut rows = 0usize;
    let mut out: Vec<VisionSample> = Vec::new();
    let mut last_t = f64::NEG_INFINITY;
    for (k, line) in lines.enumerate() {
        let ln = k + 2;
        if line.trim().is_empty() {
            continue;
        }
        rows += 1;
        let f: Vec<&str> = line.split(',').collect();
        let get = |i: usize, name: &str| {
            f.get(i)
                .copied()
                .ok_or_else(|| file_err(path, format!("line {ln}: missing field `{name}`")))
        };
        let t = parse_f64(path, ln, "t", get(it, "t")?)?;
        if t <= last_t {
            return Err(file_err(
                path,
                format!("line {ln}: time {t} does not increase (previous {last_t})"),
            ));
        }
        last_t = t;
        let u = match get(iu, "unit")?.trim() {
            "deg" => OpeningUnit::Deg,
            "px" => OpeningUnit::Px,
            other => {
                return Err(file_err(
                    path,
                    format!("line {ln}: field `unit` should be `deg` or `px`, found `{other}`"),
                ));
            }
        };
        if *unit.get_or_insert(u) != u {
            return Err(file_err(
                path,
                format!("line {ln}: unit changes within the file"),
            ));
        }
        if get(is, "status")?.trim() != "ok" {
            continue;
        }
        out.push(VisionSample {
            t,
            opening: parse_f64(path, ln, "opening", get(io, "opening")?)?,
        });
    }
    let unit = unit.ok_or_else(|| file_err(path, "no rows".into()))?;
    if out.len() < MIN_MATCHED {
        return Err(file_err(
            path,
            format!(
                "{} measured rows of {rows}; at least {MIN_MATCHED} are needed",
                out.len()
            ),
        ));
    }
    Ok((out, unit, rows))
}

/// The encoder as a function of host time: linear interpolation, `None` in gaps and outside.
struct EncoderSignal {
    t: Vec<f64>,
    v: Vec<f64>,
    max_gap: f64,
}

impl EncoderSignal {
    fn new(samples: &[EncoderSample], map: &EncoderMap) -> Self {
        let t: Vec<f64> = samples.iter().map(|s| s.t).collect();
        let v = samples.iter().map(|s| map.angle_rad(s)).collect();
        let mut d: Vec<f64> = t.windows(2).map(|w| w[1] - w[0]).collect();
        d.sort_by(f64::total_cmp);
        let median = d.get(d.len() / 2).copied().unwrap_or(0.0);
        Self {
            t,
            v,
            max_gap: median * GAP_PERIODS,
        }
    }

    fn at(&self, t: f64) -> Option<f64> {
        let i = self.t.partition_point(|&x| x <= t);
        if i == 0 || i >= self.t.len() {
            return None;
        }
        let (t0, t1) = (self.t[i - 1], self.t[i]);
        if t1 - t0 > self.max_gap {
            return None;
        }
        let a = (t - t0) / (t1 - t0);
        Some(self.v[i - 1] * (1.0 - a) + self.v[i] * a)
    }
}

/// Least-squares `y ≈ a x + b` and the residual RMS; `None` when degenerate.
fn linear_fit(x: &[f64], y: &[f64]) -> Option<(f64, f64, f64)> {
    let n = x.len() as f64;
    if x.len() < 2 {
        return None;
    }
    let (mx, my) = (x.iter().sum::<f64>() / n, y.iter().sum::<f64>() / n);
    let (mut sxx, mut sxy) = (0.0, 0.0);
    for (a, b) in x.iter().zip(y) {
        sxx += (a - mx) * (a - mx);
        sxy += (a - mx) * (b - my);
    }
    if sxx <= 0.0 {
        return None;
    }
    let a = sxy / sxx;
    let b = my - a * mx;
    let rms = (x
        .iter()
        .zip(y)
        .map(|(xi, yi)| (a * xi + b - yi).powi(2))
        .sum::<f64>()
        / n)
        .sqrt();
    Some((a, b, rms))
}

/// A mean-removed, unit-variance resampling on a `GRID_S` grid (gaps are 0).
fn resample(times: &[f64], value: impl Fn(f64) -> Option<f64>) -> (f64, Vec<f64>) {
    let (Some(&t0), Some(&t1)) = (times.first(), times.last()) else {
        return (0.0, vec![]);
    };
    let n = ((t1 - t0) / GRID_S).floor() as usize + 1;
    let raw: Vec<Option<f64>> = (0..n).map(|k| value(t0 + k as f64 * GRID_S)).collect();
    let vals: Vec<f64> = raw.iter().flatten().copied().collect();
    let m = vals.iter().sum::<f64>() / vals.len().max(1) as f64;
    let sd = (vals.iter().map(|v| (v - m).powi(2)).sum::<f64>() / vals.len().max(1) as f64)
        .sqrt()
        .max(f64::MIN_POSITIVE);
    (
        t0,
        raw.iter()
            .map(|v| v.map_or(0.0, |v| (v - m) / sd))
            .collect(),
    )
}

/// Vision as a step-free function of video time: linear interpolation between measured rows
/// closer than a few frame periods.
fn vision_at(vision: &[VisionSample], max_gap: f64, t: f64) -> Option<f64> {
    let i = vision.partition_point(|s| s.t <= t);
    if i == 0 || i >= vision.len() {
        return None;
    }
    let (a, b) = (vision[i - 1], vision[i]);
    if b.t - a.t > max_gap {
        return None;
    }
    let w = (t - a.t) / (b.t - a.t);
    Some(a.opening * (1.0 - w) + b.opening * w)
}

/// Coarse offset (host − video) at the cross-correlation peak, by FFT.
fn coarse_offset(enc: &EncoderSignal, vision: &[VisionSample]) -> Result<f64, BenchError> {
    let mut dv: Vec<f64> = vision.windows(2).map(|w| w[1].t - w[0].t).collect();
    dv.sort_by(f64::total_cmp);
    let v_gap = dv.get(dv.len() / 2).copied().unwrap_or(0.0) * GAP_PERIODS;
    let vt: Vec<f64> = vision.iter().map(|s| s.t).collect();
    let (e0, e) = resample(&enc.t, |t| enc.at(t));
    let (v0, v) = resample(&vt, |t| vision_at(vision, v_gap, t));
    let n = (e.len() + v.len()).next_power_of_two();
    let mut planner = FftPlanner::<f64>::new();
    let fwd = planner.plan_fft_forward(n);
    let inv = planner.plan_fft_inverse(n);
    let mut a: Vec<Complex<f64>> = (0..n)
        .map(|i| Complex::new(e.get(i).copied().unwrap_or(0.0), 0.0))
        .collect();
    let mut b: Vec<Complex<f64>> = (0..n)
        .map(|i| Complex::new(v.get(i).copied().unwrap_or(0.0), 0.0))
        .collect();
    fwd.process(&mut a);
    fwd.process(&mut b);
    let mut c: Vec<Complex<f64>> = a.iter().zip(&b).map(|(x, y)| x * y.conj()).collect();
    inv.process(&mut c);
    // c[lag] = Σ e[i + lag] v[i]: video sample i matches encoder sample i + lag.
    let min_overlap = (MIN_OVERLAP * e.len().min(v.len()) as f64) as i64;
    let (el, vl) = (e.len() as i64, v.len() as i64);
    let mut best: Option<(f64, i64)> = None;
    for idx in 0..n {
        let lag = if idx < n / 2 {
            idx as i64
        } else {
            idx as i64 - n as i64
        };
        let overlap = (el.min(vl + lag) - lag.max(0)).min(vl);
        if overlap < min_overlap {
            continue;
        }
        // The raw sum (not divided by the overlap) favours long overlaps: a near-periodic
        // motion correlates almost as well one cycle off, over a shorter overlap.
        let score = c[idx].re;
        if best.is_none_or(|(s, _)| score > s) {
            best = Some((score, lag));
        }
    }
    let (_, lag) = best.ok_or_else(|| BenchError::Setting {
        name: "recordings",
        detail: "the encoder and vision recordings cannot overlap by half: are they of the same session?".into(),
    })?;
    Ok(e0 - v0 + lag as f64 * GRID_S)
}

/// Align, map and compare. `map` turns encoder readings into the jaw angle (rad).
pub fn compare(
    encoder: &[EncoderSample],
    vision: &[VisionSample],
    unit: OpeningUnit,
    vision_rows: usize,
    map: &EncoderMap,
) -> Result<(Comparison, Aligned), BenchError> {
    let enc = EncoderSignal::new(encoder, map);
    let coarse = coarse_offset(&enc, vision)?;
    // Fine search: the offset minimizing the residual of a linear map vision ≈ a·enc + b.
    let matched = |offset: f64| -> (Vec<f64>, Vec<f64>, Vec<f64>) {
        let mut t = Vec::with_capacity(vision.len());
        let mut x = Vec::with_capacity(vision.len());
        let mut y = Vec::with_capacity(vision.len());
        for s in vision {
            if let Some(e) = enc.at(s.t + offset) {
                t.push(s.t);
                x.push(e);
                y.push(s.opening);
            }
        }
        (t, x, y)
    };
    let scan = |centre: f64, half: f64, step: f64| -> Option<(f64, f64)> {
        let steps = (half / step).round() as i64;
        let mut best: Option<(f64, f64)> = None;
        for k in -steps..=steps {
            let off = centre + k as f64 * step;
            let (_, x, y) = matched(off);
            if x.len() < MIN_MATCHED {
                continue;
            }
            if let Some((_, _, rms)) = linear_fit(&x, &y)
                && best.is_none_or(|(r, _)| rms < r)
            {
                best = Some((rms, off));
            }
        }
        best
    };
    let best = scan(coarse, REFINE_HALF_S, REFINE_COARSE_STEP_S)
        .and_then(|(_, wide)| scan(wide, REFINE_COARSE_STEP_S, REFINE_STEP_S));
    let (_, offset_s) = best.ok_or_else(|| BenchError::Setting {
        name: "recordings",
        detail: format!(
            "fewer than {MIN_MATCHED} vision rows fall inside the encoder recording at the best offset"
        ),
    })?;
    let (t, x, y) = matched(offset_s);
    let (gain, intercept) = match (unit, map.zero_count, map.px_per_m) {
        (OpeningUnit::Deg, _, _) => (1f64.to_degrees(), 0.0),
        // Encoder counts → metres (the tool's encoder map) → rectified px.
        (OpeningUnit::Px, Some(_), Some(px_per_m)) => (px_per_m, 0.0),
        (OpeningUnit::Px, _, _) => {
            let (a, b, _) = linear_fit(&x, &y).ok_or_else(|| BenchError::Setting {
                name: "encoder",
                detail: "the encoder did not move: open and close the jaw during the recording"
                    .into(),
            })?;
            (a, b)
        }
    };
    let encoder_vals: Vec<f64> = x.iter().map(|v| gain * v + intercept).collect();
    let err: Vec<f64> = y.iter().zip(&encoder_vals).map(|(v, e)| v - e).collect();
    let n = err.len();
    let rmse = (err.iter().map(|e| e * e).sum::<f64>() / n as f64).sqrt();
    let bias = err.iter().sum::<f64>() / n as f64;
    let max_error = err.iter().fold(0.0f64, |m, e| m.max(e.abs()));
    let correlation = pearson(&y, &encoder_vals);
    let cycle_s = dominant_period(&enc);
    Ok((
        Comparison {
            rmse,
            unit,
            offset_s,
            n,
            max_error,
            bias,
            correlation,
            gain,
            intercept,
            vision_measured: vision.len(),
            vision_rows,
            cycle_s,
            map_source: map.source.clone(),
        },
        Aligned {
            t,
            vision: y,
            encoder: encoder_vals,
        },
    ))
}

fn pearson(a: &[f64], b: &[f64]) -> f64 {
    let n = a.len() as f64;
    let (ma, mb) = (a.iter().sum::<f64>() / n, b.iter().sum::<f64>() / n);
    let (mut sab, mut saa, mut sbb) = (0.0, 0.0, 0.0);
    for (x, y) in a.iter().zip(b) {
        sab += (x - ma) * (y - mb);
        saa += (x - ma) * (x - ma);
        sbb += (y - mb) * (y - mb);
    }
    sab / (saa * sbb).sqrt().max(f64::MIN_POSITIVE)
}

/// The motion's dominant period from the encoder's autocorrelation (first peak after the
/// first zero crossing); the recording length if there is none.
fn dominant_period(enc: &EncoderSignal) -> f64 {
    let (_, x) = resample(&enc.t, |t| enc.at(t));
    let step = 10; // 10 ms lags are plenty for a period
    let n = x.len();
    let ac = |lag: usize| -> f64 {
        (0..n - lag)
            .step_by(step)
            .map(|i| x[i] * x[i + lag])
            .sum::<f64>()
            / (n - lag) as f64
    };
    let total = n as f64 * GRID_S;
    let mut lag = step;
    while lag < n / 2 && ac(lag) > 0.0 {
        lag += step;
    }
    let mut best = (f64::NEG_INFINITY, 0usize);
    while lag < n / 2 {
        let v = ac(lag);
        if v > best.0 {
            best = (v, lag);
        } else if best.0 > 0.0 && v < 0.0 {
            break;
        }
        lag += step;
    }
    if best.1 == 0 {
        total
    } else {
        best.1 as f64 * GRID_S
    }
}

/// Plot vision and encoder over one cycle from the middle of the recording, like the paper's
/// `fig:eef-dot-trails`.
pub fn plot_cycle(cmp: &Comparison, aligned: &Aligned, path: &Path) -> Result<(), BenchError> {
    let (Some(&first), Some(&last)) = (aligned.t.first(), aligned.t.last()) else {
        return Err(file_err(path, "nothing to plot".into()));
    };
    let span = cmp.cycle_s.min(last - first);
    let start = (first + last - span) / 2.0;
    let window = |v: &[f64]| -> Vec<(f64, f64)> {
        aligned
            .t
            .iter()
            .zip(v)
            .filter(|(t, _)| **t >= start && **t <= start + span)
            .map(|(t, v)| (t - start, *v))
            .collect()
    };
    let unit = match cmp.unit {
        OpeningUnit::Deg => "deg",
        OpeningUnit::Px => "px",
    };
    let mut fig = Chart::new(
        900,
        500,
        &format!(
            "vision vs encoder: rmse {:.3} {unit}, n {}",
            cmp.rmse, cmp.n
        ),
        Axis::new("time in cycle (s)"),
        Axis::new(&format!("opening ({unit})")),
    );
    // As in the paper's figure: vision in blue, the encoder in orange on top.
    fig.series.push(Series {
        name: "vision".into(),
        color: [31, 95, 191],
        mark: Mark::Points(2),
        points: window(&aligned.vision),
    });
    fig.series.push(Series {
        name: "encoder".into(),
        color: [235, 125, 20],
        mark: Mark::Line(2),
        points: window(&aligned.encoder),
    });
    fig.save_svg(path)
        .map_err(|e| file_err(path, e.to_string()))
}

/// Files written by [`run`].
#[derive(Debug, Clone)]
pub struct CompareOutputs {
    /// `compare.json`.
    pub json: PathBuf,
    /// `compare.svg`.
    pub plot: PathBuf,
    /// `aligned.csv`.
    pub aligned: PathBuf,
}

/// Read both files, compare and write `compare.json`, `compare.svg` and `aligned.csv`
/// (`t_video,vision,encoder,error`) into `out_dir`.
pub fn run(
    encoder_path: &Path,
    vision_path: &Path,
    map: &EncoderMap,
    out_dir: &Path,
) -> Result<(Comparison, CompareOutputs), BenchError> {
    if !(map.counts_per_rev.is_finite() && map.counts_per_rev > 0.0) {
        return Err(BenchError::Setting {
            name: "counts-per-rev",
            detail: format!("expected a positive count, got {}", map.counts_per_rev),
        });
    }
    if !(map.scale.is_finite() && map.scale != 0.0) {
        return Err(BenchError::Setting {
            name: "scale",
            detail: format!(
                "expected a finite non-zero jaw/horn ratio, got {}",
                map.scale
            ),
        });
    }
    let encoder = read_encoder(encoder_path)?;
    let (vision, unit, rows) = read_vision(vision_path)?;
    let (cmp, aligned) = compare(&encoder, &vision, unit, rows, map)?;
    std::fs::create_dir_all(out_dir)
        .map_err(|e| file_err(out_dir, format!("cannot create the output folder: {e}")))?;
    let outputs = CompareOutputs {
        json: out_dir.join("compare.json"),
        plot: out_dir.join("compare.svg"),
        aligned: out_dir.join("aligned.csv"),
    };
    let json =
        serde_json::to_string_pretty(&cmp).map_err(|e| file_err(&outputs.json, e.to_string()))?;
    let write = |p: &Path, b: &[u8]| {
        kiwi_core::io::write_atomic(p, b).map_err(|e| file_err(p, e.to_string()))
    };
    write(&outputs.json, json.as_bytes())?;
    let mut csv = String::from("t_video,vision,encoder,error\n");
    for i in 0..aligned.t.len() {
        let (v, e) = (aligned.vision[i], aligned.encoder[i]);
        csv.push_str(&format!("{:.6},{v:.6},{e:.6},{:.6}\n", aligned.t[i], v - e));
    }
    write(&outputs.aligned, csv.as_bytes())?;
    plot_cycle(&cmp, &aligned, &outputs.plot)?;
    Ok((cmp, outputs))
}
