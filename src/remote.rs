//! The object-store cache of `--cache-url`: S3 (`s3://bucket/prefix`), GCS
//! (`gs://`), Azure (`az://`, `abfs://`) or a folder (`file:///path`),
//! through the `object_store` crate.
//!
//! Credentials and endpoints come from the usual environment variables of
//! each service (`AWS_ACCESS_KEY_ID`, `AWS_SECRET_ACCESS_KEY`,
//! `AWS_DEFAULT_REGION`, `AWS_ENDPOINT`, `AWS_ALLOW_HTTP`, `GOOGLE_*`,
//! `AZURE_*`). Entries are content-addressed (their name is the Merkle key),
//! so workers on many machines share one prefix and plain overwrites are
//! safe. The store's calls are async; a small runtime of this store's own
//! runs them for the engine's threads.

use std::sync::Arc;

use depthgraph_graph::cache::BlobStore;
use object_store::path::Path as StorePath;
use object_store::{ObjectStore, ObjectStoreExt, PutPayload};

/// A `--cache-url` that cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum RemoteError {
    /// Not a URL, or a scheme the store does not know.
    #[error("--cache-url {url}: {message}")]
    Url {
        /// What was given.
        url: String,
        /// Why it cannot be used.
        message: String,
    },
    /// The store answered the start-up check with an error (unreachable,
    /// refused credentials, no such bucket).
    #[error("--cache-url {url}: the store cannot be used: {message}")]
    Unreachable {
        /// The store.
        url: String,
        /// Its answer.
        message: String,
    },
}

/// An object store under a prefix.
pub struct ObjectStoreBlobs {
    store: Box<dyn ObjectStore>,
    prefix: String,
    url: String,
    runtime: tokio::runtime::Runtime,
}

impl ObjectStoreBlobs {
    fn location(&self, name: &str) -> StorePath {
        if self.prefix.is_empty() {
            StorePath::from(name)
        } else {
            StorePath::from(format!("{}/{name}", self.prefix))
        }
    }
}

impl BlobStore for ObjectStoreBlobs {
    fn describe(&self) -> String {
        self.url.clone()
    }

    fn get(&self, name: &str) -> Result<Option<Vec<u8>>, String> {
        let at = self.location(name);
        self.runtime.block_on(async {
            match self.store.get(&at).await {
                Ok(r) => r
                    .bytes()
                    .await
                    .map(|b| Some(b.to_vec()))
                    .map_err(|e| e.to_string()),
                Err(object_store::Error::NotFound { .. }) => Ok(None),
                Err(e) => Err(e.to_string()),
            }
        })
    }

    fn put(&self, name: &str, bytes: &[u8]) -> Result<(), String> {
        let at = self.location(name);
        let payload = PutPayload::from(bytes.to_vec());
        self.runtime
            .block_on(self.store.put(&at, payload))
            .map(|_| ())
            .map_err(|e| e.to_string())
    }
}

/// Opens the store of `url` and checks once that it answers (a miss on a
/// probe name is an answer); credentials from the environment.
pub fn open(url: &str) -> Result<Arc<dyn BlobStore>, RemoteError> {
    let bad = |message: String| RemoteError::Url {
        url: url.to_string(),
        message,
    };
    let parsed = url::Url::parse(url).map_err(|e| bad(e.to_string()))?;
    let options = std::env::vars().filter(|(k, _)| {
        ["AWS_", "GOOGLE_", "AZURE_"]
            .iter()
            .any(|p| k.starts_with(p))
    });
    let (store, prefix) =
        object_store::parse_url_opts(&parsed, options).map_err(|e| bad(e.to_string()))?;
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .thread_name("depthgraph-store")
        .enable_all()
        .build()
        .map_err(|e| bad(format!("cannot start its I/O threads: {e}")))?;
    let blobs = ObjectStoreBlobs {
        store,
        prefix: prefix.as_ref().trim_matches('/').to_string(),
        url: url.to_string(),
        runtime,
    };
    blobs
        .get("depthgraph-probe")
        .map_err(|message| RemoteError::Unreachable {
            url: url.to_string(),
            message,
        })?;
    Ok(Arc::new(blobs))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_folder_store_round_trips_under_its_prefix() {
        let dir = tempfile::tempdir().unwrap();
        let url = format!("file://{}/cache/prefix", dir.path().display());
        let s = open(&url).unwrap();
        assert_eq!(s.get("ab/x.bin").unwrap(), None);
        s.put("ab/x.bin", b"bytes").unwrap();
        assert_eq!(s.get("ab/x.bin").unwrap().as_deref(), Some(&b"bytes"[..]));
        assert!(dir.path().join("cache/prefix/ab/x.bin").exists());
        s.put("ab/x.bin", b"other").unwrap();
        assert_eq!(s.get("ab/x.bin").unwrap().as_deref(), Some(&b"other"[..]));
    }

    #[test]
    fn bad_urls_and_dead_stores_are_errors_naming_the_url() {
        let e = open("not a url").err().unwrap().to_string();
        assert!(e.contains("--cache-url not a url"), "{e}");
        let e = open("ftp://host/x").err().unwrap().to_string();
        assert!(e.contains("ftp://host/x"), "{e}");
    }
}
