//! `imu.csv`: stream, validate and run the units check on any bytes without panicking.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let path = std::path::Path::new("imu.csv");
    let Ok(reader) = kiwi_core::imu::ImuCsvReader::from_reader(data, path) else {
        return;
    };
    let Ok(samples) = reader.collect::<kiwi_core::Result<Vec<_>>>() else {
        return;
    };
    let _ = kiwi_core::imu::check_imu_samples(path, &samples);
    if let Ok(series) = kiwi_core::imu::ImuSeries::new(samples, path) {
        let (t0, t1) = series.time_range();
        let _ = series.interpolate(0.5 * (t0 + t1));
    }
});
