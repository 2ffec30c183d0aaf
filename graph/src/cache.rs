//! Result caches: a byte-budgeted in-memory LRU and a content-addressed,
//! bounded on-disk store. Both are keyed by the Merkle [`Key`] of a node.

use std::collections::{BTreeMap, HashMap};
use std::fs;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::SystemTime;

use crate::codec;
use crate::key::Key;
use crate::node::Outputs;

/// In-memory LRU holding at most `budget_bytes` of values.
pub struct MemoryCache {
    budget_bytes: usize,
    used: usize,
    tick: u64,
    entries: HashMap<Key, (Arc<Outputs>, usize, u64)>,
    by_age: BTreeMap<u64, Key>,
}

impl MemoryCache {
    /// An empty cache holding at most `budget_bytes`.
    pub fn new(budget_bytes: usize) -> Self {
        Self {
            budget_bytes,
            used: 0,
            tick: 0,
            entries: HashMap::new(),
            by_age: BTreeMap::new(),
        }
    }
    /// The budget in bytes.
    pub fn budget_bytes(&self) -> usize {
        self.budget_bytes
    }
    /// Bytes currently held.
    pub fn used_bytes(&self) -> usize {
        self.used
    }
    /// Number of results held.
    pub fn len(&self) -> usize {
        self.entries.len()
    }
    /// True when nothing is held.
    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }
    /// Looks up and marks as recently used.
    pub fn get(&mut self, key: &Key) -> Option<Arc<Outputs>> {
        self.tick += 1;
        let tick = self.tick;
        let (out, _, age) = self.entries.get_mut(key)?;
        self.by_age.remove(age);
        *age = tick;
        self.by_age.insert(tick, *key);
        Some(out.clone())
    }
    /// Inserts; a result larger than the whole budget is not kept.
    pub fn put(&mut self, key: Key, out: Arc<Outputs>) {
        let size = out.bytes();
        if size > self.budget_bytes {
            return;
        }
        if let Some((_, old, age)) = self.entries.remove(&key) {
            self.used -= old;
            self.by_age.remove(&age);
        }
        while self.used + size > self.budget_bytes {
            let Some((_, victim)) = self.by_age.pop_first() else {
                break;
            };
            if let Some((_, s, _)) = self.entries.remove(&victim) {
                self.used -= s;
            }
        }
        self.tick += 1;
        self.entries.insert(key, (out, size, self.tick));
        self.by_age.insert(self.tick, key);
        self.used += size;
    }
    /// Drops every entry.
    pub fn clear(&mut self) {
        self.entries.clear();
        self.by_age.clear();
        self.used = 0;
    }
}

/// Content-addressed files `<dir>/<first two hex>/<key>.bin`, at most
/// `budget_bytes` in all; the least recently used (by modification time,
/// refreshed on read) are removed first.
///
/// A corrupt or truncated file reads as a miss. Writes go to a temporary
/// file renamed into place, so a crash never leaves a partial entry.
#[derive(Debug, Clone)]
pub struct DiskCache {
    dir: PathBuf,
    budget_bytes: u64,
    /// What this process knows of the store's size since it last scanned
    /// it (see [`Tally`]), shared by the clones of one store.
    tally: Arc<Mutex<Tally>>,
}

/// The store's entries as this process knows them: those of the last
/// scan of its folders, plus what it wrote and read since. A put evicts
/// from this index when it passes the budget, and scans the folders (a
/// `stat` per entry) only every [`RESCAN_EVERY`] writes, to see what
/// other processes sharing the store did; before, every write scanned
/// (quadratic over a batch, slow on a network folder).
#[derive(Debug, Default)]
struct Tally {
    /// Entry path: size, last use. `None` until the first scan.
    index: Option<HashMap<PathBuf, (u64, SystemTime)>>,
    /// Their total size.
    bytes: u64,
    puts_since_scan: u32,
    /// Scans so far (how often the folders were read).
    scans: u64,
}

/// Writes between two scans of a store whose estimate is within budget.
pub const RESCAN_EVERY: u32 = 64;

impl DiskCache {
    /// A store in `dir` of at most `budget_bytes` in all; its directories are
    /// created when entries are written.
    pub fn new(dir: impl Into<PathBuf>, budget_bytes: u64) -> Self {
        Self {
            dir: dir.into(),
            budget_bytes,
            tally: Arc::new(Mutex::new(Tally::default())),
        }
    }
    /// The store's directory.
    pub fn dir(&self) -> &Path {
        &self.dir
    }
    fn path(&self, key: &Key) -> PathBuf {
        self.dir.join(entry_name(key))
    }
    /// Reads an entry; `None` on a miss or an unreadable entry. Extension
    /// values are read with `decoders`.
    pub fn get(&self, key: &Key, decoders: &codec::Decoders) -> Option<Outputs> {
        let path = self.path(key);
        let bytes = fs::read(&path).ok()?;
        let out = codec::decode(&bytes, decoders);
        if out.is_none() {
            let _ = fs::remove_file(&path);
        } else if let Ok(f) = fs::File::options().append(true).open(&path) {
            let now = SystemTime::now();
            let _ = f.set_modified(now);
            let mut t = self.tally.lock().unwrap_or_else(|e| e.into_inner());
            if let Some((_, used)) = t.index.as_mut().and_then(|i| i.get_mut(&path)) {
                *used = now;
            }
        }
        out
    }
    /// Writes an entry, then trims the store to its budget.
    pub fn put(&self, key: &Key, out: &Outputs) -> std::io::Result<()> {
        if !codec::persistable(out) {
            return Ok(());
        }
        let bytes = codec::encode(out);
        if bytes.len() as u64 > self.budget_bytes {
            return Ok(());
        }
        let path = self.path(key);
        let parent = path.parent().unwrap_or(&self.dir);
        fs::create_dir_all(parent)?;
        // process and thread in the name: concurrent writers of one key
        // (two processes sharing the store, two runs of one engine) never
        // write into the same temporary file
        let tmp = parent.join(format!(".{}.{}.tmp", key.to_hex(), temp_suffix()));
        let written = (|| {
            let mut f = fs::File::create(&tmp)?;
            f.write_all(&bytes)?;
            f.sync_data()?;
            fs::rename(&tmp, &path)
        })();
        if let Err(e) = written {
            // a full disk leaves no partial file behind
            let _ = fs::remove_file(&tmp);
            return Err(e);
        }
        let mut guard = self.tally.lock().unwrap_or_else(|e| e.into_inner());
        let t = &mut *guard;
        t.puts_since_scan += 1;
        let Some(index) = t
            .index
            .as_mut()
            .filter(|_| t.puts_since_scan < RESCAN_EVERY)
        else {
            drop(guard);
            return self.trim();
        };
        let size = bytes.len() as u64;
        // the file's own time, the clock the scans read (a network folder's
        // clock may differ from this machine's)
        let stamp = fs::metadata(&path)
            .and_then(|m| m.modified())
            .unwrap_or_else(|_| SystemTime::now());
        if let Some((old, _)) = index.insert(path, (size, stamp)) {
            t.bytes = t.bytes.saturating_sub(old);
        }
        t.bytes = t.bytes.saturating_add(size);
        if t.bytes <= self.budget_bytes {
            return Ok(());
        }
        // over the budget: the least recently used known entries go
        let mut by_age: Vec<(PathBuf, u64, SystemTime)> = index
            .iter()
            .map(|(p, (s, u))| (p.clone(), *s, *u))
            .collect();
        by_age.sort_by_key(|(_, _, u)| *u);
        // an entry that cannot be removed (another user's file, one held
        // open) leaves the index all the same and the next one goes; the
        // first failure is returned once the store is within budget
        let mut result = Ok(());
        for (p, s, _) in by_age {
            if t.bytes <= self.budget_bytes {
                break;
            }
            if let Err(e) = remove_if_present(&p) {
                result = result.and(Err(e));
            }
            index.remove(&p);
            t.bytes = t.bytes.saturating_sub(s);
        }
        result
    }
    /// How many times this store (and its clones) read its folders to
    /// trim them.
    pub fn scans(&self) -> u64 {
        self.tally.lock().unwrap_or_else(|e| e.into_inner()).scans
    }
    /// Total bytes of the entries on disk.
    pub fn used_bytes(&self) -> u64 {
        self.entries().iter().map(|(_, s, _)| s).sum()
    }
    fn entries(&self) -> Vec<(PathBuf, u64, SystemTime)> {
        self.files().0
    }
    /// The entries (path, size, last use), and the temporary files that
    /// writers left (path, last modified).
    #[allow(clippy::type_complexity)]
    fn files(&self) -> (Vec<(PathBuf, u64, SystemTime)>, Vec<(PathBuf, SystemTime)>) {
        let (mut out, mut tmps) = (Vec::new(), Vec::new());
        let own_suffix = format!(".{}.bin", codec::VERSION_TAG);
        let Ok(dirs) = fs::read_dir(&self.dir) else {
            return (out, tmps);
        };
        for d in dirs.flatten() {
            // only the store's own folders (two hex digits, `entry_name`):
            // a cache folder shared with other files (`--cache-dir .`)
            // keeps them
            let folder = d.file_name();
            let folder = folder.to_str().unwrap_or("");
            if !(folder.len() == 2 && folder.chars().all(|c| c.is_ascii_hexdigit())) {
                continue;
            }
            let Ok(files) = fs::read_dir(d.path()) else {
                continue;
            };
            for f in files.flatten() {
                let p = f.path();
                let Ok(m) = f.metadata() else {
                    continue; // removed meanwhile by another process
                };
                let t = m.modified().unwrap_or(SystemTime::UNIX_EPOCH);
                let name = p.file_name().and_then(|n| n.to_str()).unwrap_or("");
                // entries of another codec version (another depthgraph
                // sharing the store) are neither counted nor evicted; those
                // of the layout before version tags (`<key>.bin`, written by
                // earlier builds of this one) are counted and evicted first
                if name.ends_with(&own_suffix) {
                    out.push((p, m.len(), t));
                } else if is_untagged_entry(name) {
                    out.push((p, m.len(), SystemTime::UNIX_EPOCH));
                } else if is_temp_entry(name) {
                    tmps.push((p, t));
                }
            }
        }
        (out, tmps)
    }
    /// Removes the temporary files of writers that died before renaming
    /// them (a process killed mid-write), once they are older than
    /// [`STALE_TMP`], then the least recently used entries until the store
    /// fits its budget. Files another process removed meanwhile are not an
    /// error: several processes may share one store.
    pub fn trim(&self) -> std::io::Result<()> {
        let (mut entries, tmps) = self.files();
        let now = SystemTime::now();
        // a failure is remembered and the trim goes on (one file that
        // cannot be removed must not stop eviction for good); the first is
        // returned at the end
        let mut result = Ok(());
        for (p, t) in tmps {
            if now.duration_since(t).is_ok_and(|age| age >= STALE_TMP)
                && let Err(e) = remove_if_present(&p)
            {
                result = result.and(Err(e));
            }
        }
        let mut total: u64 = entries.iter().map(|(_, s, _)| s).sum();
        entries.sort_by_key(|(_, _, t)| *t);
        let mut kept = entries.len();
        for (k, (p, s, _)) in entries.iter().enumerate() {
            if total <= self.budget_bytes {
                kept = k;
                break;
            }
            if let Err(e) = remove_if_present(p) {
                result = result.and(Err(e));
            }
            // counted as gone either way: the next oldest goes next
            total -= s;
            kept = k + 1;
        }
        let index = entries
            .drain(kept.min(entries.len())..)
            .map(|(p, s, u)| (p, (s, u)))
            .collect();
        let mut t = self.tally.lock().unwrap_or_else(|e| e.into_inner());
        t.index = Some(index);
        t.bytes = total;
        t.puts_since_scan = 0;
        t.scans += 1;
        result
    }
}

/// A store of named byte blobs shared by many workers (an object store:
/// S3, GCS, Azure, or a shared folder), the third cache level after memory
/// and the local disk. Entries are content-addressed (the name is the
/// Merkle key), so two workers writing one entry write the same bytes and a
/// plain overwrite is safe.
pub trait BlobStore: Send + Sync {
    /// Where the store is, for messages (e.g. `s3://bucket/prefix`).
    fn describe(&self) -> String;
    /// The blob called `name`; `Ok(None)` when there is none.
    fn get(&self, name: &str) -> Result<Option<Vec<u8>>, String>;
    /// Stores `bytes` as `name`, replacing what was there.
    fn put(&self, name: &str, bytes: &[u8]) -> Result<(), String>;
}

/// Node outputs in a [`BlobStore`], under the disk cache's entry names
/// (`ab/<key>.dg5.bin`), so entries of another codec version never meet.
/// Remote failures are misses: a cache that cannot be reached is not an
/// error of the run (the command line checks the store once at start).
#[derive(Clone)]
pub struct RemoteCache {
    store: Arc<dyn BlobStore>,
    /// Set at the first failed call: the store is not asked again by this
    /// engine (a store that went away must not slow every node down).
    failed: Arc<std::sync::atomic::AtomicBool>,
}

impl std::fmt::Debug for RemoteCache {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "RemoteCache({})", self.store.describe())
    }
}

impl RemoteCache {
    /// A cache in `store`.
    pub fn new(store: Arc<dyn BlobStore>) -> Self {
        Self {
            store,
            failed: Arc::default(),
        }
    }
    /// Whether a call failed, after which the store is no longer used.
    pub fn failed(&self) -> bool {
        self.failed.load(std::sync::atomic::Ordering::Relaxed)
    }
    fn note<T>(&self, r: Result<T, String>) -> Result<T, String> {
        if r.is_err() {
            self.failed
                .store(true, std::sync::atomic::Ordering::Relaxed);
        }
        r
    }
    /// The store's description.
    pub fn describe(&self) -> String {
        self.store.describe()
    }
    /// The blob name of `key`'s entry (the disk cache's relative path).
    pub fn name(key: &Key) -> String {
        entry_name(key)
    }
    /// Reads an entry; `None` on a miss, an unreachable store or an entry
    /// that does not decode.
    pub fn get(&self, key: &Key, decoders: &codec::Decoders) -> Option<Outputs> {
        if self.failed() {
            return None;
        }
        let bytes = self.note(self.store.get(&Self::name(key))).ok()??;
        codec::decode(&bytes, decoders)
    }
    /// Writes an entry (values that cannot be persisted are skipped).
    pub fn put(&self, key: &Key, out: &Outputs) -> Result<(), String> {
        if !codec::persistable(out) || self.failed() {
            return Ok(());
        }
        self.note(self.store.put(&Self::name(key), &codec::encode(out)))
    }
}

/// How old a writer's temporary file must be before [`DiskCache::trim`]
/// takes it for the leftover of a killed process (a live writer renames
/// its file within the time of one write).
pub const STALE_TMP: std::time::Duration = std::time::Duration::from_secs(15 * 60);

/// `host.pid.thread.nanos`: a part of a temporary file's name that no
/// other live writer uses (another machine on a shared filesystem, another
/// process, another thread of this one). The clock's nanoseconds guard
/// against two machines that report the same host name (an inherited
/// `$HOSTNAME`, cloned containers) and happen to run writers of one entry
/// under one pid; a writer creates and renames its file within one call.
pub fn temp_suffix() -> String {
    use std::hash::{Hash, Hasher};
    let mut h = std::collections::hash_map::DefaultHasher::new();
    std::thread::current().id().hash(&mut h);
    let ns = SystemTime::now()
        .duration_since(SystemTime::UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos());
    format!(
        "{}.{}.{:x}.{ns:x}",
        host_tag(),
        std::process::id(),
        h.finish()
    )
}

/// The machine's host name, reduced to `[A-Za-z0-9-]` (at most 32
/// characters), or `host` when it cannot be read.
fn host_tag() -> String {
    // the kernel's name first: `$HOSTNAME` may be inherited from the
    // machine a job was submitted on
    let name = fs::read_to_string("/proc/sys/kernel/hostname")
        .ok()
        .or_else(|| fs::read_to_string("/etc/hostname").ok())
        .or_else(|| std::env::var("HOSTNAME").ok())
        .unwrap_or_default();
    let tag: String = name
        .trim()
        .chars()
        .filter(|c| c.is_ascii_alphanumeric() || *c == '-')
        .take(32)
        .collect();
    if tag.is_empty() {
        "host".to_string()
    } else {
        tag
    }
}

/// `ab/<key>.dg5.bin`: where both the disk cache and a shared store keep
/// `key`'s entry (the first two hex digits as a folder, the codec's version
/// tag in the name).
fn entry_name(key: &Key) -> String {
    let hex = key.to_hex();
    format!("{}/{hex}.{}.bin", &hex[..2], codec::VERSION_TAG)
}

/// `.<64 hex digits>.<suffix>.tmp`: a writer's temporary file
/// ([`DiskCache::put`]).
fn is_temp_entry(name: &str) -> bool {
    name.strip_prefix('.')
        .and_then(|n| n.strip_suffix(".tmp"))
        .and_then(|n| n.split_once('.'))
        .is_some_and(|(h, rest)| {
            h.len() == 64 && h.chars().all(|c| c.is_ascii_hexdigit()) && !rest.is_empty()
        })
}

/// `<64 hex digits>.bin`: an entry of the layout before version tags.
fn is_untagged_entry(name: &str) -> bool {
    name.strip_suffix(".bin")
        .is_some_and(|h| h.len() == 64 && h.chars().all(|c| c.is_ascii_hexdigit()))
}

fn remove_if_present(p: &Path) -> std::io::Result<()> {
    match fs::remove_file(p) {
        Err(e) if e.kind() != std::io::ErrorKind::NotFound => Err(e),
        _ => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::value::Value;

    /// Sets `path`'s modification time to `t` (an old file).
    fn backdate(path: &Path, t: SystemTime) {
        fs::File::options()
            .append(true)
            .open(path)
            .unwrap()
            .set_modified(t)
            .unwrap();
    }

    fn key(n: u8) -> Key {
        Key::from_bytes([n; 32])
    }
    fn out(n: usize) -> Arc<Outputs> {
        let img = crate::value::Image::filled(n, 1, 0.0f32);
        Arc::new(Outputs::new().with("d", Value::Depth(Arc::new(img))))
    }

    #[test]
    fn memory_cache_evicts_least_recent_within_budget() {
        let mut c = MemoryCache::new(100);
        c.put(key(1), out(10)); // 40 bytes
        c.put(key(2), out(10)); // 80
        assert!(c.get(&key(1)).is_some()); // 1 is now most recent
        c.put(key(3), out(10)); // needs eviction of 2
        assert!(c.get(&key(2)).is_none());
        assert!(c.get(&key(1)).is_some());
        assert!(c.get(&key(3)).is_some());
        assert!(c.used_bytes() <= 100);
        c.put(key(4), out(1000)); // bigger than the budget: ignored
        assert!(c.get(&key(4)).is_none());
    }

    #[test]
    fn disk_cache_round_trip_and_budget() {
        let dir = tempfile::tempdir().unwrap();
        let one = codec::encode(&out(100)).len() as u64;
        let c = DiskCache::new(dir.path(), one * 2 + 10);
        c.put(&key(1), &out(100)).unwrap();
        std::thread::sleep(std::time::Duration::from_millis(20));
        c.put(&key(2), &out(100)).unwrap();
        assert_eq!(
            c.get(&key(1), &Default::default()).unwrap().values,
            out(100).values
        );
        std::thread::sleep(std::time::Duration::from_millis(20));
        c.put(&key(3), &out(100)).unwrap();
        assert!(c.used_bytes() <= one * 2 + 10);
        // key 2 was the least recently used
        assert!(c.get(&key(2), &Default::default()).is_none());
        assert!(c.get(&key(1), &Default::default()).is_some());
        assert!(c.get(&key(3), &Default::default()).is_some());
    }

    /// A put scans the store only when this process's estimate passes the
    /// budget or every RESCAN_EVERY writes: a file another process wrote
    /// is not seen at once, but within that many writes, and the store
    /// never grows past the budget through this process's own writes.
    #[test]
    fn puts_scan_the_store_only_when_the_estimate_asks() {
        let dir = tempfile::tempdir().unwrap();
        let wide = |k: u64| Key::from_bytes(*blake3::hash(&k.to_le_bytes()).as_bytes());
        let one = codec::encode(&out(100)).len() as u64;
        let budget = one * 200;
        let c = DiskCache::new(dir.path(), budget);
        c.put(&wide(1), &out(100)).unwrap();
        // another process's entries, beyond the budget together
        let other = DiskCache::new(dir.path(), u64::MAX);
        for k in 1000..1250u64 {
            other.put(&wide(k), &out(100)).unwrap();
        }
        assert!(other.used_bytes() > budget);
        c.put(&wide(2), &out(100)).unwrap();
        // not scanned yet: the other entries are all still there
        assert!(c.used_bytes() > budget);
        for k in 3..(3 + u64::from(RESCAN_EVERY)) {
            c.put(&wide(k), &out(100)).unwrap();
        }
        assert!(c.used_bytes() <= budget);
        // this process's own writes keep it within budget at each put, and
        // a full store is not scanned at each: one scan per RESCAN_EVERY
        let before = c.scans();
        for k in 5000..5300u64 {
            c.put(&wide(k), &out(100)).unwrap();
            assert!(c.used_bytes() <= budget, "after {k}");
        }
        let scans = c.scans() - before;
        assert!(
            scans <= 300 / u64::from(RESCAN_EVERY),
            "{scans} scans for 300 writes"
        );
    }

    /// An entry that cannot be removed (here a folder in its place) does
    /// not stop eviction: the next oldest go, the newest stay.
    #[test]
    fn an_entry_that_cannot_be_removed_does_not_stop_eviction() {
        let dir = tempfile::tempdir().unwrap();
        let one = codec::encode(&out(100)).len() as u64;
        let c = DiskCache::new(dir.path(), one * 3);
        let stuck = c.path(&key(9));
        fs::create_dir_all(stuck.join("inside")).unwrap();
        for k in 1..=8u8 {
            let _ = c.put(&key(k), &out(100));
            std::thread::sleep(std::time::Duration::from_millis(5));
        }
        let _ = c.trim();
        assert!(stuck.exists());
        assert!(c.get(&key(8), &Default::default()).is_some());
        assert!(c.get(&key(7), &Default::default()).is_some());
        assert!(c.get(&key(1), &Default::default()).is_none());
        assert!(c.get(&key(4), &Default::default()).is_none());
    }

    #[test]
    fn corrupt_disk_entry_is_a_miss() {
        let dir = tempfile::tempdir().unwrap();
        let c = DiskCache::new(dir.path(), 1 << 20);
        c.put(&key(7), &out(4)).unwrap();
        let p = c.path(&key(7));
        fs::write(&p, b"garbage").unwrap();
        assert!(c.get(&key(7), &Default::default()).is_none());
        assert!(!p.exists());
    }

    #[test]
    fn truncated_entry_is_a_miss_and_is_replaced_by_the_next_put() {
        let dir = tempfile::tempdir().unwrap();
        let c = DiskCache::new(dir.path(), 1 << 20);
        c.put(&key(5), &out(16)).unwrap();
        let p = c.path(&key(5));
        let full = fs::read(&p).unwrap();
        for cut in [0, 8, full.len() / 2, full.len() - 1] {
            fs::write(&p, &full[..cut]).unwrap();
            assert!(c.get(&key(5), &Default::default()).is_none(), "cut {cut}");
            c.put(&key(5), &out(16)).unwrap();
            assert_eq!(fs::read(&p).unwrap(), full);
        }
        // one flipped bit anywhere, a pixel's included, is a miss (the
        // entry's checksum), and the damaged file is removed
        for at in [9, full.len() / 2, full.len() - 40, full.len() - 1] {
            let mut bad = full.clone();
            bad[at] ^= 0x40;
            fs::write(&p, &bad).unwrap();
            assert!(c.get(&key(5), &Default::default()).is_none(), "byte {at}");
            assert!(!p.exists(), "byte {at}");
            c.put(&key(5), &out(16)).unwrap();
        }
    }

    #[test]
    fn trim_removes_a_killed_writers_stale_temp_file_only() {
        let dir = tempfile::tempdir().unwrap();
        let c = DiskCache::new(dir.path(), 1 << 20);
        c.put(&key(1), &out(4)).unwrap();
        let sub = c.path(&key(1)).parent().unwrap().to_path_buf();
        let stale = sub.join(format!(".{}.123.4.tmp", key(2).to_hex()));
        let fresh = sub.join(format!(".{}.123.5.tmp", key(3).to_hex()));
        fs::write(&stale, b"half an entry").unwrap();
        fs::write(&fresh, b"being written").unwrap();
        let old = SystemTime::now() - STALE_TMP - std::time::Duration::from_secs(60);
        backdate(&stale, old);
        c.trim().unwrap();
        assert!(!stale.exists());
        assert!(fresh.exists());
        assert!(c.get(&key(1), &Default::default()).is_some());
    }

    /// A cache folder that holds other files too (`--cache-dir .`) keeps
    /// them: only the store's own temporary files and entries, in its
    /// two-hex-digit folders, are ever removed.
    #[test]
    fn trim_leaves_files_that_are_not_the_stores_alone() {
        let dir = tempfile::tempdir().unwrap();
        let c = DiskCache::new(dir.path(), 1);
        let old = SystemTime::now() - STALE_TMP - std::time::Duration::from_secs(60);
        let mine = [
            dir.path().join("out").join("draft.tmp"),
            dir.path()
                .join("out")
                .join(format!("{}.bin", key(7).to_hex())),
            dir.path().join("ab").join("notes.tmp"),
            dir.path().join("ab").join(".x.tmp"),
        ];
        for f in &mine {
            fs::create_dir_all(f.parent().unwrap()).unwrap();
            fs::write(f, b"the user's").unwrap();
            backdate(f, old);
        }
        // a stale temporary file of the store's own goes
        let sub = dir.path().join(&key(1).to_hex()[..2]);
        fs::create_dir_all(&sub).unwrap();
        let stale = sub.join(format!(".{}.1.2.tmp", key(1).to_hex()));
        fs::write(&stale, b"half an entry").unwrap();
        backdate(&stale, old);
        c.trim().unwrap();
        assert!(!stale.exists());
        for f in &mine {
            assert!(f.exists(), "{} removed", f.display());
        }
    }

    #[derive(Default)]
    struct Blobs(std::sync::Mutex<BTreeMap<String, Vec<u8>>>);
    impl BlobStore for Blobs {
        fn describe(&self) -> String {
            "memory".into()
        }
        fn get(&self, name: &str) -> Result<Option<Vec<u8>>, String> {
            Ok(self.0.lock().unwrap().get(name).cloned())
        }
        fn put(&self, name: &str, bytes: &[u8]) -> Result<(), String> {
            self.0
                .lock()
                .unwrap()
                .insert(name.to_string(), bytes.to_vec());
            Ok(())
        }
    }

    #[test]
    fn a_remote_cache_round_trips_and_misses_on_damage() {
        let blobs = Arc::new(Blobs::default());
        let c = RemoteCache::new(blobs.clone());
        assert!(c.get(&key(4), &Default::default()).is_none());
        c.put(&key(4), &out(8)).unwrap();
        assert_eq!(
            c.get(&key(4), &Default::default()).unwrap().values,
            out(8).values
        );
        let name = RemoteCache::name(&key(4));
        assert!(name.ends_with(".dg5.bin") && name.starts_with("04/"));
        blobs
            .0
            .lock()
            .unwrap()
            .insert(name, b"DGCACHE5 damaged".to_vec());
        assert!(c.get(&key(4), &Default::default()).is_none());
    }

    #[test]
    fn entries_of_another_codec_version_are_left_alone_and_untagged_ones_evicted() {
        let dir = tempfile::tempdir().unwrap();
        let one = codec::encode(&out(50)).len() as u64;
        let c = DiskCache::new(dir.path(), one);
        c.put(&key(1), &out(50)).unwrap();
        let sub = c.path(&key(1)).parent().unwrap().to_path_buf();
        // a newer depthgraph's entry, bigger than the budget, is left alone;
        // an entry of the untagged layout counts and goes first
        let newer = sub.join(format!("{}.dg9.bin", key(1).to_hex()));
        let older = sub.join(format!("{}.bin", key(2).to_hex()));
        fs::write(&newer, vec![7u8; (one * 3) as usize]).unwrap();
        fs::write(&older, b"DGCACHE2 whatever").unwrap();
        c.put(&key(3), &out(50)).unwrap();
        c.trim().unwrap();
        assert!(newer.exists());
        assert!(!older.exists());
        assert!(c.used_bytes() <= one);
        assert!(c.get(&key(3), &Default::default()).is_some());
    }

    #[test]
    fn temporary_names_name_the_host_and_differ_between_threads() {
        let a = temp_suffix();
        let c = std::thread::spawn(temp_suffix).join().unwrap();
        assert_ne!(a, c);
        assert!(a.starts_with(&format!("{}.{}.", host_tag(), std::process::id())));
    }

    #[test]
    fn trim_tolerates_entries_removed_by_another_process() {
        let dir = tempfile::tempdir().unwrap();
        let one = codec::encode(&out(50)).len() as u64;
        let c = DiskCache::new(dir.path(), one * 10);
        for n in 0..4 {
            c.put(&key(n), &out(50)).unwrap();
        }
        // the listing is taken, then a file vanishes: removing it is not an error
        assert!(remove_if_present(&c.path(&key(0))).is_ok());
        assert!(remove_if_present(&c.path(&key(0))).is_ok());
        let small = DiskCache::new(dir.path(), one);
        small.trim().unwrap();
        assert!(small.used_bytes() <= one);
    }
}
