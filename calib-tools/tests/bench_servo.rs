#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]
//! End-to-end: record the simulated servo on a pseudo-terminal through every injected fault
//! (silence, corrupted checksum, wrong id, unplug/replug) and check that no reply the servo
//! sent is lost and every fault is counted.

use std::time::Duration;

use kiwi_calib::bench::fake::{FakeServo, FakeServoConfig, Fault};
use kiwi_calib::bench::record::{ENCODER_CSV, REPORT_JSON, RecordConfig, record};

#[test]
fn records_through_every_fault_without_losing_a_sample() {
    let dir = tempfile::tempdir().unwrap();
    let link = dir.path().join("servo");
    let mut fake = FakeServoConfig::new(1, &link);
    // Request 0 is the recorder's torque-off; then one read per period (plus retries).
    fake.faults = vec![
        (10, Fault::Silence),
        (20, Fault::CorruptChecksum),
        (30, Fault::WrongId),
        (40, Fault::Unplug),
        (60, Fault::Silence),
        (70, Fault::CorruptChecksum),
        (80, Fault::WrongId),
    ];
    fake.unplug = Duration::from_millis(300);
    let servo = FakeServo::start(fake).unwrap();

    let mut config = RecordConfig::new(link.to_str().unwrap(), 1);
    config.rate_hz = 50.0;
    config.duration_s = 2.5;
    config.timeout = Duration::from_millis(15);
    let out = dir.path().join("rec");
    let mut ticks_seen = 0;
    let report = record(&config, &out, &mut |r| ticks_seen = r.ticks).unwrap();
    let stats = servo.stop();
    eprintln!("{report:#?}\n{stats:#?}");

    // Every fault happened and was counted by kind.
    assert_eq!(stats.silences, 2);
    assert_eq!(stats.corrupted, 2);
    assert_eq!(stats.wrong_ids, 2);
    assert_eq!(stats.unplugs, 1);
    assert_eq!(report.bad_checksums, 2);
    assert_eq!(report.wrong_ids, 2);
    assert!(report.disconnects >= 1, "{report:?}");
    assert_eq!(report.reconnects, 1);
    // The two silences time out (the unplug is a disconnect); a loaded machine may add more.
    assert!(report.timeouts >= 2, "{report:?}");
    let spurious = report.timeouts - 2;

    // The log holds exactly the positions the servo sent in clean replies, in order.
    let text = std::fs::read_to_string(out.join(ENCODER_CSV)).unwrap();
    let mut lines = text.lines();
    assert_eq!(lines.next(), Some("t,raw,angle_rad"));
    let rows: Vec<(f64, u16, f64)> = lines
        .map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            (
                f[0].parse().unwrap(),
                f[1].parse().unwrap(),
                f[2].parse().unwrap(),
            )
        })
        .collect();
    assert_eq!(rows.len() as u64, report.samples);
    assert!(rows.windows(2).all(|w| w[1].0 > w[0].0), "times increase");
    for &(_, raw, angle) in &rows {
        let expect = f64::from(raw) / 4096.0 * std::f64::consts::TAU;
        assert!((angle - expect).abs() < 1e-6);
    }
    let recorded: Vec<u16> = rows.iter().map(|r| r.1).collect();
    if spurious == 0 {
        assert_eq!(recorded, stats.served_positions, "no lost sample");
    } else {
        // Replies that arrived after their timeout were discarded: at most that many.
        assert!(stats.served_positions.len() as u64 - recorded.len() as u64 <= spurious);
    }
    // Only the periods while the device was gone have no sample: 300 ms at 50 Hz ≈ 15.
    assert_eq!(report.ticks, report.samples + report.missed);
    assert!(report.missed <= 25, "{report:?}");
    assert!(report.samples >= 100, "{report:?}");
    assert_eq!(ticks_seen, report.ticks);
    assert!(report.longest_gap_s > 0.25 && report.longest_gap_s < 0.6);

    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join(REPORT_JSON)).unwrap()).unwrap();
    assert_eq!(json["bad_checksums"], 2);
    assert_eq!(json["reconnects"], 1);

    // An existing recording is never overwritten.
    assert!(record(&config, &out, &mut |_| {}).is_err());
}

#[test]
fn a_missing_device_is_waited_for_then_recorded() {
    let dir = tempfile::tempdir().unwrap();
    let link = dir.path().join("late");
    let mut config = RecordConfig::new(link.to_str().unwrap(), 1);
    config.rate_hz = 50.0;
    config.duration_s = 1.0;
    let out = dir.path().join("rec");
    let link2 = link.clone();
    let starter = std::thread::spawn(move || {
        std::thread::sleep(Duration::from_millis(300));
        FakeServo::start(FakeServoConfig::new(1, &link2)).unwrap()
    });
    let report = record(&config, &out, &mut |_| {}).unwrap();
    let servo = starter.join().unwrap();
    let stats = servo.stop();
    assert!(report.missed >= 10, "{report:?}");
    assert!(report.samples >= 25, "{report:?}");
    // Every recorded sample was served; the request in flight when the recording ended may
    // have been answered without being recorded.
    let served = stats.served_positions.len();
    assert!(
        served == report.samples as usize || served == report.samples as usize + 1,
        "served {served}, recorded {}",
        report.samples
    );
    assert_eq!(report.reconnects, 0);
}

/// Run `f` on another thread; fail if it does not return in `limit` (a hang fails the test
/// instead of blocking the test run).
fn within<T: Send + 'static>(limit: Duration, f: impl FnOnce() -> T + Send + 'static) -> T {
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let _ = tx.send(f());
    });
    rx.recv_timeout(limit)
        .expect("hung: a thread waits on one that failed")
}

#[test]
fn the_servo_thread_stops_while_a_client_is_mid_request() {
    // The consumer (the servo thread) is stopped while the producer (a client) has sent half a
    // request and still holds the port open.
    let dir = tempfile::tempdir().unwrap();
    let link = dir.path().join("servo");
    let servo = FakeServo::start(FakeServoConfig::new(1, &link)).unwrap();
    let mut port = kiwi_calib::bench::servo::open_port(
        link.to_str().unwrap(),
        1_000_000,
        Duration::from_millis(50),
    )
    .unwrap();
    std::io::Write::write_all(&mut port, &[0xFF, 0xFF, 0x01]).unwrap();
    let stats = within(Duration::from_secs(10), move || servo.stop());
    assert_eq!(stats.served_positions.len(), 0);
    drop(port);
}

#[test]
fn a_servo_that_dies_mid_recording_ends_the_recording_on_time() {
    // The producer (the servo) goes away for good mid-stream: the recorder keeps its clock,
    // counts the missed periods and ends at its duration.
    let dir = tempfile::tempdir().unwrap();
    let link = dir.path().join("servo");
    let servo = FakeServo::start(FakeServoConfig::new(1, &link)).unwrap();
    let mut config = RecordConfig::new(link.to_str().unwrap(), 1);
    config.rate_hz = 50.0;
    config.duration_s = 1.5;
    config.timeout = Duration::from_millis(15);
    let out = dir.path().join("rec");
    let killer = std::thread::spawn(move || {
        std::thread::sleep(Duration::from_millis(500));
        servo.stop()
    });
    let started = std::time::Instant::now();
    let report = within(Duration::from_secs(20), move || {
        record(&config, &out, &mut |_| {}).unwrap()
    });
    let stats = killer.join().unwrap();
    assert!(
        started.elapsed() < Duration::from_secs(5),
        "{:?}",
        started.elapsed()
    );
    assert!(report.samples >= 10 && report.missed >= 20, "{report:?}");
    // A reply in flight when the servo stopped may be lost, never invented.
    assert!(report.samples as usize <= stats.served_positions.len());
}
