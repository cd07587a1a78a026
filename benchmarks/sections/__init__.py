"""Sections of docs/benchmarks.md, in report order.

A section is a module here with

- ``TITLE``: its heading;
- ``run(quick: bool) -> dict``: measures and returns JSON-serialisable results (stored under
  the module's name in docs/benchmarks/results.json);
- ``render(results: dict, figures: pathlib.Path) -> str``: markdown from those results,
  writing its PNGs into ``figures`` (docs/benchmarks/) and linking them as
  ``benchmarks/<file>.png`` (relative to docs/).

``render`` reads only the stored results, so a report can be re-rendered, or one section
re-measured, without rerunning the others (``run.py --sections NAME``, ``--render-only``).
To add a section (e.g. a whole-iteration breakdown calling the trainer), write the module
and add its name to ``SECTIONS``.
"""

SECTIONS = [
    "kernels",
    "splatting",
    "rendering",
    "iteration",
    "quality",
    "conditions",
    "leaving_out",
]
