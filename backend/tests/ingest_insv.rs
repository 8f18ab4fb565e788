//! `kiwi ingest` on Insta360-like recordings built here: ffmpeg writes the video tracks (known
//! frame times, a red front-candidate lens and a blue one) and a PCM audio track that starts a
//! known 10 ms after the video, and `kiwi_fixtures::insv` appends a metadata trailer written
//! from the documented record layout. Ingest must recover every frame time, every IMU sample
//! (values, units, axes, clock) and the audio to the sample, join split recordings and lens
//! file pairs, and fail with the named errors of the known field failures.

#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

use std::path::{Path, PathBuf};
use std::process::Command;

use kiwi_backend::BackendError;
use kiwi_backend::frames::FrameSource;
use kiwi_backend::ingest::{CameraInput, IngestOptions, LensOutput, ingest_episode};
use kiwi_core::imu::ImuSeries;
use kiwi_core::layout::{EpisodeConfig, EpisodeLayout, HeadConfig, Session, Side, WristConfig};
use kiwi_core::video::VideoCodec;
use kiwi_fixtures::insv::{InsvTrailer, TrailerImu, TrailerLayout};

const RATE: &str = "30000/1001";
const FPS: f64 = 30000.0 / 1001.0;
const FRAMES: usize = 45;
const SIDE: u32 = 96;
const AUDIO_RATE: u32 = 48_000;
/// The audio track starts this long after the first video frame.
const AUDIO_DELAY_S: f64 = 0.01;
/// Device clock (µs) of the first video frame.
const FIRST_FRAME_US: i64 = 5_000_000;
const GYRO_OFFSET_MS: f64 = 1.6;

fn ffmpeg(args: &[&str]) {
    let out = Command::new("ffmpeg")
        .args(["-nostdin", "-hide_banner", "-loglevel", "error", "-y"])
        .args(args)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "ffmpeg {args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// Deterministic test audio: a chirp with a click every 100 ms.
fn audio_samples(n: usize) -> Vec<i16> {
    (0..n)
        .map(|i| {
            let t = i as f64 / f64::from(AUDIO_RATE);
            let v = 0.3 * (2.0 * std::f64::consts::PI * (300.0 + 900.0 * t) * t).sin()
                + if i % 4800 < 8 { 0.5 } else { 0.0 };
            (v * 32767.0).round() as i16
        })
        .collect()
}

fn write_wav(path: &Path, samples: &[i16]) {
    let spec = hound::WavSpec {
        channels: 1,
        sample_rate: AUDIO_RATE,
        bits_per_sample: 16,
        sample_format: hound::SampleFormat::Int,
    };
    let mut w = hound::WavWriter::create(path, spec).unwrap();
    for &s in samples {
        w.write_sample(s).unwrap();
    }
    w.finalize().unwrap();
}

/// A recording file: one constant-colour video track of `frames` frames per colour, and an
/// audio track unless `audio` is None.
fn recording(
    path: &Path,
    colours: &[&str],
    frames: usize,
    audio: Option<&Path>,
    extra_video_args: &[&str],
) {
    let mut args: Vec<String> = Vec::new();
    for c in colours {
        args.extend([
            "-f".into(),
            "lavfi".into(),
            "-i".into(),
            // Each track ends after `frames` frames by itself (an output frame limit
            // would end the file when the first track reaches it, one frame short on the
            // others).
            format!("color=c={c}:s={SIDE}x{SIDE}:r={RATE},format=yuv420p,trim=end_frame={frames}"),
        ]);
    }
    if let Some(a) = audio {
        args.extend([
            "-itsoffset".into(),
            AUDIO_DELAY_S.to_string(),
            "-i".into(),
            a.display().to_string(),
        ]);
    }
    for k in 0..colours.len() {
        args.extend(["-map".into(), format!("{k}:v")]);
    }
    if audio.is_some() {
        args.extend(["-map".into(), format!("{}:a", colours.len())]);
        args.extend(["-c:a".into(), "pcm_s16le".into()]);
    }
    args.extend(
        [
            "-shortest",
            "-c:v",
            "libx264",
            "-preset",
            "ultrafast",
            "-g",
            "10",
        ]
        .map(String::from),
    );
    args.extend(extra_video_args.iter().map(|s| (*s).to_string()));
    args.extend(["-f".into(), "mov".into(), path.display().to_string()]);
    let refs: Vec<&str> = args.iter().map(String::as_str).collect();
    ffmpeg(&refs);
}

/// Raw IMU samples at 1 kHz from 10 ms before the first frame to the end, device clock µs;
/// counts vary per sample and axis so that any mix-up shows. The accelerometer holds gravity
/// (1 g on the device's first axis, ±0.1 g of variation) and the gyro ±1.2 °/s of noise around
/// rest, so the log passes KIWI's plausibility check of IMU units.
fn raw_imu(first_frame_us: i64, frames: usize) -> Vec<(u64, [u16; 6])> {
    // Counts per g at the ±32 g range.
    const ONE_G: i64 = 1024;
    let end = first_frame_us + (frames as f64 / FPS * 1e6) as i64;
    let mut out = Vec::new();
    let mut t = first_frame_us - 10_000;
    let mut k = 0u64;
    while t < end {
        let accel =
            |axis: u64, g: i64| (32768 + g + ((k * 37 + axis * 13) % 200) as i64 - 100) as u16;
        let gyro = |axis: u64| (32768 + ((k * 37 + axis * 1013) % 40) as i64 - 20) as u16;
        out.push((
            t as u64,
            [
                accel(0, ONE_G),
                accel(1, 0),
                accel(2, 0),
                gyro(3),
                gyro(4),
                gyro(5),
            ],
        ));
        t += 1000;
        k += 1;
    }
    out
}

fn trailer(
    model: &str,
    imu: TrailerImu,
    first_frame_us: i64,
    layout: TrailerLayout,
) -> InsvTrailer {
    InsvTrailer {
        serial: "TEST0001".into(),
        camera_type: model.into(),
        firmware: "v1.10.9_build1".into(),
        dimension: (SIDE, SIDE),
        frame_rate: FPS,
        first_frame_timestamp: first_frame_us,
        rolling_shutter_ms: 15.9,
        gyro_timestamp_ms: Some(GYRO_OFFSET_MS),
        ranges: (32, 2000),
        offset_v3: "2_1.9_100_100_48_48_0_0_90_0_0_0_0.1_0.2_0.3_0_0_192_96_113_1.9_100_100_144_48_0_0_90_0_0_-0.03_0.1_0.2_0.3_0_0_192_96_113_197632".into(),
        imu,
        // Two entries before the first frame (µs clock; a trailer on another clock replaces them).
        exposures: (0..FRAMES as u64 + 4)
            .map(|k| ((first_frame_us as u64).saturating_sub(2 * 33_367) + k * 33_367, 0.004))
            .collect(),
        layout,
        in_box: true,
    }
}

fn session(dir: &Path, head: bool) -> PathBuf {
    let mut wrists = std::collections::BTreeMap::new();
    wrists.insert(
        Side::Left,
        WristConfig {
            unit: "X5-T1".into(),
            calibration: "units/X5-T1/2026-01-01".into(),
            tool: kiwi_core::layout::ToolKind::Chopstick,
        },
    );
    let s = Session {
        schema_version: 1,
        name: "ingest-test".into(),
        map_episode: "ep000".into(),
        map_wrist: None,
        wrists,
        head: head.then(|| HeadConfig {
            unit: "GO3-T1".into(),
            calibration: "units/GO3-T1/2026-01-01".into(),
            marker_id: 3,
            marker_size_m: 0.08,
            marker_dictionary: "4x4_50".into(),
            mount: None,
        }),
        episodes: vec![EpisodeConfig {
            name: "ep000".into(),
            description: String::new(),
        }],
        export: None,
        floor: None,
    };
    std::fs::create_dir_all(dir.join("episodes")).unwrap();
    let toml = dir.join("session.toml");
    s.save(&toml).unwrap();
    toml
}

fn options(output: LensOutput) -> IngestOptions {
    IngestOptions {
        resolution: 64,
        output,
        mode: Some("x5-29.97fps".into()),
        ..IngestOptions::default()
    }
}

fn wav_samples(path: &Path) -> Vec<i16> {
    hound::WavReader::open(path)
        .unwrap()
        .samples::<i16>()
        .map(Result::unwrap)
        .collect()
}

/// KIWI's X5 axes: x = -device y, y = -device z, z = +device x.
fn x5_axes(v: [f64; 3]) -> [f64; 3] {
    [-v[1], -v[2], v[0]]
}

#[test]
fn an_x5_recording_and_a_go3_recording_are_ingested_exactly() {
    let tmp = tempfile::tempdir().unwrap();
    let audio = audio_samples(AUDIO_RATE as usize * 2);
    let wav = tmp.path().join("audio.wav");
    write_wav(&wav, &audio);
    // The X5: both lenses in one file (track 0 red, track 1 blue), indexed trailer in a box.
    let x5 = tmp.path().join("VID_20260101_120000_00_001.insv");
    recording(&x5, &["red", "blue"], FRAMES, Some(&wav), &[]);
    let imu = raw_imu(FIRST_FRAME_US, FRAMES);
    trailer(
        "Insta360 X5",
        TrailerImu::Raw(imu.clone()),
        FIRST_FRAME_US,
        TrailerLayout::Indexed,
    )
    .append_to(&x5)
    .unwrap();
    // The GO 3: one lens, float IMU (ms clock), back-to-back trailer without a box.
    let go3 = tmp.path().join("VID_20260101_120000_00_002.mp4");
    recording(&go3, &["green"], FRAMES, Some(&wav), &[]);
    let float_imu: Vec<(u64, [f64; 3], [f64; 3])> = (0..120u64)
        .map(|k| {
            let f = k as f64;
            (
                4990 + k * 5,
                [0.001 * f, -0.2, 1.0],
                [0.0001 * f, 0.0002, -0.0003],
            )
        })
        .collect();
    let mut go3_trailer = trailer(
        "Insta360 GO 3",
        TrailerImu::Float(float_imu.clone()),
        5000,
        TrailerLayout::Contiguous,
    );
    go3_trailer.in_box = false;
    go3_trailer.gyro_timestamp_ms = None;
    go3_trailer.exposures.clear();
    go3_trailer.append_to(&go3).unwrap();

    let toml = session(&tmp.path().join("s"), true);
    let report = ingest_episode(
        &toml,
        "ep001",
        &[
            CameraInput {
                camera: "left".into(),
                files: vec![x5.clone()],
                imu_csv: None,
            },
            CameraInput {
                camera: "head".into(),
                files: vec![go3.clone()],
                imu_csv: None,
            },
        ],
        &options(LensOutput::Video(VideoCodec::Utvideo)),
    )
    .unwrap();
    println!("{}", serde_json::to_string_pretty(&report).unwrap());
    let layout = EpisodeLayout::new(&report.episode_dir);
    assert!(
        Session::load(&toml)
            .unwrap()
            .episodes
            .iter()
            .any(|e| e.name == "ep001"),
        "the episode is added to session.toml"
    );

    // Frame times: every frame, from the container, per lens; front is track 0 (red).
    for (camera, lens, colour) in [
        ("left", "front", [0u8, 0, 254]),
        ("left", "rear", [254, 0, 0]),
        ("head", "main", [0, 128, 0]),
    ] {
        let src = FrameSource::open(&layout.lens_dir(camera, lens)).unwrap();
        assert_eq!(src.len(), FRAMES, "{camera}/{lens}");
        for (k, f) in src.frames().iter().enumerate() {
            assert!(
                (f.t - k as f64 / FPS).abs() < 1e-9,
                "{camera}/{lens} frame {k}: {} s",
                f.t
            );
        }
        assert_eq!(src.resolution().unwrap(), (64, 64), "resized to 64 px");
        let mut seen = 0;
        src.for_each_color(|_, img| {
            let px = &img.bgr[(32 * 64 + 32) * 3..(32 * 64 + 32) * 3 + 3];
            for c in 0..3 {
                assert!(
                    (i32::from(px[c]) - i32::from(colour[c])).abs() <= 3,
                    "{camera}/{lens}: pixel {px:?}, expected about {colour:?} (BGR)"
                );
            }
            seen += 1;
            Ok(())
        })
        .unwrap();
        assert_eq!(seen, FRAMES);
    }

    // IMU: every sample, SI units, KIWI axes, on the video clock (gyro offset applied).
    let got = ImuSeries::read_csv(&layout.imu_csv("left")).unwrap();
    assert_eq!(got.samples().len(), imu.len());
    let g = 9.806_65;
    for (s, (t, c)) in got.samples().iter().zip(&imu) {
        let t_video = (*t as i64 - FIRST_FRAME_US) as f64 * 1e-6 - GYRO_OFFSET_MS * 1e-3;
        assert!((s.t - t_video).abs() < 1e-9, "t {} vs {t_video}", s.t);
        let v = |i: usize| f64::from(c[i]) - 32768.0;
        let accel = x5_axes([v(0), v(1), v(2)]).map(|x| x * 32.0 / 32768.0 * g);
        let gyro = x5_axes([v(3), v(4), v(5)])
            .map(|x| x * 2000.0 / 32768.0 * std::f64::consts::PI / 180.0);
        for i in 0..3 {
            assert!(
                (s.accel[i] - accel[i]).abs() < 1e-9,
                "accel {:?} vs {accel:?}",
                s.accel
            );
            assert!(
                (s.gyro[i] - gyro[i]).abs() < 1e-12,
                "gyro {:?} vs {gyro:?}",
                s.gyro
            );
        }
    }
    let head = ImuSeries::read_csv(&layout.imu_csv("head")).unwrap();
    assert_eq!(head.samples().len(), float_imu.len());
    for (s, (t, a, w)) in head.samples().iter().zip(&float_imu) {
        assert!((s.t - (*t as f64 - 5000.0) * 1e-3).abs() < 1e-9);
        for i in 0..3 {
            assert!((s.accel[i] - a[i] * g).abs() < 1e-9);
            assert!((s.gyro[i] - w[i]).abs() < 1e-12);
        }
    }

    // Audio: the file's samples, shifted by the track's start, sample 0 at video time 0.
    let delay = (AUDIO_DELAY_S * f64::from(AUDIO_RATE)).round() as usize;
    for camera in ["left", "head"] {
        let got = wav_samples(&layout.audio_wav(camera));
        assert!(
            got[..delay].iter().all(|&v| v == 0),
            "{camera}: silence before the track"
        );
        assert_eq!(
            &got[delay..],
            &audio[..got.len() - delay],
            "{camera}: audio to the sample"
        );
    }

    // Metadata and exposure times.
    let meta = layout.read_meta("left").unwrap();
    let rec = meta.recording.unwrap();
    assert_eq!(meta.camera_model, "Insta360 X5");
    assert_eq!(rec.firmware, "v1.10.9_build1");
    assert_eq!(rec.lenses[0].native_resolution, [SIDE, SIDE]);
    assert!((rec.lenses[0].scale - 64.0 / f64::from(SIDE)).abs() < 1e-12);
    assert_eq!(rec.imu.axis_map, "-y,-z,+x");
    assert!(rec.lens_calibration_strings.contains_key("offset_v3"));
    assert!((meta.fps - FPS).abs() < 1e-6);
    let exposure = std::fs::read_to_string(layout.camera_dir("left").join("exposure.csv")).unwrap();
    assert_eq!(exposure.lines().count(), FRAMES + 4 + 1);
}

#[test]
fn split_recordings_and_lens_file_pairs_are_joined() {
    let tmp = tempfile::tempdir().unwrap();
    let audio = audio_samples(AUDIO_RATE as usize * 3);
    let wav = tmp.path().join("audio.wav");
    write_wav(&wav, &audio);
    // Two segments, each a _00_/_10_ pair; the second starts where the first ends.
    let n1 = 30;
    let second_us = FIRST_FRAME_US + (n1 as f64 / FPS * 1e6).round() as i64;
    let mut files = Vec::new();
    for (seq, first_us, frames) in [(7, FIRST_FRAME_US, n1), (8, second_us, 20)] {
        for (code, colour) in [("00", "red"), ("10", "blue")] {
            let f = tmp
                .path()
                .join(format!("VID_20260101_120000_{code}_{seq:03}.insv"));
            recording(&f, &[colour], frames, Some(&wav), &[]);
            trailer(
                "Insta360 X5",
                TrailerImu::Raw(raw_imu(first_us, frames)),
                first_us,
                TrailerLayout::Indexed,
            )
            .append_to(&f)
            .unwrap();
            files.push(f);
        }
    }
    files.reverse(); // the order given does not matter
    let toml = session(&tmp.path().join("s"), false);
    let report = ingest_episode(
        &toml,
        "ep001",
        &[CameraInput {
            camera: "left".into(),
            files,
            imu_csv: None,
        }],
        &options(LensOutput::Images),
    )
    .unwrap();
    let layout = EpisodeLayout::new(&report.episode_dir);
    for lens in ["front", "rear"] {
        let src = FrameSource::open(&layout.lens_dir("left", lens)).unwrap();
        assert_eq!(src.len(), 50);
        for (k, f) in src.frames().iter().enumerate() {
            assert!(
                (f.t - k as f64 / FPS).abs() < 1e-9,
                "{lens} frame {k}: {}",
                f.t
            );
        }
        // PNG output: the front lens is the _00_ file (red).
        let img = src.load_color(40).unwrap();
        let red = img.bgr[2] > 200 && img.bgr[0] < 50;
        assert_eq!(red, lens == "front", "{lens}: {:?}", &img.bgr[..3]);
    }
    let imu = ImuSeries::read_csv(&layout.imu_csv("left")).unwrap();
    let dt: Vec<f64> = imu.samples().windows(2).map(|w| w[1].t - w[0].t).collect();
    assert!(
        dt.iter().all(|d| *d > 0.0 && *d < 1.5e-3),
        "IMU continuous across segments"
    );
    let audio_got = wav_samples(&layout.audio_wav("left"));
    let second_start = (n1 as f64 / FPS * f64::from(AUDIO_RATE)).round() as usize
        + (AUDIO_DELAY_S * f64::from(AUDIO_RATE)).round() as usize;
    assert_eq!(
        audio_got[second_start], audio[0],
        "the second segment's audio is placed"
    );
}

fn ingest_err(files: Vec<PathBuf>, imu_csv: Option<PathBuf>) -> BackendError {
    let tmp = tempfile::tempdir().unwrap();
    let toml = session(&tmp.path().join("s"), false);
    let e = ingest_episode(
        &toml,
        "ep001",
        &[CameraInput {
            camera: "left".into(),
            files,
            imu_csv,
        }],
        &options(LensOutput::Video(VideoCodec::Utvideo)),
    )
    .unwrap_err();
    assert!(
        !tmp.path().join("s/episodes/ep001").exists(),
        "a failed ingest leaves no episode"
    );
    e
}

#[test]
fn known_field_failures_have_named_errors() {
    let tmp = tempfile::tempdir().unwrap();
    let wav = tmp.path().join("audio.wav");
    write_wav(&wav, &audio_samples(AUDIO_RATE as usize * 2));

    // X5 firmware that writes no gyro record.
    let no_gyro = tmp.path().join("VID_20260101_120000_00_001.insv");
    recording(&no_gyro, &["red", "blue"], 10, Some(&wav), &[]);
    trailer(
        "Insta360 X5",
        TrailerImu::None,
        FIRST_FRAME_US,
        TrailerLayout::Indexed,
    )
    .append_to(&no_gyro)
    .unwrap();
    let e = ingest_err(vec![no_gyro], None);
    assert!(matches!(e, BackendError::NoGyroRecord { .. }), "{e}");
    assert!(
        e.to_string().contains("v1.10.9_build1") && e.to_string().contains("firmware"),
        "{e}"
    );

    // No audio track.
    let silent = tmp.path().join("VID_20260101_120000_00_002.insv");
    recording(&silent, &["red", "blue"], 10, None, &[]);
    trailer(
        "Insta360 X5",
        TrailerImu::Raw(raw_imu(FIRST_FRAME_US, 10)),
        FIRST_FRAME_US,
        TrailerLayout::Indexed,
    )
    .append_to(&silent)
    .unwrap();
    let e = ingest_err(vec![silent], None);
    assert!(matches!(e, BackendError::MissingAudio { .. }), "{e}");

    // One lens track only.
    let one = tmp.path().join("VID_20260101_120000_00_003.insv");
    recording(&one, &["red"], 10, Some(&wav), &[]);
    trailer(
        "Insta360 X5",
        TrailerImu::Raw(raw_imu(FIRST_FRAME_US, 10)),
        FIRST_FRAME_US,
        TrailerLayout::Indexed,
    )
    .append_to(&one)
    .unwrap();
    let e = ingest_err(vec![one], None);
    assert!(
        matches!(
            e,
            BackendError::MissingLensTrack {
                found: 1,
                expected: 2,
                ..
            }
        ),
        "{e}"
    );

    // Variable frame rate: frame 10 comes 40 ms late (a generic file with an IMU CSV).
    let vfr = tmp.path().join("vfr.mov");
    recording(
        &vfr,
        &["red", "blue"],
        20,
        Some(&wav),
        &[
            "-vf",
            "setpts=PTS+if(gte(N\\,10)\\,0.04/TB\\,0)",
            "-fps_mode",
            "passthrough",
        ],
    );
    let imu = tmp.path().join("imu.csv");
    std::fs::write(
        &imu,
        "t,gx,gy,gz,ax,ay,az\n0,0,0,0,0,0,9.8\n0.01,0,0,0,0,0,9.8\n",
    )
    .unwrap();
    let e = ingest_err(vec![vfr], Some(imu));
    assert!(
        matches!(e, BackendError::VariableFrameRate { frame: 10, .. }),
        "{e}"
    );
    println!("{e}");
}
