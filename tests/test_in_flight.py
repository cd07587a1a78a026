"""urhead._in_flight: frames a few at a time, in order, with the same results as one after
another — for plain functions with uneven durations and for an avatar's renders from several
cameras at once (its kept pixel rays, maps copy and rows shared between the threads)."""

from __future__ import annotations

import math
import sys
import threading
import time

import numpy as np
import pytest
import torch

from urhead._in_flight import default_depth, in_flight
from urhead.camera import Camera
from urhead.model import load_avatar
from use_avatar import make_use_avatar


class Recorder:
    """A function of uneven duration that records how many of its calls overlap."""

    def __init__(self):
        self.lock = threading.Lock()
        self.running = 0
        self.most = 0
        self.started: list[int] = []
        self.finished: list[int] = []
        self.running_at_start: dict[int, int] = {}

    def __call__(self, x: int) -> int:
        with self.lock:
            self.running += 1
            self.most = max(self.most, self.running)
            self.started.append(x)
            self.running_at_start[x] = self.running
        time.sleep(0.002 * ((7 * x) % 5))  # later items often finish first
        with self.lock:
            self.running -= 1
            self.finished.append(x)
        return x * x


@pytest.mark.parametrize("depth", [1, 2, 3, 5])
def test_results_come_in_order_with_at_most_depth_calls_at_once(depth):
    fn = Recorder()
    assert list(in_flight(fn, range(23), depth)) == [x * x for x in range(23)]
    assert sorted(fn.finished) == list(range(23))
    assert fn.most <= depth
    if depth > 1:
        assert fn.most > 1  # they did overlap
    # the first call ran alone: nothing else had started before it finished
    assert fn.running_at_start[0] == 1 and fn.started.index(1) > fn.finished.index(0)


def test_empty_and_single_sequences():
    assert list(in_flight(lambda x: x, [], 3)) == []
    assert list(in_flight(lambda x: x + 1, [4], 3)) == [5]


def test_the_callers_autograd_mode_holds_in_the_workers():
    def mode(_):
        return torch.is_grad_enabled()

    with torch.no_grad():
        assert list(in_flight(mode, range(6), 3)) == [False] * 6
    assert list(in_flight(mode, range(6), 3)) == [True] * 6


def test_an_error_is_raised_at_its_item_and_stops_the_rest():
    started = []

    def fn(x):
        started.append(x)
        if x == 4:
            raise RuntimeError("bad frame 4")
        time.sleep(0.001)
        return x

    got = []
    with pytest.raises(RuntimeError, match="bad frame 4"):
        for y in in_flight(fn, range(100), 3):
            got.append(y)
    assert got == [0, 1, 2, 3]
    assert max(started) < 4 + 3 + 1  # no call started beyond what was in flight


def test_closing_early_waits_for_the_started_calls_and_starts_no_more():
    fn = Recorder()
    results = in_flight(fn, range(50), 3)
    assert [next(results) for _ in range(4)] == [0, 1, 4, 9]
    results.close()
    assert fn.running == 0  # every started call has finished
    started = len(fn.started)
    time.sleep(0.02)
    assert len(fn.started) == started <= 4 + 3


@pytest.mark.parametrize("depth", [0, -1, 1.5, True, "2"])
def test_depth_must_be_a_positive_int(depth):
    with pytest.raises(ValueError, match="depth"):
        list(in_flight(lambda x: x, range(3), depth))


def test_default_depth_is_one_more_than_the_kernel_threads(monkeypatch):
    monkeypatch.setenv("URHEAD_NUM_THREADS", "2")
    assert default_depth() == 3


@pytest.fixture(scope="module")
def use(tmp_path_factory):
    return make_use_avatar(tmp_path_factory.mktemp("in_flight"))


def test_an_avatars_renders_in_flight_are_those_rendered_one_after_another(use):
    """Views from four cameras of different sizes, alternating, rendered two and three at a
    time: each image is bit for bit the sequential render of its view (the kept pixel rays
    must follow each thread's camera; the frozen maps' float16 copy and kept rows are
    shared)."""
    avatar = load_avatar(use.avatar_dir)
    params = avatar.frame(0)
    with torch.no_grad():
        centre = avatar.skin(params)[0].mean(0).tolist()
    cameras = [
        Camera.look_at(
            [centre[0] + 0.3 * math.sin(a), centre[1], centre[2] + 0.6 * math.cos(a)],
            centre,
            width=40 + 8 * k,
            height=40 + 8 * k,
        )
        for k, a in enumerate(np.linspace(-0.6, 0.6, 4))
    ]
    views = [cameras[i % 4] for i in range(16)]

    def render(camera):
        return avatar.render(params, camera).image

    with torch.no_grad():
        expected = [render(c) for c in views]
        assert not torch.equal(expected[0][:40, :40], expected[1][:40, :40])
        interval = sys.getswitchinterval()
        sys.setswitchinterval(1e-6)  # threads swap often: a shared cache's races show
        try:
            for depth in (2, 3, 4):
                got = list(in_flight(render, views, depth))
                assert all(torch.equal(a, b) for a, b in zip(got, expected, strict=True))
        finally:
            sys.setswitchinterval(interval)
