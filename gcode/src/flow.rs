//! O-word control flow (LinuxCNC `sub`/`call`/`if`/`while`/`do`/`repeat`,
//! Fanuc/Mach3 `O<n>` with `M98 P L` / `M99`): the parsed O-word line, the
//! program text kept for jumps, call frames and open blocks.
//!
//! The interpreter reads a stream; a loop or a call has to go back. From the
//! first O-word line on, every line read is kept (`Program`), so jumps are
//! indices into it. Programs without O-words never buffer.

use crate::expr::SUB_PARAMS;
use crate::lex::LexError;
use crate::ErrorKind;
use std::collections::HashMap;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Keyword {
    Sub,
    EndSub,
    Call,
    Return,
    If,
    ElseIf,
    Else,
    EndIf,
    While,
    EndWhile,
    Do,
    Repeat,
    EndRepeat,
    Break,
    Continue,
    /// `O1000` alone: a Fanuc/Mach3 program number (start of an M98 subprogram).
    Number,
}

impl Keyword {
    pub fn name(self) -> &'static str {
        match self {
            Keyword::Sub => "sub",
            Keyword::EndSub => "endsub",
            Keyword::Call => "call",
            Keyword::Return => "return",
            Keyword::If => "if",
            Keyword::ElseIf => "elseif",
            Keyword::Else => "else",
            Keyword::EndIf => "endif",
            Keyword::While => "while",
            Keyword::EndWhile => "endwhile",
            Keyword::Do => "do",
            Keyword::Repeat => "repeat",
            Keyword::EndRepeat => "endrepeat",
            Keyword::Break => "break",
            Keyword::Continue => "continue",
            Keyword::Number => "program number",
        }
    }
}

/// One O-word line: `o<name> keyword rest...`.
pub(crate) struct OLine {
    /// Lower case, blanks removed; numbers without leading zeros (`O0100` = `o100`).
    pub name: String,
    pub kw: Keyword,
    /// Byte offset after the keyword (arguments / condition follow).
    pub rest: usize,
}

/// Offset of a leading O-word (after blanks and an optional N word), for
/// lines that are skipped without being lexed.
pub(crate) fn o_at(b: &[u8]) -> Option<usize> {
    let mut i = 0;
    let blanks = |i: &mut usize| {
        while *i < b.len() && (b[*i] == b' ' || b[*i] == b'\t') {
            *i += 1;
        }
    };
    blanks(&mut i);
    if i < b.len() && (b[i] == b'/') {
        i += 1;
        blanks(&mut i);
    }
    if i < b.len() && (b[i] | 0x20) == b'n' {
        i += 1;
        while i < b.len() && (b[i].is_ascii_digit() || b[i] == b' ' || b[i] == b'.') {
            i += 1;
        }
    }
    (i < b.len() && (b[i] | 0x20) == b'o').then_some(i)
}

/// Parses the O-word at `b[at]`.
pub(crate) fn parse(b: &[u8], at: usize) -> Result<OLine, LexError> {
    let mut i = at + 1;
    let blanks = |i: &mut usize| {
        while *i < b.len() && (b[*i] == b' ' || b[*i] == b'\t') {
            *i += 1;
        }
    };
    blanks(&mut i);
    let mut name = String::new();
    if b.get(i) == Some(&b'<') {
        i += 1;
        while i < b.len() && b[i] != b'>' {
            if b[i] != b' ' && b[i] != b'\t' {
                name.push(b[i].to_ascii_lowercase() as char);
            }
            i += 1;
        }
        if i >= b.len() {
            return Err((
                at,
                ErrorKind::Syntax,
                "O-word name '<' without closing '>'".into(),
            ));
        }
        i += 1;
    } else {
        let s = i;
        while i < b.len() && (b[i].is_ascii_digit() || b[i] == b' ') {
            i += 1;
        }
        let digits: String = b[s..i]
            .iter()
            .filter(|c| c.is_ascii_digit())
            .map(|&c| c as char)
            .collect();
        let n: u64 = digits.parse().map_err(|_| {
            (
                at,
                ErrorKind::Syntax,
                "O-word needs a number or a <name>".to_string(),
            )
        })?;
        name = n.to_string();
    }
    if name.is_empty() {
        return Err((at, ErrorKind::Syntax, "empty O-word name 'o<>'".into()));
    }
    blanks(&mut i);
    let s = i;
    while i < b.len() && b[i].is_ascii_alphabetic() {
        i += 1;
    }
    let word = b[s..i].to_ascii_lowercase();
    let kw = match word.as_slice() {
        b"sub" => Keyword::Sub,
        b"endsub" => Keyword::EndSub,
        b"call" => Keyword::Call,
        b"return" => Keyword::Return,
        b"if" => Keyword::If,
        b"elseif" => Keyword::ElseIf,
        b"else" => Keyword::Else,
        b"endif" => Keyword::EndIf,
        b"while" => Keyword::While,
        b"endwhile" => Keyword::EndWhile,
        b"do" => Keyword::Do,
        b"repeat" => Keyword::Repeat,
        b"endrepeat" => Keyword::EndRepeat,
        b"break" => Keyword::Break,
        b"continue" => Keyword::Continue,
        b"" => Keyword::Number,
        _ => {
            return Err((
                s,
                ErrorKind::Syntax,
                format!(
                    "unknown O-word keyword '{}'",
                    String::from_utf8_lossy(&b[s..i])
                ),
            ))
        }
    };
    Ok(OLine { name, kw, rest: i })
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum BlockKind {
    If { taken: bool },
    While,
    Do,
    Repeat,
}

impl BlockKind {
    /// The O-word that opens the block.
    pub fn keyword(self) -> &'static str {
        match self {
            BlockKind::If { .. } => "if",
            BlockKind::While => "while",
            BlockKind::Do => "do",
            BlockKind::Repeat => "repeat",
        }
    }
}

/// An open if/loop: its name, kind, the index of its opening line, and
/// (repeat) how many passes are left.
#[derive(Debug, Clone)]
pub(crate) struct OpenBlock {
    pub name: String,
    pub kind: BlockKind,
    pub start: usize,
    pub left: f64,
}

/// A subroutine call in progress.
pub(crate) struct Frame {
    pub name: String,
    /// Index of the line after the call.
    pub return_to: usize,
    /// Index of the first body line (M98 repeats go back here).
    pub body: usize,
    /// The caller's #1..#30.
    pub saved: [f64; SUB_PARAMS],
    /// Open blocks of the caller (restored on return).
    pub blocks: Vec<OpenBlock>,
    /// M98 L: passes left after this one; `None` for an O-word call.
    pub m98_left: Option<u32>,
    pub call_line: u32,
}

/// Lines are not interpreted until the O-word `name` with one of `until`.
pub(crate) struct Skip {
    pub name: String,
    pub until: &'static [Keyword],
    /// Whether the matching line is skipped too (an `endsub` after a
    /// definition) or then interpreted (`else`, `endif`, ...).
    pub inclusive: bool,
    /// Searching a subroutine to call (defined further down): the call.
    pub then_call: Option<PendingCall>,
    /// Line of the O-word that started the skip (for "file ended" errors).
    pub from_line: u32,
}

pub(crate) struct PendingCall {
    pub args: [f64; SUB_PARAMS],
    pub return_to: usize,
    pub m98_times: Option<u32>,
    pub call_line: u32,
}

/// The kept program text, as lines (source line number, byte range).
#[derive(Default)]
pub(crate) struct Program {
    pub text: Vec<u8>,
    pub lines: Vec<(u32, usize, usize)>,
}

#[derive(Default)]
pub(crate) struct Flow {
    /// Lines are being kept (an O-word was seen).
    pub buffering: bool,
    pub prog: Program,
    /// Index of the next line to run (== `prog.lines.len()`: read a new one).
    pub pc: usize,
    /// Index of the line being run.
    pub cur: usize,
    /// Subroutine name -> index of its `sub` (or `O<n>`) line.
    pub subs: HashMap<String, usize>,
    pub frames: Vec<Frame>,
    pub blocks: Vec<OpenBlock>,
    pub skip: Option<Skip>,
    /// Backward jumps and calls so far (loop passes, M98 repeats, calls), bounded by
    /// `Config::max_loop_iterations`.
    pub jumps: u64,
}
