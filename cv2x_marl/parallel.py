"""Ray for the package's parallel work: one way to start or join Ray, used by ``cv2x-marl sweep``
(:mod:`cv2x_marl.rl.sweep`) and ``cv2x-marl dataset --ray``.

With no address an embedded local Ray starts (one CPU slot per core) and is shut down afterwards;
its session files go to a short temporary folder that is removed at the end (Ray's unix socket
paths must stay under ~107 characters, so they cannot live under a deep run folder). With an
address (``auto``, ``ray://host:10001``) an existing cluster is used. Ray is the ``[ray]`` extra.

Without Ray, :func:`map_in_processes` runs independent items in a pool of spawned processes (the standard
library's): ``cv2x-marl validate --workers`` and ``cv2x-marl benchmark --backend processes``.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import sys
import tempfile
from collections.abc import Callable, Iterator, Sequence
from typing import Any

from cv2x_marl.extras import require


@contextlib.contextmanager
def ray_session(address: str | None = None, num_cpus: int | None = None) -> Iterator[Any]:
    """Connect to Ray (``address``) or start an embedded local one; shut it down and remove its
    session files afterwards. Ray's own console output goes to stderr."""
    ray = require("ray", "Ray sweeps and --ray")
    if ray.is_initialized():  # the caller manages Ray
        yield ray
        return
    tmp = None if address else tempfile.mkdtemp(prefix="cv2x-ray-")
    kwargs: dict[str, Any] = {"include_dashboard": False, "log_to_driver": False, "configure_logging": False}
    if address:
        kwargs["address"] = address
    else:
        kwargs.update(num_cpus=num_cpus or os.cpu_count() or 1, _temp_dir=tmp)
    try:
        with contextlib.redirect_stdout(sys.stderr):
            ray.init(**kwargs)
        yield ray
    finally:
        if ray.is_initialized():
            ray.shutdown()
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)


def map_on_ray(fn: Callable[..., Any], args: Sequence[tuple[Any, ...]], address: str | None = None) -> list[Any]:
    """``[fn(*a) for a in args]`` as Ray tasks (one CPU each), results in input order."""
    with ray_session(address) as ray:
        remote = ray.remote(num_cpus=1)(fn)
        return list(ray.get([remote.remote(*a) for a in args]))


def usable_cpus() -> int:
    """The CPUs this process may run on (its affinity mask where the system reports one, else the count)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def map_in_processes(
    fn: Callable[[Any], Any],
    items: Sequence[Any],
    workers: int,
    cost: Callable[[Any], float] | None = None,
    on_done: Callable[[int, Any], None] | None = None,
) -> list[Any]:
    """``[fn(x) for x in items]`` in a pool of ``workers`` spawned processes (standard library only: no
    Ray), results in input order.

    Each item must be independent and seeded on its own, so the results equal a one-process run's. The
    items run costliest first when ``cost`` is given (the pool is then not left waiting on one large item
    at the end); ``on_done(i, result)`` is called in this process as each item ``i`` finishes (a progress
    bar). The processes are spawned, not forked: a fork of a process holding numba or BLAS threads can hang.

    Args:
        fn: a picklable (module-level) function of one item.
        items: the items.
        workers: processes (>= 1; 1 or a single item: in this process).
        cost: the relative cost of an item (optional).
        on_done: called with (input index, result) as each item finishes.
    """
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ValueError(f"workers must be an integer >= 1, got {workers!r}")
    if workers == 1 or len(items) <= 1:
        out = []
        for i, x in enumerate(items):
            out.append(fn(x))
            if on_done is not None:
                on_done(i, out[-1])
        return out
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor, as_completed

    order = sorted(range(len(items)), key=lambda i: -cost(items[i])) if cost is not None else range(len(items))
    results: list[Any] = [None] * len(items)
    ctx = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=min(workers, len(items)), mp_context=ctx) as pool:
        futures = {pool.submit(fn, items[i]): i for i in order}
        for fut in as_completed(futures):
            i = futures[fut]
            results[i] = fut.result()
            if on_done is not None:
                on_done(i, results[i])
    return results
