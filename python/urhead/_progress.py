"""Progress for long commands: a tqdm bar on a terminal, and plain lines at most every
``interval`` seconds when the stream is a file or a pipe (a log file then holds a few
readable lines instead of thousands of ``\\r`` updates)."""

from __future__ import annotations

import sys
import time
from collections.abc import Iterable, Iterator
from typing import TextIO, TypeVar

T = TypeVar("T")

PLAIN_INTERVAL_SECONDS = 10.0


class PlainProgress:
    """``desc: 30/90 frames (33 %), 45 s, ~90 s left`` lines, the first after the first
    step, then at most one per ``interval`` seconds, and the last when the count reaches
    the total or the progress is closed."""

    def __init__(
        self, total: int, desc: str, unit: str, stream: TextIO, interval: float, initial: int = 0
    ):
        self.total, self.desc, self.unit = total, desc, unit
        self.stream, self.interval = stream, interval
        self.count = self._initial = initial
        self.postfix = ""
        self._start = time.monotonic()
        self._printed_at: float | None = None
        self._printed_count = initial

    def set_description(self, desc: str) -> None:
        self.desc = desc

    def set_postfix(self, **values) -> None:
        """Shown at the end of the next line, as tqdm shows its postfix."""
        self.postfix = ", ".join(f"{k}={v}" for k, v in values.items())

    def update(self, n: int = 1) -> None:
        self.count += n
        now = time.monotonic()
        due = self._printed_at is None or now - self._printed_at >= self.interval
        if due or self.count >= self.total:
            self._print(now)

    def close(self) -> None:
        if self.count != self._printed_count:
            self._print(time.monotonic())

    def _print(self, now: float) -> None:
        elapsed = now - self._start
        line = f"{self.desc}: {self.count}/{self.total} {self.unit}s"
        if self.total > 0:
            line += f" ({100 * self.count / self.total:.0f} %)"
        line += f", {elapsed:.0f} s"
        done = self.count - self._initial
        if done > 0 and self.count < self.total:
            line += f", ~{elapsed / done * (self.total - self.count):.0f} s left"
        if self.postfix:
            line += f" ({self.postfix})"
        print(line, file=self.stream, flush=True)
        self._printed_at, self._printed_count = now, self.count

    def __enter__(self) -> PlainProgress:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class _Silent:
    def update(self, n: int = 1) -> None:
        pass

    def set_description(self, desc: str) -> None:
        pass

    def set_postfix(self, **values) -> None:
        pass

    def close(self) -> None:
        pass

    def __enter__(self) -> _Silent:
        return self

    def __exit__(self, *exc) -> None:
        pass


def progress(
    total: int,
    desc: str,
    unit: str = "frame",
    *,
    enabled: bool = True,
    stream: TextIO | None = None,
    interval: float = PLAIN_INTERVAL_SECONDS,
    initial: int = 0,
):
    """A context manager with ``update(n=1)``: tqdm when ``stream`` (default stderr) is a
    terminal, :class:`PlainProgress` otherwise, nothing when not ``enabled``."""
    stream = sys.stderr if stream is None else stream
    if not enabled:
        return _Silent()
    if stream.isatty():
        from tqdm import tqdm

        return tqdm(total=total, desc=desc, unit=unit, file=stream, initial=initial)
    return PlainProgress(total, desc, unit, stream, interval, initial)


def tracked(
    items: Iterable[T], total: int, desc: str, unit: str = "frame", **kwargs
) -> Iterator[T]:
    """Yields ``items``, reporting each one as done when the next is asked for."""
    with progress(total, desc, unit, **kwargs) as bar:
        for item in items:
            yield item
            bar.update(1)
