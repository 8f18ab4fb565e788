//! `calibration.json`: parse and validate any bytes without panicking.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(text) = std::str::from_utf8(data)
        && let Ok(cal) =
            kiwi_core::artifact::UnitCalibration::from_json(text, "calibration.json".as_ref())
    {
        // What validated must also export and project without panicking.
        let _ = kiwi_core::kalibr::camchain_yaml(&cal);
        let _ = kiwi_core::basalt::calibration_json(&cal);
        let _ = cal.missing_for_reconstruction();
        for lens in &cal.lenses {
            let _ = lens.camera();
        }
    }
});
