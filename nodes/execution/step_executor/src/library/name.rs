//! The rules for motion names: short, visible text that displays as what it is (names are shown in
//! logs, listings and terminals, and stored as YAML keys' values).

/// The longest motion name, in bytes of UTF-8.
pub const MAX_NAME_BYTES: usize = 128;

/// Why a motion name is refused (the rule it breaks). Names are shown in logs, listings and
/// terminals, so they must be short, visible text that displays as what it is.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum NameError {
    #[error("name must not be empty or whitespace only")]
    Empty,
    #[error("name must not start or end with whitespace")]
    OuterWhitespace,
    #[error("name is {bytes} bytes long; at most {MAX_NAME_BYTES} bytes are allowed")]
    TooLong { bytes: usize },
    #[error("name contains the control character U+{code:04X} at byte {at} (printable characters only)")]
    Control { code: u32, at: usize },
    #[error("name contains the bidirectional control character U+{code:04X} at byte {at} (it can make the name display as another)")]
    Bidi { code: u32, at: usize },
    #[error("name contains the invisible format character U+{code:04X} at byte {at} (printable characters only)")]
    Invisible { code: u32, at: usize },
}

/// Checks a motion name: not empty, no surrounding whitespace, at most [`MAX_NAME_BYTES`], no control
/// characters, no bidirectional embedding/override/isolate characters (U+202A–U+202E, U+2066–U+2069)
/// and no other invisible format characters (zero-width spaces and joiners, marks, separators, BOM).
pub fn validate_name(name: &str) -> Result<(), NameError> {
    if name.trim().is_empty() {
        return Err(NameError::Empty);
    }
    if name.len() > MAX_NAME_BYTES {
        return Err(NameError::TooLong { bytes: name.len() });
    }
    for (at, ch) in name.char_indices() {
        let code = u32::from(ch);
        if ch.is_control() {
            return Err(NameError::Control { code, at });
        }
        if matches!(ch, '\u{202A}'..='\u{202E}' | '\u{2066}'..='\u{2069}' | '\u{200E}' | '\u{200F}' | '\u{061C}') {
            return Err(NameError::Bidi { code, at });
        }
        if matches!(ch, '\u{00AD}' | '\u{180E}' | '\u{200B}'..='\u{200D}' | '\u{2028}' | '\u{2029}' | '\u{2060}'..='\u{2065}' | '\u{206A}'..='\u{206F}' | '\u{FEFF}' | '\u{FFF9}'..='\u{FFFB}')
        {
            return Err(NameError::Invisible { code, at });
        }
    }
    if name.trim() != name {
        return Err(NameError::OuterWhitespace);
    }
    Ok(())
}
