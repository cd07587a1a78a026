//! Large output buffers. A fresh multi-megabyte allocation is mapped lazily, and touching
//! it costs one page fault per 4 KiB page — on a virtual machine that can cost more than
//! the kernel writing the buffer (measured: 116 MB written fresh in ~70 ms with 4 KiB
//! pages, ~22 ms with 2 MiB pages). So large buffers ask for transparent huge pages before
//! their first touch. Buffers sized by a caller's input are allocated fallibly, so a request
//! too large for memory is an error the caller sees, never an abort.

use std::alloc::Layout;
use std::marker::PhantomData;
use std::mem::MaybeUninit;

use rayon::prelude::*;

use crate::error::{Error, Result};

/// Buffers at least this large (bytes) are advised to use huge pages.
const HUGE_PAGE_THRESHOLD: usize = 4 << 20;
const HUGE_PAGE: usize = 2 << 20;

/// Element types whose all-zero bit pattern is a valid value equal to their zero: plain
/// integers and IEEE floats. Sealed, so `zeroed` can never hand out zero bytes as a type
/// for which they would be invalid (references, enums, `NonZero*`).
pub trait ZeroBits: sealed::Sealed + Copy {}

mod sealed {
    pub trait Sealed {}
}

macro_rules! zero_bits {
    ($($t:ty),*) => {$(
        impl sealed::Sealed for $t {}
        impl ZeroBits for $t {}
    )*};
}
zero_bits!(f32, f64, i8, i16, i32, i64, u8, u16, u32, u64, usize, isize);

/// `len` zeros named `what` (the name goes into the error). `Err(OutOfMemory)` when the
/// byte count overflows or the allocator refuses, instead of aborting the process.
///
/// Where the zeros come from:
/// - small buffers, and buffers made outside a kernel pool: `alloc_zeroed` (`calloc`);
/// - from [`PARALLEL_ZEROING`] up to [`FRESH_PAGES`], on a pool's thread: an uninitialised
///   block, zeroed by the pool's threads. glibc clears a reused heap block (the command
///   line keeps freed memory, so nearly every output is one) with a serial `memset` on the
///   calling thread while the pool's other workers wait: ~5 % of a 512² frame's CPU time;
/// - larger buffers: `calloc` again, which gets fresh zero pages from the kernel and writes
///   nothing (a sparse accumulator then only faults in the pages it touches).
///
/// Buffers of 4 MiB and more are advised to be huge pages before anything touches them.
pub fn zeroed<T: ZeroBits>(what: &'static str, len: usize) -> Result<Vec<T>> {
    let out_of_memory = || Error::OutOfMemory {
        what,
        elements: len,
        bytes: len as u128 * std::mem::size_of::<T>() as u128,
    };
    let layout = Layout::array::<T>(len).map_err(|_| out_of_memory())?;
    let bytes = layout.size();
    if bytes == 0 {
        return Ok(Vec::new());
    }
    let parallel =
        (PARALLEL_ZEROING..FRESH_PAGES).contains(&bytes) && rayon::current_thread_index().is_some();
    // SAFETY: `layout` has a non-zero size, as both allocation functions require.
    let ptr = unsafe {
        if parallel {
            std::alloc::alloc(layout)
        } else {
            std::alloc::alloc_zeroed(layout)
        }
    };
    if ptr.is_null() {
        return Err(out_of_memory());
    }
    advise_huge_pages_of(ptr as usize, bytes);
    if parallel {
        // SAFETY: the `bytes` bytes at `ptr` are one live allocation that nothing else
        // references yet; writing bytes (`u8` has no invalid values) needs no prior init.
        let raw = unsafe { std::slice::from_raw_parts_mut(ptr, bytes) };
        raw.par_chunks_mut(ZEROING_CHUNK).for_each(|chunk| chunk.fill(0));
    }
    // SAFETY: `ptr` is a live allocation from the global allocator with exactly the layout
    // `Vec<T>` uses for capacity `len` (`Layout::array::<T>(len)`), so the Vec may own and
    // later free it. All `len` elements are initialised: the bytes are zero and `T: ZeroBits`
    // guarantees all-zero bytes are a valid `T`.
    Ok(unsafe { Vec::from_raw_parts(ptr.cast::<T>(), len, len) })
}

/// Buffers at least this large (bytes) are zeroed by the pool's threads (see [`zeroed`]).
const PARALLEL_ZEROING: usize = 256 << 10;
/// Buffers at least this large (bytes) are left to `calloc`'s fresh zero pages: glibc maps
/// blocks this large afresh (32 MiB is its largest mmap threshold, the one the command line
/// sets), so no zeroing pass runs for them.
const FRESH_PAGES: usize = 32 << 20;
/// Bytes zeroed per parallel task.
const ZEROING_CHUNK: usize = 64 << 10;

/// [`zeroed`] for a long-lived table, on fresh huge pages made resident by a first write
/// each. Two ways a table would otherwise miss them:
/// - its memory can be reused heap memory already backed by 4 KiB pages (with the command
///   line's `keep_freed_memory`, glibc serves even a 64 MiB block from the freed heap): the
///   advised whole 2 MiB pages are given back first (`MADV_DONTNEED`; they read as zeros
///   again), so they are faulted afresh;
/// - a table read before it is written (an Adam moment: the step reads a row, then writes
///   it) would first map the kernel's shared huge zero page and copy it on the write, a
///   fault that under memory pressure falls back to 4 KiB pages where a first write still
///   compacts for a huge page.
///
/// The table is resident at once: meant for tables a fit touches nearly everywhere anyway.
pub fn zeroed_resident<T: ZeroBits>(what: &'static str, len: usize) -> Result<Vec<T>> {
    let mut buf: Vec<T> = zeroed(what, len)?;
    let Some((start, end)) = huge_page_range(&buf) else {
        return Ok(buf);
    };
    discard_pages(start, end - start);
    let base = buf.as_mut_ptr().cast::<u8>();
    for offset in (start - base as usize..end - base as usize).step_by(HUGE_PAGE) {
        // SAFETY: `offset` lies inside the buffer; the byte reads as zero (calloc, or a
        // discarded page), and a volatile write of zero keeps it so while making the kernel
        // fault the page in.
        unsafe { base.add(offset).write_volatile(0) };
    }
    Ok(buf)
}

/// `len` copies of `value` named `what`, reserved with `try_reserve_exact`:
/// `Err(OutOfMemory)` instead of an abort when the allocator refuses. For fill values other
/// than zero; zeros should come from [`zeroed`].
pub fn filled<T: Clone>(what: &'static str, len: usize, value: T) -> Result<Vec<T>> {
    let mut buf = Vec::new();
    refill(&mut buf, what, len, value)?;
    Ok(buf)
}

/// Makes `buf` `len` copies of `value`, reusing its memory: a buffer kept across calls
/// costs no page faults once grown. Grows with `try_reserve_exact`, so `Err(OutOfMemory)`
/// instead of an abort when the allocator refuses.
pub fn refill<T: Clone>(buf: &mut Vec<T>, what: &'static str, len: usize, value: T) -> Result<()> {
    buf.clear();
    reserve_exact(buf, what, len)?;
    buf.resize(len, value);
    advise_huge_pages(buf);
    Ok(())
}

/// Room for `additional` more elements in `buf` (`try_reserve_exact`): `Err(OutOfMemory)`
/// naming `what` instead of an abort when the allocator refuses.
fn reserve_exact<T>(buf: &mut Vec<T>, what: &'static str, additional: usize) -> Result<()> {
    buf.try_reserve_exact(additional).map_err(|_| Error::OutOfMemory {
        what,
        elements: additional,
        bytes: additional as u128 * std::mem::size_of::<T>() as u128,
    })
}

/// Asks the kernel to back the whole 2 MiB pages inside `buf` with huge pages. Only
/// advice: a no-op for small buffers, on other systems, or if the kernel declines.
pub fn advise_huge_pages<T>(buf: &[T]) {
    advise_huge_pages_of(buf.as_ptr() as usize, std::mem::size_of_val(buf));
}

/// [`advise_huge_pages`] for the `bytes` bytes at address `base` (memory not yet written).
fn advise_huge_pages_of(base: usize, bytes: usize) {
    if let Some((start, end)) = huge_page_range_of(base, bytes) {
        madvise_huge(start, end - start);
    }
}

/// The address range of the whole 2 MiB pages inside `buf`, for buffers large enough to
/// advise; None otherwise.
fn huge_page_range<T>(buf: &[T]) -> Option<(usize, usize)> {
    huge_page_range_of(buf.as_ptr() as usize, std::mem::size_of_val(buf))
}

/// [`huge_page_range`] of the `bytes` bytes at address `base`.
fn huge_page_range_of(base: usize, bytes: usize) -> Option<(usize, usize)> {
    if bytes < HUGE_PAGE_THRESHOLD {
        return None;
    }
    let start = base.next_multiple_of(HUGE_PAGE);
    let end = (base + bytes) / HUGE_PAGE * HUGE_PAGE;
    (end > start).then_some((start, end))
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

#[cfg(target_os = "linux")]
fn discard_pages(start: usize, len: usize) {
    // SAFETY: the range lies inside one live allocation owned by the caller, holding only
    // zeros, in private anonymous memory (glibc's heap or its mmapped blocks): after
    // MADV_DONTNEED its pages read as zeros again, so the contents do not change. Its
    // failure is harmless (the pages stay as they were).
    unsafe {
        libc::madvise(start as *mut libc::c_void, len, libc::MADV_DONTNEED);
    }
}

#[cfg(not(target_os = "linux"))]
fn discard_pages(_start: usize, _len: usize) {}

/// A copy of `src` named `what`, copied in parallel chunks into memory that is never
/// zeroed first (a kernel that starts from its input image and edits a few pixels: a
/// `zeroed` buffer then a serial copy was two serial passes over the image).
/// `Err(OutOfMemory)` when the allocator refuses.
pub fn copied<T: Copy + Send + Sync>(what: &'static str, src: &[T]) -> Result<Vec<T>> {
    const CHUNK: usize = 32 << 10;
    let mut buf: Vec<T> = Vec::new();
    reserve_exact(&mut buf, what, src.len())?;
    advise_huge_pages_of(buf.as_ptr() as usize, std::mem::size_of_val(src));
    buf.spare_capacity_mut()[..src.len()]
        .par_chunks_mut(CHUNK)
        .zip(src.par_chunks(CHUNK))
        .for_each(|(dst, src)| {
            for (d, s) in dst.iter_mut().zip(src) {
                d.write(*s);
            }
        });
    // SAFETY: the capacity is at least `src.len()` and the chunks above wrote every one of
    // the first `src.len()` elements.
    unsafe { buf.set_len(src.len()) };
    Ok(buf)
}

/// The `parts` one after another, each copied into its place in parallel (a serial
/// `concat` of a step's ~420k texel entries left the pool's other worker idle).
/// `Err(OutOfMemory)` when the allocator refuses.
pub fn concatenated<T: Copy + Send + Sync>(what: &'static str, parts: &[Vec<T>]) -> Result<Vec<T>> {
    let total: usize = parts.iter().map(Vec::len).sum();
    let mut buf: Vec<T> = Vec::new();
    reserve_exact(&mut buf, what, total)?;
    let mut places = Vec::with_capacity(parts.len());
    let mut rest = &mut buf.spare_capacity_mut()[..total];
    for part in parts {
        let (place, tail) = rest.split_at_mut(part.len());
        places.push(place);
        rest = tail;
    }
    places.into_par_iter().zip(parts).for_each(|(place, part)| {
        for (d, s) in place.iter_mut().zip(part) {
            d.write(*s);
        }
    });
    // SAFETY: the capacity is at least `total`, and the places, which partition its first
    // `total` elements, were each written whole from their part of the same length.
    unsafe { buf.set_len(total) };
    Ok(buf)
}

/// Room for `len` elements named `what`, none written yet: for a kernel output whose every
/// element the kernel writes (through [`Slot`]), which a [`zeroed`] buffer would first
/// have zeroed in a pass of its own — the zero stores alone cost what a light kernel's
/// writes do (a step's 17 MB pixel gradient: 1.72 → 1.28 ms without them).
/// `Err(OutOfMemory)` when the allocator refuses.
pub fn unwritten<T>(what: &'static str, len: usize) -> Result<Vec<MaybeUninit<T>>> {
    let mut buf = Vec::new();
    reserve_exact(&mut buf, what, len)?;
    advise_huge_pages_of(buf.as_ptr() as usize, len * std::mem::size_of::<T>());
    // SAFETY: the capacity is at least `len`, and `MaybeUninit` needs no initialisation.
    unsafe { buf.set_len(len) };
    // The unit tests see every element a kernel fails to write: all-ones bytes are NaN
    // (a float's), −1 (an integer's), never the zero a reused block often holds.
    #[cfg(test)]
    // SAFETY: bytes written into the buffer's own `MaybeUninit` elements.
    unsafe {
        std::ptr::write_bytes(buf.as_mut_ptr(), 0xFF, len)
    };
    Ok(buf)
}

/// An [`unwritten`] buffer, now written.
///
/// # Safety
/// Every element of `buf` has been written.
pub unsafe fn assume_written<T>(buf: Vec<MaybeUninit<T>>) -> Vec<T> {
    let mut buf = std::mem::ManuallyDrop::new(buf);
    // SAFETY: every element is initialised (the caller's contract); the pointer, length
    // and capacity are the Vec's own, and `MaybeUninit<T>` has `T`'s layout.
    unsafe { Vec::from_raw_parts(buf.as_mut_ptr().cast::<T>(), buf.len(), buf.capacity()) }
}

/// A part of an [`unwritten`] buffer, now written, to read back.
///
/// # Safety
/// Every element of `part` has been written.
pub unsafe fn written_part<T>(part: &[MaybeUninit<T>]) -> &[T] {
    // SAFETY: every element is initialised (the caller's contract), and `[MaybeUninit<T>]`
    // has `[T]`'s layout.
    unsafe { &*(part as *const [MaybeUninit<T>] as *const [T]) }
}

/// Zeros written over `part` of an [`unwritten`] buffer (the elements a kernel leaves at
/// zero: a lookup off the texture, the channels past a row's colour).
#[inline(always)]
pub fn write_zeros<T: crate::Real>(part: &mut [MaybeUninit<T>]) {
    part.fill(MaybeUninit::new(T::zero()));
}

/// Where a kernel puts an output value: an element of a written buffer, or of an
/// [`unwritten`] one. The same kernel code then writes either.
pub trait Slot<T>: Sized {
    fn set(&mut self, value: T);
}

impl<T> Slot<T> for T {
    #[inline(always)]
    fn set(&mut self, value: T) {
        *self = value;
    }
}

impl<T> Slot<T> for MaybeUninit<T> {
    #[inline(always)]
    fn set(&mut self, value: T) {
        self.write(value);
    }
}

/// A slice several threads write at once, each index by exactly one of them: the scatter
/// of a parallel counting sort, whose destinations are disjoint by construction but not
/// contiguous per thread (so the slice cannot be split into `&mut` parts).
pub struct DisjointWrites<'a, T> {
    ptr: *mut T,
    len: usize,
    _slice: PhantomData<&'a mut [T]>,
}

// SAFETY: the wrapper only hands out writes of `T` values to distinct indices (the
// caller's guarantee, see `write`), which is what sending `T`s to those threads means.
unsafe impl<T: Send> Send for DisjointWrites<'_, T> {}
// SAFETY: as above; shared access only writes, and never twice to one index.
unsafe impl<T: Send> Sync for DisjointWrites<'_, T> {}

impl<'a, T> DisjointWrites<'a, T> {
    pub fn new(slice: &'a mut [T]) -> Self {
        Self {
            ptr: slice.as_mut_ptr(),
            len: slice.len(),
            _slice: PhantomData,
        }
    }

    /// `slice[index] = value`; an index out of range panics.
    ///
    /// # Safety
    /// No other thread reads or writes `index` while the wrapper lives.
    #[inline(always)]
    pub unsafe fn write(&self, index: usize, value: T) {
        assert!(index < self.len, "index {index} out of {}", self.len);
        // SAFETY: in bounds (checked), the slice is borrowed mutably for `'a`, and no
        // other thread touches this index (the caller's contract).
        unsafe { self.ptr.add(index).write(value) };
    }
}

/// `dst[..n] = src[..n]` element by element, for rows of a handful of elements (a
/// pixel's channels): `copy_from_slice` of a length unknown at compile time is a
/// `memcpy` call, which costs more than the copy when done once per pixel.
#[inline(always)]
pub fn copy_short<T: Copy, O: Slot<T>>(dst: &mut [O], src: &[T], n: usize) {
    for (d, s) in dst[..n].iter_mut().zip(&src[..n]) {
        d.set(*s);
    }
}

/// Hints the CPU to start loading the cache lines of `data` (random-access kernels issue
/// it a few items ahead, so several memory reads overlap).
///
/// The lines go to L2 (`T1`), not L1 (`T0`): a random-access kernel has dozens of lines in
/// flight (Adam's 8 rows ahead are ~70), more than L1's miss buffers hold (our reading of
/// why; the gain itself is measured). Measured on the development machine
/// (AMD EPYC, 2 cores), `T0` → `T1`: the paper's iteration 108–115 → 101–106 ms in 4
/// process pairs (CPU −12 ms), its sparse Adam step ~−2.5 ms, the texture lookups −15 to
/// −20 %; `T2` is `T1` on this CPU, `NTA` no gain. On an Intel Ice Lake host the two
/// hints measured the same (the texture lookups and the Adam step within noise).
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
                std::arch::x86_64::_mm_prefetch::<{ std::arch::x86_64::_MM_HINT_T1 }>(line as *const i8);
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
    fn concatenated_parts_are_the_serial_concat() {
        let parts: Vec<Vec<u64>> = [0usize, 5, 0, 70_000, 1, 33]
            .iter()
            .enumerate()
            .map(|(k, &n)| (0..n as u64).map(|i| i * 7 + k as u64).collect())
            .collect();
        for threads in [1, 2, 3] {
            let joined = crate::testing::on_threads(threads, || concatenated("test parts", &parts).unwrap());
            assert_eq!(joined, parts.concat());
        }
        assert!(concatenated::<u8>("no parts", &[]).unwrap().is_empty());
    }

    #[test]
    fn zeroed_buffers_are_zero_whatever_their_size() {
        for len in [0usize, 7, 3 << 20] {
            let v: Vec<f32> = zeroed("test buffer", len).unwrap();
            assert_eq!(v.len(), len);
            assert!(v.iter().all(|&x| x == 0.0));
        }
    }

    #[test]
    fn zeroed_buffers_are_zero_on_a_pool_whatever_their_size() {
        // On a pool's thread the middle sizes are zeroed by the pool, not by calloc; memory
        // freed dirty just before is likely handed out again, and must read as zeros.
        let pool = rayon::ThreadPoolBuilder::new().num_threads(2).build().unwrap();
        pool.install(|| {
            let bytes = [
                PARALLEL_ZEROING - 4,
                PARALLEL_ZEROING,
                (3 << 20) + 12,
                FRESH_PAGES + 4,
            ];
            for len in bytes.map(|b| b / 4) {
                drop(vec![-3.25f32; len]);
                let v: Vec<f32> = zeroed("test buffer", len).unwrap();
                assert_eq!(v.len(), len);
                assert!(v.iter().all(|x| x.to_bits() == 0), "{len} elements");
            }
        });
    }

    #[test]
    fn copies_are_equal_whatever_their_size() {
        for len in [0usize, 7, (32 << 10) + 3, 3 << 20] {
            let src: Vec<f32> = (0..len).map(|i| i as f32 * 0.5 - 7.0).collect();
            assert_eq!(copied("test copy", &src).unwrap(), src);
        }
    }

    #[test]
    fn resident_zeroed_buffers_are_zero_whatever_their_size() {
        for len in [0usize, 7, 3 << 20, (9 << 20) + 5] {
            // Memory freed dirty just before may be handed out again: still all zeros.
            drop(vec![1.5f32; len]);
            let v: Vec<f32> = zeroed_resident("test buffer", len).unwrap();
            assert_eq!(v.len(), len);
            assert!(v.iter().all(|&x| x == 0.0));
        }
    }

    #[test]
    fn zeroed_refuses_a_size_the_allocator_cannot_give() {
        // 2^61 f32 = 8 EiB: a valid layout, but no machine can map it.
        let len = usize::MAX / 8;
        let err = zeroed::<f32>("huge map", len).unwrap_err();
        assert_eq!(
            err,
            Error::OutOfMemory {
                what: "huge map",
                elements: len,
                bytes: len as u128 * 4
            }
        );
        assert!(err.to_string().contains("huge map"), "{err}");
    }

    #[test]
    fn zeroed_refuses_a_byte_count_that_overflows() {
        let len = usize::MAX / 2;
        let err = zeroed::<f64>("overflowing map", len).unwrap_err();
        let Error::OutOfMemory { bytes, .. } = err else {
            panic!("expected OutOfMemory, got {err:?}");
        };
        assert!(bytes > usize::MAX as u128);
    }

    #[test]
    fn filled_refuses_a_size_the_allocator_cannot_give() {
        let err = filled("huge fill", usize::MAX / 4, 1.0f32).unwrap_err();
        assert!(
            matches!(
                err,
                Error::OutOfMemory {
                    what: "huge fill",
                    ..
                }
            ),
            "{err:?}"
        );
        assert_eq!(filled("small fill", 3, -1i32).unwrap(), vec![-1, -1, -1]);
    }
}
