//! `kiwi-calib qr-clock`: the display video for the QR-clock rig. Every frame shows a QR code
//! of the display clock (`kiwi_core::rig::qr_text`) and the time in large seven-segment digits;
//! the audio track chirps on the schedule of `kiwi_core::rig`. Frames are piped to `ffmpeg`
//! (a system package installed by `make deps`), which muxes them with the chirp track.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use image::{Rgb, RgbImage};

use kiwi_core::audio::write_wav;
use kiwi_core::io::write_atomic;
use kiwi_core::rig::{DOUBLE_GAP_S, chirp_schedule, chirp_waveform, qr_modules};

use crate::error::{CalibError, Result};

/// Width and height of the display video (px).
pub const VIDEO_SIZE: (u32, u32) = (1280, 720);
/// Audio sample rate of the display video (Hz).
pub const AUDIO_RATE_HZ: u32 = 48_000;

/// What `qr-clock` wrote.
#[derive(Debug, Clone, serde::Serialize)]
pub struct QrClockOutput {
    /// The video.
    pub video: PathBuf,
    /// The chirp schedule (`clock_s,double`).
    pub schedule: PathBuf,
    /// Frames in the video.
    pub frames: u64,
    /// Chirps scheduled.
    pub chirps: usize,
}

const SEGMENTS: [[bool; 7]; 10] = [
    [true, true, true, true, true, true, false],
    [false, true, true, false, false, false, false],
    [true, true, false, true, true, false, true],
    [true, true, true, true, false, false, true],
    [false, true, true, false, false, true, true],
    [true, false, true, true, false, true, true],
    [true, false, true, true, true, true, true],
    [true, true, true, false, false, false, false],
    [true, true, true, true, true, true, true],
    [true, true, true, true, false, true, true],
];

fn fill(img: &mut RgbImage, x0: u32, y0: u32, w: u32, h: u32, color: Rgb<u8>) {
    for y in y0..(y0 + h).min(img.height()) {
        for x in x0..(x0 + w).min(img.width()) {
            img.put_pixel(x, y, color);
        }
    }
}

/// Draw a seven-segment digit string (digits and '.') at `(x, y)` with digit height `h`.
fn draw_digits(img: &mut RgbImage, text: &str, x: u32, y: u32, h: u32) {
    let (w, t) = (h / 2, (h / 10).max(2));
    let black = Rgb([0, 0, 0]);
    let mut cx = x;
    for ch in text.chars() {
        if ch == '.' {
            fill(img, cx, y + h - t, t, t, black);
            cx += 2 * t;
            continue;
        }
        let Some(d) = ch.to_digit(10) else { continue };
        let s = SEGMENTS[d as usize];
        let half = h / 2;
        let segs = [
            (cx + t, y, w - 2 * t, t),
            (cx + w - t, y + t, t, half - t),
            (cx + w - t, y + half, t, half - t),
            (cx + t, y + h - t, w - 2 * t, t),
            (cx, y + half, t, half - t),
            (cx, y + t, t, half - t),
            (cx + t, y + half - t / 2, w - 2 * t, t),
        ];
        for (on, (sx, sy, sw, sh)) in s.iter().zip(segs) {
            if *on {
                fill(img, sx, sy, sw, sh, black);
            }
        }
        cx += w + 2 * t;
    }
}

/// Render display frame `n`.
pub fn render_frame(n: u64, refresh_hz: f64) -> Result<RgbImage> {
    let (w, h) = VIDEO_SIZE;
    let mut img = RgbImage::from_pixel(w, h, Rgb([255, 255, 255]));
    let code = qr_modules(n, refresh_hz)
        .map_err(|e| CalibError::Internal(format!("QR encoding failed: {e}")))?;
    let modules = code.side as u32;
    let quiet = 4;
    let module_px = (h - 40) / (modules + 2 * quiet);
    let (ox, oy) = (40 + quiet * module_px, 20 + quiet * module_px);
    for r in 0..modules {
        for c in 0..modules {
            if code.is_dark(r as usize, c as usize) {
                fill(
                    &mut img,
                    ox + c * module_px,
                    oy + r * module_px,
                    module_px,
                    module_px,
                    Rgb([0, 0, 0]),
                );
            }
        }
    }
    let seconds = n as f64 / refresh_hz;
    draw_digits(&mut img, &format!("{seconds:.3}"), h + 40, h / 2 - 60, 120);
    Ok(img)
}

/// Chirps end this long before the video does, so the last one is whole (s).
const SCHEDULE_END_MARGIN_S: f64 = 0.1;

/// The chirps of a display of `duration_s` seconds.
pub fn schedule(duration_s: f64) -> Vec<kiwi_core::rig::Chirp> {
    chirp_schedule(0.0, duration_s - SCHEDULE_END_MARGIN_S)
}

/// The chirp track for a display of `duration_s` seconds.
pub fn chirp_track(duration_s: f64) -> Vec<f32> {
    let rate = f64::from(AUDIO_RATE_HZ);
    let mut samples = vec![0.0f32; (duration_s * rate).ceil() as usize];
    let wave = chirp_waveform(rate);
    for chirp in schedule(duration_s) {
        let onsets = if chirp.double {
            vec![chirp.clock_s, chirp.clock_s + DOUBLE_GAP_S]
        } else {
            vec![chirp.clock_s]
        };
        for onset in onsets {
            let i0 = (onset * rate).round() as usize;
            for (k, v) in wave.iter().enumerate() {
                if let Some(s) = samples.get_mut(i0 + k) {
                    *s += 0.7 * v;
                }
            }
        }
    }
    samples
}

/// Write the display video `out` (with ffmpeg), its chirp schedule beside it.
pub fn write_qr_clock(out: &Path, duration_s: f64, refresh_hz: f64) -> Result<QrClockOutput> {
    if !(duration_s > 0.0 && duration_s <= 3600.0) {
        return Err(CalibError::Input {
            path: out.to_path_buf(),
            message: format!("--duration {duration_s}: expected seconds in (0, 3600]"),
        });
    }
    if out.exists() {
        return Err(CalibError::Input {
            path: out.to_path_buf(),
            message: "exists and is never overwritten; choose another --out".into(),
        });
    }
    let wav = out.with_extension("chirps.wav");
    write_wav(&wav, &chirp_track(duration_s), AUDIO_RATE_HZ)?;
    let schedule_path = out.with_extension("chirps.csv");
    let schedule = schedule(duration_s);
    let mut csv = String::from("clock_s,double\n");
    for c in &schedule {
        csv.push_str(&format!("{},{}\n", c.clock_s, c.double));
    }
    write_atomic(&schedule_path, csv.as_bytes())?;
    let tmp = out.with_extension("partial.mp4");
    let encoded = encode(out, &tmp, &wav, duration_s, refresh_hz);
    let _ = std::fs::remove_file(&wav);
    let frames = match encoded {
        Ok(frames) => frames,
        Err(e) => {
            // Nothing of a failed run stays behind.
            let _ = std::fs::remove_file(&tmp);
            let _ = std::fs::remove_file(&schedule_path);
            return Err(e);
        }
    };
    std::fs::rename(&tmp, out).map_err(|e| CalibError::Input {
        path: out.to_path_buf(),
        message: e.to_string(),
    })?;
    Ok(QrClockOutput {
        video: out.to_path_buf(),
        schedule: schedule_path,
        frames,
        chirps: schedule.len(),
    })
}

/// The ffmpeg binary: `KIWI_FFMPEG` if set (another build, or a path), else `ffmpeg`.
fn ffmpeg_program() -> std::ffi::OsString {
    std::env::var_os("KIWI_FFMPEG").unwrap_or_else(|| "ffmpeg".into())
}

/// Stream the frames into ffmpeg, muxed with the chirp track, into `tmp`; returns the frame
/// count. If ffmpeg stops reading (it failed), it is killed and waited for, never left behind.
fn encode(out: &Path, tmp: &Path, wav: &Path, duration_s: f64, refresh_hz: f64) -> Result<u64> {
    let (w, h) = VIDEO_SIZE;
    let mut child = Command::new(ffmpeg_program())
        .args([
            "-y",
            "-loglevel",
            "error",
            "-f",
            "rawvideo",
            "-pix_fmt",
            "rgb24",
            "-s",
            &format!("{w}x{h}"),
            "-r",
            &format!("{refresh_hz}"),
            "-i",
            "-",
        ])
        .arg("-i")
        .arg(wav)
        .args([
            "-c:v",
            "libx264",
            "-preset",
            "veryfast",
            "-crf",
            "16",
            "-pix_fmt",
            "yuv420p",
            "-c:a",
            "aac",
            "-b:a",
            "192k",
            "-shortest",
            "-f",
            "mp4",
        ])
        .arg(tmp)
        .stdin(Stdio::piped())
        .spawn()
        .map_err(|e| CalibError::Input {
            path: PathBuf::from("ffmpeg"),
            message: format!(
                "cannot run ffmpeg ({e}); install it with `make deps` (Debian package ffmpeg)"
            ),
        })?;
    let frames = (duration_s * refresh_hz).round() as u64;
    let fed = (|| -> Result<()> {
        let mut stdin = child
            .stdin
            .take()
            .ok_or_else(|| CalibError::Internal("ffmpeg stdin unavailable".into()))?;
        for n in 0..frames {
            let img = render_frame(n, refresh_hz)?;
            stdin
                .write_all(img.as_raw())
                .map_err(|e| CalibError::Input {
                    path: out.to_path_buf(),
                    message: format!(
                        "ffmpeg stopped reading frames after {n} of {frames} ({e}); does it \
                         have libx264 and aac?"
                    ),
                })?;
        }
        Ok(())
        // stdin is dropped here: ffmpeg sees the end of the stream.
    })();
    if fed.is_err() {
        let _ = child.kill();
    }
    let status = child.wait().map_err(|e| CalibError::Input {
        path: out.to_path_buf(),
        message: format!("waiting for ffmpeg: {e}"),
    })?;
    fed?;
    if !status.success() {
        return Err(CalibError::Input {
            path: out.to_path_buf(),
            message: format!("ffmpeg failed ({status}); does it have libx264 and aac?"),
        });
    }
    Ok(frames)
}
