//! `audio.wav`: read the header (against the claimed file size) and decode any bytes without
//! panicking or allocating what the header merely claims.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let path = std::path::Path::new("audio.wav");
    if kiwi_core::audio::wav_info(data, data.len() as u64, path).is_ok() {
        let _ = kiwi_core::audio::decode_wav(data, path);
    }
});
