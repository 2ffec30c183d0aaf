//! A checked pipeline: every kind known, every parameter converted and in
//! range, every wire type-correct, no cycle. Built from a [`Document`] and a
//! [`Registry`] by [`Pipeline::check`], which reports *all* problems at once,
//! each with its location.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::Arc;

use petgraph::algo::{tarjan_scc, toposort};
use petgraph::graph::{DiGraph, NodeIndex};

use crate::codec::Decoders;
use crate::document::{Document, split_ref};
use crate::error::{CheckError, Location};
use crate::node::Node;
use crate::params::{ParamKind, ParamMap, ParamValue};
use crate::registry::{Registry, closest};
use crate::ron_text::RonValue;

/// Where an input comes from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Source {
    /// Index of the producing node in [`Pipeline::nodes`].
    pub node: usize,
    /// Output port of that node.
    pub port: String,
}

/// One node of a checked pipeline.
#[derive(Clone)]
pub struct PipelineNode {
    /// The node's name in the document.
    pub name: String,
    /// Its kind.
    pub kind: String,
    /// The implementation the registry chose (its preferred backend).
    pub node: Arc<dyn Node>,
    /// Every declared parameter, defaults filled in.
    pub params: ParamMap,
    /// Input port -> source.
    pub inputs: BTreeMap<String, Source>,
}

/// A requested output: all ports of a node, or one.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct OutputRef {
    /// Index of the node in [`Pipeline::nodes`].
    pub node: usize,
    /// One output port, or `None` for all of them.
    pub port: Option<String>,
}

/// A pipeline ready to run.
#[derive(Clone)]
pub struct Pipeline {
    /// Name of the document, for messages (usually its path).
    pub file: String,
    /// The nodes, in document order.
    pub nodes: Vec<PipelineNode>,
    /// Edges point from producer to consumer; weights are node indices.
    pub graph: DiGraph<usize, ()>,
    /// Node indices in a topological order.
    pub order: Vec<usize>,
    /// Requested outputs; when the document names none, every sink, or if
    /// there is none every node nothing consumes.
    pub outputs: Vec<OutputRef>,
    /// How the disk cache reads extension values back (from the registry).
    pub decoders: Arc<Decoders>,
}

impl Pipeline {
    /// Checks `doc` against `registry`.
    pub fn check(doc: &Document, registry: &Registry) -> Result<Pipeline, Vec<CheckError>> {
        let mut errors = Vec::new();
        let file = doc.file.as_str();
        let names: Vec<&str> = doc.nodes.iter().map(|n| n.name.value.as_str()).collect();
        let index: BTreeMap<&str, usize> = names.iter().enumerate().map(|(i, n)| (*n, i)).collect();

        // Kinds and parameters.
        let mut resolved: Vec<Option<Arc<dyn Node>>> = Vec::new();
        let mut params_of: Vec<ParamMap> = Vec::new();
        for decl in &doc.nodes {
            let node = registry.get(&decl.kind.value);
            if node.is_none() {
                errors.push(CheckError::UnknownKind {
                    loc: Location::new(file, decl.kind.pos),
                    node: decl.name.value.clone(),
                    kind: decl.kind.value.clone(),
                    suggestion: registry.suggest(&decl.kind.value).map(str::to_string),
                });
            }
            let mut params = ParamMap::new();
            if let Some(node) = &node {
                let schema = node.schema();
                params.extend(schema.default_params());
                for (key, val) in &decl.params {
                    let pfile = decl
                        .param_files
                        .get(&key.value)
                        .map(String::as_str)
                        .unwrap_or(file);
                    let Some(spec) = schema.param(&key.value) else {
                        errors.push(CheckError::UnknownParam {
                            loc: Location::new(pfile, key.pos),
                            node: decl.name.value.clone(),
                            kind: decl.kind.value.clone(),
                            param: key.value.clone(),
                            suggestion: closest(&key.value, schema.params.iter().map(|p| p.name))
                                .map(str::to_string),
                        });
                        continue;
                    };
                    let bad = |message: String| CheckError::BadParam {
                        loc: Location::new(pfile, val.pos),
                        node: decl.name.value.clone(),
                        param: key.value.clone(),
                        message,
                    };
                    match convert(&spec.kind, &val.value) {
                        Err(m) => errors.push(bad(m)),
                        Ok(v) => match spec.kind.validate(&v) {
                            Err(e) => errors.push(bad(e.to_string())),
                            Ok(()) => {
                                params.insert(key.value.clone(), v);
                            }
                        },
                    }
                }
            }
            resolved.push(node);
            params_of.push(params);
        }

        // Wires.
        let mut inputs_of: Vec<BTreeMap<String, Source>> = vec![BTreeMap::new(); doc.nodes.len()];
        let mut graph = DiGraph::<usize, ()>::new();
        let gi: Vec<NodeIndex> = (0..doc.nodes.len()).map(|i| graph.add_node(i)).collect();
        for (i, decl) in doc.nodes.iter().enumerate() {
            let schema = resolved[i].as_ref().map(|n| n.schema());
            for (port, src) in &decl.inputs {
                let in_spec = match schema {
                    Some(s) => match s.input(&port.value) {
                        Some(p) => Some(p),
                        None => {
                            errors.push(CheckError::UnknownPort {
                                loc: Location::new(file, port.pos),
                                node: decl.name.value.clone(),
                                kind: decl.kind.value.clone(),
                                direction: "input",
                                port: port.value.clone(),
                                suggestion: closest(&port.value, s.inputs.iter().map(|p| p.name))
                                    .map(str::to_string),
                                available: s.inputs.iter().map(|p| p.name.to_string()).collect(),
                            });
                            continue;
                        }
                    },
                    None => None,
                };
                let loc = Location::new(file, src.pos);
                let Some((src_node, src_port)) = split_ref(&src.value) else {
                    errors.push(CheckError::Format {
                        loc,
                        message: format!(
                            "node `{}` input `{}`: expected \"node.port\", found \"{}\"",
                            decl.name.value, port.value, src.value
                        ),
                    });
                    continue;
                };
                let Some(&j) = index.get(src_node) else {
                    errors.push(CheckError::UnknownNode {
                        loc,
                        name: src_node.to_string(),
                        suggestion: closest(src_node, names.iter().copied()).map(str::to_string),
                    });
                    continue;
                };
                if let Some(src_schema) = resolved[j].as_ref().map(|n| n.schema()) {
                    match src_schema.output(src_port) {
                        None => {
                            errors.push(CheckError::UnknownPort {
                                loc,
                                node: src_node.to_string(),
                                kind: src_schema.kind.to_string(),
                                direction: "output",
                                port: src_port.to_string(),
                                suggestion: closest(
                                    src_port,
                                    src_schema.outputs.iter().map(|p| p.name),
                                )
                                .map(str::to_string),
                                available: src_schema
                                    .outputs
                                    .iter()
                                    .map(|p| p.name.to_string())
                                    .collect(),
                            });
                            continue;
                        }
                        Some(out) => {
                            if let Some(inp) = in_spec
                                && !out.ty.connects_to(inp.ty)
                            {
                                errors.push(CheckError::TypeMismatch {
                                    loc,
                                    node: decl.name.value.clone(),
                                    port: port.value.clone(),
                                    expected: inp.ty,
                                    found: out.ty,
                                    source_ref: src.value.clone(),
                                });
                                continue;
                            }
                        }
                    }
                }
                inputs_of[i].insert(
                    port.value.clone(),
                    Source {
                        node: j,
                        port: src_port.to_string(),
                    },
                );
                graph.update_edge(gi[j], gi[i], ());
            }
            if let Some(s) = schema {
                for p in s.inputs.iter().filter(|p| !p.optional) {
                    if !decl.inputs.iter().any(|(k, _)| k.value == p.name) {
                        errors.push(CheckError::MissingInput {
                            loc: Location::new(file, decl.name.pos),
                            node: decl.name.value.clone(),
                            kind: decl.kind.value.clone(),
                            port: p.name.to_string(),
                            ty: p.ty,
                        });
                    }
                }
            }
        }

        // Cycles: every strongly connected component with more than one node,
        // or a node wired to itself.
        for scc in tarjan_scc(&graph) {
            let self_loop = scc.len() == 1 && graph.contains_edge(scc[0], scc[0]);
            if scc.len() > 1 || self_loop {
                let mut members: Vec<usize> = scc.iter().map(|n| graph[*n]).collect();
                members.sort();
                let path = cycle_path(&members, &inputs_of, &names);
                let first = members[0];
                errors.push(CheckError::Cycle {
                    loc: Location::new(file, doc.nodes[first].name.pos),
                    path,
                });
            }
        }

        // Requested outputs.
        let mut outputs = Vec::new();
        for o in &doc.outputs {
            let loc = Location::new(file, o.pos);
            // "node" or "node.port" (a node name itself has no dot)
            let (node_name, port) = match split_ref(&o.value) {
                Some((n, p)) if !index.contains_key(o.value.as_str()) => (n, Some(p)),
                _ => (o.value.as_str(), None),
            };
            let Some(&i) = index.get(node_name) else {
                errors.push(CheckError::UnknownNode {
                    loc,
                    name: node_name.to_string(),
                    suggestion: closest(node_name, names.iter().copied()).map(str::to_string),
                });
                continue;
            };
            if let (Some(p), Some(node)) = (port, &resolved[i]) {
                let s = node.schema();
                if s.output(p).is_none() {
                    errors.push(CheckError::UnknownPort {
                        loc,
                        node: node_name.to_string(),
                        kind: s.kind.to_string(),
                        direction: "output",
                        port: p.to_string(),
                        suggestion: closest(p, s.outputs.iter().map(|p| p.name))
                            .map(str::to_string),
                        available: s.outputs.iter().map(|p| p.name.to_string()).collect(),
                    });
                    continue;
                }
            }
            outputs.push(OutputRef {
                node: i,
                port: port.map(str::to_string),
            });
        }

        if !errors.is_empty() {
            return Err(errors);
        }
        let order: Vec<usize> = match toposort(&graph, None) {
            Ok(o) => o.into_iter().map(|n| graph[n]).collect(),
            Err(c) => {
                return Err(vec![CheckError::Cycle {
                    loc: Location::new(file, doc.nodes[graph[c.node_id()]].name.pos),
                    path: vec![names[graph[c.node_id()]].to_string()],
                }]);
            }
        };
        let nodes: Vec<PipelineNode> = doc
            .nodes
            .iter()
            .zip(resolved)
            .zip(params_of)
            .zip(inputs_of)
            .filter_map(|(((decl, node), params), inputs)| {
                Some(PipelineNode {
                    name: decl.name.value.clone(),
                    kind: decl.kind.value.clone(),
                    node: node?,
                    params,
                    inputs,
                })
            })
            .collect();
        if outputs.is_empty() {
            // Default: every sink, or every node nothing consumes.
            let sinks: Vec<usize> = (0..nodes.len())
                .filter(|i| nodes[*i].node.schema().sink)
                .collect();
            let leaves: Vec<usize> = (0..nodes.len())
                .filter(|i| graph.neighbors(gi[*i]).next().is_none())
                .collect();
            let chosen = if sinks.is_empty() { leaves } else { sinks };
            outputs = chosen
                .into_iter()
                .map(|node| OutputRef { node, port: None })
                .collect();
        }
        Ok(Pipeline {
            file: doc.file.clone(),
            nodes,
            graph,
            order,
            outputs,
            decoders: registry.decoders(),
        })
    }

    /// Index of the node called `name`.
    pub fn index_of(&self, name: &str) -> Option<usize> {
        self.nodes.iter().position(|n| n.name == name)
    }

    /// Every file the pipeline reads (from load nodes' parameters), and
    /// the files that say what it reads (a sequence's index): no sink may
    /// write over them ([`crate::node::Node::guarded_files`]).
    pub fn input_files(&self) -> Vec<PathBuf> {
        self.nodes
            .iter()
            .flat_map(|n| n.node.guarded_files(&n.params))
            .collect()
    }

    /// Indices of `start` and every node downstream of it.
    pub fn downstream_of(&self, start: usize) -> Vec<usize> {
        let mut seen = vec![false; self.nodes.len()];
        let mut stack = vec![start];
        while let Some(i) = stack.pop() {
            if std::mem::replace(&mut seen[i], true) {
                continue;
            }
            for n in self.graph.neighbors(NodeIndex::new(i)) {
                stack.push(self.graph[n]);
            }
        }
        (0..self.nodes.len()).filter(|i| seen[*i]).collect()
    }
}

/// A cycle through the first of `members` (a strongly connected
/// component, or one node wired to itself) along its wires, for the
/// message: the shortest, found breadth first from that node to the nodes
/// that consume it, and so on back to it (`a -> a` for a node wired to
/// itself). A greedy walk could circle inside the component and never
/// return to its start (`a -> b -> c -> b -> c`).
fn cycle_path(
    members: &[usize],
    inputs: &[BTreeMap<String, Source>],
    names: &[&str],
) -> Vec<String> {
    let start = members[0];
    // the members that take an input from `cur`, in index order
    let consumers = |cur: usize| {
        members
            .iter()
            .copied()
            .filter(move |m| inputs[*m].values().any(|s| s.node == cur))
    };
    let mut prev: BTreeMap<usize, usize> = BTreeMap::new();
    let mut queue = std::collections::VecDeque::from([start]);
    while let Some(cur) = queue.pop_front() {
        for m in consumers(cur) {
            if m == start {
                // back from `cur` to the start along the recorded steps
                let mut back = Vec::new();
                let mut at = cur;
                while at != start {
                    back.push(at);
                    at = prev[&at];
                }
                back.reverse();
                let mut path = vec![names[start].to_string()];
                path.extend(back.iter().map(|&i| names[i].to_string()));
                path.push(names[start].to_string());
                return path;
            }
            if let std::collections::btree_map::Entry::Vacant(e) = prev.entry(m) {
                e.insert(cur);
                queue.push_back(m);
            }
        }
    }
    // (a component always holds a cycle through each member; the members
    // as they are, should the wires say otherwise)
    members.iter().map(|&i| names[i].to_string()).collect()
}

/// Converts a written value to the parameter's kind, or says why not.
pub fn convert(kind: &ParamKind, v: &RonValue) -> Result<ParamValue, String> {
    let num = |v: &RonValue| match v {
        RonValue::Int(i) => Some(*i as f64),
        RonValue::Float(f) => Some(*f),
        _ => None,
    };
    let expected = || format!("expected {}, found {}", kind.type_name(), v.describe());
    match kind {
        ParamKind::Float { .. } => num(v).map(ParamValue::Float).ok_or_else(expected),
        ParamKind::Int { .. } => match v {
            RonValue::Int(i) => Ok(ParamValue::Int(*i)),
            RonValue::Float(f) => Err(format!("expected an integer, found the float {f}")),
            _ => Err(expected()),
        },
        ParamKind::Bool => match v {
            RonValue::Bool(b) => Ok(ParamValue::Bool(*b)),
            _ => Err(expected()),
        },
        ParamKind::Text | ParamKind::InputPath | ParamKind::OutputPath => match v {
            RonValue::Str(s) => Ok(ParamValue::Text(s.clone())),
            _ => Err(expected()),
        },
        ParamKind::Choice(_) => match v {
            RonValue::Str(s) | RonValue::Ident(s) => Ok(ParamValue::Text(s.clone())),
            _ => Err(expected()),
        },
        ParamKind::Points => match v {
            RonValue::List(items) => items
                .iter()
                .map(|it| match &it.value {
                    RonValue::Tuple { items: xy, .. } | RonValue::List(xy) if xy.len() == 2 => {
                        match (num(&xy[0].value), num(&xy[1].value)) {
                            (Some(x), Some(y)) => Ok([x, y]),
                            _ => Err(format!("point at {}: expected (x, y) numbers", it.pos)),
                        }
                    }
                    _ => Err(format!("point at {}: expected (x, y)", it.pos)),
                })
                .collect::<Result<Vec<_>, _>>()
                .map(ParamValue::Points),
            _ => Err(expected()),
        },
        ParamKind::Floats { .. } => match v {
            RonValue::List(items) => items
                .iter()
                .map(|it| {
                    num(&it.value).ok_or_else(|| format!("item at {}: expected a number", it.pos))
                })
                .collect::<Result<Vec<_>, _>>()
                .map(ParamValue::Floats),
            _ => Err(expected()),
        },
        ParamKind::Vec3 { .. } => match v {
            RonValue::Tuple { items, .. } | RonValue::List(items) if items.len() == 3 => {
                let xs: Option<Vec<f64>> = items.iter().map(|i| num(&i.value)).collect();
                xs.map(|x| ParamValue::Vec3([x[0], x[1], x[2]]))
                    .ok_or_else(|| "expected three numbers (x, y, z)".to_string())
            }
            _ => Err(expected()),
        },
    }
}

#[cfg(test)]
mod cycle_tests {
    use super::*;

    fn wires(edges: &[(usize, usize)], n: usize) -> Vec<BTreeMap<String, Source>> {
        let mut inputs = vec![BTreeMap::new(); n];
        for (k, &(from, to)) in edges.iter().enumerate() {
            inputs[to].insert(
                format!("in{k}"),
                Source {
                    node: from,
                    port: "out".into(),
                },
            );
        }
        inputs
    }

    /// The message's cycle returns to its start: through a component whose
    /// inner loop (b, c) a greedy walk kept circling, and for a node wired
    /// to itself.
    #[test]
    fn the_cycle_named_returns_to_its_start() {
        let names = ["a", "b", "c", "d"];
        let inputs = wires(&[(0, 1), (1, 2), (2, 1), (2, 3), (3, 0)], 4);
        assert_eq!(
            cycle_path(&[0, 1, 2, 3], &inputs, &names),
            ["a", "b", "c", "d", "a"]
        );
        let own = wires(&[(0, 0)], 1);
        assert_eq!(cycle_path(&[0], &own, &names), ["a", "a"]);
    }
}
