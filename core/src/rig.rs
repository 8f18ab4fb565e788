//! The QR-clock rig's contract, shared by the display generator (`kiwi-calib qr-clock`), the
//! simulator and the analysis (`kiwi-calib av-delay`): what the QR codes say, when the chirps
//! sound, and what a chirp is.
//!
//! The display clock `c` (s) runs from the start of the display video. Display frame `n` shows
//! the QR text `KIWI-CLOCK <ms>` with `ms = round(n · 1000 / refresh)` during `[n, n+1)/refresh`;
//! chirps start at `c = k · CHIRP_PERIOD_S` (k ≥ 1), and every `CHIRPS_PER_MARK`-th is a double
//! chirp (a second one `DOUBLE_GAP_S` later), which resolves which chirp is which.

use crate::error::CoreError;

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

/// One display frame's QR code: `side × side` modules, row-major, `true` for a dark module
/// (without the quiet zone).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct QrModules {
    /// Modules per side.
    pub side: usize,
    /// Row-major, `true` = dark.
    pub dark: Vec<bool>,
}

impl QrModules {
    /// Whether the module at `row`, `col` (from the top left) is dark.
    pub fn is_dark(&self, row: usize, col: usize) -> bool {
        self.dark[row * self.side + col]
    }
}

/// Error correction of every rig code: medium (15 % of codewords), the QR standard's default.
const QR_EC_LEVEL: qrcode::EcLevel = qrcode::EcLevel::M;

/// Mask of every rig code: one for all. A camera frame read while the display refreshes holds
/// the top of one code and the bottom of the next. Consecutive codes differ in a few codewords
/// (the last digits of the clock); with one mask, the two parts agree on the format and on every
/// other module, and error correction repairs the few that differ. With each code's own best
/// mask (the QR standard's choice) the parts disagree wherever the masks do, and fewer such
/// frames decode: on the simulator's rig at 119.88 fps (two X5 units, three seeds, 10 s), 4-9 %
/// more frames decoded with one mask.
const QR_MASK: qrcode::canvas::MaskPattern = qrcode::canvas::MaskPattern::Checkerboard;

/// The QR code of display frame `n` at `refresh_hz` ([`qr_text`], error correction medium, one
/// fixed mask for every frame).
pub fn qr_modules(frame: u64, refresh_hz: f64) -> Result<QrModules, CoreError> {
    let text = qr_text(frame, refresh_hz);
    let failed = |e: qrcode::types::QrError| CoreError::Invalid {
        path: "<memory>".into(),
        field: "rig QR code".into(),
        expected: "a text that fits a QR code".into(),
        found: format!("`{text}`: {e}"),
        fix: "use a display refresh rate and clock that give a short rig text".into(),
    };
    let bits = qrcode::bits::encode_auto(text.as_bytes(), QR_EC_LEVEL).map_err(failed)?;
    let version = bits.version();
    let (data, ec) = qrcode::ec::construct_codewords(&bits.into_bytes(), version, QR_EC_LEVEL)
        .map_err(failed)?;
    let mut canvas = qrcode::canvas::Canvas::new(version, QR_EC_LEVEL);
    canvas.draw_all_functional_patterns();
    canvas.draw_data(&data, &ec);
    canvas.apply_mask(QR_MASK);
    let dark: Vec<bool> = canvas
        .into_colors()
        .into_iter()
        .map(|c| c == qrcode::Color::Dark)
        .collect();
    let side = version.width().max(0) as usize;
    Ok(QrModules { side, dark })
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

    /// Every code of a recording has the same size and the same format information (error
    /// correction and mask: the 15 modules beside the top-left finder, row 8 and column 8),
    /// so a code mixed from two frames agrees with itself everywhere but in the codewords that
    /// differ.
    #[test]
    fn every_code_has_one_size_and_one_format() {
        let format = |q: &QrModules| -> Vec<bool> {
            let row: Vec<bool> = (0..9)
                .filter(|&c| c != 6)
                .map(|c| q.is_dark(8, c))
                .collect();
            let col = (0..8).filter(|&r| r != 6).map(|r| q.is_dark(r, 8));
            row.into_iter().chain(col).collect()
        };
        for refresh in [60.0, 59.94, 120.0] {
            let first = qr_modules(0, refresh).unwrap();
            assert_eq!(first.dark.len(), first.side * first.side);
            for frame in (1..1200).step_by(7) {
                let q = qr_modules(frame, refresh).unwrap();
                assert_eq!(q.side, first.side, "frame {frame} at {refresh} Hz");
                assert_eq!(format(&q), format(&first), "frame {frame} at {refresh} Hz");
                assert_ne!(q.dark, first.dark, "frame {frame} at {refresh} Hz");
            }
        }
    }
}
