//! One way for every stage to read a lens stream's frames, whatever the lens folder holds: one
//! image per frame (`frames/000000.png`) or one video and its descriptor (`video.json`, see
//! docs/conventions.md). Stages ask for frames by index — in order (decoded ahead on another
//! thread), in parallel batches, or one at a time (random access) — and never open files
//! themselves.
//!
//! Random access into a video goes through one decoder with a small cache: a frame just behind
//! the decoder is served by decoding a short window before it once (the localizer's backward
//! pass walks back frame by frame), a frame a little ahead by decoding forward, anything else by
//! a seek.

use std::collections::VecDeque;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

use opencv::prelude::*;
use rayon::prelude::*;

use kiwi_core::camera::{Camera, CameraModel};
use kiwi_core::layout::{CameraMeta, FrameRecord, LensStorage, VideoStream, read_frames_csv};

use crate::error::{BackendError, Result};
pub use crate::formats::video::ColorImage;
use crate::formats::video::{FRAME_TIME_TOLERANCE_S, VideoReader};
use crate::vision::features::GrayImage;

/// Frames decoded ahead of the consumer (one parallel batch for images, and the queue): enough
/// to keep two cores busy, small in memory.
pub const DECODE_BATCH: usize = 16;
/// Decoded video frames kept for random access (BGR, 2.8 MB each at 960 px).
const CACHE_FRAMES: usize = 24;
/// A frame this far behind the decoder is read by decoding the window of frames before it once,
/// so that a backward walk costs one seek per window instead of one per frame.
const BACKWARD_WINDOW: usize = 12;

/// A lens stream's frames, by index.
pub struct FrameSource {
    lens_dir: PathBuf,
    frames: Vec<FrameRecord>,
    storage: LensStorage,
    cursor: Option<Mutex<Cursor>>,
}

/// The random-access decoder of a video stream.
struct Cursor {
    reader: VideoReader,
    cache: VecDeque<(usize, Arc<ColorImage>)>,
}

fn input_err(path: &Path, message: String) -> BackendError {
    BackendError::Input {
        path: path.to_path_buf(),
        message,
    }
}

impl ColorImage {
    /// Luma of the frame, with the weights of [`GrayImage::from_rgb`] (images read from PNG and
    /// from a lossless video are the same bytes).
    pub fn to_gray(&self) -> Result<GrayImage> {
        GrayImage::from_bgr(self.width as u32, self.height as u32, &self.bgr)
    }

    /// A frame from pixels red first (`width · height · 3` bytes), the inverse of
    /// [`Self::to_rgb`]; `None` when the buffer does not hold that many bytes.
    pub fn from_rgb(width: usize, height: usize, rgb: &[u8]) -> Option<Self> {
        (rgb.len() == width * height * 3).then(|| Self {
            width,
            height,
            bgr: rgb
                .chunks_exact(3)
                .flat_map(|p| [p[2], p[1], p[0]])
                .collect(),
        })
    }

    /// The pixels red first (`width · height · 3` bytes), as image files and datasets store
    /// them.
    pub fn to_rgb(&self) -> Vec<u8> {
        self.bgr
            .chunks_exact(3)
            .flat_map(|p| [p[2], p[1], p[0]])
            .collect()
    }
}

impl FrameSource {
    /// Open a lens folder (`frames.csv` and its images, or `frames.csv`, `video.json` and the
    /// video).
    pub fn open(lens_dir: &Path) -> Result<Self> {
        let csv = lens_dir.join("frames.csv");
        if !csv.is_file() {
            return Err(input_err(
                &csv,
                "missing: a lens folder holds frames.csv (and its images or video); check the \
                 lens folder, or re-ingest the episode"
                    .into(),
            ));
        }
        let frames = read_frames_csv(&csv)?;
        if frames.is_empty() {
            return Err(input_err(&csv, "expected frames, found none".into()));
        }
        let storage = LensStorage::of(lens_dir)?;
        let cursor = match &storage {
            LensStorage::Images => None,
            LensStorage::Video(video) => {
                video.check_frames(&csv, &frames)?;
                let reader = VideoReader::open(&lens_dir.join(&video.file), video)?;
                Some(Mutex::new(Cursor {
                    reader,
                    cache: VecDeque::new(),
                }))
            }
        };
        Ok(Self {
            lens_dir: lens_dir.to_path_buf(),
            frames,
            storage,
            cursor,
        })
    }

    /// The lens folder.
    pub fn lens_dir(&self) -> &Path {
        &self.lens_dir
    }

    /// `frames.csv`'s rows.
    pub fn frames(&self) -> &[FrameRecord] {
        &self.frames
    }

    /// Number of frames.
    pub fn len(&self) -> usize {
        self.frames.len()
    }

    /// Whether the stream has no frame (never, once opened).
    pub fn is_empty(&self) -> bool {
        self.frames.is_empty()
    }

    /// How the folder stores its frames.
    pub fn storage(&self) -> &LensStorage {
        &self.storage
    }

    /// The video descriptor of a video stream.
    pub fn video(&self) -> Option<&VideoStream> {
        match &self.storage {
            LensStorage::Video(v) => Some(v),
            LensStorage::Images => None,
        }
    }

    /// Image size `(width, height)`: from `video.json`, or from the first image's header.
    pub fn resolution(&self) -> Result<(u32, u32)> {
        match &self.storage {
            LensStorage::Video(v) => Ok((v.width, v.height)),
            LensStorage::Images => {
                let path = self.lens_dir.join(&self.frames[0].file);
                image::image_dimensions(&path)
                    .map_err(|e| input_err(&path, format!("cannot read the image header: {e}")))
            }
        }
    }

    /// Check that a lens model was calibrated at this stream's image size. A calibration made at
    /// another resolution is rejected: its pixels mean other directions. `meta` (the camera's
    /// `meta.json`) adds the ingest scale to the message when it is known.
    pub fn check_calibration_size(
        &self,
        camera: &Camera,
        calibration_path: &Path,
        meta: Option<&CameraMeta>,
    ) -> Result<()> {
        let (w, h) = self.resolution()?;
        let (cw, ch) = camera.resolution();
        if (cw, ch) == (w, h) {
            return Ok(());
        }
        let lens = self
            .lens_dir
            .file_name()
            .map_or_else(String::new, |n| n.to_string_lossy().into_owned());
        let ingest = meta
            .and_then(|m| m.recording.as_ref())
            .and_then(|r| r.lenses.iter().find(|l| l.name == lens))
            .map_or_else(String::new, |l| {
                format!(
                    " (ingest scaled the native {}x{} by {})",
                    l.native_resolution[0], l.native_resolution[1], l.scale
                )
            });
        Err(input_err(
            calibration_path,
            format!(
                "lens `{lens}` is calibrated at {cw}x{ch} px, the frames of {} are {w}x{h} px{ingest}: \
                 a calibration at another resolution is not used silently; certify the unit at \
                 {w} px, or re-ingest at {cw} px (kiwi ingest --resolution {cw})",
                self.lens_dir.display()
            ),
        ))
    }

    /// Decode frame `i` (colour).
    pub fn load_color(&self, i: usize) -> Result<ColorImage> {
        self.check_index(i)?;
        match self.video_frame(i) {
            Some(frame) => Ok((*frame?).clone()),
            None => load_image_bgr(&self.lens_dir.join(&self.frames[i].file)),
        }
    }

    /// Decode frame `i` (luma).
    pub fn load_gray(&self, i: usize) -> Result<GrayImage> {
        self.check_index(i)?;
        match self.video_frame(i) {
            Some(frame) => frame?.to_gray(),
            None => GrayImage::load(&self.lens_dir.join(&self.frames[i].file)),
        }
    }

    /// Check that frame `i` is in the stream.
    fn check_index(&self, i: usize) -> Result<()> {
        if i >= self.frames.len() {
            return Err(input_err(
                &self.lens_dir,
                format!("frame {i} asked for, the stream has {}", self.frames.len()),
            ));
        }
        Ok(())
    }

    /// Frame `i` of a video-backed stream through its random-access decoder (shared, cached);
    /// `None` for a stream of images.
    fn video_frame(&self, i: usize) -> Option<Result<Arc<ColorImage>>> {
        let cursor = self.cursor.as_ref()?;
        Some(
            cursor
                .lock()
                .map_err(|_| input_err(&self.lens_dir, "a decoding thread failed earlier".into()))
                .and_then(|mut c| c.load(i, &self.frames)),
        )
    }

    /// Call `f(index, image)` for every frame in order, luma. Frames are decoded ahead on another
    /// thread (images in parallel batches through rayon, a video sequentially) while `f` runs;
    /// `f` sees every frame in order, so results do not depend on the thread count. Stops at the
    /// first error (decoding or `f`).
    pub fn for_each_gray(&self, f: impl FnMut(usize, GrayImage) -> Result<()>) -> Result<()> {
        let all: Vec<usize> = (0..self.frames.len()).collect();
        self.for_each_gray_at(&all, f)
    }

    /// [`FrameSource::for_each_gray`] over the frames `indices` (strictly increasing):
    /// `f(k, image of frame indices[k])`.
    pub fn for_each_gray_at(
        &self,
        indices: &[usize],
        f: impl FnMut(usize, GrayImage) -> Result<()>,
    ) -> Result<()> {
        self.for_each_decoded(indices, |i| self.load_gray(i), VideoReader::read_gray, f)
    }

    /// [`FrameSource::for_each_gray`] in colour.
    pub fn for_each_color(&self, f: impl FnMut(usize, ColorImage) -> Result<()>) -> Result<()> {
        let all: Vec<usize> = (0..self.frames.len()).collect();
        self.for_each_decoded(&all, |i| self.load_color(i), VideoReader::read, f)
    }

    /// [`FrameSource::for_each_gray_at`] in colour: only the frames at `indices` (strictly
    /// increasing) are decoded; `f(k, image of frame indices[k])`.
    pub fn for_each_color_at(
        &self,
        indices: &[usize],
        f: impl FnMut(usize, ColorImage) -> Result<()>,
    ) -> Result<()> {
        self.for_each_decoded(indices, |i| self.load_color(i), VideoReader::read, f)
    }

    /// Check that `indices` name frames of this stream in strictly increasing order.
    pub fn check_indices(&self, indices: &[usize]) -> Result<()> {
        check_increasing_below(&self.lens_dir, indices, self.frames.len())
    }

    fn for_each_decoded<T: Send>(
        &self,
        indices: &[usize],
        load: impl Fn(usize) -> Result<T> + Sync,
        read_video: impl Fn(&mut VideoReader) -> Result<(T, Option<f64>)> + Sync,
        mut f: impl FnMut(usize, T) -> Result<()>,
    ) -> Result<()> {
        self.check_indices(indices)?;
        let n = indices.len();
        // A caller inside a one-thread rayon pool (`--threads 1`) gets one decoding thread.
        let parallel = rayon::current_num_threads() > 1;
        let (tx, rx) = std::sync::mpsc::sync_channel::<Result<T>>(DECODE_BATCH);
        std::thread::scope(|scope| {
            let (load, read_video) = (&load, &read_video);
            scope.spawn(move || match &self.storage {
                LensStorage::Images => {
                    for chunk in indices.chunks(DECODE_BATCH) {
                        let batch: Vec<Result<T>> = if parallel {
                            chunk.par_iter().map(|&i| load(i)).collect()
                        } else {
                            chunk.iter().map(|&i| load(i)).collect()
                        };
                        for img in batch {
                            let failed = img.is_err();
                            // The receiver hangs up after an error of `f`: stop decoding.
                            if tx.send(img).is_err() || failed {
                                return;
                            }
                        }
                    }
                }
                LensStorage::Video(video) => {
                    // A decoder of its own: sequential decoding never disturbs random access.
                    let mut reader =
                        match VideoReader::open(&self.lens_dir.join(&video.file), video) {
                            Ok(r) => r,
                            Err(e) => {
                                let _ = tx.send(Err(e));
                                return;
                            }
                        };
                    // Frames between the wanted ones are decoded (a video is read in order) and
                    // their times checked, but not converted to images.
                    let last = indices.last().copied().unwrap_or(0);
                    let mut wanted = indices.iter().peekable();
                    for i in 0..=last {
                        if wanted.peek() != Some(&&i) {
                            let time = |r: &mut VideoReader| r.read_time().map(|t| ((), t));
                            if let Err(e) = read_checked(&mut reader, i, &self.frames, time) {
                                let _ = tx.send(Err(e));
                                return;
                            }
                            continue;
                        }
                        wanted.next();
                        let img = read_checked(&mut reader, i, &self.frames, read_video);
                        let failed = img.is_err();
                        if tx.send(img).is_err() || failed {
                            return;
                        }
                    }
                }
            });
            // Owned here, so that an early return drops the receiver before the scope joins:
            // the decoder's next `send` then fails and it stops instead of blocking forever on
            // a full channel.
            let rx = rx;
            for i in 0..n {
                let img = rx.recv().map_err(|_| BackendError::Vision {
                    context: "image decoding".into(),
                    message: format!("the decoding thread stopped before frame {i}"),
                })??;
                f(i, img)?;
            }
            Ok(())
        })
    }

    /// `f(index, decoded frame or its decoding error)` for the given frames, in parallel; the
    /// results come back in the order of `indices`. Images decode in parallel; a video decodes
    /// in order on one thread (batch by batch, ahead of the workers) while the workers run `f`.
    pub fn map_color<T: Send>(
        &self,
        indices: &[usize],
        f: impl Fn(usize, Result<ColorImage>) -> T + Sync,
    ) -> Vec<T> {
        if self.cursor.is_none() {
            return indices
                .par_iter()
                .map(|&i| f(i, self.load_color(i)))
                .collect();
        }
        let mut out = Vec::with_capacity(indices.len());
        let (tx, rx) = std::sync::mpsc::sync_channel::<Vec<(usize, Result<ColorImage>)>>(1);
        std::thread::scope(|scope| {
            scope.spawn(move || {
                for chunk in indices.chunks(DECODE_BATCH) {
                    let batch: Vec<_> = chunk.iter().map(|&i| (i, self.load_color(i))).collect();
                    if tx.send(batch).is_err() {
                        return;
                    }
                }
            });
            let rx = rx;
            while let Ok(batch) = rx.recv() {
                let results: Vec<T> = batch.into_par_iter().map(|(i, img)| f(i, img)).collect();
                out.extend(results);
            }
        });
        out
    }
}

/// Check that `indices` are strictly increasing and below `len` (frames of the stream in
/// `lens_dir`, named in the error).
pub fn check_increasing_below(lens_dir: &Path, indices: &[usize], len: usize) -> Result<()> {
    let increasing = indices.windows(2).all(|w| w[0] < w[1]);
    match indices.last() {
        Some(&last) if last >= len => Err(input_err(
            lens_dir,
            format!("frame {last} asked for, the stream has {len} frames"),
        )),
        _ if !increasing => Err(input_err(
            lens_dir,
            "frames asked for out of order: expected strictly increasing indices".into(),
        )),
        _ => Ok(()),
    }
}

/// Read the next frame of `reader` (frame `i`) and check its container time against
/// `frames.csv`.
fn read_checked<T>(
    reader: &mut VideoReader,
    i: usize,
    frames: &[FrameRecord],
    read: impl FnOnce(&mut VideoReader) -> Result<(T, Option<f64>)>,
) -> Result<T> {
    let (img, time_s) = read(reader)?;
    let expected = frames[i].t - frames[0].t;
    // A frame without a container time (drained from the decoder at the end) is known by its
    // position: the reader counts frames from the checked ones before it.
    if let Some(time_s) = time_s
        && (time_s - expected).abs() > FRAME_TIME_TOLERANCE_S
    {
        return Err(input_err(
            reader.path(),
            format!(
                "frame {i} is at {time_s:.6} s in the video, frames.csv puts it at {expected:.6} s \
                 after the first frame: the video and frames.csv disagree (frames dropped or \
                 duplicated while encoding?); re-write the stream"
            ),
        ));
    }
    Ok(img)
}

impl Cursor {
    fn cached(&self, i: usize) -> Option<Arc<ColorImage>> {
        self.cache
            .iter()
            .find(|(k, _)| *k == i)
            .map(|(_, img)| Arc::clone(img))
    }

    fn keep(&mut self, i: usize, img: Arc<ColorImage>) {
        if self.cache.len() == CACHE_FRAMES {
            self.cache.pop_front();
        }
        self.cache.push_back((i, img));
    }

    fn load(&mut self, i: usize, frames: &[FrameRecord]) -> Result<Arc<ColorImage>> {
        if let Some(img) = self.cached(i) {
            return Ok(img);
        }
        let next = self.reader.next_index();
        let start = if i >= next && i - next < BACKWARD_WINDOW {
            next
        } else if i < next && next - i <= CACHE_FRAMES {
            // Just behind: decode the window that ends at `i` once.
            i.saturating_sub(BACKWARD_WINDOW - 1)
        } else {
            i
        };
        self.reader.seek(start)?;
        let mut last = None;
        for k in start..=i {
            let img = Arc::new(read_checked(
                &mut self.reader,
                k,
                frames,
                VideoReader::read,
            )?);
            self.keep(k, Arc::clone(&img));
            last = Some(img);
        }
        last.ok_or_else(|| input_err(self.reader.path(), format!("frame {i} not decoded")))
    }
}

/// Read one image file as packed BGR.
pub fn load_image_bgr(path: &Path) -> Result<ColorImage> {
    let bad = |message: String| BackendError::Input {
        path: path.to_path_buf(),
        message,
    };
    let mat = opencv::imgcodecs::imread(path, opencv::imgcodecs::IMREAD_COLOR)
        .map_err(|e| bad(format!("cannot read the image: {e}")))?;
    if mat.empty() {
        return Err(bad(
            "cannot read the image (missing or not an image); check frames.csv".into(),
        ));
    }
    let (w, h) = (mat.cols() as usize, mat.rows() as usize);
    let bytes = mat
        .data_bytes()
        .map_err(|e| bad(format!("cannot access the pixels: {e}")))?;
    if bytes.len() != w * h * 3 {
        return Err(bad(format!(
            "expected {w}x{h}x3 bytes, found {}",
            bytes.len()
        )));
    }
    Ok(ColorImage {
        width: w,
        height: h,
        bgr: bytes.to_vec(),
    })
}
