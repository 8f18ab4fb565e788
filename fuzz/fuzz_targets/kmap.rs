//! A visual map (`.kmap`): parse and validate any bytes without panicking.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = kiwi_backend::vision::map::VisualMap::from_bytes(data, "map.kmap".as_ref());
});
