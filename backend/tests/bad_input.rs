#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]
//! `kiwi` on bad input: a tiny simulated session (64 px, 1 s), broken in one way per case.
//! Every case fails (non-zero exit, within a timeout: nothing hangs), its message names the
//! file or field, and nothing is written or changed (the folders hashed before and after).

use std::path::{Path, PathBuf};

use kiwi_core::imu::{ImuSeries, write_imu_csv};
use kiwi_core::layout::{EpisodeLayout, Session};
use kiwi_fixtures::check::{Case, run_all, snapshot};
use kiwi_fixtures::session::{SessionOptions, write_session};

const KIWI: &str = env!("CARGO_BIN_EXE_kiwi");

fn s(p: &Path) -> String {
    p.display().to_string()
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        let target = to.join(e.file_name());
        if e.path().is_dir() {
            copy_dir(&e.path(), &target);
        } else {
            std::fs::copy(e.path(), &target).unwrap();
        }
    }
}

/// A copy of the session in `<root>/<name>`, changed by `edit(session_root, episode_layout)`.
fn variant(
    base: &Path,
    root: &Path,
    name: &str,
    edit: impl FnOnce(&Path, &EpisodeLayout),
) -> PathBuf {
    let dir = root.join(name);
    copy_dir(base, &dir);
    let layout = EpisodeLayout::new(dir.join("episodes").join("ep000"));
    edit(&dir, &layout);
    dir
}

fn frame(layout: &EpisodeLayout, camera: &str, lens: &str, i: usize) -> PathBuf {
    layout
        .lens_dir(camera, lens)
        .join(EpisodeLayout::frame_file_name(i))
}

fn map_imu(layout: &EpisodeLayout, camera: &str, f: impl Fn(&mut kiwi_core::imu::ImuSample)) {
    let path = layout.imu_csv(camera);
    let mut samples = ImuSeries::read_csv(&path).unwrap().samples().to_vec();
    samples.iter_mut().for_each(f);
    write_imu_csv(&path, &samples).unwrap();
}

#[test]
fn kiwi_refuses_bad_input_and_writes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    let base = root.join("base");
    let mut o = SessionOptions::new(&base);
    o.resolution = 64;
    o.duration_s = 1.0;
    o.head = false;
    o.noise_sigma = 0.0;
    let summary = write_session(&o).unwrap();
    let kiwi = Path::new(KIWI);

    // The intact session passes inspect (and inspect writes nothing).
    let before = snapshot(&base);
    let ok = std::process::Command::new(KIWI)
        .args(["inspect", &s(&summary.session_toml)])
        .output()
        .unwrap();
    let said =
        String::from_utf8_lossy(&ok.stdout).into_owned() + &String::from_utf8_lossy(&ok.stderr);
    assert!(ok.status.success(), "{said}");
    assert!(said.contains("no problem found"), "{said}");
    assert_eq!(snapshot(&base), before);

    let session = Session::load(&summary.session_toml).unwrap();
    let left_cal = base.join(&session.wrists.values().next().unwrap().calibration);
    let right_cal = base.join(&session.wrists.values().nth(1).unwrap().calibration);
    let toml = |d: &Path| s(&d.join("session.toml"));

    let missing = variant(&base, root, "missing", |_, l| {
        std::fs::remove_file(frame(l, "left", "front", 60)).unwrap();
    });
    let corrupt = variant(&base, root, "corrupt", |_, l| {
        std::fs::write(frame(l, "left", "rear", 61), b"\x89PNG\r\n\x1a\nnot really").unwrap();
    });
    let resized = variant(&base, root, "resized", |_, l| {
        image::GrayImage::new(80, 80)
            .save(frame(l, "right", "front", 5))
            .unwrap();
    });
    let nan = variant(&base, root, "nan", |_, l| {
        let path = l.imu_csv("left");
        let text = std::fs::read_to_string(&path).unwrap();
        let mut lines: Vec<String> = text.lines().map(str::to_string).collect();
        let fields: Vec<String> = lines[200].split(',').map(str::to_string).collect();
        lines[200] = format!("{},NaN,0,0,0,0,9.81", fields[0]);
        std::fs::write(&path, lines.join("\n") + "\n").unwrap();
    });
    let truncated = variant(&base, root, "truncated", |_, l| {
        let path = l.audio_wav("right");
        let bytes = std::fs::read(&path).unwrap();
        std::fs::write(&path, &bytes[..bytes.len() / 2]).unwrap();
    });
    let text_wav = variant(&base, root, "textwav", |_, l| {
        std::fs::write(l.audio_wav("left"), "this is not audio").unwrap();
    });
    let in_g = variant(&base, root, "in_g", |_, l| {
        map_imu(l, "right", |x| x.accel /= 9.80665);
    });
    let in_ms = variant(&base, root, "in_ms", |_, l| {
        map_imu(l, "left", |x| x.t *= 1000.0);
    });
    let bad_tool = variant(&base, root, "badtool", |d, _| {
        let path = d.join("session.toml");
        let text = std::fs::read_to_string(&path).unwrap();
        let text = text.replacen("tool = \"chopstick\"", "tool = \"spoon\"", 1);
        std::fs::write(&path, text).unwrap();
    });
    let swapped = variant(&base, root, "swapped", |_, l| {
        let mut meta = l.read_meta("right").unwrap();
        meta.unit_id = l.read_meta("left").unwrap().unit_id;
        l.write_meta(&meta).unwrap();
    });
    let backwards = variant(&base, root, "backwards", |_, l| {
        let path = l.frames_csv("left", "front");
        let text = std::fs::read_to_string(&path).unwrap();
        let mut lines: Vec<&str> = text.lines().collect();
        lines.swap(10, 11);
        std::fs::write(&path, lines.join("\n") + "\n").unwrap();
    });

    let ep = |d: &Path| s(&d.join("episodes").join("ep000"));
    let out = root.join("out");
    let o = |name: &str| s(&out.join(name));

    // Files for the estimation commands.
    let files = root.join("files");
    std::fs::create_dir_all(&files).unwrap();
    let random_kmap = files.join("random.kmap");
    std::fs::write(
        &random_kmap,
        (0..2048u32)
            .map(|i| (i * 7919 % 256) as u8)
            .collect::<Vec<_>>(),
    )
    .unwrap();
    let text_kmap = files.join("notes.kmap");
    std::fs::write(&text_kmap, "notes about the map").unwrap();
    let poses = files.join("poses.csv");
    std::fs::write(
        &poses,
        "t,status,px,py,pz,qx,qy,qz,qw\n0.0,lost,,,,,,,\n0.1,lost,,,,,,,\n",
    )
    .unwrap();
    let obs = files.join("obs.csv");
    std::fs::write(&obs, "t,source,px,py,pz,qx,qy,qz,qw\n").unwrap();
    let text_wav_file = files.join("text.wav");
    std::fs::write(&text_wav_file, "RIFF but not really").unwrap();
    let g_imu = s(&EpisodeLayout::new(in_g.join("episodes/ep000")).imu_csv("right"));
    let ms_imu = s(&EpisodeLayout::new(in_ms.join("episodes/ep000")).imu_csv("left"));
    let base_layout = EpisodeLayout::new(base.join("episodes/ep000"));
    let frames_csv = s(&base_layout.frames_csv("left", "front"));
    let left_wav = s(&base_layout.audio_wav("left"));
    let right_wav = s(&base_layout.audio_wav("right"));
    let left_cal_json = s(&left_cal.join("calibration.json"));
    let right_cal_json = s(&right_cal.join("calibration.json"));
    // Earlier gripper outputs that must not be replaced silently.
    let earlier = out.join("earlier");
    std::fs::create_dir_all(&earlier).unwrap();
    std::fs::write(
        earlier.join("opening.csv"),
        "t,opening,unit,confidence,status\n",
    )
    .unwrap();

    let mut cases = vec![
        // Item 5: inspect checks every file it claims to.
        Case::new(
            "inspect, missing middle frame",
            kiwi,
            &["inspect", &toml(&missing)],
        )
        .says(&["left/front/frames/000060.png", "no such file"]),
        Case::new(
            "inspect, corrupt frame",
            kiwi,
            &["inspect", &toml(&corrupt)],
        )
        .says(&["left/rear/frames/000061.png", "readable image"]),
        Case::new(
            "inspect, wrong-size frame",
            kiwi,
            &["inspect", &toml(&resized)],
        )
        .says(&["right/front/frames/000005.png", "64×64", "80×80"]),
        Case::new(
            "inspect --deep, wrong-size frame",
            kiwi,
            &["inspect", "--deep", &toml(&resized)],
        )
        .says(&["000005.png", "80×80"]),
        Case::new("inspect, NaN in imu.csv", kiwi, &["inspect", &toml(&nan)]).says(&[
            "left/imu.csv",
            "line 201",
            "finite",
        ]),
        Case::new(
            "inspect, truncated WAV",
            kiwi,
            &["inspect", &toml(&truncated)],
        )
        .says(&["right/audio.wav", "truncated"]),
        Case::new("inspect, text WAV", kiwi, &["inspect", &toml(&text_wav)])
            .says(&["left/audio.wav", "not a readable WAV"]),
        Case::new(
            "inspect, accelerometer in g",
            kiwi,
            &["inspect", &toml(&in_g)],
        )
        .says(&["right/imu.csv", "in g"]),
        Case::new(
            "inspect, IMU times in ms",
            kiwi,
            &["inspect", &toml(&in_ms)],
        )
        .says(&["left/imu.csv", "milliseconds"]),
        Case::new(
            "inspect, frames out of order",
            kiwi,
            &["inspect", &toml(&backwards)],
        )
        .says(&["left/front/frames.csv", "line 12"]),
        Case::new(
            "inspect, other wrist's unit",
            kiwi,
            &["inspect", &toml(&swapped)],
        )
        .says(&["right/meta.json", "recorded by unit"]),
        // Item 7: messages that name the file, the field and the fix.
        Case::new(
            "inspect, a folder as session.toml",
            kiwi,
            &["inspect", &s(&base)],
        )
        .says(&["is a folder", "session.toml"]),
        Case::new(
            "inspect, unknown tool",
            kiwi,
            &["inspect", &toml(&bad_tool)],
        )
        .says(&["session.toml", "wrists.left.tool", "line", "spoon"]),
        Case::new(
            "localize, random-bytes map",
            kiwi,
            &[
                "localize",
                "--map",
                &s(&random_kmap),
                "--episode",
                &ep(&base),
                "--lens",
                "rear",
                "--camera",
                "left",
                "--out",
                &o("poses.csv"),
            ],
        )
        .says(&["random.kmap", "binary data", "kiwi map"]),
        Case::new(
            "localize, a text file as map",
            kiwi,
            &[
                "localize",
                "--map",
                &s(&text_kmap),
                "--episode",
                &ep(&base),
                "--lens",
                "rear",
                "--camera",
                "left",
                "--out",
                &o("poses2.csv"),
            ],
        )
        .says(&["notes.kmap", "found text starting"]),
        Case::new(
            "metric, a folder as poses",
            kiwi,
            &[
                "metric",
                "--poses",
                &s(&files),
                "--imu",
                &g_imu,
                "--calibration",
                &right_cal_json,
                "--out",
                &o("metric.json"),
            ],
        )
        .says(&["files", "folder"]),
        // Item 1: a wrong-size frame ends the mapper with an error, not a hang.
        Case::new(
            "map, wrong-size frame",
            kiwi,
            &[
                "map",
                "--episode",
                &ep(&resized),
                "--lens",
                "front",
                "--camera",
                "right",
                "--out",
                &o("right_front.kmap"),
            ],
        )
        .says(&["000005.png", "80×80", "64×64"]),
        // Item 3: nothing writes into a dated set.
        Case::new(
            "map into a dated set",
            kiwi,
            &[
                "map",
                "--episode",
                &ep(&base),
                "--lens",
                "front",
                "--camera",
                "left",
                "--out",
                &s(&left_cal.join("front.kmap")),
            ],
        )
        .says(&["dated calibration set"]),
        Case::new(
            "gripper --calibrate into a dated set",
            kiwi,
            &[
                "gripper",
                "--episode",
                &ep(&base),
                "--camera",
                "left",
                "--calibration",
                &left_cal_json,
                "--tool",
                "chopstick",
                "--calibrate",
                "--out",
                &s(&left_cal.join("tool.json")),
            ],
        )
        .says(&["dated calibration set"]),
        // Item 5: gripper checks the unit and never replaces its outputs silently.
        Case::new(
            "gripper, other wrist's calibration",
            kiwi,
            &[
                "gripper",
                "--episode",
                &ep(&base),
                "--camera",
                "left",
                "--calibration",
                &right_cal_json,
                "--tool",
                "chopstick",
                "--out",
                &o("grip"),
            ],
        )
        .says(&["left/meta.json", "recorded by unit", "other wrist"]),
        Case::new(
            "gripper, earlier output",
            kiwi,
            &[
                "gripper",
                "--episode",
                &ep(&base),
                "--camera",
                "left",
                "--calibration",
                &left_cal_json,
                "--tool",
                "chopstick",
                "--out",
                &s(&earlier),
            ],
        )
        .says(&["opening.csv", "--overwrite"]),
        // Item 5: sync.
        Case::new(
            "sync, --av-delay for no camera",
            kiwi,
            &[
                "sync",
                "--audio",
                &format!("left={left_wav}"),
                "--audio",
                &format!("right={right_wav}"),
                "--av-delay",
                "lfet=0.012",
            ],
        )
        .says(&["--av-delay", "lfet", "left, right"]),
        Case::new(
            "sync, --mode for no camera",
            kiwi,
            &[
                "sync",
                "--audio",
                &format!("left={left_wav}"),
                "--audio",
                &format!("right={right_wav}"),
                "--mode",
                "head=30fps",
            ],
        )
        .says(&["--mode", "head"]),
        Case::new(
            "sync, text as WAV",
            kiwi,
            &[
                "sync",
                "--audio",
                &format!("left={left_wav}"),
                "--audio",
                &format!("right={}", s(&text_wav_file)),
            ],
        )
        .says(&["text.wav", "not a readable WAV"]),
        Case::new(
            "sync, a folder as WAV",
            kiwi,
            &[
                "sync",
                "--audio",
                &format!("left={left_wav}"),
                "--audio",
                &format!("right={}", s(&files)),
            ],
        )
        .says(&["files", "folder"]),
        Case::new(
            "sync, one camera",
            kiwi,
            &["sync", "--audio", &format!("left={left_wav}")],
        )
        .says(&["at least two"]),
        Case::new(
            "sync, a camera twice",
            kiwi,
            &[
                "sync",
                "--audio",
                &format!("left={left_wav}"),
                "--audio",
                &format!("left={right_wav}"),
            ],
        )
        .says(&["twice"]),
        // Item 5: fuse options; item 2: units in the IMU log.
        Case::new(
            "fuse --visual-rate 0",
            kiwi,
            &[
                "fuse",
                "--imu",
                &g_imu,
                "--frames",
                &frames_csv,
                "--observations",
                &s(&obs),
                "--imu-noise",
                "1e-4,1e-5,1e-3,1e-4",
                "--visual-rate",
                "0",
                "--out",
                &o("t.csv"),
            ],
        )
        .says(&["--visual-rate", "> 0"]),
        Case::new(
            "fuse --visual-rate=-5",
            kiwi,
            &[
                "fuse",
                "--imu",
                &g_imu,
                "--frames",
                &frames_csv,
                "--observations",
                &s(&obs),
                "--imu-noise",
                "1e-4,1e-5,1e-3,1e-4",
                "--visual-rate=-5",
                "--out",
                &o("t.csv"),
            ],
        )
        .says(&["--visual-rate", "> 0"]),
        Case::new(
            "fuse, accelerometer in g",
            kiwi,
            &[
                "fuse",
                "--imu",
                &g_imu,
                "--frames",
                &frames_csv,
                "--observations",
                &s(&obs),
                "--imu-noise",
                "1e-4,1e-5,1e-3,1e-4",
                "--out",
                &o("t.csv"),
            ],
        )
        .says(&["right/imu.csv", "in g", "9.80665"]),
        Case::new(
            "fuse, IMU times in ms",
            kiwi,
            &[
                "fuse",
                "--imu",
                &ms_imu,
                "--frames",
                &frames_csv,
                "--observations",
                &s(&obs),
                "--imu-noise",
                "1e-4,1e-5,1e-3,1e-4",
                "--out",
                &o("t.csv"),
            ],
        )
        .says(&["left/imu.csv", "milliseconds"]),
        Case::new(
            "metric, accelerometer in g",
            kiwi,
            &[
                "metric",
                "--poses",
                &s(&poses),
                "--imu",
                &g_imu,
                "--calibration",
                &right_cal_json,
                "--out",
                &o("metric.json"),
            ],
        )
        .says(&["right/imu.csv", "in g"]),
    ];
    // Each case watches the outputs' folders, the base session and the variant it reads.
    let variants = [
        &missing, &corrupt, &resized, &nan, &truncated, &text_wav, &in_g, &in_ms, &bad_tool,
        &swapped, &backwards,
    ];
    for c in &mut cases {
        let used = variants
            .iter()
            .filter(|v| c.args.iter().any(|a| a.contains(&s(v))))
            .map(|v| (*v).clone());
        c.watched = used
            .chain([base.clone(), out.clone(), files.clone()])
            .collect();
    }
    let ran = run_all(&cases);
    assert!(ran >= 30, "{ran}");
}

#[test]
fn kiwi_run_ends_when_a_stage_fails_mid_stream() {
    // A wrong-size frame in the middle of the mapping episode: the map stage fails, the
    // stages that need it are blocked with the reason, and the run ends (timeout = hang).
    let dir = tempfile::tempdir().unwrap();
    let base = dir.path().join("s");
    let mut o = SessionOptions::new(&base);
    o.resolution = 64;
    o.duration_s = 1.0;
    o.head = false;
    let summary = write_session(&o).unwrap();
    let layout = EpisodeLayout::new(base.join("episodes/ep000"));
    image::GrayImage::new(80, 80)
        .save(frame(&layout, "left", "front", 4))
        .unwrap();
    let case = Case::new(
        "run, wrong-size frame",
        Path::new(KIWI),
        &["run", "--session", &s(&summary.session_toml)],
    )
    .says(&["000004.png", "80×80"]);
    case.run().unwrap();
}

/// A progress display that fails (panics) mid-run: on the third stage it is told about and on
/// every progress update after the tenth. The runner's workers wait on one another through a
/// condition variable; a stage whose consumer failed must still be decided, or they wait forever.
struct FailingProgress {
    starts: std::sync::atomic::AtomicUsize,
    updates: std::sync::atomic::AtomicUsize,
}

impl kiwi_backend::pipeline::runner::Progress for FailingProgress {
    fn start(&self, _: &kiwi_backend::pipeline::stage::StageId) {
        if self
            .starts
            .fetch_add(1, std::sync::atomic::Ordering::SeqCst)
            == 2
        {
            panic!("progress display failed at a stage start");
        }
    }
    fn update(&self, _: &kiwi_backend::pipeline::stage::StageId, _: usize, _: usize) {
        if self
            .updates
            .fetch_add(1, std::sync::atomic::Ordering::SeqCst)
            >= 10
        {
            panic!("progress display failed mid-stage");
        }
    }
    fn finish(
        &self,
        _: &kiwi_backend::pipeline::stage::StageId,
        _: &kiwi_backend::pipeline::runner::Outcome,
    ) {
    }
}

#[test]
fn the_run_scheduler_ends_when_a_consumer_fails_mid_run() {
    use kiwi_backend::pipeline::runner::{Outcome, RunOptions, run};
    let dir = tempfile::tempdir().unwrap();
    let base = dir.path().join("s");
    let mut o = SessionOptions::new(&base);
    o.resolution = 64;
    o.duration_s = 1.0;
    o.head = false;
    let summary = write_session(&o).unwrap();
    let (tx, rx) = std::sync::mpsc::channel();
    let session_toml = summary.session_toml.clone();
    std::thread::spawn(move || {
        let ctx = kiwi_backend::pipeline::SessionContext::load(&session_toml).unwrap();
        let progress = FailingProgress {
            starts: 0.into(),
            updates: 0.into(),
        };
        let options = RunOptions {
            threads: Some(2),
            ..RunOptions::default()
        };
        let _ = tx.send(run(&ctx, &options, &progress).map_err(|e| e.to_string()));
    });
    let report = rx
        .recv_timeout(std::time::Duration::from_secs(120))
        .expect("the run hung after its progress display failed")
        .unwrap();
    // Every stage was decided: none is left waiting, and the failed ones say why.
    assert!(
        report
            .stages
            .iter()
            .all(|s| !matches!(s.outcome, Outcome::Skipped)),
        "{:#?}",
        report.stages
    );
    let failed: Vec<&str> = report
        .stages
        .iter()
        .filter_map(|s| match &s.outcome {
            Outcome::Failed { reason } => Some(reason.as_str()),
            _ => None,
        })
        .collect();
    assert!(
        failed.iter().any(|r| r.contains("panic")),
        "{:#?}",
        report.stages
    );
    assert!(report.failed_episodes() >= 1);
}
