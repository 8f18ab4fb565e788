//! Video-backed lens streams end cleanly when either side fails: a consumer that fails
//! mid-stream stops the decoder thread (no hang), a selection decodes only its frames, and a
//! video that disagrees with `frames.csv` names the frame. A colour video's luma, read in order
//! or at random, is the luma of the pixels written (red, green and blue in their places).

#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

use std::path::{Path, PathBuf};
use std::sync::mpsc;
use std::time::Duration;

use kiwi_backend::error::BackendError;
use kiwi_backend::frames::{DECODE_BATCH, FrameSource};
use kiwi_backend::vision::features::GrayImage;
use kiwi_core::video::{VideoCodec, VideoStreamWriter};

/// A stream that hangs fails the test after this long instead of blocking the test run.
const HANG_TIMEOUT: Duration = Duration::from_secs(60);
const SIZE: u32 = 32;

/// A lossless video stream of `n` frames whose grey level is the frame index.
fn video_stream(dir: &Path, n: usize) -> PathBuf {
    let lens = dir.join("front");
    let mut w = VideoStreamWriter::create(&lens, VideoCodec::Utvideo, SIZE, SIZE, "30").unwrap();
    for i in 0..n {
        w.push_rgb(&vec![i as u8; (SIZE * SIZE * 3) as usize])
            .unwrap();
    }
    let times: Vec<f64> = (0..n).map(|i| i as f64 / 30.0).collect();
    w.finish(&times).unwrap();
    lens
}

/// Run `f` on another thread; fail if it does not return within [`HANG_TIMEOUT`].
fn within_timeout<T: Send + 'static>(f: impl FnOnce() -> T + Send + 'static) -> T {
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        let _ = tx.send(f());
    });
    rx.recv_timeout(HANG_TIMEOUT)
        .expect("the video stream hung: a thread waits on one that failed")
}

#[test]
fn a_consumer_failing_mid_video_stops_the_decoder() {
    let dir = tempfile::tempdir().unwrap();
    // Many more frames than the channel holds: the decoder is blocked on a full channel when
    // the consumer fails.
    let lens = video_stream(dir.path(), 6 * DECODE_BATCH);
    let (seen, result) = within_timeout(move || {
        let source = FrameSource::open(&lens).unwrap();
        let mut seen = 0;
        let r = source.for_each_gray(|i, _| {
            seen += 1;
            if i == 3 {
                Err(BackendError::Vision {
                    context: "test".into(),
                    message: "consumer failed".into(),
                })
            } else {
                Ok(())
            }
        });
        (seen, r)
    });
    assert_eq!(seen, 4);
    assert!(result.unwrap_err().to_string().contains("consumer failed"));
}

#[test]
fn a_selection_of_a_video_decodes_exactly_its_frames() {
    let dir = tempfile::tempdir().unwrap();
    let n = 3 * DECODE_BATCH;
    let lens = video_stream(dir.path(), n);
    let source = FrameSource::open(&lens).unwrap();
    let wanted: Vec<usize> = (5..n).step_by(7).collect();
    let mut got = Vec::new();
    source
        .for_each_gray_at(&wanted, |k, image| {
            got.push((k, image.data[0]));
            Ok(())
        })
        .unwrap();
    let expected: Vec<(usize, u8)> = wanted
        .iter()
        .enumerate()
        .map(|(k, &i)| (k, i as u8))
        .collect();
    assert_eq!(got, expected);
    let e = source
        .for_each_gray_at(&[3, 2], |_, _| Ok(()))
        .unwrap_err()
        .to_string();
    assert!(e.contains("increasing"), "{e}");
    let e = source
        .for_each_gray_at(&[n], |_, _| Ok(()))
        .unwrap_err()
        .to_string();
    assert!(e.contains(&format!("frame {n}")), "{e}");
}

#[test]
fn a_video_whose_frames_csv_disagrees_names_the_frame_and_does_not_hang() {
    let dir = tempfile::tempdir().unwrap();
    let lens = video_stream(dir.path(), 4 * DECODE_BATCH);
    // Frame 20 claimed a frame period later than the video holds it.
    let csv = lens.join("frames.csv");
    let text = std::fs::read_to_string(&csv).unwrap();
    let mut out = String::new();
    for (line_no, line) in text.lines().enumerate() {
        if line_no >= 21 {
            let (t, file) = line.split_once(',').unwrap();
            let t: f64 = t.parse().unwrap();
            out.push_str(&format!("{},{file}\n", t + 1.0 / 30.0));
        } else {
            out.push_str(line);
            out.push('\n');
        }
    }
    std::fs::write(&csv, out).unwrap();
    let result = within_timeout(move || {
        let source = FrameSource::open(&lens).unwrap();
        source.for_each_gray(|_, _| {
            std::thread::sleep(Duration::from_millis(1));
            Ok(())
        })
    });
    let e = result.unwrap_err().to_string();
    assert!(e.contains("frame 20") && e.contains("disagree"), "{e}");
}

#[test]
fn a_colour_video_reads_as_the_luma_of_its_pixels_in_order_and_at_random() {
    let dir = tempfile::tempdir().unwrap();
    let lens = dir.path().join("front");
    let n = 12;
    // Red, green and blue each vary their own way, so a swapped channel changes the luma.
    let frame = |i: usize| -> Vec<u8> {
        (0..(SIZE * SIZE) as usize)
            .flat_map(|p| {
                let (x, y) = (p % SIZE as usize, p / SIZE as usize);
                [
                    (8 * x + i) as u8,
                    (5 * y + 3 * i) as u8,
                    (255 - 7 * x - y) as u8,
                ]
            })
            .collect()
    };
    let mut w = VideoStreamWriter::create(&lens, VideoCodec::Utvideo, SIZE, SIZE, "30").unwrap();
    for i in 0..n {
        w.push_rgb(&frame(i)).unwrap();
    }
    let times: Vec<f64> = (0..n).map(|i| i as f64 / 30.0).collect();
    w.finish(&times).unwrap();
    let expected = |i: usize| GrayImage::from_rgb(SIZE, SIZE, &frame(i)).unwrap();
    let source = FrameSource::open(&lens).unwrap();
    let mut read = 0;
    source
        .for_each_gray(|i, image| {
            assert_eq!(image, expected(i), "frame {i} read in order");
            read += 1;
            Ok(())
        })
        .unwrap();
    assert_eq!(read, n);
    for i in [9, 2, 7] {
        assert_eq!(
            source.load_gray(i).unwrap(),
            expected(i),
            "frame {i} read at random"
        );
        assert_eq!(
            source.load_color(i).unwrap().to_rgb(),
            frame(i),
            "frame {i} in colour"
        );
    }
}
