//! The PDS3 Object Description Language (ODL) as real labels write it (docs/formats.md):
//!
//! * `KEY = VALUE` statements, keywords case-insensitive, namespaced keys (`CH1:SWATH_WIDTH`),
//!   pointer keys (`^IMAGE`);
//! * `OBJECT = X … END_OBJECT [= X]` and `GROUP … END_GROUP` nesting, in any letter case; the
//!   closing name is not checked (real labels misspell it);
//! * values: integers, reals (`1737400.`, `1.5E-3`), radix integers (`16#FF#`), double-quoted
//!   strings (may span lines), single-quoted literals (`'N/A'`), bare symbols, dates and times,
//!   sequences `( … )` and sets `{ … }` (nested, may span lines), each optionally followed by a
//!   unit in angle brackets (`0.984 <AU>`);
//! * comments `/* … */` anywhere, CRLF line ends, space padding, `END` closing the label (what
//!   follows it — e.g. an attached image — is ignored).
//!
//! Errors carry the 1-based line and column.

use std::fmt;

/// A parsed value.
#[derive(Debug, Clone, PartialEq)]
pub enum Value {
    Integer(i64),
    Real(f64),
    /// A double-quoted string, with line breaks and their indentation folded to one space.
    Text(String),
    /// A bare symbol, date/time or single-quoted literal, as written.
    Symbol(String),
    Sequence(Vec<Value>),
    Set(Vec<Value>),
    /// A value followed by `<unit>`.
    WithUnit(Box<Value>, String),
}

impl Value {
    /// The value without its unit.
    pub fn bare(&self) -> &Value {
        match self {
            Value::WithUnit(v, _) => v,
            v => v,
        }
    }
    /// The unit, if one was written.
    pub fn unit(&self) -> Option<&str> {
        match self {
            Value::WithUnit(_, u) => Some(u),
            _ => None,
        }
    }
    /// A number (integer or real), ignoring any unit.
    pub fn as_f64(&self) -> Option<f64> {
        match self.bare() {
            Value::Integer(i) => Some(*i as f64),
            Value::Real(r) => Some(*r),
            _ => None,
        }
    }
    /// An integer, ignoring any unit.
    pub fn as_i64(&self) -> Option<i64> {
        match self.bare() {
            Value::Integer(i) => Some(*i),
            _ => None,
        }
    }
    /// A string from a quoted string, literal or symbol.
    pub fn as_str(&self) -> Option<&str> {
        match self.bare() {
            Value::Text(s) | Value::Symbol(s) => Some(s),
            _ => None,
        }
    }
}

/// The value as ODL writes it (`-1 <AU>`, `"text"`, `(1, 2)`), for messages.
impl fmt::Display for Value {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let list = |f: &mut fmt::Formatter<'_>, v: &[Value], open: &str, close: &str| {
            f.write_str(open)?;
            for (i, x) in v.iter().enumerate() {
                if i > 0 {
                    f.write_str(", ")?;
                }
                write!(f, "{x}")?;
            }
            f.write_str(close)
        };
        match self {
            Value::Integer(i) => write!(f, "{i}"),
            Value::Real(r) => write!(f, "{r}"),
            Value::Text(s) => write!(f, "\"{s}\""),
            Value::Symbol(s) => f.write_str(s),
            Value::Sequence(v) => list(f, v, "(", ")"),
            Value::Set(v) => list(f, v, "{", "}"),
            Value::WithUnit(v, u) => write!(f, "{v} <{u}>"),
        }
    }
}

/// Where a pointer (`^NAME = …`) points.
#[derive(Debug, Clone, PartialEq)]
pub enum Pointer {
    /// A detached file, starting at its first byte.
    File(String),
    /// A detached file starting at a 1-based record.
    FileRecord(String, u64),
    /// A detached file starting at a 1-based byte.
    FileBytes(String, u64),
    /// The label's own file, at a 1-based record.
    Record(u64),
    /// The label's own file, at a 1-based byte.
    Bytes(u64),
}

/// A statement's key, value and where it was written.
#[derive(Debug, Clone, PartialEq)]
pub struct Attribute {
    /// As written, including any `^` and namespace.
    pub key: String,
    pub value: Value,
    pub line: usize,
}

/// An OBJECT or GROUP block (or the label's top level), with its statements in order.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Object {
    /// The block's name (`OBJECT = NAME`); empty at the top level.
    pub name: String,
    /// True for GROUP blocks.
    pub is_group: bool,
    pub attributes: Vec<Attribute>,
    pub children: Vec<Object>,
    pub line: usize,
}

impl Object {
    /// The first attribute named `key` (case-insensitive).
    pub fn get(&self, key: &str) -> Option<&Value> {
        self.attributes
            .iter()
            .find(|a| a.key.eq_ignore_ascii_case(key))
            .map(|a| &a.value)
    }
    /// The attribute record (with its line) named `key`.
    /// `KEY (line N)` for messages, where the keyword is in this object; `KEY` otherwise.
    pub fn at(&self, key: &str) -> String {
        match self.attribute(key) {
            Some(a) => format!("{key} (line {})", a.line),
            None => key.to_string(),
        }
    }

    pub fn attribute(&self, key: &str) -> Option<&Attribute> {
        self.attributes
            .iter()
            .find(|a| a.key.eq_ignore_ascii_case(key))
    }
    /// The first child block named `name` (case-insensitive).
    pub fn child(&self, name: &str) -> Option<&Object> {
        self.children
            .iter()
            .find(|c| c.name.eq_ignore_ascii_case(name))
    }
    /// All child blocks named `name`.
    pub fn children_named<'a>(&'a self, name: &'a str) -> impl Iterator<Item = &'a Object> + 'a {
        self.children
            .iter()
            .filter(move |c| c.name.eq_ignore_ascii_case(name))
    }
    /// A depth-first search for the first block named `name`, this one included.
    pub fn find(&self, name: &str) -> Option<&Object> {
        if self.name.eq_ignore_ascii_case(name) {
            return Some(self);
        }
        self.children.iter().find_map(|c| c.find(name))
    }
    /// The pointer `^name` (given without the caret), interpreted.
    pub fn pointer(&self, name: &str) -> Option<Result<Pointer, String>> {
        let a = self.attributes.iter().find(|a| {
            a.key
                .strip_prefix('^')
                .is_some_and(|k| k.eq_ignore_ascii_case(name))
        })?;
        Some(
            interpret_pointer(&a.value)
                .ok_or_else(|| format!("^{name} (line {}) is not a pointer PDS3 defines", a.line)),
        )
    }
}

fn interpret_pointer(v: &Value) -> Option<Pointer> {
    let count = |v: &Value| -> Option<(u64, bool)> {
        let n = u64::try_from(v.as_i64()?).ok()?;
        match v.unit() {
            None => Some((n, false)),
            Some(u) if u.eq_ignore_ascii_case("BYTES") => Some((n, true)),
            Some(_) => None,
        }
    };
    match v {
        Value::Sequence(items) => match items.as_slice() {
            [file] => Some(Pointer::File(file.as_str()?.to_string())),
            [file, off] => {
                let f = file.as_str()?.to_string();
                let (n, bytes) = count(off)?;
                Some(if bytes {
                    Pointer::FileBytes(f, n)
                } else {
                    Pointer::FileRecord(f, n)
                })
            }
            _ => None,
        },
        Value::Text(s) | Value::Symbol(s) => Some(Pointer::File(s.clone())),
        other => {
            let (n, bytes) = count(other)?;
            Some(if bytes {
                Pointer::Bytes(n)
            } else {
                Pointer::Record(n)
            })
        }
    }
}

/// The parsed label.
#[derive(Debug, Clone, PartialEq)]
pub struct Label {
    /// Top-level statements and blocks.
    pub root: Object,
    /// Byte length of the label text up to and including the line with `END`.
    pub label_bytes: usize,
}

impl std::ops::Deref for Label {
    type Target = Object;
    fn deref(&self) -> &Object {
        &self.root
    }
}

/// A malformed label: what, and where (1-based line and column).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub struct ParseError {
    pub line: usize,
    pub column: usize,
    pub message: String,
}

impl fmt::Display for ParseError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "line {}, column {}: {}",
            self.line, self.column, self.message
        )
    }
}

/// Labels larger than this are refused (real PDS3 labels are kilobytes).
pub const MAX_LABEL_BYTES: usize = 16 << 20;
/// Blocks nested deeper than this are refused.
const MAX_DEPTH: usize = 64;

struct Cursor<'a> {
    s: &'a [u8],
    i: usize,
    line: usize,
    col: usize,
    /// Where the first quoted string that swallowed a `KEY = …` line began: the sign of a
    /// missing closing quote, reported there if parsing fails further on.
    suspect: Option<(usize, usize)>,
}

/// Whether quoted text holds a line that reads like a statement (`KEY =`): a string that
/// does has most likely lost its closing quote.
fn swallows_a_statement(raw: &str) -> bool {
    raw.lines().skip(1).any(|l| {
        let l = l.trim_start();
        let key: String = l
            .chars()
            .take_while(|c| c.is_ascii_alphanumeric() || matches!(c, '_' | ':' | '^'))
            .collect();
        !key.is_empty()
            && key.starts_with(|c: char| c.is_ascii_alphabetic() || c == '^')
            && l[key.len()..].trim_start().starts_with('=')
    })
}

impl<'a> Cursor<'a> {
    fn peek(&self) -> Option<u8> {
        self.s.get(self.i).copied()
    }
    fn peek2(&self) -> Option<u8> {
        self.s.get(self.i + 1).copied()
    }
    fn bump(&mut self) -> Option<u8> {
        let c = self.peek()?;
        self.i += 1;
        if c == b'\n' {
            self.line += 1;
            self.col = 1;
        } else {
            self.col += 1;
        }
        Some(c)
    }
    fn err(&self, message: impl Into<String>) -> ParseError {
        ParseError {
            line: self.line,
            column: self.col,
            message: message.into(),
        }
    }
    /// Skip spaces, tabs, line ends and comments. Returns whether a line end was crossed.
    fn skip_ws(&mut self) -> Result<bool, ParseError> {
        let mut newline = false;
        loop {
            match self.peek() {
                Some(b' ' | b'\t' | b'\r' | 0x0c) => {
                    self.bump();
                }
                Some(b'\n') => {
                    newline = true;
                    self.bump();
                }
                Some(b'/') if self.peek2() == Some(b'*') => {
                    let (l, c) = (self.line, self.col);
                    self.bump();
                    self.bump();
                    loop {
                        match self.bump() {
                            None => {
                                return Err(ParseError {
                                    line: l,
                                    column: c,
                                    message: "comment `/*` is never closed".into(),
                                })
                            }
                            Some(b'*') if self.peek() == Some(b'/') => {
                                self.bump();
                                break;
                            }
                            Some(b'\n') => newline = true,
                            _ => {}
                        }
                    }
                }
                _ => return Ok(newline),
            }
        }
    }
    /// From an opening delimiter at the cursor to `close` on the same line: the text between.
    fn delimited_on_line(&mut self, close: u8, what: &str) -> Result<String, ParseError> {
        let (line, column) = (self.line, self.col);
        self.bump();
        let start = self.i;
        loop {
            match self.bump() {
                None | Some(b'\n') => {
                    return Err(ParseError {
                        line,
                        column,
                        message: format!("{what} is never closed on its line"),
                    })
                }
                Some(b) if b == close => break,
                _ => {}
            }
        }
        Ok(String::from_utf8_lossy(&self.s[start..self.i - 1]).into_owned())
    }

    fn word(&mut self) -> String {
        let start = self.i;
        while let Some(c) = self.peek() {
            let slash = c == b'/' && self.i > start && self.peek2() != Some(b'*');
            if c.is_ascii_alphanumeric()
                || slash
                || matches!(c, b'_' | b':' | b'^' | b'-' | b'.' | b'+' | b'#')
            {
                self.bump();
            } else {
                break;
            }
        }
        String::from_utf8_lossy(&self.s[start..self.i]).into_owned()
    }
}

/// Parse a label from its bytes. Bytes after the `END` statement are ignored.
pub fn parse_label(bytes: &[u8]) -> Result<Label, ParseError> {
    if bytes.len() > MAX_LABEL_BYTES
        && !bytes[..MAX_LABEL_BYTES]
            .windows(3)
            .any(|w| w.eq_ignore_ascii_case(b"END"))
    {
        return Err(ParseError {
            line: 1,
            column: 1,
            message: format!("no END within the first {MAX_LABEL_BYTES} bytes: not a PDS3 label"),
        });
    }
    let mut c = Cursor {
        s: bytes,
        i: 0,
        line: 1,
        col: 1,
        suspect: None,
    };
    parse_statements(&mut c).map_err(|e| match c.suspect {
        Some((line, column)) if line < e.line => ParseError {
            line,
            column,
            message: format!(
                "this string's closing quote seems to be missing: it runs on over `KEY =` lines to line {}, where parsing fails ({})",
                e.line, e.message
            ),
        },
        _ => e,
    })
}

/// The statements of a label, to its `END`.
fn parse_statements(c: &mut Cursor) -> Result<Label, ParseError> {
    let mut stack: Vec<Object> = vec![Object::default()];
    loop {
        c.skip_ws()?;
        let (line, col) = (c.line, c.col);
        let Some(ch) = c.peek() else {
            return Err(c.err("the label ends without an END statement"));
        };
        if !(ch.is_ascii_alphabetic() || ch == b'^') {
            return Err(c.err(format!("expected a keyword, found {}", describe(ch))));
        }
        let key = c.word();
        if key.eq_ignore_ascii_case("END") {
            // END must stand alone (not END_OBJECT, handled below as a key).
            if stack.len() > 1 {
                let open = stack.last().expect("non-empty");
                return Err(ParseError {
                    line,
                    column: col,
                    message: format!(
                        "END while OBJECT/GROUP `{}` opened on line {} is still open",
                        open.name, open.line
                    ),
                });
            }
            while let Some(b) = c.peek() {
                c.bump();
                if b == b'\n' {
                    break;
                }
            }
            let root = stack.pop().expect("root");
            return Ok(Label {
                root,
                label_bytes: c.i,
            });
        }
        c.skip_ws()?;
        let upper = key.to_ascii_uppercase();
        let is_end_block = upper == "END_OBJECT" || upper == "END_GROUP";
        if c.peek() != Some(b'=') {
            if is_end_block {
                close_block(&mut stack, &upper, line, col)?;
                continue;
            }
            return Err(c.err(format!("expected `=` after `{key}`")));
        }
        c.bump();
        c.skip_ws()?;
        if is_end_block {
            // `END_OBJECT = NAME`: the name is not checked.
            c.word();
            close_block(&mut stack, &upper, line, col)?;
            continue;
        }
        let value = parse_value(c, 0)?;
        if upper == "OBJECT" || upper == "GROUP" {
            if stack.len() > MAX_DEPTH {
                return Err(ParseError {
                    line,
                    column: col,
                    message: format!("blocks nested deeper than {MAX_DEPTH}"),
                });
            }
            let name = value
                .as_str()
                .map(str::to_string)
                .ok_or_else(|| ParseError {
                    line,
                    column: col,
                    message: format!("{upper} needs a name"),
                })?;
            stack.push(Object {
                name,
                is_group: upper == "GROUP",
                line,
                ..Object::default()
            });
        } else {
            stack
                .last_mut()
                .expect("root")
                .attributes
                .push(Attribute { key, value, line });
        }
    }
}

fn close_block(
    stack: &mut Vec<Object>,
    which: &str,
    line: usize,
    column: usize,
) -> Result<(), ParseError> {
    if stack.len() < 2 {
        return Err(ParseError {
            line,
            column,
            message: format!("{which} without an open OBJECT or GROUP"),
        });
    }
    let done = stack.pop().expect("checked");
    stack.last_mut().expect("checked").children.push(done);
    Ok(())
}

fn describe(b: u8) -> String {
    if b.is_ascii_graphic() {
        format!("`{}`", b as char)
    } else {
        format!("byte 0x{b:02X}")
    }
}

fn parse_value(c: &mut Cursor, depth: usize) -> Result<Value, ParseError> {
    if depth > MAX_DEPTH {
        return Err(c.err("sequences nested too deeply"));
    }
    let v = match c.peek() {
        None => return Err(c.err("the label ends where a value was expected")),
        Some(b'"') => {
            let (l, col) = (c.line, c.col);
            c.bump();
            let start = c.i;
            loop {
                match c.bump() {
                    None => {
                        return Err(ParseError {
                            line: l,
                            column: col,
                            message: "string is never closed".into(),
                        })
                    }
                    Some(b'"') => break,
                    _ => {}
                }
            }
            let raw = std::str::from_utf8(&c.s[start..c.i - 1]).map_err(|e| ParseError {
                line: l,
                column: col,
                message: format!("string is not UTF-8 (byte {} of it)", e.valid_up_to()),
            })?;
            if c.suspect.is_none() && swallows_a_statement(raw) {
                c.suspect = Some((l, col));
            }
            Value::Text(fold_lines(raw))
        }
        Some(b'\'') => Value::Symbol(c.delimited_on_line(b'\'', "literal `'`")?),
        Some(open @ (b'(' | b'{')) => {
            let close = if open == b'(' { b')' } else { b'}' };
            let (l, col) = (c.line, c.col);
            c.bump();
            let mut items = Vec::new();
            loop {
                c.skip_ws()?;
                match c.peek() {
                    None => {
                        return Err(ParseError {
                            line: l,
                            column: col,
                            message: format!("`{}` is never closed", open as char),
                        })
                    }
                    Some(x) if x == close => {
                        c.bump();
                        break;
                    }
                    Some(b',') => {
                        c.bump();
                    }
                    Some(_) => items.push(parse_value(c, depth + 1)?),
                }
            }
            if open == b'(' {
                Value::Sequence(items)
            } else {
                Value::Set(items)
            }
        }
        Some(ch) if ch.is_ascii_alphanumeric() || matches!(ch, b'-' | b'+' | b'.' | b'_') => {
            scalar(c.word())
        }
        Some(ch) => return Err(c.err(format!("expected a value, found {}", describe(ch)))),
    };
    // Optional unit: only on the same line.
    let save = (c.i, c.line, c.col);
    let crossed = c.skip_ws()?;
    if !crossed && c.peek() == Some(b'<') {
        let unit = c.delimited_on_line(b'>', "unit `<`")?.trim().to_string();
        return Ok(Value::WithUnit(Box::new(v), unit));
    }
    (c.i, c.line, c.col) = save;
    Ok(v)
}

/// Classify a bare word: integer, radix integer, real, or symbol (dates stay symbols).
fn scalar(w: String) -> Value {
    if let Ok(i) = w.parse::<i64>() {
        return Value::Integer(i);
    }
    if let Some((radix, rest)) = w.split_once('#') {
        if let (Ok(r), Some(digits)) = (radix.parse::<u32>(), rest.strip_suffix('#')) {
            if (2..=16).contains(&r) {
                if let Ok(i) = i64::from_str_radix(digits, r) {
                    return Value::Integer(i);
                }
            }
        }
    }
    let looks_numeric = w
        .bytes()
        .next()
        .is_some_and(|b| b.is_ascii_digit() || matches!(b, b'-' | b'+' | b'.'));
    if looks_numeric && !w.contains(['T', ':']) {
        if let Ok(r) = w.parse::<f64>() {
            return Value::Real(r);
        }
    }
    Value::Symbol(w)
}

/// Fold a multi-line string: each line break with the indentation around it becomes one space.
fn fold_lines(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    for (k, part) in s.split('\n').enumerate() {
        let part = part.trim_end_matches('\r');
        if k == 0 {
            out.push_str(part.trim_end());
        } else {
            let t = part.trim();
            if !t.is_empty() {
                if !out.is_empty() {
                    out.push(' ');
                }
                out.push_str(t);
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn values_units_pointers_and_nesting() {
        let text = "PDS_VERSION_ID = PDS3\r\n/* comment */\r\nA = 1737400. <m> /* inline */\r\nB = \"two\r\n   lines\"\r\nC = (1, 2.5,\r\n  'N/A')\r\nD = {X, \"Y\"}\r\nCH1:E = 304 <pixel>\r\nF = 2009-01-06T11:34:23\r\nCLK = 4/1165041.799 /* c */\r\n^IMAGE = (\"F.IMG\", 12)\r\n^TABLE = 2904 <BYTES>\r\nG = 16#1F#\r\nobject = OUTER\r\n  Group = G1\r\n    H = -3\r\n  End_Group\r\nEND_OBJECT = OUTR\r\nEND\r\nbinary";
        let l = parse_label(text.as_bytes()).unwrap();
        assert_eq!(l.get("a").unwrap().as_f64(), Some(1737400.0));
        assert_eq!(l.get("A").unwrap().unit(), Some("m"));
        assert_eq!(l.get("B").unwrap().as_str(), Some("two lines"));
        assert_eq!(
            l.get("C").unwrap(),
            &Value::Sequence(vec![
                Value::Integer(1),
                Value::Real(2.5),
                Value::Symbol("N/A".into())
            ])
        );
        assert_eq!(
            l.get("D").unwrap(),
            &Value::Set(vec![Value::Symbol("X".into()), Value::Text("Y".into())])
        );
        assert_eq!(l.get("ch1:e").unwrap().as_i64(), Some(304));
        assert_eq!(l.get("F").unwrap().as_str(), Some("2009-01-06T11:34:23"));
        assert_eq!(l.get("CLK").unwrap().as_str(), Some("4/1165041.799"));
        assert_eq!(
            l.pointer("IMAGE").unwrap().unwrap(),
            Pointer::FileRecord("F.IMG".into(), 12)
        );
        assert_eq!(l.pointer("table").unwrap().unwrap(), Pointer::Bytes(2904));
        assert_eq!(l.get("G").unwrap().as_i64(), Some(31));
        // Messages show values as ODL writes them (a quoted string's folded line break stays
        // folded; a literal loses its quotes).
        let shown: Vec<String> = ["A", "B", "C", "D", "CH1:E"]
            .iter()
            .map(|k| l.get(k).unwrap().to_string())
            .collect();
        assert_eq!(
            shown,
            [
                "1737400 <m>",
                "\"two lines\"",
                "(1, 2.5, N/A)",
                "{X, \"Y\"}",
                "304 <pixel>"
            ]
        );
        let outer = l.child("outer").unwrap();
        assert_eq!(
            outer.child("G1").unwrap().get("H").unwrap().as_i64(),
            Some(-3)
        );
        assert!(outer.child("G1").unwrap().is_group);
        assert_eq!(&text.as_bytes()[l.label_bytes..], b"binary");
    }

    #[test]
    fn errors_name_line_and_column() {
        let cases: [(&str, usize, &str); 8] = [
            ("A = 1 <m\nEND\n", 1, "unit `<` is never closed"),
            ("A = 'x\nEND\n", 1, "literal `'` is never closed"),
            ("A = 1\nB = \"open\nEND\n", 2, "never closed"),
            ("A = 1\nOBJECT = X\nB = 2\nEND\n", 4, "still open"),
            ("A = 1\nEND_OBJECT\nEND\n", 2, "without an open"),
            ("A = 1\nB 2\nEND\n", 2, "expected `=`"),
            ("A = 1\nB = (1, 2\n", 2, "never closed"),
            ("A = 1\n", 2, "without an END"),
        ];
        for (text, line, what) in cases {
            let e = parse_label(text.as_bytes()).unwrap_err();
            assert_eq!(e.line, line, "{text:?}: {e}");
            assert!(e.message.contains(what), "{text:?}: {e}");
        }
        let e = parse_label(b"A = \"\xff\xfe\"\nEND\n").unwrap_err();
        assert!(e.message.contains("UTF-8"), "{e}");
    }

    /// A string whose closing quote is missing swallows the statements after it up to the
    /// next quote, and parsing fails far below: the error points where the string starts.
    #[test]
    fn an_unterminated_string_is_reported_where_it_starts() {
        let text =
            "PDS_VERSION_ID = PDS3\nA = \"no end\nB = 1\nC = 2\nD = 3\nE = \"x\"\nF = 4\nEND\n";
        let e = parse_label(text.as_bytes()).unwrap_err();
        assert_eq!((e.line, e.column), (2, 5), "{e}");
        assert!(e.message.contains("closing quote"), "{e}");
        // Multi-line strings without statements inside stay legal.
        let ok = "A = \"one\n  two = words\n  three\"\nEND\n";
        assert!(parse_label(ok.as_bytes()).is_ok());
    }
}
