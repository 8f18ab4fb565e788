//! IMU samples, validated IMU series, and the `imu.csv` format every KIWI tool reads.
//!
//! `imu.csv` has the header `t,gx,gy,gz,ax,ay,az`: time in seconds on the camera's own clock,
//! angular rate in rad/s, specific force in m/s² (gravity included, as an accelerometer reads it),
//! all in the IMU frame. [`ImuCsvReader`] streams it sample by sample so hour-long static logs
//! never sit in memory; [`ImuSeries`] holds a validated in-memory series.

use std::io::{BufRead, BufReader, BufWriter, Read, Write};
use std::path::{Path, PathBuf};

use nalgebra::Vector3;

use crate::error::{CoreError, Result};
use crate::io::write_atomic_with;

/// The header of `imu.csv`.
pub const IMU_CSV_HEADER: &str = "t,gx,gy,gz,ax,ay,az";

/// A gap is reported when consecutive samples are further apart than this many nominal periods
/// (a dropped sample or two is normal jitter; more means data is missing).
pub const GAP_FACTOR: f64 = 2.5;

/// One IMU reading.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ImuSample {
    /// Time (s) on the device clock.
    pub t: f64,
    /// Angular rate (rad/s) in the IMU frame.
    pub gyro: Vector3<f64>,
    /// Specific force (m/s²) in the IMU frame, gravity included.
    pub accel: Vector3<f64>,
}

impl ImuSample {
    /// A sample from its parts.
    pub fn new(t: f64, gyro: Vector3<f64>, accel: Vector3<f64>) -> Self {
        Self { t, gyro, accel }
    }

    fn is_finite(&self) -> bool {
        self.t.is_finite()
            && self
                .gyro
                .iter()
                .chain(self.accel.iter())
                .all(|v| v.is_finite())
    }
}

/// A stretch where samples are missing.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ImuGap {
    /// Time of the last sample before the gap (s).
    pub start: f64,
    /// Time of the first sample after the gap (s).
    pub end: f64,
}

/// A validated IMU series: finite values, strictly increasing timestamps, at least two samples.
#[derive(Debug, Clone)]
pub struct ImuSeries {
    samples: Vec<ImuSample>,
    rate_hz: f64,
    gaps: Vec<ImuGap>,
}

impl ImuSeries {
    /// Validate samples; `source` names where they came from in error messages.
    pub fn new(samples: Vec<ImuSample>, source: &Path) -> Result<Self> {
        if samples.len() < 2 {
            return Err(CoreError::Invalid {
                path: source.to_path_buf(),
                field: "samples".into(),
                expected: "at least 2 IMU samples".into(),
                found: format!("{}", samples.len()),
                fix: "record a longer log or check that the file is the IMU stream".into(),
            });
        }
        for (i, s) in samples.iter().enumerate() {
            if !s.is_finite() {
                return Err(CoreError::Invalid {
                    path: source.to_path_buf(),
                    field: format!("sample {i} (t = {})", s.t),
                    expected: "finite values".into(),
                    found: "NaN or infinity".into(),
                    fix: "remove or repair the sample".into(),
                });
            }
            if i > 0 && s.t <= samples[i - 1].t {
                return Err(non_monotonic(
                    source,
                    &format!("sample {i}"),
                    s.t,
                    samples[i - 1].t,
                ));
            }
        }
        let mut dts: Vec<f64> = samples.windows(2).map(|w| w[1].t - w[0].t).collect();
        let period = median(&mut dts);
        let gaps = samples
            .windows(2)
            .filter(|w| w[1].t - w[0].t > GAP_FACTOR * period)
            .map(|w| ImuGap {
                start: w[0].t,
                end: w[1].t,
            })
            .collect();
        Ok(Self {
            samples,
            rate_hz: 1.0 / period,
            gaps,
        })
    }

    /// Read and validate an `imu.csv` file, including the units check of [`check_imu_log`].
    pub fn read_csv(path: &Path) -> Result<Self> {
        let reader = ImuCsvReader::open(path)?;
        let samples = reader.collect::<Result<Vec<_>>>()?;
        let series = Self::new(samples, path)?;
        check_imu_samples(path, &series.samples)?;
        Ok(series)
    }

    /// Write the series as `imu.csv` atomically.
    pub fn write_csv(&self, path: &Path) -> Result<()> {
        write_imu_csv(path, &self.samples)
    }

    /// The samples, in time order.
    pub fn samples(&self) -> &[ImuSample] {
        &self.samples
    }

    /// Sample rate estimated from the median period (Hz).
    pub fn rate_hz(&self) -> f64 {
        self.rate_hz
    }

    /// Stretches longer than [`GAP_FACTOR`] nominal periods without samples.
    pub fn gaps(&self) -> &[ImuGap] {
        &self.gaps
    }

    /// First and last timestamps (s).
    pub fn time_range(&self) -> (f64, f64) {
        (self.samples[0].t, self.samples[self.samples.len() - 1].t)
    }

    /// Linear interpolation of the reading at time `t`; `None` outside the series.
    pub fn interpolate(&self, t: f64) -> Option<ImuSample> {
        let (t0, t1) = self.time_range();
        if !(t >= t0 && t <= t1) {
            return None;
        }
        let i = self.samples.partition_point(|s| s.t <= t);
        if i == 0 {
            return Some(self.samples[0]);
        }
        if i >= self.samples.len() {
            return Some(self.samples[self.samples.len() - 1]);
        }
        let (a, b) = (&self.samples[i - 1], &self.samples[i]);
        let s = (t - a.t) / (b.t - a.t);
        Some(ImuSample {
            t,
            gyro: a.gyro.lerp(&b.gyro, s),
            accel: a.accel.lerp(&b.accel, s),
        })
    }
}

/// The error for a timestamp that does not increase.
fn non_monotonic(path: &Path, field: &str, t: f64, previous: f64) -> CoreError {
    CoreError::Invalid {
        path: path.to_path_buf(),
        field: format!("{field}, column t"),
        expected: format!("a timestamp after the previous {previous} s"),
        found: format!("{t} s"),
        fix: "the log must be sorted with no repeated times (was it concatenated or merged?)"
            .into(),
    }
}

/// Median of a slice (reorders it). Panics never; returns NaN for an empty slice.
fn median(values: &mut [f64]) -> f64 {
    if values.is_empty() {
        return f64::NAN;
    }
    let mid = values.len() / 2;
    let (_, m, _) = values.select_nth_unstable_by(mid, f64::total_cmp);
    *m
}

/// Streams `imu.csv` one validated sample at a time (finite, increasing timestamps), so logs of
/// hours at 1 kHz are read in bounded memory.
pub struct ImuCsvReader<R: Read> {
    lines: std::io::Lines<BufReader<R>>,
    path: PathBuf,
    line_number: usize,
    previous_t: Option<f64>,
}

impl ImuCsvReader<std::fs::File> {
    /// Open an `imu.csv` file and check its header.
    pub fn open(path: &Path) -> Result<Self> {
        let file = std::fs::File::open(path).map_err(|source| CoreError::Io {
            action: "opening",
            path: path.to_path_buf(),
            source,
        })?;
        Self::from_reader(file, path)
    }
}

impl<R: Read> ImuCsvReader<R> {
    /// Read `imu.csv` content from any reader; `path` is used in error messages.
    pub fn from_reader(reader: R, path: &Path) -> Result<Self> {
        let mut lines = BufReader::with_capacity(1 << 16, reader).lines();
        let header = match lines.next() {
            Some(Ok(h)) => h,
            Some(Err(source)) => {
                return Err(CoreError::Io {
                    action: "reading",
                    path: path.to_path_buf(),
                    source,
                });
            }
            None => String::new(),
        };
        let normalized: String = header
            .trim()
            .chars()
            .filter(|c| !c.is_whitespace())
            .collect();
        if normalized != IMU_CSV_HEADER {
            return Err(CoreError::Invalid {
                path: path.to_path_buf(),
                field: "line 1 (header)".into(),
                expected: format!("the header `{IMU_CSV_HEADER}` (s, rad/s, m/s²)"),
                found: format!("`{}`", header.trim()),
                fix: "convert the log to KIWI's imu.csv format (see docs/conventions.md)".into(),
            });
        }
        Ok(Self {
            lines,
            path: path.to_path_buf(),
            line_number: 1,
            previous_t: None,
        })
    }

    fn parse_line(&self, line: &str) -> Result<ImuSample> {
        let mut values = [0.0; 7];
        let mut count = 0;
        for (i, field) in line.split(',').enumerate() {
            if i >= 7 {
                count = 8;
                break;
            }
            let field = field.trim();
            values[i] = field.parse::<f64>().map_err(|_| CoreError::Invalid {
                path: self.path.clone(),
                field: format!("line {}, column {}", self.line_number, column_name(i)),
                expected: "a number".into(),
                found: format!("`{field}`"),
                fix: "repair or remove the line".into(),
            })?;
            count = i + 1;
        }
        if count != 7 {
            return Err(CoreError::Invalid {
                path: self.path.clone(),
                field: format!("line {}", self.line_number),
                expected: "7 comma-separated values (t,gx,gy,gz,ax,ay,az)".into(),
                found: format!(
                    "{} values",
                    if count > 7 {
                        "more than 7".into()
                    } else {
                        count.to_string()
                    }
                ),
                fix: "repair or remove the line".into(),
            });
        }
        let sample = ImuSample::new(
            values[0],
            Vector3::new(values[1], values[2], values[3]),
            Vector3::new(values[4], values[5], values[6]),
        );
        if !sample.is_finite() {
            return Err(CoreError::Invalid {
                path: self.path.clone(),
                field: format!("line {}", self.line_number),
                expected: "finite values".into(),
                found: "NaN or infinity".into(),
                fix: "repair or remove the line".into(),
            });
        }
        Ok(sample)
    }
}

fn column_name(i: usize) -> &'static str {
    ["t", "gx", "gy", "gz", "ax", "ay", "az"]
        .get(i)
        .copied()
        .unwrap_or("?")
}

impl<R: Read> Iterator for ImuCsvReader<R> {
    type Item = Result<ImuSample>;

    fn next(&mut self) -> Option<Self::Item> {
        loop {
            let line = match self.lines.next()? {
                Ok(l) => l,
                Err(source) => {
                    return Some(Err(CoreError::Io {
                        action: "reading",
                        path: self.path.clone(),
                        source,
                    }));
                }
            };
            self.line_number += 1;
            if line.trim().is_empty() {
                continue;
            }
            let sample = match self.parse_line(&line) {
                Ok(s) => s,
                Err(e) => return Some(Err(e)),
            };
            if let Some(prev) = self.previous_t
                && sample.t <= prev
            {
                return Some(Err(non_monotonic(
                    &self.path,
                    &format!("line {}", self.line_number),
                    sample.t,
                    prev,
                )));
            }
            self.previous_t = Some(sample.t);
            return Some(Ok(sample));
        }
    }
}

/// Writes `imu.csv` incrementally (for logs too long to hold in memory). Call
/// [`ImuCsvWriter::finish`] to flush; the file is written in place, so write to a temporary
/// name and rename when the whole log is complete.
pub struct ImuCsvWriter<W: Write> {
    out: BufWriter<W>,
}

impl<W: Write> ImuCsvWriter<W> {
    /// Start a file: writes the header.
    pub fn new(writer: W) -> std::io::Result<Self> {
        let mut out = BufWriter::with_capacity(1 << 16, writer);
        writeln!(out, "{IMU_CSV_HEADER}")?;
        Ok(Self { out })
    }

    /// Append one sample (shortest representations that read back to the same `f64`).
    pub fn write(&mut self, s: &ImuSample) -> std::io::Result<()> {
        writeln!(
            self.out,
            "{},{:e},{:e},{:e},{:e},{:e},{:e}",
            s.t, s.gyro.x, s.gyro.y, s.gyro.z, s.accel.x, s.accel.y, s.accel.z
        )
    }

    /// Flush and return the underlying writer.
    pub fn finish(self) -> std::io::Result<W> {
        self.out
            .into_inner()
            .map_err(std::io::IntoInnerError::into_error)
    }
}

/// Write samples as `imu.csv` atomically (temporary file + rename).
pub fn write_imu_csv(path: &Path, samples: &[ImuSample]) -> Result<()> {
    write_atomic_with(path, |file| {
        let mut writer = ImuCsvWriter::new(file)?;
        for s in samples {
            writer.write(s)?;
        }
        writer.finish()?;
        Ok(())
    })
}

/// Standard gravity (m/s²).
pub const STANDARD_GRAVITY_M_S2: f64 = 9.806_65;
/// Lowest plausible IMU sample rate (Hz): camera IMUs log at 100 Hz to a few kHz, phones at
/// 50 Hz or more; below this the timestamps are almost certainly not in seconds.
const MIN_IMU_RATE_HZ: f64 = 20.0;
/// Highest plausible IMU sample rate (Hz): no MEMS IMU streams faster.
const MAX_IMU_RATE_HZ: f64 = 20_000.0;
/// A resting accelerometer reads |g| within this of standard gravity (m/s²): latitude and
/// altitude change g by < 0.05 m/s², consumer IMUs' scale and bias errors by a few per cent.
const REST_GRAVITY_TOLERANCE_M_S2: f64 = 1.0;
/// Without a resting stretch the median |specific force| of a hand-held log lies in this range
/// (m/s²): hand motion adds and removes up to a few g around gravity, but only free fall
/// brings the median below half a g, and no hand keeps up 5 g; a log in g (median ≈ 1–3) or in
/// mm/s² (≈ 10 000) falls far outside.
const MOVING_GRAVITY_RANGE_M_S2: (f64, f64) = (5.0, 50.0);
/// Length (s) of the windows in which rest is detected.
const REST_WINDOW_S: f64 = 0.1;
/// A window is at rest when the mean specific force of its two halves differs by less than
/// this fraction of |g| (0.01 ≈ 0.2 rad/s of rotation or 0.1 m/s² of acceleration change).
const REST_CHANGE_FRACTION: f64 = 0.01;
/// ... and when |specific force| varies by less than this fraction of its mean (a tap or a
/// shake is not rest).
const REST_SPREAD_FRACTION: f64 = 0.05;
/// Rest-based checks need at least this many resting windows (half a second).
const MIN_REST_WINDOWS: usize = 5;
/// At rest a gyro reads its zero-rate offset (consumer MEMS: ±1–5 °/s) plus the little
/// rotation rest allows; a median above this (rad/s, ≈ 29 °/s) is not rad/s.
const MAX_REST_GYRO_RAD_S: f64 = 0.5;
/// The white noise density of MEMS gyros is 5e-5 to 5e-4 rad/s/√Hz; ten times the worst is
/// not a gyro in rad/s (in deg/s the same sensors read 57× higher).
const MAX_GYRO_NOISE_DENSITY: f64 = 5e-3;
/// No MEMS gyro measures beyond ±4000 °/s (70 rad/s); readings above this are in other units.
const MAX_GYRO_RAD_S: f64 = 70.0;
/// Fraction of samples allowed above [`MAX_GYRO_RAD_S`] (isolated glitches).
const MAX_GYRO_OUTLIER_FRACTION: f64 = 1e-3;
/// Length (s) of the windows of the rotation-consistency fit: short enough to follow hand
/// rotation, long enough to average the sensors' white noise.
const ROTATION_WINDOW_S: f64 = 0.02;
/// The rotation-consistency scale is trusted when its standard error is below this.
const ROTATION_SCALE_MAX_SE: f64 = 0.05;
/// A trusted rotation scale outside this range means gyro and accelerometer disagree. Wide on
/// purpose: the body's own acceleration biases the fit low on some motions (simulated 40 s
/// hand-held surveys: seed 11 fits 0.45 and 0.71 on its two wrists, seeds 3 and 7 fit
/// 0.93-1.05; tabletop and walk episodes 0.94-1.11), so the lower bound keeps about half the
/// lowest fit seen as margin, while the mistakes it is for are far outside (deg/s read as
/// rad/s: ×57; rad/s read as deg/s: ×1/57; a flipped frame: < 0).
const ROTATION_SCALE_RANGE: (f64, f64) = (0.25, 4.0);
/// The rotation-consistency fit needs the log to turn: below this RMS rate (rad/s, about
/// 6 °/s) of the windowed gyro, its regressor is gyro noise and the fitted scale shrinks
/// towards zero whatever the units (a resting or slowly drifting log).
const ROTATION_MIN_RMS_RAD_S: f64 = 0.1;
/// Degrees per radian: a gyro in deg/s reads this many times the rad/s value.
const DEG_PER_RAD: f64 = 180.0 / std::f64::consts::PI;

/// What [`check_imu_log`] measured in an IMU log.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct ImuLogSummary {
    /// Number of samples.
    pub samples: usize,
    /// Mean sample rate (Hz).
    pub rate_hz: f64,
    /// Duration (s).
    pub duration_s: f64,
    /// |specific force| at rest (or the median over the log when it never rests), m/s².
    pub gravity_m_s2: f64,
    /// Fraction of the log's windows in which the IMU rests.
    pub rest_fraction: f64,
    /// Rotation the gyro reports relative to the rotation of gravity the accelerometer sees
    /// (≈ 1 for a consistent log); `None` when the log turns too little to tell.
    pub rotation_scale: Option<f64>,
}

/// Check that an IMU log is physically plausible in KIWI's units: timestamps in seconds
/// (a plausible rate), accelerometer in m/s² (|g| at rest), gyroscope in rad/s (magnitudes,
/// noise at rest, and rotation consistent with the accelerometer's view of gravity). An error
/// names the likely unit mistake and the fix. Every reader of an IMU log calls this.
///
/// `n` samples span `time_range`; `gyro(i)` and `accel(i)` give sample `i`.
pub fn check_imu_log(
    path: &Path,
    n: usize,
    time_range: (f64, f64),
    gyro: impl Fn(usize) -> Vector3<f64>,
    accel: impl Fn(usize) -> Vector3<f64>,
) -> Result<ImuLogSummary> {
    let (t0, t1) = time_range;
    let duration_s = t1 - t0;
    let invalid = |field: &str, expected: String, found: String, fix: String| CoreError::Invalid {
        path: path.to_path_buf(),
        field: field.into(),
        expected,
        found,
        fix,
    };
    if n < 2 || duration_s.is_nan() || duration_s <= 0.0 {
        return Err(invalid(
            "samples",
            "at least 2 samples with increasing times".into(),
            format!("{n} sample(s) over {duration_s} s"),
            "record a longer log or check that the file is the IMU stream".into(),
        ));
    }
    let rate_hz = (n - 1) as f64 / duration_s;
    if !(MIN_IMU_RATE_HZ..=MAX_IMU_RATE_HZ).contains(&rate_hz) {
        return Err(invalid(
            "column t",
            format!(
                "times in seconds: a sample rate between {MIN_IMU_RATE_HZ} and \
                 {MAX_IMU_RATE_HZ} Hz"
            ),
            format!(
                "{n} samples over {duration_s} s, i.e. {rate_hz:.4} Hz over {:.2} h",
                duration_s / 3600.0
            ),
            time_unit_hint(rate_hz),
        ));
    }
    let mut summary = ImuLogSummary {
        samples: n,
        rate_hz,
        duration_s,
        gravity_m_s2: f64::NAN,
        rest_fraction: 0.0,
        rotation_scale: None,
    };

    // Rest windows (scale-free: judged by the accelerometer's steadiness alone).
    let w = ((REST_WINDOW_S * rate_hz).round() as usize).max(4);
    let mut rest_gravity = Vec::new();
    let mut rest_gyro = Vec::new();
    let mut rest_gyro_std = Vec::new();
    let mut window_gravity = Vec::new();
    for start in (0..n.saturating_sub(w - 1)).step_by(w) {
        let half = w / 2;
        let mean = |range: std::ops::Range<usize>, f: &dyn Fn(usize) -> Vector3<f64>| {
            let len = range.len() as f64;
            range.map(f).sum::<Vector3<f64>>() / len
        };
        let a1 = mean(start..start + half, &accel);
        let a2 = mean(start + half..start + w, &accel);
        let a = (a1 + a2) / 2.0;
        let norms: Vec<f64> = (start..start + w).map(|i| accel(i).norm()).collect();
        let mu = norms.iter().sum::<f64>() / w as f64;
        let spread = (norms.iter().map(|v| (v - mu).powi(2)).sum::<f64>() / (w - 1) as f64).sqrt();
        window_gravity.push(a.norm());
        if mu > 0.0
            && (a1 - a2).norm() < REST_CHANGE_FRACTION * mu
            && spread < REST_SPREAD_FRACTION * mu
        {
            rest_gravity.push(a.norm());
            let g = mean(start..start + w, &gyro);
            rest_gyro.push(g.norm());
            let var = (start..start + w)
                .map(|i| (gyro(i) - g).norm_squared())
                .sum::<f64>()
                / (3 * (w - 1)) as f64;
            rest_gyro_std.push(var.sqrt());
        }
    }
    let windows = window_gravity.len().max(1);
    summary.rest_fraction = rest_gravity.len() as f64 / windows as f64;
    let at_rest = rest_gravity.len() >= MIN_REST_WINDOWS;
    let (gravity, range) = if at_rest {
        let g = median(&mut rest_gravity);
        (
            g,
            (
                STANDARD_GRAVITY_M_S2 - REST_GRAVITY_TOLERANCE_M_S2,
                STANDARD_GRAVITY_M_S2 + REST_GRAVITY_TOLERANCE_M_S2,
            ),
        )
    } else if !window_gravity.is_empty() {
        (median(&mut window_gravity), MOVING_GRAVITY_RANGE_M_S2)
    } else {
        let mut all: Vec<f64> = (0..n).map(|i| accel(i).norm()).collect();
        (median(&mut all), MOVING_GRAVITY_RANGE_M_S2)
    };
    summary.gravity_m_s2 = gravity;
    if !(range.0..=range.1).contains(&gravity) {
        return Err(invalid(
            "columns ax, ay, az",
            format!(
                "specific force in m/s²: |accelerometer| ≈ {STANDARD_GRAVITY_M_S2} m/s² {}",
                if at_rest {
                    format!("at rest ({} to {})", range.0, range.1)
                } else {
                    format!(
                        "over the log (median of 0.1 s means {} to {})",
                        range.0, range.1
                    )
                }
            ),
            format!("{gravity:.4}"),
            gravity_unit_hint(gravity).into(),
        ));
    }

    // Gyro magnitudes beyond any MEMS range.
    let over = (0..n).filter(|&i| gyro(i).norm() > MAX_GYRO_RAD_S).count();
    if over as f64 > MAX_GYRO_OUTLIER_FRACTION * n as f64 {
        let peak = (0..n).map(|i| gyro(i).norm()).fold(0.0, f64::max);
        return Err(invalid(
            "columns gx, gy, gz",
            format!("angular rate in rad/s: at most {MAX_GYRO_RAD_S} rad/s (4000 °/s)"),
            format!("{over} samples above it, up to {peak:.1}"),
            DEG_PER_S_FIX.into(),
        ));
    }

    // At rest the gyro reads its offset and white noise.
    if at_rest {
        let offset = median(&mut rest_gyro);
        let density = median(&mut rest_gyro_std) / rate_hz.sqrt();
        if offset > MAX_REST_GYRO_RAD_S || density > MAX_GYRO_NOISE_DENSITY {
            return Err(invalid(
                "columns gx, gy, gz",
                format!(
                    "angular rate in rad/s: at rest, an offset below {MAX_REST_GYRO_RAD_S} rad/s \
                     and white noise below {MAX_GYRO_NOISE_DENSITY:e} rad/s/√Hz"
                ),
                format!(
                    "an offset of {offset:.4} and white noise of {density:.3e} /√Hz while the \
                     accelerometer rests"
                ),
                DEG_PER_S_FIX.into(),
            ));
        }
    }

    // Rotation consistency: in the body frame, specific force f turns as df/dt = -ω × f
    // (plus the body's jerk, uncorrelated with it), so regressing df/dt on -ω × f gives the
    // gyro's scale relative to the rotation the accelerometer sees.
    let wr = ((ROTATION_WINDOW_S * rate_hz).round() as usize).max(1);
    let m = n / wr;
    if m >= 3 {
        let means: Vec<(Vector3<f64>, Vector3<f64>)> = (0..m)
            .map(|k| {
                let r = k * wr..(k + 1) * wr;
                let g = r.clone().map(&gyro).sum::<Vector3<f64>>() / wr as f64;
                let a = r.map(&accel).sum::<Vector3<f64>>() / wr as f64;
                (g, a)
            })
            .collect();
        let dt = 2.0 * wr as f64 / rate_hz;
        let (mut sxx, mut sxy, mut syy) = (0.0, 0.0, 0.0);
        for k in 1..m - 1 {
            let y = (means[k + 1].1 - means[k - 1].1) / dt;
            let x = -means[k].0.cross(&means[k].1);
            sxx += x.dot(&x);
            sxy += x.dot(&y);
            syy += y.dot(&y);
        }
        let count = 3 * (m - 2);
        let rms_rate = (means.iter().map(|(g, _)| g.norm_squared()).sum::<f64>() / m as f64).sqrt();
        if sxx > 0.0 && count > 3 && rms_rate >= ROTATION_MIN_RMS_RAD_S {
            let s = sxy / sxx;
            let residual = ((syy - s * sxy) / (count - 1) as f64).max(0.0);
            let se = (residual / sxx).sqrt();
            if se < ROTATION_SCALE_MAX_SE {
                summary.rotation_scale = Some(s);
                if !(ROTATION_SCALE_RANGE.0..=ROTATION_SCALE_RANGE.1).contains(&s) {
                    return Err(invalid(
                        "columns gx, gy, gz",
                        "angular rate in rad/s, in the accelerometer's axes: the rotation the \
                         gyro reports matches how gravity turns in the accelerometer (ratio ≈ 1)"
                            .into(),
                        format!("the gyro reports {s:.4} times that rotation (± {se:.4})"),
                        rotation_scale_hint(s).into(),
                    ));
                }
            }
        }
    }
    Ok(summary)
}

/// [`check_imu_log`] over samples in memory.
pub fn check_imu_samples(path: &Path, samples: &[ImuSample]) -> Result<ImuLogSummary> {
    let range = match (samples.first(), samples.last()) {
        (Some(a), Some(b)) => (a.t, b.t),
        _ => (0.0, 0.0),
    };
    check_imu_log(
        path,
        samples.len(),
        range,
        |i| samples[i].gyro,
        |i| samples[i].accel,
    )
}

const DEG_PER_S_FIX: &str = "the gyroscope looks like it is in deg/s: multiply gx, gy, gz by \
                             π/180 = 0.0174533 (KIWI's imu.csv is in rad/s)";

/// A log whose |specific force| (at rest, or its median while moving) lies in this range is in
/// g: 1 at rest, up to a few while shaken; no m/s² log reads this little unless in free fall.
const G_UNITS_RANGE: (f64, f64) = (0.5, 4.0);

/// The likely unit mistake behind an accelerometer that reads `gravity` at rest.
pub fn gravity_unit_hint(gravity: f64) -> &'static str {
    if (G_UNITS_RANGE.0..=G_UNITS_RANGE.1).contains(&gravity) {
        "the accelerometer looks like it is in g: multiply ax, ay, az by 9.80665"
    } else if (gravity / STANDARD_GRAVITY_M_S2 - 1000.0).abs() < 200.0
        || (gravity - 1000.0).abs() < 200.0
    {
        "the accelerometer looks like it is in mm/s² or milli-g: convert ax, ay, az to m/s²"
    } else if gravity < 0.5 {
        "the accelerometer reads no gravity: KIWI needs the raw specific force (gravity \
         included), not linear acceleration"
    } else {
        "convert the accelerometer columns to m/s² (docs/conventions.md)"
    }
}

fn time_unit_hint(rate_hz: f64) -> String {
    let plausible = |r: f64| (MIN_IMU_RATE_HZ..=MAX_IMU_RATE_HZ).contains(&r);
    for (factor, unit) in [
        (1e3, "milliseconds"),
        (1e6, "microseconds"),
        (1e9, "nanoseconds"),
    ] {
        if plausible(rate_hz * factor) {
            return format!(
                "the timestamps look like {unit} (a {:.0} Hz IMU): divide t by {factor:e} \
                 (KIWI's imu.csv is in seconds)",
                rate_hz * factor
            );
        }
    }
    "write t in seconds on the camera clock (docs/conventions.md)".into()
}

fn rotation_scale_hint(s: f64) -> &'static str {
    if (s * DEG_PER_RAD - 1.0).abs() < 0.5 {
        DEG_PER_S_FIX
    } else if s < 0.0 {
        "the gyro turns the opposite way: a gyro or accelerometer axis is flipped (or the \
         accelerometer reads gravity instead of specific force); express both in the same \
         right-handed IMU frame"
    } else {
        "check the gyro's units (rad/s) and that gyro and accelerometer share one IMU frame \
         (same axis order and signs)"
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn series(ts: &[f64]) -> Vec<ImuSample> {
        ts.iter()
            .map(|&t| ImuSample::new(t, Vector3::new(t, 0.0, 0.0), Vector3::new(0.0, 0.0, 9.81)))
            .collect()
    }

    #[test]
    fn validates_order_and_reports_gaps() {
        let p = Path::new("imu.csv");
        let ts: Vec<f64> = (0..100)
            .map(|i| f64::from(i) * 0.001)
            .chain([0.2, 0.201])
            .collect();
        let s = ImuSeries::new(series(&ts), p).unwrap();
        assert!((s.rate_hz() - 1000.0).abs() < 1e-6);
        assert_eq!(s.gaps().len(), 1);
        let err = ImuSeries::new(series(&[0.0, 0.001, 0.001]), p).unwrap_err();
        assert!(err.to_string().contains("sorted"), "{err}");
        let mut bad = series(&[0.0, 0.001, 0.002]);
        bad[1].accel.x = f64::NAN;
        assert!(ImuSeries::new(bad, p).is_err());
    }

    #[test]
    fn interpolates_linearly() {
        let s = ImuSeries::new(series(&[0.0, 1.0, 2.0]), Path::new("x")).unwrap();
        let m = s.interpolate(1.5).unwrap();
        assert!((m.gyro.x - 1.5).abs() < 1e-15);
        assert!(s.interpolate(2.5).is_none());
    }

    #[test]
    fn csv_round_trip_and_errors() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("imu.csv");
        let samples = series(&[0.0, 0.001, 0.002]);
        write_imu_csv(&path, &samples).unwrap();
        let back = ImuSeries::read_csv(&path).unwrap();
        assert_eq!(back.samples(), &samples[..]);

        let text = "t,gx,gy,gz,ax,ay,az\n0.0,0,0,0,0,0,9.8\n0.001,0,0,x,0,0,9.8\n";
        let err = ImuCsvReader::from_reader(text.as_bytes(), Path::new("imu.csv"))
            .unwrap()
            .collect::<Result<Vec<_>>>()
            .unwrap_err();
        assert!(err.to_string().contains("line 3, column gz"), "{err}");

        let err = ImuCsvReader::from_reader("time,wx\n".as_bytes(), Path::new("imu.csv"))
            .err()
            .unwrap();
        assert!(err.to_string().contains("header"), "{err}");

        let text = "t,gx,gy,gz,ax,ay,az\n0.002,0,0,0,0,0,9.8\n0.001,0,0,0,0,0,9.8\n";
        let err = ImuCsvReader::from_reader(text.as_bytes(), Path::new("imu.csv"))
            .unwrap()
            .collect::<Result<Vec<_>>>()
            .unwrap_err();
        assert!(err.to_string().contains("line 3"), "{err}");
    }
}
