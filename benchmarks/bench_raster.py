"""Mesh branch benchmark: rasterize → interpolate → texture → SH stand-in → antialias,
forward + backward, with urhead's Rust ops and with the plain-torch references.

Scene (as the criterion bench ``rust/urhead-core/benches/raster.rs``): a bumpy sphere of
10 080 faces / 5 112 vertices at 512 × 512 covering ~46 % of the image, a 2048² × 56
float32 texture, a fixed 56 → 3 linear map standing in for SH evaluation, a composite over
a background by coverage, and antialiasing of the 3-channel image.

The brute-force reference cannot run at that size (its rasterizer tests every triangle at
every pixel; its antialiasing is a Python loop over pixel pairs), so both chains are also
timed on a reduced scene, and the reference's full-size time is *estimated* by scaling
each of its ops from the reduced scene: rasterize by pixels × faces, the others by
pixels. Interpolate and texture references are additionally timed at full size.

Usage: python benchmarks/bench_raster.py [--repeats N]
"""

from __future__ import annotations

import argparse
import itertools
import math
import statistics
import time

import torch

import urhead
from urhead import ops
from urhead.ops import _reference as ref


def bumpy_sphere(n_lat, n_lon, radius=0.115):
    verts, uvs = [], []
    for i in range(n_lat + 1):
        theta = math.pi * i / n_lat
        for j in range(n_lon):
            phi = 2 * math.pi * j / n_lon
            r = radius * (
                1 + 0.08 * math.sin(3 * phi) * math.sin(2 * theta) + 0.05 * math.cos(5 * theta)
            )
            verts.append(
                [
                    r * math.sin(theta) * math.cos(phi),
                    1.2 * r * math.cos(theta),
                    0.6 + r * math.sin(theta) * math.sin(phi),
                ]
            )
            uvs.append([j / n_lon, 1 - i / n_lat])
    faces = []
    for i in range(n_lat):
        for j in range(n_lon):
            a, b = i * n_lon + j, i * n_lon + (j + 1) % n_lon
            c, d = (i + 1) * n_lon + j, (i + 1) * n_lon + (j + 1) % n_lon
            faces += [[a, c, b], [b, c, d]]
    return torch.tensor(verts), torch.tensor(faces, dtype=torch.int32), torch.tensor(uvs)


class Scene:
    def __init__(self, n_lat, n_lon, side, tex_side, channels=56, seed=0):
        g = torch.Generator().manual_seed(seed)
        self.verts, self.faces, self.uvs = bumpy_sphere(n_lat, n_lon)
        focal = 900.0 * side / 512
        k = torch.tensor([[focal, 0, side / 2], [0, focal, side / 2], [0, 0, 1.0]])
        self.camera = urhead.Camera(k, torch.eye(4), side, side)
        self.tex = torch.rand(tex_side, tex_side, channels, generator=g) * 2 - 1
        self.mix = (torch.rand(channels, 3, generator=g) - 0.5) * 0.4
        self.background = torch.tensor([0.5, 0.5, 0.5])
        self.grad = torch.rand(side, side, 3, generator=g) * 2 - 1
        self.topology = ops.antialias_topology(self.faces, self.verts.shape[0])


def chain(scene, impl, timings=None):
    """Forward and backward of the whole chain; per-op forward and backward times are
    recorded into ``timings`` (op → list of ms) when given."""
    verts = scene.verts.clone().requires_grad_(True)
    tex = scene.tex.clone().requires_grad_(True)
    stamps = []

    def mark(name):
        stamps.append((name, time.perf_counter()))

    class Marker(torch.autograd.Function):
        """Records when the backward pass reaches this point of the graph, i.e. when the
        backward of the op consuming it (``name``) has finished."""

        @staticmethod
        def forward(ctx, x, name):
            ctx.name = name
            return x.view_as(x)

        @staticmethod
        def backward(ctx, g):
            mark(ctx.name)
            return g, None

    mark("start")
    raster = impl.rasterize(verts, scene.faces, scene.camera)
    mark("rasterize")
    bary = Marker.apply(raster.bary, "interpolate_bwd")
    raster = raster._replace(bary=bary)
    uv = impl.interpolate(scene.uvs, raster, scene.faces)
    mark("interpolate")
    uv = Marker.apply(uv, "texture_bwd")
    sampled = impl.texture(tex, uv)
    mark("texture")
    sampled = Marker.apply(sampled, "sh_composite_bwd")
    covered = (raster.tri_id >= 0)[..., None]
    color = torch.where(covered, sampled @ scene.mix, scene.background)
    mark("sh_composite")
    color = Marker.apply(color, "antialias_bwd")
    image = impl.antialias(color, raster, verts, scene.faces, scene.camera)
    mark("antialias")
    image = Marker.apply(image, "loss_bwd")
    loss = (image * scene.grad).sum()
    mark("loss")
    loss.backward()
    mark("rasterize_bwd")
    if timings is not None:
        times = dict(stamps)
        order = [n for n, _ in stamps]
        for a, b in itertools.pairwise(order):
            timings.setdefault(b, []).append((times[b] - times[a]) * 1e3)
    return (times := dict(stamps))["rasterize_bwd"] - times["start"]


def chain_covered_only(scene):
    """The same chain, but texture and SH run only on covered pixels (gather, then scatter
    into the background image): what a trainer can do to halve the 56-channel traffic."""
    verts = scene.verts.clone().requires_grad_(True)
    tex = scene.tex.clone().requires_grad_(True)
    start = time.perf_counter()
    raster = ops.rasterize(verts, scene.faces, scene.camera)
    uv = ops.interpolate(scene.uvs, raster, scene.faces)
    side = scene.camera.height * scene.camera.width
    idx = (raster.tri_id.reshape(-1) >= 0).nonzero()[:, 0]
    shaded = ops.texture(tex, uv.reshape(-1, 2)[idx]) @ scene.mix
    color = scene.background.repeat(side, 1).index_put((idx,), shaded).reshape(*uv.shape[:2], 3)
    image = ops.antialias(color, raster, verts, scene.faces, scene.camera)
    (image * scene.grad).sum().backward()
    return time.perf_counter() - start


class Rust:
    rasterize = staticmethod(ops.rasterize)
    interpolate = staticmethod(ops.interpolate)
    texture = staticmethod(ops.texture)

    @staticmethod
    def antialias(color, raster, verts, faces, camera, topology=None):
        return ops.antialias(color, raster, verts, faces, camera, topology)


class Reference:
    rasterize = staticmethod(ref.rasterize)
    interpolate = staticmethod(ref.interpolate)
    texture = staticmethod(ref.texture)
    antialias = staticmethod(ref.antialias)


def median_ms(fn, repeats):
    fn()  # warm-up
    return statistics.median(fn() * 1e3 for _ in range(repeats))


def per_op(scene, impl, repeats):
    timings = {}
    chain(scene, impl)
    for _ in range(repeats):
        chain(scene, impl, timings)
    return {k: statistics.median(v) for k, v in timings.items()}


OPS = ("rasterize", "interpolate", "texture", "antialias")


def measure_ops(scene, impl, repeats) -> dict[str, float]:
    """Median forward+backward ms of each op inside the chain (its forward stage plus the
    backward stage that ends when its backward has run), and of the whole chain."""
    stages = per_op(scene, impl, repeats)
    ops_ms = {op: stages[op] + stages[f"{op}_bwd"] for op in OPS}
    ops_ms["chain"] = sum(stages.values())
    return ops_ms


def report(title, ops_ms):
    print(f"  {title}")
    for name, ms in ops_ms.items():
        print(f"    {name:18s} {ms:9.2f} ms")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=9)
    args = parser.parse_args()
    print(
        f"torch {torch.__version__}, torch threads {torch.get_num_threads()}, urhead threads ",
        end="",
    )
    from urhead._threads import num_threads

    print(num_threads())

    full = Scene(70, 72, 512, 2048)
    covered = float((ops.rasterize(full.verts, full.faces, full.camera).tri_id >= 0).float().mean())
    print(
        f"full scene: {full.faces.shape[0]} faces, 512², {100 * covered:.1f} % covered, "
        f"texture 2048² × 56 float32"
    )
    rust_full = median_ms(lambda: chain(full, Rust), args.repeats)
    print(f"urhead chain forward+backward, median of {args.repeats}: {rust_full:.1f} ms")
    report("per stage (forward marks, then backward marks):", per_op(full, Rust, args.repeats))
    covered_only = median_ms(lambda: chain_covered_only(full), args.repeats)
    print(f"urhead chain with texture + SH on covered pixels only: {covered_only:.1f} ms")

    small = Scene(20, 21, 128, 512, seed=1)
    small_faces, small_pixels = small.faces.shape[0], 128 * 128
    print(f"\nreduced scene: {small_faces} faces, 128², texture 512² × 56")
    rust_small = median_ms(lambda: chain(small, Rust), args.repeats)
    ref_reps = max(3, args.repeats // 3)
    ref_small_ops = per_op(small, Reference, ref_reps)
    ref_small = sum(ref_small_ops.values())
    print(f"urhead chain:    {rust_small:9.2f} ms")
    ratio = ref_small / rust_small
    print(f"reference chain: {ref_small:9.2f} ms   (measured; ratio reference/urhead {ratio:.0f}×)")
    report("reference per stage:", ref_small_ops)

    pixel_scale = (512 * 512) / small_pixels
    raster_scale = pixel_scale * full.faces.shape[0] / small_faces
    estimate = sum(
        ms * (raster_scale if name in ("rasterize", "rasterize_bwd") else pixel_scale)
        for name, ms in ref_small_ops.items()
    )
    print(
        f"\nreference at full size, ESTIMATED by scaling the reduced run (rasterize × pixels·faces "
        f"= {raster_scale:.0f}, other stages × pixels = {pixel_scale:.0f}): {estimate / 1e3:.1f} s "
        f"→ ratio ≈ {estimate / rust_full:.0f}×"
    )

    # Interpolate and texture references do run at full size: measured ratios.
    raster = ops.rasterize(full.verts, full.faces, full.camera)
    uv = ops.interpolate(full.uvs, raster, full.faces)
    g_uv = torch.rand(uv.shape)
    g_tex = torch.rand(512, 512, 56) * (raster.tri_id >= 0)[..., None]

    def op_time(fn, inputs, grad):
        def run():
            xs = [x.clone().requires_grad_(True) for x in inputs]
            t = time.perf_counter()
            (fn(*xs) * grad).sum().backward()
            return time.perf_counter() - t

        return median_ms(run, max(3, args.repeats // 3))

    print("\nmeasured at full size, forward+backward:")
    for name, rust_fn, ref_fn, inputs, grad in [
        (
            "interpolate",
            lambda a, b: ops.interpolate(a, raster._replace(bary=b), full.faces),
            lambda a, b: ref.interpolate(a, raster._replace(bary=b), full.faces),
            [full.uvs, raster.bary],
            g_uv,
        ),
        ("texture", ops.texture, ref.texture, [full.tex, uv], g_tex),
    ]:
        r, e = op_time(rust_fn, inputs, grad), op_time(ref_fn, inputs, grad)
        print(f"  {name:12s} urhead {r:8.2f} ms   reference {e:8.2f} ms   ratio {e / r:5.1f}×")


if __name__ == "__main__":
    main()
