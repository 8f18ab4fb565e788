//! A localizer's `poses.csv`: parse any bytes without panicking.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(text) = std::str::from_utf8(data) {
        let _ = kiwi_backend::formats::tables::parse_localizations(text, "poses.csv".as_ref());
    }
});
