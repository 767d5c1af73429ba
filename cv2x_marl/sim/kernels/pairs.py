"""Pairs of vehicles within range (cell lists, Verlet list filtering), pair geometry and link indexing."""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


@njit(cache=True)
def _grow(a: NDArray[np.int64], size: int) -> NDArray[np.int64]:
    out = np.empty(size, dtype=np.int64)
    out[: a.shape[0]] = a
    return out


@njit(cache=True)
def _min_image(d: float, box: float) -> float:
    if math.isfinite(box):
        return d - box * round(d / box)
    return d


@njit(cache=True)
def pairs_within_range(
    pos_m: FloatArray, box_m: FloatArray, range_m: float
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Unordered vehicle pairs at most ``range_m`` apart, sorted by ``(i, j)``, ``i < j``.

    A sweep over the vehicles sorted along x (wrapped when the x axis is periodic): for each vehicle,
    the others within ``range_m`` along x ahead and behind (each at most once, so a ring shorter than
    twice the range is fine), kept when the minimum-image distance satisfies ``dx^2 + dy^2 <= r^2``.
    The pairs of scipy's KD-tree query (``query_pairs``, tested), in ``(i, j)`` order; cost
    ``O(N log N + N k)`` with k the vehicles within range along x.

    Args:
        pos_m: [N, 2] positions, m.
        box_m: [2] period of each axis, m (inf: not periodic).
        range_m: the cut-off, m.

    Returns:
        ``(i, j)``, each [P] int64.
    """
    n = pos_m.shape[0]
    bx, by = box_m[0], box_m[1]
    px = math.isfinite(bx)
    x = pos_m[:, 0].copy()
    if px:
        x = x - bx * np.floor(x / bx)
    order = np.argsort(x, kind="mergesort")
    sx = x[order]
    rank = np.empty(n, dtype=np.int64)
    rank[order] = np.arange(n)
    r2 = range_m * range_m
    slack = range_m * (1.0 + 1e-9) + 1e-9  # the sweep along x never cuts a pair the distance test keeps
    cap = max(1024, 16 * n)
    out_i = np.empty(cap, dtype=np.int64)
    out_j = np.empty(cap, dtype=np.int64)
    tmp = np.empty(n, dtype=np.int64)
    m = 0
    for i in range(n):
        k = rank[i]
        cnt = 0
        visited = 0
        for s in range(1, n):
            kk = k + s
            shift = 0.0
            if kk >= n:
                if not px:
                    break
                kk -= n
                shift = bx
            if sx[kk] + shift - sx[k] > slack:
                break
            visited += 1
            j = order[kk]
            if j > i:
                dx = _min_image(pos_m[j, 0] - pos_m[i, 0], bx)
                dy = _min_image(pos_m[j, 1] - pos_m[i, 1], by)
                if dx * dx + dy * dy <= r2:
                    tmp[cnt] = j
                    cnt += 1
        for s in range(1, n - visited):
            kk = k - s
            shift = 0.0
            if kk < 0:
                if not px:
                    break
                kk += n
                shift = bx
            if sx[k] + shift - sx[kk] > slack:
                break
            j = order[kk]
            if j > i:
                dx = _min_image(pos_m[j, 0] - pos_m[i, 0], bx)
                dy = _min_image(pos_m[j, 1] - pos_m[i, 1], by)
                if dx * dx + dy * dy <= r2:
                    tmp[cnt] = j
                    cnt += 1
        if m + cnt > cap:
            cap = max(2 * cap, m + cnt)
            out_i = _grow(out_i, cap)
            out_j = _grow(out_j, cap)
        row = np.sort(tmp[:cnt])
        for c in range(cnt):
            out_i[m + c] = i
            out_j[m + c] = row[c]
        m += cnt
    return out_i[:m].copy(), out_j[:m].copy()


@njit(cache=True)
def links_by_transmitter(tx: NDArray[np.int64], n: int) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """The period's links grouped by transmitter (a counting sort, ``O(L + N)``).

    Args:
        tx: [L] the transmitter of each link.
        n: N.

    Returns:
        ``start`` [N + 1] and ``index`` [L]: the links of transmitter ``t`` are
        ``index[start[t]:start[t + 1]]``, increasing.
    """
    start = np.zeros(n + 1, dtype=np.int64)
    for k in range(tx.shape[0]):
        start[tx[k] + 1] += 1
    for t in range(n):
        start[t + 1] += start[t]
    fill = start[:-1].copy()
    index = np.empty(tx.shape[0], dtype=np.int64)
    for k in range(tx.shape[0]):
        t = tx[k]
        index[fill[t]] = k
        fill[t] += 1
    return start, index


@njit(cache=True)
def active_links(start: NDArray[np.int64], index: NDArray[np.int64], senders: NDArray[np.int64]) -> NDArray[np.int64]:
    """The links of the transmitters ``senders``, in increasing link order (the order the numpy period
    visits them in), from :func:`links_by_transmitter`'s grouping.

    Args:
        start, index: :func:`links_by_transmitter`.
        senders: [A] the transmitters of a chunk.

    Returns:
        [L_A] link indices, increasing.
    """
    count = 0
    for a in range(senders.shape[0]):
        count += start[senders[a] + 1] - start[senders[a]]
    out = np.empty(count, dtype=np.int64)
    m = 0
    for a in range(senders.shape[0]):
        t = senders[a]
        for q in range(start[t], start[t + 1]):
            out[m] = index[q]
            m += 1
    radix_sort(out, index.shape[0])
    return out


@njit(cache=True)
def radix_sort(a: NDArray[np.int64], bound: int) -> None:
    """Sort ``a`` in place, ascending, for values in ``[0, bound)``: an LSD radix sort in 12-bit digits
    (two passes below 2^24, each a count and a stable scatter: ``O(len(a))``; numba's quicksort costs
    ``O(len(a) log len(a))`` with a branch miss per comparison). Short arrays use ``a.sort()``.

    Args:
        a: [M] int64, each in ``[0, bound)``.
        bound: one past the largest value ``a`` may hold.
    """
    n = a.shape[0]
    if n < 256:
        a.sort()
        return
    bits = 1
    while (1 << bits) < bound:
        bits += 1
    src = a
    dst = np.empty_like(a)
    count = np.empty(4097, dtype=np.int64)
    shift = 0
    swapped = False
    while shift < bits:
        count[:] = 0
        for i in range(n):
            count[((src[i] >> shift) & 4095) + 1] += 1
        for d in range(4096):
            count[d + 1] += count[d]
        for i in range(n):
            d = (src[i] >> shift) & 4095
            dst[count[d]] = src[i]
            count[d] += 1
        src, dst = dst, src
        swapped = not swapped
        shift += 12
    if swapped:  # the last pass wrote into the scratch
        a[:] = src


@njit(cache=True)
def pair_geometry(
    pos_m: FloatArray, vel_mps: FloatArray, i: NDArray[np.int64], j: NDArray[np.int64], box_m: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Displacement, distance and relative speed of the pairs ``(i, j)`` in one pass.

    The numpy path's arithmetic element by element: ``pos[j] - pos[i]`` folded onto the torus where an
    axis is periodic (``d - box * round(d / box)``, round half to even as ``np.round``), ``hypot`` of it,
    and ``hypot`` of ``vel[i] - vel[j]``: equal to the last bit.

    Args:
        pos_m: [N, 2] positions, m.
        vel_mps: [N, 2] velocities, m/s.
        i, j: [P] the pairs.
        box_m: [2] period of each axis, m (inf: not periodic, or distances not wrapped).

    Returns:
        ``dx, dy, distance`` [P] (m) and relative speed [P] (m/s).
    """
    p = i.shape[0]
    dx = np.empty(p)
    dy = np.empty(p)
    dist = np.empty(p)
    rel = np.empty(p)
    bx, by = box_m[0], box_m[1]
    for k in range(p):
        a, b = i[k], j[k]
        x = _min_image(pos_m[b, 0] - pos_m[a, 0], bx)
        y = _min_image(pos_m[b, 1] - pos_m[a, 1], by)
        dx[k] = x
        dy[k] = y
        dist[k] = math.hypot(x, y)
        rel[k] = math.hypot(vel_mps[a, 0] - vel_mps[b, 0], vel_mps[a, 1] - vel_mps[b, 1])
    return dx, dy, dist, rel


@njit(cache=True)
def filter_pairs_within_range(
    pos_m: FloatArray, box_m: FloatArray, range_m: float, cand_i: NDArray[np.int32], cand_j: NDArray[np.int32]
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """The candidate pairs at most ``range_m`` apart, in candidate order: a Verlet list's step.

    The acceptance test is :func:`pairs_within_range`'s, to the bit (minimum-image ``dx``, ``dy``,
    ``dx^2 + dy^2 <= r^2``), so when the candidates hold every pair in range, sorted by ``(i, j)``
    (``pairs_within_range`` at a larger radius, while no vehicle has moved more than half the
    difference since), the result equals ``pairs_within_range(pos_m, box_m, range_m)``.

    Args:
        pos_m: [N, 2] positions, m.
        box_m: [2] period of each axis, m (inf: not periodic).
        range_m: the cut-off, m.
        cand_i, cand_j: [C] candidate pairs, ``i < j`` (int32: the list is kept between periods).

    Returns:
        ``(i, j)``, each [P] int64, ``P <= C``.
    """
    bx, by = box_m[0], box_m[1]
    r2 = range_m * range_m
    c = cand_i.shape[0]
    out_i = np.empty(c, dtype=np.int64)
    out_j = np.empty(c, dtype=np.int64)
    m = 0
    for k in range(c):
        i = cand_i[k]
        j = cand_j[k]
        dx = _min_image(pos_m[j, 0] - pos_m[i, 0], bx)
        dy = _min_image(pos_m[j, 1] - pos_m[i, 1], by)
        if dx * dx + dy * dy <= r2:
            out_i[m] = i
            out_j[m] = j
            m += 1
    return out_i[:m].copy(), out_j[:m].copy()
