//! Decode a video-backed lens stream (`video.json` + its video file) frame by frame through
//! OpenCV's FFmpeg backend: sequential reads, seeks by frame index, and a check of every frame's
//! container time against `frames.csv`.
//!
//! Frames come out as packed 8-bit BGR, as OpenCV gives them. A stream written by KIWI holds
//! only what KIWI wrote into it (planar RGB for the lossless codecs, so the conversion to BGR is
//! a byte shuffle and images are bit-identical to the PNGs they were made from).

use std::borrow::Cow;
use std::path::{Path, PathBuf};

use opencv::core::Mat;
use opencv::prelude::*;
use opencv::videoio::{
    CAP_FFMPEG, CAP_PROP_FRAME_COUNT, CAP_PROP_FRAME_HEIGHT, CAP_PROP_FRAME_WIDTH,
    CAP_PROP_POS_FRAMES, CAP_PROP_POS_MSEC, VideoCapture,
};

use kiwi_core::layout::VideoStream;

use crate::error::{BackendError, Result};
use crate::vision::features::GrayImage;

/// A frame's container time may differ from its `frames.csv` time by this much: containers
/// round times to their time base (1 ms in Matroska), while the neighbouring frame of a
/// 119.88 Hz stream is 8.3 ms away.
pub const FRAME_TIME_TOLERANCE_S: f64 = 1.0e-3;

/// One decoded frame: packed 8-bit BGR, row-major.
#[derive(Debug, Clone, PartialEq)]
pub struct ColorImage {
    /// Width (px).
    pub width: usize,
    /// Height (px).
    pub height: usize,
    /// `width · height · 3` bytes, blue first.
    pub bgr: Vec<u8>,
}

/// An open video of a lens stream, positioned before frame [`VideoReader::next_index`].
pub struct VideoReader {
    path: PathBuf,
    capture: VideoCapture,
    frames: usize,
    width: usize,
    height: usize,
    next: usize,
    buffer: Mat,
}

fn video_err(path: &Path, message: String) -> BackendError {
    BackendError::Input {
        path: path.to_path_buf(),
        message,
    }
}

impl VideoReader {
    /// Open the video `path` of a stream described by `stream` and check its size and frame count.
    pub fn open(path: &Path, stream: &VideoStream) -> Result<Self> {
        let cv = |e: opencv::Error| {
            video_err(
                path,
                format!("cannot open the video ({e}); is it complete and is ffmpeg support built?"),
            )
        };
        let capture = VideoCapture::from_file(path, CAP_FFMPEG).map_err(cv)?;
        if !capture.is_opened().map_err(cv)? {
            return Err(video_err(
                path,
                "cannot open the video (missing, truncated or not a video); re-write the stream"
                    .into(),
            ));
        }
        let width = capture.get(CAP_PROP_FRAME_WIDTH).map_err(cv)? as usize;
        let height = capture.get(CAP_PROP_FRAME_HEIGHT).map_err(cv)? as usize;
        if (width, height) != (stream.width as usize, stream.height as usize) {
            return Err(video_err(
                path,
                format!(
                    "expected {}x{} frames as video.json says, found {width}x{height}; \
                     re-write the stream",
                    stream.width, stream.height
                ),
            ));
        }
        Ok(Self {
            path: path.to_path_buf(),
            capture,
            frames: stream.frames,
            width,
            height,
            next: 0,
            buffer: Mat::default(),
        })
    }

    /// The frame count the container states (an estimate for some containers; `video.json`'s
    /// count, checked while decoding, is the truth).
    pub fn container_frame_count(&self) -> f64 {
        self.capture.get(CAP_PROP_FRAME_COUNT).unwrap_or(f64::NAN)
    }

    /// Index of the frame the next [`VideoReader::read`] returns.
    pub fn next_index(&self) -> usize {
        self.next
    }

    /// Frames in the stream.
    pub fn len(&self) -> usize {
        self.frames
    }

    /// Whether the stream has no frame.
    pub fn is_empty(&self) -> bool {
        self.frames == 0
    }

    /// Move so that the next read returns frame `index`.
    pub fn seek(&mut self, index: usize) -> Result<()> {
        if index == self.next {
            return Ok(());
        }
        if index >= self.frames {
            return Err(video_err(
                &self.path,
                format!(
                    "frame {index} asked for, the stream has {} frames",
                    self.frames
                ),
            ));
        }
        let ok = self
            .capture
            .set(CAP_PROP_POS_FRAMES, index as f64)
            .map_err(|e| video_err(&self.path, format!("cannot seek to frame {index}: {e}")))?;
        if !ok {
            return Err(video_err(
                &self.path,
                format!("the decoder cannot seek to frame {index}; re-write the stream"),
            ));
        }
        self.next = index;
        Ok(())
    }

    fn ended_early(&self, i: usize) -> BackendError {
        video_err(
            &self.path,
            format!(
                "the video ends at frame {i}, video.json and frames.csv list {} frames; the file \
                 is truncated or is not this stream's: re-write the stream",
                self.frames
            ),
        )
    }

    /// Decode the next frame; returns it with its container time relative to the first frame
    /// (s), when the decoder gives one.
    pub fn read(&mut self) -> Result<(ColorImage, Option<f64>)> {
        let time_s = self.decode()?;
        let bgr = self.decoded_bgr()?.into_owned();
        let (width, height) = (self.width, self.height);
        Ok((ColorImage { width, height, bgr }, time_s))
    }

    /// [`VideoReader::read`] in luma (the weights of [`GrayImage::from_rgb`]), converted
    /// straight from the decoder's buffer.
    pub fn read_gray(&mut self) -> Result<(GrayImage, Option<f64>)> {
        let time_s = self.decode()?;
        let gray =
            GrayImage::from_bgr(self.width as u32, self.height as u32, &self.decoded_bgr()?)?;
        Ok((gray, time_s))
    }

    /// Move past the next frame, decoded but not converted to an image; its container time as
    /// [`VideoReader::read`] gives it.
    pub fn read_time(&mut self) -> Result<Option<f64>> {
        let i = self.next;
        if i >= self.frames {
            return Err(video_err(
                &self.path,
                format!("read past the last frame ({} frames)", self.frames),
            ));
        }
        let grabbed = self
            .capture
            .grab()
            .map_err(|e| video_err(&self.path, format!("frame {i}: cannot decode: {e}")))?;
        if !grabbed {
            return Err(self.ended_early(i));
        }
        let msec = self
            .capture
            .get(CAP_PROP_POS_MSEC)
            .map_err(|e| video_err(&self.path, format!("frame {i}: no time: {e}")))?;
        self.next += 1;
        // OpenCV reports 0 for frames it drains from the decoder after the last packet (the
        // delayed frames of a stream with B-frames): no time known.
        Ok((i == 0 || msec != 0.0).then_some(msec * 1e-3))
    }

    /// Decode the next frame into the reader's buffer and check its size; its container time
    /// as [`VideoReader::read`] gives it.
    fn decode(&mut self) -> Result<Option<f64>> {
        let time_s = self.read_time()?;
        let i = self.next - 1;
        let got = self
            .capture
            .retrieve(&mut self.buffer, 0)
            .map_err(|e| video_err(&self.path, format!("frame {i}: cannot decode: {e}")))?;
        if !got || self.buffer.empty() {
            return Err(self.ended_early(i));
        }
        let (w, h) = (self.buffer.cols() as usize, self.buffer.rows() as usize);
        if (w, h) != (self.width, self.height) || self.buffer.channels() != 3 {
            return Err(video_err(
                &self.path,
                format!(
                    "frame {i}: expected a {}x{} colour frame, decoded {w}x{h} with {} channels",
                    self.width,
                    self.height,
                    self.buffer.channels()
                ),
            ));
        }
        Ok(time_s)
    }

    /// The packed BGR bytes of the frame [`VideoReader::decode`] decoded last: the decoder's
    /// buffer itself when its rows are contiguous, else a packed copy.
    fn decoded_bgr(&self) -> Result<Cow<'_, [u8]>> {
        let i = self.next.saturating_sub(1);
        let err = |e: opencv::Error| video_err(&self.path, format!("frame {i}: {e}"));
        if self.buffer.is_continuous() {
            return Ok(Cow::Borrowed(self.buffer.data_bytes().map_err(err)?));
        }
        let mut packed = Vec::with_capacity(self.width * self.height * 3);
        for r in 0..self.height as i32 {
            packed.extend_from_slice(self.buffer.row(r).map_err(err)?.data_bytes().map_err(err)?);
        }
        Ok(Cow::Owned(packed))
    }

    /// The video file.
    pub fn path(&self) -> &Path {
        &self.path
    }
}
