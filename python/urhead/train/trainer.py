"""The fit: joint optimisation of the UV maps, the Gaussians' placement and the per-frame
FLAME parameters (DESIGN.md "One training iteration"), with held-out PSNR logged against
training wall-clock time, atomic checkpoints and exact resumption.

Timing: ``seconds`` everywhere is training time — the iterations themselves, sampling
rounds included — excluding the held-out evaluations and checkpoint writes, so curves from
runs with different logging settings compare.
"""

from __future__ import annotations

import csv
import io
import json
import logging
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from urhead._atomic import write_bytes_atomically
from urhead.config import RESUMABLE_CHANGES, FitConfig
from urhead.data.background import subject_background
from urhead.eval import RefineSettings, evaluate_frames
from urhead.eval.per_frame import FLAME_PARAMETERS, METRIC_REGION
from urhead.eval.stlpips import load_stlpips
from urhead.head import head_fingerprint
from urhead.head.leave_out import leave_out_faces
from urhead.losses import psnr
from urhead.model import GaussianSampler, build_avatar, save_avatar
from urhead.model.avatar import Avatar, Render
from urhead.model.io import add_to_description
from urhead.ops import TextureGather
from urhead.optim import SparseAdam
from urhead.train.checkpoint import (
    find_checkpoint,
    load_checkpoint,
    remove_checkpoints,
    save_checkpoint,
)
from urhead.train.guard import StepGuard
from urhead.train.objective import Objective
from urhead.train.plots import plot_psnr_vs_time
from urhead.train.scene import (
    PartChoice,
    SceneMeasures,
    analyse_scene,
    choose_parts,
    log_choices,
    mouth_faces_left_out,
    scene_report,
)
from urhead.train.units import check_metres

log = logging.getLogger("urhead.fit")

PSNR_CSV = "psnr_vs_time.csv"


@dataclass
class FitState:
    """What the loop carries between iterations (and what a checkpoint restores)."""

    avatar: Avatar
    maps_opt: SparseAdam
    frames_opt: SparseAdam
    map_lr: torch.Tensor
    guard: StepGuard
    sampler: GaussianSampler
    iteration: int
    seconds: float
    history: list


@dataclass
class FitResult:
    avatar: Avatar
    metrics: dict
    out: Path
    refined: dict = field(default_factory=dict)
    """The held-out frames' refined FLAME parameters the metrics were scored with, by
    ``(timestep, camera_index)`` (empty without refinement)."""


def frame_order(seed: int, epoch: int, count: int) -> np.ndarray:
    """The training frames' order in ``epoch``: a permutation fixed by (seed, epoch)."""
    return np.random.default_rng([seed, 0, epoch]).permutation(count)


def uv_lr_factor(config: FitConfig, iteration: int) -> float:
    """Exponential decay of the UV-map learning rates after ``lr_decay_start``, reaching
    ``lr_decay_final`` at the last iteration."""
    span = config.iterations - config.lr_decay_start
    if iteration <= config.lr_decay_start or span <= 0:
        return 1.0
    return config.lr_decay_final ** ((iteration - config.lr_decay_start) / span)


def active_sh_degree(config: FitConfig, iteration: int) -> int:
    """The SH degree the colour is evaluated with at ``iteration``: one band more every
    ``sh_degree_every`` iterations (3DGS's schedule: low frequencies settle before the
    higher bands can fit noise), the full degree from the start when it is 0."""
    if config.sh_degree_every == 0:
        return config.sh_degree
    return min(config.sh_degree, iteration // config.sh_degree_every)


def eval_subset(frames, count: int) -> list:
    """``count`` held-out frames spread evenly over the sequence (all if fewer)."""
    n = len(frames)
    if n <= count:
        return list(range(n))
    return sorted({int(i) for i in np.linspace(0, n - 1, count).round()})


class Trainer:
    """One fit of ``subject`` with ``head`` into ``out``. Call :meth:`run`."""

    def __init__(self, subject, head, config: FitConfig, out: Path, *, progress: bool = True):
        self.subject = subject
        self.head = head
        self.config = config
        self.out = Path(out)
        self.progress = progress
        self.use_normals = bool(config.normal_loss and subject.has_normals)
        self.objective = Objective.for_fit(config, head, self.use_normals)
        self.gaussians = bool(config.gaussians)
        self.held_out = subject.test if len(subject.test) else subject.val
        if len(subject.train) == 0:
            raise ValueError(f"{subject.root}: the subject has no training frames")
        if len(self.held_out) == 0:
            raise ValueError(f"{subject.root}: the subject has no test or val frames to score")
        check_metres(subject, head)
        requested = None if config.background == "auto" else config.background
        self.background = subject_background(subject, requested)
        # Recorded in checkpoints: resuming with another subject or head is refused.
        self.inputs = {"subject": subject.fingerprint(), "head": head_fingerprint(head)}
        # What the scene needs (start() measures it, or reads it from the checkpoint).
        self.scene: SceneMeasures | None = None
        self.parts: dict[str, PartChoice] = {}

    # --- set-up --------------------------------------------------------------------

    def _new_state(self) -> tuple[Avatar, dict]:
        """A new avatar with the parts the scene needs: without the mouth's faces and
        atlas rows for a mouth that never opens, without the offset map E where nothing
        lies off the surface, with the eye joints fixed for eyes that never move."""
        c = self.config
        head, map_size = self.head, c.uv_resolution
        if not self.parts["mouth"].used:
            dropped = mouth_faces_left_out(self.head, self.scene)
            kept = leave_out_faces(self.head, dropped, c.uv_resolution)
            head, map_size = kept.head, kept.map_size
            log.info(
                "mouth: %d faces left out; maps of atlas rows %d-%d (%d × %d)",
                kept.faces_left_out,
                kept.first_row,
                kept.first_row + map_size[0] - 1,
                *map_size,
            )
        avatar = build_avatar(
            head,
            self.subject.train,
            resolution=map_size,
            sh_degree=c.sh_degree,
            gaussians=self.gaussians,
            initial_gaussians=c.initial_gaussians if self.gaussians else 0,
            offsets=self.parts["offsets"].used,
            shading=c.shading,
            background=self.background,
            depth_eps=c.depth_eps,
            color_frames=c.color_init_frames,
            rng=np.random.default_rng([c.seed, 1]),
        )
        if not self.parts["eyes"].used:
            eyes = _eye_columns(avatar)
            with torch.no_grad():
                avatar.frame_params[:, eyes] = avatar.frame_params[:, eyes].median(0).values
        return avatar, {"iteration": 0, "seconds": 0.0, "history": []}

    def _optimizers(self, avatar: Avatar) -> tuple[SparseAdam, SparseAdam, torch.Tensor]:
        c = self.config
        avatar.maps.requires_grad_(True)
        avatar.frame_params.requires_grad_(True)
        map_lr = avatar.layout.channel_rates(
            c.lr_color,
            c.lr_normal,
            c.lr_displacement,
            c.lr_opacity,
            c.lr_scale,
            offset=c.lr_offset,
            sh_rest=c.sh_rest_rate,
            shading=c.lr_shading,
        )
        e = avatar.num_expr
        frame_lr = torch.tensor(
            [c.lr_expression] * e + [c.lr_pose] * 15 + [c.lr_translation] * 3,
            dtype=torch.float32,
        )
        if not self.parts["eyes"].used:
            frame_lr[_eye_columns(avatar)] = 0.0  # fixed joints
        maps_opt = SparseAdam([avatar.maps], lr=map_lr.clone(), moments=c.map_moments)
        frames_opt = SparseAdam([avatar.frame_params], lr=frame_lr)
        return maps_opt, frames_opt, map_lr

    def _describe(self, avatar: Avatar) -> None:
        c = self.config
        left_out = []
        if not self.subject.has_normals:
            left_out.append("normal loss (the subject has no normal maps)")
        elif not c.normal_loss:
            left_out.append("normal loss (switched off)")
        if not self.gaussians:
            left_out.append("Gaussian branch and its O, S maps (mesh only)")
        elif c.sampling != "adaptive":
            left_out.append("UV error accumulation (uniform sampling)")
        if c.mesh_term == 0 and self.gaussians:
            left_out.append("mesh-only L1 term")
        if c.lambda_ssim == 0:
            left_out.append("SSIM term")
        if self.gaussians and not c.gaussian_offset:
            left_out.append("Gaussian offset map E")
        scene_parts = {
            "mouth": "mouth interior and teeth (the mouth never opens)",
            "eyes": "per-frame eye joints (the eyes never move)",
        }
        for name, what in scene_parts.items():
            if not self.parts[name].used:
                left_out.append(what)
        if not c.shading:
            left_out.append("pose-driven shading maps A")
        if c.refine_steps + c.refine_full_steps == 0:
            left_out.append("test-time refinement of held-out FLAME rows")
        log.info(
            "fit: %d train / %d held-out frames, maps %d × %d × %d channels (SH %d), %d Gaussians",
            len(self.subject.train),
            len(self.held_out),
            *avatar.maps.shape[:2],
            avatar.layout.channels,
            c.sh_degree,
            avatar.num_gaussians,
        )
        log.info("left out: %s", "; ".join(left_out) if left_out else "nothing")

    def _choose_parts(self, measures: SceneMeasures) -> None:
        self.scene = measures
        self.parts = choose_parts(measures, self.config)
        log_choices(self.parts)

    # --- the loop ------------------------------------------------------------------

    def start(self, resume: bool = False) -> FitState:
        """The state the loop starts from: the last checkpoint (with ``resume``) or a new
        avatar."""
        c = self.config
        self.out.mkdir(parents=True, exist_ok=True)
        checkpoint = find_checkpoint(self.out) if resume else None
        if checkpoint is not None:
            avatar, saved = load_checkpoint(checkpoint)
            if _fitted_settings(saved["config"]) != _fitted_settings(asdict(c)):
                raise ValueError(
                    f"{checkpoint}: was written with a different configuration; "
                    "resume with the same options or start a new --out"
                )
            self._check_resumed_inputs(checkpoint, avatar, saved.get("inputs"))
            log.info("resuming from %s at iteration %d", checkpoint, saved["iteration"])
            self._choose_parts(SceneMeasures.from_dict(saved["scene"]["measures"]))
        else:
            self._choose_parts(
                analyse_scene(self.subject.train, self.head, self.subject.has_normals)
            )
            avatar, saved = self._new_state()
        self._describe(avatar)
        maps_opt, frames_opt, map_lr = self._optimizers(avatar)
        state = FitState(
            avatar=avatar,
            maps_opt=maps_opt,
            frames_opt=frames_opt,
            map_lr=map_lr,
            guard=StepGuard(avatar, maps_opt, frames_opt, map_lr, start=saved["iteration"]),
            sampler=GaussianSampler(c, avatar.head, avatar.num_gaussians),
            iteration=saved["iteration"],
            seconds=saved["seconds"],
            history=list(saved["history"]),
        )
        if "maps_opt" in saved:
            maps_opt.load_state_dict(saved["maps_opt"])
            frames_opt.load_state_dict(saved["frames_opt"])
            state.sampler.load_state(saved)
        if "guard" in saved:
            state.guard.load_state(saved["guard"])
        return state

    def step(self, state: FitState) -> tuple[torch.Tensor, Render, object]:
        """One training iteration (DESIGN.md steps 1–9) on the frame the schedule picks;
        returns ``(loss, render, frame)``."""
        c = self.config
        avatar = state.avatar
        train = self.subject.train
        it = state.iteration
        epoch, slot = divmod(it, len(train))
        row = int(frame_order(c.seed, epoch, len(train))[slot])
        frame = train[row]
        for group in state.maps_opt.param_groups:
            group["lr"] = state.map_lr * uv_lr_factor(c, it)
        row_params = F.embedding(torch.tensor([row]), avatar.frame_params, sparse=True)[0]
        # The maps' gradient stays as the lookups' samples: the optimiser builds it as it
        # updates (one pass over the touched texels fewer than a built gradient).
        gather = TextureGather(avatar.maps)
        render = avatar.render(
            avatar.split_params(row_params),
            frame.camera,
            gaussians=self.gaussians,
            occlusion_aware=c.occlusion_aware,
            normals=self.use_normals,
            gather=gather,
            sh_degree=active_sh_degree(c, it),
        )
        loss = self.objective(render, frame)
        # The sampler's serial UV error charge overlaps the backward pass (a worker
        # thread); it counts only if the guard applies the step.
        observation = state.sampler.start_observing(render, frame)
        loss.backward()
        if state.guard.step(it, row, loss.detach(), gather.samples()):  # applies or undoes
            state.sampler.apply(observation)
        else:
            state.sampler.prune_oversized(avatar, render, frame)
        avatar.maps.grad = None
        avatar.frame_params.grad = None
        state.iteration = it = it + 1
        state.guard.end_iteration(it)
        state.sampler.step_end(avatar, frame, it)
        return loss.detach(), render, frame

    def run(self, resume: bool = False) -> FitResult:
        """Trains to ``config.iterations`` (from the last checkpoint with ``resume``),
        then scores the held-out frames and writes the outputs."""
        c = self.config
        state = self.start(resume)
        eval_frames = [self.held_out[i] for i in eval_subset(self.held_out, c.eval_frames)]
        last_eval = state.seconds if state.history else -math.inf
        bar = _progress(c.iterations, state.iteration, self.progress)
        train_psnr = None
        while state.iteration < c.iterations:
            tick = time.perf_counter()
            loss, render, frame = self.step(state)
            state.seconds += time.perf_counter() - tick
            it = state.iteration
            with torch.no_grad():
                value = float(psnr(render.image.clamp(0, 1), frame.image, frame.mask))
            if math.isfinite(value):  # not for a frame with an empty mask
                train_psnr = value if train_psnr is None else 0.9 * train_psnr + 0.1 * value
            if state.seconds - last_eval >= c.eval_every_seconds or it == c.iterations:
                held = evaluate_frames(state.avatar, eval_frames, mesh_only=False).psnr
                state.history.append((round(state.seconds, 3), it, held))
                last_eval = state.seconds
                log.info("%.1f s, iteration %d: held-out PSNR %.2f dB", state.seconds, it, held)
                bar.set_description(f"fit (held-out {held:.2f} dB)")
            bar.set_postfix(loss=f"{float(loss):.4f}", psnr=f"{train_psnr or math.nan:.2f}")
            bar.update(1)
            if it % c.checkpoint_every == 0 and it < c.iterations:
                state.guard.settle(it)  # only a verified state is written
                save_checkpoint(self.out, state.avatar, self._checkpoint_state(state))
        bar.close()
        state.guard.settle(state.iteration)
        return self._finish(state.avatar, state.seconds, state.history, state.guard.events)

    def _check_resumed_inputs(self, checkpoint: Path, avatar: Avatar, saved: dict | None):
        """Refuses a checkpoint of another subject or head. One written before checkpoints
        recorded their inputs (``saved`` None) is checked on what it holds: its head and
        its training timesteps."""
        if saved is None:
            log.warning(
                "%s: an older checkpoint without the subject's fingerprint; checked: the head "
                "and the training timesteps",
                checkpoint,
            )
            timesteps = [r.timestep for r in self.subject.train.records]
            same_frames = avatar.timesteps.tolist() == timesteps
            saved = {
                "head": head_fingerprint(avatar.head),
                "subject": self.inputs["subject"] if same_frames else None,
            }
        for key, option in (("subject", f"subject {self.subject.root}"), ("head", "--head")):
            if saved.get(key) != self.inputs[key]:
                raise ValueError(
                    f"{checkpoint}: was written for another {key} than {option}; "
                    "resume with the same subject and --head or start a new --out"
                )

    def _checkpoint_state(self, state: FitState) -> dict:
        return {
            "inputs": self.inputs,
            "iteration": state.iteration,
            "seconds": state.seconds,
            "history": list(state.history),
            "config": asdict(self.config),
            "scene": scene_report(self.scene, self.parts),
            "maps_opt": state.maps_opt.state_dict(),
            "frames_opt": state.frames_opt.state_dict(),
            **state.sampler.state(),
            "guard": state.guard.state(),
        }

    def _finish(self, avatar: Avatar, seconds: float, history: list, events: list) -> FitResult:
        c = self.config
        avatar.maps.requires_grad_(False)
        avatar.frame_params.requires_grad_(False)
        recorded = {
            "subject": str(Path(self.subject.root).resolve()),
            "camera": self.subject.train.records[0].camera.to_dict(),
        }
        # Written before the final evaluation, so a failure there never loses the fit.
        extra = {"config": asdict(c), "scene": scene_report(self.scene, self.parts), **recorded}
        save_avatar(avatar, self.out / "avatar", extra=extra)
        held_out = list(self.held_out)
        refine = RefineSettings(steps=c.refine_steps, full_steps=c.refine_full_steps)
        tick = time.perf_counter()
        stlpips, stlpips_note = load_stlpips()
        bar = _progress(
            len(held_out), 0, self.progress and refine.total_steps > 0, "refine held-out"
        )
        with bar:
            scores = evaluate_frames(
                avatar,
                held_out,
                occlusion_aware=c.occlusion_aware,
                refine=refine,
                progress=lambda: bar.update(1),
            )
        # ST-LPIPS costs ~1.3 s of CPU per 512² frame (its first convolution runs at full
        # size), more than the rest of the evaluation: the fit scores it on the eval_frames
        # spread evenly over the held-out frames; `urhead eval` scores every frame.
        perceptual_frames = [held_out[i] for i in eval_subset(held_out, c.eval_frames)]
        perceptual = (
            evaluate_frames(
                avatar,
                perceptual_frames,
                occlusion_aware=c.occlusion_aware,
                mesh_only=False,
                stlpips=stlpips,
            ).stlpips_alex
            if stlpips is not None and perceptual_frames
            else None
        )
        metrics = {
            "psnr": scores.psnr,
            "psnr_full": scores.psnr_full,
            "psnr_refined": scores.psnr_refined,
            "psnr_refined_full": scores.psnr_refined_full,
            "ssim": scores.ssim,
            "ssim_refined": scores.ssim_refined,
            "lpips": scores.lpips,
            "stlpips_alex": perceptual,
            "stlpips_frames": len(perceptual_frames) if perceptual is not None else 0,
            "psnr_mesh_only": scores.psnr_mesh_only,
            "num_gaussians": avatar.num_gaussians,
            "seconds": round(seconds, 2),
            "evaluation_seconds": round(time.perf_counter() - tick, 2),
            "iterations": c.iterations,
            "held_out_frames": len(held_out),
            "refine_steps": c.refine_steps,
            "refine_full_steps": c.refine_full_steps,
            "rejected_steps": [asdict(e) for e in events],
            "metric_region": METRIC_REGION,
            "flame_parameters": FLAME_PARAMETERS,
            "background": avatar.background.tolist(),
        }
        if stlpips_note is not None:
            metrics["stlpips_skipped"] = stlpips_note
        add_to_description(self.out / "avatar", {"metrics": metrics})
        _write_history(self.out / PSNR_CSV, history)
        plot_psnr_vs_time(history, self.out / "psnr_vs_time.png", title=_title(c, avatar))
        write_bytes_atomically(self.out / "metrics.json", json.dumps(metrics, indent=2).encode())
        remove_checkpoints(self.out)  # the avatar supersedes them (GBs at 2048²)
        refined = {}
        if scores.refined_params is not None:
            keys = [(f.timestep, f.camera_index) for f in held_out]
            refined = dict(zip(keys, scores.refined_params, strict=True))
        return FitResult(avatar, metrics, self.out, refined)


def _eye_columns(avatar: Avatar) -> slice:
    """The frame-parameter columns of the two eye joints' axis-angles."""
    start = avatar.num_expr + 9
    return slice(start, start + 6)


def _title(c: FitConfig, avatar: Avatar) -> str:
    return (
        f"held-out PSNR vs training time — maps {c.uv_resolution}², SH {c.sh_degree}, "
        f"{avatar.num_gaussians} Gaussians"
    )


def _write_history(path: Path, history: list) -> None:
    rows = io.StringIO(newline="")
    writer = csv.writer(rows)
    writer.writerow(["seconds", "iteration", "psnr"])
    writer.writerows(history)
    write_bytes_atomically(path, rows.getvalue().encode())


def _progress(total: int, initial: int, enabled: bool, desc: str = "fit"):
    """A tqdm bar on a terminal, a plain line every few seconds in a log file."""
    from urhead._progress import progress

    unit = "it" if desc == "fit" else "frame"
    return progress(total, desc, unit, enabled=enabled, initial=initial)


def _fitted_settings(config: dict) -> dict:
    """A config (as saved) without the fields a resume may change
    (:data:`urhead.config.RESUMABLE_CHANGES`); a checkpoint from before such a field
    existed compares equal too."""
    return {k: v for k, v in config.items() if k not in RESUMABLE_CHANGES}
