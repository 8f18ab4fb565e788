//! The QR-clock rig's contract, shared by the display generator (`kiwi-calib qr-clock`), the
//! simulator and the analysis (`kiwi-calib av-delay`): what the QR codes say, when the chirps
//! sound, and what a chirp is.
//!
//! The display clock `c` (s) runs from the start of the display video. Display frame `n` shows
//! the QR text `KIWI-CLOCK <ms>` with `ms = round(n · 1000 / refresh)` during `[n, n+1)/refresh`;
//! chirps start at `c = k · CHIRP_PERIOD_S` (k ≥ 1), and every `CHIRPS_PER_MARK`-th is a double
//! chirp (a second one `DOUBLE_GAP_S` later), which resolves which chirp is which.

/// Text before the clock value in every QR code.
pub const QR_PREFIX: &str = "KIWI-CLOCK ";
/// Period of the chirps on the display clock (s).
pub const CHIRP_PERIOD_S: f64 = 0.5;
/// Every this many chirps, a double chirp (every 10 s).
pub const CHIRPS_PER_MARK: u64 = 20;
/// Length of one chirp (s).
pub const CHIRP_S: f64 = 0.02;
/// Start frequency of a chirp (Hz).
pub const CHIRP_F0_HZ: f64 = 1500.0;
/// End frequency of a chirp (Hz).
pub const CHIRP_F1_HZ: f64 = 4500.0;
/// Gap from a double chirp's first onset to its second (s).
pub const DOUBLE_GAP_S: f64 = 0.06;
/// Speed of sound in room air (m/s): turns the rig speaker's distance into the sound's travel time.
pub const SPEED_OF_SOUND_M_S: f64 = 343.0;

/// One scheduled chirp.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Chirp {
    /// Onset on the display clock (s).
    pub clock_s: f64,
    /// Whether it is a double chirp (a mark).
    pub double: bool,
}

/// Chirps with onsets in `[from_s, to_s]` of display clock.
pub fn chirp_schedule(from_s: f64, to_s: f64) -> Vec<Chirp> {
    let first = (from_s / CHIRP_PERIOD_S).ceil().max(1.0) as u64;
    let last = (to_s / CHIRP_PERIOD_S).floor().max(0.0) as u64;
    (first..=last)
        .map(|k| Chirp {
            clock_s: k as f64 * CHIRP_PERIOD_S,
            double: k.is_multiple_of(CHIRPS_PER_MARK),
        })
        .collect()
}

/// The chirp waveform at `rate_hz` (Hann-windowed linear sweep, peak amplitude 1).
pub fn chirp_waveform(rate_hz: f64) -> Vec<f32> {
    let n = (CHIRP_S * rate_hz).round() as usize;
    (0..n)
        .map(|k| {
            let t = k as f64 / rate_hz;
            let phase = std::f64::consts::TAU
                * (CHIRP_F0_HZ * t + 0.5 * (CHIRP_F1_HZ - CHIRP_F0_HZ) / CHIRP_S * t * t);
            let window = (std::f64::consts::PI * k as f64 / n as f64).sin();
            (window * phase.sin()) as f32
        })
        .collect()
}

/// The QR text of display frame `n` at `refresh_hz`.
pub fn qr_text(frame: u64, refresh_hz: f64) -> String {
    format!(
        "{QR_PREFIX}{}",
        (frame as f64 * 1000.0 / refresh_hz).round() as u64
    )
}

/// The clock (s) a QR text encodes, if it is a rig code.
pub fn parse_qr_text(text: &str) -> Option<f64> {
    text.strip_prefix(QR_PREFIX)?
        .trim()
        .parse::<u64>()
        .ok()
        .map(|ms| ms as f64 / 1000.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn schedule_and_codes() {
        let s = chirp_schedule(9.2, 10.6);
        assert_eq!(
            s.iter().map(|c| c.clock_s).collect::<Vec<_>>(),
            vec![9.5, 10.0, 10.5]
        );
        assert!(s[1].double && !s[0].double);
        assert_eq!(parse_qr_text(&qr_text(90, 60.0)), Some(1.5));
        assert_eq!(parse_qr_text("hello"), None);
        assert_eq!(chirp_waveform(48_000.0).len(), 960);
    }
}
