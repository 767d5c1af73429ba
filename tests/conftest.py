"""Test-suite options shared by every test module.

``CV2X_MARL_TEST_ULP_NOISE=1`` (the last pass of ``make test-portable``) makes numpy's float64
``exp``, ``log``, ``log10`` and ``power`` return results moved by 1-2 ulp for about 5 in 8 values, as a
deterministic function of the value: what another CPU's SIMD math (numpy's AVX-512 paths) does to
the numpy side of a compiled-kernel comparison. The compiled kernels keep the C library's
functions, so a test that compares the two bit for bit where they run different implementations
fails on every machine, not only on an AVX-512 one. The kernels must already be in numba's cache
(the pass before compiles them): numba cannot compile a kernel that calls the wrapped functions.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any

import numpy as np


def _with_ulp_noise(f: Callable[..., Any]) -> Callable[..., Any]:
    def noisy(*args: Any, **kwargs: Any) -> Any:
        r = f(*args, **kwargs)
        if isinstance(r, np.ndarray) and r.dtype == np.float64 and r.size > 1 and "out" not in kwargs:
            h = (r.view(np.uint64) * np.uint64(0x9E3779B97F4A7C15)) >> np.uint64(61)
            up, down = np.nextafter(r, np.inf), np.nextafter(r, -np.inf)
            up2, down2 = np.nextafter(up, np.inf), np.nextafter(down, -np.inf)
            moved = np.isfinite(r) & (r != 1.0) & (r != 0.0)  # exp(0) = 1 and log(1) = 0 are exact everywhere
            r = np.select(
                [moved & (h <= 1), moved & (h == 2), moved & (h == 3), moved & (h == 4)], [up, down, up2, down2], r
            )
        return r

    return noisy


if os.environ.get("CV2X_MARL_TEST_ULP_NOISE") == "1":
    from numba import njit

    njit(lambda x: x + 1.0)(1.0)  # numba registers numpy's ufuncs before they are wrapped
    for _name in ("exp", "log", "log10", "power"):
        setattr(np, _name, _with_ulp_noise(getattr(np, _name)))
