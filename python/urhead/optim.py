"""Sparse ("lazy") Adam for UV maps: only texels that received gradient are touched."""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import torch

from urhead import hugepages
from urhead._threads import num_threads
from urhead.errors import DTypeError, InvalidArgumentError, ShapeError
from urhead.ops._bridge import native


def _channel_lr(lr, channels: int) -> torch.Tensor:
    t = torch.as_tensor(lr, dtype=torch.float32).detach().cpu().reshape(-1)
    if t.numel() == 1:
        t = t.expand(channels)
    if t.numel() != channels:
        raise ShapeError(
            f"lr must be a float or have one entry per channel ({channels}), got {t.numel()}"
        )
    return t.contiguous()


def rows_and_values(param: torch.Tensor, grad: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Touched rows (K,) int64, strictly increasing, and their gradients (K, C)."""
    channels = param.shape[-1]
    if grad.is_sparse:
        if grad.sparse_dim() != param.dim() - 1 or grad.dense_dim() != 1:
            raise InvalidArgumentError(
                "a sparse gradient must index every dimension but the last (channels), "
                f"got sparse_dim {grad.sparse_dim()}, dense_dim {grad.dense_dim()} for a "
                f"parameter of shape {tuple(param.shape)}"
            )
        grad = grad.coalesce()
        index = grad.indices()
        rows = index[0]
        for dim in range(1, index.shape[0]):  # row-major flat index over the leading dims
            rows = rows * param.shape[dim] + index[dim]
        return rows.contiguous(), grad.values().to(torch.float32).contiguous()
    # A dense gradient (e.g. from a plain-torch path): the touched rows are those with any
    # non-zero (or non-finite) entry. This is a dense pass, paid only by dense gradients.
    flat = grad.reshape(-1, channels)
    rows = (flat != 0).any(1).nonzero()[:, 0]
    return rows, flat[rows].to(torch.float32).contiguous()


RowJournal = native("RowJournal")
"""``RowJournal(rows, channels, moments="float32")``: the values the rows of one ``(rows,
channels)`` table had before steps given it first changed them since its last ``clear()``;
``restore(param, exp_avg, exp_avg_sq, steps)`` (flat ``(N, C)`` views — the moments through
:func:`moment_array` — and ``(N,)`` counts) writes them back. ``moments`` is the optimiser's
(:attr:`SparseAdam.moments`). Its buffers keep their capacity across clears."""

MOMENT_DTYPES = {"float32": torch.float32, "bfloat16": torch.bfloat16}


def moment_array(moment: torch.Tensor):
    """A moment table as the native step takes it: float32 as is, bfloat16 as its uint16
    bits (numpy has no bfloat16); shares memory with ``moment``."""
    if moment.dtype == torch.bfloat16:
        return moment.view(torch.uint16).numpy()
    return moment.numpy()


@dataclass(frozen=True)
class StepReport:
    """What one step of one table saw and did."""

    peaks: torch.Tensor
    """(C,) each channel's largest gradient magnitude; +inf where an entry was NaN or
    infinite; 0 when the table had no gradient."""
    rejected_rows: int
    """Rows skipped whole for a NaN or infinite gradient entry."""
    non_finite_rows: int
    """Rows whose updated values came out NaN or infinite (written; saved first in a
    journal)."""


class SparseAdam(torch.optim.Optimizer):
    """Adam that updates only the rows (texels) present in the gradient.

    Each parameter is a float32 table whose last dimension is channels, e.g. a UV atlas
    (H, W, C). Gradients may be sparse COO tensors indexing every dimension but the last
    (what :func:`urhead.ops.texture` produces, like ``nn.Embedding(sparse=True)``) or dense.

    Differences from ``torch.optim.Adam``, all deliberate:
    - lazy: untouched texels keep their parameters and moments bit for bit;
    - each texel counts its own steps for bias correction, so texels first seen late take
      correctly sized steps;
    - ``lr`` may be a float or a (C,) per-channel tensor (one table can hold maps with
      different rates); torch LR schedulers work on either;
    - a texel whose gradient is NaN or infinite is skipped whole and counted in
      ``state["rejected_rows"]``; steps are bounded by lr·max(1, (1 − β1)/√(1 − β2));
    - ``moments="bfloat16"`` stores both moments in 16 bits (half their memory, a third
      less memory traffic a step). The update runs in float32 and only the stored moments
      are rounded: the first to nearest, the second stochastically (a hash of texel and
      step count, the same on any thread count), since ``0.999·v`` rounded to nearest
      bfloat16 is ``v`` again and a texel's ``v`` would never decay (NUMERICS.md case 33).
    """

    def __init__(
        self,
        params: Iterable,
        lr: float | Sequence[float] | torch.Tensor = 1e-3,
        betas: tuple[float, float] = (0.9, 0.999),
        eps: float = 1e-15,
        moments: str = "float32",
    ):
        if moments not in MOMENT_DTYPES:
            raise InvalidArgumentError(
                f"moments must be one of {sorted(MOMENT_DTYPES)}, got {moments!r}"
            )
        self.moments = moments
        super().__init__(params, {"lr": lr, "betas": betas, "eps": eps})
        for group in self.param_groups:
            for p in group["params"]:
                if p.dtype != torch.float32 or p.device.type != "cpu":
                    raise DTypeError(
                        f"SparseAdam parameters must be float32 CPU tensors, "
                        f"got {p.dtype} on {p.device}"
                    )
                if p.dim() < 1 or not p.is_contiguous():
                    raise InvalidArgumentError(
                        "SparseAdam parameters must be contiguous tables (..., C)"
                    )

    def load_state_dict(self, state_dict: dict) -> None:
        """As torch's, then the per-texel step counts are made int32 again and the moments
        this optimiser's dtype: torch casts every floating-point-able state tensor to the
        parameter's dtype (exact for counts below 2²⁴). A state saved with the other moment
        dtype loads too (float32 moments rounded to nearest bfloat16, or widened exactly)."""
        super().load_state_dict(state_dict)
        for group in self.param_groups:
            for p in group["params"]:
                state = self.state[p]
                if "steps" in state:
                    state["steps"] = hugepages.copy(state["steps"].to(torch.int32))
                    for moment in ("exp_avg", "exp_avg_sq"):
                        dtype = MOMENT_DTYPES[self.moments]
                        state[moment] = hugepages.copy(state[moment].to(dtype))

    @torch.no_grad()
    def step(self, closure=None):
        loss = None
        if closure is not None:
            with torch.enable_grad():
                loss = closure()
        for group in self.param_groups:
            for p in group["params"]:
                self._step_table(group, p)
        return loss

    @torch.no_grad()
    def step_reported(
        self,
        journal: RowJournal | None = None,
        texture_samples: Sequence[tuple[torch.Tensor, torch.Tensor]] | None = None,
    ) -> StepReport:
        """One step of an optimiser of a single table, saving the rows it changes into
        ``journal`` first (if given), and what it saw: the step's inspection costs no pass
        over the gradient beyond the update's own.

        ``texture_samples``: the table is a texture ``(Ht, Wt, C)`` and its gradient is that
        of bilinear lookups given as segments ``[(uv (M_i, 2), v_out (M_i, C)), ...]``
        (:meth:`urhead.ops.TextureGather.samples`), used instead of ``.grad`` (which must be
        None): each texel's gradient row is summed as the update reaches it, never stored
        — the result is bit for bit that of a step on the coalesced gradient of the
        concatenated lookups, one pass over the touched rows cheaper (and the segments are
        never joined)."""
        [[group, p]] = [(g, p) for g in self.param_groups for p in g["params"]]
        report = self._step_table(group, p, journal, texture_samples)
        if report is None:
            return StepReport(torch.zeros(p.shape[-1]), 0, 0)
        return report

    def _step_table(
        self, group: dict, p: torch.Tensor, journal=None, texture_samples=None
    ) -> StepReport | None:
        if texture_samples is not None and p.grad is not None:
            raise InvalidArgumentError(
                "a step takes its gradient from .grad or from texture_samples, not both"
            )
        if p.grad is None and texture_samples is None:
            return None
        channels = p.shape[-1]
        state = self.state[p]
        if not state:
            # Read and written at random rows every step: on huge pages, as the maps are.
            dtype = MOMENT_DTYPES[self.moments]
            state["exp_avg"] = hugepages.zeros(p.shape, dtype)
            state["exp_avg_sq"] = hugepages.zeros(p.shape, dtype)
            state["steps"] = hugepages.zeros((p.numel() // channels,), torch.int32)
            state["rejected_rows"] = 0
        beta1, beta2 = group["betas"]
        tables = (
            p.detach().numpy(),
            moment_array(state["exp_avg"]),
            moment_array(state["exp_avg_sq"]),
        )
        settings = (
            _channel_lr(group["lr"], channels).numpy(),
            float(beta1),
            float(beta2),
            float(group["eps"]),
            num_threads(),
            journal,
        )
        if texture_samples is not None:
            segments = _checked_samples(p, texture_samples)
            found = native("sparse_adam_step_sampled")(
                *tables, state["steps"].numpy(), segments, *settings
            )
        else:
            rows, values = rows_and_values(p, p.grad)
            if rows.numel() == 0:
                return None
            flat = (t.reshape(-1, channels) for t in tables)
            found = native("sparse_adam_step")(
                *flat, state["steps"].numpy(), rows.numpy(), values.numpy(), *settings
            )
        rejected, non_finite, peaks = found
        state["rejected_rows"] += rejected
        return StepReport(torch.from_numpy(peaks), rejected, non_finite)


def _checked_samples(p: torch.Tensor, segments) -> list:
    """``[(uv, v_out), ...]`` lookups of texture ``p (Ht, Wt, C)`` as float32 numpy arrays."""
    if p.dim() != 3:
        raise ShapeError(f"texture_samples need a texture (Ht, Wt, C), got {tuple(p.shape)}")
    channels = p.shape[-1]
    checked = []
    for i, segment in enumerate(segments):
        if not (isinstance(segment, tuple | list) and len(segment) == 2):
            raise InvalidArgumentError(
                f"texture_samples must be a list of (uv, v_out) segments, got {type(segment)} "
                f"at {i}"
            )
        uv, v_out = segment
        if uv.dim() != 2 or uv.shape[1] != 2 or v_out.shape != (uv.shape[0], channels):
            raise ShapeError(
                f"texture_samples segment {i} must be uv (M, 2) and v_out (M, {channels}), got "
                f"{tuple(uv.shape)} and {tuple(v_out.shape)}"
            )
        if uv.dtype != torch.float32 or v_out.dtype != torch.float32:
            raise DTypeError(
                f"texture_samples must be float32, got {uv.dtype} and {v_out.dtype} in segment {i}"
            )
        checked.append((uv.detach().contiguous().numpy(), v_out.detach().contiguous().numpy()))
    return checked
