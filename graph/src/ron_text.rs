//! A RON reader that remembers where every value was written.
//!
//! The `ron` crate checks syntax (its messages are the ones users know);
//! this reader then builds a tree whose nodes carry line and column, so a
//! semantic error (unknown kind, parameter out of range, type mismatch...) can
//! point at the exact text at fault. It accepts the RON subset pipelines use:
//! structs (named or anonymous), tuples, maps, lists, strings, numbers,
//! booleans, identifiers, `Some(..)`/`None`, and `//` and `/* */` comments.

use std::fmt;

/// A position in the text, 1-based line and column (columns count chars).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Pos {
    /// Line, from 1.
    pub line: usize,
    /// Column, from 1, counted in chars.
    pub col: usize,
}

impl fmt::Display for Pos {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}:{}", self.line, self.col)
    }
}

/// A value with its starting position.
#[derive(Debug, Clone, PartialEq)]
pub struct Spanned<T> {
    /// Where the value starts.
    pub pos: Pos,
    /// The value.
    pub value: T,
}

/// A parsed RON value.
#[derive(Debug, Clone, PartialEq)]
pub enum RonValue {
    /// A string, escapes resolved.
    Str(String),
    /// An integer.
    Int(i64),
    /// A float (also `inf`, `-inf` and `NaN`).
    Float(f64),
    /// `true` or `false`.
    Bool(bool),
    /// A bare identifier such as `None` or an enum variant.
    Ident(String),
    /// `[a, b, ...]`.
    List(Vec<Spanned<RonValue>>),
    /// `{key: value, ...}`, entries in written order.
    Map(Vec<(Spanned<RonValue>, Spanned<RonValue>)>),
    /// `Name(field: value, ...)` or `(field: value, ...)`.
    Struct {
        /// The name before the parenthesis, if any.
        name: Option<String>,
        /// Fields in written order, each name with its position.
        fields: Vec<(Spanned<String>, Spanned<RonValue>)>,
    },
    /// `Name(a, b)` or `(a, b)`; `Some(x)` is a tuple named `Some`.
    Tuple {
        /// The name before the parenthesis, if any.
        name: Option<String>,
        /// Items in written order.
        items: Vec<Spanned<RonValue>>,
    },
}

impl RonValue {
    /// What the value is, for messages ("a string", "a map"...).
    pub fn describe(&self) -> &'static str {
        match self {
            RonValue::Str(_) => "a string",
            RonValue::Int(_) => "an integer",
            RonValue::Float(_) => "a float",
            RonValue::Bool(_) => "a bool",
            RonValue::Ident(_) => "an identifier",
            RonValue::List(_) => "a list",
            RonValue::Map(_) => "a map",
            RonValue::Struct { .. } => "a struct",
            RonValue::Tuple { .. } => "a tuple",
        }
    }
}

/// A syntax error at a position.
#[derive(Debug, Clone, PartialEq)]
pub struct SyntaxError {
    /// Where the error is.
    pub pos: Pos,
    /// What is wrong.
    pub message: String,
    /// The `ron` crate reads the text, but it holds RON this reader does not
    /// take into a pipeline (a range, a char or byte literal, a hex, binary
    /// or suffixed number): a format error at the place, not a syntax error.
    pub valid_ron: bool,
}

/// A comment of the text (`// ...` without its line break, `/* ... */`
/// whole, or a `#![...]` attribute line), where it starts, and whether it
/// stands on a line of its own (only blanks before it).
#[derive(Debug, Clone, PartialEq)]
pub struct Comment {
    /// Where the comment starts.
    pub pos: Pos,
    /// Its text as written.
    pub text: String,
    /// Nothing but blanks before it on its line.
    pub own_line: bool,
}

/// Parses a whole RON text into a spanned tree.
pub fn parse(text: &str) -> Result<Spanned<RonValue>, SyntaxError> {
    parse_with_comments(text).map(|(v, _)| v)
}

/// [`parse`], also returning the text's comments in written order.
pub fn parse_with_comments(text: &str) -> Result<(Spanned<RonValue>, Vec<Comment>), SyntaxError> {
    // First the reference parser, for its messages and positions.
    if let Err(e) = ron::from_str::<ron::Value>(text) {
        return Err(SyntaxError {
            pos: Pos {
                line: e.span.start.line,
                col: e.span.start.col,
            },
            message: e.code.to_string(),
            valid_ron: false,
        });
    }
    let mut p = Parser::new(text);
    let read = (|| {
        p.skip_ws()?;
        let v = p.value()?;
        p.skip_ws()?;
        if p.peek().is_some() {
            return Err(p.err("unexpected text after the end of the document"));
        }
        Ok(v)
    })();
    read.map(|v| (v, p.comments)).map_err(|e| SyntaxError {
        message: format!(
            "{} (valid RON, but not a form a pipeline takes: write plain numbers, strings, lists, maps and structs)",
            e.message
        ),
        valid_ron: true,
        ..e
    })
}

struct Parser<'a> {
    chars: Vec<char>,
    i: usize,
    line: usize,
    col: usize,
    _text: &'a str,
    comments: Vec<Comment>,
    /// The line of the last character read that is not a blank or part of
    /// a comment (0: none yet): a comment on another line stands on its own.
    code_line: usize,
    /// Reading a comment (its characters are not code).
    in_comment: bool,
}

impl<'a> Parser<'a> {
    fn new(text: &'a str) -> Self {
        // RON allows `#![enable(...)]` extension attributes at the top; skip them.
        Self {
            chars: text.chars().collect(),
            i: 0,
            line: 1,
            col: 1,
            _text: text,
            comments: Vec::new(),
            code_line: 0,
            in_comment: false,
        }
    }
    fn pos(&self) -> Pos {
        Pos {
            line: self.line,
            col: self.col,
        }
    }
    fn err(&self, msg: impl Into<String>) -> SyntaxError {
        SyntaxError {
            pos: self.pos(),
            message: msg.into(),
            valid_ron: false,
        }
    }
    fn peek(&self) -> Option<char> {
        self.chars.get(self.i).copied()
    }
    fn peek_at(&self, k: usize) -> Option<char> {
        self.chars.get(self.i + k).copied()
    }
    fn bump(&mut self) -> Option<char> {
        let c = self.peek()?;
        if !self.in_comment && !c.is_whitespace() {
            self.code_line = self.line;
        }
        self.i += 1;
        if c == '\n' {
            self.line += 1;
            self.col = 1;
        } else {
            self.col += 1;
        }
        Some(c)
    }
    /// Keeps the comment from char `from` (at `start`) to here; a
    /// trailing `\r` (a CRLF line) is not part of it.
    fn note_comment(&mut self, start: Pos, from: usize) {
        let text: String = self.chars[from..self.i].iter().collect();
        let own_line = self.code_line != start.line;
        self.in_comment = false;
        self.comments.push(Comment {
            pos: start,
            text: text.trim_end_matches('\r').to_string(),
            own_line,
        });
    }
    fn skip_ws(&mut self) -> Result<(), SyntaxError> {
        loop {
            match (self.peek(), self.peek_at(1)) {
                (Some(c), _) if c.is_whitespace() => {
                    self.bump();
                }
                (Some('/'), Some('/')) | (Some('#'), Some('!')) => {
                    let (start, from) = (self.pos(), self.i);
                    self.in_comment = true;
                    while let Some(c) = self.peek() {
                        if c == '\n' {
                            break;
                        }
                        self.bump();
                    }
                    self.note_comment(start, from);
                }
                (Some('/'), Some('*')) => {
                    let (start, from) = (self.pos(), self.i);
                    self.in_comment = true;
                    self.bump();
                    self.bump();
                    let mut depth = 1;
                    while depth > 0 {
                        match (self.bump(), self.peek()) {
                            (Some('*'), Some('/')) => {
                                self.bump();
                                depth -= 1;
                            }
                            (Some('/'), Some('*')) => {
                                self.bump();
                                depth += 1;
                            }
                            (None, _) => {
                                return Err(SyntaxError {
                                    pos: start,
                                    message: "unterminated block comment".into(),
                                    valid_ron: false,
                                });
                            }
                            _ => {}
                        }
                    }
                    self.note_comment(start, from);
                }
                _ => return Ok(()),
            }
        }
    }
    fn expect_char(&mut self, c: char) -> Result<(), SyntaxError> {
        self.skip_ws()?;
        if self.peek() == Some(c) {
            self.bump();
            Ok(())
        } else {
            Err(self.err(format!("expected `{c}`")))
        }
    }

    fn value(&mut self) -> Result<Spanned<RonValue>, SyntaxError> {
        self.skip_ws()?;
        let pos = self.pos();
        let value = match self.peek() {
            Some('"') => RonValue::Str(self.string()?),
            // a raw identifier `r#name` (as `ron` reads it: letters, digits,
            // `_`, `.`, `+`, `-`): the name
            Some('r')
                if self.peek_at(1) == Some('#')
                    && self.peek_at(2).is_some_and(|c| {
                        c.is_alphanumeric() || matches!(c, '_' | '.' | '+' | '-')
                    }) =>
            {
                self.bump();
                self.bump();
                let mut ident = String::new();
                while let Some(c) = self.peek() {
                    if c.is_alphanumeric() || matches!(c, '_' | '.' | '+' | '-') {
                        ident.push(c);
                        self.bump();
                    } else {
                        break;
                    }
                }
                self.skip_ws()?;
                if self.peek() == Some('(') {
                    self.paren(Some(ident))?
                } else {
                    RonValue::Ident(ident)
                }
            }
            Some('r') if matches!(self.peek_at(1), Some('"') | Some('#')) => {
                RonValue::Str(self.raw_string()?)
            }
            Some('[') => {
                self.bump();
                let mut items = Vec::new();
                loop {
                    self.skip_ws()?;
                    if self.peek() == Some(']') {
                        self.bump();
                        break;
                    }
                    items.push(self.value()?);
                    self.skip_ws()?;
                    match self.peek() {
                        Some(',') => {
                            self.bump();
                        }
                        Some(']') => {}
                        _ => return Err(self.err("expected `,` or `]`")),
                    }
                }
                RonValue::List(items)
            }
            Some('{') => {
                self.bump();
                let mut entries = Vec::new();
                loop {
                    self.skip_ws()?;
                    if self.peek() == Some('}') {
                        self.bump();
                        break;
                    }
                    let k = self.value()?;
                    self.expect_char(':')?;
                    let v = self.value()?;
                    entries.push((k, v));
                    self.skip_ws()?;
                    match self.peek() {
                        Some(',') => {
                            self.bump();
                        }
                        Some('}') => {}
                        _ => return Err(self.err("expected `,` or `}`")),
                    }
                }
                RonValue::Map(entries)
            }
            Some('(') => self.paren(None)?,
            Some(c) if c.is_ascii_digit() || c == '-' || c == '+' || c == '.' => self.number()?,
            Some(c) if c.is_alphabetic() || c == '_' => {
                let ident = self.ident();
                match ident.as_str() {
                    "true" => RonValue::Bool(true),
                    "false" => RonValue::Bool(false),
                    "inf" => RonValue::Float(f64::INFINITY),
                    "NaN" => RonValue::Float(f64::NAN),
                    _ => {
                        self.skip_ws()?;
                        if self.peek() == Some('(') {
                            self.paren(Some(ident))?
                        } else {
                            RonValue::Ident(ident)
                        }
                    }
                }
            }
            Some(c) => return Err(self.err(format!("unexpected character `{c}`"))),
            None => return Err(self.err("unexpected end of text")),
        };
        Ok(Spanned { pos, value })
    }

    /// `( ... )` after an optional name: a struct when the first item is `ident:`.
    fn paren(&mut self, name: Option<String>) -> Result<RonValue, SyntaxError> {
        self.bump(); // (
        self.skip_ws()?;
        // Look ahead: identifier followed by ':' (but not '::') means struct fields.
        let save = (self.i, self.line, self.col);
        // the look-ahead's comments are read again below
        let seen = self.comments.len();
        let is_struct = if self.peek().is_some_and(|c| c.is_alphabetic() || c == '_') {
            let _ = self.ident();
            self.skip_ws()?;
            self.peek() == Some(':')
        } else {
            false
        };
        (self.i, self.line, self.col) = save;
        self.comments.truncate(seen);
        if is_struct {
            let mut fields = Vec::new();
            loop {
                self.skip_ws()?;
                if self.peek() == Some(')') {
                    self.bump();
                    break;
                }
                let pos = self.pos();
                if !self.peek().is_some_and(|c| c.is_alphabetic() || c == '_') {
                    return Err(self.err("expected a field name"));
                }
                let key = self.ident();
                self.expect_char(':')?;
                let v = self.value()?;
                fields.push((Spanned { pos, value: key }, v));
                self.skip_ws()?;
                match self.peek() {
                    Some(',') => {
                        self.bump();
                    }
                    Some(')') => {}
                    _ => return Err(self.err("expected `,` or `)`")),
                }
            }
            Ok(RonValue::Struct { name, fields })
        } else {
            let mut items = Vec::new();
            loop {
                self.skip_ws()?;
                if self.peek() == Some(')') {
                    self.bump();
                    break;
                }
                items.push(self.value()?);
                self.skip_ws()?;
                match self.peek() {
                    Some(',') => {
                        self.bump();
                    }
                    Some(')') => {}
                    _ => return Err(self.err("expected `,` or `)`")),
                }
            }
            Ok(RonValue::Tuple { name, items })
        }
    }

    fn ident(&mut self) -> String {
        let mut s = String::new();
        while let Some(c) = self.peek() {
            if c.is_alphanumeric() || c == '_' {
                s.push(c);
                self.bump();
            } else {
                break;
            }
        }
        s
    }

    fn string(&mut self) -> Result<String, SyntaxError> {
        let start = self.pos();
        self.bump(); // "
        let mut s = String::new();
        loop {
            match self.bump() {
                None => {
                    return Err(SyntaxError {
                        pos: start,
                        message: "unterminated string".into(),
                        valid_ron: false,
                    });
                }
                Some('"') => return Ok(s),
                Some('\\') => match self.bump() {
                    Some('n') => s.push('\n'),
                    Some('t') => s.push('\t'),
                    Some('r') => s.push('\r'),
                    Some('0') => s.push('\0'),
                    Some('\\') => s.push('\\'),
                    Some('"') => s.push('"'),
                    Some('\'') => s.push('\''),
                    Some('u') => {
                        self.expect_char('{')?;
                        let mut hex = String::new();
                        while let Some(c) = self.peek() {
                            if c == '}' {
                                break;
                            }
                            hex.push(c);
                            self.bump();
                        }
                        self.expect_char('}')?;
                        let c = u32::from_str_radix(&hex, 16)
                            .ok()
                            .and_then(char::from_u32)
                            .ok_or_else(|| self.err("invalid unicode escape"))?;
                        s.push(c);
                    }
                    _ => return Err(self.err("invalid escape")),
                },
                Some(c) => s.push(c),
            }
        }
    }

    fn raw_string(&mut self) -> Result<String, SyntaxError> {
        let start = self.pos();
        self.bump(); // r
        let mut hashes = 0;
        while self.peek() == Some('#') {
            self.bump();
            hashes += 1;
        }
        self.expect_char('"')?;
        let mut s = String::new();
        loop {
            match self.bump() {
                None => {
                    return Err(SyntaxError {
                        pos: start,
                        message: "unterminated raw string".into(),
                        valid_ron: false,
                    });
                }
                Some('"') => {
                    let mut n = 0;
                    while n < hashes && self.peek_at(n) == Some('#') {
                        n += 1;
                    }
                    if n == hashes {
                        for _ in 0..hashes {
                            self.bump();
                        }
                        return Ok(s);
                    }
                    s.push('"');
                }
                Some(c) => s.push(c),
            }
        }
    }

    fn number(&mut self) -> Result<RonValue, SyntaxError> {
        let mut s = String::new();
        if matches!(self.peek(), Some('-') | Some('+')) {
            s.push(self.bump().unwrap_or('+'));
        }
        if self.peek().is_some_and(|c| c.is_alphabetic()) {
            let id = self.ident();
            let sign = if s == "-" { -1.0 } else { 1.0 };
            return match id.as_str() {
                "inf" => Ok(RonValue::Float(sign * f64::INFINITY)),
                "NaN" => Ok(RonValue::Float(f64::NAN)),
                _ => Err(self.err(format!("invalid number `{s}{id}`"))),
            };
        }
        let mut is_float = false;
        while let Some(c) = self.peek() {
            if c.is_ascii_digit() || c == '_' {
                if c != '_' {
                    s.push(c);
                }
                self.bump();
            } else if c == '.' || c == 'e' || c == 'E' {
                is_float = true;
                s.push(c);
                self.bump();
                if (c == 'e' || c == 'E') && matches!(self.peek(), Some('-') | Some('+')) {
                    s.push(self.bump().unwrap_or('+'));
                }
            } else {
                break;
            }
        }
        if is_float {
            s.parse::<f64>()
                .map(RonValue::Float)
                .map_err(|_| self.err(format!("invalid number `{s}`")))
        } else {
            s.parse::<i64>()
                .map(RonValue::Int)
                .map_err(|_| self.err(format!("invalid integer `{s}`")))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn positions_of_nested_values() {
        let text = "(\n  a: 1,\n  b: { \"x\": [1.5, -2] },\n  c: Some(\"s\"),\n)";
        let v = parse(text).unwrap();
        let RonValue::Struct { fields, .. } = v.value else {
            panic!("not a struct")
        };
        assert_eq!(fields[0].0.value, "a");
        assert_eq!(fields[0].0.pos, Pos { line: 2, col: 3 });
        assert_eq!(fields[0].1.value, RonValue::Int(1));
        assert_eq!(fields[1].1.pos, Pos { line: 3, col: 6 });
        let RonValue::Map(m) = &fields[1].1.value else {
            panic!("not a map")
        };
        assert_eq!(m[0].0.value, RonValue::Str("x".into()));
        let RonValue::List(l) = &m[0].1.value else {
            panic!("not a list")
        };
        assert_eq!(l[1].value, RonValue::Int(-2));
        assert_eq!(l[0].pos, Pos { line: 3, col: 14 });
        assert!(matches!(&fields[2].1.value, RonValue::Tuple { name: Some(n), .. } if n == "Some"));
    }

    #[test]
    fn syntax_error_has_position() {
        let e = parse("(\n  a: 1,\n  b: [1, 2\n)").unwrap_err();
        assert!(e.pos.line >= 3, "{e:?}");
    }

    #[test]
    fn comments_and_floats() {
        let v = parse("// c\n[1e-3, /* x */ 2.0, -inf]").unwrap();
        let RonValue::List(l) = v.value else { panic!() };
        assert_eq!(l[0].value, RonValue::Float(1e-3));
        assert_eq!(l[2].value, RonValue::Float(f64::NEG_INFINITY));
    }

    #[test]
    fn raw_identifiers_read_as_ron_reads_them() {
        for text in ["r#rams", "r#a-b.c+d", "r#Name(1)"] {
            assert!(ron::from_str::<ron::Value>(text).is_ok(), "{text}");
            assert!(parse(text).is_ok(), "{text}");
        }
        assert!(matches!(parse("r#rams").unwrap().value, RonValue::Ident(ref s) if s == "rams"));
    }

    #[test]
    fn ron_the_reader_does_not_take_is_a_format_error_at_its_place() {
        for text in [
            "(version: ..1)",
            "(a: 0x1F)",
            "(a: 'c')",
            "(a: 1u8)",
            "(a: b'a')",
        ] {
            assert!(ron::from_str::<ron::Value>(text).is_ok(), "{text}");
            let e = parse(text).unwrap_err();
            assert!(e.valid_ron, "{text}");
            assert_eq!(e.pos.line, 1);
            assert!(
                e.pos.col > 1 && e.pos.col <= text.len(),
                "{text}: {:?}",
                e.pos
            );
        }
        assert!(!parse("(a: ").unwrap_err().valid_ron);
    }
}
