//! Rayon thread pools sized per call. Pools are cached per (process, thread count) because
//! creating one costs far more than a small kernel; the process id in the key makes the
//! cache fork-safe (a forked child has none of its parent's threads, so it builds its own).
//!
//! The first thread of a process to call in (the Python interpreter's main thread, in
//! practice) is made a member of the pool it asks for: a call from it runs on it, and only
//! the other workers are woken to share the work. A call handed to a pool it is not part of
//! waits for one sleeping worker to wake and take it, then sleeps until woken with the
//! result: two wake-ups, ~40–150 µs on a virtual machine, on every call between stretches
//! of Python (a fit makes ~45 such calls an iteration, a frame ~17). Other threads, and
//! that thread at another thread count, use the shared pools as before. Kernels cut their
//! work the same whichever thread runs it, so results are unchanged.

use std::cell::Cell;
use std::sync::{Arc, Mutex};

use rayon::{ThreadPool, ThreadPoolBuilder};

struct Pools {
    pid: u32,
    by_size: Vec<(usize, Arc<ThreadPool>)>,
    /// Whether a thread of this process has been made a member of a pool (see
    /// [`with_threads`]); at most one is, so such pools never accumulate.
    member_taken: bool,
}

static POOLS: Mutex<Option<Pools>> = Mutex::new(None);

thread_local! {
    /// The pool this thread is a member of: `(process id, thread count, pool)`. Leaked: it
    /// lives as long as the process (rayon never frees a pool its caller joined), and no
    /// thread-local destructor has to drop it at exit.
    static MEMBER_OF: Cell<Option<(u32, usize, &'static ThreadPool)>> = const { Cell::new(None) };
}

fn pools(guard: &mut Option<Pools>, pid: u32) -> &mut Pools {
    if guard.as_ref().is_none_or(|p| p.pid != pid) {
        // Stale pools from the parent: their threads do not exist here. Leak rather than
        // drop, since dropping would try to wake threads that were never forked.
        if let Some(stale) = guard.take() {
            std::mem::forget(stale);
        }
        *guard = Some(Pools {
            pid,
            by_size: Vec::new(),
            member_taken: false,
        });
    }
    guard.as_mut().expect("initialised above")
}

fn builder(num_threads: usize) -> ThreadPoolBuilder {
    ThreadPoolBuilder::new()
        .num_threads(num_threads)
        .thread_name(|i| format!("urhead-{i}"))
}

/// The shared pool of `num_threads` workers.
fn shared_pool(pools: &mut Pools, num_threads: usize) -> Arc<ThreadPool> {
    if let Some((_, p)) = pools.by_size.iter().find(|(n, _)| *n == num_threads) {
        return p.clone();
    }
    let p = Arc::new(
        builder(num_threads)
            .build()
            .expect("spawning rayon worker threads"),
    );
    pools.by_size.push((num_threads, p.clone()));
    p
}

/// The pool a call from this thread runs on, if it is a member of one.
fn member_pool(num_threads: usize) -> Option<&'static ThreadPool> {
    let pid = std::process::id();
    if let Some((p, n, pool)) = MEMBER_OF.get() {
        return (p == pid && n == num_threads).then_some(pool);
    }
    // A poisoned lock only means another thread panicked while holding it; the cache is
    // still consistent (entries are inserted whole).
    let mut guard = POOLS.lock().unwrap_or_else(|p| p.into_inner());
    let pools = pools(&mut guard, pid);
    if pools.member_taken {
        return None;
    }
    pools.member_taken = true;
    // This thread becomes worker 0 (an error: it already works for another pool).
    let pool: &'static ThreadPool =
        Box::leak(Box::new(builder(num_threads).use_current_thread().build().ok()?));
    MEMBER_OF.set(Some((pid, num_threads, pool)));
    Some(pool)
}

/// The shared pool of `num_threads` workers, for calls from any thread.
fn shared(num_threads: usize) -> Arc<ThreadPool> {
    let mut guard = POOLS.lock().unwrap_or_else(|p| p.into_inner());
    shared_pool(pools(&mut guard, std::process::id()), num_threads)
}

/// Runs `f` on a pool of `num_threads` workers (at least one).
pub fn with_threads<R: Send>(num_threads: usize, f: impl FnOnce() -> R + Send) -> R {
    let n = num_threads.max(1);
    match member_pool(n) {
        Some(pool) => pool.install(f),
        None => shared(n).install(f),
    }
}
