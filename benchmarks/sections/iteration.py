"""One training iteration at the paper's settings (512² image, 2048² maps × 56 channels,
SH degree 3, 24k Gaussians), forward + backward, against the DESIGN.md budget.

The whole iteration is :meth:`Trainer.step` itself (render, loss, backward, sparse Adam on
maps and FLAME rows, UV error accumulation). Each stage is also timed alone, forward and
backward, from detached inputs with a random upstream gradient, with the avatar's own stage
methods and, as in the trainer, its map lookups recorded in a ``TextureGather``; the maps'
gradient is built inside the sparse Adam stage, from a real iteration's lookups, as the
trainer's step builds it; "everything else" is the whole minus the stages (autograd
bookkeeping, the loss's small terms, the FLAME-row Adam, error accumulation, Python).

Every figure is a median of wall time and of process CPU time (user + system, all threads):
on a shared machine the CPU time stays meaningful when the wall time is inflated by other
work. The whole iteration is timed over whole windows of the step guard, after its first
(whose journal pages are faulted in once): the first steps of each window also copy every
map row they change into the undo journal, so the mean over whole windows, not the median,
is what a fit's iterations cost, and the 50k-iteration projection uses it.
"""

from __future__ import annotations

import statistics
from pathlib import Path

import torch

from sections.common import ms, one_torch_thread, save, table
from sections.scene import paper_scene
from timing import median_wall_cpu_ms, wall_cpu_samples
from urhead import hugepages
from urhead.losses import ssim_l1
from urhead.ops import TextureGather, texture
from urhead.train.guard import WINDOW

TITLE = "Whole training iteration at the paper's settings"
ITERATION_BUDGET_MS = 100
PAPER_GPU_MS = 120 * 60_000 / 50_000  # the paper: 50k iterations in 120 min on an RTX 3090

BUDGET_MS = {
    "skinning + displacement": 2,
    "mesh branch": 15,
    "Gaussian lift from UV": 3,
    "splatting": 40,
    "SSIM + L1": 10,
    "sparse Adam": 10,
    "everything else": 20,
}


def _leaf(t: torch.Tensor) -> torch.Tensor:
    return t.detach().clone().requires_grad_(True)


def stage_functions(trainer, state):
    """name → a callable running that stage's forward and backward once."""
    avatar = state.avatar
    frame = trainer.subject.train[0]
    camera = frame.camera
    g = torch.Generator().manual_seed(0)

    def clear():
        avatar.maps.grad = None
        avatar.frame_params.grad = None

    params = avatar.frame(frame.timestep)
    with torch.no_grad():
        verts, rotations = avatar.skin(params)
        displaced, offsets = avatar.displace(verts, rotations)
        mesh = avatar.shade_mesh(displaced, offsets, rotations, camera, False)
        lift = avatar.lift_gaussians(verts, rotations, camera)
        image = avatar.splat(lift, camera, mesh.depth, mesh.rgba).image
    h, w = camera.height, camera.width
    g_verts = torch.randn(verts.shape, generator=g) * 1e-3
    g_image = torch.randn(h, w, 3, generator=g) * 1e-3

    # As in Trainer.step, map lookups record their output gradient in a TextureGather
    # (collected here, and applied by the sparse Adam stage).
    def skinning():
        gather = TextureGather(avatar.maps)
        v, r = avatar.skin(avatar.frame(frame.timestep))
        d, _ = avatar.displace(v, r, gather)
        d.backward(g_verts)
        gather.samples()
        clear()

    def mesh_branch():
        gather = TextureGather(avatar.maps)
        m = avatar.shade_mesh(_leaf(displaced), offsets, rotations, camera, False, gather)
        m.image.backward(g_image)
        gather.samples()
        clear()

    def lift_stage():
        gather = TextureGather(avatar.maps)
        out = avatar.lift_gaussians(_leaf(verts), rotations, camera, gather)
        tensors = [out.means, out.quats, out.scales, out.opacities, out.colors]
        torch.autograd.backward(tensors, [torch.ones_like(t) * 1e-3 for t in tensors])
        gather.samples()
        clear()

    leaves = lift._replace(
        means=_leaf(lift.means),
        quats=_leaf(lift.quats),
        scales=_leaf(lift.scales),
        opacities=_leaf(lift.opacities),
        colors=_leaf(lift.colors),
    )

    def splatting():
        out = avatar.splat(leaves, camera, mesh.depth, mesh.rgba)  # over the mesh, as render
        out.image.backward(g_image)

    def loss_stage():
        x = _leaf(image)
        # weighted inside one kernel pass, as the trainer's objective
        loss = ssim_l1(x, frame.image, ssim_weight=-0.2, l1_weight=0.8) + 0.2
        loss.backward()

    # A real iteration's lookups for the optimiser stage, which builds their gradient as
    # it updates (as Trainer.step does).
    gather = TextureGather(avatar.maps)
    out = avatar.render(params, camera, gather=gather)
    (out.image - frame.image).abs().mean().backward()
    map_samples = gather.samples()
    clear()

    def adam():
        state.maps_opt.step_reported(None, map_samples)

    return {
        "skinning + displacement": skinning,
        "mesh branch": mesh_branch,
        "Gaussian lift from UV": lift_stage,
        "splatting": splatting,
        "SSIM + L1": loss_stage,
        "sparse Adam": adam,
    }, touched_texels(avatar.maps, map_samples)


def touched_texels(maps: torch.Tensor, samples) -> int:
    """Distinct texels the lookups' gradient touches."""
    grad = TextureGather(maps)
    for segment in samples:
        grad.record(*segment)
    return int(grad.gradient()._nnz())


def _move_tables(state, allocate) -> None:
    """Puts the maps and their Adam moments into new storage from ``allocate(tensor)``
    (every holder of the tensors sees the move: ``.data`` and the optimiser's state)."""
    maps = state.avatar.maps
    with torch.no_grad():
        maps.data = allocate(maps)
    moments = state.maps_opt.state[maps]
    for name in ("exp_avg", "exp_avg_sq", "steps"):
        moments[name] = allocate(moments[name])


def page_size_gain(trainer, state, repeats: int, rounds: int = 3) -> dict:
    """What huge pages pay, same process: ``{"huge"|"torch": {"lookup", "step"}}`` median
    timings with the maps and moments as the trainer allocates them (huge pages,
    :mod:`urhead.hugepages`) and moved into copies from torch's allocator (4 KiB pages
    unless THP is on for everything), alternating ``rounds`` times so a change in the
    machine's load hits both alike. ``lookup``: bilinear lookups of 200k random UV points
    in the maps; ``step``: :meth:`Trainer.step`. Ends with the tables on huge pages."""
    uv = torch.rand(200_000, 2, generator=torch.Generator().manual_seed(0))
    allocators = {"torch": lambda t: t.detach().clone(), "huge": hugepages.copy}
    calls = {
        "lookup": lambda: texture(state.avatar.maps.detach(), uv),
        "step": lambda: trainer.step(state),
    }
    samples = {kind: {call: ([], []) for call in calls} for kind in allocators}
    per_round = max(repeats // rounds, 2)
    for _ in range(rounds):
        for kind, allocate in allocators.items():
            _move_tables(state, allocate)
            for call, fn in calls.items():
                fn()  # the first call after a move pays its page faults
                wall, cpu = wall_cpu_samples(fn, per_round)
                samples[kind][call][0].extend(wall)
                samples[kind][call][1].extend(cpu)
    return {
        kind: {
            call: {"wall_ms": statistics.median(w), "cpu_ms": statistics.median(c)}
            for call, (w, c) in by_call.items()
        }
        for kind, by_call in samples.items()
    }


def whole_windows_ms(trainer, state, windows: int) -> dict:
    """Medians and means of ``Trainer.step``'s wall and CPU time over ``windows`` whole
    guard windows, after the first."""
    for _ in range(WINDOW + 2):
        trainer.step(state)
    wall, cpu = wall_cpu_samples(lambda: trainer.step(state), windows * WINDOW)
    return {
        "wall_ms": statistics.median(wall),
        "cpu_ms": statistics.median(cpu),
        "mean_wall_ms": statistics.mean(wall),
        "mean_cpu_ms": statistics.mean(cpu),
    }


def measure(num_gaussians: int, repeats: int, windows: int) -> dict:
    trainer, state = paper_scene(num_gaussians)
    whole = whole_windows_ms(trainer, state, windows)
    stages, touched = stage_functions(trainer, state)
    result = {name: median_wall_cpu_ms(fn, repeats) for name, fn in stages.items()}
    result["everything else"] = {
        key: max(whole[key] - sum(r[key] for r in result.values()), 0.0)
        for key in ("wall_ms", "cpu_ms")
    }
    return {
        "gaussians": state.avatar.num_gaussians,
        "uv_resolution": state.avatar.resolution,
        "channels": state.avatar.layout.channels,
        "touched_texels": touched,
        "stages": result,
        "whole": whole,
        "huge_pages": page_size_gain(trainer, state, repeats),
    }


def run(quick: bool) -> dict:
    with one_torch_thread():
        return {"runs": [measure(24_000, 5 if quick else 20, 1 if quick else 3)]}


def render(results: dict, figures: Path) -> str:
    import matplotlib.pyplot as plt

    r = results["runs"][0]
    stages, whole = r["stages"], r["whole"]
    rows = [
        [name, ms(stages[name]["wall_ms"]), ms(stages[name]["cpu_ms"]), str(BUDGET_MS[name])]
        for name in BUDGET_MS
    ]
    rows.append(
        [
            "**whole iteration**",
            f"**{ms(whole['wall_ms'])}**",
            f"**{ms(whole['cpu_ms'])}**",
            f"**{ITERATION_BUDGET_MS}**",
        ]
    )
    fig, ax = plt.subplots(figsize=(6.4, 3.2))
    names = list(BUDGET_MS)
    y = range(len(names))
    wall = [stages[n]["wall_ms"] for n in names]
    ax.barh([i + 0.27 for i in y], wall, height=0.27, label="measured, wall")
    cpu = [stages[n]["cpu_ms"] for n in names]
    ax.barh(list(y), cpu, height=0.27, label="measured, process CPU")
    ax.barh([i - 0.27 for i in y], [BUDGET_MS[n] for n in names], height=0.27, label="budget")
    ax.set_yticks(list(y), names, fontsize=8)
    ax.invert_yaxis()
    ax.set_xlabel("ms per iteration, forward + backward (median)")
    ax.legend(fontsize=8)
    # Results stored before the mean was measured have the median only.
    mean_wall = whole.get("mean_wall_ms", whole["wall_ms"])
    projected_min = mean_wall * 50_000 / 60_000
    mean_note = (
        f" Over whole guard windows the mean is {ms(mean_wall)} ms wall / "
        f"{ms(whole['mean_cpu_ms'])} ms CPU (each window's first steps also save the map "
        "rows they change into the undo journal)."
        if "mean_wall_ms" in whole
        else ""
    )
    return "\n\n".join(
        [
            f"{r['gaussians']:,} Gaussians, {r['uv_resolution']}² maps × {r['channels']} "
            f"channels, 512² image; one iteration's map gradient touches "
            f"{r['touched_texels']:,} texels. Stage times are each stage alone "
            "(forward + backward from detached inputs; 'sparse Adam' builds the maps' "
            "gradient from the iteration's lookups as it updates, as the trainer does); "
            "'everything else' is the whole "
            "iteration minus them. Wall and process CPU time (user + system, all threads) "
            "are medians; CPU / wall is the parallelism reached, and CPU time is the figure "
            "to compare across runs on a busy machine. The whole iteration is timed over "
            "whole windows of the step guard, after its first.",
            f"**The iteration: {ms(whole['wall_ms'])} ms wall against the "
            f"{ITERATION_BUDGET_MS} ms budget ({whole['wall_ms'] / ITERATION_BUDGET_MS:.2f}× "
            f"it; the paper's GPU: {PAPER_GPU_MS:.0f} ms), {ms(whole['cpu_ms'])} ms of CPU "
            f"({whole['cpu_ms'] / whole['wall_ms']:.2f} cores busy).**{mean_note} At this "
            f"rate 50k iterations take {projected_min:.0f} min (the paper: 120 min on an "
            "RTX 3090).",
            table(["stage", "wall ms", "CPU ms", "budget ms (wall)"], rows),
            _pages_note(r["huge_pages"]),
            save(fig, figures, "iteration_stages"),
        ]
    )


def _pages_note(pages: dict) -> str:
    huge, plain = pages["huge"], pages["torch"]

    def compare(what: str) -> str:
        h, p = huge[what], plain[what]
        return (
            f"{ms(h['wall_ms'])} ms wall / {ms(h['cpu_ms'])} ms CPU on huge pages against "
            f"{ms(p['wall_ms'])} / {ms(p['cpu_ms'])} on 4 KiB pages "
            f"({1 - h['cpu_ms'] / p['cpu_ms']:.0%} less CPU)"
        )

    return (
        "**What huge pages pay** (same run, the same tables moved between torch's allocator "
        "and `urhead.hugepages`): bilinear lookups of 200k random UV points in the maps "
        f"{compare('lookup')}; the whole iteration {compare('step')}. Medians over "
        "alternating rounds."
    )
