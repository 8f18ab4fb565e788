//! Export videos through the `ffmpeg` program: the frames chosen for an export's rows are
//! decoded from the lens stream and piped raw into ffmpeg, which writes them at the export's
//! exact rate, so frame `k`'s presentation time is row `k`'s timestamp.

use std::io::Write as _;
use std::path::Path;
use std::process::{Child, ChildStdin, Command, Stdio};

use crate::error::{BackendError, Result};
use crate::export::Rate;
use crate::frames::{ColorImage, FrameSource};

/// Video codec of exported views: H.264 decodes everywhere (LeRobot accepts h264, hevc and
/// libsvtav1) and encodes fast.
pub const VIDEO_CODEC: &str = "h264";
/// Keyframe interval: LeRobot's default, so a random frame is at most one frame from a
/// keyframe.
pub const KEYFRAME_INTERVAL: u32 = 2;
/// Constant rate factor: visually lossless for 8-bit fisheye frames.
const CRF: u32 = 18;
/// Pixel format every decoder reads.
pub const PIX_FMT: &str = "yuv420p";

fn video_err(path: &Path, message: &str) -> BackendError {
    BackendError::Export(format!("{}: {message}", path.display()))
}

/// An ffmpeg process writing one mp4.
struct Encoder {
    child: Child,
    stdin: Option<ChildStdin>,
    width: usize,
    height: usize,
}

impl Encoder {
    fn start(path: &Path, width: usize, height: usize, rate: Rate) -> Result<Self> {
        let mut child = Command::new("ffmpeg")
            .args(["-hide_banner", "-loglevel", "error", "-y", "-f", "rawvideo"])
            .args(["-pix_fmt", "bgr24", "-s", &format!("{width}x{height}")])
            .args([
                "-framerate",
                &format!("{}/{}", rate.num, rate.den),
                "-i",
                "-",
            ])
            .args(["-c:v", "libx264", "-preset", "veryfast"])
            .args([
                "-crf",
                &CRF.to_string(),
                "-g",
                &KEYFRAME_INTERVAL.to_string(),
            ])
            // No B-frames: decode order is presentation order and no edit list shifts time 0.
            .args(["-bf", "0"])
            .args(["-pix_fmt", PIX_FMT, "-video_track_timescale"])
            .arg(rate.num.to_string())
            .args(["-movflags", "+faststart"])
            .arg(path)
            .stdin(Stdio::piped())
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .map_err(|e| {
                video_err(
                    path,
                    &format!(
                        "cannot start ffmpeg ({e}): install it (`make deps`, Debian package \
                         ffmpeg)"
                    ),
                )
            })?;
        let stdin = child.stdin.take();
        Ok(Self {
            child,
            stdin,
            width,
            height,
        })
    }

    fn push(&mut self, path: &Path, frame: &ColorImage) -> Result<()> {
        if frame.width != self.width || frame.height != self.height {
            return Err(video_err(
                path,
                &format!(
                    "frame of {}x{} px in a stream of {}x{}",
                    frame.width, frame.height, self.width, self.height
                ),
            ));
        }
        let Some(stdin) = self.stdin.as_mut() else {
            return Err(video_err(path, "ffmpeg's input is closed"));
        };
        stdin
            .write_all(&frame.bgr)
            .map_err(|e| video_err(path, &format!("ffmpeg stopped reading frames: {e}")))
    }

    fn finish(mut self, path: &Path) -> Result<()> {
        drop(self.stdin.take());
        let mut stderr = String::new();
        if let Some(mut pipe) = self.child.stderr.take() {
            let _ = std::io::Read::read_to_string(&mut pipe, &mut stderr);
        }
        let status = self
            .child
            .wait()
            .map_err(|e| video_err(path, &format!("ffmpeg did not finish: {e}")))?;
        if !status.success() {
            return Err(video_err(
                path,
                &format!("ffmpeg failed ({status}): {}", stderr.trim()),
            ));
        }
        Ok(())
    }
}

impl Drop for Encoder {
    fn drop(&mut self) {
        // An encoder dropped before `finish` (an error elsewhere) must not outlive the export.
        if self.stdin.is_some() {
            drop(self.stdin.take());
            let _ = self.child.kill();
            let _ = self.child.wait();
        }
    }
}

/// Encode `picks[k]` (frame indices of `source`, non-decreasing) as frame `k` of an mp4 at
/// `rate`, showing each frame to `inspect(k, frame)` as it goes. Returns the frame size
/// (width, height).
pub fn encode_frames(
    source: &FrameSource,
    picks: &[usize],
    rate: Rate,
    path: &Path,
    mut inspect: impl FnMut(usize, &ColorImage),
) -> Result<(usize, usize)> {
    let (width, height) = source.resolution()?;
    let (width, height) = (width as usize, height as usize);
    let mut encoder = Encoder::start(path, width, height, rate)?;
    for_each_pick(
        source,
        picks,
        |m| video_err(path, &m),
        |k, frame| {
            inspect(k, frame);
            encoder.push(path, frame)
        },
    )?;
    encoder.finish(path)?;
    Ok((width, height))
}

/// Call `f(k, frame)` for every pick `k` of `picks` (frame indices of `source`, non-decreasing),
/// in order, decoding only the picked frames (a frame picked for several rows is decoded once).
/// `err` makes this function's own errors (picks out of order, a stream shorter than its picks)
/// name what is being exported.
pub fn for_each_pick(
    source: &FrameSource,
    picks: &[usize],
    err: impl Fn(String) -> BackendError,
    mut f: impl FnMut(usize, &ColorImage) -> Result<()>,
) -> Result<()> {
    if picks.windows(2).any(|w| w[1] < w[0]) {
        return Err(err("frames must be chosen in time order".into()));
    }
    let mut unique = picks.to_vec();
    unique.dedup();
    let mut next = 0usize;
    source.for_each_color_at(&unique, |u, frame| {
        let i = unique[u];
        while next < picks.len() && picks[next] == i {
            f(next, &frame)?;
            next += 1;
        }
        Ok(())
    })?;
    if next != picks.len() {
        return Err(err(format!(
            "the lens stream ended after {next} of {} frames",
            picks.len()
        )));
    }
    Ok(())
}
