//! Kalibr `camchain.yaml` and `imu.yaml`: parse any bytes without panicking.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(text) = std::str::from_utf8(data) {
        let _ = kiwi_core::kalibr::lenses_from_camchain(text, "camchain.yaml".as_ref());
        let _ = kiwi_core::kalibr::imu_from_yaml(text, "imu.yaml".as_ref());
    }
});
