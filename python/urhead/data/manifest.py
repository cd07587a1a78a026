"""A folder's manifest: the size and SHA-256 of every file in it, written last, so a
cached folder can be checked before it is trusted (a truncated or edited file, a file
gone). Used by ``urhead synth``'s cache."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

MANIFEST = "manifest.json"


def write_manifest(folder: Path) -> None:
    """Writes ``folder/manifest.json`` listing every other file under ``folder``
    (``{"files": {relative path: {"size": bytes, "sha256": hex}}}``). Call it once the
    folder is complete."""
    folder = Path(folder)
    files = {
        path.relative_to(folder).as_posix(): {"size": path.stat().st_size, "sha256": _sha256(path)}
        for path in sorted(folder.rglob("*"))
        if path.is_file() and path.relative_to(folder).as_posix() != MANIFEST
    }
    (folder / MANIFEST).write_text(json.dumps({"files": files}, indent=1))


def manifest_problem(folder: Path) -> str | None:
    """None when every file the manifest of ``folder`` lists is there with its size and
    hash; else what is wrong (the first file at fault, or a missing / unreadable
    manifest). Sizes are checked for all files before any hash is computed."""
    folder = Path(folder)
    try:
        files = json.loads((folder / MANIFEST).read_text())["files"]
        expected = {name: (int(e["size"]), str(e["sha256"])) for name, e in files.items()}
    except FileNotFoundError:
        return f"{MANIFEST} is missing"
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as e:
        return f"{MANIFEST} is unreadable ({type(e).__name__})"
    for name, (size, _) in expected.items():
        if Path(name).is_absolute() or ".." in Path(name).parts:
            return f"{MANIFEST} names a file outside the folder ({name})"
        try:
            actual = (folder / name).stat().st_size
        except OSError:
            return f"{name} is missing"
        if actual != size:
            return f"{name} has {actual} bytes, the manifest says {size}"
    for name, (_, digest) in expected.items():
        if _sha256(folder / name) != digest:
            return f"{name} differs from the manifest (SHA-256)"
    return None


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()
