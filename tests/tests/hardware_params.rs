//! The hat mount's parameters are where the simulator puts the hat marker, so the printed head
//! module and the synthetic sessions agree.

#![allow(clippy::unwrap_used)]

use std::path::Path;

use kiwi_core::hardware::HardwareParams;
use kiwi_fixtures::scenario::cam_from_marker;
use kiwi_fixtures::session::{HAT_MARKER_ID, HAT_MARKER_SIZE_M};
use nalgebra::Vector3;

#[test]
fn hat_mount_matches_the_simulated_hat_marker() {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../hardware/params.toml");
    let p = HardwareParams::load(&path).unwrap();
    assert_eq!(p.hat.tag_id, HAT_MARKER_ID);
    assert!((p.hat.tag_size_mm / 1000.0 - HAT_MARKER_SIZE_M).abs() < 1e-12);
    let t = cam_from_marker();
    let expected = Vector3::new(
        0.0,
        -p.hat.tag_above_camera_mm,
        p.hat.tag_ahead_of_camera_mm,
    ) / 1000.0;
    assert!(
        (t.translation.vector - expected).norm() < 1e-12,
        "{:?}",
        t.translation
    );
    // Facing forward (marker z along the head's z), printed up pointing up (marker y = -head y).
    let z = t.rotation * Vector3::z();
    let y = t.rotation * Vector3::y();
    assert!((z - Vector3::z()).norm() < 1e-12 && (y + Vector3::y()).norm() < 1e-12);
}
