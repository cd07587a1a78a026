"""Head models: the official FLAME files (converted once to our ``.npz``), the built-in
procedural head, and UV-space tools. Everything downstream reads a :class:`HeadModel`."""

from urhead.head.flame import load_flame
from urhead.head.model import (
    FORMAT_VERSION,
    JOINT_NAMES,
    REGION_NAMES,
    HeadModel,
    head_fingerprint,
    load_head,
    region_index,
    save_head,
)
from urhead.head.procedural import procedural_head
from urhead.head.teeth import TeethConfig, add_teeth
from urhead.head.uv import (
    UvLookup,
    seam_free_vertex_uv,
    texel_centers,
    triangle_id_map,
    uv_region_masks,
)

__all__ = [
    "FORMAT_VERSION",
    "JOINT_NAMES",
    "REGION_NAMES",
    "HeadModel",
    "TeethConfig",
    "UvLookup",
    "add_teeth",
    "head_fingerprint",
    "load_flame",
    "load_head",
    "procedural_head",
    "region_index",
    "save_head",
    "seam_free_vertex_uv",
    "texel_centers",
    "triangle_id_map",
    "uv_region_masks",
]
