//! Reading exposure brackets: a list file or files with times, values kept
//! after the camera response (not linearised).

use std::path::{Path, PathBuf};

use depthgraph_graph::node_params;
use depthgraph_graph::prelude::*;
use rayon::prelude::*;
// ---------------------------------------------------------------------------
// Loading brackets
// ---------------------------------------------------------------------------

node_params! {
    /// Parameters of `LoadBracket`.
    pub struct LoadBracketParams {
        /// Text file listing the exposures, one per line: `filename exposure_time_s [more columns]`;
        /// `#` starts a comment; file names are relative to the list's directory (Debevec's
        /// memorial `image_list.txt` reads as is). Of HDRShop's further columns (`1/shutter
        /// f/stop gain(dB) ND`), f-stop, gain and ND must be the same on every line: the time
        /// alone is taken as the exposure. Times in seconds: a list whose longer times are the
        /// darker images (1/shutter values, as OpenCV's example lists give) is refused. Leave
        /// empty to use `files`.
        pub list: String = "", ParamKind::InputPath;
        /// Comma-separated image files (8/16-bit PNG or TIFF, JPEG; relative to the working
        /// directory like LoadColor's path), used when `list` is empty.
        pub files: String = "", ParamKind::Text;
        /// Exposure time in seconds of each file of `files`, in the same order.
        pub times_s: Vec<f64> = Vec::<f64>::new(), ParamKind::Floats { min: 0.0, max: 1e6 };
        /// Debevec's memorial series marks shifted borders with pure blue (0, 0, 255):
        /// such pixels become missing (NaN, weight 0 in the merge).
        pub mask_pure_blue: bool = false, ParamKind::Bool;
    }
}

/// Parses an exposure list (see [`LoadBracketParams::list`]); `list` is the
/// list's own path, for errors and for resolving relative file names.
pub fn parse_bracket_list(text: &str, list: &Path) -> Result<Vec<(PathBuf, f64)>, NodeError> {
    let dir = list
        .parent()
        .filter(|d| !d.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    let err = |line: usize, message: String| NodeError::Decode {
        path: list.to_path_buf(),
        message: format!("line {line}: {message}"),
    };
    let mut out = Vec::new();
    // the first exposure's columns after its time
    let mut first_rest: Vec<String> = Vec::new();
    for (n, raw) in text.lines().enumerate() {
        let line = raw.split('#').next().unwrap_or("").trim();
        if line.is_empty() {
            continue;
        }
        let mut tokens = line.split_whitespace();
        let (Some(name), Some(time)) = (tokens.next(), tokens.next()) else {
            return Err(err(
                n + 1,
                format!("expected `filename exposure_time_s`, found `{line}`"),
            ));
        };
        let t: f64 = time.parse().map_err(|_| {
            err(
                n + 1,
                format!("exposure time `{time}` of {name} is not a number"),
            )
        })?;
        if !(t.is_finite() && t > 0.0) {
            return Err(err(
                n + 1,
                format!("exposure time {t} s of {name} must be positive"),
            ));
        }
        // the columns after the time (`1/shutter_speed f/stop gain(db)
        // ND_filters`, or without the first): the merge takes the time alone as the
        // exposure, so the aperture, gain and filter must be the same on
        // every line (numbers that differ would be merged as equal
        // exposures, silently wrong)
        let rest: Vec<&str> = tokens.collect();
        // after the time: `1/shutter f/stop gain ND` (Debevec's lists), or
        // `f/stop gain ND`; told apart by the first line's column count
        // (fewer columns say nothing of the aperture: not checked), and
        // checked on lines with as many
        let first_col = match first_rest.len() {
            n if n >= 4 => Some(1),
            3 => Some(0),
            _ => None,
        }
        .filter(|_| rest.len() == first_rest.len());
        for (off, what) in [(0, "f-stop"), (1, "gain"), (2, "ND filter")] {
            let Some(col) = first_col.map(|c| c + off) else {
                break;
            };
            let (Some(here), Some(first)) = (rest.get(col), first_rest.get(col)) else {
                continue;
            };
            if let (Ok(a), Ok(b)) = (here.parse::<f64>(), first.parse::<f64>())
                && a != b
            {
                return Err(err(
                    n + 1,
                    format!(
                        "{name}'s {what} is {here}, the first exposure's {first}: exposures that \
                         differ in anything but time are not merged (give each line a time that \
                         includes the difference, and equal {what}s)"
                    ),
                ));
            }
        }
        if out.is_empty() {
            first_rest = rest.iter().map(|t| t.to_string()).collect();
        }
        out.push((dir.join(name), t));
    }
    if out.is_empty() {
        return Err(NodeError::Decode {
            path: list.to_path_buf(),
            message: "lists no exposure (expected lines `filename exposure_time_s`)".into(),
        });
    }
    Ok(out)
}

/// The files and times the parameters name (reads the list file if set).
pub fn bracket_entries(p: &LoadBracketParams) -> Result<Vec<(PathBuf, f64)>, NodeError> {
    let files: Vec<&str> = p
        .files
        .split(',')
        .map(str::trim)
        .filter(|f| !f.is_empty())
        .collect();
    if !p.list.is_empty() {
        if !files.is_empty() || !p.times_s.is_empty() {
            return Err(NodeError::param(
                "list",
                "set either `list` or `files` + `times_s`, not both",
            ));
        }
        let path = Path::new(&p.list);
        let text = std::fs::read_to_string(path).map_err(|e| NodeError::read(path, e))?;
        return parse_bracket_list(&text, path);
    }
    if files.is_empty() {
        return Err(NodeError::param(
            "list",
            "no exposures given: set `list` (a file of `filename exposure_time_s` lines) or `files` and `times_s`",
        ));
    }
    if files.len() != p.times_s.len() {
        return Err(NodeError::param(
            "times_s",
            format!(
                "holds {} times for the {} files of `files`; expected one per file",
                p.times_s.len(),
                files.len()
            ),
        ));
    }
    files
        .iter()
        .zip(&p.times_s)
        .map(|(f, t)| {
            if t.is_finite() && *t > 0.0 {
                Ok((PathBuf::from(f), *t))
            } else {
                Err(NodeError::param(
                    "times_s",
                    format!("exposure time {t} s of {f} must be positive"),
                ))
            }
        })
        .collect()
}

/// Loads an exposure bracket: values are the stored codes scaled to `[0, 1]`
/// (`/255`, `/65535`), **not** sRGB-linearised, since the merge needs the
/// values after the camera response. Every image must have the size of the
/// first; pure-blue pixels become NaN when `mask_pure_blue` is set.
pub fn load_bracket(p: &LoadBracketParams) -> Result<ExposureStack, NodeError> {
    load_bracket_with(p, &crate::io::Limits::default())
}

/// [`load_bracket`] with each image's header checked against `lim` before
/// its pixels are decoded.
pub fn load_bracket_with(
    p: &LoadBracketParams,
    lim: &crate::io::Limits,
) -> Result<ExposureStack, NodeError> {
    let entries = bracket_entries(p)?;
    let loaded: Vec<Result<ColorImage, NodeError>> = entries
        .par_iter()
        .map(|(path, _)| crate::io::load_color_with(path, crate::io::ColorSpace::Linear, lim))
        .collect();
    let mut stack = ExposureStack::default();
    for ((path, t), img) in entries.iter().zip(loaded) {
        let mut img = img?;
        if let Some(first) = stack.images.first()
            && img.dims() != first.dims()
        {
            return Err(NodeError::Decode {
                path: path.clone(),
                message: format!(
                    "is {}x{} but {} is {}x{}; every exposure must have the same size",
                    img.width(),
                    img.height(),
                    entries[0].0.display(),
                    first.width(),
                    first.height()
                ),
            });
        }
        if p.mask_pure_blue {
            for px in img.as_mut_slice() {
                if *px == [0.0, 0.0, 1.0] {
                    *px = [f32::NAN; 3];
                }
            }
        }
        stack.images.push(img);
        stack.times_s.push(*t);
    }
    let param = if p.list.is_empty() { "times_s" } else { "list" };
    check_times_follow_brightness(&stack, param)?;
    Ok(stack)
}

/// A step in mean level (of [0, 1]) between two exposures that counts as
/// brighter or darker.
const BRIGHTNESS_STEP: f64 = 0.01;

/// Longer exposures are brighter: a stack whose every measurable step from
/// one exposure time to the next longer one is darker has its times
/// inverted (a list giving 1/shutter, as OpenCV's tutorial lists do, read
/// as seconds), and the merge would be silently wrong: an error naming
/// `param`. Steps within [`BRIGHTNESS_STEP`] (saturated or black frames)
/// say nothing and are not counted.
pub fn check_times_follow_brightness(stack: &ExposureStack, param: &str) -> Result<(), NodeError> {
    let mean = |img: &ColorImage| {
        let (sum, n) = img
            .as_slice()
            .iter()
            .flatten()
            .filter(|v| v.is_finite())
            .fold((0.0f64, 0usize), |(s, n), v| (s + f64::from(*v), n + 1));
        // guard: an image with no finite value has no level
        (n > 0).then(|| sum / n as f64)
    };
    let mut by_time: Vec<(f64, Option<f64>)> = stack
        .times_s
        .iter()
        .zip(&stack.images)
        .map(|(t, img)| (*t, mean(img)))
        .collect();
    by_time.sort_by(|a, b| a.0.total_cmp(&b.0));
    let (mut up, mut down) = (0usize, 0usize);
    for pair in by_time.windows(2) {
        let ((ta, Some(a)), (tb, Some(b))) = (pair[0], pair[1]) else {
            continue;
        };
        if tb > ta {
            up += usize::from(b - a > BRIGHTNESS_STEP);
            down += usize::from(a - b > BRIGHTNESS_STEP);
        }
    }
    if down > 0 && up == 0 {
        let (longest, shortest) = (
            by_time.last().map_or(0.0, |e| e.0),
            by_time.first().map_or(0.0, |e| e.0),
        );
        return Err(NodeError::param(
            param,
            format!(
                "the exposure times run opposite to the images' brightness (the longest, {longest} s, \
                 is the darkest; the shortest, {shortest} s, the brightest): times given as 1/shutter \
                 (as OpenCV's example lists give them) read as seconds are inverted; give seconds"
            ),
        ));
    }
    Ok(())
}

depthgraph_graph::ports! {
    /// Outputs of `LoadBracket`.
    outputs struct LoadBracketOut {
        /// values in [0, 1] after the camera response; NaN = missing
        exposures: ExposureStack,
    }
}

pub(super) fn load_bracket_eval(
    ctx: &EvalCtx,
    _: NoInputs,
    p: &LoadBracketParams,
) -> Result<Produced<LoadBracketOut>, NodeError> {
    Ok(LoadBracketOut {
        exposures: load_bracket_with(p, &crate::io::Limits::of(ctx))?,
    }
    .into())
}

pub(super) fn bracket_files(p: &LoadBracketParams) -> Vec<PathBuf> {
    let mut out = Vec::new();
    if !p.list.is_empty() {
        out.push(PathBuf::from(&p.list));
    }
    // best effort: the images the list names (an unreadable list is reported by eval)
    if let Ok(entries) = bracket_entries(p) {
        out.extend(entries.into_iter().map(|e| e.0));
    }
    out
}
