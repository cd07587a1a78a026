"""A fit's memory, estimated before anything is built, and the memory this process may
use: a request that cannot fit is refused with the estimate instead of dying in an
allocation."""

from __future__ import annotations

from urhead._memory import available_memory_bytes
from urhead.config import FitConfig
from urhead.errors import SizeLimitError
from urhead.model.map_layout import MapLayout

MAP_COPIES = 3
"""The UV maps live three times over a fit: the maps and Adam's two moments (the map
gradient is sparse)."""

OVERHEAD_BYTES = 1 << 30
"""Everything else (torch, renders at 512²), measured well under 1 GiB. Decoded frames
are cached within a quarter of the memory available when the subject is opened
(:func:`urhead.data.reader.default_cache_bytes`)."""


def fit_memory_bytes(config: FitConfig) -> int:
    """Bytes a fit with ``config`` needs at least: the float32 maps, ``MAP_COPIES`` times."""
    layout = MapLayout(
        config.sh_degree,
        config.gaussians,
        offsets=config.gaussians and config.gaussian_offset,
        shading=config.shading,
    )
    return MAP_COPIES * config.uv_resolution**2 * layout.channels * 4 + OVERHEAD_BYTES


def check_fit_memory(config: FitConfig, available: int | None = None) -> None:
    """Raises :class:`SizeLimitError` naming ``--uv-resolution`` and the estimate when the
    fit needs more memory than ``available`` (default: :func:`available_memory_bytes`)."""
    available = available_memory_bytes() if available is None else available
    needed = fit_memory_bytes(config)
    if available is not None and needed > available:
        raise SizeLimitError(
            f"--uv-resolution {config.uv_resolution}: the fit needs about {needed / 2**30:.1f} "
            f"GiB ({MAP_COPIES} copies of {config.uv_resolution}² maps), more than the "
            f"{available / 2**30:.1f} GiB available; use a smaller --uv-resolution"
        )
