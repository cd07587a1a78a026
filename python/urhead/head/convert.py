"""``urhead convert-flame``: the official FLAME files → our ``.npz`` head format."""

from __future__ import annotations

import argparse

from urhead.head.flame import load_flame
from urhead.head.model import save_head


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "convert-flame",
        help="convert FLAME's generic_model.pkl / flame2023.pkl to a urhead head (.npz)",
        description="Convert the official (licensed) FLAME model files to urhead's .npz head "
        "format, adding the VHAP teeth rows and the mouth plate unless --no-teeth.",
    )
    p.add_argument("pkl", help="generic_model.pkl (FLAME 2020) or flame2023.pkl")
    p.add_argument("--obj", help="head_template_mesh.obj: the UV layout (without it: no UVs)")
    p.add_argument("--masks", help="FLAME_masks.pkl: region labels (without it: estimated)")
    p.add_argument("--no-teeth", action="store_true", help="do not add the teeth and plate")
    p.add_argument("-o", "--output", required=True, help="the .npz to write")
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    head = load_flame(args.pkl, obj_path=args.obj, teeth=not args.no_teeth, masks_path=args.masks)
    save_head(head, args.output)
    uv = "with UVs" if head.has_uv else "without UVs"
    print(f"wrote {args.output}: {head.num_vertices} vertices, {head.num_faces} faces, {uv}")
    return 0
