//! RGB-D sequences: one color and depth pair per frame index.
//!
//! A sequence is one of:
//! - a **TUM RGB-D folder** (`rgb.txt` and `depth.txt`, lines
//!   `timestamp path`): colour and depth frames are associated as TUM's
//!   `associate.py` does, by nearest timestamp within `max_difference_s`,
//!   the closest candidate pairs first, each frame used once, the pairs then
//!   in colour-time order;
//! - a **list file**: one frame per line, `color depth` or the four columns
//!   `t color t depth` that `associate.py` prints, `#` comments, paths
//!   relative to the list's folder;
//! - a **glob** of colour files (`*` and `?` in the file name only) with a
//!   second glob for the depth files, paired in name order.
//!
//! [`frames`] lists the pairs; the `LoadSequence` node reads the pair of its
//! `frame` parameter (`frame: "{frame}"` in a pipeline run by `depthgraph
//! batch`, whose `--frames all` is [`frames`]' length).

use std::fs;
use std::path::{Path, PathBuf};

use depthgraph_graph::node_params;
use depthgraph_graph::prelude::*;

use super::decode::read_file;
use super::{ColorSpace, DepthEncoding, Limits, LoadDepthParams, load_color_with, load_depth_with};

node_params! {
    /// Parameters of `LoadSequence`.
    pub struct LoadSequenceParams {
        /// A TUM RGB-D folder (with rgb.txt and depth.txt), a list file
        /// (`color depth` per line), or a glob of colour files such as
        /// `seq/rgb/*.png` (then `depth_glob` is required).
        pub source: String = "", ParamKind::InputPath;
        /// With a glob `source`: the glob of the depth files, paired with the
        /// colour files in name order.
        pub depth_glob: String = "", ParamKind::Text;
        /// Which pair to read, from 0 (`"{frame}"` in a batch).
        pub frame: u32 = 0u32, ParamKind::Int { min: 0, max: 100_000_000 };
        /// TUM folders: the largest time difference of an associated pair, seconds
        /// (associate.py's default 0.02).
        pub max_difference_s: f64 = 0.02, ParamKind::Float { min: 1e-6, max: 10.0 };
        /// Stored depth units per metre; 0 = auto: 5000 in a TUM folder (its
        /// convention), else as LoadDepth (1000 for integer files, 1 for float).
        pub depth_scale: f64 = 0.0, ParamKind::Float { min: 0.0, max: 1e9 };
        /// Encoding of 8/16-bit colour files.
        pub color_space: ColorSpace = ColorSpace::Srgb, ParamKind::Choice(ColorSpace::NAMES);
    }
}

/// One frame of a sequence: its colour and depth files.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FramePair {
    /// The colour image.
    pub color: PathBuf,
    /// The depth image.
    pub depth: PathBuf,
}

/// What kind of sequence `source` names.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SequenceKind {
    /// A TUM RGB-D folder.
    Tum,
    /// A list file.
    List,
    /// A glob of colour files.
    Glob,
}

/// The kind of sequence `source` names.
pub fn kind_of(source: &Path) -> SequenceKind {
    let s = source.to_string_lossy();
    if s.contains('*') || s.contains('?') {
        SequenceKind::Glob
    } else if source.is_dir() {
        SequenceKind::Tum
    } else {
        SequenceKind::List
    }
}

fn bad(path: &Path, message: impl Into<String>) -> NodeError {
    NodeError::Decode {
        path: path.to_path_buf(),
        message: message.into(),
    }
}

fn read_text(path: &Path) -> Result<String, NodeError> {
    // (a regular file only, within the default budget: `read_file`)
    let bytes = read_file(path, &Limits::default())?;
    String::from_utf8(bytes).map_err(|_| bad(path, "not UTF-8 text"))
}

/// `(timestamp, path)` lines of a TUM list, paths relative to `dir`.
fn tum_list(path: &Path, dir: &Path) -> Result<Vec<(f64, PathBuf)>, NodeError> {
    let mut out = Vec::new();
    for (n, line) in read_text(path)?.lines().enumerate() {
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        // as associate.py reads them: commas and tabs are spaces, and a
        // line without a path is skipped
        let line = line.replace([',', '\t'], " ");
        let mut cols = line.split_whitespace();
        let (Some(t), Some(file)) = (cols.next(), cols.next()) else {
            continue;
        };
        let t: f64 = t
            .parse()
            .ok()
            .filter(|t: &f64| t.is_finite())
            .ok_or_else(|| bad(path, format!("line {}: `{t}` is not a timestamp", n + 1)))?;
        out.push((t, dir.join(file)));
    }
    Ok(out)
}

/// Candidate pairs [`associate`] weighs at most (24 bytes each): a real
/// capture has one or two per colour frame; lists of repeated timestamps
/// or a tolerance of minutes over thousands of frames would ask for
/// gigabytes.
pub const MAX_ASSOCIATION_CANDIDATES: usize = 1 << 24;

/// TUM's association: candidate pairs with `|ta - tb| < max_difference`,
/// taken closest first, each colour and depth frame at most once; the
/// result in colour-time order. Returns index pairs into `a` and `b`, or
/// the number of candidates when more than [`MAX_ASSOCIATION_CANDIDATES`]
/// fall within the tolerance (counted before any is stored).
pub fn associate(a: &[f64], b: &[f64], max_difference: f64) -> Result<Vec<(usize, usize)>, usize> {
    // b's indices sorted by time, for a window search per colour stamp
    let mut bs: Vec<usize> = (0..b.len()).collect();
    bs.sort_by(|&i, &j| b[i].total_cmp(&b[j]).then(i.cmp(&j)));
    let times: Vec<f64> = bs.iter().map(|&i| b[i]).collect();
    // the window of each colour stamp: its depth stamps `lo..hi` (the
    // differences of the test below, so a pair exactly at the rounding
    // edge of the limit is judged once, alike)
    let window = |ta: f64| {
        let lo = times.partition_point(|&t| ta - t >= max_difference);
        let hi = lo + times[lo..].partition_point(|&t| t - ta < max_difference);
        (lo, hi)
    };
    let count: usize = a
        .iter()
        .map(|&ta| {
            let (lo, hi) = window(ta);
            hi - lo
        })
        .fold(0usize, usize::saturating_add);
    if count > MAX_ASSOCIATION_CANDIDATES {
        return Err(count);
    }
    let mut cand: Vec<(f64, usize, usize)> = Vec::with_capacity(count);
    for (i, &ta) in a.iter().enumerate() {
        let (lo, hi) = window(ta);
        for k in lo..hi {
            let d = (ta - times[k]).abs();
            if d < max_difference {
                cand.push((d, i, bs[k]));
            }
        }
    }
    cand.sort_by(|x, y| x.0.total_cmp(&y.0).then(x.1.cmp(&y.1)).then(x.2.cmp(&y.2)));
    let (mut used_a, mut used_b) = (vec![false; a.len()], vec![false; b.len()]);
    let mut out = Vec::new();
    for (_, i, j) in cand {
        if !used_a[i] && !used_b[j] {
            used_a[i] = true;
            used_b[j] = true;
            out.push((i, j));
        }
    }
    out.sort_by(|x, y| a[x.0].total_cmp(&a[y.0]).then(x.0.cmp(&y.0)));
    Ok(out)
}

/// Whether `name` matches the glob `pat` (`*` any run, `?` one character).
fn glob_match(pat: &[char], name: &[char]) -> bool {
    let (mut p, mut n) = (0, 0);
    let (mut star, mut mark) = (None, 0);
    while n < name.len() {
        if p < pat.len() && (pat[p] == '?' || pat[p] == name[n]) {
            p += 1;
            n += 1;
        } else if p < pat.len() && pat[p] == '*' {
            star = Some(p);
            mark = n;
            p += 1;
        } else if let Some(s) = star {
            p = s + 1;
            mark += 1;
            n = mark;
        } else {
            return false;
        }
    }
    pat[p..].iter().all(|c| *c == '*')
}

/// The files matching a glob whose wildcards are in the file name only, in
/// name order.
fn glob(pattern: &str) -> Result<Vec<PathBuf>, NodeError> {
    let path = Path::new(pattern);
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let d = dir.to_string_lossy();
    if d.contains('*') || d.contains('?') {
        return Err(bad(
            path,
            "wildcards are taken in the file name only, not in folders",
        ));
    }
    let pat: Vec<char> = path
        .file_name()
        .map(|f| f.to_string_lossy().chars().collect())
        .unwrap_or_default();
    let mut out = Vec::new();
    for e in fs::read_dir(&dir).map_err(|e| NodeError::read(&dir, e))? {
        let e = e.map_err(|e| NodeError::read(&dir, e))?;
        let name: Vec<char> = e.file_name().to_string_lossy().chars().collect();
        if glob_match(&pat, &name) && e.path().is_file() {
            out.push(e.path());
        }
    }
    out.sort();
    Ok(out)
}

/// Every frame of the sequence `p.source` names, in order.
pub fn frames(p: &LoadSequenceParams) -> Result<Vec<FramePair>, NodeError> {
    if p.source.is_empty() {
        return Err(NodeError::param(
            "source",
            "no sequence given; set it with --set <node>.source=FOLDER|LIST|GLOB",
        ));
    }
    let source = Path::new(&p.source);
    match kind_of(source) {
        SequenceKind::Tum => {
            let rgb = tum_list(&source.join("rgb.txt"), source)?;
            let depth = tum_list(&source.join("depth.txt"), source)?;
            let ta: Vec<f64> = rgb.iter().map(|r| r.0).collect();
            let tb: Vec<f64> = depth.iter().map(|d| d.0).collect();
            let pairs = associate(&ta, &tb, p.max_difference_s).map_err(|n| {
                bad(
                    source,
                    format!(
                        "{n} colour and depth frames lie within max_difference_s ({} s) of each \
                         other, more than the {MAX_ASSOCIATION_CANDIDATES} the association weighs \
                         (repeated timestamps in rgb.txt or depth.txt, or too large a tolerance)",
                        p.max_difference_s
                    ),
                )
            })?;
            Ok(pairs
                .into_iter()
                .map(|(i, j)| FramePair {
                    color: rgb[i].1.clone(),
                    depth: depth[j].1.clone(),
                })
                .collect())
        }
        SequenceKind::List => {
            let dir = source.parent().unwrap_or(Path::new(""));
            let mut out = Vec::new();
            for (n, line) in read_text(source)?.lines().enumerate() {
                let line = line.trim();
                if line.is_empty() || line.starts_with('#') {
                    continue;
                }
                let cols: Vec<&str> = line.split_whitespace().collect();
                let stamp = |t: &str| t.parse::<f64>().is_ok_and(f64::is_finite);
                let (c, d) = match cols.as_slice() {
                    [c, d] => (c, d),
                    [t, c, u, d] if stamp(t) && stamp(u) => (c, d),
                    [_, _, _, _] => {
                        return Err(bad(
                            source,
                            format!(
                                "line {}: four columns must be `t color t depth` with numeric timestamps \
                                 (paths cannot hold spaces)",
                                n + 1
                            ),
                        ));
                    }
                    _ => {
                        return Err(bad(
                            source,
                            format!(
                                "line {}: expected `color depth` or `t color t depth`, found {} columns",
                                n + 1,
                                cols.len()
                            ),
                        ));
                    }
                };
                out.push(FramePair {
                    color: dir.join(c),
                    depth: dir.join(d),
                });
            }
            Ok(out)
        }
        SequenceKind::Glob => {
            if p.depth_glob.is_empty() {
                return Err(NodeError::param(
                    "depth_glob",
                    "a glob `source` needs the glob of its depth files",
                ));
            }
            let colors = glob(&p.source)?;
            let depths = glob(&p.depth_glob)?;
            if colors.len() != depths.len() {
                return Err(bad(
                    source,
                    format!(
                        "{} colour files but {} depth files match `{}`: they are paired in name order",
                        colors.len(),
                        depths.len(),
                        p.depth_glob
                    ),
                ));
            }
            Ok(colors
                .into_iter()
                .zip(depths)
                .map(|(color, depth)| FramePair { color, depth })
                .collect())
        }
    }
}

/// The pair of frame `p.frame`; an error names the sequence and its length.
pub fn frame(p: &LoadSequenceParams) -> Result<FramePair, NodeError> {
    let all = frames(p)?;
    let n = all.len();
    all.into_iter().nth(p.frame as usize).ok_or_else(|| {
        bad(
            Path::new(&p.source),
            format!(
                "frame {} asked for, but the sequence holds {n} (0..{n})",
                p.frame
            ),
        )
    })
}

/// The files a `LoadSequence` node reads, for its cache key: the frame's
/// pair. The index files are left out on purpose: a sequence that grows
/// (a capture still being written) keeps its earlier frames' keys, and a
/// frame the index maps to other files has other contents. When the frame
/// cannot be resolved, the index (so that fixing it changes the key).
pub fn files_read(p: &LoadSequenceParams) -> Vec<PathBuf> {
    match frame(p) {
        Ok(f) => vec![f.color, f.depth],
        Err(_) => index_files(p),
    }
}

/// The files that say which files a `LoadSequence` node reads: a TUM
/// folder's `rgb.txt` and `depth.txt`, a list file (a glob has none). Left
/// out of its cache key ([`files_read`]), guarded from the pipeline's
/// sinks all the same.
pub fn index_files(p: &LoadSequenceParams) -> Vec<PathBuf> {
    let source = PathBuf::from(&p.source);
    match kind_of(&source) {
        SequenceKind::Tum => vec![source.join("rgb.txt"), source.join("depth.txt")],
        SequenceKind::List => vec![source],
        SequenceKind::Glob => Vec::new(),
    }
}

depthgraph_graph::ports! {
    /// Outputs of `LoadSequence`.
    outputs struct LoadSequenceOut {
        /// linear RGB of the frame
        color: ColorImage,
        /// depth of the frame in metres, 0 where the sensor gave none
        depth: DepthMap,
    }
}

/// Reads frame `p.frame` of a sequence (the `LoadSequence` node's function).
pub fn load_frame(
    p: &LoadSequenceParams,
    lim: &Limits,
) -> Result<(ColorImage, DepthMap), NodeError> {
    let pair = frame(p)?;
    let scale = match (p.depth_scale, kind_of(Path::new(&p.source))) {
        (s, _) if s > 0.0 => s,
        (_, SequenceKind::Tum) => 5000.0,
        _ => 0.0,
    };
    let dp = LoadDepthParams {
        path: pair.depth.to_string_lossy().into_owned(),
        encoding: DepthEncoding::Depth,
        scale,
        ..Default::default()
    };
    let color = load_color_with(&pair.color, p.color_space, lim)?;
    let depth = load_depth_with(&pair.depth, &dp, lim)?;
    if color.dims() != depth.dims() {
        return Err(bad(
            &pair.depth,
            format!(
                "depth is {}x{} but its colour frame {} is {}x{}",
                depth.width(),
                depth.height(),
                pair.color.display(),
                color.width(),
                color.height()
            ),
        ));
    }
    Ok((color, depth))
}

pub(super) fn eval(
    ctx: &EvalCtx,
    _: NoInputs,
    p: &LoadSequenceParams,
) -> Result<Produced<LoadSequenceOut>, NodeError> {
    let (color, depth) = load_frame(p, &Limits::of(ctx))?;
    Ok(LoadSequenceOut { color, depth }.into())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn association_takes_the_closest_pairs_once() {
        // colour at 0, 1, 2; depth at 0.01, 0.99, 1.005, 5
        let a = [0.0, 1.0, 2.0];
        let b = [0.01, 0.99, 1.005, 5.0];
        assert_eq!(associate(&a, &b, 0.02), Ok(vec![(0, 0), (1, 2)]));
        // depth 1.005 is nearer to colour 1 than 0.99, so 0.99 stays unused;
        // a larger tolerance still pairs each frame once
        assert_eq!(associate(&a, &b, 2.0), Ok(vec![(0, 0), (1, 2), (2, 1)]));
        assert_eq!(associate(&a, &[], 1.0), Ok(vec![]));
        // a pair just inside the limit in floating point is paired, one at it is not
        let (ta, tb) = (1305031102.199999, 1305031102.179999);
        assert!((ta - tb) < 0.02);
        assert_eq!(associate(&[ta], &[tb], 0.02), Ok(vec![(0, 0)]));
        assert_eq!(associate(&[1.5], &[1.25], 0.25), Ok(vec![]));
        // 5000 repeated stamps a side: 25 M candidates, counted, not stored
        let same = vec![7.0; 5000];
        assert_eq!(associate(&same, &same, 0.02), Err(25_000_000));
    }

    #[test]
    fn tum_lists_read_as_associate_py_reads_them() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("rgb.txt");
        fs::write(&p, "# c\n1.0,rgb/a.png\n2.0\trgb/b.png\n3.0\n\n").unwrap();
        let l = tum_list(&p, dir.path()).unwrap();
        assert_eq!(l.len(), 2);
        assert_eq!(l[1].1, dir.path().join("rgb/b.png"));
        fs::write(&p, "x rgb/a.png\n").unwrap();
        assert!(
            tum_list(&p, dir.path())
                .unwrap_err()
                .to_string()
                .contains("line 1")
        );
    }

    #[test]
    fn globs_match_names() {
        let m = |p: &str, n: &str| {
            glob_match(
                &p.chars().collect::<Vec<_>>(),
                &n.chars().collect::<Vec<_>>(),
            )
        };
        assert!(m("*.png", "a.png"));
        assert!(m("rgb_??.png", "rgb_01.png"));
        assert!(!m("rgb_??.png", "rgb_1.png"));
        assert!(m("*", ""));
        assert!(m("a*b*c", "aXbYbc"));
        assert!(!m("*.png", "a.png.txt"));
    }

    fn write_pair(dir: &Path, name: &str, z_mm: u16) -> (String, String) {
        let c = format!("rgb/{name}.png");
        let d = format!("depth/{name}.png");
        fs::create_dir_all(dir.join("rgb")).unwrap();
        fs::create_dir_all(dir.join("depth")).unwrap();
        image::RgbImage::from_pixel(3, 2, image::Rgb([10, 20, 30]))
            .save(dir.join(&c))
            .unwrap();
        image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_pixel(3, 2, image::Luma([z_mm]))
            .save(dir.join(&d))
            .unwrap();
        (c, d)
    }

    /// A four-column list line is `t color t depth` only with numeric
    /// timestamps: paths with spaces are an error naming the line, not a
    /// silent pairing of their halves.
    #[test]
    fn a_list_line_of_paths_with_spaces_is_an_error() {
        let dir = tempfile::tempdir().unwrap();
        let list = dir.path().join("l.txt");
        fs::write(&list, "1.0 a.png 1.0 a_d.png\nmy color.png my depth.png\n").unwrap();
        let p = LoadSequenceParams {
            source: list.to_string_lossy().into_owned(),
            ..Default::default()
        };
        let e = frames(&p).unwrap_err().to_string();
        assert!(e.contains("line 2") && e.contains("timestamps"), "{e}");
        fs::write(&list, "1.0 a.png 1.0 a_d.png\n").unwrap();
        let f = frames(&p).unwrap();
        assert_eq!(f.len(), 1);
        assert_eq!(f[0].color, dir.path().join("a.png"));
        assert_eq!(f[0].depth, dir.path().join("a_d.png"));
    }

    #[test]
    fn a_tum_folder_list_file_and_glob_give_the_same_frames() {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        let mut rgb = String::from("# color\n");
        let mut depth = String::from("# depth\n");
        let mut list = String::new();
        for (k, z) in [5000u16, 10000, 15000].into_iter().enumerate() {
            let (c, dd) = write_pair(d, &format!("{k}"), z);
            rgb += &format!("{}.000 {c}\n", 100 + k);
            depth += &format!("{}.004 {dd}\n", 100 + k);
            list += &format!("{c} {dd}\n");
        }
        fs::write(d.join("rgb.txt"), rgb).unwrap();
        fs::write(d.join("depth.txt"), depth).unwrap();
        fs::write(d.join("list.txt"), list).unwrap();
        let tum = LoadSequenceParams {
            source: d.to_string_lossy().into_owned(),
            frame: 2,
            ..Default::default()
        };
        assert_eq!(frames(&tum).unwrap().len(), 3);
        let (c, z) = load_frame(&tum, &Limits::default()).unwrap();
        assert_eq!(c.dims(), (3, 2));
        // TUM's 5000 units per metre
        assert!((*z.get(0, 0) - 3.0).abs() < 1e-6);
        let list = LoadSequenceParams {
            source: d.join("list.txt").to_string_lossy().into_owned(),
            frame: 2,
            depth_scale: 5000.0,
            ..Default::default()
        };
        assert_eq!(frames(&list).unwrap(), frames(&tum).unwrap());
        let globbed = LoadSequenceParams {
            source: d.join("rgb/*.png").to_string_lossy().into_owned(),
            depth_glob: d.join("depth/*.png").to_string_lossy().into_owned(),
            ..Default::default()
        };
        assert_eq!(frames(&globbed).unwrap(), frames(&tum).unwrap());
        // too tight a tolerance associates nothing; a frame past the end names the length
        let tight = LoadSequenceParams {
            max_difference_s: 0.001,
            ..tum.clone()
        };
        assert!(frames(&tight).unwrap().is_empty());
        let past = LoadSequenceParams { frame: 3, ..tum };
        let e = load_frame(&past, &Limits::default())
            .unwrap_err()
            .to_string();
        assert!(e.contains("frame 3") && e.contains("holds 3"), "{e}");
    }

    #[test]
    fn malformed_sequences_are_errors_naming_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let list = dir.path().join("l.txt");
        fs::write(&list, "a.png b.png c.png\n").unwrap();
        let p = LoadSequenceParams {
            source: list.to_string_lossy().into_owned(),
            ..Default::default()
        };
        let e = frames(&p).unwrap_err().to_string();
        assert!(e.contains("l.txt") && e.contains("line 1"), "{e}");
        let g = LoadSequenceParams {
            source: dir.path().join("*.png").to_string_lossy().into_owned(),
            ..Default::default()
        };
        assert!(frames(&g).unwrap_err().to_string().contains("depth_glob"));
        let missing = LoadSequenceParams {
            source: dir.path().join("nope.txt").to_string_lossy().into_owned(),
            ..Default::default()
        };
        assert_eq!(
            frames(&missing).unwrap_err().kind(),
            depthgraph_graph::error::FailureKind::Data
        );
    }
}
