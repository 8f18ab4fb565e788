//! `qr-clock` round trip: every frame of the generated video decodes to its clock, and the chirp
//! detector finds every scheduled chirp in the video's audio within 0.1 ms. Needs ffmpeg
//! (installed by `make deps`).

#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

use std::process::Command;

use kiwi_calib::av_delay::detect_chirps;
use kiwi_calib::qr_clock::{VIDEO_SIZE, write_qr_clock};
use kiwi_core::rig::{DOUBLE_GAP_S, qr_text};

#[test]
fn generated_display_video_round_trips() {
    let dir = tempfile::tempdir().unwrap();
    let video = dir.path().join("clock.mp4");
    let out = write_qr_clock(&video, 3.0, 60.0).unwrap();
    assert_eq!(out.frames, 180);
    let csv = std::fs::read_to_string(&out.schedule).unwrap();
    assert_eq!(csv.lines().count(), 1 + out.chirps);
    // Never overwrites.
    assert!(write_qr_clock(&video, 3.0, 60.0).is_err());

    let decoded = Command::new("ffmpeg")
        .args(["-v", "error", "-i"])
        .arg(&video)
        .args(["-f", "rawvideo", "-pix_fmt", "gray", "-"])
        .output()
        .unwrap();
    assert!(decoded.status.success());
    let (w, h) = (VIDEO_SIZE.0 as usize, VIDEO_SIZE.1 as usize);
    let frames: Vec<&[u8]> = decoded.stdout.chunks(w * h).collect();
    assert_eq!(frames.len(), 180);
    for (n, frame) in frames.iter().enumerate() {
        let mut img = rqrr::PreparedImage::prepare_from_greyscale(w, h, |x, y| frame[y * w + x]);
        let grids = img.detect_grids();
        let texts: Vec<String> = grids
            .iter()
            .filter_map(|g| g.decode().ok().map(|(_, t)| t))
            .collect();
        assert_eq!(texts, vec![qr_text(n as u64, 60.0)], "frame {n}");
    }

    let wav = dir.path().join("audio.wav");
    let status = Command::new("ffmpeg")
        .args(["-v", "error", "-i"])
        .arg(&video)
        .args(["-vn", "-ac", "1", "-ar", "48000"])
        .arg(&wav)
        .status()
        .unwrap();
    assert!(status.success());
    let audio = kiwi_core::audio::read_audio(&wav).unwrap();
    let onsets = detect_chirps(&audio.samples, audio.rate_hz);
    let mut expected = Vec::new();
    for c in kiwi_calib::qr_clock::schedule(3.0) {
        expected.push(c.clock_s);
        if c.double {
            expected.push(c.clock_s + DOUBLE_GAP_S);
        }
    }
    assert_eq!(onsets.len(), expected.len(), "{onsets:?}");
    for (found, want) in onsets.iter().zip(&expected) {
        assert!(
            (found - want).abs() < 1e-4,
            "chirp at {want} s found at {found} s"
        );
    }
}

#[test]
fn an_encoder_that_dies_mid_stream_is_reaped_and_leaves_nothing() {
    // The consumer (ffmpeg) exits after reading a few bytes: the frame writer must see the
    // broken pipe, wait for the process (no hang, no zombie) and remove what it wrote.
    use std::os::unix::fs::PermissionsExt as _;
    let dir = tempfile::tempdir().unwrap();
    let fake = dir.path().join("ffmpeg");
    std::fs::write(&fake, "#!/bin/sh\nhead -c 1000 > /dev/null\nexit 1\n").unwrap();
    std::fs::set_permissions(&fake, std::fs::Permissions::from_mode(0o755)).unwrap();
    let out_dir = dir.path().join("out");
    std::fs::create_dir_all(&out_dir).unwrap();
    let (tx, rx) = std::sync::mpsc::channel();
    let (bin, video) = (env!("CARGO_BIN_EXE_kiwi-calib"), out_dir.join("clock.mp4"));
    let fake2 = fake.clone();
    std::thread::spawn(move || {
        let output = Command::new(bin)
            .env("KIWI_FFMPEG", &fake2)
            .args(["qr-clock", "--duration", "3", "--out"])
            .arg(&video)
            .output()
            .unwrap();
        let _ = tx.send(output);
    });
    let output = rx
        .recv_timeout(std::time::Duration::from_secs(60))
        .expect("qr-clock hung on a dead encoder");
    let said = String::from_utf8_lossy(&output.stderr);
    assert!(!output.status.success());
    assert!(said.contains("ffmpeg stopped reading frames"), "{said}");
    let left: Vec<_> = std::fs::read_dir(&out_dir).unwrap().collect();
    assert!(left.is_empty(), "left behind: {left:?}");
}
