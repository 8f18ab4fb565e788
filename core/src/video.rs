//! Write a video-backed lens stream (docs/conventions.md, "Video-backed lens streams"): packed
//! 8-bit RGB frames are piped into the `ffmpeg` program, which encodes them into the lens
//! folder's video; `video.json` and `frames.csv` are written once the video is complete, so a
//! folder never claims a video that is not all there. The simulator and `kiwi ingest` both
//! write streams through here; decoding is the backend's (`kiwi_backend::frames`).

use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdin, Command, Stdio};

use crate::error::{CoreError, Result};
use crate::layout::{FrameRecord, VIDEO_JSON, VIDEO_SCHEMA_VERSION, VideoStream, write_frames_csv};

/// The video file of a stream written here, inside the lens folder.
pub const VIDEO_FILE_NAME: &str = "video.mkv";
/// The program that encodes (found on `PATH`; `make deps` installs it).
pub const FFMPEG: &str = "ffmpeg";
/// Frames between keyframes of the near-lossless H.264 streams: a random access decodes at most
/// this many frames (a quarter second at 119.88 Hz).
pub const H264_KEYFRAME_INTERVAL: u32 = 30;

/// How a stream's video is encoded.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum VideoCodec {
    /// Ut Video, planar RGB: lossless (frames decode bit-identical to the PNGs they replace),
    /// intra-only, the fastest to decode; about the size of the PNGs (2 % smaller on simulated
    /// 960 px frames, docs/ingest.md).
    Utvideo,
    /// FFV1 level 3, planar RGB, every frame a keyframe: lossless and about 18 % smaller than
    /// PNGs, but decodes about five times slower than Ut Video.
    Ffv1,
    /// H.264 (libx264), 4:4:4 chroma, constant quality `crf` (0 is lossless in luma and chroma
    /// planes, but not through the RGB ↔ YUV conversion): about 20× smaller than PNGs at crf 12.
    H264 {
        /// x264's constant rate factor (lower is better; 12 is visually lossless).
        crf: u8,
    },
}

impl VideoCodec {
    /// Parse `utvideo`, `ffv1`, `h264` (crf 12) or `h264:CRF`.
    pub fn parse(text: &str) -> std::result::Result<Self, String> {
        match text {
            "utvideo" => Ok(Self::Utvideo),
            "ffv1" => Ok(Self::Ffv1),
            "h264" | "x264" => Ok(Self::H264 { crf: 12 }),
            other => match other
                .strip_prefix("h264:")
                .or_else(|| other.strip_prefix("x264:"))
            {
                Some(crf) => crf
                    .parse::<u8>()
                    .ok()
                    .filter(|c| *c <= 51)
                    .map(|crf| Self::H264 { crf })
                    .ok_or_else(|| format!("`{other}`: the crf of h264:CRF is 0..=51")),
                None => Err(format!(
                    "`{other}`: expected utvideo, ffv1, h264 or h264:CRF (e.g. h264:12)"
                )),
            },
        }
    }

    /// The codec as ffmpeg names it.
    pub fn name(self) -> &'static str {
        match self {
            Self::Utvideo => "utvideo",
            Self::Ffv1 => "ffv1",
            Self::H264 { .. } => "h264",
        }
    }

    /// Whether decoding gives back the encoded RGB pixels exactly.
    pub fn lossless(self) -> bool {
        !matches!(self, Self::H264 { .. })
    }

    /// Frames between random-access points.
    pub fn keyframe_interval(self) -> u32 {
        match self {
            Self::Utvideo | Self::Ffv1 => 1,
            Self::H264 { .. } => H264_KEYFRAME_INTERVAL,
        }
    }

    /// ffmpeg's encoder arguments.
    pub fn encoder_args(self) -> Vec<String> {
        let args: Vec<String> = match self {
            Self::Utvideo => ["-c:v", "utvideo", "-pix_fmt", "gbrp"]
                .map(String::from)
                .to_vec(),
            Self::Ffv1 => [
                "-c:v", "ffv1", "-level", "3", "-g", "1", "-slices", "4", "-pix_fmt", "gbrp",
            ]
            .map(String::from)
            .to_vec(),
            Self::H264 { crf } => vec![
                "-c:v".into(),
                "libx264".into(),
                "-preset".into(),
                "veryfast".into(),
                "-crf".into(),
                crf.to_string(),
                "-g".into(),
                H264_KEYFRAME_INTERVAL.to_string(),
                // No B-frames: each frame decodes from its own packet, with its own time.
                "-bf".into(),
                "0".into(),
                "-pix_fmt".into(),
                "yuv444p".into(),
            ],
        };
        args
    }
}

/// Encodes one lens stream: [`VideoStreamWriter::push_rgb`] each frame in order, then
/// [`VideoStreamWriter::finish`] with the frame times.
pub struct VideoStreamWriter {
    lens_dir: PathBuf,
    partial: PathBuf,
    codec: VideoCodec,
    width: u32,
    height: u32,
    frames: usize,
    child: Child,
    stdin: Option<ChildStdin>,
    stderr: Option<std::thread::JoinHandle<String>>,
}

fn spawn_err(path: &Path, e: &std::io::Error) -> CoreError {
    CoreError::Io {
        action: "starting ffmpeg to write",
        path: path.to_path_buf(),
        source: std::io::Error::new(
            e.kind(),
            format!("{e} (install ffmpeg: `make deps`, or apt-get install ffmpeg)"),
        ),
    }
}

impl VideoStreamWriter {
    /// Start encoding `width × height` frames at `rate` frames per second (as ffmpeg reads a
    /// rate: `119.88`, `120000/1001`) into `lens_dir` (created if missing).
    pub fn create(
        lens_dir: &Path,
        codec: VideoCodec,
        width: u32,
        height: u32,
        rate: &str,
    ) -> Result<Self> {
        std::fs::create_dir_all(lens_dir).map_err(|e| CoreError::Io {
            action: "creating",
            path: lens_dir.to_path_buf(),
            source: e,
        })?;
        let partial = lens_dir.join(format!(".{VIDEO_FILE_NAME}.partial.mkv"));
        let mut cmd = Command::new(FFMPEG);
        cmd.args(["-nostdin", "-hide_banner", "-loglevel", "error", "-y"])
            .args(["-f", "rawvideo", "-pix_fmt", "rgb24"])
            .args(["-s", &format!("{width}x{height}"), "-framerate", rate])
            .args(["-i", "-", "-an"])
            .args(codec.encoder_args())
            .args(["-f", "matroska"])
            .arg(&partial)
            .stdin(Stdio::piped())
            .stdout(Stdio::null())
            .stderr(Stdio::piped());
        let mut child = cmd.spawn().map_err(|e| spawn_err(&partial, &e))?;
        let stdin = child.stdin.take();
        let stderr = child.stderr.take().map(|mut s| {
            std::thread::spawn(move || {
                let mut text = String::new();
                let _ = s.read_to_string(&mut text);
                text
            })
        });
        Ok(Self {
            lens_dir: lens_dir.to_path_buf(),
            partial,
            codec,
            width,
            height,
            frames: 0,
            child,
            stdin,
            stderr,
        })
    }

    /// Frames pushed so far.
    pub fn frames(&self) -> usize {
        self.frames
    }

    /// Append one frame: packed RGB, `width · height · 3` bytes.
    pub fn push_rgb(&mut self, rgb: &[u8]) -> Result<()> {
        let expected = self.width as usize * self.height as usize * 3;
        if rgb.len() != expected {
            return Err(CoreError::invalid_value(
                "frame",
                format!("{}x{} RGB = {expected} bytes", self.width, self.height),
                format!("{} bytes", rgb.len()),
                "push frames of the stream's size",
            ));
        }
        let Some(stdin) = self.stdin.as_mut() else {
            return Err(self.failed("the encoder's input is closed"));
        };
        if let Err(e) = stdin.write_all(rgb) {
            let message = format!("writing frame {}: {e}", self.frames);
            return Err(self.failed(&message));
        }
        self.frames += 1;
        Ok(())
    }

    fn failed(&mut self, what: &str) -> CoreError {
        self.stdin = None;
        let _ = self.child.kill();
        let _ = self.child.wait();
        let log = self
            .stderr
            .take()
            .and_then(|h| h.join().ok())
            .unwrap_or_default();
        let _ = std::fs::remove_file(&self.partial);
        CoreError::Io {
            action: "encoding",
            path: self.partial.clone(),
            source: std::io::Error::other(format!("{what}; ffmpeg said: {}", log.trim())),
        }
    }

    /// Close the video, then write `video.json` and `frames.csv` (one row per frame, `times`
    /// on the camera clock); returns the descriptor.
    pub fn finish(mut self, times: &[f64]) -> Result<VideoStream> {
        if times.len() != self.frames {
            let message = format!(
                "{} frame times for {} frames pushed",
                times.len(),
                self.frames
            );
            return Err(self.failed(&message));
        }
        drop(self.stdin.take());
        let status = self.child.wait().map_err(|e| CoreError::Io {
            action: "waiting for ffmpeg writing",
            path: self.partial.clone(),
            source: e,
        })?;
        let log = self
            .stderr
            .take()
            .and_then(|h| h.join().ok())
            .unwrap_or_default();
        if !status.success() || self.frames == 0 {
            let _ = std::fs::remove_file(&self.partial);
            return Err(CoreError::Io {
                action: "encoding",
                path: self.partial.clone(),
                source: std::io::Error::other(format!(
                    "ffmpeg ended with {status} after {} frames: {}",
                    self.frames,
                    log.trim()
                )),
            });
        }
        let file = self.lens_dir.join(VIDEO_FILE_NAME);
        std::fs::rename(&self.partial, &file).map_err(|e| CoreError::Io {
            action: "renaming the finished video to",
            path: file.clone(),
            source: e,
        })?;
        let stream = VideoStream {
            schema_version: VIDEO_SCHEMA_VERSION,
            file: VIDEO_FILE_NAME.into(),
            frames: self.frames,
            width: self.width,
            height: self.height,
            codec: self.codec.name().into(),
            lossless: self.codec.lossless(),
            keyframe_interval: self.codec.keyframe_interval(),
            encoder: self.codec.encoder_args().join(" "),
        };
        let rows: Vec<FrameRecord> = times
            .iter()
            .enumerate()
            .map(|(i, &t)| FrameRecord {
                t,
                file: stream.frame_ref(i),
            })
            .collect();
        write_frames_csv(&self.lens_dir.join("frames.csv"), &rows)?;
        stream.save(&self.lens_dir.join(VIDEO_JSON))?;
        Ok(stream)
    }
}

impl Drop for VideoStreamWriter {
    fn drop(&mut self) {
        // Not finished (an error or a panic upstream): stop the encoder, leave no partial file.
        if self.stdin.is_some() {
            self.stdin = None;
            let _ = self.child.kill();
            let _ = self.child.wait();
            let _ = std::fs::remove_file(&self.partial);
        }
    }
}
