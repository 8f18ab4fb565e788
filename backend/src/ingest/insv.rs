//! The metadata trailer Insta360 cameras append to their recordings (`.insv`, and the GO 3's
//! files): the camera's description (a protobuf record), its IMU samples, exposure times and
//! lens calibration strings. Written from the public descriptions of the layout (see
//! docs/ingest.md for the sources and for what was checked on which files); no vendor
//! specification exists.
//!
//! Layout, read from the end of the file (integers little-endian):
//!
//! ```text
//! … records …  [u8 format, u8 id, u32 size] ← header of the record nearest the footer, at EOF-78
//! [32 bytes reserved][u32 trailer size][u32 version][32 ASCII bytes of TRAILER_MAGIC]  ← EOF
//! ```
//!
//! Every record's payload is followed by its 6-byte header; `trailer size` counts from the first
//! record's payload to the end of the file. Newer cameras (X4, X5) make the record nearest the
//! footer an index (id 0) of 10-byte entries `u8 id, u8 format, u32 size, u32 offset from the
//! trailer's start`, and pad between records; older ones write the records back to back, to be
//! walked backwards from the footer.

use std::collections::BTreeMap;
use std::io::{Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};

use crate::error::{BackendError, Result};

/// The last 32 bytes of a file with an Insta360 trailer.
pub const TRAILER_MAGIC: &[u8; 32] = b"8db42d694ccc418790edff439fe026bf";
/// The footer: 32 reserved bytes, trailer size, version, magic.
pub const FOOTER_LEN: u64 = 72;
/// A record header: format, id, payload size.
pub const RECORD_HEADER_LEN: u64 = 6;
/// An index entry: id, format, size, offset.
pub const INDEX_ENTRY_LEN: usize = 10;
/// Trailers larger than this are not read (the largest records, thumbnails and IMU logs of long
/// recordings, stay well below).
const MAX_TRAILER_BYTES: u64 = 1 << 30;
/// Records larger than this are not read into memory.
const MAX_RECORD_BYTES: u64 = 512 << 20;

/// Record ids (the second header byte).
pub mod record_id {
    /// The index of an indexed trailer.
    pub const INDEX: u8 = 0;
    /// The camera's description (protobuf).
    pub const METADATA: u8 = 1;
    /// IMU samples.
    pub const GYRO: u8 = 3;
    /// Exposure time per captured frame.
    pub const EXPOSURE: u8 = 4;
}

/// Record formats (the first header byte).
pub mod record_format {
    /// Packed binary.
    pub const BINARY: u8 = 0;
    /// Protobuf.
    pub const PROTOBUF: u8 = 1;
}

/// A raw IMU sample: `u64` time stamp, accelerometer then gyroscope as offset-binary `u16`.
pub const RAW_IMU_SAMPLE_LEN: usize = 8 + 6 * 2;
/// A float IMU sample: `u64` time stamp (ms), accelerometer (g) then gyroscope (rad/s) as `f64`.
pub const FLOAT_IMU_SAMPLE_LEN: usize = 8 + 6 * 8;
/// An exposure entry: `u64` time stamp, `f64` exposure time (s).
pub const EXPOSURE_ENTRY_LEN: usize = 16;
/// The zero of the raw samples' offset-binary encoding, and the count that full scale maps to.
const RAW_ZERO: f64 = 32768.0;

/// Protobuf field numbers of the metadata record used here.
mod field {
    pub const SERIAL: u32 = 1;
    pub const CAMERA_TYPE: u32 = 2;
    pub const FIRMWARE: u32 = 3;
    pub const OFFSET: u32 = 5;
    pub const DIMENSION: u32 = 19;
    pub const FRAME_RATE: u32 = 20;
    pub const FIRST_FRAME_TIMESTAMP: u32 = 24;
    pub const ROLLING_SHUTTER_MS: u32 = 25;
    pub const FILE_GROUP: u32 = 26;
    pub const GYRO_TIMESTAMP_MS: u32 = 28;
    pub const HAS_GYRO_TIMESTAMP: u32 = 29;
    pub const OFFSET_V2: u32 = 53;
    pub const OFFSET_V3: u32 = 54;
    pub const IS_RAW_GYRO: u32 = 62;
    pub const GYRO_CONFIG: u32 = 65;
    pub const OFFSET_V6: u32 = 111;
}

/// How the trailer's records are found.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TrailerLayout {
    /// An index record lists every record (X4, X5).
    Indexed,
    /// Records back to back, walked backwards from the footer.
    Contiguous,
}

/// Where one record lies in the file.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RecordRef {
    /// Record id ([`record_id`]).
    pub id: u8,
    /// Record format ([`record_format`]).
    pub format: u8,
    /// File offset of the payload.
    pub offset: u64,
    /// Payload size.
    pub size: u64,
}

/// The records of a trailer.
#[derive(Debug, Clone)]
pub struct Trailer {
    /// The footer's version word.
    pub version: u32,
    /// File offset of the trailer's first byte.
    pub start: u64,
    /// How the records were found.
    pub layout: TrailerLayout,
    /// Every record, by position.
    pub records: Vec<RecordRef>,
}

impl Trailer {
    /// The first record with this id.
    pub fn record(&self, id: u8) -> Option<&RecordRef> {
        self.records.iter().find(|r| r.id == id)
    }
}

/// A recording split by the camera: which part of which group this file is.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct FileGroup {
    /// Media type code.
    pub kind: u64,
    /// This file's index in the group.
    pub index: u64,
    /// The group's identifier.
    pub identify: String,
    /// Files in the group.
    pub total: u64,
}

/// What the metadata record says (fields the file leaves out are `None` or empty).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Insta360Metadata {
    /// Serial number.
    pub serial: String,
    /// Camera model (`Insta360 X5`).
    pub camera_type: String,
    /// Firmware (`v1.10.7_build2`).
    pub firmware: String,
    /// Per-lens coded image size.
    pub dimension: Option<(u32, u32)>,
    /// Frame rate.
    pub frame_rate: Option<f64>,
    /// Device time stamp of the first video frame (the IMU's clock and unit).
    pub first_frame_timestamp: Option<i64>,
    /// Readout time of one frame (ms).
    pub rolling_shutter_ms: Option<f64>,
    /// Gyro-to-video offset (ms), applied when `has_gyro_timestamp`.
    pub gyro_timestamp_ms: Option<f64>,
    /// Whether the camera measured the gyro offset.
    pub has_gyro_timestamp: bool,
    /// Whether the IMU record holds raw `u16` samples (else `f64` in g and rad/s).
    pub is_raw_gyro: bool,
    /// Accelerometer full scale (g) of raw samples.
    pub accel_range_g: Option<f64>,
    /// Gyroscope full scale (deg/s) of raw samples.
    pub gyro_range_dps: Option<f64>,
    /// Lens calibration strings by name (`offset`, `offset_v2`, `offset_v3`, `offset_v6`).
    pub lens_offsets: BTreeMap<String, String>,
    /// The group a split recording belongs to.
    pub file_group: Option<FileGroup>,
}

/// One IMU sample in SI units, still in the device's axes and on its clock.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DeviceImuSample {
    /// Device time stamp (in [`Insta360Telemetry::clock_unit_s`]).
    pub timestamp: u64,
    /// Angular rate (rad/s), device axes.
    pub gyro: [f64; 3],
    /// Specific force (m/s²), device axes.
    pub accel: [f64; 3],
}

/// One exposure entry.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ExposureEntry {
    /// Device time stamp (in [`Insta360Telemetry::clock_unit_s`]).
    pub timestamp: u64,
    /// Exposure time (s).
    pub exposure_s: f64,
}

/// Everything read from a trailer.
#[derive(Debug, Clone)]
pub struct Insta360Telemetry {
    /// The file.
    pub file: PathBuf,
    /// The records and how they were found.
    pub trailer: Trailer,
    /// The camera's description.
    pub metadata: Insta360Metadata,
    /// IMU samples (`None`: the file has no gyro record).
    pub imu: Option<Vec<DeviceImuSample>>,
    /// Exposure entries (empty when the file has none).
    pub exposures: Vec<ExposureEntry>,
    /// Seconds per device time-stamp tick: 1 µs for raw samples, 1 ms for float samples.
    pub clock_unit_s: f64,
}

/// Standard gravity (m/s² per g).
pub const STANDARD_GRAVITY: f64 = 9.806_65;

fn bad(path: &Path, message: &str) -> BackendError {
    BackendError::Input {
        path: path.to_path_buf(),
        message: format!("Insta360 metadata trailer: {message}"),
    }
}

fn io(path: &Path, e: &std::io::Error) -> BackendError {
    BackendError::Input {
        path: path.to_path_buf(),
        message: format!("cannot read the file: {e}"),
    }
}

fn u32_le(b: &[u8]) -> u32 {
    u32::from_le_bytes([b[0], b[1], b[2], b[3]])
}

fn u64_le(b: &[u8]) -> u64 {
    let mut a = [0u8; 8];
    a.copy_from_slice(&b[..8]);
    u64::from_le_bytes(a)
}

fn read_at(file: &mut std::fs::File, path: &Path, offset: u64, len: u64) -> Result<Vec<u8>> {
    file.seek(SeekFrom::Start(offset))
        .map_err(|e| io(path, &e))?;
    let mut buf = vec![0u8; len as usize];
    file.read_exact(&mut buf).map_err(|e| io(path, &e))?;
    Ok(buf)
}

/// Whether a file ends with the trailer magic.
pub fn has_trailer(path: &Path) -> Result<bool> {
    let mut file = std::fs::File::open(path).map_err(|e| io(path, &e))?;
    let size = file.metadata().map_err(|e| io(path, &e))?.len();
    if size < FOOTER_LEN {
        return Ok(false);
    }
    let tail = read_at(&mut file, path, size - TRAILER_MAGIC.len() as u64, 32)?;
    Ok(tail == TRAILER_MAGIC)
}

/// Find the trailer's records (`None` when the file has no trailer).
pub fn read_trailer(path: &Path) -> Result<Option<Trailer>> {
    let mut file = std::fs::File::open(path).map_err(|e| io(path, &e))?;
    let size = file.metadata().map_err(|e| io(path, &e))?.len();
    if size < FOOTER_LEN + RECORD_HEADER_LEN {
        return Ok(None);
    }
    let footer = read_at(&mut file, path, size - FOOTER_LEN, FOOTER_LEN)?;
    if &footer[40..] != TRAILER_MAGIC {
        return Ok(None);
    }
    let trailer_size = u64::from(u32_le(&footer[32..36]));
    let version = u32_le(&footer[36..40]);
    if trailer_size < FOOTER_LEN + RECORD_HEADER_LEN
        || trailer_size > size
        || trailer_size > MAX_TRAILER_BYTES
    {
        return Err(bad(
            path,
            &format!(
                "the footer gives a trailer of {trailer_size} bytes in a {size}-byte file; the \
                 file is damaged or truncated"
            ),
        ));
    }
    let start = size - trailer_size;
    let first_header_at = size - FOOTER_LEN - RECORD_HEADER_LEN;
    let header = read_at(&mut file, path, first_header_at, RECORD_HEADER_LEN)?;
    let (id, len) = (header[1], u64::from(u32_le(&header[2..6])));
    if id == record_id::INDEX && len > 0 && len % INDEX_ENTRY_LEN as u64 == 0 {
        if len > first_header_at - start {
            return Err(bad(
                path,
                &format!("the index record ({len} bytes) runs past the trailer"),
            ));
        }
        let index = read_at(&mut file, path, first_header_at - len, len)?;
        let mut records = Vec::new();
        for (k, e) in index.chunks_exact(INDEX_ENTRY_LEN).enumerate() {
            let (rid, rformat) = (e[0], e[1]);
            let (rsize, roffset) = (u64::from(u32_le(&e[2..6])), u64::from(u32_le(&e[6..10])));
            if rsize == 0 {
                continue;
            }
            if roffset + rsize > trailer_size {
                return Err(bad(
                    path,
                    &format!(
                        "index entry {k} (record {rid}) spans bytes {roffset}..{} of a \
                         {trailer_size}-byte trailer",
                        roffset + rsize
                    ),
                ));
            }
            records.push(RecordRef {
                id: rid,
                format: rformat,
                offset: start + roffset,
                size: rsize,
            });
        }
        return Ok(Some(Trailer {
            version,
            start,
            layout: TrailerLayout::Indexed,
            records,
        }));
    }
    // Contiguous: walk the headers backwards until the trailer's start.
    let mut records = Vec::new();
    let mut header_at = first_header_at;
    loop {
        let h = read_at(&mut file, path, header_at, RECORD_HEADER_LEN)?;
        let (rformat, rid, rsize) = (h[0], h[1], u64::from(u32_le(&h[2..6])));
        if rsize == 0 || rsize > header_at - start {
            return Err(bad(
                path,
                &format!(
                    "record {rid} at byte {header_at} claims {rsize} bytes, {} are left before \
                     the trailer's start; the trailer is damaged",
                    header_at - start
                ),
            ));
        }
        let offset = header_at - rsize;
        records.push(RecordRef {
            id: rid,
            format: rformat,
            offset,
            size: rsize,
        });
        if offset == start {
            break;
        }
        if offset < start + RECORD_HEADER_LEN {
            return Err(bad(
                path,
                &format!(
                    "the record walk ends {} bytes after the trailer's start, not on it; the \
                     trailer is damaged",
                    offset - start
                ),
            ));
        }
        header_at = offset - RECORD_HEADER_LEN;
    }
    records.reverse();
    Ok(Some(Trailer {
        version,
        start,
        layout: TrailerLayout::Contiguous,
        records,
    }))
}

/// A protobuf field value (wire types 0, 1, 2, 5).
#[derive(Debug, Clone, Copy)]
enum Wire<'a> {
    Varint(u64),
    Fixed64(u64),
    Bytes(&'a [u8]),
    Fixed32(u32),
}

fn varint(buf: &[u8], pos: &mut usize) -> Option<u64> {
    let mut v = 0u64;
    for shift in (0..64).step_by(7) {
        let b = *buf.get(*pos)?;
        *pos += 1;
        v |= u64::from(b & 0x7f) << shift;
        if b & 0x80 == 0 {
            return Some(v);
        }
    }
    None
}

/// The fields of one protobuf message, in order (`None`: not a valid message).
fn protobuf_fields(buf: &[u8]) -> Option<Vec<(u32, Wire<'_>)>> {
    let mut pos = 0;
    let mut out = Vec::new();
    while pos < buf.len() {
        let key = varint(buf, &mut pos)?;
        let number = u32::try_from(key >> 3).ok()?;
        let value = match key & 7 {
            0 => Wire::Varint(varint(buf, &mut pos)?),
            1 => {
                let b = buf.get(pos..pos + 8)?;
                pos += 8;
                Wire::Fixed64(u64_le(b))
            }
            2 => {
                let len = usize::try_from(varint(buf, &mut pos)?).ok()?;
                let b = buf.get(pos..pos.checked_add(len)?)?;
                pos += len;
                Wire::Bytes(b)
            }
            5 => {
                let b = buf.get(pos..pos + 4)?;
                pos += 4;
                Wire::Fixed32(u32_le(b))
            }
            _ => return None,
        };
        out.push((number, value));
    }
    Some(out)
}

fn as_f64(w: Wire<'_>) -> Option<f64> {
    match w {
        Wire::Fixed64(v) => Some(f64::from_bits(v)),
        Wire::Fixed32(v) => Some(f64::from(f32::from_bits(v))),
        Wire::Varint(v) => Some(v as f64),
        Wire::Bytes(_) => None,
    }
}

fn as_text(w: Wire<'_>) -> Option<String> {
    match w {
        Wire::Bytes(b) => Some(
            String::from_utf8_lossy(b)
                .trim_end_matches('\0')
                .to_string(),
        ),
        _ => None,
    }
}

fn as_u64(w: Wire<'_>) -> Option<u64> {
    match w {
        Wire::Varint(v) => Some(v),
        _ => None,
    }
}

/// Decode the metadata record.
pub fn parse_metadata(path: &Path, buf: &[u8]) -> Result<Insta360Metadata> {
    let fields = protobuf_fields(buf)
        .ok_or_else(|| bad(path, "the metadata record is not a valid protobuf message"))?;
    let mut m = Insta360Metadata::default();
    for (number, value) in fields {
        match number {
            field::SERIAL => m.serial = as_text(value).unwrap_or_default(),
            field::CAMERA_TYPE => m.camera_type = as_text(value).unwrap_or_default(),
            field::FIRMWARE => m.firmware = as_text(value).unwrap_or_default(),
            field::OFFSET | field::OFFSET_V2 | field::OFFSET_V3 | field::OFFSET_V6 => {
                let name = match number {
                    field::OFFSET => "offset",
                    field::OFFSET_V2 => "offset_v2",
                    field::OFFSET_V3 => "offset_v3",
                    _ => "offset_v6",
                };
                if let Some(t) = as_text(value).filter(|t| !t.is_empty()) {
                    m.lens_offsets.insert(name.into(), t);
                }
            }
            field::DIMENSION => {
                if let Wire::Bytes(b) = value {
                    let sub = protobuf_fields(b).unwrap_or_default();
                    let get = |n| {
                        sub.iter()
                            .find(|(k, _)| *k == n)
                            .and_then(|(_, v)| as_u64(*v))
                    };
                    if let (Some(w), Some(h)) = (get(1), get(2)) {
                        m.dimension = Some((w as u32, h as u32));
                    }
                }
            }
            field::FRAME_RATE => m.frame_rate = as_f64(value),
            field::FIRST_FRAME_TIMESTAMP => {
                m.first_frame_timestamp = as_u64(value).map(|v| v as i64);
            }
            field::ROLLING_SHUTTER_MS => m.rolling_shutter_ms = as_f64(value),
            field::GYRO_TIMESTAMP_MS => m.gyro_timestamp_ms = as_f64(value),
            field::HAS_GYRO_TIMESTAMP => {
                m.has_gyro_timestamp = as_u64(value).is_some_and(|v| v != 0);
            }
            field::IS_RAW_GYRO => m.is_raw_gyro = as_u64(value).is_some_and(|v| v != 0),
            field::GYRO_CONFIG => {
                if let Wire::Bytes(b) = value {
                    for (k, v) in protobuf_fields(b).unwrap_or_default() {
                        match k {
                            1 => m.accel_range_g = as_f64(v),
                            2 => m.gyro_range_dps = as_f64(v),
                            _ => {}
                        }
                    }
                }
            }
            field::FILE_GROUP => {
                if let Wire::Bytes(b) = value {
                    let mut g = FileGroup::default();
                    for (k, v) in protobuf_fields(b).unwrap_or_default() {
                        match k {
                            1 => g.kind = as_u64(v).unwrap_or(0),
                            2 => g.index = as_u64(v).unwrap_or(0),
                            3 => g.identify = as_text(v).unwrap_or_default(),
                            4 => g.total = as_u64(v).unwrap_or(0),
                            _ => {}
                        }
                    }
                    m.file_group = Some(g);
                }
            }
            _ => {}
        }
    }
    Ok(m)
}

/// Decode the IMU record: SI units, device axes, device time stamps.
pub fn parse_imu(path: &Path, meta: &Insta360Metadata, buf: &[u8]) -> Result<Vec<DeviceImuSample>> {
    let item = if meta.is_raw_gyro {
        RAW_IMU_SAMPLE_LEN
    } else {
        FLOAT_IMU_SAMPLE_LEN
    };
    if !buf.len().is_multiple_of(item) {
        return Err(bad(
            path,
            &format!(
                "the gyro record holds {} bytes, not a whole number of {item}-byte {} samples",
                buf.len(),
                if meta.is_raw_gyro { "raw" } else { "float" }
            ),
        ));
    }
    let deg = std::f64::consts::PI / 180.0;
    let (accel_scale, gyro_scale) = if meta.is_raw_gyro {
        let (Some(acc), Some(gyr)) = (meta.accel_range_g, meta.gyro_range_dps) else {
            return Err(bad(
                path,
                "raw IMU samples but no accelerometer and gyroscope full-scale ranges in the \
                 metadata (field 65); cannot convert them to SI units",
            ));
        };
        (acc / RAW_ZERO * STANDARD_GRAVITY, gyr / RAW_ZERO * deg)
    } else {
        (STANDARD_GRAVITY, 1.0)
    };
    let mut out = Vec::with_capacity(buf.len() / item);
    for (k, s) in buf.chunks_exact(item).enumerate() {
        let timestamp = u64_le(s);
        let (accel, gyro) = if meta.is_raw_gyro {
            let v =
                |i: usize| f64::from(u16::from_le_bytes([s[8 + 2 * i], s[9 + 2 * i]])) - RAW_ZERO;
            (
                [v(0) * accel_scale, v(1) * accel_scale, v(2) * accel_scale],
                [v(3) * gyro_scale, v(4) * gyro_scale, v(5) * gyro_scale],
            )
        } else {
            let v = |i: usize| f64::from_bits(u64_le(&s[8 + 8 * i..]));
            (
                [v(0) * accel_scale, v(1) * accel_scale, v(2) * accel_scale],
                [v(3) * gyro_scale, v(4) * gyro_scale, v(5) * gyro_scale],
            )
        };
        if !(accel.iter().chain(&gyro).all(|x| x.is_finite())) {
            return Err(bad(path, &format!("IMU sample {k} is not finite")));
        }
        if let Some(prev) = out.last().map(|p: &DeviceImuSample| p.timestamp)
            && timestamp <= prev
        {
            return Err(bad(
                path,
                &format!(
                    "IMU sample {k}: time stamp {timestamp} is not after the previous {prev}; the \
                     gyro record is damaged"
                ),
            ));
        }
        out.push(DeviceImuSample {
            timestamp,
            gyro,
            accel,
        });
    }
    Ok(out)
}

/// Decode an exposure record.
pub fn parse_exposures(path: &Path, buf: &[u8]) -> Result<Vec<ExposureEntry>> {
    if !buf.len().is_multiple_of(EXPOSURE_ENTRY_LEN) {
        return Err(bad(
            path,
            &format!(
                "the exposure record holds {} bytes, not a whole number of 16-byte entries",
                buf.len()
            ),
        ));
    }
    Ok(buf
        .chunks_exact(EXPOSURE_ENTRY_LEN)
        .map(|e| ExposureEntry {
            timestamp: u64_le(e),
            exposure_s: f64::from_bits(u64_le(&e[8..])),
        })
        .collect())
}

/// Read a file's trailer and decode the records KIWI uses.
pub fn read_telemetry(path: &Path) -> Result<Insta360Telemetry> {
    let trailer = read_trailer(path)?.ok_or_else(|| {
        bad(
            path,
            "no trailer (the file does not end with the Insta360 magic)",
        )
    })?;
    let mut file = std::fs::File::open(path).map_err(|e| io(path, &e))?;
    let mut record = |id: u8| -> Result<Option<Vec<u8>>> {
        match trailer.record(id) {
            None => Ok(None),
            Some(r) if r.size > MAX_RECORD_BYTES => Err(bad(
                path,
                &format!(
                    "record {id} claims {} bytes; the trailer is damaged",
                    r.size
                ),
            )),
            Some(r) => read_at(&mut file, path, r.offset, r.size).map(Some),
        }
    };
    let metadata = match record(record_id::METADATA)? {
        Some(b) => parse_metadata(path, &b)?,
        None => {
            return Err(bad(
                path,
                "no metadata record (id 1): not a recording KIWI can read",
            ));
        }
    };
    let imu = match record(record_id::GYRO)? {
        Some(b) => Some(parse_imu(path, &metadata, &b)?),
        None => None,
    };
    let exposures = match record(record_id::EXPOSURE)? {
        Some(b) => parse_exposures(path, &b)?,
        None => Vec::new(),
    };
    let clock_unit_s = if metadata.is_raw_gyro { 1e-6 } else { 1e-3 };
    Ok(Insta360Telemetry {
        file: path.to_path_buf(),
        trailer,
        metadata,
        imu,
        exposures,
        clock_unit_s,
    })
}

impl Insta360Telemetry {
    /// Seconds after the first video frame of a device time stamp.
    pub fn video_time(&self, timestamp: u64) -> Option<f64> {
        let fft = self.metadata.first_frame_timestamp?;
        Some((timestamp as i64 - fft) as f64 * self.clock_unit_s)
    }

    /// The gyro-to-video offset the camera states (s; 0 when it measured none): an IMU sample's
    /// video time is its [`Insta360Telemetry::video_time`] minus this.
    pub fn gyro_offset_s(&self) -> f64 {
        match (
            self.metadata.has_gyro_timestamp,
            self.metadata.gyro_timestamp_ms,
        ) {
            (true, Some(ms)) => ms * 1e-3,
            _ => 0.0,
        }
    }
}
