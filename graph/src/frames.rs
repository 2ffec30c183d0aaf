//! Frame sequences: a pipeline that takes a frame index.
//!
//! A document takes a frame index when one of its string parameters holds a
//! `{frame}` placeholder: in a path (`"frames/rgb_{frame:05}.png"`, a
//! printf-style width with `0` for zero padding) or as the whole value of a
//! number parameter (`frame: "{frame}"`), which then becomes that integer.
//! [`Document::for_frame`](crate::document::Document::for_frame) gives the document of one frame; the checker
//! never sees a placeholder.
//!
//! [`FrameSelection`] is the `--frames` argument: `0..100` (half-open, as
//! Rust's ranges: frames 0 to 99), `0..100:5` (every 5th), `7` (one frame)
//! or `all` (every frame the pipeline's sequence sources hold).

use std::fmt;

/// The `--frames` argument.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FrameSelection {
    /// `start..end:step`, `end` excluded.
    Range {
        /// First frame.
        start: u64,
        /// One past the last frame.
        end: u64,
        /// Distance between frames, at least 1.
        step: u64,
    },
    /// Every frame of the pipeline's sequence sources.
    All,
}

/// A `--frames` text that is not a selection.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error(
    "--frames `{text}`: {why} (expected `START..END` (END excluded), `START..END:STEP`, `N` or `all`)"
)]
pub struct FrameSelectionError {
    /// What was given.
    pub text: String,
    /// What is wrong with it.
    pub why: String,
}

/// The most frames one selection may name: a typo such as
/// `0..1000000000` is refused instead of listing a billion frames.
pub const MAX_FRAMES: u64 = 1_000_000;

impl FrameSelection {
    /// Reads `0..100`, `0..100:5`, `7` or `all`.
    pub fn parse(text: &str) -> Result<Self, FrameSelectionError> {
        let err = |why: &str| FrameSelectionError {
            text: text.to_string(),
            why: why.to_string(),
        };
        let t = text.trim();
        if t.eq_ignore_ascii_case("all") {
            return Ok(FrameSelection::All);
        }
        let num = |s: &str, what: &str| -> Result<u64, FrameSelectionError> {
            s.trim()
                .parse::<u64>()
                .map_err(|_| err(&format!("{what} `{}` is not a frame number", s.trim())))
        };
        let (range, step) = match t.split_once(':') {
            Some((r, s)) => (r, num(s, "the step")?),
            None => (t, 1),
        };
        if step == 0 {
            return Err(err("the step must be at least 1"));
        }
        let (start, end) = match range.split_once("..") {
            Some((a, b)) => {
                if b.starts_with('=') {
                    return Err(err("`..=` is not taken: END is excluded, write END + 1"));
                }
                (num(a, "the start")?, num(b, "the end")?)
            }
            None if step == 1 => {
                let n = num(range, "the frame")?;
                (n, n.saturating_add(1))
            }
            None => return Err(err("a step needs a range")),
        };
        if end <= start {
            return Err(err(&format!(
                "the range {start}..{end} holds no frame (END is excluded)"
            )));
        }
        if (end - start).div_ceil(step) > MAX_FRAMES {
            return Err(err(&format!("more than {MAX_FRAMES} frames")));
        }
        Ok(FrameSelection::Range { start, end, step })
    }

    /// The frames, in increasing order; `all` resolves to `0..count` with
    /// `count` the sequence length (`None`: no sequence source, an error the
    /// caller words).
    pub fn frames(&self, count: Option<u64>) -> Option<Vec<u64>> {
        match *self {
            FrameSelection::Range { start, end, step } => {
                Some((start..end).step_by(step as usize).collect())
            }
            FrameSelection::All => count.map(|n| (0..n).collect()),
        }
    }
}

impl fmt::Display for FrameSelection {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            FrameSelection::Range { start, end, step } if *step == 1 => {
                write!(f, "{start}..{end}")
            }
            FrameSelection::Range { start, end, step } => write!(f, "{start}..{end}:{step}"),
            FrameSelection::All => f.write_str("all"),
        }
    }
}

/// One placeholder found in a text: its byte span and its formatting.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Placeholder {
    start: usize,
    end: usize,
    width: usize,
    zero: bool,
}

/// Finds the `{frame}` / `{frame:W}` / `{frame:0W}` placeholders of `s`;
/// `Err` names a malformed one (`{frame:x}`, `{frame` without `}`).
fn placeholders(s: &str) -> Result<Vec<Placeholder>, String> {
    let mut out = Vec::new();
    let mut from = 0;
    while let Some(off) = s[from..].find("{frame") {
        let start = from + off;
        let rest = &s[start + "{frame".len()..];
        let Some(close) = rest.find('}') else {
            return Err(format!("`{{frame` at byte {start} has no closing `}}`"));
        };
        let spec = &rest[..close];
        let (width, zero) = if spec.is_empty() {
            (0, false)
        } else if let Some(w) = spec.strip_prefix(':') {
            let zero = w.starts_with('0') && w.len() > 1;
            match w.parse::<usize>() {
                Ok(n) if n <= 20 && !w.is_empty() => (n, zero),
                _ => {
                    return Err(format!(
                        "`{{frame{spec}}}`: expected `{{frame}}`, `{{frame:W}}` or `{{frame:0W}}` with a width of at most 20"
                    ));
                }
            }
        } else {
            // `{frames}` or `{frame_count}`: not ours, leave it as written
            from = start + 1;
            continue;
        };
        let end = start + "{frame".len() + close + 1;
        out.push(Placeholder {
            start,
            end,
            width,
            zero,
        });
        from = end;
    }
    Ok(out)
}

/// `s` with every frame placeholder replaced by `frame`, or `None` when it
/// has none. `Err` names a malformed placeholder.
///
/// ```
/// use depthgraph_graph::frames::expand;
/// assert_eq!(expand("rgb_{frame:05}.png", 42).unwrap().as_deref(), Some("rgb_00042.png"));
/// assert_eq!(expand("{frame}", 7).unwrap().as_deref(), Some("7"));
/// assert_eq!(expand("plain.png", 7).unwrap(), None);
/// ```
pub fn expand(s: &str, frame: u64) -> Result<Option<String>, String> {
    let found = placeholders(s)?;
    if found.is_empty() {
        return Ok(None);
    }
    let mut out = String::with_capacity(s.len() + 8);
    let mut at = 0;
    for p in found {
        out.push_str(&s[at..p.start]);
        let n = if p.zero {
            format!("{frame:0w$}", w = p.width)
        } else {
            format!("{frame:w$}", w = p.width)
        };
        out.push_str(&n);
        at = p.end;
    }
    out.push_str(&s[at..]);
    Ok(Some(out))
}

/// Whether `s` holds a (well-formed or not) frame placeholder.
pub fn has_placeholder(s: &str) -> bool {
    !matches!(placeholders(s), Ok(v) if v.is_empty())
}

/// Whether `s` is exactly one unpadded placeholder (`"{frame}"`), the form
/// that becomes an integer in a number parameter.
pub fn is_whole_placeholder(s: &str) -> bool {
    placeholders(s)
        .is_ok_and(|p| p.len() == 1 && p[0].start == 0 && p[0].end == s.len() && p[0].width == 0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::document::Document;
    use crate::ron_text::RonValue;

    #[test]
    fn selections_parse_as_documented() {
        let r = |s, e, st| FrameSelection::Range {
            start: s,
            end: e,
            step: st,
        };
        assert_eq!(FrameSelection::parse("0..100").unwrap(), r(0, 100, 1));
        assert_eq!(FrameSelection::parse(" 0..100:5 ").unwrap(), r(0, 100, 5));
        assert_eq!(FrameSelection::parse("7").unwrap(), r(7, 8, 1));
        assert_eq!(FrameSelection::parse("ALL").unwrap(), FrameSelection::All);
        let f = FrameSelection::parse("0..10:3")
            .unwrap()
            .frames(None)
            .unwrap();
        assert_eq!(f, vec![0, 3, 6, 9]);
        assert_eq!(FrameSelection::All.frames(Some(3)).unwrap(), vec![0, 1, 2]);
        assert_eq!(FrameSelection::All.frames(None), None);
        for bad in [
            "",
            "5..5",
            "9..3",
            "0..10:0",
            "a..3",
            "0..=9",
            "3:2",
            "0..1000001",
        ] {
            let e = FrameSelection::parse(bad).unwrap_err();
            assert!(e.to_string().contains("--frames"), "{bad}: {e}");
        }
        for s in ["0..100", "0..100:5", "all"] {
            assert_eq!(FrameSelection::parse(s).unwrap().to_string(), s);
        }
    }

    #[test]
    fn placeholders_expand_with_widths() {
        assert_eq!(
            expand("a{frame}b{frame:03}c", 5).unwrap().unwrap(),
            "a5b005c"
        );
        assert_eq!(expand("{frame:4}", 12).unwrap().unwrap(), "  12");
        assert_eq!(expand("{frame:02}", 1234).unwrap().unwrap(), "1234");
        assert_eq!(expand("{frames}.txt", 1).unwrap(), None);
        assert!(expand("x{frame:q}", 1).is_err());
        assert!(expand("x{frame", 1).is_err());
        assert!(has_placeholder("x{frame:q}"));
        assert!(!has_placeholder("{frames}"));
    }

    #[test]
    fn a_document_for_one_frame_has_no_placeholder_left() {
        let doc = Document::parse(
            r#"(version: 1, nodes: {
                "a": (kind: "K", params: (path: "d/{frame:04}.png", n: "{frame}", s: "x{frame}")),
                "b": (kind: "K", params: (path: "fixed.png")),
            })"#,
            "t.ron",
        )
        .unwrap();
        assert_eq!(
            doc.frame_params(),
            vec![
                ("a".to_string(), "path".to_string()),
                ("a".to_string(), "n".to_string()),
                ("a".to_string(), "s".to_string())
            ]
        );
        let f = doc.for_frame(17).unwrap();
        let a = &f.nodes[0].params;
        assert_eq!(a[0].1.value, RonValue::Str("d/0017.png".into()));
        assert_eq!(a[1].1.value, RonValue::Int(17));
        assert_eq!(a[2].1.value, RonValue::Str("x17".into()));
        assert!(f.frame_params().is_empty());
        assert_eq!(f.nodes[1], doc.nodes[1]);

        let bad = Document::parse(
            r#"(version: 1, nodes: {"a": (kind: "K", params: (path: "{frame:zz}"))})"#,
            "t.ron",
        )
        .unwrap();
        let e = bad.for_frame(0).unwrap_err();
        let text = e[0].to_string();
        assert!(
            text.contains("t.ron:1") && text.contains("`path`"),
            "{text}"
        );
    }
}
