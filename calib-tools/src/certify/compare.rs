//! Compare a certification with an earlier one of the same unit (the firmware-change case):
//! which parameters moved beyond their combined uncertainty and their practical floor.

use nalgebra::{UnitQuaternion, Vector3};
use serde::Serialize;

use kiwi_core::artifact::UnitCalibration;

use super::policy::ComparePolicy;

/// One compared parameter.
#[derive(Debug, Clone, Serialize)]
pub struct ParamChange {
    /// Parameter name, e.g. `front.intrinsics.fx`, `rear.cam_from_imu.rotation_deg`.
    pub name: String,
    /// `intrinsics`, `extrinsics`, `time_shift`, `imu_noise` or `av_delay`.
    pub group: String,
    /// Previous value (for rotations and translations: 0).
    pub previous: f64,
    /// Current value (for rotations and translations: the size of the change).
    pub current: f64,
    /// Size of the change (current − previous; rotation angle or translation distance).
    pub change: f64,
    /// Combined 1σ uncertainty of the change (0 when neither set records one).
    pub sigma: f64,
    /// The floor a change must exceed to matter.
    pub floor: f64,
    /// Beyond both `sigmas · sigma` and the floor.
    pub significant: bool,
}

/// The comparison result.
#[derive(Debug, Clone, Serialize)]
pub struct Comparison {
    /// The previous set's folder.
    pub previous: String,
    /// The previous set's firmware and date.
    pub previous_firmware: String,
    /// Date of the previous set.
    pub previous_date: String,
    /// Every compared parameter.
    pub parameters: Vec<ParamChange>,
    /// Names of the significant changes.
    pub significant: Vec<String>,
    /// Groups with at least one significant change.
    pub changed_groups: Vec<String>,
    /// Parameters only one of the two sets has.
    pub not_compared: Vec<String>,
}

/// A standard deviation recorded as a certification check (`<name>` → value).
fn check_value(cal: &UnitCalibration, name: &str) -> Option<f64> {
    cal.certification
        .as_ref()?
        .checks
        .iter()
        .find(|c| c.name == name)
        .map(|c| c.value)
}

fn combined(a: Option<f64>, b: Option<f64>) -> f64 {
    (a.unwrap_or(0.0).powi(2) + b.unwrap_or(0.0).powi(2)).sqrt()
}

/// Compare `current` with `previous` (found in folder `previous_dir`).
pub fn compare(
    previous: &UnitCalibration,
    previous_dir: &str,
    current: &UnitCalibration,
    policy: &ComparePolicy,
) -> Comparison {
    let mut params = Vec::new();
    let mut not_compared = Vec::new();
    let mut push = |name: String,
                    group: &str,
                    previous: f64,
                    current: f64,
                    change: f64,
                    sigma: f64,
                    floor: f64| {
        let significant = change.abs() > policy.sigmas * sigma && change.abs() > floor;
        params.push(ParamChange {
            name,
            group: group.into(),
            previous,
            current,
            change,
            sigma,
            floor,
            significant,
        });
    };
    for lens in &current.lenses {
        let Some(old) = previous.lens(&lens.name) else {
            not_compared.push(format!("{} (lens not in the previous set)", lens.name));
            continue;
        };
        let (a, b) = (old.intrinsics.params(), lens.intrinsics.params());
        if a.len() == b.len() {
            let names = lens.intrinsics.param_names();
            for (i, name) in names.iter().enumerate() {
                let sa = old.param_std.as_ref().and_then(|s| s.get(i).copied());
                let sb = lens.param_std.as_ref().and_then(|s| s.get(i).copied());
                let floor = if i < 4 {
                    policy.min_change_px
                } else {
                    policy.min_change_distortion
                };
                push(
                    format!("{}.intrinsics.{name}", lens.name),
                    "intrinsics",
                    a[i],
                    b[i],
                    b[i] - a[i],
                    combined(sa, sb),
                    floor,
                );
            }
        } else {
            not_compared.push(format!("{}.intrinsics (different models)", lens.name));
        }
        match (old.cam_from_imu(), lens.cam_from_imu()) {
            (Some(pa), Some(pb)) => {
                let angle = (pa.rotation.inverse() * pb.rotation).angle().to_degrees();
                let rs = combined(
                    check_value(previous, &format!("{}.rotation_std_deg", lens.name)),
                    check_value(current, &format!("{}.rotation_std_deg", lens.name)),
                );
                push(
                    format!("{}.cam_from_imu.rotation_deg", lens.name),
                    "extrinsics",
                    0.0,
                    angle,
                    angle,
                    rs,
                    policy.min_change_rotation_deg,
                );
                let d = (pb.translation.vector - pa.translation.vector).norm();
                let ts = combined(
                    check_value(previous, &format!("{}.translation_std_m", lens.name)),
                    check_value(current, &format!("{}.translation_std_m", lens.name)),
                );
                push(
                    format!("{}.cam_from_imu.translation_m", lens.name),
                    "extrinsics",
                    0.0,
                    d,
                    d,
                    ts,
                    policy.min_change_translation_m,
                );
            }
            (None, None) => {}
            _ => not_compared.push(format!("{}.cam_from_imu", lens.name)),
        }
        match (old.time_shift_s, lens.time_shift_s) {
            (Some(a), Some(b)) => push(
                format!("{}.time_shift_s", lens.name),
                "time_shift",
                a,
                b,
                b - a,
                combined(
                    check_value(previous, &format!("{}.time_shift_std_s", lens.name)),
                    check_value(current, &format!("{}.time_shift_std_s", lens.name)),
                ),
                policy.min_change_time_shift_s,
            ),
            (None, None) => {}
            _ => not_compared.push(format!("{}.time_shift_s", lens.name)),
        }
    }
    match (&previous.imu, &current.imu) {
        (Some(a), Some(b)) => {
            let white = |c: &UnitCalibration| check_value(c, "imu.white_noise_rel_std");
            let walk = |c: &UnitCalibration| check_value(c, "imu.random_walk_rel_std");
            for (name, va, vb, rel_a, rel_b) in [
                (
                    "gyroscope_noise_density",
                    a.gyroscope_noise_density,
                    b.gyroscope_noise_density,
                    white(previous),
                    white(current),
                ),
                (
                    "accelerometer_noise_density",
                    a.accelerometer_noise_density,
                    b.accelerometer_noise_density,
                    white(previous),
                    white(current),
                ),
                (
                    "gyroscope_random_walk",
                    a.gyroscope_random_walk,
                    b.gyroscope_random_walk,
                    walk(previous),
                    walk(current),
                ),
                (
                    "accelerometer_random_walk",
                    a.accelerometer_random_walk,
                    b.accelerometer_random_walk,
                    walk(previous),
                    walk(current),
                ),
            ] {
                push(
                    format!("imu.{name}"),
                    "imu_noise",
                    va,
                    vb,
                    vb - va,
                    combined(rel_a.map(|r| r * va), rel_b.map(|r| r * vb)),
                    policy.min_change_imu_rel * va.abs(),
                );
            }
        }
        (None, None) => {}
        _ => not_compared.push("imu".into()),
    }
    for d in &current.av_delays {
        match previous.av_delays.iter().find(|p| p.mode == d.mode) {
            Some(p) => push(
                format!("av_delay.{}", d.mode),
                "av_delay",
                p.delay_s,
                d.delay_s,
                d.delay_s - p.delay_s,
                combined(Some(p.std_s), Some(d.std_s)),
                policy.min_change_av_delay_s,
            ),
            None => not_compared.push(format!("av_delay.{}", d.mode)),
        }
    }
    let significant: Vec<String> = params
        .iter()
        .filter(|p| p.significant)
        .map(|p| p.name.clone())
        .collect();
    let mut changed_groups: Vec<String> = params
        .iter()
        .filter(|p| p.significant)
        .map(|p| p.group.clone())
        .collect();
    changed_groups.sort();
    changed_groups.dedup();
    Comparison {
        previous: previous_dir.into(),
        previous_firmware: previous.firmware.clone(),
        previous_date: previous.date.clone(),
        parameters: params,
        significant,
        changed_groups,
        not_compared,
    }
}

/// The rotation of a rotation vector given in degrees.
pub fn rotation_from_deg(v: &[f64; 3]) -> UnitQuaternion<f64> {
    UnitQuaternion::from_scaled_axis(Vector3::new(v[0], v[1], v[2]) * std::f64::consts::PI / 180.0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use kiwi_core::artifact::{Certification, Check};

    fn sample() -> UnitCalibration {
        let text = r#"{"schema_version": 1, "unit_id": "U", "camera_model": "X5",
            "firmware": "1", "date": "2026-01-01",
            "lenses": [{"name": "front", "intrinsics": {"model": "kb4", "fx": 300.0, "fy": 300.0,
              "cx": 479.5, "cy": 479.5, "k1": 0.02, "k2": -0.003, "k3": 0.0005, "k4": -0.00005},
              "resolution": [960, 960], "valid_fov_rad": 3.3, "param_std": [0.02, 0.02, 0.05,
              0.05, 1e-5, 1e-5, 1e-5, 1e-5], "time_shift_s": 0.001}],
            "av_delays": [{"mode": "m", "delay_s": 0.03, "std_s": 0.0002, "repeats": 2}],
            "provenance": {"tool": "t", "tool_version": "0", "created_utc": ""}}"#;
        let mut c = UnitCalibration::from_json(text, std::path::Path::new("x")).unwrap();
        c.certification = Some(Certification {
            passed: true,
            checks: vec![Check {
                name: "front.time_shift_std_s".into(),
                value: 2e-5,
                threshold: 1e-4,
                comparison: "at_most".into(),
                passed: true,
            }],
        });
        c
    }

    #[test]
    fn flags_only_parameters_beyond_sigma_and_floor() {
        let a = sample();
        let mut b = sample();
        let same = compare(&a, "a", &b, &ComparePolicy::default());
        assert!(same.significant.is_empty(), "{:?}", same.significant);
        if let kiwi_core::artifact::Intrinsics::Kb4 { fx, .. } = &mut b.lenses[0].intrinsics {
            *fx += 1.0;
        }
        // Within 4 σ (σ = 0.28 ms) but above the floor: not significant.
        b.av_delays[0].delay_s += 0.0008;
        let c = compare(&a, "a", &b, &ComparePolicy::default());
        assert_eq!(c.significant, vec!["front.intrinsics.fx".to_string()]);
        assert_eq!(c.changed_groups, vec!["intrinsics".to_string()]);
    }
}
