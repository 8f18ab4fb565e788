//! Audio decoding and resampling for sync: the shared implementation in `kiwi_core::audio`.

pub use kiwi_core::audio::{Audio, decimate, read_audio, resample};
