"""Where Gaussians live: UV points on the atlas, drawn uniformly or in proportion to the
accumulated UV-space error (the paper's error-driven sampling, Sec. 3.3), and the fit's
sampling policy behind one seam (:class:`GaussianSampler`)."""

from __future__ import annotations

import logging
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import torch

from urhead.errors import InvalidArgumentError
from urhead.head.uv import UvLookup
from urhead.model.avatar import Avatar
from urhead.ops import accumulate_uv_error, texture

log = logging.getLogger("urhead.fit")


class UvSurface:
    """Draws UV points that lie on the atlas and locates their faces."""

    def __init__(self, uv_coords: np.ndarray, uv_faces: np.ndarray):
        self.lookup = UvLookup(uv_coords, uv_faces)

    def locate(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``uv`` (N, 2) → ``(face (N,) int64, bary (N, 3))``, face −1 off the atlas."""
        return self.lookup.locate(uv)

    def uniform(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """(n, 2) float32 points uniform over the atlas' UV area (rejection sampling)."""
        if n <= 0:
            return np.zeros((0, 2), np.float32)
        out = []
        have = 0
        while have < n:
            uv = rng.random((max(2 * (n - have), 64), 2))
            face, _ = self.locate(uv)
            hits = uv[face >= 0]
            out.append(hits)
            have += len(hits)
        return np.concatenate(out)[:n].astype(np.float32)


class ErrorAccumulator:
    """The visibility-normalised UV error w(u, v) = (1/N) Σ_t V·E_uv, on a G × G grid.

    Each rendered frame adds its per-pixel photometric error at the UV coordinate the pixel
    sees (the pixel is then a visible observation of that cell). Cells are coarser than the
    maps on purpose: a 512² image sees each 2048² texel rarely, and sampling needs a
    density, not a per-texel value.
    """

    def __init__(self, grid: int):
        self.grid = int(grid)
        self.error = torch.zeros(self.grid * self.grid, dtype=torch.float64)
        self.count = torch.zeros(self.grid * self.grid, dtype=torch.float64)

    def add(
        self,
        image: torch.Tensor,
        target: torch.Tensor,
        mask: torch.Tensor,
        pixels: torch.Tensor,
        uv: torch.Tensor,
    ) -> None:
        """Charges a frame's per-pixel error ‖I − I_gt‖₁ inside the mask to UV: a covered
        pixel at the UV it sees; a pixel inside the mask that the mesh misses (hair volume,
        a silhouette the mesh has not reached) at the UV of the nearest covered pixel, so
        that error draws Gaussians to the surface next to it.

        image, target: (H, W, 3); mask: (H, W); pixels: (P,) int64 flat indices of the
        covered pixels; uv: (P, 2) the UV each sees (see :func:`accumulate_uv_error`).
        """
        accumulate_uv_error(image, target, mask, pixels, uv, self.error, self.count)

    def start(self, image, target, mask, pixels, uv, worker: ThreadPoolExecutor) -> Future:
        """:meth:`add`'s charge begun on ``worker`` (the kernel runs without the GIL), into
        fresh grids that :meth:`commit` adds: ``0 + s`` is ``s``, so the grids come out bit
        for bit those of :meth:`add`. The tensors must not change until it is done."""
        return worker.submit(self._charge, image, target, mask, pixels, uv)

    def _charge(self, image, target, mask, pixels, uv) -> tuple[torch.Tensor, torch.Tensor]:
        error, count = torch.zeros_like(self.error), torch.zeros_like(self.count)
        accumulate_uv_error(image, target, mask, pixels, uv, error, count)
        return error, count

    def commit(self, charge: Future) -> None:
        """Adds a charge begun by :meth:`start` (its error, if any, is raised here)."""
        error, count = charge.result()
        self.error += error
        self.count += count

    def density(self) -> torch.Tensor:
        """(G·G,) normalised error per cell, 0 where never seen."""
        return torch.where(self.count > 0, self.error / self.count.clamp_min(1), 0.0)

    def sample(self, n: int, surface: UvSurface, rng: np.random.Generator) -> np.ndarray:
        """(≤ n, 2) float32 UV points drawn in proportion to the density, jittered
        uniformly inside their cell and kept when they land on the atlas."""
        w = self.density().numpy()
        total = w.sum()
        if n <= 0 or not total > 0:
            return np.zeros((0, 2), np.float32)
        cells = rng.choice(w.size, size=n, p=w / total)
        g = self.grid
        row, col = np.divmod(cells, g)
        jitter = rng.random((n, 2))
        uv = np.stack([(col + jitter[:, 0]) / g, 1 - (row + jitter[:, 1]) / g], 1)
        face, _ = surface.locate(uv)
        return uv[face >= 0].astype(np.float32)

    def reset(self) -> None:
        self.error.zero_()
        self.count.zero_()

    def state(self) -> dict:
        return {"error": self.error.clone(), "count": self.count.clone()}

    def load_state(self, state: dict) -> None:
        self.error.copy_(state["error"])
        self.count.copy_(state["count"])


def set_gaussians(avatar: Avatar, surface: UvSurface, uv: np.ndarray) -> np.ndarray:
    """Replaces the avatar's Gaussians by those at UV points ``uv`` (N, 2) on the atlas,
    ordered by 32-texel tile of the maps and then row-major inside it, so the lookups of
    neighbouring Gaussians hit the same cache lines of a 2048² map. Returns the order
    (N,): the new Gaussian i is ``uv[order[i]]``."""
    h, w = avatar.maps.shape[:2]
    col = np.clip((uv[:, 0] * w).astype(np.int64), 0, w - 1)
    row = np.clip(((1 - uv[:, 1]) * h).astype(np.int64), 0, h - 1)
    order = np.lexsort((col, row, col // 32, row // 32))
    uv = uv[order]
    face, bary = surface.locate(uv)
    if (face < 0).any():
        raise InvalidArgumentError("Gaussian UV points must lie on the atlas")
    avatar.gaussian_uv = torch.from_numpy(np.ascontiguousarray(uv, np.float32))
    avatar.gaussian_face = torch.from_numpy(face)
    avatar.gaussian_bary = torch.from_numpy(bary.astype(np.float32))
    return order


@dataclass(frozen=True)
class Observation:
    """A rendered frame's contribution to the sampler, begun before its step was judged:
    the UV error charge under way (None when the sampling is not adaptive) and the
    Gaussians' (N, 2) screen radii (None without Gaussians)."""

    charge: Future | None
    radii: torch.Tensor | None


class GaussianSampler:
    """The fit's Gaussian sampling policy, behind one seam (the pattern of gsplat's
    strategies): the trainer begins each rendered frame's observation before its step is
    judged (:meth:`start_observing`), applies it when the step is applied (:meth:`apply`;
    :meth:`observe` does both at once) and calls :meth:`step_end` after each iteration;
    the sampler owns its state (the UV error, each Gaussian's largest screen radius) and
    its checkpoint entries (:meth:`state`).

    Every ``sample_every`` iterations it prunes Gaussians that are faint
    (opacity < ``prune_opacity``) or grew too large on screen, then draws new ones in
    proportion to the UV error (``sampling="adaptive"``) or uniformly, at most
    ``sample_cap`` per round and ``max_gaussians`` in all.
    """

    def __init__(self, config, head, num_gaussians: int):
        self.config = config
        self.adaptive = bool(config.gaussians) and config.sampling == "adaptive"
        self.surface = UvSurface(head.uv_coords, head.uv_faces)
        self.accumulator = ErrorAccumulator(min(config.error_grid, config.uv_resolution))
        self.max_radius = torch.zeros(num_gaussians, dtype=torch.int32)
        self._worker: ThreadPoolExecutor | None = None  # started by the first observation

    def observe(self, render, frame) -> None:
        """After a step that was applied: charges the frame's error to UV (adaptive) and
        records each Gaussian's screen radius."""
        self.apply(self.start_observing(render, frame))

    def start_observing(self, render, frame) -> Observation:
        """Begins :meth:`observe`'s work on ``render`` before the step is judged: the UV
        error charge (serial, a few ms at 512²) runs on a worker thread while the caller
        runs the backward pass on the other core. :meth:`apply` it once the step is
        applied; drop it otherwise."""
        charge = None
        if self.adaptive:
            if self._worker is None:
                self._worker = ThreadPoolExecutor(1, thread_name_prefix="urhead-uv-error")
            charge = self.accumulator.start(
                render.image.detach(),
                frame.image,
                frame.mask,
                render.mesh.pixels,
                render.mesh.uv.detach(),
                self._worker,
            )
        radii = render.gaussians.radii if render.gaussians is not None else None
        return Observation(charge, radii)

    def apply(self, observation: Observation) -> None:
        """Adds an observation begun by :meth:`start_observing`."""
        if observation.charge is not None:
            self.accumulator.commit(observation.charge)
        if observation.radii is not None:
            self.max_radius = torch.maximum(self.max_radius, observation.radii.amax(-1))

    def prune_oversized(self, avatar, render, frame) -> int:
        """After a step the guard rejected: prunes at once the Gaussians that ``render``
        drew larger than the screen limit, and returns how many. The guard rolls the maps
        back but not the Gaussian set, so a Gaussian sampled onto a texel whose scale has
        run away (a white Gaussian on a white background costs nothing while it grows)
        would otherwise make every later step jump until the next round, which the
        rejected steps never inform (:meth:`observe` sees applied steps only)."""
        if render.gaussians is None or avatar.num_gaussians == 0:
            return 0
        keep = render.gaussians.radii.amax(-1) <= self._screen_limit(frame)
        pruned = int((~keep).sum())
        if pruned:
            order = set_gaussians(avatar, self.surface, avatar.gaussian_uv[keep].numpy())
            self.max_radius = self.max_radius[keep][torch.from_numpy(order)]
            log.info(
                "pruned %d Gaussians larger than the screen limit after a rejected step", pruned
            )
        return pruned

    def step_end(self, avatar, frame, iteration: int) -> None:
        """After ``iteration`` iterations are done: resamples on the schedule (never after
        the last one)."""
        c = self.config
        if c.gaussians and iteration % c.sample_every == 0 and iteration < c.iterations:
            self.resample(avatar, frame, iteration)

    def resample(self, avatar, frame, iteration: int) -> None:
        """Prunes faint or oversized Gaussians, then adds new ones where the UV error is
        (or uniformly), within the per-round cap and the budget."""
        c = self.config
        with torch.no_grad():
            at_gaussians = texture(avatar.maps, avatar.gaussian_uv)
            opacity = torch.sigmoid(at_gaussians[:, avatar.layout.opacity])
        keep = (opacity >= c.prune_opacity) & (self.max_radius <= self._screen_limit(frame))
        uv = avatar.gaussian_uv[keep].numpy()
        rng = np.random.default_rng([c.seed, 2, iteration])
        room = max(min(c.sample_cap, c.max_gaussians - len(uv)), 0)
        if self.adaptive:
            new = self.accumulator.sample(room, self.surface, rng)
            self.accumulator.reset()
        else:
            new = self.surface.uniform(room, rng)
        set_gaussians(avatar, self.surface, np.concatenate([uv, new]))
        self.max_radius = torch.zeros(avatar.num_gaussians, dtype=torch.int32)
        log.debug(
            "iteration %d: pruned %d, added %d → %d",
            iteration,
            int((~keep).sum()),
            len(new),
            avatar.num_gaussians,
        )

    def _screen_limit(self, frame) -> float:
        """The largest screen radius a Gaussian may keep, pixels."""
        side = max(frame.camera.width, frame.camera.height)
        return self.config.prune_screen_fraction * side

    def state(self) -> dict:
        """The checkpoint entries: ``accumulator`` (the UV error) and ``max_radius``."""
        return {"accumulator": self.accumulator.state(), "max_radius": self.max_radius}

    def load_state(self, saved: dict) -> None:
        self.accumulator.load_state(saved["accumulator"])
        self.max_radius = saved["max_radius"]
