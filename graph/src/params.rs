//! Node parameters: one declaration gives the serde struct a node's code
//! uses and the schema (type, default, range, doc) that the CLI, the checker,
//! the editor and the docs read. See [`node_params!`](crate::node_params).

use std::collections::BTreeMap;
use std::fmt;

/// What values a parameter takes.
#[derive(Debug, Clone, PartialEq)]
pub enum ParamKind {
    /// A real number in `[min, max]` (inclusive).
    Float {
        /// Smallest value admitted.
        min: f64,
        /// Largest value admitted.
        max: f64,
    },
    /// An integer in `[min, max]` (inclusive).
    Int {
        /// Smallest value admitted.
        min: i64,
        /// Largest value admitted.
        max: i64,
    },
    /// `true` or `false`.
    Bool,
    /// Free text.
    Text,
    /// A file the pipeline reads (never overwritten by a sink).
    InputPath,
    /// A file the pipeline writes; relative paths are resolved against `--out`.
    OutputPath,
    /// One of a fixed set of names.
    Choice(&'static [&'static str]),
    /// A list of `(x, y)` pixel positions, e.g. lasso clicks.
    Points,
    /// A list of real numbers, each in `[min, max]`.
    Floats {
        /// Smallest value admitted.
        min: f64,
        /// Largest value admitted.
        max: f64,
    },
    /// Three real numbers, each in `[min, max]`.
    Vec3 {
        /// Smallest value admitted.
        min: f64,
        /// Largest value admitted.
        max: f64,
    },
}

impl ParamKind {
    /// Short type name for messages and `depthgraph nodes`.
    pub fn type_name(&self) -> &'static str {
        match self {
            ParamKind::Float { .. } => "float",
            ParamKind::Int { .. } => "integer",
            ParamKind::Bool => "bool",
            ParamKind::Text => "text",
            ParamKind::InputPath => "input path",
            ParamKind::OutputPath => "output path",
            ParamKind::Choice(_) => "choice",
            ParamKind::Points => "list of (x, y) points",
            ParamKind::Floats { .. } => "list of floats",
            ParamKind::Vec3 { .. } => "(x, y, z)",
        }
    }

    /// Human-readable range, e.g. `[0, 1]` or `one of "a", "b"`.
    pub fn range_text(&self) -> String {
        match self {
            ParamKind::Float { min, max }
            | ParamKind::Floats { min, max }
            | ParamKind::Vec3 { min, max } => format!("[{min}, {max}]"),
            ParamKind::Int { min, max } => format!("[{min}, {max}]"),
            ParamKind::Choice(c) => {
                let names: Vec<String> = c.iter().map(|s| format!("\"{s}\"")).collect();
                format!("one of {}", names.join(", "))
            }
            _ => String::new(),
        }
    }

    /// Checks that `v` is of this kind and within range. The error says what
    /// was expected and what was found.
    pub fn validate(&self, v: &ParamValue) -> Result<(), ParamCheck> {
        let type_err = || ParamCheck::Type {
            expected: self.type_name(),
            found: v.type_name(),
        };
        let range_err = |x: f64| ParamCheck::Range {
            value: x,
            range: self.range_text(),
        };
        match (self, v) {
            (ParamKind::Float { min, max }, ParamValue::Float(x)) => {
                if x.is_nan() || *x < *min || *x > *max {
                    return Err(range_err(*x));
                }
            }
            (ParamKind::Int { min, max }, ParamValue::Int(x)) => {
                if x < min || x > max {
                    return Err(range_err(*x as f64));
                }
            }
            (ParamKind::Bool, ParamValue::Bool(_)) => {}
            (
                ParamKind::Text | ParamKind::InputPath | ParamKind::OutputPath,
                ParamValue::Text(_),
            ) => {}
            (ParamKind::Choice(c), ParamValue::Text(s)) => {
                if !c.contains(&s.as_str()) {
                    return Err(ParamCheck::Choice {
                        found: s.clone(),
                        choices: c,
                    });
                }
            }
            (ParamKind::Points, ParamValue::Points(p)) => {
                if let Some(bad) = p.iter().flatten().find(|x| !x.is_finite()) {
                    return Err(range_err(*bad));
                }
            }
            (ParamKind::Floats { min, max }, ParamValue::Floats(xs)) => {
                if let Some(x) = xs.iter().find(|x| x.is_nan() || **x < *min || **x > *max) {
                    return Err(range_err(*x));
                }
            }
            (ParamKind::Vec3 { min, max }, ParamValue::Vec3(xs)) => {
                if let Some(x) = xs.iter().find(|x| x.is_nan() || **x < *min || **x > *max) {
                    return Err(range_err(*x));
                }
            }
            _ => return Err(type_err()),
        }
        Ok(())
    }

    /// Converts a value written in a looser form to this kind where that is
    /// unambiguous (an integer literal for a float parameter).
    pub fn coerce(&self, v: ParamValue) -> ParamValue {
        match (self, v) {
            (ParamKind::Float { .. }, ParamValue::Int(i)) => ParamValue::Float(i as f64),
            (ParamKind::Floats { .. }, ParamValue::Floats(x)) => ParamValue::Floats(x),
            (_, v) => v,
        }
    }
}

/// Why a parameter value was refused.
#[derive(Debug, Clone, PartialEq)]
pub enum ParamCheck {
    /// The value has another type than the parameter.
    Type {
        /// Type name the parameter takes.
        expected: &'static str,
        /// Type name of the value given.
        found: &'static str,
    },
    /// A number outside the parameter's range (for lists, the first such element).
    Range {
        /// The offending number (integers converted to `f64`).
        value: f64,
        /// The range, as [`ParamKind::range_text`] writes it.
        range: String,
    },
    /// Text that is not one of the allowed names.
    Choice {
        /// The text given.
        found: String,
        /// The allowed names.
        choices: &'static [&'static str],
    },
}

impl fmt::Display for ParamCheck {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            ParamCheck::Type { expected, found } => write!(f, "expected {expected}, found {found}"),
            ParamCheck::Range { value, range } => write!(f, "value {value} is outside {range}"),
            ParamCheck::Choice { found, choices } => {
                let names: Vec<String> = choices.iter().map(|s| format!("\"{s}\"")).collect();
                write!(f, "\"{found}\" is not one of {}", names.join(", "))
            }
        }
    }
}

/// A parameter value as written in a pipeline.
#[derive(Debug, Clone, PartialEq)]
pub enum ParamValue {
    /// A real number.
    Float(f64),
    /// An integer.
    Int(i64),
    /// A boolean.
    Bool(bool),
    /// Text, paths and choices.
    Text(String),
    /// A list of `(x, y)` pixel positions.
    Points(Vec<[f64; 2]>),
    /// A list of real numbers.
    Floats(Vec<f64>),
    /// Three real numbers `(x, y, z)`.
    Vec3([f64; 3]),
}

impl ParamValue {
    /// Short type name for messages, e.g. `"float"`.
    pub fn type_name(&self) -> &'static str {
        match self {
            ParamValue::Float(_) => "float",
            ParamValue::Int(_) => "integer",
            ParamValue::Bool(_) => "bool",
            ParamValue::Text(_) => "text",
            ParamValue::Points(_) => "list of points",
            ParamValue::Floats(_) => "list of floats",
            ParamValue::Vec3(_) => "(x, y, z)",
        }
    }

    /// Canonical bytes for hashing: floats by bit pattern, so `0.1` and
    /// `0.10000000000000001` (the same f64) hash alike and `-0.0` differs from `0.0`.
    pub fn canonical_bytes(&self, out: &mut Vec<u8>) {
        match self {
            ParamValue::Float(x) => {
                out.push(1);
                out.extend_from_slice(&x.to_bits().to_le_bytes());
            }
            ParamValue::Int(x) => {
                out.push(2);
                out.extend_from_slice(&x.to_le_bytes());
            }
            ParamValue::Bool(b) => out.extend_from_slice(&[3, *b as u8]),
            ParamValue::Text(s) => {
                out.push(4);
                out.extend_from_slice(&(s.len() as u64).to_le_bytes());
                out.extend_from_slice(s.as_bytes());
            }
            ParamValue::Points(p) => {
                out.push(5);
                out.extend_from_slice(&(p.len() as u64).to_le_bytes());
                for x in p.iter().flatten() {
                    out.extend_from_slice(&x.to_bits().to_le_bytes());
                }
            }
            ParamValue::Floats(p) => {
                out.push(6);
                out.extend_from_slice(&(p.len() as u64).to_le_bytes());
                for x in p {
                    out.extend_from_slice(&x.to_bits().to_le_bytes());
                }
            }
            ParamValue::Vec3(p) => {
                out.push(7);
                for x in p {
                    out.extend_from_slice(&x.to_bits().to_le_bytes());
                }
            }
        }
    }

    /// The value written as RON text (what `Document::to_ron` emits).
    pub fn to_ron(&self) -> String {
        fn float(x: f64) -> String {
            if x.is_finite() && x == x.trunc() && x.abs() < 1e15 {
                format!("{x:.1}")
            } else {
                format!("{x:?}")
            }
        }
        match self {
            ParamValue::Float(x) => float(*x),
            ParamValue::Int(i) => i.to_string(),
            ParamValue::Bool(b) => b.to_string(),
            ParamValue::Text(s) => quote(s),
            ParamValue::Points(p) => {
                let items: Vec<String> = p
                    .iter()
                    .map(|[x, y]| format!("({}, {})", float(*x), float(*y)))
                    .collect();
                format!("[{}]", items.join(", "))
            }
            ParamValue::Floats(p) => {
                let items: Vec<String> = p.iter().map(|x| float(*x)).collect();
                format!("[{}]", items.join(", "))
            }
            ParamValue::Vec3([a, b, c]) => format!("({}, {}, {})", float(*a), float(*b), float(*c)),
        }
    }
}

/// RON string literal with escapes.
pub fn quote(s: &str) -> String {
    let mut out = String::with_capacity(s.len() + 2);
    out.push('"');
    for c in s.chars() {
        match c {
            '"' => out.push_str("\\\""),
            '\\' => out.push_str("\\\\"),
            '\n' => out.push_str("\\n"),
            '\t' => out.push_str("\\t"),
            '\r' => out.push_str("\\r"),
            c => out.push(c),
        }
    }
    out.push('"');
    out
}

impl fmt::Display for ParamValue {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.to_ron())
    }
}

/// Parameter values by name, sorted (the canonical order for hashing).
pub type ParamMap = BTreeMap<String, ParamValue>;

/// One parameter of a node kind.
#[derive(Debug, Clone, PartialEq)]
pub struct ParamSpec {
    /// Field name, as written in pipelines.
    pub name: &'static str,
    /// Type and range of the values it takes.
    pub kind: ParamKind,
    /// Value used when the pipeline gives none.
    pub default: ParamValue,
    /// One-line description.
    pub doc: &'static str,
}

/// A parameter struct declared with [`node_params!`](crate::node_params).
pub trait NodeParams: Sized + Default + Clone + Send + Sync + 'static {
    /// Schema of every field, in declaration order.
    fn specs() -> Vec<ParamSpec>;
    /// Builds the struct from checked values; absent names keep their default.
    fn from_values(values: &ParamMap) -> Result<Self, String>;
    /// All fields as values.
    fn to_values(&self) -> ParamMap;
}

/// Turns a default written in [`node_params!`](crate::node_params) into the field's type: the
/// value itself, or a `&str` for a `String` field.
pub trait ParamDefault<T> {
    /// The default as a value of the field's type.
    fn into_default(self) -> T;
}
impl<T> ParamDefault<T> for T {
    fn into_default(self) -> T {
        self
    }
}
impl ParamDefault<String> for &str {
    fn into_default(self) -> String {
        self.to_string()
    }
}

/// Conversion of a Rust field to a [`ParamValue`].
pub trait ToParam {
    /// The field as a parameter value.
    fn to_param(&self) -> ParamValue;
}
/// Conversion of a checked [`ParamValue`] to a Rust field.
pub trait FromParam: Sized {
    /// The field from a checked value; `Err` with a message when the value has another type.
    fn from_param(v: &ParamValue) -> Result<Self, String>;
}

macro_rules! float_param {
    ($($t:ty),*) => {$(
        impl ToParam for $t { fn to_param(&self) -> ParamValue { ParamValue::Float(*self as f64) } }
        impl FromParam for $t {
            fn from_param(v: &ParamValue) -> Result<Self, String> {
                match v {
                    ParamValue::Float(x) => Ok(*x as $t),
                    ParamValue::Int(i) => Ok(*i as $t),
                    other => Err(format!("expected float, found {}", other.type_name())),
                }
            }
        }
    )*};
}
float_param!(f32, f64);

macro_rules! int_param {
    ($($t:ty),*) => {$(
        impl ToParam for $t { fn to_param(&self) -> ParamValue { ParamValue::Int(*self as i64) } }
        impl FromParam for $t {
            fn from_param(v: &ParamValue) -> Result<Self, String> {
                match v {
                    ParamValue::Int(i) => <$t>::try_from(*i).map_err(|_| format!("integer {i} does not fit")),
                    other => Err(format!("expected integer, found {}", other.type_name())),
                }
            }
        }
    )*};
}
int_param!(u8, u16, u32, u64, usize, i32, i64);

impl ToParam for bool {
    fn to_param(&self) -> ParamValue {
        ParamValue::Bool(*self)
    }
}
impl FromParam for bool {
    fn from_param(v: &ParamValue) -> Result<Self, String> {
        match v {
            ParamValue::Bool(b) => Ok(*b),
            other => Err(format!("expected bool, found {}", other.type_name())),
        }
    }
}
impl ToParam for String {
    fn to_param(&self) -> ParamValue {
        ParamValue::Text(self.clone())
    }
}
impl FromParam for String {
    fn from_param(v: &ParamValue) -> Result<Self, String> {
        match v {
            ParamValue::Text(s) => Ok(s.clone()),
            other => Err(format!("expected text, found {}", other.type_name())),
        }
    }
}
impl ToParam for Vec<[f64; 2]> {
    fn to_param(&self) -> ParamValue {
        ParamValue::Points(self.clone())
    }
}
impl FromParam for Vec<[f64; 2]> {
    fn from_param(v: &ParamValue) -> Result<Self, String> {
        match v {
            ParamValue::Points(p) => Ok(p.clone()),
            other => Err(format!("expected points, found {}", other.type_name())),
        }
    }
}
impl ToParam for Vec<f64> {
    fn to_param(&self) -> ParamValue {
        ParamValue::Floats(self.clone())
    }
}
impl FromParam for Vec<f64> {
    fn from_param(v: &ParamValue) -> Result<Self, String> {
        match v {
            ParamValue::Floats(p) => Ok(p.clone()),
            other => Err(format!(
                "expected list of floats, found {}",
                other.type_name()
            )),
        }
    }
}
impl ToParam for [f64; 3] {
    fn to_param(&self) -> ParamValue {
        ParamValue::Vec3(*self)
    }
}
impl FromParam for [f64; 3] {
    fn from_param(v: &ParamValue) -> Result<Self, String> {
        match v {
            ParamValue::Vec3(p) => Ok(*p),
            other => Err(format!("expected (x, y, z), found {}", other.type_name())),
        }
    }
}

/// Declares a parameter struct and its schema in one place.
///
/// Each field carries doc comments (they become the parameter's documentation),
/// a type, a default and a [`ParamKind`] giving its range:
///
/// ```
/// use depthgraph_graph::{node_params, params::{NodeParams, ParamKind}};
/// node_params! {
///     /// Parameters of a blur.
///     pub struct BlurParams {
///         /// Gaussian standard deviation in pixels.
///         pub sigma_px: f64 = 1.5, ParamKind::Float { min: 0.0, max: 100.0 };
///         /// Border handling.
///         pub border: String = "clamp", ParamKind::Choice(&["clamp", "zero"]);
///     }
/// }
/// let specs = BlurParams::specs();
/// assert_eq!(specs[0].name, "sigma_px");
/// assert_eq!(BlurParams::default().sigma_px, 1.5);
/// ```
#[macro_export]
macro_rules! node_params {
    (
        $(#[$meta:meta])*
        $vis:vis struct $name:ident {
            $(
                $(#[doc = $doc:literal])+
                $fvis:vis $field:ident : $ty:ty = $default:expr, $kind:expr;
            )*
        }
    ) => {
        $(#[$meta])*
        #[derive(Debug, Clone, PartialEq)]
        $vis struct $name {
            $( $(#[doc = $doc])+ $fvis $field: $ty, )*
        }

        impl ::core::default::Default for $name {
            fn default() -> Self {
                Self { $( $field: $crate::params::ParamDefault::<$ty>::into_default($default), )* }
            }
        }

        impl $crate::params::NodeParams for $name {
            fn specs() -> ::std::vec::Vec<$crate::params::ParamSpec> {
                let d = <Self as ::core::default::Default>::default();
                let _ = &d;
                ::std::vec![ $(
                    $crate::params::ParamSpec {
                        name: stringify!($field),
                        kind: $kind,
                        default: $crate::params::ToParam::to_param(&d.$field),
                        doc: concat!($($doc, "\n"),+).trim_ascii(),
                    },
                )* ]
            }
            fn from_values(values: &$crate::params::ParamMap) -> ::core::result::Result<Self, ::std::string::String> {
                let mut out = <Self as ::core::default::Default>::default();
                $(
                    if let Some(v) = values.get(stringify!($field)) {
                        out.$field = $crate::params::FromParam::from_param(v)
                            .map_err(|e| format!("parameter `{}`: {}", stringify!($field), e))?;
                    }
                )*
                let _ = values;
                Ok(out)
            }
            fn to_values(&self) -> $crate::params::ParamMap {
                let mut m = $crate::params::ParamMap::new();
                $( m.insert(stringify!($field).to_string(), $crate::params::ToParam::to_param(&self.$field)); )*
                m
            }
        }
    };
}

/// Declares a choice parameter's type: a Rust enum whose variants are
/// written in pipelines as the given names. The schema takes its names
/// from `NAMES` (`ParamKind::Choice(Enum::NAMES)`), so a node matches on
/// the enum and has no arm for a name it does not know.
///
/// ```
/// use depthgraph_graph::param_choice;
/// use depthgraph_graph::params::{FromParam, ParamValue, ToParam};
/// param_choice! {
///     /// Border handling.
///     pub enum Border {
///         /// Repeat the edge pixel.
///         Clamp = "clamp",
///         /// Zero outside.
///         Zero = "zero",
///     }
/// }
/// assert_eq!(Border::NAMES, &["clamp", "zero"]);
/// assert_eq!(Border::from_param(&ParamValue::Text("zero".into())), Ok(Border::Zero));
/// assert_eq!(Border::Clamp.to_param(), ParamValue::Text("clamp".into()));
/// assert!(Border::from_param(&ParamValue::Text("wrap".into())).is_err());
/// ```
#[macro_export]
macro_rules! param_choice {
    (
        $(#[$meta:meta])*
        $vis:vis enum $name:ident {
            $(
                $(#[doc = $doc:literal])*
                $variant:ident = $text:literal
            ),+ $(,)?
        }
    ) => {
        $(#[$meta])*
        #[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
        $vis enum $name {
            $( $(#[doc = $doc])* $variant, )+
        }

        impl $name {
            /// The names as written in pipelines, in declaration order.
            pub const NAMES: &'static [&'static str] = &[$($text),+];
            /// The name as written in pipelines.
            pub fn name(self) -> &'static str {
                match self { $( Self::$variant => $text, )+ }
            }
            /// The choice written `name`, if any.
            pub fn from_name(name: &str) -> ::core::option::Option<Self> {
                match name { $( $text => Some(Self::$variant), )+ _ => None }
            }
        }

        impl ::core::fmt::Display for $name {
            fn fmt(&self, f: &mut ::core::fmt::Formatter<'_>) -> ::core::fmt::Result {
                f.write_str(self.name())
            }
        }

        impl $crate::params::ToParam for $name {
            fn to_param(&self) -> $crate::params::ParamValue {
                $crate::params::ParamValue::Text(self.name().to_string())
            }
        }

        impl $crate::params::FromParam for $name {
            fn from_param(v: &$crate::params::ParamValue) -> ::core::result::Result<Self, ::std::string::String> {
                match v {
                    $crate::params::ParamValue::Text(t) => Self::from_name(t).ok_or_else(|| {
                        format!("\"{t}\" is not one of {:?}", Self::NAMES)
                    }),
                    other => Err(format!("expected one of {:?}, found {}", Self::NAMES, other.type_name())),
                }
            }
        }
    };
}

#[cfg(test)]
mod tests {
    use super::*;

    crate::node_params! {
        /// Test params.
        pub struct P {
            /// A float.
            pub a: f64 = 0.5, ParamKind::Float { min: 0.0, max: 1.0 };
            /// An int.
            /// Second doc line.
            pub n: u32 = 3, ParamKind::Int { min: 1, max: 10 };
            /// A choice.
            pub mode: String = "x", ParamKind::Choice(&["x", "y"]);
        }
    }

    #[test]
    fn specs_carry_defaults_and_docs() {
        let s = P::specs();
        assert_eq!(s.len(), 3);
        assert_eq!(s[0].default, ParamValue::Float(0.5));
        assert_eq!(s[1].default, ParamValue::Int(3));
        assert_eq!(s[1].doc, "An int.\n Second doc line.");
        for spec in &s {
            spec.kind.validate(&spec.default).unwrap();
        }
    }

    #[test]
    fn round_trip_through_values() {
        let mut v = P::default().to_values();
        v.insert("n".into(), ParamValue::Int(7));
        let p = P::from_values(&v).unwrap();
        assert_eq!(p.n, 7);
        assert_eq!(p.to_values(), v);
    }

    #[test]
    fn validation_names_range_and_type() {
        let k = ParamKind::Float { min: 0.0, max: 1.0 };
        assert!(matches!(
            k.validate(&ParamValue::Float(2.0)),
            Err(ParamCheck::Range { .. })
        ));
        assert!(matches!(
            k.validate(&ParamValue::Float(f64::NAN)),
            Err(ParamCheck::Range { .. })
        ));
        assert!(matches!(
            k.validate(&ParamValue::Bool(true)),
            Err(ParamCheck::Type { .. })
        ));
        let c = ParamKind::Choice(&["a", "b"]);
        let e = c.validate(&ParamValue::Text("z".into())).unwrap_err();
        assert_eq!(e.to_string(), "\"z\" is not one of \"a\", \"b\"");
    }

    #[test]
    fn canonical_bytes_distinguish_float_bits() {
        let mut a = Vec::new();
        let mut b = Vec::new();
        ParamValue::Float(0.0).canonical_bytes(&mut a);
        ParamValue::Float(-0.0).canonical_bytes(&mut b);
        assert_ne!(a, b);
    }
}
