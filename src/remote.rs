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
//! runs them for the engine's threads. Cloud stores retry a few times
//! within 20 s; after a failed call the engine stops asking the store
//! (every later lookup is a miss) and the batch summary says so.

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
    /// The store answered the start-up check with a refusal a retry will
    /// not change: credentials refused, no permission to write, no such
    /// bucket.
    #[error("--cache-url {url}: the store refuses this client: {message}")]
    Refused {
        /// The store.
        url: String,
        /// Its answer.
        message: String,
    },
    /// The store could not answer the start-up check (unreachable, timed
    /// out, a server error).
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

/// How long a cloud store may take: a few retries within 20 s, 5 s to
/// connect, 60 s per request (object_store's defaults retry for minutes,
/// which a cache should not: a miss costs less than the wait).
fn retry() -> object_store::RetryConfig {
    object_store::RetryConfig {
        max_retries: 3,
        retry_timeout: std::time::Duration::from_secs(20),
        backoff: object_store::BackoffConfig::default(),
    }
}

const CONNECT_TIMEOUT: &str = "5s";
const REQUEST_TIMEOUT: &str = "60s";

/// The store of `url` with its service's environment variables, the
/// timeouts and retries of [`retry`] for cloud stores.
fn build(url: &url::Url) -> object_store::Result<(Box<dyn ObjectStore>, StorePath)> {
    use object_store::{ClientConfigKey as C, ObjectStoreScheme as S};
    let (scheme, path) = S::parse(url)?;
    let store: Box<dyn ObjectStore> = match scheme {
        S::AmazonS3 => {
            use object_store::aws::{AmazonS3Builder, AmazonS3ConfigKey as K};
            Box::new(
                AmazonS3Builder::from_env()
                    .with_url(url.as_str())
                    .with_retry(retry())
                    .with_config(K::Client(C::ConnectTimeout), CONNECT_TIMEOUT)
                    .with_config(K::Client(C::Timeout), REQUEST_TIMEOUT)
                    .build()?,
            )
        }
        S::GoogleCloudStorage => {
            use object_store::gcp::{GoogleCloudStorageBuilder, GoogleConfigKey as K};
            Box::new(
                GoogleCloudStorageBuilder::from_env()
                    .with_url(url.as_str())
                    .with_retry(retry())
                    .with_config(K::Client(C::ConnectTimeout), CONNECT_TIMEOUT)
                    .with_config(K::Client(C::Timeout), REQUEST_TIMEOUT)
                    .build()?,
            )
        }
        S::MicrosoftAzure => {
            use object_store::azure::{AzureConfigKey as K, MicrosoftAzureBuilder};
            Box::new(
                MicrosoftAzureBuilder::from_env()
                    .with_url(url.as_str())
                    .with_retry(retry())
                    .with_config(K::Client(C::ConnectTimeout), CONNECT_TIMEOUT)
                    .with_config(K::Client(C::Timeout), REQUEST_TIMEOUT)
                    .build()?,
            )
        }
        _ => return object_store::parse_url(url),
    };
    Ok((store, path))
}

/// Whether the store's error is a refusal (credentials, permissions, a
/// bucket that does not exist: the write of a probe found no container)
/// or a failure to answer.
fn classify(url: &str, e: object_store::Error) -> RemoteError {
    use object_store::Error as E;
    let message = e.to_string();
    let url = url.to_string();
    // a folder store reports the file system's error inside `Generic`
    let mut io_kind = None;
    let mut cause: Option<&(dyn std::error::Error + 'static)> = Some(&e);
    while let Some(c) = cause {
        if let Some(io) = c.downcast_ref::<std::io::Error>() {
            io_kind = Some(io.kind());
            break;
        }
        cause = c.source();
    }
    use std::io::ErrorKind as K;
    let refused_io = matches!(
        io_kind,
        Some(K::PermissionDenied | K::ReadOnlyFilesystem | K::NotADirectory | K::IsADirectory)
    );
    match e {
        E::PermissionDenied { .. } | E::Unauthenticated { .. } | E::NotFound { .. } => {
            RemoteError::Refused { url, message }
        }
        _ if refused_io => RemoteError::Refused { url, message },
        _ => RemoteError::Unreachable { url, message },
    }
}

/// The start-up check: the store takes a small probe object (under the
/// prefix, `depthgraph-probe`) and gives it back. A read alone passed on a
/// bucket that does not exist (S3 answers "not found", a miss) and failed
/// where a client may read and write objects but not list the bucket.
fn probe(blobs: &ObjectStoreBlobs) -> Result<(), RemoteError> {
    const PROBE: &[u8] = b"depthgraph cache probe\n";
    let at = blobs.location("depthgraph-probe");
    blobs.runtime.block_on(async {
        blobs
            .store
            .put(&at, PutPayload::from_static(PROBE))
            .await
            .map_err(|e| classify(&blobs.url, e))?;
        let back = blobs
            .store
            .get(&at)
            .await
            .map_err(|e| classify(&blobs.url, e))?
            .bytes()
            .await
            .map_err(|e| classify(&blobs.url, e))?;
        if back.as_ref() == PROBE {
            Ok(())
        } else {
            Err(RemoteError::Unreachable {
                url: blobs.url.clone(),
                message: "the probe object read back differs from what was written".into(),
            })
        }
    })
}

/// Checks `url` without contacting the store: a URL, of a scheme the
/// store knows (a Slurm submission's check: its tasks open the store).
pub fn check_url(url: &str) -> Result<(), RemoteError> {
    // the client `open` makes (no request is sent): a scheme this build
    // cannot serve, or a URL its builder refuses, fails here
    client(url).map(|_| ())
}

/// The client of `url` and its prefix, or why there is none.
fn client(url: &str) -> Result<(Box<dyn ObjectStore>, StorePath), RemoteError> {
    let bad = |message: String| RemoteError::Url {
        url: url.to_string(),
        message,
    };
    let parsed = url::Url::parse(url).map_err(|e| bad(e.to_string()))?;
    build(&parsed).map_err(|e| bad(e.to_string()))
}

/// Opens the store of `url` and checks once that it takes and gives back a
/// probe object ([`probe`]); credentials from the environment.
pub fn open(url: &str) -> Result<Arc<dyn BlobStore>, RemoteError> {
    let (store, prefix) = client(url)?;
    let bad = |message: String| RemoteError::Url {
        url: url.to_string(),
        message,
    };
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
    probe(&blobs)?;
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
        assert!(check_url("s3://bucket/prefix").is_ok());
        for bad in ["not a url", "nope://x"] {
            let e = check_url(bad).unwrap_err().to_string();
            assert!(e.contains(bad), "{e}");
        }
        assert!(check_url("https://host/x").is_err());
        // a folder store under a file: refused (a usage error), not
        // unreachable (which a Slurm task retries and requeues forever)
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("file"), b"x").unwrap();
        let url = format!("file://{}/file/prefix", dir.path().display());
        match open(&url) {
            Err(RemoteError::Refused { .. }) => {}
            Err(other) => panic!("{other}"),
            Ok(_) => panic!("a store under a file opened"),
        }
        let e = open("not a url").err().unwrap().to_string();
        assert!(e.contains("--cache-url not a url"), "{e}");
        let e = open("ftp://host/x").err().unwrap().to_string();
        assert!(e.contains("ftp://host/x"), "{e}");
    }
}
