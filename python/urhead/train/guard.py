"""The step guard: keeps non-finite and diverging steps out of the fit (NUMERICS.md case 31).

The guard applies every iteration's step itself (through the two optimisers) and judges
it. A step is bad when

- non-finite: the loss, or a gradient entry of some parameter group, is NaN or infinite,
  or an update came out non-finite;
- exploding: the loss exceeds ``LOSS_JUMP`` times the larger of the loss the same frame
  had at its previous visit and the median of the recent accepted losses, or one group's
  largest gradient exceeds ``GRADIENT_JUMP`` times the median of that group's recent
  largest gradients.

A bad step is undone: the parameters and Adam moments go back to the last good state,
the learning rate of the group it came from is halved (the group whose gradient stands
out most against its own recent median, for a loss jump), and a warning names the
iteration, what went wrong and the group. The good states are the starts of windows of
``WINDOW`` iterations: a window ends when the next step's loss is judged good (it vouches
for the state the window's steps made); :meth:`StepGuard.settle` ends the current one
after checking every table is finite, before a checkpoint or the avatar is written, so
neither ever holds a non-finite value.

Cost: the optimiser's kernel does the inspection in its own pass over the gradient (each
channel's largest magnitude, rows rejected for a non-finite entry, updates that came out
non-finite), and saves each map row into a persistent journal just before the window's
first step that changes it: one copy per distinct row per window, never a second atlas.
Nothing non-finite can enter the state without a step reporting it, so windows end
without scanning the tables. The frame table is small and copied whole per window.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from dataclasses import asdict, dataclass

import torch

from urhead.errors import NonFiniteError
from urhead.model.avatar import POSE_SIZE, Avatar
from urhead.optim import RowJournal, SparseAdam, StepReport, moment_array

log = logging.getLogger("urhead.fit")

WINDOW = 20
"""Iterations between good states: a rollback loses at most this many."""
HISTORY = 25
"""Accepted iterations the medians are taken over."""
WARMUP = 5
"""Accepted iterations before a loss jump is judged (a group's gradient jump needs
``HISTORY // 2`` iterations in which the group had a gradient)."""
LOSS_JUMP = 3.0
"""A frame's loss this many times its previous one (or the recent median) is divergence.
Natural spread (two synthetic subjects, 300–400 iterations at 64²): a frame's loss at most
1.21× its previous visit; at every rate ×100 the first divergence shows as 7.4×."""
STRIKES = 2
"""Loss jumps of one frame after which its loss is taken as its reference."""
GRADIENT_JUMP = 1e4
"""A group's largest gradient this many times its recent median is an explosion (natural
spread, same runs: at most 45×)."""
LR_CUT = 0.5
"""Factor on the learning rate of the group a bad step came from."""


@dataclass(frozen=True)
class GuardEvent:
    """One rejected step: where, what, which group, and the iteration restored."""

    iteration: int
    kind: str  # "non-finite loss", "non-finite gradient", "loss jump", "gradient jump", …
    group: str
    detail: str
    restored_to: int


class _Group:
    """A parameter group the guard reports on and cuts the rate of: some channels of one
    table (``"maps"`` or ``"frames"``)."""

    def __init__(self, name: str, table: str, channels: slice):
        self.name, self.table, self.channels = name, table, channels


class StepGuard:
    """Applies, judges and rolls back the steps of one fit's two optimisers.

    ``map_lr`` (C,) is the trainer's base per-channel map rate (cut in place); the frame
    rates are the frame optimiser's own per-channel ``lr`` tensor. ``start`` is the
    iteration the fit starts (or resumes) at."""

    def __init__(
        self,
        avatar: Avatar,
        maps_opt: SparseAdam,
        frames_opt: SparseAdam,
        map_lr: torch.Tensor,
        *,
        start: int = 0,
    ):
        self.maps, self.frames = avatar.maps, avatar.frame_params
        self.maps_opt, self.frames_opt = maps_opt, frames_opt
        self.map_lr = map_lr
        self.frame_lr = frames_opt.param_groups[0]["lr"]
        e = avatar.num_expr
        self.groups = [_Group(name, "maps", s) for name, s in avatar.layout.named_maps()]
        self.groups += [
            _Group("FLAME expression", "frames", slice(0, e)),
            _Group("FLAME pose", "frames", slice(e, e + POSE_SIZE)),
            _Group("FLAME translation", "frames", slice(e + POSE_SIZE, e + POSE_SIZE + 3)),
        ]
        for table in (self.maps, self.frames):
            if not torch.isfinite(table).all():
                raise NonFiniteError("the fit's starting state has NaN or infinite values")
        self.losses: deque[float] = deque(maxlen=HISTORY)
        self.peaks: deque[torch.Tensor] = deque(maxlen=HISTORY)  # (groups,) each
        self.frame_loss: dict[int, float] = {}
        self.strikes: dict[int, int] = {}  # loss jumps of a frame since it was last accepted
        self.events: list[GuardEvent] = []
        self.journal = RowJournal(
            self.maps.numel() // self.maps.shape[-1], self.maps.shape[-1], maps_opt.moments
        )
        self._begin_window(start)

    # --- the per-iteration calls ----------------------------------------------------

    def step(
        self,
        iteration: int,
        row: int,
        loss: torch.Tensor,
        map_samples: list[tuple[torch.Tensor, torch.Tensor]] | None = None,
    ) -> bool:
        """Applies the step of ``iteration`` (training frame ``row``, its ``loss``, the
        gradients on the two tables' ``.grad``, or for the maps their lookups
        ``map_samples`` (:meth:`urhead.ops.TextureGather.samples`)) and judges it. Returns
        whether it stands; a bad step is undone with the rest of its window and its group's
        rate cut."""
        value = float(loss)
        loss_problem = self._judge_loss(value, row)
        if loss_problem is None and self._window_due:  # the loss vouches for the state
            self._begin_window(iteration)
        maps = self.maps_opt.step_reported(self.journal, map_samples)
        frames = self.frames_opt.step_reported()
        channel_peaks = {"maps": maps.peaks, "frames": frames.peaks}
        peaks = torch.stack([channel_peaks[g.table][g.channels].amax() for g in self.groups])
        problem = self._judge(peaks, (maps, frames), loss_problem)
        if problem is not None:
            kind, group, detail = problem
            if kind == "loss jump":
                self._strike(row, value)
            self._roll_back(iteration, kind, group, detail)
            return False
        self.losses.append(value)
        self.peaks.append(peaks)
        self.frame_loss[row] = value
        self.strikes.pop(row, None)
        return True

    def end_iteration(self, iteration: int) -> None:
        """Called after every iteration: every ``WINDOW`` iterations the window is due to
        end, at the next step whose loss shows the state is good."""
        self._window_due = iteration - self.window_start >= WINDOW

    def settle(self, iteration: int) -> None:
        """Ends the current window at ``iteration``: the state becomes the last good one if
        every table is finite (one flat pass each), else the window is rolled back. Call
        before writing the state anywhere."""
        found = self._first_non_finite()
        if found is not None:
            table, group = found
            self._roll_back(iteration, "non-finite state", group, f"in {table}")
            return
        self._begin_window(iteration)

    # --- checkpoints ------------------------------------------------------------------

    def state(self) -> dict:
        """What a checkpoint keeps so a resumed fit judges and steps as this one would."""
        return {
            "map_lr": self.map_lr.clone(),
            "frame_lr": self.frame_lr.clone(),
            "losses": list(self.losses),
            "peaks": torch.stack(list(self.peaks)) if self.peaks else torch.zeros(0),
            "frame_loss": [[row, loss] for row, loss in self.frame_loss.items()],
            "strikes": [[row, n] for row, n in self.strikes.items()],
            "events": [asdict(e) for e in self.events],
        }

    def load_state(self, state: dict) -> None:
        self.map_lr.copy_(state["map_lr"])
        self.frame_lr.copy_(state["frame_lr"])
        self.losses.extend(state["losses"])
        self.peaks.extend(state["peaks"].unbind(0) if state["peaks"].numel() else [])
        self.frame_loss = {int(row): float(loss) for row, loss in state["frame_loss"]}
        self.strikes = {int(row): int(n) for row, n in state["strikes"]}
        self.events = [GuardEvent(**e) for e in state["events"]]

    # --- inside -----------------------------------------------------------------------

    def _judge_loss(self, loss: float, row: int) -> tuple[str, str] | None:
        """``(kind, detail)`` of a bad loss, None for a good one."""
        if not math.isfinite(loss):
            return "non-finite loss", f"loss {loss}"
        if len(self.losses) < WARMUP:
            return None
        # A frame that shows almost nothing (off-screen) has a loss near 0: judged against
        # the recent median too, its jumps are measured on the scale of the whole fit.
        reference = float(torch.tensor(list(self.losses)).median())
        reference = max(reference, self.frame_loss.get(row, reference))
        if loss > LOSS_JUMP * reference:
            return "loss jump", f"loss {loss:.4g} vs {reference:.4g}"
        return None

    def _judge(self, peaks: torch.Tensor, reports: tuple[StepReport, ...], loss_problem):
        """``(kind, group, detail)`` of a bad step, None for a good one."""
        if not torch.isfinite(peaks).all():
            group = self.groups[int((~torch.isfinite(peaks)).nonzero()[0, 0])]
            return "non-finite gradient", group, "NaN or infinite entries"
        if any(r.non_finite_rows for r in reports):
            table, group = self._first_non_finite()
            return "non-finite update", group, f"in {table}"
        if loss_problem is not None and loss_problem[0] == "non-finite loss":
            return loss_problem[0], self._most_unusual(peaks), loss_problem[1]
        if len(self.losses) >= WARMUP:
            ratio = _ratio_to_median(peaks, torch.stack(list(self.peaks)))
            worst = int(ratio.argmax())
            if ratio[worst] > GRADIENT_JUMP:
                detail = f"largest gradient {float(peaks[worst]):.3g}, {float(ratio[worst]):.3g}×"
                return "gradient jump", self.groups[worst], detail + " its recent median"
        if loss_problem is not None:
            return loss_problem[0], self._most_unusual(peaks), loss_problem[1]
        return None

    def _strike(self, row: int, loss: float) -> None:
        """Counts a loss jump of frame ``row``. A frame new to the guard, or one that jumped
        ``STRIKES`` times from restored states, is harder than the rest rather than a sign
        of divergence: its loss becomes its reference, so it cannot be rejected forever."""
        self.strikes[row] = self.strikes.get(row, 0) + 1
        if row not in self.frame_loss or self.strikes[row] >= STRIKES:
            self.frame_loss[row] = loss
            del self.strikes[row]

    def _most_unusual(self, peaks: torch.Tensor) -> _Group:
        """The group whose largest gradient stands out most against its recent median."""
        if not self.peaks:
            return self.groups[int(peaks.nan_to_num(0, 0, 0).argmax())]
        ratio = _ratio_to_median(peaks.nan_to_num(0, 0, 0), torch.stack(list(self.peaks)))
        return self.groups[int(ratio.argmax())]

    def _roll_back(self, iteration: int, kind: str, group: _Group, detail: str) -> None:
        self._restore()
        rates = self.map_lr if group.table == "maps" else self.frame_lr
        rates[group.channels] *= LR_CUT
        event = GuardEvent(iteration, kind, group.name, detail, self.window_start)
        self.events.append(event)
        log.warning(
            "iteration %d: %s in %s (%s); rolled back to iteration %d, %s learning rate × %g",
            iteration,
            kind,
            group.name,
            detail,
            self.window_start,
            group.name,
            LR_CUT,
        )
        self._begin_window(self.window_start)

    def _begin_window(self, iteration: int) -> None:
        self.window_start = iteration
        self._window_due = False
        self.journal.clear()
        state = self.frames_opt.state.get(self.frames, {})
        self._frames_saved = (
            self.frames.detach().clone(),
            {k: v.clone() if torch.is_tensor(v) else v for k, v in state.items()},
        )

    def _restore(self) -> None:
        with torch.no_grad():
            state = self.maps_opt.state.get(self.maps, {})
            if state:  # else no step has run, so the journal is empty
                self.journal.restore(
                    self._flat(self.maps).numpy(),
                    moment_array(self._flat(state["exp_avg"])),
                    moment_array(self._flat(state["exp_avg_sq"])),
                    state["steps"].numpy(),
                )
            frames, moments = self._frames_saved
            self.frames.copy_(frames)
            live = self.frames_opt.state[self.frames]
            live.clear()
            live.update({k: v.clone() if torch.is_tensor(v) else v for k, v in moments.items()})

    def _first_non_finite(self) -> tuple[str, _Group] | None:
        """``(table, group)`` of the first NaN or infinity in the parameters or moments,
        None if all are finite."""
        for name, table in self._tables():
            if not bool(torch.isfinite(table).all()):  # a flat reduction: fast
                channel = int((~torch.isfinite(table).all(0)).nonzero()[0, 0])
                return name, self._group_of_channel(name, channel)
        return None

    def _tables(self):
        """``(name, (N, C) table)`` of everything a step changes."""
        for owner, param, opt in (
            ("maps", self.maps, self.maps_opt),
            ("frames", self.frames, self.frames_opt),
        ):
            yield owner, self._flat(param)
            state = opt.state.get(param, {})
            for key in ("exp_avg", "exp_avg_sq"):
                if key in state:
                    yield f"{owner}' Adam {key}", self._flat(state[key])

    def _group_of_channel(self, table_name: str, channel: int) -> _Group:
        table = "maps" if table_name.startswith("maps") else "frames"
        return next(
            g
            for g in self.groups
            if g.table == table and g.channels.start <= channel < g.channels.stop
        )

    @staticmethod
    def _flat(table: torch.Tensor) -> torch.Tensor:
        return table.detach().view(-1, table.shape[-1])


def _ratio_to_median(peaks: torch.Tensor, history: torch.Tensor) -> torch.Tensor:
    """(groups,) each group's peak over the median of its non-zero recent peaks (0 for a
    group with too few of them: a group seen rarely is not judged)."""
    seen = history > 0
    median = torch.where(seen, history, torch.nan).nanmedian(0).values
    enough = seen.sum(0) >= HISTORY // 2
    ratio = peaks / median
    return torch.where(enough, ratio, torch.zeros_like(ratio))
