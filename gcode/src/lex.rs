//! Line lexer: bytes of one line -> a fixed-size [`Block`] (no allocation).

use crate::expr::{self, Params, SysView};
use crate::{ErrorKind, GcodeError};

/// Most G / M words accepted on one line; LinuxCNC allows 4 M words and real
/// programs stay far below these.
pub(crate) const MAX_G: usize = 16;
pub(crate) const MAX_M: usize = 8;

/// Words of one line. Values of letters are indexed by `letter - b'A'`;
/// `mask` says which letters are present. Positions are byte offsets.
pub(crate) struct Block {
    /// Letters A..Z, then `@` (polar radius) and `^` (polar angle).
    pub vals: [f64; 28],
    pub pos: [u32; 28],
    pub mask: u32,
    /// G codes as value * 10 (G90.1 -> 901), with byte offset.
    pub g: [(u16, u32); MAX_G],
    pub ng: usize,
    pub m: [(u16, u32); MAX_M],
    pub nm: usize,
    /// Byte range of a `(msg, ...)` text.
    pub msg: Option<(usize, usize)>,
    /// Byte range of a `(print, ...)` / `(debug, ...)` text (parameters
    /// substituted when the line runs).
    pub debug: Option<(usize, usize)>,
    /// The line needs more than the plain path: a parameter, an assignment,
    /// a debug message or M98/M99. One flag keeps plain lines to one test.
    pub special: bool,
}

impl Block {
    pub fn new() -> Self {
        Block {
            vals: [0.0; 28],
            pos: [0; 28],
            mask: 0,
            g: [(0, 0); MAX_G],
            ng: 0,
            m: [(0, 0); MAX_M],
            nm: 0,
            msg: None,
            debug: None,
            special: false,
        }
    }
    #[inline]
    pub fn has(&self, letter: u8) -> bool {
        self.mask & bit(letter) != 0
    }
    #[inline]
    pub fn get(&self, letter: u8) -> Option<f64> {
        if self.has(letter) {
            Some(self.vals[(letter - b'A') as usize])
        } else {
            None
        }
    }
    #[inline]
    pub fn pos_of(&self, letter: u8) -> u32 {
        self.pos[(letter - b'A') as usize]
    }
}

/// Slots of LinuxCNC's polar words in [`Block`].
pub(crate) const POLAR_R: usize = 26;
pub(crate) const POLAR_A: usize = 27;
pub(crate) const POLAR_MASK: u32 = (1 << POLAR_R) | (1 << POLAR_A);

#[inline]
pub(crate) const fn bit(letter: u8) -> u32 {
    1 << (letter - b'A')
}

/// What a line turned out to be.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum LineKind {
    /// Words (possibly none: blank or comment-only lines).
    Words,
    /// A `%` tape marker.
    Percent,
    /// Starts with `/` and block delete is on.
    Deleted,
    /// An O-word (subroutine or control flow) at this byte offset; the
    /// interpreter reads the rest of the line.
    OWord(usize),
}

/// Error before the column is known in characters: (byte offset, kind, message).
pub(crate) type LexError = (usize, ErrorKind, String);

/// 1-based character column of byte offset `off` in `line` (ASCII fast path).
pub(crate) fn column(line: &[u8], off: usize) -> u32 {
    let off = off.min(line.len());
    let prefix = &line[..off];
    let chars = if prefix.is_ascii() {
        off
    } else {
        // Count UTF-8 lead bytes; invalid bytes each count as one column.
        prefix.iter().filter(|&&b| (b & 0xC0) != 0x80).count()
    };
    u32::try_from(chars + 1).unwrap_or(u32::MAX)
}

pub(crate) fn make_error(line_no: u32, line: &[u8], e: LexError) -> GcodeError {
    GcodeError {
        line: line_no,
        column: column(line, e.0),
        kind: e.1,
        message: e.2,
    }
}

/// Exact powers of ten (all representable in f64), for the fast number path.
const POW10: [f64; 23] = [
    1e0, 1e1, 1e2, 1e3, 1e4, 1e5, 1e6, 1e7, 1e8, 1e9, 1e10, 1e11, 1e12, 1e13, 1e14, 1e15, 1e16,
    1e17, 1e18, 1e19, 1e20, 1e21, 1e22,
];

/// Parses a real number starting at `*i` (after the letter). Spaces and tabs
/// are allowed anywhere in it, as in LinuxCNC. Correctly rounded: the fast
/// path is exact (mantissa < 2^53 and a power of ten <= 1e22, one IEEE
/// division), anything longer goes through `str::parse`.
#[inline]
pub(crate) fn parse_number(b: &[u8], i: &mut usize) -> Result<f64, LexError> {
    parse_number_hot(b, i)
}

/// [`parse_number`], always inlined: for the one hot call site, the words of
/// a line in [`lex_line`].
#[inline(always)]
fn parse_number_hot(b: &[u8], i: &mut usize) -> Result<f64, LexError> {
    // Fast path for the common shape `[-+]digits[.digits]` with no blanks
    // inside; anything else goes to the general scanner below.
    let mut j = *i;
    let mut neg = false;
    if j < b.len() && (b[j] == b'-' || b[j] == b'+') {
        neg = b[j] == b'-';
        j += 1;
    }
    let (mut mant, int_digits) = digits(b, j, 0);
    j += int_digits;
    let mut frac = 0;
    if j < b.len() && b[j] == b'.' {
        j += 1;
        (mant, frac) = digits(b, j, mant);
        j += frac;
    }
    let ndig = int_digits + frac;
    // "X1 Y2" ends at the blank; "X1 2" (LinuxCNC: 12) continues past it.
    let mut k = j;
    while k < b.len() && (b[k] == b' ' || b[k] == b'\t') {
        k += 1;
    }
    let continues = k > j && k < b.len() && (b[k].is_ascii_digit() || b[k] == b'.');
    // Up to 15 digits the mantissa is below 2^53 and the power of ten within the table: one
    // comparison for the usual case; up to 19 digits the values decide.
    let exact = (1..=15).contains(&ndig)
        || (ndig > 0 && ndig <= 19 && mant < (1u64 << 53) && frac < POW10.len());
    if exact && !continues {
        // The blanks after the number are skipped too: the caller would only step over them.
        *i = k;
        // Below 2^53, so the signed conversion (one instruction; the unsigned one is several on
        // baseline x86-64) is exact.
        let v = (mant as i64) as f64 / POW10[frac];
        return Ok(if neg { -v } else { v });
    }
    parse_number_general(b, i)
}

/// The run of ASCII digits at `b[j..]` appended to `mant` (`mant * 10 + digit` each,
/// wrapping: the caller only uses a mantissa of at most 19 digits): (mantissa, digits).
#[inline(always)]
fn digits(b: &[u8], j: usize, mut mant: u64) -> (u64, usize) {
    let rest = b.get(j..).unwrap_or_default();
    let mut n = 0;
    for &c in rest {
        let d = c.wrapping_sub(b'0');
        if d > 9 {
            break;
        }
        mant = mant.wrapping_mul(10).wrapping_add(u64::from(d));
        n += 1;
    }
    (mant, n)
}

/// General scanner: blanks anywhere (LinuxCNC), long mantissas, errors.
#[cold]
fn parse_number_general(b: &[u8], i: &mut usize) -> Result<f64, LexError> {
    let start = *i;
    let mut j = *i;
    while j < b.len() && (b[j] == b' ' || b[j] == b'\t') {
        j += 1;
    }
    let mut neg = false;
    if j < b.len() && (b[j] == b'-' || b[j] == b'+') {
        neg = b[j] == b'-';
        j += 1;
    }
    let mut mant: u64 = 0;
    let mut digits = 0u32; // significant digits accumulated
    let mut frac = 0u32;
    let mut seen_digit = false;
    let mut seen_dot = false;
    let mut overflow = false;
    while j < b.len() {
        let c = b[j];
        if c.is_ascii_digit() {
            seen_digit = true;
            if digits < 19 {
                mant = mant * 10 + u64::from(c - b'0');
                if mant != 0 {
                    digits += 1;
                }
                if seen_dot {
                    frac += 1;
                }
            } else {
                overflow = true;
            }
        } else if c == b'.' {
            if seen_dot {
                break;
            }
            seen_dot = true;
        } else if c != b' ' && c != b'\t' {
            break;
        }
        j += 1;
    }
    if !seen_digit {
        // An expression or parameter follows: the caller evaluates it, so
        // no message is built (this is the parametric programs' hot path).
        if matches!(b.get(j), Some(b'#' | b'[')) {
            return Err((start, ErrorKind::Syntax, String::new()));
        }
        return Err((start, ErrorKind::Syntax, number_expected(b, j)));
    }
    *i = j;
    if !overflow && mant < (1u64 << 53) && (frac as usize) < POW10.len() {
        let v = mant as f64 / POW10[frac as usize];
        return Ok(if neg { -v } else { v });
    }
    slow_number(&b[start..j], start)
}

#[cold]
fn slow_number(text: &[u8], start: usize) -> Result<f64, LexError> {
    let mut buf = [0u8; 64];
    let mut n = 0;
    for &c in text {
        if c == b' ' || c == b'\t' {
            continue;
        }
        if n == buf.len() {
            return Err((start, ErrorKind::Syntax, "number too long".to_string()));
        }
        buf[n] = c;
        n += 1;
    }
    std::str::from_utf8(&buf[..n])
        .ok()
        .and_then(|s| s.parse::<f64>().ok())
        .filter(|v| v.is_finite())
        .ok_or_else(|| (start, ErrorKind::Syntax, "invalid number".to_string()))
}

#[cold]
fn number_expected(b: &[u8], j: usize) -> String {
    match b.get(j) {
        Some(&c) if c.is_ascii_graphic() => format!("expected a number, found '{}'", c as char),
        _ => "expected a number".to_string(),
    }
}

/// Letters the interpreter understands; others are unsupported words.
const SUPPORTED: u32 = bit(b'N')
    | bit(b'A')
    | bit(b'G')
    | bit(b'M')
    | bit(b'X')
    | bit(b'Y')
    | bit(b'Z')
    | bit(b'I')
    | bit(b'J')
    | bit(b'K')
    | bit(b'R')
    | bit(b'F')
    | bit(b'S')
    | bit(b'T')
    | bit(b'P')
    | bit(b'H')
    | bit(b'Q')
    | bit(b'L')
    | bit(b'D');

/// Lexes one line (no trailing newline) into `blk`. Parameters and
/// expressions are evaluated with `params` (whose system values come from
/// `sys`, asked only when a line reads a parameter); assignments are left in
/// `params.pending`.
pub(crate) fn lex_line(
    b: &[u8],
    block_delete: bool,
    blk: &mut Block,
    params: &mut Params,
    sys: &dyn Fn() -> SysView,
) -> Result<LineKind, LexError> {
    blk.mask = 0;
    blk.ng = 0;
    blk.nm = 0;
    blk.msg = None;
    blk.debug = None;
    if blk.special {
        blk.special = false;
        params.pending.clear();
    }
    let mut i = 0;
    // Leading blanks, then block delete / tape marker checks.
    while i < b.len() && (b[i] == b' ' || b[i] == b'\t') {
        i += 1;
    }
    if i < b.len() {
        if b[i] == b'/' {
            if block_delete {
                return Ok(LineKind::Deleted);
            }
            i += 1;
        } else if b[i] == b'%' {
            if b[i + 1..]
                .iter()
                .all(|&c| c == b' ' || c == b'\t' || c == b'\r')
            {
                return Ok(LineKind::Percent);
            }
            return Err((
                i,
                ErrorKind::Syntax,
                "'%' must be alone on its line".to_string(),
            ));
        }
    }
    while i < b.len() {
        let c = b[i];
        let up = c & !0x20;
        if up.is_ascii_uppercase() {
            let idx = (up - b'A') as usize;
            let at = i;
            if SUPPORTED & (1 << idx) == 0 {
                if up == b'O' {
                    if blk.mask != 0 || blk.ng != 0 || blk.nm != 0 {
                        return Err((
                            at,
                            ErrorKind::Syntax,
                            "an O-word must be the first word of its line".to_string(),
                        ));
                    }
                    return Ok(LineKind::OWord(at));
                }
                return Err((at, ErrorKind::Unsupported, unsupported_letter(up)));
            }
            i += 1;
            // Report number errors at the word's letter.
            let after = i;
            let v = match parse_number_hot(b, &mut i) {
                Ok(v) => v,
                Err(e) => {
                    i = after;
                    blk.special = true;
                    word_value(b, &mut i, params, sys).ok_or((at, e.1, e.2))??
                }
            };
            match up {
                b'G' => {
                    if blk.ng == MAX_G {
                        return Err((at, ErrorKind::Invalid, "too many G words".to_string()));
                    }
                    blk.g[blk.ng] = (code10(v, at, 'G')?, at as u32);
                    blk.ng += 1;
                }
                b'M' => {
                    if blk.nm == MAX_M {
                        return Err((at, ErrorKind::Invalid, "too many M words".to_string()));
                    }
                    let code = code10(v, at, 'M')?;
                    blk.special |= code == 980 || code == 990;
                    blk.m[blk.nm] = (code, at as u32);
                    blk.nm += 1;
                }
                _ => {
                    if blk.mask & (1 << idx) != 0 {
                        return Err((
                            at,
                            ErrorKind::Invalid,
                            format!("{} word repeated on one line", up as char),
                        ));
                    }
                    blk.mask |= 1 << idx;
                    blk.vals[idx] = v;
                    blk.pos[idx] = at as u32;
                }
            }
            continue;
        }
        match c {
            b' ' | b'\t' | b'\r' => i += 1,
            b';' => break,
            b'@' | b'^' => polar_word(b, &mut i, blk, params, sys)?,
            b'(' => {
                let rest = &b[i + 1..];
                let Some(close) = rest.iter().position(|&x| x == b')' || x == b'(') else {
                    return Err((i, ErrorKind::Syntax, "unclosed comment '('".to_string()));
                };
                if rest[close] == b'(' {
                    return Err((
                        i + 1 + close,
                        ErrorKind::Syntax,
                        "nested comment '(' inside a comment".to_string(),
                    ));
                }
                let text = &rest[..close];
                let t = text
                    .iter()
                    .position(|&x| x != b' ' && x != b'\t')
                    .unwrap_or(text.len());
                if text.len() >= t + 4 && text[t..t + 4].eq_ignore_ascii_case(b"msg,") {
                    let s = i + 1 + t + 4;
                    blk.msg = Some((s, i + 1 + close));
                } else if text.len() >= t + 6
                    && (text[t..t + 6].eq_ignore_ascii_case(b"debug,")
                        || text[t..t + 6].eq_ignore_ascii_case(b"print,"))
                {
                    blk.debug = Some((i + 1 + t + 6, i + 1 + close));
                    blk.special = true;
                }
                i += close + 2;
            }
            b'#' => {
                blk.special = true;
                params.sys = sys();
                expr::assignment(b, &mut i, params)?;
            }
            b'[' => {
                return Err((
                    i,
                    ErrorKind::Syntax,
                    "an expression '[...]' must follow a word letter (X[1+2])".to_string(),
                ))
            }
            _ => {
                return Err((i, ErrorKind::Syntax, unexpected(b, i)));
            }
        }
    }
    Ok(LineKind::Words)
}

/// LinuxCNC's polar words: `@radius`, `^angle` (degrees). Out of line so
/// that the number parser stays inlined in the letter path.
#[cold]
#[inline(never)]
fn polar_word(
    b: &[u8],
    i: &mut usize,
    blk: &mut Block,
    params: &mut Params,
    sys: &dyn Fn() -> SysView,
) -> Result<(), LexError> {
    let at = *i;
    let c = b[at];
    let idx = if c == b'@' { POLAR_R } else { POLAR_A };
    *i += 1;
    let after = *i;
    let v = match parse_number(b, i) {
        Ok(v) => v,
        Err(e) => {
            *i = after;
            blk.special = true;
            word_value(b, i, params, sys).ok_or((at, e.1, e.2))??
        }
    };
    if blk.mask & (1 << idx) != 0 {
        return Err((
            at,
            ErrorKind::Invalid,
            format!("{} word repeated on one line", c as char),
        ));
    }
    blk.mask |= 1 << idx;
    blk.vals[idx] = v;
    blk.pos[idx] = at as u32;
    Ok(())
}

/// The value of a word that is not a plain number: `X[..]`, `X#1`, `X-#<a>`,
/// `XSIN[..]`. `None` when it does not start like one (the caller reports its
/// own number error).
#[cold]
fn word_value(
    b: &[u8],
    i: &mut usize,
    params: &mut Params,
    sys: &dyn Fn() -> SysView,
) -> Option<Result<f64, LexError>> {
    let mut j = *i;
    while j < b.len() && matches!(b[j], b' ' | b'\t' | b'-' | b'+') {
        j += 1;
    }
    match b.get(j) {
        Some(b'[' | b'#') => {}
        Some(c)
            if c.is_ascii_alphabetic() && b.get(j + 1).is_some_and(|c| c.is_ascii_alphabetic()) => {
        }
        _ => return None,
    }
    params.sys = sys();
    Some(expr::real_value(b, i, params))
}

#[cold]
fn unexpected(b: &[u8], i: usize) -> String {
    let c = b[i];
    if c.is_ascii_graphic() {
        format!("unexpected character '{}'", c as char)
    } else if c < 0x80 {
        format!("unexpected control character 0x{c:02x}")
    } else {
        let ch = std::str::from_utf8(&b[i..])
            .ok()
            .or_else(|| {
                (2..=4)
                    .filter_map(|n| b.get(i..i + n).and_then(|s| std::str::from_utf8(s).ok()))
                    .next()
            })
            .and_then(|s| s.chars().next());
        match ch {
            Some(ch) => format!("unexpected character '{ch}' outside a comment"),
            None => "unexpected non-ASCII byte outside a comment".to_string(),
        }
    }
}

#[cold]
fn unsupported_letter(up: u8) -> String {
    match up {
        b'B' | b'C' | b'U' | b'V' | b'W' => {
            format!(
                "axis word {} is not supported (X/Y/Z and the rotary A axis only)",
                up as char
            )
        }
        b'E' => "E word (extruder) is not supported".to_string(),
        _ => format!("{} word is not supported", up as char),
    }
}

/// G/M number as value * 10 (G90.1 -> 901); at most one decimal.
#[inline]
fn code10(v: f64, at: usize, letter: char) -> Result<u16, LexError> {
    let t = v * 10.0;
    // Round by truncating t + 0.5 (t >= 0 here): f64::round is a libm call
    // on baseline x86-64, visible in profiles at one G word per line.
    let r = if (-0.5..9999.5).contains(&t) {
        f64::from((t + 0.5) as u16)
    } else {
        -1.0
    };
    if r < 0.0 || (t - r).abs() > 1e-6 {
        return Err((
            at,
            ErrorKind::Syntax,
            format!("invalid {letter} number {v}"),
        ));
    }
    Ok(r as u16)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]
    use super::*;

    fn lex(b: &[u8], bd: bool, blk: &mut Block) -> Result<LineKind, LexError> {
        lex_line(b, bd, blk, &mut Params::default(), &SysView::default)
    }

    fn num(s: &str) -> f64 {
        let mut i = 0;
        parse_number(s.as_bytes(), &mut i).unwrap()
    }

    #[test]
    fn numbers_match_std() {
        for s in [
            "0",
            "1",
            "-1",
            "+2.5",
            ".5",
            "5.",
            "-.001",
            "123.456789",
            "0.1",
            "3.14159265358979323846264",
            "99999999999999999999.5",
            "-0.000",
        ] {
            let expect: f64 = s.parse().unwrap();
            assert_eq!(num(s), expect, "{s}");
        }
        assert_eq!(num(" - 1 2 . 5"), -12.5);
        assert_eq!(num("1 2"), 12.0);
        assert_eq!(num("1.5 Y"), 1.5);
        assert_eq!(num("12345678901234567890.5"), 12345678901234567890.5);
    }

    #[test]
    fn lexes_words_and_comments() {
        let mut b = Block::new();
        let k = lex(b"n10 g1x1.5 (msg, hi there) y-2 ; z", true, &mut b).unwrap();
        assert_eq!(k, LineKind::Words);
        assert_eq!(b.get(b'X'), Some(1.5));
        assert_eq!(b.get(b'Y'), Some(-2.0));
        assert_eq!(b.get(b'Z'), None);
        assert_eq!(b.ng, 1);
        assert_eq!(b.g[0].0, 10);
        assert!(b.msg.is_some());
        assert!(lex(b"G1 (open", true, &mut b).is_err());
        assert_eq!(lex(b"/G1 X1", true, &mut b).unwrap(), LineKind::Deleted);
        assert_eq!(lex(b" % ", true, &mut b).unwrap(), LineKind::Percent);
        assert_eq!(lex(b"O100 sub", true, &mut b).unwrap(), LineKind::OWord(0));
    }
}
