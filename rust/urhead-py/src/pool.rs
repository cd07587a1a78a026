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
use std::sync::Mutex;

use rayon::{ThreadPool, ThreadPoolBuilder};

/// Pools live as long as the process (leaked): a call borrows one without a reference count,
/// and nothing drops a pool a thread still belongs to.
type Pool = &'static ThreadPool;

struct Pools {
    pid: u32,
    by_size: Vec<(usize, Pool)>,
    /// Whether a thread of this process has been made a member of a pool (see
    /// [`with_threads`]); at most one is, so such pools never accumulate.
    member_taken: bool,
}

static POOLS: Mutex<Option<Pools>> = Mutex::new(None);

thread_local! {
    /// The pool this thread is a member of: `(process id, thread count, pool)`.
    static MEMBER_OF: Cell<Option<(u32, usize, Pool)>> = const { Cell::new(None) };
}

fn builder(num_threads: usize) -> ThreadPoolBuilder {
    ThreadPoolBuilder::new()
        .num_threads(num_threads)
        .thread_name(|i| format!("urhead-{i}"))
}

/// The pool a call from this thread with `num_threads` runs on.
fn pool(num_threads: usize) -> Pool {
    let pid = std::process::id();
    let member = MEMBER_OF.get();
    if let Some((p, n, pool)) = member {
        if p == pid && n == num_threads {
            return pool; // no lock on the member's calls
        }
    }
    // A poisoned lock only means another thread panicked while holding it; the cache is
    // still consistent (entries are inserted whole).
    let mut guard = POOLS.lock().unwrap_or_else(|p| p.into_inner());
    if guard.as_ref().is_none_or(|p| p.pid != pid) {
        // A forked child: the parent's pools (leaked) have no threads here.
        *guard = Some(Pools {
            pid,
            by_size: Vec::new(),
            member_taken: false,
        });
    }
    let pools = guard.as_mut().expect("initialised above");
    if member.is_none() && !pools.member_taken {
        pools.member_taken = true;
        // This thread becomes worker 0 (an error: it already works for another pool).
        if let Ok(pool) = builder(num_threads).use_current_thread().build() {
            let pool: Pool = Box::leak(Box::new(pool));
            MEMBER_OF.set(Some((pid, num_threads, pool)));
            return pool;
        }
    }
    if let Some(&(_, pool)) = pools.by_size.iter().find(|(n, _)| *n == num_threads) {
        return pool;
    }
    let pool: Pool = Box::leak(Box::new(
        builder(num_threads)
            .build()
            .expect("spawning rayon worker threads"),
    ));
    pools.by_size.push((num_threads, pool));
    pool
}

/// Runs `f` on a pool of `num_threads` workers (at least one).
pub fn with_threads<R: Send>(num_threads: usize, f: impl FnOnce() -> R + Send) -> R {
    pool(num_threads.max(1)).install(f)
}
