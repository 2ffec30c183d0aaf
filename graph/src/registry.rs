//! The registry of node kinds: name -> implementation.

use std::collections::BTreeMap;
use std::sync::Arc;

use crate::codec::Decoders;
use crate::node::Node;
use crate::value::ExtensionDecoder;

/// Node kinds by name. A kind may have several backends ("cpu", "wgpu") with
/// identical schemas; [`Registry::get`] returns the preferred one available.
#[derive(Clone, Default)]
pub struct Registry {
    kinds: BTreeMap<&'static str, Vec<Arc<dyn Node>>>,
    /// Backend names in order of preference, e.g. `["wgpu", "cpu"]`.
    preference: Vec<&'static str>,
    /// Decoders of extension values, for the disk cache.
    decoders: Arc<Decoders>,
}

/// Registering a kind twice, or a backend whose schema differs.
#[derive(Debug, thiserror::Error)]
pub enum RegistryError {
    /// [`Registry::register`] was given a kind that is already registered.
    #[error("node kind `{0}` is registered twice")]
    Duplicate(&'static str),
    /// [`Registry::register_backend`] was given a backend whose schema
    /// differs from the kind's first one.
    #[error(
        "backend `{backend}` of `{kind}` has a schema that differs from the first registered one"
    )]
    SchemaMismatch {
        /// The node kind.
        kind: &'static str,
        /// The new backend's name.
        backend: &'static str,
    },
    /// A second backend was added for a kind that has no first one.
    #[error("node kind `{0}` has no CPU implementation to add a backend to")]
    Missing(&'static str),
}

impl Registry {
    /// An empty registry that prefers the "cpu" backend.
    pub fn new() -> Self {
        Self {
            kinds: BTreeMap::new(),
            preference: vec!["cpu"],
            decoders: Arc::default(),
        }
    }

    /// Adds a node kind; fails when the name is taken.
    pub fn register(&mut self, node: impl Node + 'static) -> Result<(), RegistryError> {
        let kind = node.schema().kind;
        if self.kinds.contains_key(kind) {
            return Err(RegistryError::Duplicate(kind));
        }
        self.kinds.insert(kind, vec![Arc::new(node)]);
        Ok(())
    }

    /// Adds another backend of an existing kind. Its schema (version, ports,
    /// parameters) must equal the first one's, so cache keys agree.
    pub fn register_backend(&mut self, node: impl Node + 'static) -> Result<(), RegistryError> {
        let schema = node.schema();
        let kind = schema.kind;
        let backend = node.backend();
        let Some(list) = self.kinds.get_mut(kind) else {
            self.kinds.insert(kind, vec![Arc::new(node)]);
            return Ok(());
        };
        let first = list[0].schema();
        if first.version != schema.version
            || first.inputs != schema.inputs
            || first.outputs != schema.outputs
            || first.params != schema.params
        {
            return Err(RegistryError::SchemaMismatch { kind, backend });
        }
        list.push(Arc::new(node));
        Ok(())
    }

    /// Declares an extension value kind ([`Extension`](crate::value::Extension))
    /// and how the disk cache reads it back.
    pub fn register_value(&mut self, type_name: &'static str, decoder: ExtensionDecoder) {
        Arc::make_mut(&mut self.decoders).insert(type_name, decoder);
    }

    /// The decoders of extension values.
    pub fn decoders(&self) -> Arc<Decoders> {
        self.decoders.clone()
    }

    /// Sets the preferred backends, most preferred first; "cpu" is always the fallback.
    pub fn prefer_backends(&mut self, order: &[&'static str]) {
        self.preference = order.to_vec();
        if !self.preference.contains(&"cpu") {
            self.preference.push("cpu");
        }
    }

    /// The implementation of `kind` on the most preferred available backend.
    pub fn get(&self, kind: &str) -> Option<Arc<dyn Node>> {
        let list = self.kinds.get(kind)?;
        for want in &self.preference {
            if let Some(n) = list.iter().find(|n| n.backend() == *want) {
                return Some(n.clone());
            }
        }
        list.first().cloned()
    }

    /// All kind names, sorted.
    pub fn kinds(&self) -> impl Iterator<Item = &'static str> + '_ {
        self.kinds.keys().copied()
    }

    /// The registered kind closest to `name` (case-insensitive edit distance),
    /// when it is close enough to be a plausible typo.
    pub fn suggest(&self, name: &str) -> Option<&'static str> {
        closest(name, self.kinds())
    }
}

/// The candidate closest to `name` by edit distance, when within a third of
/// its length (at least 2 edits); case differences count as half an edit.
pub fn closest<'a>(name: &str, candidates: impl IntoIterator<Item = &'a str>) -> Option<&'a str> {
    let lower = name.to_lowercase();
    let mut best: Option<(usize, &'a str)> = None;
    for c in candidates {
        let d = 2 * edit_distance(&lower, &c.to_lowercase()) + usize::from(c != name);
        if best.is_none_or(|(bd, _)| d < bd) {
            best = Some((d, c));
        }
    }
    let limit = 2 * (name.chars().count() / 3).max(2) + 1;
    best.filter(|(d, _)| *d <= limit).map(|(_, c)| c)
}

/// Levenshtein distance over chars.
pub fn edit_distance(a: &str, b: &str) -> usize {
    let b: Vec<char> = b.chars().collect();
    let mut prev: Vec<usize> = (0..=b.len()).collect();
    let mut cur = vec![0; b.len() + 1];
    for (i, ca) in a.chars().enumerate() {
        cur[0] = i + 1;
        for (j, cb) in b.iter().enumerate() {
            let sub = prev[j] + usize::from(ca != *cb);
            cur[j + 1] = sub.min(prev[j + 1] + 1).min(cur[j] + 1);
        }
        std::mem::swap(&mut prev, &mut cur);
    }
    prev[b.len()]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn distance_and_suggestion() {
        assert_eq!(edit_distance("kitten", "sitting"), 3);
        let names = ["PullPush", "DualPullPush", "SaveColor"];
        assert_eq!(closest("PulPush", names), Some("PullPush"));
        assert_eq!(closest("pullpush", names), Some("PullPush"));
        assert_eq!(closest("Completely", names), None);
    }
}
