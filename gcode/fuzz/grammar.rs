//! A byte-driven G-code generator for structure-aware fuzzing: the fuzzer's bytes are read as
//! choices in a small grammar of G-code, so that its mutations stay programs and reach what
//! random bytes never do in 10 M tries: nesting 100,000 levels deep, numbers like `10**300`,
//! values on and just past every limit, one construct repeated thousands of times, O-word
//! blocks nested far past their limit. Shared by `#[path]` between the `grammar` target of
//! `gcode/fuzz` and the pendant's `upload` target (`plugins/mpg-pendant/fuzz`).
//!
//! Generating never recurses on the input (deep nests are made by repetition), allocates at
//! most about `MAX_PROGRAM_BYTES`, and every byte sequence gives a program (missing bytes read
//! as zero).

/// Largest program generated: room for several lines longer than the reader's 64 KiB limit.
pub const MAX_PROGRAM_BYTES: usize = 256 * 1024;
/// Deepest nest generated: beyond what one 64 KiB line can hold.
pub const MAX_NEST: usize = 100_000;

/// The fuzzer's bytes, read as choices.
pub struct Choices<'a> {
    data: &'a [u8],
    pos: usize,
}

impl<'a> Choices<'a> {
    pub fn new(data: &'a [u8]) -> Self {
        Choices { data, pos: 0 }
    }

    pub fn done(&self) -> bool {
        self.pos >= self.data.len()
    }

    pub fn byte(&mut self) -> u8 {
        let b = self.data.get(self.pos).copied().unwrap_or(0);
        self.pos += 1;
        b
    }

    pub fn u16(&mut self) -> u16 {
        u16::from(self.byte()) << 8 | u16::from(self.byte())
    }

    /// A choice in `0..n` (`n` > 0).
    pub fn below(&mut self, n: usize) -> usize {
        if n <= 256 {
            usize::from(self.byte()) % n
        } else {
            usize::from(self.u16()) % n
        }
    }

    pub fn pick<T: Copy>(&mut self, items: &[T]) -> T {
        items[self.below(items.len())]
    }

    /// How deep a nest goes: mostly shallow, often on either side of the reader's 64-level
    /// limit, sometimes thousands of levels, up to [`MAX_NEST`].
    pub fn depth(&mut self) -> usize {
        match self.below(8) {
            0..=3 => self.below(12),
            4 | 5 => 58 + self.below(12),
            6 => 64 + self.below(2000),
            _ => ((usize::from(self.u16()) << 1) | self.below(2)) % (MAX_NEST + 1),
        }
    }

    /// How often a construct repeats: mostly a few times, sometimes tens of thousands.
    pub fn count(&mut self) -> usize {
        match self.below(8) {
            0..=4 => 1 + self.below(8),
            5 | 6 => 50 + self.below(200),
            _ => usize::from(self.u16()),
        }
    }
}

/// Constructs that open one or more nesting levels of a value, and what closes them.
const NESTS: [(&str, &str); 14] = [
    ("[", "]"),
    ("#[", "]"),
    ("#", ""),
    ("-[", "]"),
    ("+[", "]"),
    ("ABS[", "]"),
    ("SIN[", "]"),
    ("ATAN[1]/[", "]"),
    ("[1+", "]"),
    ("[2**", "]"),
    ("[1 EQ ", "]"),
    ("[#1*", "]"),
    ("[1 OR 1 EQ 1 + 1 * 1 ** ", "]"),
    ("EXP[", "]"),
];

/// Values on and past every limit, and expressions whose results overflow or underflow.
const SPECIAL: [&str; 34] = [
    "0",
    "-0",
    "1000000",
    "-1000000",
    "1000000.0001",
    "999999.9999",
    "1000001",
    "86400",
    "86400.001",
    "100000000",
    "100000001",
    "99999999999999999999",
    "0.0000000000000000000001",
    "[10**300]",
    "[-10**300]",
    "[10**300*10**300]",
    "[0-10**308-10**308]",
    "[10**400]",
    "[10**-400]",
    "[1/[10**-300]]",
    "[1/[10**-400]]",
    "[EXP[709]]",
    "[EXP[710]]",
    "[LN[0]]",
    "[SQRT[10**300]]",
    "[TAN[90]]",
    "[2**1023*2]",
    "[1/3]",
    "[ATAN[1]/[0]]",
    "[ACOS[2]]",
    "[10**300 GT 1]",
    "[10 MOD 0]",
    "#5420",
    "#<_x>",
];

const WORDS: &[u8] = b"XYZAIJKRFSPQLHDT@^";

/// A program from the fuzzer's bytes.
pub fn program(c: &mut Choices) -> String {
    let mut out = String::new();
    while !c.done() && out.len() < MAX_PROGRAM_BYTES {
        line(c, &mut out);
        out.push('\n');
    }
    out
}

fn line(c: &mut Choices, out: &mut String) {
    match c.below(10) {
        0 | 1 => motion(c, out),
        2 => nested_line(c, out),
        3 => numbers_line(c, out),
        4 => repeated(c, out),
        5 => oword(c, out),
        6 => modal(c, out),
        7 => {
            // Raw bytes, kept to ASCII so that the rest of the program still reads.
            for _ in 0..1 + c.below(12) {
                out.push(char::from(c.byte() & 0x7f));
            }
        }
        8 => {
            let target = match c.below(3) {
                0 => format!("#{}", 1 + c.below(40)),
                1 => format!("#<v{}>", c.below(4)),
                _ => format!("#<_g{}>", c.below(4)),
            };
            out.push_str(&format!("{target} = "));
            value(c, out);
        }
        _ => {
            out.push_str(c.pick(&["M3 S1000", "M5", "M30", "%", "G80", "M2", "M0", "(msg, hi)"]));
        }
    }
}

/// A number: plain, special, a parameter or a small expression.
fn value(c: &mut Choices, out: &mut String) {
    match c.below(6) {
        0 | 1 => {
            if c.below(2) == 0 {
                out.push('-');
            }
            out.push_str(&c.below(1000).to_string());
            if c.below(2) == 0 {
                out.push_str(&format!(".{}", c.below(10_000)));
            }
        }
        2 | 3 => out.push_str(c.pick(&SPECIAL)),
        4 => out.push_str(&format!("#{}", 1 + c.below(40))),
        _ => small_expression(c, out, 3),
    }
}

/// A random expression at most `depth` levels deep (the generator's recursion is bounded by
/// `depth`, never by the input).
fn small_expression(c: &mut Choices, out: &mut String, depth: usize) {
    if depth == 0 {
        out.push_str(&c.below(100).to_string());
        return;
    }
    match c.below(4) {
        0 => {
            out.push('[');
            small_expression(c, out, depth - 1);
            out.push_str(c.pick(&[
                " + ", " - ", " * ", " / ", " ** ", " MOD ", " EQ ", " GT ", " AND ", " XOR ",
            ]));
            small_expression(c, out, depth - 1);
            out.push(']');
        }
        1 => {
            out.push_str(c.pick(&["ABS[", "SQRT[", "COS[", "FIX[", "ROUND[", "EXP[", "LN["]));
            small_expression(c, out, depth - 1);
            out.push(']');
        }
        2 => out.push_str(c.pick(&SPECIAL)),
        _ => {
            out.push_str("#[");
            small_expression(c, out, depth - 1);
            out.push(']');
        }
    }
}

/// A nest of one construct, `depth()` levels, closed or left open.
fn nest(c: &mut Choices, out: &mut String) {
    let (open, close) = c.pick(&NESTS);
    let n = c.depth();
    let closed = c.below(3) != 0;
    let budget = MAX_PROGRAM_BYTES.saturating_sub(out.len()) / (open.len() + close.len()).max(1);
    let n = n.min(budget);
    for _ in 0..n {
        out.push_str(open);
    }
    out.push('1');
    if closed {
        for _ in 0..n {
            out.push_str(close);
        }
    }
}

fn words(c: &mut Choices, out: &mut String, n: usize) {
    for _ in 0..n {
        out.push(' ');
        out.push(char::from(c.pick(WORDS)));
        value(c, out);
    }
}

fn motion(c: &mut Choices, out: &mut String) {
    out.push_str(c.pick(&[
        "G0", "G1", "G2", "G3", "G5", "G5.1", "G81", "G82", "G83", "G73", "G85", "G89", "G4",
        "G28", "G30", "G53 G0", "G91 G0", "G91 G1", "",
    ]));
    let n = 1 + c.below(5);
    words(c, out, n);
    if c.below(3) == 0 {
        out.push_str(" F");
        value(c, out);
    }
}

/// A nest where a value may stand: a word, a condition, an assignment, a call argument.
fn nested_line(c: &mut Choices, out: &mut String) {
    match c.below(6) {
        0 => {
            out.push_str(&format!("o{} if ", c.below(4)));
            nest(c, out);
        }
        1 => {
            out.push_str(&format!("#{} = ", 1 + c.below(40)));
            nest(c, out);
        }
        2 => {
            out.push_str("o<s> call [");
            nest(c, out);
            out.push(']');
        }
        3 => {
            out.push_str("G4 P");
            nest(c, out);
        }
        _ => {
            out.push_str(c.pick(&["G1 X", "G0 Y", "G1 F100 Z", "G2 I", "G0 @", "G1 A"]));
            nest(c, out);
        }
    }
}

/// Several words with values from the special list.
fn numbers_line(c: &mut Choices, out: &mut String) {
    out.push_str(c.pick(&[
        "G0",
        "G1",
        "G2",
        "G4",
        "G92",
        "G52",
        "G10 L2 P1",
        "G10 L20 P0",
        "G10 L1 P1",
        "G93 G1",
        "G95 G1",
        "G20 G0",
        "G81",
    ]));
    for _ in 0..1 + c.below(4) {
        out.push(' ');
        out.push(char::from(c.pick(WORDS)));
        out.push_str(c.pick(&SPECIAL));
    }
}

/// One construct repeated `count()` times: within a line, or as many lines.
fn repeated(c: &mut Choices, out: &mut String) {
    let unit: String = match c.below(12) {
        0 => "#1=1 ".into(),
        1 => "(c)".into(),
        2 => "G91 G0 X900000\n".into(),
        3 => format!("o{} if [1]\n", c.below(3)),
        4 => "o1 do\n".into(),
        5 => "[1]+".into(),
        6 => "G1 X1 F100\n".into(),
        7 => "G91 G1 A700000 F100\n".into(),
        8 => "o<s> call\n".into(),
        9 => "M98 P1\n".into(),
        10 => "G0 Z5\nG91 G81 X300000 Z-1 R1 L4 F100\n".into(),
        _ => {
            let mut u = String::new();
            motion(c, &mut u);
            u.push('\n');
            u
        }
    };
    let n = c
        .count()
        .min(MAX_PROGRAM_BYTES.saturating_sub(out.len()) / unit.len().max(1));
    if unit == "[1]+" {
        out.push_str("G1 X");
    }
    for _ in 0..n {
        out.push_str(&unit);
    }
    if unit == "[1]+" {
        out.push('1');
    }
}

fn oword(c: &mut Choices, out: &mut String) {
    let name = match c.below(3) {
        0 => format!("{}", c.below(4)),
        1 => "<s>".to_string(),
        _ => format!("<b{}>", c.below(3)),
    };
    let kw = c.pick(&[
        "if",
        "elseif",
        "else",
        "endif",
        "while",
        "endwhile",
        "do",
        "repeat",
        "endrepeat",
        "break",
        "continue",
        "sub",
        "endsub",
        "call",
        "return",
    ]);
    out.push_str(&format!("o{name} {kw}"));
    if matches!(
        kw,
        "if" | "elseif" | "while" | "repeat" | "return" | "endsub" | "call"
    ) {
        out.push_str(" [");
        value(c, out);
        out.push(']');
    }
}

fn modal(c: &mut Choices, out: &mut String) {
    out.push_str(c.pick(&[
        "G20", "G21", "G90", "G91", "G90.1", "G91.1", "G17", "G18", "G19", "G92.1", "G92.2",
        "G92.3", "G93", "G94", "G95", "G40", "G41 D1", "G42.1 D2", "G43 H1", "G49", "G54", "G59.3",
        "G98", "G99", "M70", "M72", "M73", "O1", "M99", "G28.1", "G30.1",
    ]));
    if c.below(2) == 0 {
        let n = c.below(3);
        words(c, out, n);
    }
}
