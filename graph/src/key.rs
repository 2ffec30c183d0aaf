//! Merkle cache keys.
//!
//! `key(node) = blake3(kind, version, canonical parameters, for each input
//! port in name order: port name, source output port, key(source))`.
//!
//! A node that reads files (a loader) has the files' contents mixed in as
//! well ([`with_file_contents`]): editing an input file, or a frame of a
//! sequence written anew, is a different result, never a stale cache hit.
//!
//! The key is known before evaluation, so a change downstream never re-runs
//! upstream work, and a change upstream changes exactly the keys of the
//! nodes that depend on it. Parameters are hashed in name order with floats
//! by bit pattern. The backend (CPU or GPU) is not part of the key: backends
//! of a kind must agree on their results.

use std::fmt;

use crate::params::ParamMap;

/// A 256-bit content key.
#[derive(Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct Key([u8; 32]);

impl Key {
    /// The key made of these 32 bytes.
    pub fn from_bytes(b: [u8; 32]) -> Self {
        Key(b)
    }
    /// The key's 32 bytes.
    pub fn as_bytes(&self) -> &[u8; 32] {
        &self.0
    }
    /// The key as 64 lowercase hex digits.
    pub fn to_hex(&self) -> String {
        self.0.iter().map(|b| format!("{b:02x}")).collect()
    }
}

impl fmt::Debug for Key {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "Key({})", &self.to_hex()[..12])
    }
}

/// Format tag mixed into every key; bump when the key recipe changes.
const RECIPE: &[u8] = b"depthgraph-key-v1";

/// Computes a node's key from its identity and its inputs' keys.
/// `inputs` are `(input port, source output port, source key)` in any order.
pub fn node_key(kind: &str, version: u32, params: &ParamMap, inputs: &[(&str, &str, Key)]) -> Key {
    let mut h = blake3::Hasher::new();
    h.update(RECIPE);
    h.update(&(kind.len() as u64).to_le_bytes());
    h.update(kind.as_bytes());
    h.update(&version.to_le_bytes());
    let mut buf = Vec::new();
    buf.extend_from_slice(&(params.len() as u64).to_le_bytes());
    for (name, value) in params {
        buf.extend_from_slice(&(name.len() as u64).to_le_bytes());
        buf.extend_from_slice(name.as_bytes());
        value.canonical_bytes(&mut buf);
    }
    h.update(&buf);
    let mut sorted: Vec<&(&str, &str, Key)> = inputs.iter().collect();
    sorted.sort_by(|a, b| a.0.cmp(b.0));
    h.update(&(sorted.len() as u64).to_le_bytes());
    for (port, src_port, key) in sorted {
        for s in [port, src_port] {
            h.update(&(s.len() as u64).to_le_bytes());
            h.update(s.as_bytes());
        }
        h.update(key.as_bytes());
    }
    Key(*h.finalize().as_bytes())
}

/// Key of a value a node derives from some of its inputs
/// ([`EvalCtx::derived`](crate::node::EvalCtx::derived)): the node's kind
/// and version, the value's name, the node's own key material for it
/// (`extra`, e.g. the parameters it depends on) and the keys of the inputs
/// it reads, so two runs that feed it the same upstream results share it.
pub fn derived_key(
    kind: &str,
    version: u32,
    name: &str,
    extra: &[u8],
    inputs: &[(&str, Option<Key>)],
) -> Key {
    let mut h = blake3::Hasher::new();
    h.update(RECIPE);
    h.update(b"derived");
    for s in [kind, name] {
        h.update(&(s.len() as u64).to_le_bytes());
        h.update(s.as_bytes());
    }
    h.update(&version.to_le_bytes());
    h.update(&(extra.len() as u64).to_le_bytes());
    h.update(extra);
    h.update(&(inputs.len() as u64).to_le_bytes());
    for (port, key) in inputs {
        h.update(&(port.len() as u64).to_le_bytes());
        h.update(port.as_bytes());
        match key {
            Some(k) => {
                h.update(&[1]);
                h.update(k.as_bytes());
            }
            None => {
                h.update(&[0]);
            }
        }
    }
    Key(*h.finalize().as_bytes())
}

/// `key` with the contents of the files a node reads mixed in, in the
/// order given: the blake3 digest of each file's bytes, or a marker for a
/// file that cannot be read or is not a regular file (the load then fails
/// with its own error, and a file that appears later gives another key).
pub fn with_file_contents(key: Key, files: &[std::path::PathBuf]) -> Key {
    if files.is_empty() {
        return key;
    }
    let mut h = blake3::Hasher::new();
    h.update(RECIPE);
    h.update(b"files");
    h.update(key.as_bytes());
    h.update(&(files.len() as u64).to_le_bytes());
    for f in files {
        // a regular file only: a FIFO or `/dev/zero` would never end (its
        // load fails with its own error)
        // (looked at before it is opened: opening a FIFO waits for a writer)
        let digest = std::fs::metadata(f).and_then(|m| {
            if !m.is_file() {
                return Err(std::io::Error::other("not a regular file"));
            }
            let file = std::fs::File::open(f)?;
            let mut d = blake3::Hasher::new();
            d.update_reader(file)?;
            Ok(d.finalize())
        });
        match digest {
            Ok(d) => {
                h.update(&[1]);
                h.update(d.as_bytes());
            }
            Err(_) => {
                h.update(&[0]);
            }
        }
    }
    Key(*h.finalize().as_bytes())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::params::ParamValue;

    #[test]
    fn key_depends_on_every_part() {
        let mut p = ParamMap::new();
        p.insert("a".into(), ParamValue::Float(1.0));
        let k0 = Key::from_bytes([0; 32]);
        let base = node_key("K", 1, &p, &[("in", "out", k0)]);
        assert_eq!(base, node_key("K", 1, &p, &[("in", "out", k0)]));
        assert_ne!(base, node_key("L", 1, &p, &[("in", "out", k0)]));
        assert_ne!(base, node_key("K", 2, &p, &[("in", "out", k0)]));
        assert_ne!(base, node_key("K", 1, &p, &[("in", "other", k0)]));
        assert_ne!(
            base,
            node_key("K", 1, &p, &[("in", "out", Key::from_bytes([1; 32]))])
        );
        let mut q = p.clone();
        q.insert(
            "a".into(),
            ParamValue::Float(f64::from_bits(1.0f64.to_bits() + 1)),
        );
        assert_ne!(base, node_key("K", 1, &q, &[("in", "out", k0)]));
    }

    #[test]
    fn derived_key_depends_on_every_part() {
        let a = Key::from_bytes([1; 32]);
        let base = derived_key("K", 1, "scene", b"p", &[("x", Some(a))]);
        assert_eq!(base, derived_key("K", 1, "scene", b"p", &[("x", Some(a))]));
        assert_ne!(base, derived_key("K", 2, "scene", b"p", &[("x", Some(a))]));
        assert_ne!(base, derived_key("K", 1, "other", b"p", &[("x", Some(a))]));
        assert_ne!(base, derived_key("K", 1, "scene", b"q", &[("x", Some(a))]));
        assert_ne!(base, derived_key("K", 1, "scene", b"p", &[("x", None)]));
        assert_ne!(base, derived_key("K", 1, "scene", b"p", &[("y", Some(a))]));
    }

    #[test]
    fn file_contents_change_the_key() {
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("a.bin");
        let k = Key::from_bytes([3; 32]);
        assert_eq!(with_file_contents(k, &[]), k);
        let missing = with_file_contents(k, std::slice::from_ref(&f));
        std::fs::write(&f, b"one").unwrap();
        let one = with_file_contents(k, std::slice::from_ref(&f));
        assert_eq!(one, with_file_contents(k, std::slice::from_ref(&f)));
        std::fs::write(&f, b"two").unwrap();
        let two = with_file_contents(k, std::slice::from_ref(&f));
        assert!(missing != one && one != two && missing != two);
        std::fs::write(&f, b"one").unwrap();
        assert_eq!(with_file_contents(k, &[f]), one);
    }

    #[test]
    fn input_order_does_not_matter() {
        let p = ParamMap::new();
        let a = Key::from_bytes([1; 32]);
        let b = Key::from_bytes([2; 32]);
        assert_eq!(
            node_key("K", 1, &p, &[("x", "o", a), ("y", "o", b)]),
            node_key("K", 1, &p, &[("y", "o", b), ("x", "o", a)])
        );
    }
}
