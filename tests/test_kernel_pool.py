"""The kernels' thread pools (rust/urhead-py/src/pool.rs): the first thread of a process to
call in runs its calls itself as a member of its pool; every other thread, thread count and
forked child uses the shared pools. Whichever runs a call, its result is the same bits.

Each scenario runs in a fresh interpreter, so which thread calls first is known."""

from __future__ import annotations

import subprocess
import sys
import textwrap

SCRIPT = textwrap.dedent(
    """
    import multiprocessing as mp, os, threading
    import torch
    torch.set_num_threads(1)
    from urhead.ops import covered_pixels, scatter_pixels

    def work(threads):
        os.environ["URHEAD_NUM_THREADS"] = str(threads)
        g = torch.Generator().manual_seed(7)
        tri_id = torch.randint(-1, 9, (512, 512), generator=g, dtype=torch.int32)
        pixels = covered_pixels(tri_id)
        values = torch.randn(pixels.shape[0], 3, generator=g).requires_grad_()
        background = torch.randn(4, generator=g).requires_grad_()
        image = scatter_pixels(values, pixels, background, (512, 512), fill=torch.ones(1))
        (image * torch.randn(image.shape, generator=g)).sum().backward()
        return [pixels, image.detach(), values.grad, background.grad]

    def same(a, b):
        return all(torch.equal(x.view(torch.int32) if x.is_floating_point() else x,
                               y.view(torch.int32) if y.is_floating_point() else y)
                   for x, y in zip(a, b, strict=True))

    first = work(FIRST)  # this (main) thread's first call: it joins a pool of FIRST threads
    results = {}
    def from_thread(i):
        results[i] = [work(t) for t in (1, 2, 3)]
    side = [threading.Thread(target=from_thread, args=(i,)) for i in range(2)]
    for t in side:
        t.start()
    here = [work(t) for t in (1, 2, 3, FIRST)]  # concurrently with the side threads
    for t in side:
        t.join()
    assert all(same(r, first) for r in here), "main thread"
    assert all(same(r, first) for rs in results.values() for r in rs), "other threads"

    def child(queue):
        queue.put(all(same(work(t), first) for t in (FIRST, 1, 3)))
    ctx = mp.get_context("fork")
    queue = ctx.Queue()
    proc = ctx.Process(target=child, args=(queue,))
    proc.start()
    assert queue.get(timeout=120), "forked child"
    proc.join(timeout=60)
    assert proc.exitcode == 0
    print("ok")
    """
)


def _run(first_threads: int) -> None:
    script = SCRIPT.replace("FIRST", str(first_threads))
    out = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=300
    )
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr[-2000:]


def test_member_pool_of_two_threads_same_bits_everywhere():
    _run(2)


def test_member_pool_of_one_thread_same_bits_everywhere():
    _run(1)
