//! IMU samples into KIWI's IMU frame and units: the per-model axis table of the cameras whose
//! files carry their own IMU, and the generic IMU CSV reader (any column names, time and sensor
//! units, axis map) for cameras that do not.
//!
//! KIWI's IMU frame of a unit is the frame its samples are written in (`imu.csv`), and the one
//! its calibration's `cam_from_imu` refers to. Any fixed proper rotation of the device axes
//! would do, as long as the unit's certification captures and its episodes go through the same
//! table; the table below is what `kiwi ingest` applies, and `meta.json` records the map used.

use std::path::Path;

use kiwi_core::imu::ImuSample;
use nalgebra::Vector3;

use crate::error::{BackendError, Result};
use crate::ingest::insv::STANDARD_GRAVITY;

/// KIWI's IMU axes x, y, z as signed device axes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct AxisMap {
    /// For each KIWI axis: the device axis (0 = x, 1 = y, 2 = z) and its sign (±1).
    pub axes: [(usize, i8); 3],
}

/// The axis maps of the camera models whose files carry IMU samples: `(camera model as the file
/// names it, map)`. Read from the public orientation table of Gyroflow's telemetry-parser for
/// files with an `offset_v3` lens calibration (X4 and X5: `yzX`; GO 3: `XYZ`, where an
/// upper-case letter is a device axis and a lower-case one its negative, one letter per output
/// axis). Not checked against a real recording here: see docs/ingest.md.
pub const MODEL_AXES: &[(&str, &str)] = &[
    ("Insta360 X5", "-y,-z,+x"),
    ("Insta360 X4", "-y,-z,+x"),
    ("Insta360 GO 3", "+x,+y,+z"),
];

impl AxisMap {
    /// The identity map.
    pub const IDENTITY: Self = Self {
        axes: [(0, 1), (1, 1), (2, 1)],
    };

    /// Parse `+x,+y,+z` style maps: KIWI x, y and z as signed device axes. The map must be a
    /// rotation (each device axis once, no mirror).
    pub fn parse(text: &str) -> std::result::Result<Self, String> {
        let parts: Vec<&str> = text.split(',').map(str::trim).collect();
        if parts.len() != 3 {
            return Err(format!(
                "`{text}`: expected three signed axes separated by commas, e.g. +x,-z,+y"
            ));
        }
        let mut axes = [(0usize, 1i8); 3];
        for (k, p) in parts.iter().enumerate() {
            let (sign, axis) = match p.as_bytes() {
                [b'+', a] | [a] => (1, *a),
                [b'-', a] => (-1, *a),
                _ => {
                    return Err(format!(
                        "`{p}` in `{text}`: expected +x, -x, +y, -y, +z or -z"
                    ));
                }
            };
            let axis = match axis.to_ascii_lowercase() {
                b'x' => 0,
                b'y' => 1,
                b'z' => 2,
                _ => return Err(format!("`{p}` in `{text}`: the axis is x, y or z")),
            };
            axes[k] = (axis, sign);
        }
        let map = Self { axes };
        let mut seen = [false; 3];
        for (a, _) in axes {
            seen[a] = true;
        }
        if seen.contains(&false) {
            return Err(format!("`{text}`: each device axis must appear once"));
        }
        if map.determinant() < 0 {
            return Err(format!(
                "`{text}` mirrors the axes (a left-handed frame); flip the sign of one axis"
            ));
        }
        Ok(map)
    }

    /// `+1` for a rotation, `-1` for a mirror.
    pub fn determinant(&self) -> i32 {
        let mut m = [[0i32; 3]; 3];
        for (row, (axis, sign)) in self.axes.iter().enumerate() {
            m[row][*axis] = i32::from(*sign);
        }
        m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
            - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
    }

    /// A device vector in KIWI's axes.
    pub fn apply(&self, v: [f64; 3]) -> Vector3<f64> {
        Vector3::from_fn(|i, _| {
            let (axis, sign) = self.axes[i];
            f64::from(sign) * v[axis]
        })
    }

    /// The map's text form.
    pub fn text(&self) -> String {
        self.axes
            .iter()
            .map(|(a, s)| format!("{}{}", if *s > 0 { '+' } else { '-' }, ['x', 'y', 'z'][*a]))
            .collect::<Vec<_>>()
            .join(",")
    }

    /// The table's map for a camera model.
    pub fn for_model(model: &str) -> Option<Self> {
        MODEL_AXES
            .iter()
            .find(|(m, _)| *m == model)
            .and_then(|(_, text)| Self::parse(text).ok())
    }
}

/// Time unit of an IMU CSV's time column.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TimeUnit(pub f64);

impl TimeUnit {
    /// Parse `s`, `ms`, `us`, `ns`.
    pub fn parse(text: &str) -> std::result::Result<Self, String> {
        match text {
            "s" => Ok(Self(1.0)),
            "ms" => Ok(Self(1e-3)),
            "us" => Ok(Self(1e-6)),
            "ns" => Ok(Self(1e-9)),
            other => Err(format!("`{other}`: expected s, ms, us or ns")),
        }
    }
}

/// How to read a generic IMU CSV.
#[derive(Debug, Clone)]
pub struct ImuCsvOptions {
    /// Column names of time, gyro x y z and accel x y z, in that order.
    pub columns: [String; 7],
    /// Seconds per unit of the time column.
    pub time_unit: TimeUnit,
    /// Gyroscope in degrees per second (else rad/s).
    pub gyro_deg_s: bool,
    /// Accelerometer in g (else m/s²).
    pub accel_g: bool,
    /// KIWI axes from the file's axes.
    pub axes: AxisMap,
    /// Added to the file's times to put them on the video clock (s).
    pub time_offset_s: f64,
}

impl Default for ImuCsvOptions {
    fn default() -> Self {
        Self {
            columns: ["t", "gx", "gy", "gz", "ax", "ay", "az"].map(String::from),
            time_unit: TimeUnit(1.0),
            gyro_deg_s: false,
            accel_g: false,
            axes: AxisMap::IDENTITY,
            time_offset_s: 0.0,
        }
    }
}

/// Parse `--imu-columns t,gx,gy,gz,ax,ay,az` (seven names).
pub fn parse_columns(text: &str) -> std::result::Result<[String; 7], String> {
    let v: Vec<String> = text.split(',').map(|s| s.trim().to_string()).collect();
    v.try_into().map_err(|v: Vec<String>| {
        format!(
            "`{text}`: expected 7 column names (time, gyro x y z, accel x y z), found {}",
            v.len()
        )
    })
}

/// Read a generic IMU CSV into KIWI samples (video clock, SI units, KIWI axes).
pub fn read_imu_csv(path: &Path, o: &ImuCsvOptions) -> Result<Vec<ImuSample>> {
    let bad = |message: String| BackendError::Input {
        path: path.to_path_buf(),
        message,
    };
    let mut reader = csv::ReaderBuilder::new()
        .has_headers(true)
        .trim(csv::Trim::All)
        .from_path(path)
        .map_err(|e| bad(format!("cannot read the IMU CSV: {e}")))?;
    let headers = reader
        .headers()
        .map_err(|e| bad(format!("cannot read the header: {e}")))?
        .clone();
    let mut idx = [0usize; 7];
    for (k, name) in o.columns.iter().enumerate() {
        idx[k] = headers.iter().position(|h| h == name).ok_or_else(|| {
            bad(format!(
                "line 1: no column `{name}` (columns: {}); name the columns with --imu-columns",
                headers.iter().collect::<Vec<_>>().join(",")
            ))
        })?;
    }
    let gyro_scale = if o.gyro_deg_s {
        std::f64::consts::PI / 180.0
    } else {
        1.0
    };
    let accel_scale = if o.accel_g { STANDARD_GRAVITY } else { 1.0 };
    let mut out: Vec<ImuSample> = Vec::new();
    for (i, row) in reader.records().enumerate() {
        let line = i + 2;
        let row = row.map_err(|e| bad(format!("line {line}: {e}")))?;
        let mut v = [0f64; 7];
        for k in 0..7 {
            let text = row.get(idx[k]).unwrap_or("");
            v[k] = text.parse().map_err(|_| {
                bad(format!(
                    "line {line}, column {}: expected a number, found `{text}`",
                    o.columns[k]
                ))
            })?;
            if !v[k].is_finite() {
                return Err(bad(format!(
                    "line {line}, column {}: not finite",
                    o.columns[k]
                )));
            }
        }
        let t = v[0] * o.time_unit.0 + o.time_offset_s;
        if let Some(prev) = out.last()
            && t <= prev.t
        {
            return Err(bad(format!(
                "line {line}: time {t} s is not after the previous {} s; the log must be sorted \
                 with no repeated times (check --imu-time-unit)",
                prev.t
            )));
        }
        let gyro = o.axes.apply([v[1], v[2], v[3]]) * gyro_scale;
        let accel = o.axes.apply([v[4], v[5], v[6]]) * accel_scale;
        out.push(ImuSample::new(t, gyro, accel));
    }
    if out.len() < 2 {
        return Err(bad("expected IMU samples, found fewer than two".into()));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn axis_maps_are_rotations_and_the_table_parses() {
        assert!(AxisMap::parse("+x,+y,-z").is_err(), "a mirror");
        assert!(AxisMap::parse("+x,+x,+z").is_err());
        let m = AxisMap::parse("-y,-z,+x").unwrap();
        assert_eq!(m.determinant(), 1);
        assert_eq!(m.apply([1.0, 2.0, 3.0]), Vector3::new(-2.0, -3.0, 1.0));
        assert_eq!(m.text(), "-y,-z,+x");
        for (model, _) in MODEL_AXES {
            assert!(AxisMap::for_model(model).is_some(), "{model}");
        }
    }
}
