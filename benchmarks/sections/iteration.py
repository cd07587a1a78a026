"""One training iteration at the paper's settings (512² image, 2048² maps × 56 channels,
SH degree 3, 24k Gaussians), forward + backward, against the DESIGN.md budget.

The whole iteration is :meth:`Trainer.step` itself (render, loss, backward, sparse Adam on
maps and FLAME rows, UV error accumulation). Each stage is also timed alone, forward and
backward, from detached inputs with a random upstream gradient, with the avatar's own stage
methods and, as in the trainer, its map lookups gathered into one sparse gradient built
within the stage; "everything else" is the whole minus the stages (autograd bookkeeping, the loss's
small terms, the FLAME-row Adam, error accumulation, Python).
"""

from __future__ import annotations

import statistics
import time
from pathlib import Path

import torch

from sections.common import ms, save, table
from sections.scene import paper_scene
from urhead.losses import l1, ssim
from urhead.ops import TextureGather

TITLE = "Whole training iteration at the paper's settings"

BUDGET_MS = {
    "skinning + displacement": 2,
    "mesh branch": 15,
    "Gaussian lift from UV": 3,
    "splatting": 40,
    "SSIM + L1": 10,
    "sparse Adam": 10,
    "everything else": 20,
}


def _median_ms(fn, repeats: int) -> float:
    fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)


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
        image = avatar.splat(lift, camera, mesh.depth).image
    h, w = camera.height, camera.width
    g_verts = torch.randn(verts.shape, generator=g) * 1e-3
    g_image = torch.randn(h, w, 3, generator=g) * 1e-3

    # As in Trainer.step, map lookups record their gradient in a TextureGather; each
    # stage includes building its share of the sparse map gradient.
    def skinning():
        gather = TextureGather(avatar.maps)
        v, r = avatar.skin(avatar.frame(frame.timestep))
        d, _ = avatar.displace(v, r, gather)
        d.backward(g_verts)
        gather.gradient()
        clear()

    def mesh_branch():
        gather = TextureGather(avatar.maps)
        m = avatar.shade_mesh(_leaf(displaced), offsets, rotations, camera, False, gather)
        m.image.backward(g_image)
        gather.gradient()
        clear()

    def lift_stage():
        gather = TextureGather(avatar.maps)
        out = avatar.lift_gaussians(_leaf(verts), rotations, camera, gather)
        tensors = [out.means, out.quats, out.scales, out.opacities, out.colors]
        torch.autograd.backward(tensors, [torch.ones_like(t) * 1e-3 for t in tensors])
        gather.gradient()
        clear()

    leaves = lift._replace(
        means=_leaf(lift.means),
        quats=_leaf(lift.quats),
        scales=_leaf(lift.scales),
        opacities=_leaf(lift.opacities),
        colors=_leaf(lift.colors),
    )

    def splatting():
        out = avatar.splat(leaves, camera, mesh.depth)
        out.image.backward(g_image)

    def loss_stage():
        x = _leaf(image)
        loss = 0.8 * l1(x, frame.image) + 0.2 * (1 - ssim(x, frame.image))
        loss.backward()

    # A real iteration's sparse gradient for the optimiser stage.
    gather = TextureGather(avatar.maps)
    out = avatar.render(params, camera, gather=gather)
    (out.image - frame.image).abs().mean().backward()
    map_grad = gather.gradient()
    clear()

    def adam():
        avatar.maps.grad = map_grad
        state.maps_opt.step()
        avatar.maps.grad = None

    return {
        "skinning + displacement": skinning,
        "mesh branch": mesh_branch,
        "Gaussian lift from UV": lift_stage,
        "splatting": splatting,
        "SSIM + L1": loss_stage,
        "sparse Adam": adam,
    }, int(map_grad._nnz())


def measure(num_gaussians: int, repeats: int) -> dict:
    trainer, state = paper_scene(num_gaussians)
    whole = _median_ms(lambda: trainer.step(state), repeats)
    stages, touched = stage_functions(trainer, state)
    result = {name: _median_ms(fn, repeats) for name, fn in stages.items()}
    result["everything else"] = max(whole - sum(result.values()), 0.0)
    return {
        "gaussians": state.avatar.num_gaussians,
        "uv_resolution": state.avatar.resolution,
        "channels": state.avatar.layout.channels,
        "touched_texels": touched,
        "stages_ms": result,
        "whole_ms": whole,
    }


def run(quick: bool) -> dict:
    return {"runs": [measure(24_000, 5 if quick else 20)]}


def render(results: dict, figures: Path) -> str:
    import matplotlib.pyplot as plt

    r = results["runs"][0]
    stages = r["stages_ms"]
    rows = [[name, ms(stages[name]), str(BUDGET_MS[name])] for name in BUDGET_MS]
    rows.append(["**whole iteration**", f"**{ms(r['whole_ms'])}**", "**100**"])
    fig, ax = plt.subplots(figsize=(6.4, 3.2))
    names = list(BUDGET_MS)
    y = range(len(names))
    ax.barh([i + 0.2 for i in y], [stages[n] for n in names], height=0.4, label="measured")
    ax.barh([i - 0.2 for i in y], [BUDGET_MS[n] for n in names], height=0.4, label="budget")
    ax.set_yticks(list(y), names, fontsize=8)
    ax.invert_yaxis()
    ax.set_xlabel("ms per iteration, forward + backward (median)")
    ax.legend(fontsize=8)
    projected_min = r["whole_ms"] * 50_000 / 60_000
    return "\n\n".join(
        [
            f"{r['gaussians']:,} Gaussians, {r['uv_resolution']}² maps × {r['channels']} "
            f"channels, 512² image; one iteration's map gradient touches "
            f"{r['touched_texels']:,} texels. Stage times are each stage alone "
            "(forward + backward from detached inputs); 'everything else' is the whole "
            f"iteration minus them. At this rate 50k iterations take {projected_min:.0f} min "
            "(the paper: 120 min on an RTX 3090).",
            table(["stage", "measured ms", "budget ms"], rows),
            save(fig, figures, "iteration_stages"),
        ]
    )
