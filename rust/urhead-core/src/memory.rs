//! Large output buffers. A fresh multi-megabyte allocation is mapped lazily, and touching
//! it costs one page fault per 4 KiB page — on a virtual machine that can cost more than
//! the kernel writing the buffer (measured: 116 MB written fresh in ~70 ms with 4 KiB
//! pages, ~22 ms with 2 MiB pages). So large buffers ask for transparent huge pages before
//! their first touch.

/// Buffers at least this large (bytes) are advised to use huge pages.
const HUGE_PAGE_THRESHOLD: usize = 4 << 20;
const HUGE_PAGE: usize = 2 << 20;

/// `len` default values (zeros). For primitive numbers the allocation is `calloc`-backed:
/// large buffers are fresh zero pages, advised to be huge pages before anything touches
/// them, and no zeroing pass runs.
pub fn zeroed<T: Clone + Default>(len: usize) -> Vec<T> {
    let v = vec![T::default(); len];
    advise_huge_pages(&v);
    v
}

/// Asks the kernel to back the whole 2 MiB pages inside `buf` with huge pages. Only
/// advice: a no-op for small buffers, on other systems, or if the kernel declines.
pub fn advise_huge_pages<T>(buf: &[T]) {
    let bytes = std::mem::size_of_val(buf);
    if bytes < HUGE_PAGE_THRESHOLD {
        return;
    }
    let start = (buf.as_ptr() as usize).next_multiple_of(HUGE_PAGE);
    let end = (buf.as_ptr() as usize + bytes) / HUGE_PAGE * HUGE_PAGE;
    if end > start {
        madvise_huge(start, end - start);
    }
}

#[cfg(target_os = "linux")]
fn madvise_huge(start: usize, len: usize) {
    // SAFETY: the range lies inside one live allocation owned by the caller's slice and is
    // page-aligned; MADV_HUGEPAGE only changes how the kernel backs the pages, never their
    // contents, and its failure is harmless.
    unsafe {
        libc::madvise(start as *mut libc::c_void, len, libc::MADV_HUGEPAGE);
    }
}

#[cfg(not(target_os = "linux"))]
fn madvise_huge(_start: usize, _len: usize) {}

/// Hints the CPU to start loading the cache lines of `data` (random-access kernels issue
/// it a few items ahead, so several memory reads overlap).
#[inline(always)]
pub fn prefetch<T>(data: &[T]) {
    #[cfg(target_arch = "x86_64")]
    {
        let start = data.as_ptr() as usize;
        let end = start + std::mem::size_of_val(data);
        let mut line = start & !63;
        while line < end {
            // SAFETY: a prefetch is only a hint; it never faults, even on a bad address, and
            // here the address is inside `data`.
            unsafe {
                std::arch::x86_64::_mm_prefetch::<{ std::arch::x86_64::_MM_HINT_T0 }>(line as *const i8);
            }
            line += 64;
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = data;
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn zeroed_buffers_are_zero_whatever_their_size() {
        for len in [0usize, 7, 3 << 20] {
            let v: Vec<f32> = zeroed(len);
            assert_eq!(v.len(), len);
            assert!(v.iter().all(|&x| x == 0.0));
        }
    }
}
