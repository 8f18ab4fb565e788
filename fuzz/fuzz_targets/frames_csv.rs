//! `frames.csv`: parse any bytes without panicking.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = kiwi_core::layout::parse_frames_csv(data, "frames.csv".as_ref());
});
