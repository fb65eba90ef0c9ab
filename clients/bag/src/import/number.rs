//! Numbers of a table's cells: values (f64, finite), ids (whole numbers) and times (exact
//! decimal arithmetic to integer ns, so `0.001` s is 1 000 000 ns and a clock of 1.7e9 s
//! keeps its nanoseconds).

/// A cell as a finite number; the error says why not.
pub(crate) fn value(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if v.is_finite() => Ok(v),
        Ok(_) => Err(format!("{} is not a finite number", shown(s))),
        Err(_) if s.contains(',') && !s.contains(['e', 'E']) => Err(format!(
            "{} is not a number (a decimal comma? numbers take a decimal point)",
            shown(s)
        )),
        Err(_) => Err(format!("{} is not a number", shown(s))),
    }
}

/// A whole number 0..=u32::MAX written as a number (`3`, also `3.0` or `3e0`).
pub(crate) fn as_id(v: f64) -> Option<u32> {
    (v.fract() == 0.0 && (0.0..=u32::MAX as f64).contains(&v)).then_some(v as u32)
}

/// A cell as an id (tip, segment, probe).
pub(crate) fn id(s: &str) -> Result<u32, String> {
    if let Ok(v) = s.parse::<u32>() {
        return Ok(v);
    }
    let v = value(s)?;
    as_id(v).ok_or_else(|| format!("{} is not a whole number from 0 to {}", shown(s), u32::MAX))
}

/// A cell quoted and cut for a message.
pub(crate) fn shown(s: &str) -> String {
    let mut t: String = s.chars().take(40).collect();
    if t.len() < s.len() {
        t.push('…');
    }
    format!("{t:?}")
}

/// `10^k` for k ≤ 38.
fn pow10(k: u32) -> u128 {
    10u128.pow(k)
}

/// A decimal number (`12`, `-0.5`, `1.25e-3`) times 10^`exponent`, rounded to the nearest
/// integer (halves away from zero): a time in its unit as ns (exponent 9 for seconds).
/// Exact for every input whose digits fit in 36 significant digits; `None` when the text is
/// not a number or the result does not fit in an i64.
pub(crate) fn scaled_integer(s: &str, exponent: i32) -> Option<i64> {
    let (neg, rest) = match s.as_bytes().first()? {
        b'-' => (true, &s[1..]),
        b'+' => (false, &s[1..]),
        _ => (false, s),
    };
    let (mantissa, exp) = match rest.find(['e', 'E']) {
        Some(i) => (&rest[..i], rest[i + 1..].parse::<i32>().ok()?),
        None => (rest, 0),
    };
    let (int, frac) = mantissa.split_once('.').unwrap_or((mantissa, ""));
    if int.is_empty() && frac.is_empty() {
        return None;
    }
    if !int.bytes().chain(frac.bytes()).all(|b| b.is_ascii_digit()) {
        return None;
    }
    // value = m × 10^e; digits past 36 significant ones only move e (and are below any ns
    // for times that fit in an i64).
    let mut m: u128 = 0;
    let mut e = i64::from(exp) + i64::from(exponent) - frac.len() as i64;
    for b in int.bytes().chain(frac.bytes()) {
        let d = u128::from(b - b'0');
        if m < pow10(36) {
            m = m * 10 + d;
        } else {
            e += 1;
        }
    }
    if m == 0 {
        return Some(0);
    }
    let magnitude: u128 = if e >= 0 {
        if e > 38 {
            return None;
        }
        m.checked_mul(pow10(e as u32))?
    } else {
        if -e > 38 {
            return Some(0);
        }
        let d = pow10((-e) as u32);
        let (q, r) = (m / d, m % d);
        if r >= d - r {
            q + 1
        } else {
            q
        }
    };
    if neg {
        if magnitude <= i64::MAX as u128 + 1 {
            Some((magnitude as i128).wrapping_neg() as i64)
        } else {
            None
        }
    } else {
        i64::try_from(magnitude).ok()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn times_convert_exactly() {
        assert_eq!(scaled_integer("0.001", 9), Some(1_000_000));
        assert_eq!(scaled_integer("1.5", 6), Some(1_500_000));
        assert_eq!(scaled_integer("-2", 9), Some(-2_000_000_000));
        assert_eq!(scaled_integer("+7", 0), Some(7));
        assert_eq!(scaled_integer("1.25e-3", 9), Some(1_250_000));
        assert_eq!(scaled_integer("1E3", 3), Some(1_000_000));
        assert_eq!(scaled_integer(".5", 3), Some(500));
        assert_eq!(scaled_integer("5.", 3), Some(5000));
        // A clock in seconds since the epoch keeps its nanoseconds (f64 would not).
        assert_eq!(
            scaled_integer("1764288000.123456789", 9),
            Some(1_764_288_000_123_456_789)
        );
        // Rounded to the nearest ns, halves away from zero.
        assert_eq!(scaled_integer("0.0000000004", 9), Some(0));
        assert_eq!(scaled_integer("0.0000000005", 9), Some(1));
        assert_eq!(scaled_integer("-0.0000000005", 9), Some(-1));
        assert_eq!(scaled_integer("1e-50", 9), Some(0));
        assert_eq!(scaled_integer("9223372036854775807", 0), Some(i64::MAX));
        assert_eq!(scaled_integer("-9223372036854775808", 0), Some(i64::MIN));
        assert_eq!(scaled_integer("9223372036854775808", 0), None);
        assert_eq!(scaled_integer("1e40", 0), None);
        assert_eq!(scaled_integer("1e10", 9), None);
        for bad in [
            "", "-", ".", "1.2.3", "abc", "1e", "0x10", "1_000", " 1", "nan", "inf",
        ] {
            assert_eq!(scaled_integer(bad, 9), None, "{bad:?}");
        }
    }

    #[test]
    fn values_and_ids() {
        assert_eq!(value("1.5"), Ok(1.5));
        assert_eq!(value("-0").map(f64::to_bits), Ok((-0.0f64).to_bits()));
        assert!(value("NaN").unwrap_err().contains("not a finite number"));
        assert!(value("inf").unwrap_err().contains("not a finite number"));
        assert!(value("1,5").unwrap_err().contains("decimal comma"));
        assert!(value("abc")
            .unwrap_err()
            .contains("\"abc\" is not a number"));
        assert_eq!(id("3"), Ok(3));
        assert_eq!(id("3.0"), Ok(3));
        assert_eq!(id("4294967295"), Ok(u32::MAX));
        assert!(id("-1").is_err());
        assert!(id("1.5").is_err());
        assert!(id("4294967296").is_err());
    }
}
