//! Checks of numbers given on the command line, shared by the three programs' argument parsers
//! (`#[arg(value_parser = kiwi_core::args::positive)]`), so that `--duration 0`, a negative
//! rate or `NaN` is refused with the same clear message everywhere before any work starts.

/// A finite number > 0 (durations, rates, sizes).
pub fn positive(text: &str) -> Result<f64, String> {
    let v = number(text)?;
    if v > 0.0 {
        Ok(v)
    } else {
        Err(format!("expected a number > 0, found {text}"))
    }
}

/// A finite number ≥ 0 (lengths where 0 means "none").
pub fn non_negative(text: &str) -> Result<f64, String> {
    let v = number(text)?;
    if v >= 0.0 {
        Ok(v)
    } else {
        Err(format!("expected a number ≥ 0 (0 for none), found {text}"))
    }
}

/// A finite number.
pub fn finite(text: &str) -> Result<f64, String> {
    number(text)
}

fn number(text: &str) -> Result<f64, String> {
    let v: f64 = text
        .trim()
        .parse()
        .map_err(|_| format!("expected a number, found `{text}`"))?;
    if v.is_finite() {
        Ok(v)
    } else {
        Err(format!("expected a finite number, found {text}"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn refuses_zero_negative_and_non_finite() {
        assert_eq!(positive("2.5"), Ok(2.5));
        assert!(positive("0").is_err());
        assert!(positive("-1").is_err());
        assert!(positive("NaN").is_err());
        assert!(positive("inf").is_err());
        assert_eq!(non_negative("0"), Ok(0.0));
        assert!(non_negative("-1").unwrap_err().contains("≥ 0"));
        assert!(finite("x").unwrap_err().contains("`x`"));
    }
}
