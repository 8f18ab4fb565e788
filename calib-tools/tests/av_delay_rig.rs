//! A/V delay and optical offsets from the simulated QR-clock rig: two X5-like units and a GO 3-like
//! camera, 60 Hz display, 119.88 and 29.97 fps modes, 10 % of frames with the code covered.
//! 20 s recordings: the cameras' rates beat against the 60 Hz refresh with a 17 s period, and the
//! clock fit needs the frames' refresh phases to cover a full cycle.

#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

use kiwi_calib::av_delay::{AvDelayOptions, analyse, rig_speaker_distances, write_outputs};
use kiwi_fixtures::rig::write_rig;
use kiwi_fixtures::unit::{LensModel, SimUnit};

#[test]
fn rig_gives_av_delays_and_offsets_within_a_millisecond() {
    let dir = tempfile::tempdir().unwrap();
    let units = [
        SimUnit::x5("RIG-A", 1, 320, LensModel::Kb4).unwrap(),
        SimUnit::x5("RIG-B", 2, 320, LensModel::Kb4).unwrap(),
        SimUnit::go3("RIG-G", 3, 320).unwrap(),
    ];
    let rig = dir.path().join("rig");
    let truth = write_rig(&rig, &units, &["119.88fps", "30fps"], 20.0, 4).unwrap();
    let options = AvDelayOptions {
        refresh_hz: 60.0,
        speaker_distance_m: truth
            .cameras
            .iter()
            .map(|c| (c.camera.clone(), c.microphone.propagation_delay_s * 343.0))
            .collect(),
        calibrations: units
            .iter()
            .map(|u| {
                (
                    dir.path().join(&u.unit_id),
                    u.true_calibration("2026-01-01"),
                )
            })
            .collect(),
    };
    let mut normalized = Vec::new();
    for mode in ["119.88fps", "30fps"] {
        let cams: Vec<_> = truth.cameras.iter().filter(|c| c.mode == mode).collect();
        let captures: Vec<_> = cams
            .iter()
            .map(|c| rig.join(mode).join(&c.camera))
            .collect();
        // Speaker distances are per capture folder name, which repeat across modes. The fast
        // mode takes them from the rig's measured geometry (rig.toml beside the camera
        // folders), the other from the options, as `--speaker-distance` passes them.
        let mut opts = options.clone();
        let distances: Vec<(String, f64)> = cams
            .iter()
            .map(|c| (c.camera.clone(), c.microphone.propagation_delay_s * 343.0))
            .collect();
        let from_file = mode == "119.88fps";
        if from_file {
            let mut toml = String::from("[speaker_distance_m]\n");
            for (camera, d) in &distances {
                toml.push_str(&format!("{camera} = {d}\n"));
            }
            std::fs::write(rig.join(mode).join("rig.toml"), toml).unwrap();
            opts.speaker_distance_m = Vec::new();
        } else {
            opts.speaker_distance_m = distances.clone();
        }
        let report = analyse(&captures, &opts).unwrap();
        for ((c, t), (_, d)) in report.captures.iter().zip(&cams).zip(&distances) {
            println!(
                "{mode} {}: {} of {} frames decoded, A/V delay error {:.3} ms (1σ {:.3} ms)",
                c.name,
                c.decoded,
                c.frames,
                (c.av_delay_s - t.microphone.av_delay_s) * 1e3,
                c.av_delay_std_s * 1e3
            );
            assert_eq!(c.speaker_distance_m, *d, "{}", c.name);
            let source = if from_file { "rig.toml" } else { "option" };
            assert_eq!(c.speaker_distance_source, source, "{}", c.name);
            let err = c.av_delay_s - t.microphone.av_delay_s;
            assert!(
                err.abs() < 1e-3,
                "{mode} {}: d {:.3} ms vs truth {:.3} ms",
                c.name,
                c.av_delay_s * 1e3,
                t.microphone.av_delay_s * 1e3
            );
            // 10 % of frames are covered and some catch a refresh mid-readout; at 320 px the GO 3
            // still decodes about a third.
            assert!(
                c.decoded as f64 > 0.3 * c.frames as f64,
                "{}: {} of {} decoded",
                c.name,
                c.decoded,
                c.frames
            );
            normalized.push(err / c.av_delay_std_s);
        }
        // Video clocks: session = local·(1+δ) + offset + shift·(1+δ).
        let video = |c: &kiwi_fixtures::rig::RigCamera| {
            let m = &c.microphone;
            let rate = 1.0 + m.drift_ppm * 1e-6;
            (m.offset_s + m.video_to_device_s * rate, rate)
        };
        for o in &report.offsets {
            let r = cams.iter().find(|c| c.camera == o.reference).unwrap();
            let k = cams.iter().find(|c| c.camera == o.capture).unwrap();
            let ((or, rr), (ok, rk)) = (video(r), video(k));
            let true_offset = (ok - or) / rr;
            let err = o.offset_s - true_offset;
            assert!(
                err.abs() < 1e-3,
                "{mode} {} vs {}: offset {:.6} vs truth {true_offset:.6}",
                o.capture,
                o.reference,
                o.offset_s
            );
            let drift_err = o.drift_ppm - (rk / rr - 1.0) * 1e6;
            assert!(
                drift_err.abs() < 4.0 * o.drift_std_ppm + 2.0,
                "drift {} ± {} ppm, error {drift_err}",
                o.drift_ppm,
                o.drift_std_ppm
            );
            normalized.push(err / o.offset_std_s);
        }
        assert_eq!(report.offsets.len(), cams.len() - 1);
        let out = dir.path().join(format!("out-{mode}"));
        let written = write_outputs(&report, &opts, &out).unwrap();
        assert!(out.join("report.md").is_file() && written.len() >= 3);
        let updated =
            kiwi_core::artifact::UnitCalibration::load(&out.join("RIG-A").join("calibration.json"))
                .unwrap();
        assert!(
            updated
                .av_delays
                .iter()
                .any(|d| d.mode.ends_with(mode) && d.repeats == 1)
        );
    }
    // Reported standard errors match the actual errors within a factor of 3.
    let rms = (normalized.iter().map(|z| z * z).sum::<f64>() / normalized.len() as f64).sqrt();
    assert!(
        (1.0 / 3.0..=3.0).contains(&rms),
        "normalized error RMS {rms:.2} over {normalized:?}"
    );
}

#[test]
fn a_rig_recording_without_chirps_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let units = [SimUnit::x5("RIG-A", 1, 320, LensModel::Kb4).unwrap()];
    let rig = dir.path().join("rig");
    write_rig(&rig, &units, &["30fps"], 3.0, 5).unwrap();
    // Replace the audio with silence.
    let wav = rig.join("30fps/cam0/audio.wav");
    kiwi_core::audio::write_wav(&wav, &vec![0.0; 48_000 * 3], 48_000).unwrap();
    assert!(rig.join("30fps/cam0/meta.json").is_file());
    let options = AvDelayOptions {
        refresh_hz: 60.0,
        speaker_distance_m: vec![],
        calibrations: vec![(
            dir.path().join("a"),
            units[0].true_calibration("2026-01-01"),
        )],
    };
    let err = analyse(&[rig.join("30fps/cam0")], &options)
        .unwrap_err()
        .to_string();
    assert!(err.contains("chirps"), "{err}");
    // Audio from another (longer) recording is refused by its length.
    kiwi_core::audio::write_wav(&wav, &vec![0.0; 48_000 * 9], 48_000).unwrap();
    let err = analyse(&[rig.join("30fps/cam0")], &options)
        .unwrap_err()
        .to_string();
    assert!(err.contains("same recording"), "{err}");
    // A refresh rate that is no monitor's is refused before any frame is read.
    for refresh_hz in [0.0, -60.0, f64::NAN, 1000.0] {
        let o = AvDelayOptions {
            refresh_hz,
            ..options.clone()
        };
        let err = analyse(&[rig.join("30fps/cam0")], &o)
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("display refresh") && err.contains("cam0"),
            "{err}"
        );
    }
}

#[test]
fn rig_geometry_in_centimetres_is_refused_naming_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let camera = dir.path().join("30fps").join("cam0");
    std::fs::create_dir_all(&camera).unwrap();
    assert!(
        rig_speaker_distances(&camera).unwrap().is_empty(),
        "no rig.toml: no distances"
    );
    let file = dir.path().join("30fps").join("rig.toml");
    std::fs::write(&file, "[speaker_distance_m]\ncam0 = 0.8\ncam1 = 1.25\n").unwrap();
    assert_eq!(
        rig_speaker_distances(&camera).unwrap(),
        vec![("cam0".to_string(), 0.8), ("cam1".to_string(), 1.25)]
    );
    std::fs::write(&file, "[speaker_distance_m]\ncam0 = 80\n").unwrap();
    let err = rig_speaker_distances(&camera).unwrap_err().to_string();
    assert!(
        err.contains("rig.toml") && err.contains("cam0") && err.contains("cm or mm"),
        "{err}"
    );
    std::fs::write(&file, "[speaker_distances]\ncam0 = 0.8\n").unwrap();
    let err = rig_speaker_distances(&camera).unwrap_err().to_string();
    assert!(err.contains("speaker_distance_m"), "{err}");
}
