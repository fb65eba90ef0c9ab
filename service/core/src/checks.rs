//! What every document (calibration, transfer function, stylus, data sheet, feature map)
//! refuses: a value outside its physical range, a hidden character in free text; and how a
//! refusal shows a number. Apart from the documents, so each uses them without depending on
//! the calibration.

/// A number as a refusal shows it: plain for everyday magnitudes, with an exponent
/// otherwise (`1e300`, not three hundred digits).
pub fn shown(v: f64) -> String {
    if v == 0.0 || (1e-4..1e7).contains(&v.abs()) || !v.is_finite() {
        format!("{v}")
    } else {
        format!("{v:e}")
    }
}

/// Checks that `v` lies in `[lo, hi]` (`unit` after the bounds); the refusal names the field,
/// the value and the range. The ranges are physical: a value outside would not be a
/// mistake the service can correct with, it would drop or flag every point.
pub fn in_range(field: &str, v: f64, lo: f64, hi: f64, unit: &str) -> Result<(), String> {
    if v.is_finite() && v >= lo && v <= hi {
        Ok(())
    } else {
        let unit = if unit.is_empty() {
            String::new()
        } else {
            format!(" {unit}")
        };
        Err(format!(
            "{field}: {} is outside the allowed range [{}, {}]{unit}",
            shown(v),
            shown(lo),
            shown(hi)
        ))
    }
}

/// Range of `sample_period_s`, s: 10 Hz to 100 kHz (the simulator's rates).
pub const SAMPLE_PERIOD_S: [f64; 2] = [1e-5, 0.1];
/// Range of a time constant of the nominal model (`first_order.tau_s`), s.
pub const TAU_S: [f64; 2] = [1e-5, 10.0];

/// Why a character may not appear in free text people read (a note, an audit record):
/// control characters, bidirectional-text controls and invisible (zero-width and other
/// format) characters make the text read otherwise than it is stored.
pub fn hidden_char(c: char) -> Option<&'static str> {
    match c {
        '\u{202A}'..='\u{202E}'
        | '\u{2066}'..='\u{2069}'
        | '\u{200E}'
        | '\u{200F}'
        | '\u{061C}' => Some("a bidirectional-text control"),
        '\u{200B}'..='\u{200D}'
        | '\u{2060}'..='\u{2064}'
        | '\u{206A}'..='\u{206F}'
        | '\u{FEFF}'
        | '\u{180E}'
        | '\u{034F}'
        | '\u{00AD}'
        | '\u{115F}'
        | '\u{1160}'
        | '\u{3164}'
        | '\u{FFA0}'
        | '\u{FFF9}'..='\u{FFFB}'
        | '\u{E0000}'..='\u{E007F}' => Some("an invisible character"),
        '\u{2028}' | '\u{2029}' => Some("a line or paragraph separator"),
        c if c.is_control() => Some("a control character"),
        _ => None,
    }
}

/// Checks free text for [`hidden_char`]s; `lines` lets line feeds and tabs through (a
/// note). The refusal names the field, the character and where it is.
pub fn check_text(field: &str, text: &str, lines: bool) -> Result<(), String> {
    for (i, c) in text.chars().enumerate() {
        if lines && (c == '\n' || c == '\t') {
            continue;
        }
        if let Some(what) = hidden_char(c) {
            return Err(format!(
                "{field}: character {} is U+{:04X}, {what}; free text may hold no control, \
                 bidirectional-override or zero-width characters",
                i + 1,
                c as u32
            ));
        }
    }
    Ok(())
}

/// `text` with each [`hidden_char`] written as `<U+XXXX>`: text that is taken, not refused
/// (a requester's claimed identity), shown as it is.
pub fn escape_text(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    for c in text.chars() {
        if hidden_char(c).is_some() {
            out.push_str(&format!("<U+{:04X}>", c as u32));
        } else {
            out.push(c);
        }
    }
    out
}
