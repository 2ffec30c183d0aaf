//! Accuracy against time: run a pipeline once per value of one parameter,
//! time the work that the parameter affects, and measure the error of an
//! output against a reference setting or a ground-truth port.

use std::fmt::Write as _;
use std::path::Path;
use std::time::Instant;

use depthgraph_graph::document::split_ref;
use depthgraph_graph::pipeline::OutputRef;
use depthgraph_graph::prelude::*;
use serde::Serialize;

use crate::metrics::{Measurement, Metric, MetricError, compare};

/// What to sweep and how to judge it.
#[derive(Debug, Clone)]
pub struct SweepSpec {
    /// `node.param`.
    pub param: String,
    /// Values, each in the syntax `--set` accepts.
    pub values: Vec<String>,
    /// `node.param=value` whose output is the reference (e.g. many samples).
    pub reference: Option<String>,
    /// A port holding ground truth (e.g. `scene.depth`), compared instead of a reference run.
    pub truth: Option<String>,
    /// The output judged, `node.port`.
    pub output: String,
    pub metric: Metric,
    /// Timed repeats per value (the median is reported).
    pub repeats: usize,
    /// Files the sweep writes itself (its CSV and plot): refused, before
    /// any value runs, where the pipeline at some value reads one.
    pub writes: Vec<std::path::PathBuf>,
}

/// One row of the result.
#[derive(Debug, Clone, Serialize)]
pub struct SweepRow {
    pub value: String,
    /// Median wall time of the nodes the parameter affects (upstream cached), ms.
    pub ms_median: f64,
    pub ms_min: f64,
    pub ms_max: f64,
    pub error: Option<Measurement>,
    /// Why there is no error value, when there is none.
    pub note: Option<String>,
}

/// Failures of a sweep.
#[derive(Debug, thiserror::Error)]
pub enum SweepError {
    #[error("{0}")]
    Check(CheckErrors),
    #[error(transparent)]
    Run(#[from] RunError),
    #[error("`{0}` is not `node.param` / `node.port`")]
    BadRef(String),
    #[error("the run produced no value for `{0}`")]
    NoValue(String),
    #[error("comparing `{output}`: {error}")]
    Metric { output: String, error: MetricError },
    #[error("give --reference or --truth to measure an error against")]
    NoReference,
    #[error("{0}: refusing to write over a file this pipeline reads")]
    WouldOverwrite(std::path::PathBuf),
}

/// The values of `--param node.p=v1,v2,...`: split at the commas outside
/// brackets and quotes, so tuple and list values (`(0.1, 0.2, 0.3)`,
/// `[1.0, 2.0]`, `"a,b"`) are one value each; each trimmed.
pub fn split_values(text: &str) -> Vec<String> {
    let mut out = Vec::new();
    let (mut depth, mut quoted, mut escaped) = (0i32, false, false);
    let mut cur = String::new();
    for c in text.chars() {
        if quoted {
            quoted = escaped || c != '"';
            escaped = !escaped && c == '\\';
        } else {
            match c {
                '"' => quoted = true,
                '(' | '[' | '{' => depth += 1,
                ')' | ']' | '}' => depth -= 1,
                ',' if depth <= 0 => {
                    out.push(cur.trim().to_string());
                    cur.clear();
                    continue;
                }
                _ => {}
            }
        }
        cur.push(c);
    }
    out.push(cur.trim().to_string());
    out
}

fn with_set(
    doc: &Document,
    sets: &[String],
    reg: &Registry,
    want: &[&str],
) -> Result<Pipeline, SweepError> {
    let mut d = doc.clone();
    for s in sets {
        d.apply_set(s)
            .map_err(|e| SweepError::Check(CheckErrors(vec![e])))?;
    }
    let mut p = Pipeline::check(&d, reg).map_err(|e| SweepError::Check(CheckErrors(e)))?;
    // Only the judged ports are requested: no file is written by a sweep.
    p.outputs = want
        .iter()
        .map(|w| {
            let (n, port) = split_ref(w).ok_or_else(|| SweepError::BadRef(w.to_string()))?;
            let node = p
                .index_of(n)
                .ok_or_else(|| SweepError::BadRef(w.to_string()))?;
            // the port too, before anything runs (a typo ran the whole
            // pipeline, then failed as an internal error)
            if !p.nodes[node]
                .node
                .schema()
                .outputs
                .iter()
                .any(|o| o.name == port)
            {
                return Err(SweepError::BadRef(w.to_string()));
            }
            Ok(OutputRef {
                node,
                port: Some(port.to_string()),
            })
        })
        .collect::<Result<_, SweepError>>()?;
    Ok(p)
}

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n == 0 {
        return f64::NAN;
    }
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

/// Runs the sweep. `progress` is called after each value.
pub fn run_sweep(
    engine: &Engine,
    doc: &Document,
    reg: &Registry,
    spec: &SweepSpec,
    base: &RunOptions,
    mut progress: impl FnMut(&SweepRow),
) -> Result<Vec<SweepRow>, SweepError> {
    let (node_name, _) =
        split_ref(&spec.param).ok_or_else(|| SweepError::BadRef(spec.param.clone()))?;
    if spec.reference.is_none() && spec.truth.is_none() {
        return Err(SweepError::NoReference);
    }
    let mut want = vec![spec.output.as_str()];
    if let Some(t) = &spec.truth {
        want.push(t);
    }
    // every value checked before the first runs (a bad last value threw
    // away the rows computed before it)
    let pipelines: Vec<Pipeline> = spec
        .values
        .iter()
        .map(|v| with_set(doc, &[format!("{}={}", spec.param, v)], reg, &want))
        .collect::<Result<_, _>>()?;
    // the files the sweep writes, against those each value reads (a swept
    // path too)
    let canon = depthgraph_graph::node::canonical_for_compare;
    for w in &spec.writes {
        let target = canon(w);
        if pipelines
            .iter()
            .flat_map(|p| p.input_files())
            .any(|f| canon(&f) == target)
        {
            return Err(SweepError::WouldOverwrite(w.clone()));
        }
    }
    let reference_value = match &spec.reference {
        Some(r) if spec.truth.is_none() => {
            let p = with_set(doc, std::slice::from_ref(r), reg, &[&spec.output])?;
            let res = engine.run(&p, base)?;
            Some(
                res.outputs
                    .get(&spec.output)
                    .cloned()
                    .ok_or_else(|| SweepError::NoValue(spec.output.clone()))?,
            )
        }
        _ => None,
    };
    let mut rows = Vec::new();
    for (v, p) in spec.values.iter().zip(&pipelines) {
        let swept = p
            .index_of(node_name)
            .ok_or_else(|| SweepError::BadRef(spec.param.clone()))?;
        // Warm-up: computes (or fetches) everything once, so upstream work is cached.
        let first = engine.run(p, base)?;
        let mut opts = base.clone();
        opts.force = p.downstream_of(swept);
        let mut times = Vec::new();
        let mut last = first;
        for _ in 0..spec.repeats.max(1) {
            let t = Instant::now();
            last = engine.run(p, &opts)?;
            times.push(t.elapsed().as_secs_f64() * 1e3);
        }
        let result = last
            .outputs
            .get(&spec.output)
            .ok_or_else(|| SweepError::NoValue(spec.output.clone()))?;
        let reference = match (&spec.truth, &reference_value) {
            (Some(t), _) => last
                .outputs
                .get(t)
                .ok_or_else(|| SweepError::NoValue(t.clone()))?,
            (None, Some(r)) => r,
            (None, None) => return Err(SweepError::NoReference),
        };
        let (error, note) = match compare(result, reference, spec.metric) {
            Ok(m) => (Some(m), None),
            Err(MetricError::Empty) => (None, Some("no valid reference pixel".to_string())),
            Err(e) => {
                return Err(SweepError::Metric {
                    output: spec.output.clone(),
                    error: e,
                });
            }
        };
        let ms_min = times.iter().copied().fold(f64::INFINITY, f64::min);
        let ms_max = times.iter().copied().fold(0.0, f64::max);
        let row = SweepRow {
            value: v.clone(),
            ms_median: median(&mut times),
            ms_min,
            ms_max,
            error,
            note,
        };
        progress(&row);
        rows.push(row);
    }
    Ok(rows)
}

/// The rows as CSV: `param,value,ms_median,ms_min,ms_max,metric,error,count,missing`.
pub fn to_csv(param: &str, metric: Metric, rows: &[SweepRow]) -> String {
    let mut s = String::from("param,value,ms_median,ms_min,ms_max,metric,error,count,missing\n");
    let m = metric.name();
    for r in rows {
        let (e, c, miss) = match r.error {
            Some(e) => (
                format!("{}", e.value),
                e.count.to_string(),
                e.missing.to_string(),
            ),
            None => (String::new(), String::new(), String::new()),
        };
        let value = if r.value.contains(',') {
            format!("\"{}\"", r.value.replace('"', "\"\""))
        } else {
            r.value.clone()
        };
        let _ = writeln!(
            s,
            "{param},{value},{:.4},{:.4},{:.4},{m},{e},{c},{miss}",
            r.ms_median, r.ms_min, r.ms_max
        );
    }
    s
}

/// Plots error against time (SVG), one labelled point per value.
pub fn plot_svg(path: &Path, param: &str, metric: Metric, rows: &[SweepRow]) -> Result<(), String> {
    use plotters::prelude::*;
    let pts: Vec<(f64, f64, &str)> = rows
        .iter()
        .filter_map(|r| {
            r.error
                .filter(|e| e.value.is_finite())
                .map(|e| (r.ms_median.max(1e-3), e.value, r.value.as_str()))
        })
        .collect();
    if pts.is_empty() {
        return Err("no finite error to plot".into());
    }
    let (xmin, xmax) = pts.iter().fold((f64::INFINITY, 0.0f64), |(a, b), p| {
        (a.min(p.0), b.max(p.0))
    });
    let (ymin, ymax) = pts
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), p| {
            (a.min(p.1), b.max(p.1))
        });
    let ypad = ((ymax - ymin).abs() * 0.1).max(1e-9);
    let root = SVGBackend::new(path, (800, 500)).into_drawing_area();
    let err = |e: DrawingAreaErrorKind<std::io::Error>| e.to_string();
    root.fill(&WHITE).map_err(err)?;
    let metric_name = metric.name().to_uppercase();
    let mut chart = ChartBuilder::on(&root)
        .caption(
            format!("{metric_name} vs time: {param}"),
            ("sans-serif", 20),
        )
        .margin(15)
        .x_label_area_size(40)
        .y_label_area_size(70)
        .build_cartesian_2d(
            (xmin * 0.8..xmax * 1.25).log_scale(),
            (ymin - ypad)..(ymax + ypad),
        )
        .map_err(err)?;
    chart
        .configure_mesh()
        .x_desc("time (ms, log scale, upstream cached)")
        .y_desc(metric_name)
        .draw()
        .map_err(err)?;
    chart
        .draw_series(LineSeries::new(pts.iter().map(|p| (p.0, p.1)), &BLUE))
        .map_err(err)?;
    chart
        .draw_series(pts.iter().map(|p| {
            EmptyElement::at((p.0, p.1))
                + Circle::new((0, 0), 4, BLUE.filled())
                + Text::new(p.2.to_string(), (6, -14), ("sans-serif", 13))
        }))
        .map_err(err)?;
    root.present().map_err(err)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Tuple, list and quoted values are one value each (a plain split at
    /// every comma made `(0.1, 0.2, 0.3)` three broken ones).
    #[test]
    fn values_split_at_top_level_commas_only() {
        assert_eq!(split_values("0, 0.5 ,1"), ["0", "0.5", "1"]);
        assert_eq!(
            split_values("(0.1,0.1,0.1),(0.2, 0.2, 0.2)"),
            ["(0.1,0.1,0.1)", "(0.2, 0.2, 0.2)"]
        );
        assert_eq!(
            split_values("[(1.0, 2.0), (3.0, 4.0)],[]"),
            ["[(1.0, 2.0), (3.0, 4.0)]", "[]"]
        );
        assert_eq!(
            split_values(r#""a,b","c\",d",e"#),
            [r#""a,b""#, r#""c\",d""#, "e"]
        );
    }

    /// The CSV names the metric as `--metric` spells it (`display-psnr`,
    /// not the enum's `displaypsnr`).
    #[test]
    fn the_csv_names_the_metric_as_the_flag_does() {
        let row = SweepRow {
            value: "1".into(),
            ms_median: 1.0,
            ms_min: 1.0,
            ms_max: 1.0,
            error: None,
            note: None,
        };
        let csv = to_csv("a.b", Metric::DisplayPsnr, &[row]);
        assert!(
            csv.lines()
                .nth(1)
                .is_some_and(|l| l.contains(",display-psnr,")),
            "{csv}"
        );
    }

    #[test]
    fn median_of_even_and_odd() {
        assert_eq!(median(&mut [3.0, 1.0, 2.0]), 2.0);
        assert_eq!(median(&mut [4.0, 1.0, 2.0, 3.0]), 2.5);
        assert!(median(&mut []).is_nan());
    }
}
