"""The URHead avatar: a head model, the packed UV maps Θ_u, the Gaussians' UV points and the
per-frame FLAME parameters, and its differentiable renderer (DESIGN.md steps 1–6).

Normals. N is stored in the head's rest pose. A posed normal is ``R·N`` normalised, with
``R`` the vertex's skinning rotation (interpolated with the barycentrics between vertices).
Expression and pose-corrective blendshapes bend the surface without rotating N; that is the
approximation every UV-normal-map avatar makes, and N is learnt to absorb it on average.

Positions. A vertex is displaced along its posed normal, ``v̂ = v + D(uv_v)·n_v`` (the mesh
branch). A Gaussian at UV point (u, v) sits at ``x = P(u, v) + D(u, v)·n(u, v)``, the
paper's Eq. 2, with P the undisplaced posed mesh at that point: at a vertex the two agree.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import NamedTuple

import numpy as np
import torch

from urhead.camera import Camera
from urhead.head.model import HeadModel, LbsTables
from urhead.model.lift_rows import GaussianLift, lift_rows
from urhead.model.map_layout import (
    SHADING_FEATURES,
    MapLayout,
    shading_features,
    shading_gain,
)
from urhead.ops import (
    antialias,
    antialias_topology,
    covered_pixels,
    half_maps,
    interpolate,
    lbs,
    rasterize,
    rasterize_gaussians,
    rotate_normalize,
    scatter_pixels,
    sh_texture,
    texture,
)
from urhead.ops.texture import TextureGather

POSE_SIZE = 15
"""FLAME pose: global, neck, jaw, left eye, right eye axis-angles."""


def flame_rows(flame: dict, count: int, num_expr: int) -> np.ndarray:
    """(count, num_expr + 18) float32 rows ``expr | pose (15) | translation`` — the layout of
    :attr:`Avatar.frame_params` — from FLAME arrays (FORMATS.md keys) holding ``count``
    frames; the expression is truncated or zero-padded to ``num_expr``."""
    expr = np.zeros((count, num_expr), np.float32)
    given = np.asarray(flame["expr"], np.float32).reshape(count, -1)[:, :num_expr]
    expr[:, : given.shape[1]] = given
    rest = [
        np.asarray(flame[k], np.float32).reshape(count, -1)
        for k in ("rotation", "neck_pose", "jaw_pose", "eyes_pose", "translation")
    ]
    return np.concatenate([expr, *rest], 1)


class FlameParams(NamedTuple):
    """One frame's FLAME parameters (1-D tensors)."""

    expr: torch.Tensor
    """(E,) expression coefficients."""
    pose: torch.Tensor
    """(15,) axis-angles: global, neck, jaw, left eye, right eye."""
    transl: torch.Tensor
    """(3,) translation, metres."""

    @classmethod
    def from_row(cls, row: torch.Tensor, num_expr: int) -> FlameParams:
        """A frame table's row ``[expr (num_expr), pose (15), transl (3)]`` split up."""
        e = num_expr
        return cls(row[:e], row[e : e + POSE_SIZE], row[e + POSE_SIZE :])


class MeshRender(NamedTuple):
    image: torch.Tensor
    """(H, W, 3) antialiased mesh colour over the background."""
    alpha: torch.Tensor
    """(H, W) antialiased coverage."""
    normals: torch.Tensor | None
    """(P, 3) unit normals in OpenCV camera axes at the covered pixels, when asked for."""
    pixels: torch.Tensor
    """(P,) int64 flat indices of the covered pixels."""
    uv: torch.Tensor
    """(P, 2) UV coordinates seen at the covered pixels (detached)."""
    depth: torch.Tensor
    """(H, W) linear view depth, +inf where empty."""
    verts: torch.Tensor
    """(V, 3) displaced posed vertices."""
    offsets: torch.Tensor
    """(V, 3) displacement of each vertex, v̂ − v."""
    tri_id: torch.Tensor
    """(H, W) int32 triangle seen at each pixel centre, −1 where empty."""
    rgba: torch.Tensor
    """(H, W, 4) the antialiased colour and coverage ``image`` and ``alpha`` view."""


class GaussianRender(NamedTuple):
    image: torch.Tensor
    """(H, W, 3) the Gaussians over what was behind them (in :meth:`Avatar.render` the
    mesh: the frame's image); premultiplied over black when nothing was."""
    transmittance: torch.Tensor
    """(H, W) transmittance left after the Gaussians."""
    radii: torch.Tensor
    """(N, 2) int32 screen radii (0 = culled)."""
    lift: GaussianLift


class Render(NamedTuple):
    image: torch.Tensor
    """(H, W, 3) the composite: Gaussians over the mesh over the background."""
    mesh: MeshRender
    gaussians: GaussianRender | None


class PixelRays:
    """(H·W, 3) float32 unit directions of a camera's pixel rays (from the camera centre
    through each pixel centre) in the camera's axes, kept for the last camera asked for: a
    fit renders the same camera over and over. Safe for frames rendered on several
    threads at once: the camera and its rays are kept as one pair, read and replaced whole."""

    def __init__(self):
        self._kept: tuple[str, torch.Tensor] | None = None

    def __call__(self, camera: Camera) -> torch.Tensor:
        key = repr(camera.core_args())
        kept = self._kept
        if kept is None or kept[0] != key:
            kept = self._kept = (key, _pixel_rays(camera))
        return kept[1]


def _pixel_rays(camera: Camera) -> torch.Tensor:
    h, w = camera.height, camera.width
    ys, xs = torch.meshgrid(
        torch.arange(h, dtype=torch.float64) + 0.5,
        torch.arange(w, dtype=torch.float64) + 0.5,
        indexing="ij",
    )
    k = camera.K.double()
    cam = torch.stack([(xs - k[0, 2]) / k[0, 0], (ys - k[1, 2]) / k[1, 1], torch.ones_like(xs)], -1)
    cam = cam.reshape(-1, 3)
    return (cam / cam.norm(dim=-1, keepdim=True)).float().contiguous()


@dataclass
class Avatar:
    """Everything a fitted avatar is. Tensors are float32 on the CPU.

    - ``maps`` (H, R, layout.channels): the UV maps (a leaf tensor; trained in place); H = R
      but for a head whose atlas is a window of rows (:mod:`urhead.head.leave_out`).
    - ``gaussian_uv`` (N, 2), ``gaussian_face`` (N,) int64, ``gaussian_bary`` (N, 3): each
      Gaussian's UV point, the face whose UV triangle holds it and its barycentrics there.
    - ``shape`` (S,) identity coefficients; ``static_offset`` (V, 3) or None (VHAP's
      per-vertex offsets), both fixed.
    - ``timesteps`` (T,) int64 and ``frame_params`` (T, E + 18): the per-frame expression,
      pose and translation of the training frames (a leaf tensor; trained).
    - ``background`` (3,) colour behind the head.
    """

    head: HeadModel
    layout: MapLayout
    maps: torch.Tensor
    gaussian_uv: torch.Tensor
    gaussian_face: torch.Tensor
    gaussian_bary: torch.Tensor
    shape: torch.Tensor
    static_offset: torch.Tensor | None
    timesteps: torch.Tensor
    frame_params: torch.Tensor
    background: torch.Tensor
    depth_eps: float = 0.01
    _tables: HeadTables | None = field(default=None, init=False, repr=False)
    _rays: PixelRays = field(default_factory=PixelRays, init=False, repr=False)
    _face_verts: tuple | None = field(default=None, init=False, repr=False)
    _frozen_rows: dict = field(default_factory=dict, init=False, repr=False)

    @property
    def num_expr(self) -> int:
        return self.frame_params.shape[1] - POSE_SIZE - 3

    @property
    def num_gaussians(self) -> int:
        return self.gaussian_uv.shape[0] if self.layout.gaussians else 0

    @property
    def resolution(self) -> int:
        """The atlas side: the maps' width (their height is less when the head's atlas is
        a window of rows, :mod:`urhead.head.leave_out`)."""
        return self.maps.shape[1]

    def frame(self, timestep: int) -> FlameParams:
        """The trained parameters of a training timestep (differentiable rows)."""
        row = self.frame_row(timestep)
        return self.split_params(self.frame_params[row])

    def frame_row(self, timestep: int) -> int:
        rows = (self.timesteps == int(timestep)).nonzero()
        if rows.numel() == 0:
            raise KeyError(f"timestep {timestep} is not a training frame of this avatar")
        return int(rows[0, 0])

    def split_params(self, row: torch.Tensor) -> FlameParams:
        return FlameParams.from_row(row, self.num_expr)

    def params_from_flame(self, flame: dict) -> FlameParams:
        """FLAME parameters of a dataset frame (FORMATS.md keys) as :class:`FlameParams`,
        expression truncated or zero-padded to this avatar's count."""
        return self.split_params(torch.from_numpy(flame_rows(flame, 1, self.num_expr)[0]))

    # --- rendering -------------------------------------------------------------------

    def tables(self) -> HeadTables:
        """Constant tensors derived from the head and identity, built once."""
        if self._tables is None:
            self._tables = head_tables(self.head, self.shape, self.static_offset, self.num_expr)
        return self._tables

    def render(
        self,
        params: FlameParams,
        camera: Camera,
        *,
        gaussians: bool = True,
        occlusion_aware: bool = True,
        normals: bool = False,
        gather: TextureGather | None = None,
        sh_degree: int | None = None,
    ) -> Render:
        """Renders one frame. Differentiable in ``maps`` (sparse gradient) and ``params``.

        Args:
            params: the frame's :class:`FlameParams`.
            camera: the view.
            gaussians: include the Gaussian layer (False renders the mesh branch alone).
            occlusion_aware: skip Gaussian samples behind the mesh (depth + ``depth_eps``).
            normals: also return the mesh normals at covered pixels (for the normal loss).
            gather: route the maps' gradient of every lookup into this
                :class:`~urhead.ops.TextureGather` (one coalesced gradient per iteration)
                instead of ``maps.grad``.
            sh_degree: evaluate colour up to this SH degree (default: the layout's; the fit
                raises it progressively).
        """
        verts, rotations = self.skin(params)
        displaced, offsets = self.displace(verts, rotations, gather)
        mesh = self.shade_mesh(
            displaced, offsets, rotations, camera, normals, gather, sh_degree=sh_degree
        )
        if not (gaussians and self.layout.gaussians and self.num_gaussians > 0):
            return Render(mesh.image, mesh, None)
        lift = self.lift_gaussians(verts, rotations, camera, gather, sh_degree=sh_degree)
        splats = self.splat(lift, camera, mesh.depth if occlusion_aware else None, mesh.rgba)
        return Render(splats.image, mesh, splats)

    # The stages of :meth:`render`, public so benchmarks and exporters can run them alone.

    def skin(self, params: FlameParams) -> tuple[torch.Tensor, torch.Tensor]:
        """FLAME skinning: ``(verts (V, 3), rotations (V, 3, 3))``."""
        return skin(self.tables().lbs, params)

    def lookup(self, uv: torch.Tensor, gather: TextureGather | None = None) -> torch.Tensor:
        """The maps at UV points (..., 2) → (..., channels), bilinear."""
        return texture(self.maps, uv) if gather is None else gather.sample(uv)

    def lookup_fixed(self, uv: torch.Tensor, gather: TextureGather | None = None) -> torch.Tensor:
        """:meth:`lookup` at UV points that stay put from frame to frame (the vertices', the
        Gaussians'). While the maps are frozen — no gradient asked of them, as in a finished
        or loaded avatar — the rows are kept and reused until the maps or ``uv`` change (an
        in-place edit bumps either's version): a rendered sequence looks them up once, not
        every frame. A fit's maps require grad, so its lookups are never kept. The rows
        returned are shared: do not edit them in place."""
        if gather is not None or self.maps.requires_grad or uv.requires_grad:
            return self.lookup(uv, gather)
        kept = self._kept_for_maps()
        entry = kept.get(id(uv))  # the entry holds uv itself, so its id is not reused
        if entry is None or entry[1] != uv._version:
            entry = kept[id(uv)] = (uv, uv._version, texture(self.maps, uv))
        return entry[2]

    def _kept_for_maps(self) -> dict:
        """What is kept for the frozen maps (rows at fixed UV points, their float16 copy),
        emptied first if the maps are other ones or were edited in place."""
        maps, kept = self.maps, self._frozen_rows
        held = kept.get("maps")
        if held is None or held[0] is not maps or held[1] != maps._version:
            kept.clear()  # other maps, or these edited in place: everything kept is stale
            kept["maps"] = (maps, maps._version)
        return kept

    def pixel_maps_source(
        self, gather: TextureGather | None = None, extra: slice | None = None
    ) -> torch.Tensor:
        """The maps the mesh branch's covered pixels read, the colour and ``extra``: while
        the maps are frozen (no gradient asked of them, no gather) a float16 copy of the
        channels up to the last of those (a prefix, so every channel keeps its index), made
        once and kept until the maps change or a wider prefix is asked for — fewer bytes
        for the pixels' random texel reads, the values within float16 rounding (NUMERICS.md
        case 34); otherwise, or for maps out of float16's range, the maps themselves."""
        if gather is not None or self.maps.requires_grad or self.maps.dtype != torch.float32:
            return self.maps
        stop = self.layout.color.stop if extra is None else max(self.layout.color.stop, extra.stop)
        kept = self._kept_for_maps()
        if "float16" not in kept or kept["float16"][0] < stop:
            kept["float16"] = (stop, half_maps(self.maps, stop))
        half = kept["float16"][1]
        return self.maps if half is None else half

    def displace(self, verts, rotations, gather=None) -> tuple[torch.Tensor, torch.Tensor]:
        """``(v̂ (V, 3), v̂ − v)``: each vertex moved by D along its posed normal."""
        at_vertex = self.layout.split(self.lookup_fixed(self.tables().vertex_uv, gather))
        vertex_normal = rotate_normalize(rotations, at_vertex.normal)
        offsets = at_vertex.displacement[:, None] * vertex_normal
        return verts + offsets, offsets

    def shade_mesh(
        self, displaced, offsets, rotations, camera, want_normals, gather=None, sh_degree=None
    ) -> MeshRender:
        """The mesh branch: rasterize, look the maps up at covered pixels, SH colour,
        antialias over the background."""
        t = self.tables()
        layout = self.layout
        raster = rasterize(displaced, t.faces, camera)
        h, w = camera.height, camera.width
        pixels = covered_pixels(raster.tri_id)
        # At the covered pixels only: no (H, W, C) images, nor their gradients, to index.
        uv = interpolate(t.uv_coords, raster, t.uv_faces, pixels)
        # The skinning rotations in camera axes (per vertex, before interpolating them):
        # the pixels' normals come out in the camera axes the normal loss compares, with no
        # per-pixel product, and the view directions from the camera's own rays.
        view = camera.viewmat[:3, :3]
        to_camera = torch.einsum("ij,vjk->vik", view, rotations)
        pixel_rot = interpolate(to_camera.reshape(-1, 9), raster, t.faces, pixels)
        pixel_rot = pixel_rot.reshape(-1, 3, 3)
        rotation = pixel_rot.detach()
        # (V·R)ᵀ·(V·ray) = Rᵀ·ray; each pixel's ray read from the image's table by the
        # kernel, with no (P, 3) gather on the one thread the glue runs on.
        local = rotate_normalize(rotation, self._rays(camera), transpose=True, rows=pixels)
        # The colour and the few other maps the pixels need, in one pass over their texels
        # whose backward does not read the maps again.
        extra = self._pixel_maps(want_normals)
        rgb, pixel_maps = sh_texture(
            self.pixel_maps_source(gather, extra),
            uv,
            local,
            self._sh_degree(sh_degree),
            extra,
            gather=gather,
        )
        if layout.shading:
            first = layout.shading_maps.start - extra.start
            world = torch.einsum("ji,pjk->pik", view, rotation)  # Vᵀ·(V·R)
            rgb = _shading_gain(rgb, pixel_maps[:, first : first + SHADING_FEATURES], world)
        # The covered pixels (alpha 1) over the background (alpha 0).
        background = torch.cat([self.background, self.background.new_zeros(1)])
        image = scatter_pixels(rgb, pixels, background, (h, w), fill=rgb.new_ones(1))
        shaded = antialias(image, raster, displaced, t.faces, camera, t.topology)
        normals = None
        if want_normals:
            normals = rotate_normalize(pixel_rot, pixel_maps[:, :3])
        return MeshRender(
            shaded[..., :3],
            shaded[..., 3],
            normals,
            pixels,
            uv.detach(),
            raster.depth,
            displaced,
            offsets,
            raster.tri_id.reshape(h, w),
            shaded,
        )

    def lift_gaussians(self, verts, rotations, camera, gather=None, sh_degree=None) -> GaussianLift:
        """Each Gaussian's attributes from its UV point: position P + D·n on the posed
        surface (P + (D + E)·n with the offset map E), rotation from the posed normal,
        scale, opacity and colour from the maps — one autograd node from the map rows
        (:func:`~urhead.model.lift_rows.lift_rows`; the geometry is
        :func:`~urhead.ops.lift_gaussians_geometry`'s kernel)."""
        return lift_rows(
            self.lookup_fixed(self.gaussian_uv, gather),
            self.layout,
            verts,
            rotations,
            self.gaussian_face_verts(),
            self.gaussian_bary,
            camera.center,
            self._sh_degree(sh_degree),
        )

    def gaussian_face_verts(self) -> torch.Tensor:
        """(N, 3) int32 vertex ids of each Gaussian's face, built once per
        ``gaussian_face`` (rebuilt when the sampler replaces or edits it)."""
        face = self.gaussian_face
        cached = self._face_verts
        if cached is None or cached[0] is not face or cached[1] != face._version:
            ids = self.tables().faces[face].contiguous()
            self._face_verts = cached = (face, face._version, ids)
        return cached[2]

    def splat(self, lift: GaussianLift, camera, depth_map, behind=None) -> GaussianRender:
        """Occlusion-aware splatting of lifted Gaussians (no occlusion with ``depth_map``
        None), composited over ``behind`` ((H, W, S), its first three channels the colour:
        the mesh's RGBA) in the same pass; over black when None."""
        out = rasterize_gaussians(
            lift.means.contiguous(),
            lift.quats.contiguous(),
            lift.scales.contiguous(),
            lift.opacities.contiguous(),
            lift.colors.contiguous(),
            camera,
            background=behind,
            depth_map=depth_map,
            depth_eps=self.depth_eps,
        )
        return GaussianRender(out.image, out.transmittance, out.radii, lift)

    def _sh_degree(self, sh_degree: int | None) -> int:
        """The SH degree used: the layout's, or ``sh_degree`` while it is lower."""
        top = self.layout.sh_degree
        return top if sh_degree is None else min(sh_degree, top)

    def _pixel_maps(self, want_normals: bool) -> slice | None:
        """The channels the mesh's pixels read besides the colour, as one range: the
        normal map for normals, up to the shading maps A when the layout has them."""
        layout = self.layout
        if layout.shading:
            return slice(layout.normal.start, layout.shading_maps.stop)
        return layout.normal if want_normals else None


def _shading_gain(rgb: torch.Tensor, shading: torch.Tensor, rotation: torch.Tensor):
    """``rgb (P, 3)`` scaled by 1 + Σ A_ij (R − I)_ij, with the shading maps' samples
    ``shading (P, 9)`` and the skinning rotations ``rotation (P, 3, 3)``."""
    return rgb * shading_gain(shading, shading_features(rotation))[:, None]


@dataclass(frozen=True, eq=False)
class HeadTables:
    """The constant tensors rendering needs, derived from the head and the identity."""

    lbs: LbsTables
    """Skinning tables with the identity baked into the template (expression columns only)."""
    faces: torch.Tensor
    """(F, 3) int32 geometry faces."""
    faces_long: torch.Tensor
    """(F, 3) int64, for indexing."""
    uv_coords: torch.Tensor
    """(T, 2) UV coordinates."""
    uv_faces: torch.Tensor
    """(F, 3) int32 UV faces."""
    vertex_uv: torch.Tensor
    """(V, 2) one UV point per vertex (seam-free)."""
    topology: torch.Tensor
    """The antialias edge topology of ``faces``."""


def skin(tables: LbsTables, params: FlameParams) -> tuple[torch.Tensor, torch.Tensor]:
    """FLAME skinning of one frame with ``tables`` (identity baked in, :func:`head_tables`):
    ``(verts (V, 3), rotations (V, 3, 3))``."""
    skinned = lbs(
        params.expr[None].contiguous(),
        params.pose[None].contiguous(),
        transl=params.transl[None].contiguous(),
        **tables,
    )
    return skinned.verts[0], skinned.rotations[0]


def head_tables(
    head: HeadModel, shape: torch.Tensor, static_offset: torch.Tensor | None, num_expr: int
) -> HeadTables:
    """The skinning tables with the identity ``shape`` (and VHAP's ``static_offset``) baked
    into the template, so the skinning kernel carries only the ``num_expr`` expression
    columns; faces, UVs, antialias topology."""
    s = shape.shape[0]
    full = head.lbs_tables(torch.float32, num_shape=s, num_expr=num_expr)
    shapedirs = full.shapedirs
    template = full.v_template + (shapedirs[:, :, :s] @ shape)
    if static_offset is not None:
        template = template + static_offset
    lbs_tables = replace(
        full,
        v_template=template.contiguous(),
        shapedirs=shapedirs[:, :, s:].contiguous(),
    )
    faces = torch.tensor(head.faces)
    return HeadTables(
        lbs=lbs_tables,
        faces=faces,
        faces_long=faces.long(),
        uv_coords=torch.tensor(head.uv_coords),
        uv_faces=torch.tensor(head.uv_faces),
        vertex_uv=torch.tensor(head.vertex_uv),
        topology=antialias_topology(faces, head.num_vertices),
    )
