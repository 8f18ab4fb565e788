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

    /// Read and validate an `imu.csv` file.
    pub fn read_csv(path: &Path) -> Result<Self> {
        let reader = ImuCsvReader::open(path)?;
        let samples = reader.collect::<Result<Vec<_>>>()?;
        Self::new(samples, path)
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
