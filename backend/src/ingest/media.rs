//! What ingest asks of the `ffprobe` and `ffmpeg` programs: a file's tracks, a video track's
//! frame times (from the container, without decoding), its frames scaled and decoded to packed
//! RGB, and its audio decoded to mono 16-bit samples.

use std::io::Read;
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdout, Command, Stdio};

use serde::Deserialize;

use crate::error::{BackendError, Result};

/// The probing program (found on `PATH`; `make deps` installs it with ffmpeg).
pub const FFPROBE: &str = "ffprobe";
/// The decoding program.
pub const FFMPEG: &str = kiwi_core::video::FFMPEG;

fn err(path: &Path, message: String) -> BackendError {
    BackendError::Input {
        path: path.to_path_buf(),
        message,
    }
}

fn run_json<T: for<'de> Deserialize<'de>>(path: &Path, args: &[&str]) -> Result<T> {
    let out = Command::new(FFPROBE)
        .args(["-v", "error", "-of", "json"])
        .args(args)
        .arg(path)
        .stdin(Stdio::null())
        .output()
        .map_err(|e| {
            err(
                path,
                format!("cannot run ffprobe ({e}); install ffmpeg (`make deps`)"),
            )
        })?;
    if !out.status.success() {
        return Err(err(
            path,
            format!(
                "ffprobe cannot read the file ({}): {}",
                out.status,
                String::from_utf8_lossy(&out.stderr).trim()
            ),
        ));
    }
    serde_json::from_slice(&out.stdout)
        .map_err(|e| err(path, format!("unexpected ffprobe output: {e}")))
}

#[derive(Debug, Deserialize)]
struct ProbeStreams {
    #[serde(default)]
    streams: Vec<ProbeStream>,
}

#[derive(Debug, Deserialize)]
struct ProbeStream {
    index: usize,
    #[serde(default)]
    codec_type: String,
    #[serde(default)]
    codec_name: String,
    #[serde(default)]
    width: Option<u32>,
    #[serde(default)]
    height: Option<u32>,
    #[serde(default)]
    r_frame_rate: String,
    #[serde(default)]
    time_base: String,
    #[serde(default)]
    start_time: Option<String>,
    #[serde(default)]
    sample_rate: Option<String>,
    #[serde(default)]
    channels: Option<u32>,
    #[serde(default)]
    disposition: Option<serde_json::Value>,
}

/// A video track.
#[derive(Debug, Clone, PartialEq)]
pub struct VideoTrack {
    /// Stream index in the file.
    pub index: usize,
    /// Codec name.
    pub codec: String,
    /// Coded width (px).
    pub width: u32,
    /// Coded height (px).
    pub height: u32,
    /// Nominal frame rate as ffmpeg states it (`120000/1001`).
    pub rate: String,
    /// Nominal frame rate (Hz).
    pub fps: f64,
    /// `(num, den)` of the track's time base (s per tick).
    pub time_base: (i64, i64),
}

/// An audio track.
#[derive(Debug, Clone, PartialEq)]
pub struct AudioTrack {
    /// Stream index in the file.
    pub index: usize,
    /// Sample rate (Hz).
    pub rate_hz: u32,
    /// Channels.
    pub channels: u32,
    /// Start time (s) on the container's clock.
    pub start_s: f64,
}

/// The tracks of a file.
#[derive(Debug, Clone)]
pub struct MediaFile {
    /// The file.
    pub path: PathBuf,
    /// Lens video tracks in file order (cover art and thumbnails left out).
    pub video: Vec<VideoTrack>,
    /// Audio tracks in file order.
    pub audio: Vec<AudioTrack>,
}

fn rational(text: &str) -> Option<(i64, i64)> {
    let (n, d) = text.split_once('/')?;
    let (n, d) = (n.trim().parse().ok()?, d.trim().parse().ok()?);
    (d != 0).then_some((n, d))
}

/// List a file's tracks.
pub fn probe(path: &Path) -> Result<MediaFile> {
    let p: ProbeStreams = run_json(path, &["-show_streams"])?;
    let mut video = Vec::new();
    let mut audio = Vec::new();
    for s in p.streams {
        match s.codec_type.as_str() {
            "video" => {
                let attached = s
                    .disposition
                    .as_ref()
                    .and_then(|d| d.get("attached_pic"))
                    .and_then(serde_json::Value::as_i64)
                    == Some(1);
                let (Some(width), Some(height)) = (s.width, s.height) else {
                    continue;
                };
                let Some((rn, rd)) = rational(&s.r_frame_rate).filter(|(n, _)| *n > 0) else {
                    continue;
                };
                let Some(time_base) = rational(&s.time_base) else {
                    continue;
                };
                if attached {
                    continue;
                }
                video.push(VideoTrack {
                    index: s.index,
                    codec: s.codec_name,
                    width,
                    height,
                    rate: s.r_frame_rate.clone(),
                    fps: rn as f64 / rd as f64,
                    time_base,
                });
            }
            "audio" => {
                let rate_hz = s
                    .sample_rate
                    .as_deref()
                    .and_then(|r| r.parse().ok())
                    .unwrap_or(0);
                if rate_hz == 0 {
                    continue;
                }
                audio.push(AudioTrack {
                    index: s.index,
                    rate_hz,
                    channels: s.channels.unwrap_or(1),
                    start_s: s
                        .start_time
                        .as_deref()
                        .and_then(|t| t.parse().ok())
                        .unwrap_or(0.0),
                });
            }
            _ => {}
        }
    }
    Ok(MediaFile {
        path: path.to_path_buf(),
        video,
        audio,
    })
}

#[derive(Debug, Deserialize)]
struct ProbePackets {
    #[serde(default)]
    packets: Vec<ProbePacket>,
}

#[derive(Debug, Deserialize)]
struct ProbePacket {
    #[serde(default)]
    pts: Option<i64>,
    #[serde(default)]
    flags: String,
}

/// The presentation times (s, container clock) of a video track's frames, in display order,
/// from the container's packets (nothing is decoded). Packets the container marks as discarded
/// (before an edit list's start) are left out, as the decoder leaves them out.
pub fn frame_times(path: &Path, track: &VideoTrack) -> Result<Vec<f64>> {
    let p: ProbePackets = run_json(
        path,
        &[
            "-select_streams",
            &track.index.to_string(),
            "-show_entries",
            "packet=pts,flags",
        ],
    )?;
    let mut pts: Vec<i64> = Vec::with_capacity(p.packets.len());
    for (k, pk) in p.packets.iter().enumerate() {
        if pk.flags.contains('D') {
            continue;
        }
        let Some(v) = pk.pts else {
            return Err(err(
                path,
                format!(
                    "video track {}: packet {k} has no presentation time; the container is damaged",
                    track.index
                ),
            ));
        };
        pts.push(v);
    }
    pts.sort_unstable();
    let (n, d) = track.time_base;
    Ok(pts
        .iter()
        .map(|&v| v as f64 * n as f64 / d as f64)
        .collect())
}

/// A running decoder that yields one track's frames as packed RGB.
pub struct FrameReader {
    path: PathBuf,
    child: Child,
    stdout: ChildStdout,
    stderr: Option<std::thread::JoinHandle<String>>,
    frame_len: usize,
    frames: usize,
}

/// Start decoding video track `track` of `path`, scaled to `width × height` (area averaging),
/// every frame passed through (none dropped or repeated).
pub fn decode_video(path: &Path, track: usize, width: u32, height: u32) -> Result<FrameReader> {
    let mut child = Command::new(FFMPEG)
        .args(["-nostdin", "-hide_banner", "-loglevel", "error", "-i"])
        .arg(path)
        .args(["-map", &format!("0:{track}"), "-an", "-sn", "-dn"])
        .args(["-fps_mode", "passthrough"])
        .args(["-vf", &format!("scale={width}:{height}:flags=area")])
        .args(["-f", "rawvideo", "-pix_fmt", "rgb24", "-"])
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .map_err(|e| {
            err(
                path,
                format!("cannot run ffmpeg ({e}); install it (`make deps`)"),
            )
        })?;
    let stdout = child
        .stdout
        .take()
        .ok_or_else(|| err(path, "ffmpeg gave no output pipe".into()))?;
    let stderr = child.stderr.take().map(|mut s| {
        std::thread::spawn(move || {
            let mut text = String::new();
            let _ = s.read_to_string(&mut text);
            text
        })
    });
    Ok(FrameReader {
        path: path.to_path_buf(),
        child,
        stdout,
        stderr,
        frame_len: width as usize * height as usize * 3,
        frames: 0,
    })
}

impl FrameReader {
    /// The next frame (`None` at the end of the track).
    pub fn next_frame(&mut self) -> Result<Option<Vec<u8>>> {
        let mut buf = vec![0u8; self.frame_len];
        let mut filled = 0;
        while filled < buf.len() {
            match self.stdout.read(&mut buf[filled..]) {
                Ok(0) => break,
                Ok(n) => filled += n,
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(e) => return Err(err(&self.path, format!("reading decoded frames: {e}"))),
            }
        }
        if filled == 0 {
            return Ok(None);
        }
        if filled < buf.len() {
            return Err(err(
                &self.path,
                format!(
                    "frame {} ended after {filled} of {} bytes",
                    self.frames,
                    buf.len()
                ),
            ));
        }
        self.frames += 1;
        Ok(Some(buf))
    }

    /// Wait for the decoder and report its failure, if any; returns the frames read.
    pub fn finish(mut self) -> Result<usize> {
        let status = self
            .child
            .wait()
            .map_err(|e| err(&self.path, format!("waiting for ffmpeg: {e}")))?;
        let log = self
            .stderr
            .take()
            .and_then(|h| h.join().ok())
            .unwrap_or_default();
        if !status.success() {
            return Err(err(
                &self.path,
                format!("ffmpeg failed decoding ({status}): {}", log.trim()),
            ));
        }
        Ok(self.frames)
    }
}

impl Drop for FrameReader {
    fn drop(&mut self) {
        // Dropped before the end (an error downstream): stop the decoder.
        if let Ok(None) = self.child.try_wait() {
            let _ = self.child.kill();
            let _ = self.child.wait();
        }
    }
}

/// Decode audio track `track` of `path` to mono 16-bit samples at its own rate (channels are
/// averaged by ffmpeg's downmix).
pub fn decode_audio(path: &Path, track: usize) -> Result<Vec<i16>> {
    let out = Command::new(FFMPEG)
        .args(["-nostdin", "-hide_banner", "-loglevel", "error", "-i"])
        .arg(path)
        .args(["-map", &format!("0:{track}"), "-vn", "-sn", "-dn"])
        .args(["-ac", "1", "-f", "s16le", "-acodec", "pcm_s16le", "-"])
        .stdin(Stdio::null())
        .output()
        .map_err(|e| {
            err(
                path,
                format!("cannot run ffmpeg ({e}); install it (`make deps`)"),
            )
        })?;
    if !out.status.success() {
        return Err(err(
            path,
            format!(
                "ffmpeg failed decoding the audio ({}): {}",
                out.status,
                String::from_utf8_lossy(&out.stderr).trim()
            ),
        ));
    }
    Ok(out
        .stdout
        .chunks_exact(2)
        .map(|b| i16::from_le_bytes([b[0], b[1]]))
        .collect())
}
