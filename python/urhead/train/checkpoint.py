"""Training checkpoints: the avatar files plus optimiser moments, sampling statistics and
the loop's position, written as one directory that replaces the previous one atomically.
Resuming from it continues bit for bit (the frame order and sampling draws are functions of
the seed and the iteration, not of a live random state)."""

from __future__ import annotations

import shutil
from pathlib import Path

import torch

from urhead._atomic import write_directory_atomically
from urhead.errors import reading
from urhead.model.io import load_avatar, write_avatar_files

CHECKPOINT_DIR = "checkpoint"


def save_checkpoint(out: Path, avatar, state: dict) -> None:
    """Writes ``out/checkpoint`` (the avatar files and ``state.pt``) atomically."""

    def fill(tmp: Path) -> None:
        write_avatar_files(avatar, tmp)
        torch.save(state, tmp / "state.pt")

    write_directory_atomically(out / CHECKPOINT_DIR, fill)


def find_checkpoint(out: Path) -> Path | None:
    """The newest complete checkpoint under ``out``: ``checkpoint`` itself, or the previous
    one kept under its temporary old name if the process died between the two renames."""
    path = out / CHECKPOINT_DIR
    if (path / "state.pt").is_file():
        return path
    leftovers = sorted(out.glob(f".{CHECKPOINT_DIR}.old-*"), key=lambda p: p.stat().st_mtime)
    for p in reversed(leftovers):
        if (p / "state.pt").is_file():
            return p
    return None


def load_checkpoint(path: Path):
    """``(avatar, state)`` from a checkpoint directory."""
    avatar = load_avatar(path)
    with reading(path / "state.pt", "checkpoint state"):
        state = torch.load(path / "state.pt", weights_only=True)
    return avatar, state


def remove_checkpoints(out: Path) -> None:
    """Deletes ``out/checkpoint`` and any leftover previous one."""
    for p in [out / CHECKPOINT_DIR, *out.glob(f".{CHECKPOINT_DIR}.old-*")]:
        shutil.rmtree(p, ignore_errors=True)
