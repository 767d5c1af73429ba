"""Ray for the package's parallel work: one way to start or join Ray, used by ``cv2x-marl sweep``
(:mod:`cv2x_marl.rl.sweep`) and ``cv2x-marl dataset --ray``.

With no address an embedded local Ray starts (one CPU slot per core) and is shut down afterwards;
its session files go to a short temporary folder that is removed at the end (Ray's unix socket
paths must stay under ~107 characters, so they cannot live under a deep run folder). With an
address (``auto``, ``ray://host:10001``) an existing cluster is used. Ray is the ``[ray]`` extra.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import sys
import tempfile
from collections.abc import Callable, Iterator, Sequence
from typing import Any


@contextlib.contextmanager
def ray_session(address: str | None = None, num_cpus: int | None = None) -> Iterator[Any]:
    """Connect to Ray (``address``) or start an embedded local one; shut it down and remove its
    session files afterwards. Ray's own console output goes to stderr."""
    from cv2x_marl.extras import require

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
