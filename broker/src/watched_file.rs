//! A file the broker keeps loaded and reloads when it changes: the password file and the ACL.
//!
//! Readers take an `Arc` snapshot, so a reload never blocks a connection and never drops one:
//! connected devices keep their session; the new contents apply from the next check.
//! A file that fails to load on reload is ignored with an error in the log and in
//! `fbbus_file_reloads_total{result="error"}`: the broker keeps the last good version,
//! because a half-edited file must not lock a whole line out.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, PoisonError, RwLock};
use std::time::SystemTime;

use crate::metrics::Metrics;

type Loader<T> = Box<dyn Fn(&Path) -> Result<T, String> + Send + Sync>;

pub struct WatchedFile<T> {
    /// Short name for logs and the metric label: "password_file" or "acl_file".
    kind: &'static str,
    path: PathBuf,
    loader: Loader<T>,
    current: RwLock<Arc<T>>,
    stamp: RwLock<Option<Stamp>>,
    /// Bumped after each new version is installed, so a reader may keep what it derived
    /// from the contents (a verdict) until this changes ([`WatchedFile::generation`]).
    generation: AtomicU64,
}

/// What tells a changed file from an unchanged one without reading it.
#[derive(Debug, Clone, PartialEq, Eq)]
struct Stamp {
    modified: Option<SystemTime>,
    len: u64,
    #[cfg(unix)]
    inode: u64,
}

fn stamp(path: &Path) -> Option<Stamp> {
    let meta = std::fs::metadata(path).ok()?;
    Some(Stamp {
        modified: meta.modified().ok(),
        len: meta.len(),
        #[cfg(unix)]
        inode: std::os::unix::fs::MetadataExt::ino(&meta),
    })
}

impl<T> WatchedFile<T> {
    /// Loads the file once; an error here stops the broker from starting.
    pub fn load(
        kind: &'static str,
        path: &Path,
        loader: impl Fn(&Path) -> Result<T, String> + Send + Sync + 'static,
    ) -> Result<WatchedFile<T>, String> {
        let stamp_before = stamp(path);
        let value = loader(path)?;
        Ok(WatchedFile {
            kind,
            path: path.to_owned(),
            loader: Box::new(loader),
            current: RwLock::new(Arc::new(value)),
            stamp: RwLock::new(stamp_before),
            generation: AtomicU64::new(0),
        })
    }

    /// The current contents.
    pub fn get(&self) -> Arc<T> {
        self.current
            .read()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()
    }

    /// Which version [`WatchedFile::get`] returns: changes whenever new contents are
    /// installed. Read it before `get`: the new contents are installed before the number
    /// changes, so what is derived from `get` is at least as new as the number it is
    /// remembered under, never older.
    pub fn generation(&self) -> u64 {
        self.generation.load(Ordering::Acquire)
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Replaces the contents after the broker itself rewrote the file (password re-hashing),
    /// so the poll does not reload what is already in memory.
    pub fn replace(&self, value: T) {
        *self.stamp.write().unwrap_or_else(PoisonError::into_inner) = stamp(&self.path);
        self.install(value);
    }

    fn install(&self, value: T) {
        *self.current.write().unwrap_or_else(PoisonError::into_inner) = Arc::new(value);
        self.generation.fetch_add(1, Ordering::Release);
    }

    /// Reloads if the file changed since the last load (`force`: reload anyway, for SIGHUP).
    /// Returns true when new contents were installed.
    pub fn reload(&self, force: bool, metrics: &Metrics) -> bool {
        let now = stamp(&self.path);
        if !force && *self.stamp.read().unwrap_or_else(PoisonError::into_inner) == now {
            return false;
        }
        *self.stamp.write().unwrap_or_else(PoisonError::into_inner) = now;
        match (self.loader)(&self.path) {
            Ok(value) => {
                self.install(value);
                metrics.reloads.with_label_values(&[self.kind, "ok"]).inc();
                tracing::info!(file = %self.path.display(), kind = self.kind, "reloaded");
                true
            }
            Err(e) => {
                metrics
                    .reloads
                    .with_label_values(&[self.kind, "error"])
                    .inc();
                tracing::error!(
                    file = %self.path.display(),
                    kind = self.kind,
                    error = %e,
                    "reload failed; keeping the previous version"
                );
                false
            }
        }
    }
}
