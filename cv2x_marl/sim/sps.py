"""Sensing-based semi-persistent scheduling, vectorised over the vehicles that reselect.

Resources are indexed within one reservation period: ``r = slot * n_subchannels + subchannel``
with ``slot`` in ``[0, RRI)``. A vehicle whose packets are generated at slot ``g`` selects from
the window ``[g + T1, g + T2]`` (mod RRI), ``M = (T2 - T1 + 1) * n_subchannels`` candidates
(TS 36.213 14.1.1.6 with one subchannel per packet):

1. exclude a candidate whose subframe the UE did not monitor (its own transmission, step 5);
2. exclude a candidate reserved by a received SCI whose PSSCH-RSRP exceeds the threshold
   (step 6); while fewer than ``ceil(0.2 M)`` remain, raise the threshold by 3 dB (step 7);
3. paper rule: the ``k = 3`` lowest-RSSI survivors, one of them uniformly (Sec. 3);
   3GPP rule: the lowest-RSSI survivors making ``ceil(0.2 M)``, one uniformly (step 8).

The 3 dB loop has a closed form: with ``v_q`` the q-th smallest RSRP of the candidates
(``q = ceil(0.2 M)``), the final threshold is ``Th + 3 max(0, ceil((v_q - Th) / 3))``.

The reselection counter (TS 36.321 5.14.1.1) is drawn uniformly in ``[5, 15]`` for RRI >= 100 ms
and ``[5 * 100 / RRI, 15 * 100 / RRI]`` for shorter RRIs; it falls by one per transmission and,
when it expires, the UE keeps its resource with probability ``keep_probability``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cv2x_marl.config import SpsConfig

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


def counter_range(cfg: SpsConfig, rri_ms: int) -> tuple[int, int]:
    """Inclusive range of the reselection counter for this RRI (TS 36.321 5.14.1.1)."""
    scale = max(1.0, 100.0 / rri_ms)
    return round(cfg.counter_min * scale), round(cfg.counter_max * scale)


def draw_counters(cfg: SpsConfig, rri_ms: int, n: int, rng: np.random.Generator) -> IntArray:
    """``n`` reselection counters, uniform on :func:`counter_range`."""
    lo, hi = counter_range(cfg, rri_ms)
    return rng.integers(lo, hi + 1, size=n)


def candidate_resources(generation_slot: IntArray, cfg: SpsConfig, rri_ms: int) -> IntArray:
    """[V, M] candidate resource indices of the selection window of each of V vehicles."""
    offsets = cfg.t1_subframes + np.arange(cfg.selection_window_subframes)
    slots = (generation_slot[:, None] + offsets[None, :]) % rri_ms  # [V, W]
    sub = np.arange(cfg.n_subchannels)
    return (slots[:, :, None] * cfg.n_subchannels + sub[None, None, :]).reshape(len(generation_slot), -1)


@dataclass(frozen=True)
class Selection:
    """Outcome of one batch of resource selections (arrays over the V selecting vehicles)."""

    choice: IntArray  # [V] index into the candidate list
    threshold_dbm: FloatArray  # [V] final RSRP threshold after the 3 dB loop
    n_kept: IntArray  # [V] candidates surviving exclusion


def select(
    rsrp_dbm: FloatArray,
    rssi_mw: NDArray[np.floating],
    cfg: SpsConfig,
    rng: np.random.Generator,
) -> Selection:
    """Choose one candidate per row.

    Args:
        rsrp_dbm: [V, M] RSRP of the SCI reserving each candidate (``-inf``: none received,
            ``+inf``: subframe not monitored, always excluded).
        rssi_mw: [V, M] sensing-window average S-RSSI of each candidate, mW.
        cfg: SPS configuration (threshold, step, minimum fraction, rule).
        rng: the SPS stream.

    Returns:
        The chosen candidate of every row, the final threshold and the number of survivors.
    """
    v, m = rsrp_dbm.shape
    q = min(m, math.ceil(cfg.min_candidate_fraction * m - 1e-9))
    th0 = cfg.rsrp_threshold_dbm
    vq = np.partition(rsrp_dbm, q - 1, axis=1)[:, q - 1]
    if np.any(np.isposinf(vq)):
        raise ValueError("more than 80 % of the candidates are unmonitored: the 3 dB loop cannot end")
    with np.errstate(invalid="ignore"):
        steps = np.where(vq > th0, np.ceil((vq - th0) / cfg.threshold_step_db - 1e-12), 0.0)
    threshold = th0 + cfg.threshold_step_db * steps
    kept = rsrp_dbm <= threshold[:, None]
    n_kept = kept.sum(axis=1)
    k = cfg.paper_best_k if cfg.selection == "paper" else q
    score = np.where(kept, rssi_mw, np.inf)
    order = np.argsort(score, axis=1, kind="stable")
    n_pick = np.minimum(k, n_kept)
    pick = np.floor(rng.random(v) * n_pick).astype(np.int64)
    choice = order[np.arange(v), pick]
    return Selection(choice, threshold, n_kept)
