//! UMI's replay buffer: `dataset.zarr.zip`, a zarr v2 store in a zip file as UMI's
//! `ReplayBuffer` writes it, with every chunk compressed by numcodecs' `zlib` codec (which a
//! stock zarr/numcodecs install decodes; zip entries are stored, as UMI stores them).
//!
//! Numbering: `robot{i}` is the session's i-th wrist in the order left, right (a one-wrist
//! session has only `robot0`); `camera{i}` is the i-th exported view (default: the wrists'
//! front lenses in the same order, then the head camera's lenses), so `camera0` is `robot0`'s
//! wrist camera as in UMI.
//!
//! ```text
//! data/robot{i}_eef_pos             f32 (T,3)    tool tip position in the scene frame (m)
//! data/robot{i}_eef_rot_axis_angle  f32 (T,3)    tool tip rotation vector (rad)
//! data/robot{i}_gripper_width       f32 (T,1)    opening: m (parallel jaw), rad (chopstick), 0 (bare hand)
//! data/robot{i}_demo_start_pose     f32 (T,6)    the episode's first tip pose (pos, rotvec) on every row
//! data/robot{i}_demo_end_pose       f32 (T,6)    the episode's last tip pose on every row
//! data/camera{i}_rgb                u8 (T,H,W,3) the view's frame nearest each row, RGB
//! data/timestamp                    f64 (T,)     the row's session time (s)
//! meta/episode_ends                 i64 (E,)     cumulative row count at each episode's end
//! ```

use std::io::Write as _;
use std::path::Path;

use flate2::Compression;
use flate2::write::ZlibEncoder;
use serde_json::json;
use zip::write::SimpleFileOptions;
use zip::{CompressionMethod, ZipWriter};

use kiwi_core::geometry::so3_log;
use kiwi_core::layout::ToolKind;

use crate::error::{BackendError, Result};
use crate::export::{
    ExportOptions, ExportReport, Rate, SessionExport, ViewStream, choose_rate, episode_grid,
    resolve_views, source_rates,
};

/// The store's file name.
pub const STORE_NAME: &str = "dataset.zarr.zip";
/// zlib level of the chunks: fast, and most of the gain.
const ZLIB_LEVEL: u32 = 1;

fn zip_err(path: &Path, e: &dyn std::fmt::Display) -> BackendError {
    BackendError::Export(format!(
        "{}: cannot write the zip store: {e}",
        path.display()
    ))
}

/// A zarr v2 store being written into a zip file.
struct ZarrZip<'a> {
    zip: ZipWriter<std::fs::File>,
    path: &'a Path,
}

impl ZarrZip<'_> {
    fn entry(&mut self, name: &str, bytes: &[u8]) -> Result<()> {
        let options = SimpleFileOptions::default()
            .compression_method(CompressionMethod::Stored)
            .large_file(bytes.len() as u64 >= u64::from(u32::MAX));
        self.zip
            .start_file(name, options)
            .map_err(|e| zip_err(self.path, &e))?;
        self.zip
            .write_all(bytes)
            .map_err(|e| zip_err(self.path, &e))
    }

    fn group(&mut self, name: &str) -> Result<()> {
        let key = if name.is_empty() {
            ".zgroup".to_string()
        } else {
            format!("{name}/.zgroup")
        };
        self.entry(&key, json!({"zarr_format": 2}).to_string().as_bytes())
    }

    /// `.zarray` of an array chunked along its first axis by `rows_per_chunk`.
    fn array_header(
        &mut self,
        name: &str,
        dtype: &str,
        shape: &[usize],
        rows_per_chunk: usize,
        attrs: Option<serde_json::Value>,
    ) -> Result<()> {
        let mut chunks = shape.to_vec();
        if let Some(c) = chunks.first_mut() {
            *c = rows_per_chunk.max(1);
        }
        let fill = if dtype.contains('f') {
            json!(0.0)
        } else {
            json!(0)
        };
        let header = json!({
            "zarr_format": 2,
            "shape": shape,
            "chunks": chunks,
            "dtype": dtype,
            "compressor": {"id": "zlib", "level": ZLIB_LEVEL},
            "fill_value": fill,
            "filters": null,
            "order": "C",
            "dimension_separator": "."
        });
        self.entry(&format!("{name}/.zarray"), header.to_string().as_bytes())?;
        if let Some(a) = attrs {
            self.entry(&format!("{name}/.zattrs"), a.to_string().as_bytes())?;
        }
        Ok(())
    }

    /// One chunk: `index` along the first axis, 0 along the others.
    fn chunk(&mut self, name: &str, index: usize, dims: usize, raw: &[u8]) -> Result<()> {
        let mut enc = ZlibEncoder::new(Vec::new(), Compression::new(ZLIB_LEVEL));
        enc.write_all(raw).map_err(|e| zip_err(self.path, &e))?;
        let bytes = enc.finish().map_err(|e| zip_err(self.path, &e))?;
        let key = std::iter::once(index.to_string())
            .chain(std::iter::repeat_n("0".to_string(), dims.saturating_sub(1)))
            .collect::<Vec<_>>()
            .join(".");
        self.entry(&format!("{name}/{key}"), &bytes)
    }

    /// A whole array in one chunk.
    fn array(
        &mut self,
        name: &str,
        dtype: &str,
        shape: &[usize],
        raw: &[u8],
        attrs: Option<serde_json::Value>,
    ) -> Result<()> {
        self.array_header(
            name,
            dtype,
            shape,
            shape.first().copied().unwrap_or(1),
            attrs,
        )?;
        if shape.first().copied().unwrap_or(0) > 0 {
            self.chunk(name, 0, shape.len(), raw)?;
        }
        Ok(())
    }
}

fn f32_bytes(v: &[f32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

/// Per robot, the rows of every array.
#[derive(Default)]
struct RobotArrays {
    pos: Vec<f32>,
    rot: Vec<f32>,
    gripper: Vec<f32>,
    start: Vec<f32>,
    end: Vec<f32>,
}

/// Write `dataset.zarr.zip` of `exp` into `dir`.
pub fn write(exp: &SessionExport, options: &ExportOptions, dir: &Path) -> Result<ExportReport> {
    let views = resolve_views(exp, options.views.as_deref())?;
    let path = dir.join(STORE_NAME);
    let file = std::fs::File::create(&path).map_err(|e| zip_err(&path, &e))?;
    let mut store = ZarrZip {
        zip: ZipWriter::new(file),
        path: &path,
    };
    store.group("")?;
    store.group("data")?;
    store.group("meta")?;
    let nw = exp.session.wrists.len();
    let mut robots: Vec<RobotArrays> = (0..nw).map(|_| RobotArrays::default()).collect();
    let mut timestamps: Vec<f64> = Vec::new();
    let mut episode_ends: Vec<i64> = Vec::new();
    let mut report = ExportReport::default();
    let mut rate_used: Option<Rate> = None;
    // Image arrays: chunks are written as episodes come; headers once the length is known.
    let mut image_shapes: Vec<Option<(usize, usize)>> = vec![None; views.len()];
    let mut row = 0usize;
    for ep in &exp.episodes {
        let streams = views
            .iter()
            .map(|v| ViewStream::open(ep, v))
            .collect::<Result<Vec<_>>>()?;
        let requested = rate_used.map(Rate::hz).or(options.fps);
        let rate = choose_rate(requested, &source_rates(ep, &streams), &ep.name)?;
        rate_used = Some(rate);
        let grid = episode_grid(ep, &streams, rate)?;
        let times = grid.times();
        for (w, wrist) in ep.wrists.iter().enumerate() {
            let mut last_opening = None;
            let mut poses = Vec::with_capacity(times.len());
            for &t in &times {
                let s = wrist.sample_row(&ep.name, t)?;
                let p = s.scene_from_tip.translation.vector;
                let r = so3_log(&s.scene_from_tip.rotation);
                let pose = [p.x, p.y, p.z, r.x, r.y, r.z].map(|v| v as f32);
                poses.push(pose);
                if s.opening.is_some() {
                    last_opening = s.opening;
                }
                let g = match wrist.tool {
                    ToolKind::BareHand => 0.0,
                    _ => last_opening.unwrap_or(0.0),
                };
                let rb = &mut robots[w];
                rb.pos.extend_from_slice(&pose[..3]);
                rb.rot.extend_from_slice(&pose[3..]);
                rb.gripper.push(g as f32);
            }
            if let (Some(first), Some(last)) = (poses.first(), poses.last()) {
                for _ in 0..poses.len() {
                    robots[w].start.extend_from_slice(first);
                    robots[w].end.extend_from_slice(last);
                }
            }
        }
        for (i, stream) in streams.iter().enumerate() {
            let (picks, worst) = stream.nearest_frames(&times);
            report.max_frame_offset_s = report.max_frame_offset_s.max(worst);
            let name = format!("data/camera{i}_rgb");
            let view = stream.view.key();
            super::video::for_each_pick(
                &stream.source,
                &picks,
                |m| super::export_err(format!("episode {}: view {view}: {m}", ep.name)),
                |k, frame| {
                    match image_shapes[i] {
                        Some(shape) if shape != (frame.width, frame.height) => {
                            return Err(super::export_err(format!(
                                "view {view}: frames of {}x{} px after frames of {}x{} px; \
                                 export episodes of one resolution together",
                                frame.width, frame.height, shape.0, shape.1
                            )));
                        }
                        _ => image_shapes[i] = Some((frame.width, frame.height)),
                    }
                    store.chunk(&name, row + k, 4, &frame.to_rgb())
                },
            )?;
        }
        row += times.len();
        timestamps.extend_from_slice(&times);
        episode_ends.push(row as i64);
        report.exported.push(ep.name.clone());
        tracing::info!(
            "export: episode {} into the UMI store: {} rows",
            ep.name,
            times.len()
        );
    }
    for (i, shape) in image_shapes.iter().enumerate() {
        let (w, h) = shape.unwrap_or((0, 0));
        store.array_header(
            &format!("data/camera{i}_rgb"),
            "|u1",
            &[row, h, w, 3],
            1,
            Some(json!({"view": format!("{}.{}", views[i].camera, views[i].lens)})),
        )?;
    }
    let tools: Vec<ToolKind> = exp.session.wrists.values().map(|w| w.tool).collect();
    for (i, (rb, side)) in robots.iter().zip(exp.session.wrists.keys()).enumerate() {
        let attrs = json!({"wrist": side.camera_name(), "frame": "scene_from_tip"});
        let unit = match tools[i] {
            ToolKind::Chopstick => "rad",
            ToolKind::ParallelJaw => "m",
            ToolKind::BareHand => "none",
        };
        store.array(
            &format!("data/robot{i}_eef_pos"),
            "<f4",
            &[row, 3],
            &f32_bytes(&rb.pos),
            Some(attrs.clone()),
        )?;
        store.array(
            &format!("data/robot{i}_eef_rot_axis_angle"),
            "<f4",
            &[row, 3],
            &f32_bytes(&rb.rot),
            Some(attrs.clone()),
        )?;
        store.array(
            &format!("data/robot{i}_gripper_width"),
            "<f4",
            &[row, 1],
            &f32_bytes(&rb.gripper),
            Some(json!({"wrist": side.camera_name(), "unit": unit})),
        )?;
        store.array(
            &format!("data/robot{i}_demo_start_pose"),
            "<f4",
            &[row, 6],
            &f32_bytes(&rb.start),
            Some(attrs.clone()),
        )?;
        store.array(
            &format!("data/robot{i}_demo_end_pose"),
            "<f4",
            &[row, 6],
            &f32_bytes(&rb.end),
            Some(attrs),
        )?;
    }
    let ts: Vec<u8> = timestamps.iter().flat_map(|x| x.to_le_bytes()).collect();
    store.array("data/timestamp", "<f8", &[row], &ts, None)?;
    let ends: Vec<u8> = episode_ends.iter().flat_map(|x| x.to_le_bytes()).collect();
    store.array(
        "meta/episode_ends",
        "<i8",
        &[episode_ends.len()],
        &ends,
        None,
    )?;
    store.zip.finish().map_err(|e| zip_err(&path, &e))?;
    report.frames = row;
    report.fps = rate_used.map(Rate::hz);
    Ok(report)
}
