//! Parameters (`#1`, `#<name>`, `#<_global>`) and `[...]` expressions, as in
//! LinuxCNC. Only reached when a line has a `#`, `[` or O-word: plain CAM
//! programs never touch this module, so their path stays allocation-free.

use crate::lex::{parse_number, LexError};
use crate::{ErrorKind, Point, MAX_EXPRESSION_DEPTH};
use std::collections::HashMap;

/// Numbered parameters #1..#5601 (LinuxCNC's RS274NGC_MAX_PARAMETERS).
pub(crate) const NUMBERED: usize = 5602;
/// Subroutine arguments are #1..#30.
pub(crate) const SUB_PARAMS: usize = 30;
/// LinuxCNC's installed rs274 compares EQ/NE/LE/GE with this tolerance.
const TOLERANCE_EQUAL: f64 = 1e-4;

/// The interpreter state that system parameters read (#5161.., #5420..,
/// `#<_x>`...). Lengths are mm; reads convert to the program's units.
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct SysView {
    pub pos: Point,
    /// A axis (degrees): position, G28/G30 stored, G92 in effect and stored.
    pub pos_a: f64,
    pub g28_a: f64,
    pub g30_a: f64,
    pub g92_a: f64,
    pub g92_saved_a: f64,
    pub inch: bool,
    pub absolute: bool,
    /// 0..9 = G54..G59.3.
    pub coord: u8,
    pub tool: u32,
    pub g28: Point,
    pub g30: Point,
    pub g92: Point,
    pub g92_saved: Point,
    pub feed_mm_min: f64,
    pub rpm: f64,
    pub plane: u16,
    pub motion_g10: i32,
}

/// Where an assignment goes.
#[derive(Debug, Clone)]
pub(crate) enum Target {
    Numbered(usize),
    Named(String),
}

#[derive(Default)]
pub(crate) struct Params {
    /// Allocated on first use.
    numbered: Vec<f64>,
    globals: HashMap<String, f64>,
    /// One scope per call level; index 0 is the main program.
    locals: Vec<HashMap<String, f64>>,
    /// Assignments of the line being read: LinuxCNC applies them after the
    /// whole line is read, so `#1=2 X#1` uses the old #1.
    pub pending: Vec<(Target, f64)>,
    pub sys: SysView,
    pub work_offsets: [Point; 9],
    /// `#<_value>` of the last return/endsub, and whether one was returned.
    pub value: f64,
    pub value_returned: bool,
    /// A `#<name>` was read or written since the interpreter last looked.
    pub named_used: bool,
    name_buf: String,
    /// Nesting levels of the value being read (see [`nested`]).
    depth: usize,
}

impl Params {
    pub fn new(work_offsets: [Point; 9]) -> Self {
        Params {
            work_offsets,
            ..Params::default()
        }
    }

    /// A probe's result: #5061..#5063 where it tripped (program units),
    /// #5064..#5069 (A B C U V W) 0, #5070 1 if it tripped, else 0.
    pub fn set_probe(&mut self, trip: [f64; 3], tripped: bool) {
        let v = self.numbered_mut();
        v[5061..=5063].copy_from_slice(&trip);
        v[5064..=5069].fill(0.0);
        v[5070] = if tripped { 1.0 } else { 0.0 };
    }

    /// Mach3's G31 result: the trip in #2000..#2002 (program coordinates and units), where
    /// Mach3 programs (autolevellers) read it. Ordinary numbered parameters otherwise.
    pub fn set_mach3_probe(&mut self, trip: [f64; 3]) {
        self.numbered_mut()[2000..=2002].copy_from_slice(&trip);
    }

    fn numbered_mut(&mut self) -> &mut Vec<f64> {
        if self.numbered.is_empty() {
            self.numbered = vec![0.0; NUMBERED];
        }
        &mut self.numbered
    }

    fn unit(&self) -> f64 {
        if self.sys.inch {
            25.4
        } else {
            1.0
        }
    }

    /// Value of numbered parameter `n` (1..5601); system ones mirror the state.
    pub fn get_numbered(&self, n: usize) -> f64 {
        let u = self.unit();
        let s = &self.sys;
        match n {
            5161..=5163 => s.g28[n - 5161] / u,
            5164 => s.g28_a,
            5181..=5183 => s.g30[n - 5181] / u,
            5184 => s.g30_a,
            5210 => {
                if s.g92 == [0.0; 3] && s.g92_a == 0.0 {
                    0.0
                } else {
                    1.0
                }
            }
            5211..=5213 => s.g92_saved[n - 5211] / u,
            5214 => s.g92_saved_a,
            5220 => f64::from(s.coord) + 1.0,
            5221..=5399 => {
                let k = (n - 5221) / 20;
                let i = (n - 5221) % 20;
                if k < 9 && i < 3 {
                    self.work_offsets[k][i] / u
                } else {
                    self.numbered.get(n).copied().unwrap_or(0.0)
                }
            }
            5400 => f64::from(s.tool),
            5420..=5422 => s.pos[n - 5420] / u,
            5423 => s.pos_a,
            5424..=5428 => 0.0,
            _ => self.numbered.get(n).copied().unwrap_or(0.0),
        }
    }

    /// Subroutine arguments #1..#30 of the current level.
    pub fn sub_params(&self) -> [f64; SUB_PARAMS] {
        let mut v = [0.0; SUB_PARAMS];
        if !self.numbered.is_empty() {
            v.copy_from_slice(&self.numbered[1..=SUB_PARAMS]);
        }
        v
    }

    pub fn set_sub_params(&mut self, v: &[f64; SUB_PARAMS]) {
        self.numbered_mut()[1..=SUB_PARAMS].copy_from_slice(v);
    }

    pub fn push_scope(&mut self) {
        self.locals.push(HashMap::new());
    }

    pub fn pop_scope(&mut self) {
        self.locals.pop();
    }

    fn get_named(&self, name: &str) -> Option<f64> {
        if let Some(rest) = name.strip_prefix('_') {
            if let Some(v) = self.globals.get(name) {
                return Some(*v);
            }
            return self.builtin(rest);
        }
        self.locals.last().and_then(|m| m.get(name)).copied()
    }

    /// Read-only `#<_name>` values that mirror the interpreter's state.
    fn builtin(&self, rest: &str) -> Option<f64> {
        let s = &self.sys;
        let u = self.unit();
        let b = |c: bool| if c { 1.0 } else { 0.0 };
        Some(match rest {
            "x" => s.pos[0] / u,
            "y" => s.pos[1] / u,
            "z" => s.pos[2] / u,
            "a" => s.pos_a,
            "b" | "c" | "u" | "v" | "w" => 0.0,
            "metric" => b(!s.inch),
            "imperial" => b(s.inch),
            "absolute" => b(s.absolute),
            "incremental" => b(!s.absolute),
            "coord_system" => match s.coord {
                0..=5 => 540.0 + 10.0 * f64::from(s.coord),
                c => 584.0 + f64::from(c),
            },
            "current_tool" | "selected_tool" => f64::from(s.tool),
            "feed" => s.feed_mm_min / u,
            "rpm" => s.rpm,
            "plane" => f64::from(s.plane),
            "motion_mode" => f64::from(s.motion_g10),
            "value" => self.value,
            "value_returned" => b(self.value_returned),
            _ => return None,
        })
    }

    /// Applies the line's assignments (LinuxCNC: after the line is read).
    pub fn commit(&mut self) {
        let pending = std::mem::take(&mut self.pending);
        for (t, v) in &pending {
            match t {
                Target::Numbered(n) => self.numbered_mut()[*n] = *v,
                Target::Named(name) => {
                    if name.starts_with('_') {
                        self.globals.insert(name.clone(), *v);
                    } else {
                        if self.locals.is_empty() {
                            self.locals.push(HashMap::new());
                        }
                        if let Some(m) = self.locals.last_mut() {
                            m.insert(name.clone(), *v);
                        }
                    }
                }
            }
        }
        self.pending = pending;
        self.pending.clear();
    }
}

#[inline]
fn skip_blanks(b: &[u8], i: &mut usize) {
    while *i < b.len() && (b[*i] == b' ' || b[*i] == b'\t') {
        *i += 1;
    }
}

fn err(at: usize, kind: ErrorKind, msg: impl Into<String>) -> LexError {
    (at, kind, msg.into())
}

/// Runs `read` one nesting level deeper: every `[`, `#` and unary sign that holds a further
/// value is one level. The reader recurses once per level, so without this bound the input
/// would decide how deep the stack goes (`X[[[[...` 4,000 deep overflowed a 2 MiB thread).
#[inline]
fn nested<T>(
    p: &mut Params,
    at: usize,
    read: impl FnOnce(&mut Params) -> Result<T, LexError>,
) -> Result<T, LexError> {
    if p.depth >= MAX_EXPRESSION_DEPTH {
        return Err(too_deep(at));
    }
    p.depth += 1;
    let r = read(p);
    p.depth -= 1;
    r
}

#[cold]
fn too_deep(at: usize) -> LexError {
    err(
        at,
        ErrorKind::Invalid,
        format!(
            "expression nested deeper than the limit of {MAX_EXPRESSION_DEPTH} levels (each '[', '#' and unary sign counts one)"
        ),
    )
}

/// An operator's or function's result that overflowed: no value that is not finite gets
/// into a word, a parameter or a condition.
#[inline]
fn finite(v: f64, at: usize, what: impl FnOnce() -> String) -> Result<f64, LexError> {
    if v.is_finite() {
        Ok(v)
    } else {
        Err(overflow(at, what()))
    }
}

#[cold]
fn overflow(at: usize, what: String) -> LexError {
    err(
        at,
        ErrorKind::Invalid,
        format!("{what} overflows: the result is not a finite number"),
    )
}

/// Reads `<name>` at `*i` (just after `#`), lower-cased and without blanks
/// (LinuxCNC ignores both), into `out`.
fn read_name(b: &[u8], i: &mut usize, out: &mut String) -> Result<(), LexError> {
    // (No Params here: callers mark `named_used`.)
    let open = *i;
    *i += 1; // '<'
    out.clear();
    while *i < b.len() && b[*i] != b'>' {
        let c = b[*i];
        if c != b' ' && c != b'\t' {
            out.push(c.to_ascii_lowercase() as char);
        }
        *i += 1;
    }
    if *i >= b.len() {
        return Err(err(
            open,
            ErrorKind::Syntax,
            "parameter name '<' without closing '>'",
        ));
    }
    *i += 1; // '>'
    if out.is_empty() {
        return Err(err(open, ErrorKind::Syntax, "empty parameter name '#<>'"));
    }
    Ok(())
}

/// Parameter number from a value: an integer from 1 to 5601.
fn param_index(v: f64, at: usize) -> Result<usize, LexError> {
    let r = v.round();
    if (v - r).abs() > 1e-4 || !(1.0..(NUMBERED as f64)).contains(&r) {
        return Err(err(
            at,
            ErrorKind::Invalid,
            format!("parameter number {v} out of range (1 to {})", NUMBERED - 1),
        ));
    }
    Ok(r as usize)
}

/// After `#` at `b[at]`: the target of an assignment or read.
fn param_target(b: &[u8], i: &mut usize, p: &mut Params, at: usize) -> Result<Target, LexError> {
    skip_blanks(b, i);
    if *i < b.len() && b[*i] == b'<' {
        p.named_used = true;
        let mut name = std::mem::take(&mut p.name_buf);
        let r = read_name(b, i, &mut name);
        let t = name.clone();
        p.name_buf = name;
        r?;
        Ok(Target::Named(t))
    } else {
        let v = nested(p, at, |p| real_value(b, i, p))?;
        Ok(Target::Numbered(param_index(v, at)?))
    }
}

/// Reads a parameter reference starting at `#` and returns its value.
fn read_param(b: &[u8], i: &mut usize, p: &mut Params) -> Result<f64, LexError> {
    let at = *i;
    nested(p, at, |p| read_param_in(b, i, p, at))
}

fn read_param_in(b: &[u8], i: &mut usize, p: &mut Params, at: usize) -> Result<f64, LexError> {
    *i += 1;
    skip_blanks(b, i);
    if *i < b.len() && b[*i] == b'<' {
        p.named_used = true;
        let mut name = std::mem::take(&mut p.name_buf);
        let r = read_name(b, i, &mut name).map(|()| p.get_named(&name));
        let r = match r {
            Ok(Some(v)) => Ok(v),
            Ok(None) => Err(err(
                at,
                ErrorKind::Invalid,
                format!("named parameter #<{name}> is not defined"),
            )),
            Err(e) => Err(e),
        };
        p.name_buf = name;
        return r;
    }
    let v = real_value(b, i, p)?;
    Ok(p.get_numbered(param_index(v, at)?))
}

/// `#n = value` or `#<name> = value` at `b[*i] == '#'`: recorded in
/// `p.pending`, applied after the line.
pub(crate) fn assignment(b: &[u8], i: &mut usize, p: &mut Params) -> Result<(), LexError> {
    let at = *i;
    *i += 1;
    let target = param_target(b, i, p, at)?;
    if let Target::Named(name) = &target {
        if name
            .strip_prefix('_')
            .is_some_and(|r| p.builtin(r).is_some())
        {
            return Err(err(
                at,
                ErrorKind::Invalid,
                format!("cannot assign to read-only parameter #<{name}>"),
            ));
        }
    }
    skip_blanks(b, i);
    if *i >= b.len() || b[*i] != b'=' {
        return Err(err(
            at,
            ErrorKind::Syntax,
            "a parameter at the start of a word must be assigned ('#1 = ...')",
        ));
    }
    *i += 1;
    let v = real_value(b, i, p)?;
    p.pending.push((target, v));
    Ok(())
}

/// A real value: number, `[expression]`, parameter, unary function or sign.
pub(crate) fn real_value(b: &[u8], i: &mut usize, p: &mut Params) -> Result<f64, LexError> {
    skip_blanks(b, i);
    let at = *i;
    let Some(&c) = b.get(*i) else {
        return Err(err(at, ErrorKind::Syntax, "expected a value"));
    };
    match c {
        b'[' => expression(b, i, p),
        b'#' => read_param(b, i, p),
        b'-' | b'+' => {
            // "-1.5" is a number; "-[..]", "-#1", "-sin[..]" negate a value.
            let mut j = *i + 1;
            skip_blanks(b, &mut j);
            if b.get(j).is_some_and(|c| c.is_ascii_digit() || *c == b'.') {
                return parse_number(b, i);
            }
            *i = j;
            let v = nested(p, at, |p| real_value(b, i, p))?;
            Ok(if c == b'-' { -v } else { v })
        }
        b'0'..=b'9' | b'.' => parse_number(b, i),
        c if c.is_ascii_alphabetic() => function(b, i, p),
        _ => Err(err(
            at,
            ErrorKind::Syntax,
            format!("expected a value, found '{}'", c as char),
        )),
    }
}

/// `[ ... ]` at `b[*i] == '['`.
pub(crate) fn expression(b: &[u8], i: &mut usize, p: &mut Params) -> Result<f64, LexError> {
    let open = *i;
    nested(p, open, |p| expression_in(b, i, p, open))
}

fn expression_in(b: &[u8], i: &mut usize, p: &mut Params, open: usize) -> Result<f64, LexError> {
    *i += 1;
    let v = binary(b, i, p, 0)?;
    skip_blanks(b, i);
    if b.get(*i) != Some(&b']') {
        return Err(err(
            open,
            ErrorKind::Syntax,
            match b.get(*i) {
                Some(&c) => format!(
                    "expected ']' to close the expression, found '{}'",
                    c as char
                ),
                None => "expression '[' without closing ']'".to_string(),
            },
        ));
    }
    *i += 1;
    Ok(v)
}

#[derive(Clone, Copy, PartialEq)]
enum Op {
    Pow,
    Mul,
    Div,
    Mod,
    Add,
    Sub,
    Eq,
    Ne,
    Gt,
    Ge,
    Lt,
    Le,
    And,
    Or,
    Xor,
}

impl Op {
    fn symbol(self) -> &'static str {
        match self {
            Op::Pow => "**",
            Op::Mul => "*",
            Op::Div => "/",
            Op::Mod => "MOD",
            Op::Add => "+",
            Op::Sub => "-",
            Op::Eq => "EQ",
            Op::Ne => "NE",
            Op::Gt => "GT",
            Op::Ge => "GE",
            Op::Lt => "LT",
            Op::Le => "LE",
            Op::And => "AND",
            Op::Or => "OR",
            Op::Xor => "XOR",
        }
    }

    /// LinuxCNC's precedence (interp_internal.cc `precedence`).
    fn prec(self) -> u8 {
        match self {
            Op::Pow => 6,
            Op::Mul | Op::Div | Op::Mod => 5,
            Op::Add | Op::Sub => 4,
            Op::Eq | Op::Ne | Op::Gt | Op::Ge | Op::Lt | Op::Le => 3,
            Op::And | Op::Or | Op::Xor => 2,
        }
    }
}

fn peek_op(b: &[u8], i: usize) -> Option<(Op, usize)> {
    let c = *b.get(i)?;
    let word = |w: &[u8]| {
        b.get(i..i + w.len())
            .is_some_and(|s| s.eq_ignore_ascii_case(w))
    };
    Some(match c {
        b'*' if b.get(i + 1) == Some(&b'*') => (Op::Pow, 2),
        b'*' => (Op::Mul, 1),
        b'/' => (Op::Div, 1),
        b'+' => (Op::Add, 1),
        b'-' => (Op::Sub, 1),
        _ if word(b"mod") => (Op::Mod, 3),
        _ if word(b"eq") => (Op::Eq, 2),
        _ if word(b"ne") => (Op::Ne, 2),
        _ if word(b"gt") => (Op::Gt, 2),
        _ if word(b"ge") => (Op::Ge, 2),
        _ if word(b"lt") => (Op::Lt, 2),
        _ if word(b"le") => (Op::Le, 2),
        _ if word(b"and") => (Op::And, 3),
        _ if word(b"or") => (Op::Or, 2),
        _ if word(b"xor") => (Op::Xor, 3),
        _ => return None,
    })
}

fn binary(b: &[u8], i: &mut usize, p: &mut Params, min_prec: u8) -> Result<f64, LexError> {
    let mut lhs = real_value(b, i, p)?;
    loop {
        skip_blanks(b, i);
        let Some((op, len)) = peek_op(b, *i) else {
            return Ok(lhs);
        };
        if op.prec() < min_prec {
            return Ok(lhs);
        }
        let at = *i;
        *i += len;
        // Left-associative: the right side binds only tighter operators.
        let rhs = binary(b, i, p, op.prec() + 1)?;
        lhs = apply(op, lhs, rhs, at)?;
    }
}

fn truth(c: bool) -> f64 {
    if c {
        1.0
    } else {
        0.0
    }
}

fn apply(op: Op, l: f64, r: f64, at: usize) -> Result<f64, LexError> {
    let v = apply_in(op, l, r, at)?;
    finite(v, at, || format!("'{}'", op.symbol()))
}

fn apply_in(op: Op, l: f64, r: f64, at: usize) -> Result<f64, LexError> {
    Ok(match op {
        Op::Pow => {
            if l < 0.0 && r.fract() != 0.0 {
                return Err(err(
                    at,
                    ErrorKind::Invalid,
                    "attempt to raise a negative number to a non-integer power",
                ));
            }
            l.powf(r)
        }
        Op::Mul => l * r,
        Op::Div => {
            if r == 0.0 {
                return Err(err(at, ErrorKind::Invalid, "division by zero"));
            }
            l / r
        }
        Op::Mod => {
            if r == 0.0 {
                return Err(err(at, ErrorKind::Invalid, "MOD by zero"));
            }
            let m = l % r;
            if m < 0.0 {
                m + r.abs()
            } else {
                m
            }
        }
        Op::Add => l + r,
        Op::Sub => l - r,
        Op::Eq => truth((l - r).abs() < TOLERANCE_EQUAL),
        Op::Ne => truth((l - r).abs() >= TOLERANCE_EQUAL),
        Op::Gt => truth(l > r),
        Op::Ge => truth((l - r).abs() < TOLERANCE_EQUAL || l >= r),
        Op::Lt => truth(l < r),
        Op::Le => truth((l - r).abs() < TOLERANCE_EQUAL || l <= r),
        Op::And => truth(l != 0.0 && r != 0.0),
        Op::Or => truth(l != 0.0 || r != 0.0),
        Op::Xor => truth((l != 0.0) != (r != 0.0)),
    })
}

/// `NAME[expr]`, `ATAN[a]/[b]`, `EXISTS[#<name>]`.
fn function(b: &[u8], i: &mut usize, p: &mut Params) -> Result<f64, LexError> {
    let at = *i;
    let start = *i;
    while *i < b.len() && b[*i].is_ascii_alphabetic() {
        *i += 1;
    }
    let mut name = [0u8; 8];
    let word = &b[start..*i];
    let n = word.len().min(8);
    for (d, s) in name.iter_mut().zip(word) {
        *d = s.to_ascii_lowercase();
    }
    let name = &name[..n];
    let unknown = || {
        err(
            at,
            ErrorKind::Syntax,
            format!(
                "unknown function or value '{}'",
                String::from_utf8_lossy(word)
            ),
        )
    };
    if word.len() > 6 {
        return Err(unknown());
    }
    skip_blanks(b, i);
    if b.get(*i) != Some(&b'[') {
        return Err(err(
            at,
            ErrorKind::Syntax,
            format!(
                "function {} needs its argument in brackets",
                String::from_utf8_lossy(word).to_uppercase()
            ),
        ));
    }
    if name == b"exists" {
        p.named_used = true;
        let open = *i;
        *i += 1;
        skip_blanks(b, i);
        if b.get(*i) != Some(&b'#') {
            return Err(err(open, ErrorKind::Syntax, "EXISTS needs #<name>"));
        }
        *i += 1;
        skip_blanks(b, i);
        if b.get(*i) != Some(&b'<') {
            return Err(err(open, ErrorKind::Syntax, "EXISTS needs #<name>"));
        }
        let mut nm = std::mem::take(&mut p.name_buf);
        let r = read_name(b, i, &mut nm).map(|()| p.get_named(&nm).is_some());
        p.name_buf = nm;
        let found = r?;
        skip_blanks(b, i);
        if b.get(*i) != Some(&b']') {
            return Err(err(
                open,
                ErrorKind::Syntax,
                "expected ']' after EXISTS[#<name>",
            ));
        }
        *i += 1;
        return Ok(truth(found));
    }
    let arg_at = *i;
    let v = expression(b, i, p)?;
    let domain = |what: &str| err(arg_at, ErrorKind::Invalid, what.to_string());
    let v = function_of(name, v, b, i, p, at, domain, unknown)?;
    finite(v, at, || String::from_utf8_lossy(word).to_uppercase())
}

/// The value of function `name` (lower case) of `v`; ATAN reads its second argument.
#[allow(clippy::too_many_arguments)]
fn function_of(
    name: &[u8],
    v: f64,
    b: &[u8],
    i: &mut usize,
    p: &mut Params,
    at: usize,
    domain: impl Fn(&str) -> LexError,
    unknown: impl Fn() -> LexError,
) -> Result<f64, LexError> {
    Ok(match name {
        b"abs" => v.abs(),
        b"acos" => {
            if !(-1.0..=1.0).contains(&v) {
                return Err(domain("ACOS argument out of range (-1 to 1)"));
            }
            v.acos().to_degrees()
        }
        b"asin" => {
            if !(-1.0..=1.0).contains(&v) {
                return Err(domain("ASIN argument out of range (-1 to 1)"));
            }
            v.asin().to_degrees()
        }
        b"atan" => {
            skip_blanks(b, i);
            if b.get(*i) != Some(&b'/') {
                return Err(err(
                    at,
                    ErrorKind::Syntax,
                    "ATAN needs two arguments: ATAN[y]/[x]",
                ));
            }
            *i += 1;
            skip_blanks(b, i);
            if b.get(*i) != Some(&b'[') {
                return Err(err(
                    at,
                    ErrorKind::Syntax,
                    "ATAN needs two arguments: ATAN[y]/[x]",
                ));
            }
            let x = expression(b, i, p)?;
            v.atan2(x).to_degrees()
        }
        b"cos" => v.to_radians().cos(),
        b"sin" => v.to_radians().sin(),
        b"tan" => v.to_radians().tan(),
        b"exp" => v.exp(),
        b"fix" => v.floor(),
        b"fup" => v.ceil(),
        b"round" => v.round(),
        b"ln" => {
            if v <= 0.0 {
                return Err(domain("LN of zero or a negative number"));
            }
            v.ln()
        }
        b"sqrt" => {
            if v < 0.0 {
                return Err(domain("SQRT of a negative number"));
            }
            v.sqrt()
        }
        _ => return Err(unknown()),
    })
}

/// `(print, ...)` / `(debug, ...)` text with `#n` / `#<name>` replaced by
/// their values (`%f`, as LinuxCNC prints them); unknown names stay as written.
pub(crate) fn substitute(text: &[u8], p: &mut Params) -> String {
    let mut out = String::new();
    let mut i = 0;
    while i < text.len() {
        if text[i] == b'#' {
            let mut j = i + 1;
            let v = if text.get(j) == Some(&b'<') {
                let mut nm = std::mem::take(&mut p.name_buf);
                let v = read_name(text, &mut j, &mut nm)
                    .ok()
                    .and_then(|()| p.get_named(&nm));
                p.name_buf = nm;
                v
            } else {
                let s = j;
                while j < text.len() && text[j].is_ascii_digit() {
                    j += 1;
                }
                std::str::from_utf8(&text[s..j])
                    .ok()
                    .and_then(|d| d.parse::<usize>().ok())
                    .filter(|n| (1..NUMBERED).contains(n))
                    .map(|n| p.get_numbered(n))
            };
            match v {
                Some(v) => {
                    out.push_str(&format!("{v:.6}"));
                    i = j;
                    continue;
                }
                None => {
                    out.push('#');
                    i += 1;
                    continue;
                }
            }
        }
        let len = match text[i] {
            c if c < 0x80 => 1,
            c if c >= 0xF0 => 4,
            c if c >= 0xE0 => 3,
            _ => 2,
        };
        out.push_str(&String::from_utf8_lossy(
            &text[i..(i + len).min(text.len())],
        ));
        i += len;
    }
    out
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn eval(s: &str) -> Result<f64, LexError> {
        let mut p = Params::default();
        let mut i = 0;
        real_value(s.as_bytes(), &mut i, &mut p)
    }

    #[test]
    fn operators_follow_linuxcnc() {
        // Values from rs274 -g on the same expressions.
        assert_eq!(eval("[10 MOD -3]").unwrap(), 1.0);
        assert_eq!(eval("[-10 MOD 3]").unwrap(), 2.0);
        assert_eq!(eval("[2**3]").unwrap(), 8.0);
        assert_eq!(eval("[-2**2]").unwrap(), 4.0);
        assert_eq!(eval("[ROUND[-2.5]]").unwrap(), -3.0);
        assert_eq!(eval("[FIX[-2.5]]").unwrap(), -3.0);
        assert_eq!(eval("[ATAN[1]/[1]]").unwrap(), 45.0);
        assert_eq!(eval("[1 EQ 1.00011]").unwrap(), 0.0);
        assert_eq!(eval("[1+2*3]").unwrap(), 7.0);
        assert_eq!(eval("[2*3 GT 5 AND 1]").unwrap(), 1.0);
        assert_eq!(eval("[3 XOR 1]").unwrap(), 0.0);
        assert_eq!(eval("[8/2/2]").unwrap(), 2.0);
        assert_eq!(eval("[2**3**2]").unwrap(), 64.0);
        assert!(eval("[1/0]").is_err());
        assert!(eval("[SQRT[-1]]").is_err());
        assert!(eval("[1+2").is_err());
    }
}
