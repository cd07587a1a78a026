"""``urhead fit-many SUBJECT... --out ROOT``: one ``urhead fit`` per subject, each a Ray task
that asks for ``--cpus-per-fit`` CPUs, on a local Ray instance or an existing cluster.

Each subject is fitted into ``ROOT/<subject folder name>`` exactly as ``urhead fit --resume``
would: a finished subject (its ``metrics.json`` exists) is skipped, an interrupted one
continues from its checkpoint, and a task whose worker dies is retried by Ray, which
resumes it the same way. A failing subject is recorded and the others go on.
``ROOT/summary.json`` is rewritten atomically as subjects finish.

Workers share nothing with the driver but ``ROOT``, the subject folders and ``--head``
(shared storage on a cluster): every path is made absolute before it is sent.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from urhead._memory import keep_freed_memory
from urhead._threads import configure_threads
from urhead.config import FitConfig
from urhead.train.command import add_fit_options, fit_config, fit_subject
from urhead.train.summary import Summary

# Ray re-runs a task whose worker process or node died (not one that raised); each re-run
# resumes from the subject's last checkpoint.
WORKER_DEATH_RETRIES = 3


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "fit-many",
        help="fit many subjects as Ray tasks (a local Ray instance or a cluster)",
        description="Fit one avatar per subject, each as a Ray task with --cpus-per-fit CPUs. "
        "Writes ROOT/<subject folder name>/ as `urhead fit` does and ROOT/summary.json. "
        "Run it again to skip finished subjects and resume interrupted ones. "
        "Needs Ray: pip install 'urhead[cluster]'.",
    )
    p.add_argument("subjects", nargs="+", type=Path, metavar="SUBJECT", help="subject folders")
    p.add_argument("--out", type=Path, required=True, metavar="ROOT", help="output root folder")
    p.add_argument(
        "--address",
        default=None,
        help="Ray cluster to join: 'auto' (the one started on this machine) or HOST:PORT; "
        "default: start a local Ray instance for this run",
    )
    p.add_argument(
        "--cpus-per-fit",
        type=int,
        default=1,
        help="CPUs each fit asks Ray for; its kernels use exactly that many threads (default: 1)",
    )
    add_fit_options(p)
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    # The arguments first: a mistake in them is named whether or not Ray is installed.
    if args.cpus_per_fit < 1:
        raise ValueError(f"--cpus-per-fit must be at least 1, got {args.cpus_per_fit}")
    config = fit_config(args)
    subjects = [s.absolute() for s in args.subjects]  # not resolve(): keep link names
    _check_distinct_names(subjects)
    try:
        import ray
    except ImportError:
        print(
            "urhead fit-many: error: needs Ray, which is not installed; "
            "install it with: pip install 'urhead[cluster]'",
            file=sys.stderr,
        )
        return 1
    root = args.out.absolute()
    root.mkdir(parents=True, exist_ok=True)
    summary = Summary(root, subjects, config)

    if args.address is None:
        ray.init(include_dashboard=False, logging_level=logging.WARNING)
    else:
        ray.init(address=args.address, logging_level=logging.WARNING)
    try:
        _check_cluster_fits(ray, args.cpus_per_fit)
        _fit_pending(ray, args, config, summary)
    finally:
        ray.shutdown()
    print(summary.table())
    failed = summary.count("failed")
    if failed:
        print(
            f"urhead fit-many: {failed} of {len(subjects)} subjects failed; see {summary.path}",
            file=sys.stderr,
        )
    return 1 if failed else 0


def _fit_pending(ray, args: argparse.Namespace, config: FitConfig, summary: Summary) -> None:
    """Submits a task per pending subject, then records each as it finishes."""
    fit = ray.remote(
        num_cpus=args.cpus_per_fit,
        max_retries=WORKER_DEATH_RETRIES,
        retry_exceptions=False,
    )(fit_in_worker)
    head = None if args.head is None else str(args.head.absolute())
    tasks = {}
    for name, row in summary.rows.items():
        if row["status"] == "pending":
            task = fit.options(name=f"fit {name}").remote(
                row["path"],
                str(summary.path.parent / name),
                config,
                head_path=head,
                test_last=args.test_last,
                cpus=args.cpus_per_fit,
            )
            tasks[task] = name
    summary.write()
    print(summary.headline(len(tasks), args.cpus_per_fit, ray.cluster_resources()), flush=True)
    while tasks:
        [task], _ = ray.wait(list(tasks), num_returns=1)
        name = tasks.pop(task)
        try:
            summary.finished(name, ray.get(task))
        except ray.exceptions.RayError as e:  # e.g. its worker or node died too often
            summary.failed(name, f"{type(e).__name__}: {str(e).strip().splitlines()[0]}")
        summary.write()
        print(summary.progress_line(name), flush=True)


def fit_in_worker(
    subject_dir: str,
    out: str,
    config: FitConfig,
    *,
    head_path: str | None,
    test_last: int | None,
    cpus: int,
) -> dict:
    """The Ray task: ``urhead fit --resume`` with the kernels on the task's ``cpus``.
    Returns the fit's metrics and its wall-clock seconds in this worker, or the error.

    A failure is returned, not raised: the subject's error is data for the summary, and
    not every exception survives Ray's pickling (urhead's DatasetError does not). The
    traceback goes to the log, which Ray forwards to the driver."""
    configure_threads(cpus)
    keep_freed_memory()
    start = time.perf_counter()
    with _fit_log_lines(Path(subject_dir).name) as log:
        try:
            result = fit_subject(
                Path(subject_dir),
                Path(out),
                config,
                head_path=None if head_path is None else Path(head_path),
                test_last=test_last,
                resume=True,
                progress=False,
            )
        except Exception as e:  # any failure of this subject is recorded; the others go on
            log.exception("failed")
            return {"error": f"{type(e).__name__}: {e}"}
    return {"metrics": result.metrics, "seconds": time.perf_counter() - start}


@contextmanager
def _fit_log_lines(name: str) -> Iterator[logging.Logger]:
    """The fit's log lines (start, resume, held-out PSNR) prefixed with the subject, on the
    worker's stderr, which Ray forwards to the driver. Undone afterwards: Ray reuses
    worker processes for other subjects."""
    logger = logging.getLogger("urhead.fit")
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter(f"{name}: %(message)s"))
    level, propagate = logger.level, logger.propagate
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    logger.propagate = False
    try:
        yield logger
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)
        logger.propagate = propagate


def _check_distinct_names(subjects: list[Path]) -> None:
    seen: dict[str, Path] = {}
    for s in subjects:
        if s.name in seen:
            raise ValueError(
                f"subjects {seen[s.name]} and {s} would both write ROOT/{s.name}; "
                "give each subject a folder of its own name"
            )
        seen[s.name] = s


def _check_cluster_fits(ray, cpus_per_fit: int) -> None:
    """A task asking for more CPUs than any node has would wait forever: refuse it."""
    largest = max((n["Resources"].get("CPU", 0) for n in ray.nodes() if n.get("Alive")), default=0)
    if largest < cpus_per_fit:
        raise ValueError(
            f"--cpus-per-fit {cpus_per_fit}: no node of the Ray cluster has that many CPUs "
            f"(largest: {largest:g})"
        )
