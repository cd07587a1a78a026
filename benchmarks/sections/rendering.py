"""Forward-only rendering FPS at 512²: a real avatar at the paper's settings (2048² maps,
SH degree 3, the procedural head) rendered by :meth:`Avatar.render`'s stages — what
``urhead render`` and a viewer do per frame. Each stage's wall time and process CPU time
(user + system, all threads) are medians over consecutive frames."""

from __future__ import annotations

import base64
import itertools
import statistics
import time
from dataclasses import replace
from pathlib import Path

import torch

from sections.common import ms, one_torch_thread, save, table
from sections.scene import paper_scene
from urhead._in_flight import default_depth, in_flight

TITLE = "Rendering FPS at 512² (forward only)"
STAGES = ("skinning", "displacement", "mesh branch", "Gaussian lift", "splatting")


@torch.no_grad()
def frame(avatar, params, camera, stamps: list | None = None) -> torch.Tensor:
    def mark(name):
        if stamps is not None:
            stamps.append((name, time.perf_counter(), time.process_time()))

    mark("start")
    verts, rotations = avatar.skin(params)
    mark("skinning")
    displaced, offsets = avatar.displace(verts, rotations)
    mark("displacement")
    mesh = avatar.shade_mesh(displaced, offsets, rotations, camera, False)
    mark("mesh branch")
    lift = avatar.lift_gaussians(verts, rotations, camera)
    mark("Gaussian lift")
    splat = avatar.splat(lift, camera, mesh.depth, mesh.rgba)  # over the mesh, as Avatar.render
    mark("splatting")
    return splat.image


def measure(num_gaussians: int, repeats: int) -> dict:
    trainer, state = paper_scene(num_gaussians)
    # As `urhead render` holds a saved avatar: maps without gradient (frozen), the same
    # tensors as the fit's.
    avatar = replace(state.avatar, maps=state.avatar.maps.detach())
    record = trainer.subject.train[0]
    params = avatar.frame(record.timestep)
    camera = record.camera
    image = frame(avatar, params, camera)  # warm-up
    per_stage = {s: [] for s in STAGES}
    per_stage_cpu = {s: [] for s in STAGES}
    totals, totals_cpu = [], []
    for _ in range(repeats):
        stamps = []
        frame(avatar, params, camera, stamps)
        for (_, t0, c0), (name, t1, c1) in itertools.pairwise(stamps):
            per_stage[name].append((t1 - t0) * 1e3)
            per_stage_cpu[name].append((c1 - c0) * 1e3)
        totals.append((stamps[-1][1] - stamps[0][1]) * 1e3)
        totals_cpu.append((stamps[-1][2] - stamps[0][2]) * 1e3)

    def median(xs):
        return sorted(xs)[len(xs) // 2]

    return dict(
        gaussians=avatar.num_gaussians,
        faces=int(avatar.head.num_faces),
        vertices=int(avatar.head.num_vertices),
        uv_resolution=avatar.resolution,
        stages={s: median(v) for s, v in per_stage.items()},
        stages_cpu={s: median(v) for s, v in per_stage_cpu.items()},
        total_ms=median(totals),
        total_cpu_ms=median(totals_cpu),
        fps=1e3 / median(totals),
        sequence=sequence_rates(avatar, trainer.subject.train, camera, rounds=max(repeats // 6, 2)),
        thumbnail=thumbnail(image),
    )


def sequence_rates(avatar, frames, camera, rounds: int, length: int = 24) -> dict:
    """ms a frame over a sequence (``length`` frames of ``frames``' parameters, one camera,
    as ``urhead render`` / ``reenact`` do), rendered one at a time and with
    :func:`~urhead._in_flight.default_depth` frames in flight; the two alternate ``rounds``
    times. Medians of the rounds, wall and process CPU time."""
    params = [avatar.frame(frames[i % len(frames)].timestep) for i in range(length)]
    depths = {"one at a time": 1, "in flight": default_depth()}
    samples = {name: ([], []) for name in depths}

    def render(p):
        return avatar.render(p, camera).image

    with torch.no_grad():
        for _ in range(rounds):
            for name, depth in depths.items():
                t0, c0 = time.perf_counter(), time.process_time()
                for _ in in_flight(render, params, depth):
                    pass
                samples[name][0].append((time.perf_counter() - t0) * 1e3 / length)
                samples[name][1].append((time.process_time() - c0) * 1e3 / length)
    return {
        "depth": depths["in flight"],
        **{
            name: {"wall_ms": statistics.median(w), "cpu_ms": statistics.median(c)}
            for name, (w, c) in samples.items()
        },
    }


def thumbnail(image: torch.Tensor, side: int = 128) -> str:
    """A (side, side, 3) uint8 RGB thumbnail as base64, small enough for results.json."""
    small = torch.nn.functional.adaptive_avg_pool2d(image.permute(2, 0, 1), side)
    pixels = (small.permute(1, 2, 0).clamp(0, 1) * 255).round().to(torch.uint8)
    return base64.b64encode(pixels.numpy().tobytes()).decode()


def run(quick: bool) -> dict:
    with one_torch_thread():
        counts = (24_000,) if quick else (24_000, 100_000)
        return {"runs": [measure(n, 10 if quick else 30) for n in counts]}


def render(results: dict, figures: Path) -> str:
    import matplotlib.pyplot as plt
    import numpy as np

    runs = results["runs"]
    body = table(
        ["Gaussians", "", *STAGES, "frame ms", "FPS"],
        [
            [
                f"{r['gaussians']:,}",
                kind,
                *(ms(r[stages][s]) for s in STAGES),
                ms(r[total]),
                f"{r['fps']:.1f}" if kind == "wall" else "",
            ]
            for r in runs
            for kind, stages, total in (
                ("wall", "stages", "total_ms"),
                ("CPU", "stages_cpu", "total_cpu_ms"),
            )
        ],
    )
    fig, ax = plt.subplots(figsize=(6, 0.6 * len(runs) + 1.2))
    left = np.zeros(len(runs))
    for s in STAGES:
        widths = np.array([r["stages"][s] for r in runs])
        ax.barh(range(len(runs)), widths, left=left, label=s)
        left += widths
    ax.set_yticks(range(len(runs)), [f"{r['gaussians']:,} Gaussians" for r in runs])
    ax.set_xlabel("ms per 512² frame (median)")
    ax.legend(fontsize=7, ncols=3, loc="upper center", bbox_to_anchor=(0.5, -0.35))
    parts = [save(fig, figures, "rendering_stages")]
    shown = next((r for r in runs if r.get("thumbnail")), None)
    if shown:
        fig, ax = plt.subplots(figsize=(2.4, 2.4))
        pixels = np.frombuffer(base64.b64decode(shown["thumbnail"]), dtype=np.uint8)
        side = round((pixels.size / 3) ** 0.5)
        ax.imshow(pixels.reshape(side, side, 3))
        ax.set_axis_off()
        parts.append(save(fig, figures, "rendering_frame"))
    r0 = runs[0]
    sequences = [r for r in runs if r.get("sequence")]
    sequence_table = table(
        ["Gaussians", "frames in flight", "wall ms a frame", "FPS", "CPU ms a frame"],
        [
            [
                f"{r['gaussians']:,}",
                str(1 if name == "one at a time" else r["sequence"]["depth"]),
                ms(r["sequence"][name]["wall_ms"]),
                f"{1e3 / r['sequence'][name]['wall_ms']:.1f}",
                ms(r["sequence"][name]["cpu_ms"]),
            ]
            for r in sequences
            for name in ("one at a time", "in flight")
        ],
    )
    return "\n\n".join(
        [
            f"An avatar on the built-in procedural head ({r0['vertices']} vertices, "
            f"{r0['faces']} faces) with {r0['uv_resolution']}² maps (56 channels, SH 3), "
            "initialised from a synthetic subject's first frame, rendered by the avatar's own "
            "stages: skinning, displacement along the normal map, the mesh branch (raster, "
            "map lookups at covered pixels, SH colour, antialias), the Gaussians lifted from "
            "their UV points and splatted with occlusion against the mesh depth, over the mesh "
            "in the same pass (T·mesh RGBA added per pixel). No gradients; medians of "
            "consecutive frames, in wall time and in process CPU time (user + system, all "
            "threads; the figure to compare across runs on a busy machine).",
            body,
            "A sequence of frames (different parameters, one camera, as `urhead render` and "
            "`reenact` render them, through `avatar.render`): one at a time, and a few in "
            "flight (`urhead._in_flight`: one frame's Python and serial stretches overlap "
            "another's kernels in the shared pool; the frames are bit for bit the same). The "
            "rate a video renders at; a single frame's latency is the table above's. Medians "
            "of alternating rounds.",
            sequence_table,
            " ".join(parts),
        ]
    )
