//! Toolpath previews as a shared, bounded resource: each one is computed once per program (and
//! whatever else it depends on) and kept in a cache bounded in bytes and entries; at most
//! `toolpath_max_concurrent` are computed at a time (the others wait, costing no CPU); identical
//! requests made while one is computed wait for that one; and a computation nobody waits for
//! any more (its clients left) is abandoned at its next check of a cancellation flag.

use crate::config::ToolpathSettings;
use crate::error::{Error, ErrorKind, Result};
use std::collections::{HashMap, VecDeque};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use tokio::sync::{watch, Semaphore};

/// Everything a toolpath depends on, as one string: the program's sha256, the vertex budget,
/// the unsupported-word policy, the tool table and the work budget (see `jobs::toolpath`).
pub type Key = String;

/// A computation's answer as every waiter gets it (core errors are not `Clone`).
type Answer = std::result::Result<Arc<Vec<u8>>, (ErrorKind, &'static str, String)>;

/// Counters for `/metrics`.
#[derive(Debug, Default)]
pub struct PreviewStats {
    /// Answered from the cache, or by a computation already under way for the same key.
    pub hits: AtomicU64,
    /// Computations run to the end (with a toolpath or a G-code error).
    pub computed: AtomicU64,
    /// Computations abandoned because every client waiting for them had gone.
    pub abandoned: AtomicU64,
    /// Computations running now.
    pub computing: AtomicU64,
}

struct Flight {
    cancel: Arc<AtomicBool>,
    /// Requests waiting for this computation (changed under `Inner`'s lock).
    waiters: usize,
    answer: watch::Receiver<Option<Answer>>,
}

#[derive(Default)]
struct Inner {
    /// Most recently used first.
    cache: VecDeque<(Key, Arc<Vec<u8>>)>,
    cache_bytes: u64,
    flights: HashMap<Key, Flight>,
}

pub struct Previews {
    settings: ToolpathSettings,
    permits: Arc<Semaphore>,
    inner: Arc<Mutex<Inner>>,
    pub stats: Arc<PreviewStats>,
}

/// Held by a request while it waits; the last one to leave cancels the computation.
struct Waiter {
    inner: Arc<Mutex<Inner>>,
    key: Key,
    cancel: Arc<AtomicBool>,
}

impl Drop for Waiter {
    fn drop(&mut self) {
        let mut inner = lock(&self.inner);
        // The flight may be gone (finished) or replaced by a newer one for the same key.
        if let Some(f) = inner.flights.get_mut(&self.key) {
            if Arc::ptr_eq(&f.cancel, &self.cancel) {
                f.waiters -= 1;
                if f.waiters == 0 {
                    self.cancel.store(true, Ordering::Relaxed);
                    inner.flights.remove(&self.key);
                }
            }
        }
    }
}

fn lock(m: &Mutex<Inner>) -> MutexGuard<'_, Inner> {
    // The lock guards plain bookkeeping that is consistent between statements.
    m.lock().unwrap_or_else(|e| e.into_inner())
}

fn answer_of(e: &Error) -> Answer {
    Err((e.kind, e.code, e.message.clone()))
}

impl Previews {
    pub fn new(settings: ToolpathSettings) -> Previews {
        Previews {
            settings,
            permits: Arc::new(Semaphore::new(settings.max_concurrent.max(1))),
            inner: Arc::default(),
            stats: Arc::default(),
        }
    }

    /// The toolpath for `key`: from the cache, from a computation under way for the same key,
    /// or computed by `compute` on a blocking thread once a permit is free. `compute` gets the
    /// cancellation flag and answers `Ok(None)` when it saw it set. Dropping the returned
    /// future (the client left) stops waiting; the last waiter to go cancels the computation.
    pub async fn get<F>(&self, key: Key, compute: F) -> Result<Arc<Vec<u8>>>
    where
        F: FnOnce(&AtomicBool) -> Result<Option<Vec<u8>>> + Send + 'static,
    {
        let (mut answer, _waiter) = {
            let mut inner = lock(&self.inner);
            if let Some(i) = inner.cache.iter().position(|(k, _)| *k == key) {
                if let Some(hit) = inner.cache.remove(i) {
                    let bytes = Arc::clone(&hit.1);
                    inner.cache.push_front(hit);
                    self.stats.hits.fetch_add(1, Ordering::Relaxed);
                    return Ok(bytes);
                }
            }
            let flight = match inner.flights.get_mut(&key) {
                Some(f) => {
                    self.stats.hits.fetch_add(1, Ordering::Relaxed);
                    f.waiters += 1;
                    f
                }
                None => {
                    let f = self.launch(key.clone(), compute);
                    inner.flights.entry(key.clone()).or_insert(f)
                }
            };
            let waiter = Waiter {
                inner: Arc::clone(&self.inner),
                key,
                cancel: Arc::clone(&flight.cancel),
            };
            (flight.answer.clone(), waiter)
        };
        loop {
            if let Some(a) = answer.borrow_and_update().clone() {
                return a.map_err(|(kind, code, message)| Error::new(kind, code, message));
            }
            if answer.changed().await.is_err() {
                return Err(Error::internal(
                    "the toolpath computation ended without an answer",
                ));
            }
        }
    }

    /// Starts the computation for `key` (one waiter) on its own task, so that it is shared by
    /// every request for the same key and outlives none of them.
    fn launch<F>(&self, key: Key, compute: F) -> Flight
    where
        F: FnOnce(&AtomicBool) -> Result<Option<Vec<u8>>> + Send + 'static,
    {
        let cancel = Arc::new(AtomicBool::new(false));
        let (tx, rx) = watch::channel(None);
        let (permits, inner, stats) = (
            Arc::clone(&self.permits),
            Arc::clone(&self.inner),
            Arc::clone(&self.stats),
        );
        let settings = self.settings;
        let flag = Arc::clone(&cancel);
        tokio::spawn(async move {
            let result = match permits.acquire_owned().await {
                // Everyone may have left while it waited for its turn.
                Ok(_) if flag.load(Ordering::Relaxed) => Ok(None),
                Ok(permit) => {
                    let flag = Arc::clone(&flag);
                    let stats = Arc::clone(&stats);
                    tokio::task::spawn_blocking(move || {
                        stats.computing.fetch_add(1, Ordering::Relaxed);
                        let r = compute(&flag);
                        stats.computing.fetch_sub(1, Ordering::Relaxed);
                        drop(permit);
                        r
                    })
                    .await
                    .unwrap_or_else(|e| Err(Error::internal(format!("toolpath failed: {e}"))))
                }
                Err(_) => Err(Error::internal("the toolpath permits are closed")),
            };
            let answer = match result {
                Ok(None) => {
                    stats.abandoned.fetch_add(1, Ordering::Relaxed);
                    return;
                }
                Ok(Some(bytes)) => Ok(Arc::new(bytes)),
                Err(e) => Err(e),
            };
            stats.computed.fetch_add(1, Ordering::Relaxed);
            let answer = match answer {
                Ok(bytes) => {
                    let mut inner = lock(&inner);
                    Self::keep(&mut inner, &settings, &key, &bytes, &flag);
                    Ok(bytes)
                }
                Err(e) => {
                    let mut inner = lock(&inner);
                    Self::forget_flight(&mut inner, &key, &flag);
                    answer_of(&e)
                }
            };
            // Waiters that left meanwhile dropped their receivers; nobody to tell is fine.
            let _ = tx.send(Some(answer));
        });
        Flight {
            cancel,
            waiters: 1,
            answer: rx,
        }
    }

    fn forget_flight(inner: &mut Inner, key: &str, flag: &Arc<AtomicBool>) {
        if inner
            .flights
            .get(key)
            .is_some_and(|f| Arc::ptr_eq(&f.cancel, flag))
        {
            inner.flights.remove(key);
        }
    }

    /// Caches a finished toolpath (unless it alone exceeds the bounds), evicting the least
    /// recently used ones beyond `cache_bytes` / `cache_entries`.
    fn keep(
        inner: &mut Inner,
        settings: &ToolpathSettings,
        key: &str,
        bytes: &Arc<Vec<u8>>,
        flag: &Arc<AtomicBool>,
    ) {
        Self::forget_flight(inner, key, flag);
        let size = bytes.len() as u64;
        if settings.cache_entries == 0 || size > settings.cache_bytes {
            return;
        }
        if let Some(i) = inner.cache.iter().position(|(k, _)| k == key) {
            if let Some((_, old)) = inner.cache.remove(i) {
                inner.cache_bytes -= old.len() as u64;
            }
        }
        inner.cache.push_front((key.to_string(), Arc::clone(bytes)));
        inner.cache_bytes += size;
        while inner.cache.len() > settings.cache_entries || inner.cache_bytes > settings.cache_bytes
        {
            match inner.cache.pop_back() {
                Some((_, old)) => inner.cache_bytes -= old.len() as u64,
                None => break,
            }
        }
    }

    /// Prometheus text: the counters and the cache's size.
    pub fn prometheus(&self) -> String {
        let get = |c: &AtomicU64| c.load(Ordering::Relaxed);
        let (entries, bytes) = {
            let inner = lock(&self.inner);
            (inner.cache.len(), inner.cache_bytes)
        };
        format!(
            "# HELP fresa_toolpath_cache_hits_total Toolpath requests answered from the cache or by a computation already under way.\n\
             # TYPE fresa_toolpath_cache_hits_total counter\nfresa_toolpath_cache_hits_total {}\n\
             # HELP fresa_toolpath_computed_total Toolpath computations run to the end.\n\
             # TYPE fresa_toolpath_computed_total counter\nfresa_toolpath_computed_total {}\n\
             # HELP fresa_toolpath_abandoned_total Toolpath computations abandoned because their clients left.\n\
             # TYPE fresa_toolpath_abandoned_total counter\nfresa_toolpath_abandoned_total {}\n\
             # HELP fresa_toolpath_computing Toolpath computations running now.\n\
             # TYPE fresa_toolpath_computing gauge\nfresa_toolpath_computing {}\n\
             # HELP fresa_toolpath_cache_entries Toolpaths kept in memory.\n\
             # TYPE fresa_toolpath_cache_entries gauge\nfresa_toolpath_cache_entries {entries}\n\
             # HELP fresa_toolpath_cache_bytes Bytes of the toolpaths kept in memory.\n\
             # TYPE fresa_toolpath_cache_bytes gauge\nfresa_toolpath_cache_bytes {bytes}\n",
            get(&self.stats.hits),
            get(&self.stats.computed),
            get(&self.stats.abandoned),
            get(&self.stats.computing),
        )
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use std::time::Duration;

    fn previews(cache_bytes: u64, cache_entries: usize) -> Previews {
        Previews::new(ToolpathSettings {
            cache_bytes,
            cache_entries,
            max_concurrent: 1,
        })
    }

    #[tokio::test]
    async fn computed_once_then_cached_and_bounded() {
        let p = previews(10, 2);
        for _ in 0..3 {
            let b = p.get("a".into(), |_| Ok(Some(vec![1; 4]))).await.unwrap();
            assert_eq!(*b, vec![1; 4]);
        }
        assert_eq!(p.stats.computed.load(Ordering::Relaxed), 1);
        assert_eq!(p.stats.hits.load(Ordering::Relaxed), 2);
        // b (4 bytes) and c (4 bytes) fit beside a? 12 > 10: a, the oldest, goes.
        p.get("b".into(), |_| Ok(Some(vec![2; 4]))).await.unwrap();
        p.get("c".into(), |_| Ok(Some(vec![3; 4]))).await.unwrap();
        {
            let inner = lock(&p.inner);
            let keys: Vec<_> = inner.cache.iter().map(|(k, _)| k.as_str()).collect();
            assert_eq!(keys, ["c", "b"]);
            assert_eq!(inner.cache_bytes, 8);
        }
        // Larger than the whole cache: served, not kept.
        p.get("d".into(), |_| Ok(Some(vec![4; 11]))).await.unwrap();
        assert_eq!(lock(&p.inner).cache.len(), 2);
        // Errors are answered, not kept.
        let e = p
            .get("e".into(), |_| {
                Err(Error::invalid("invalid_gcode", "line 1"))
            })
            .await
            .unwrap_err();
        assert_eq!(e.code, "invalid_gcode");
        assert!(!lock(&p.inner).flights.contains_key("e"));
    }

    #[tokio::test]
    async fn the_last_waiter_to_leave_cancels_the_computation() {
        let p = Arc::new(previews(1 << 20, 8));
        let (started_tx, started_rx) = std::sync::mpsc::channel();
        let slow = move |cancel: &AtomicBool| {
            let _ = started_tx.send(());
            while !cancel.load(Ordering::Relaxed) {
                std::thread::sleep(Duration::from_millis(1));
            }
            Ok(None)
        };
        let first = tokio::spawn({
            let p = Arc::clone(&p);
            async move { p.get("k".into(), slow).await }
        });
        tokio::task::spawn_blocking(move || started_rx.recv().unwrap())
            .await
            .unwrap();
        // A second identical request joins the same computation.
        let second = tokio::spawn({
            let p = Arc::clone(&p);
            async move { p.get("k".into(), |_| panic!("computed twice")).await }
        });
        let deadline = std::time::Instant::now() + Duration::from_secs(30);
        while p.stats.hits.load(Ordering::Relaxed) == 0 {
            assert!(std::time::Instant::now() < deadline, "never joined");
            tokio::time::sleep(Duration::from_millis(1)).await;
        }
        first.abort();
        let _ = first.await;
        assert_eq!(
            p.stats.abandoned.load(Ordering::Relaxed),
            0,
            "one still waits"
        );
        second.abort();
        let _ = second.await;
        let deadline = std::time::Instant::now() + Duration::from_secs(30);
        while p.stats.abandoned.load(Ordering::Relaxed) == 0 {
            assert!(std::time::Instant::now() < deadline, "not abandoned");
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
        assert_eq!(p.stats.computed.load(Ordering::Relaxed), 0);
        // A new request for the same key starts afresh.
        let b = p.get("k".into(), |_| Ok(Some(vec![7]))).await.unwrap();
        assert_eq!(*b, vec![7]);
    }
}
