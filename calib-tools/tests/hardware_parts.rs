//! Every printed part renders with OpenSCAD to a closed STL that fits the printer, every holder
//! and tool carries the one shared dovetail (probed on the rendered meshes), and the generated
//! hardware files are those the parameters give.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::path::{Path, PathBuf};
use std::process::Command;

use kiwi_calib::hardware::{
    HardwareLayout, Mesh, QuickReleaseSide, check_all, failed_probes, stale_files,
};
use kiwi_core::hardware::HardwareParams;

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

fn require_openscad() {
    let found = Command::new("openscad").arg("--version").output().is_ok();
    assert!(
        found,
        "`openscad` is not installed: `make deps` installs it (Debian package openscad); this \
         test renders every printed part with it"
    );
}

#[test]
fn every_part_renders_closed_fits_the_printer_and_shares_the_dovetail() {
    require_openscad();
    let layout = HardwareLayout::new(&root());
    let params = HardwareParams::load(&layout.params()).unwrap();
    let out = tempfile::tempdir().unwrap();
    let checks = check_all(&layout, out.path()).unwrap();
    assert_eq!(checks.len(), 12, "one STL per part file");
    let mut problems = Vec::new();
    for c in &checks {
        problems.extend(
            c.problems(&params)
                .into_iter()
                .map(|p| format!("{}: {p}", c.part.name)),
        );
    }
    assert!(problems.is_empty(), "{}", problems.join("\n"));
    // Where each part must carry the quick-release, and which side.
    use QuickReleaseSide::{Clamp, Plate};
    let expected: [(&str, &[QuickReleaseSide]); 6] = [
        ("camera_holder_light", &[Plate]),
        ("camera_holder_robust", &[Plate, Plate]),
        ("chopstick_body", &[Clamp]),
        ("parallel_jaw_body", &[Clamp]),
        ("wrist_cuff", &[Clamp]),
        ("flange_adapter_iso50", &[Clamp]),
    ];
    for (name, sides) in expected {
        let c = checks.iter().find(|c| c.part.name == name).unwrap();
        let found: Vec<QuickReleaseSide> = c.part.quick_release.iter().map(|f| f.side).collect();
        assert_eq!(found, sides, "{name}");
    }
    // The probes can fail: a clamp probed as if it were a plate, and a plate whose profile is
    // 1 mm narrower than the parameters say, are caught.
    let body = checks
        .iter()
        .find(|c| c.part.name == "chopstick_body")
        .unwrap();
    let mesh = Mesh::read(&body.part.stl).unwrap();
    let mut as_plate = body.part.quick_release[0].clone();
    as_plate.side = Plate;
    assert!(failed_probes(&mesh, &params, &as_plate).len() > 10);
    let holder = checks
        .iter()
        .find(|c| c.part.name == "camera_holder_light")
        .unwrap();
    let mesh = Mesh::read(&holder.part.stl).unwrap();
    let mut wider = params.clone();
    wider.quick_release.width_mm += 1.0;
    assert!(!failed_probes(&mesh, &wider, &holder.part.quick_release[0]).is_empty());
}

#[test]
fn generated_hardware_files_are_up_to_date() {
    let stale = stale_files(&HardwareLayout::new(&root())).unwrap();
    assert!(
        stale.is_empty(),
        "out of date (run `make hardware`): {stale:?}"
    );
}
