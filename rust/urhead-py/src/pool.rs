//! Rayon thread pools sized per call. Pools are cached per (process, thread count) because
//! creating one costs far more than a small kernel; the process id in the key makes the
//! cache fork-safe (a forked child has none of its parent's threads, so it builds its own).

use std::sync::{Arc, Mutex};

use rayon::{ThreadPool, ThreadPoolBuilder};

struct Pools {
    pid: u32,
    by_size: Vec<(usize, Arc<ThreadPool>)>,
}

static POOLS: Mutex<Option<Pools>> = Mutex::new(None);

fn pool(num_threads: usize) -> Arc<ThreadPool> {
    let pid = std::process::id();
    // A poisoned lock only means another thread panicked while holding it; the cache is
    // still consistent (entries are inserted whole).
    let mut guard = POOLS.lock().unwrap_or_else(|p| p.into_inner());
    if guard.as_ref().is_none_or(|p| p.pid != pid) {
        // Stale pools from the parent: their threads do not exist here. Leak rather than
        // drop, since dropping would try to wake threads that were never forked.
        if let Some(stale) = guard.take() {
            std::mem::forget(stale);
        }
        *guard = Some(Pools {
            pid,
            by_size: Vec::new(),
        });
    }
    let pools = guard.as_mut().expect("initialised above");
    if let Some((_, p)) = pools.by_size.iter().find(|(n, _)| *n == num_threads) {
        return p.clone();
    }
    let p = Arc::new(
        ThreadPoolBuilder::new()
            .num_threads(num_threads)
            .thread_name(|i| format!("urhead-{i}"))
            .build()
            .expect("spawning rayon worker threads"),
    );
    pools.by_size.push((num_threads, p.clone()));
    p
}

/// Runs `f` on a pool of `num_threads` workers (at least one).
pub fn with_threads<R: Send>(num_threads: usize, f: impl FnOnce() -> R + Send) -> R {
    pool(num_threads.max(1)).install(f)
}
