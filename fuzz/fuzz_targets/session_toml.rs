//! `session.toml`: parse and validate any bytes without panicking.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(text) = std::str::from_utf8(data)
        && let Ok(session) = kiwi_core::layout::parse_session(text, "session.toml".as_ref())
    {
        let _ = session.validate();
        let _ = session.camera_names();
    }
});
