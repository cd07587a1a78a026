"""``ROOT/summary.json`` of ``urhead fit-many``: one row per subject (status, held-out PSNR
in the mask and over the full image, seconds, error), rewritten atomically as subjects
finish, and the progress lines and table printed from it."""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

from urhead._atomic import write_file_atomically
from urhead.config import FitConfig

SUMMARY = "summary.json"


class Summary:
    """The rows of one run's subjects, each ``pending`` until its fit is recorded. Rows of
    subjects finished by an earlier run keep that run's seconds."""

    def __init__(self, root: Path, subjects: list[Path], config: FitConfig):
        self.path = root / SUMMARY
        earlier = _earlier_rows(self.path)
        self.rows = {s.name: _initial_row(root, s, config, earlier.get(s.name)) for s in subjects}

    def finished(self, name: str, outcome: dict) -> None:
        if "error" in outcome:
            self.failed(name, outcome["error"])
            return
        m = outcome["metrics"]
        self.rows[name].update(
            status="done",
            psnr=m.get("psnr"),
            psnr_full=m.get("psnr_full"),
            seconds=round(outcome["seconds"], 2),
        )

    def failed(self, name: str, error: str) -> None:
        self.rows[name].update(status="failed", error=error)

    def count(self, status: str) -> int:
        return sum(r["status"] == status for r in self.rows.values())

    def write(self) -> None:
        counts = {s: self.count(s) for s in ("done", "skipped", "failed", "pending")}
        text = json.dumps({**counts, "subjects": list(self.rows.values())}, indent=2)
        write_file_atomically(self.path, lambda tmp: tmp.write_text(text))

    def headline(self, submitted: int, cpus_per_fit: int, resources: dict) -> str:
        return (
            f"fit-many: {len(self.rows)} subjects: {submitted} to fit, "
            f"{self.count('skipped')} finished earlier, {self.count('failed')} refused; "
            f"{cpus_per_fit} CPU(s) per fit on a Ray cluster of {resources.get('CPU', 0):g} CPUs"
        )

    def progress_line(self, name: str) -> str:
        row = self.rows[name]
        settled = len(self.rows) - self.count("pending")
        head = f"[{settled}/{len(self.rows)}] {name}:"
        if row["status"] == "failed":
            return f"{head} failed: {row['error']}"
        return f"{head} done in {row['seconds']:.1f} s, held-out PSNR {_psnr_text(row)}"

    def table(self) -> str:
        header = ("subject", "status", "PSNR mask", "PSNR full", "seconds", "error")
        lines = [header]
        for r in self.rows.values():
            lines.append(
                (
                    r["subject"],
                    r["status"],
                    _number(r["psnr"], ".2f"),
                    _number(r["psnr_full"], ".2f"),
                    _number(r["seconds"], ".1f"),
                    r["error"] or "",
                )
            )
        widths = [max(len(line[i]) for line in lines) for i in range(len(header))]
        return "\n".join(
            "  ".join(cell.ljust(w) for cell, w in zip(line, widths, strict=True)).rstrip()
            for line in lines
        )


def _initial_row(root: Path, subject: Path, config: FitConfig, earlier: dict | None) -> dict:
    """``skipped`` if the subject's fit finished (with this configuration), ``failed`` if
    it finished with another one, else ``pending``."""
    row = {
        "subject": subject.name,
        "path": str(subject),
        "status": "pending",
        "psnr": None,
        "psnr_full": None,
        "seconds": None,
        "error": None,
    }
    out = root / subject.name
    if not (out / "metrics.json").is_file():
        return row
    metrics = json.loads((out / "metrics.json").read_text())
    avatar_meta = out / "avatar" / "avatar.json"
    fitted_with = (
        json.loads(avatar_meta.read_text()).get("config") if avatar_meta.is_file() else None
    )
    if fitted_with is not None and fitted_with != asdict(config):
        return {
            **row,
            "status": "failed",
            "error": f"{out} was fitted with a different configuration; "
            "use the same options, or remove it or choose another --out to fit it again",
        }
    seconds = (
        earlier.get("seconds") if earlier and earlier.get("status") in ("done", "skipped") else None
    )
    return {
        **row,
        "status": "skipped",
        "psnr": metrics.get("psnr"),
        "psnr_full": metrics.get("psnr_full"),
        "seconds": seconds,
    }


def _earlier_rows(path: Path) -> dict[str, dict]:
    """The previous run's rows by subject name (none if there was no readable summary)."""
    try:
        rows = json.loads(path.read_text())["subjects"]
    except (OSError, ValueError, KeyError, TypeError):
        return {}
    return {r["subject"]: r for r in rows if isinstance(r, dict) and "subject" in r}


def _number(value, spec: str) -> str:
    return "-" if value is None else format(value, spec)


def _psnr_text(row: dict) -> str:
    text = f"{_number(row['psnr'], '.2f')} dB in the mask"
    if row["psnr_full"] is not None:
        text += f", {row['psnr_full']:.2f} dB full image"
    return text
