//! Audio: one function turns a file into mono samples at a known rate ([`read_audio`]), one
//! writes WAV ([`write_wav`]), and windowed-sinc resampling and decimation bring recordings to a
//! common analysis rate. Used by sync, the A/V-delay rig analysis and the simulator.
//!
//! WAV is read with hound today; audio inside `.mp4`/`.insv` arrives with ingest, behind the same
//! [`read_audio`] entry point.

use std::path::Path;

use crate::error::{CoreError, Result};

/// Mono audio at a sample rate.
#[derive(Debug, Clone)]
pub struct Audio {
    /// Sample rate (Hz).
    pub rate_hz: f64,
    /// Samples, full scale ±1.
    pub samples: Vec<f32>,
}

impl Audio {
    /// Duration (s).
    pub fn duration_s(&self) -> f64 {
        self.samples.len() as f64 / self.rate_hz
    }
}

fn audio_error(path: &Path, message: impl Into<String>) -> CoreError {
    CoreError::Invalid {
        path: path.to_path_buf(),
        field: "audio".into(),
        expected: "a readable WAV track".into(),
        found: message.into(),
        fix: "extract the camera's audio as WAV (ffmpeg -i IN -vn -ac 1 OUT.wav)".into(),
    }
}

/// Decode an audio file to mono (channels averaged).
pub fn read_audio(path: &Path) -> Result<Audio> {
    if path.is_dir() {
        return Err(audio_error(path, "it is a folder; expected a WAV file"));
    }
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .unwrap_or("")
        .to_ascii_lowercase();
    if ext != "wav" {
        return Err(audio_error(
            path,
            format!(
                "cannot decode `.{ext}` audio yet; extract a WAV track first (ffmpeg -i IN -vn -ac 1 OUT.wav)"
            ),
        ));
    }
    let file = std::fs::File::open(path).map_err(|source| CoreError::Io {
        action: "opening",
        path: path.to_path_buf(),
        source,
    })?;
    decode_wav(std::io::BufReader::new(file), path)
}

/// Decode WAV content from any reader to mono; `path` names it in errors.
pub fn decode_wav<R: std::io::Read>(reader: R, path: &Path) -> Result<Audio> {
    let reader = hound::WavReader::new(reader)
        .map_err(|e| audio_error(path, format!("not a readable WAV file: {e}")))?;
    let spec = reader.spec();
    let channels = usize::from(spec.channels.max(1));
    let interleaved: Vec<f32> = match spec.sample_format {
        hound::SampleFormat::Float => reader
            .into_samples::<f32>()
            .collect::<std::result::Result<_, _>>(),
        hound::SampleFormat::Int => {
            let scale = 1.0 / (1u64 << (spec.bits_per_sample.clamp(1, 32) - 1)) as f32;
            reader
                .into_samples::<i32>()
                .map(|s| s.map(|v| v as f32 * scale))
                .collect::<std::result::Result<_, _>>()
        }
    }
    .map_err(|e| audio_error(path, format!("WAV data is damaged: {e}")))?;
    let samples: Vec<f32> = interleaved
        .chunks(channels)
        .map(|c| c.iter().sum::<f32>() / channels as f32)
        .collect();
    if samples.is_empty() {
        return Err(audio_error(path, "the WAV file holds no samples"));
    }
    if samples.iter().any(|s| !s.is_finite()) {
        return Err(audio_error(
            path,
            "the WAV file holds NaN or infinite samples",
        ));
    }
    Ok(Audio {
        rate_hz: f64::from(spec.sample_rate),
        samples,
    })
}

/// What a WAV file's header says, checked against the file's size.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
pub struct WavInfo {
    /// Sample rate (Hz).
    pub rate_hz: u32,
    /// Channels.
    pub channels: u16,
    /// Samples per channel the header announces.
    pub frames: u32,
}

/// Read a WAV header without decoding the samples, and check that the file holds as many
/// bytes as the header announces (a truncated copy fails here). `file_len` is the file's size.
pub fn wav_info<R: std::io::Read>(reader: R, file_len: u64, path: &Path) -> Result<WavInfo> {
    let reader = hound::WavReader::new(reader)
        .map_err(|e| audio_error(path, format!("not a readable WAV file: {e}")))?;
    let spec = reader.spec();
    let frames = reader.duration();
    if spec.sample_rate == 0 || spec.channels == 0 {
        return Err(audio_error(
            path,
            format!(
                "the header says {} Hz and {} channels",
                spec.sample_rate, spec.channels
            ),
        ));
    }
    if frames == 0 {
        return Err(audio_error(path, "the WAV file holds no samples"));
    }
    let bytes =
        u64::from(frames) * u64::from(spec.channels) * u64::from(spec.bits_per_sample.div_ceil(8));
    if file_len < bytes {
        return Err(audio_error(
            path,
            format!(
                "the header announces {frames} samples ({bytes} bytes) but the file has only \
                 {file_len} bytes: it is truncated (copy it again)"
            ),
        ));
    }
    Ok(WavInfo {
        rate_hz: spec.sample_rate,
        channels: spec.channels,
        frames,
    })
}

/// Half-width of the resampling kernel in input samples at the lower of the two rates.
const RESAMPLE_HALF_TAPS: usize = 16;

/// Resample to `rate_hz` with a Hann-windowed sinc (cut off at the lower Nyquist frequency).
pub fn resample(audio: &Audio, rate_hz: f64) -> Audio {
    if (audio.rate_hz - rate_hz).abs() < 1e-9 {
        return audio.clone();
    }
    let ratio = rate_hz / audio.rate_hz;
    let cutoff = ratio.min(1.0); // fraction of the input Nyquist band kept
    let half = RESAMPLE_HALF_TAPS as f64 / cutoff;
    let n_out = (audio.samples.len() as f64 * ratio).floor() as usize;
    let input = &audio.samples;
    let out: Vec<f32> = (0..n_out)
        .map(|k| {
            let center = k as f64 / ratio;
            let lo = (center - half).ceil().max(0.0) as usize;
            let hi = ((center + half).floor() as usize).min(input.len().saturating_sub(1));
            let mut acc = 0.0;
            for i in lo..=hi {
                let x = i as f64 - center;
                let arg = std::f64::consts::PI * x * cutoff;
                let sinc = if arg.abs() < 1e-12 {
                    1.0
                } else {
                    arg.sin() / arg
                };
                let window = 0.5 + 0.5 * (std::f64::consts::PI * x / half).cos();
                acc += f64::from(input[i]) * sinc * window * cutoff;
            }
            acc as f32
        })
        .collect();
    Audio {
        rate_hz,
        samples: out,
    }
}

/// Decimate by an integer factor after a windowed-sinc low-pass (for the fingerprint rate).
pub fn decimate(audio: &Audio, factor: usize) -> Audio {
    if factor <= 1 {
        return audio.clone();
    }
    let cutoff = 0.9 / factor as f64;
    let half = 8 * factor;
    let taps: Vec<f64> = (0..=2 * half)
        .map(|i| {
            let x = i as f64 - half as f64;
            let arg = std::f64::consts::PI * x * cutoff;
            let sinc = if x == 0.0 { 1.0 } else { arg.sin() / arg };
            sinc * cutoff * (0.5 + 0.5 * (std::f64::consts::PI * x / (half as f64 + 1.0)).cos())
        })
        .collect();
    let input = &audio.samples;
    let out: Vec<f32> = (0..input.len() / factor)
        .map(|k| {
            let c = k * factor;
            let mut acc = 0.0;
            for (j, t) in taps.iter().enumerate() {
                if let Some(v) = (c + j).checked_sub(half).and_then(|i| input.get(i)) {
                    acc += f64::from(*v) * t;
                }
            }
            acc as f32
        })
        .collect();
    Audio {
        rate_hz: audio.rate_hz / factor as f64,
        samples: out,
    }
}

/// Write mono 16-bit PCM WAV atomically.
pub fn write_wav(path: &Path, samples: &[f32], rate_hz: u32) -> Result<()> {
    let spec = hound::WavSpec {
        channels: 1,
        sample_rate: rate_hz,
        bits_per_sample: 16,
        sample_format: hound::SampleFormat::Int,
    };
    let mut bytes = std::io::Cursor::new(Vec::with_capacity(samples.len() * 2 + 44));
    {
        let wav_err = |e: hound::Error| CoreError::Io {
            action: "encoding WAV for",
            path: path.to_path_buf(),
            source: std::io::Error::other(e.to_string()),
        };
        let mut writer = hound::WavWriter::new(&mut bytes, spec).map_err(wav_err)?;
        for &s in samples {
            let v = (f64::from(s) * 32767.0).round().clamp(-32768.0, 32767.0) as i16;
            writer.write_sample(v).map_err(wav_err)?;
        }
        writer.finalize().map_err(wav_err)?;
    }
    crate::io::write_atomic(path, &bytes.into_inner())
}
