"""The batched one-mover step for observation version 3 (``cv2x/SingleMover-v3``): field and measurements.

:class:`~cv2x_marl.env.mover_batch.MoverBatch` steps K one-mover copies in one compiled call. With
observation version 3 a step also reads the shadowing field where the mover now stands (its row and
column), takes one period of measurements (the draws of every pair from each copy's ``measurement``
stream, drawn inside the compiled step by :func:`cv2x_marl.env.pcg64.draw_column_into`: numpy's ``PCG64``
draws bit for bit, the copy's generator state kept in :attr:`V3Stacks.rng_state` and written back into its
``numpy.random.Generator`` by :meth:`V3Stacks.sync`; the mover's column of reports updated) and builds the
measured and own v3 entries. :class:`V3Stacks` holds that per-copy state; :func:`mover_steps_v3` is
``MobilityEnv.step_mover`` for K copies: the same compiled functions in the same order (the field's
:func:`~cv2x_marl.sim.kernels.field.pair_field_db`, :func:`~cv2x_marl.sim.kernels.mover_column`, the
measurement update :func:`~cv2x_marl.env.measurement.update_columns`, the observation kernels), so
bit-identical to it (tested: ``tests/env/test_v3_fast.py``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
from numba import njit
from numpy.typing import NDArray

from cv2x_marl.env import step
from cv2x_marl.env.measurement import RSRP_REF_DBM, RSRP_SCALE_DB, update_columns
from cv2x_marl.env.mover_kernels import (
    CopyStacks,
    LinkConstants,
    ObservationConstants,
    StepConstants,
    StepOutputs,
    move_mover,
    observe_mover,
)
from cv2x_marl.env.observation import FEATURES, OWN
from cv2x_marl.env.observation_fills import measured_kernel, own_v3_kernel
from cv2x_marl.env.pcg64 import ZIGGURAT_F64, ZIGGURAT_U64, draw_column_into, jump_table, set_state, state_of
from cv2x_marl.sim.kernels import mover_column
from cv2x_marl.sim.kernels.field import field_pairs_row_into, gather_mover_pairs

if TYPE_CHECKING:
    from cv2x_marl.env.mobility_env import MobilityEnv

FloatArray = NDArray[np.float64]


def widened(owner: Any, name: str, width: int, fill: float) -> NDArray[Any]:
    """Stack ``name`` of ``owner`` [K, ..., G], its last axis grown to at least ``width`` (new entries ``fill``)."""
    stack = getattr(owner, name)
    if width > stack.shape[-1]:
        grown = np.full((*stack.shape[:-1], width), fill, dtype=stack.dtype)
        grown[..., : stack.shape[-1]] = stack
        setattr(owner, name, grown)
        stack = grown
    return stack


class V3Stacks:
    """Per-copy state of the v3 step for K copies of N vehicles (``W`` the sensing window, ``F`` the
    field's waves, ``G`` the interferer table's width)."""

    def __init__(self, envs: list[MobilityEnv]) -> None:
        first = envs[0]
        k, n = len(envs), first.n
        self.k, self.n = k, n
        self.has_field = bool(first.options.shadow_field)
        self.window = int(first.options.sensing_window)
        self.error_db = float(first.options.rsrp_error_db)
        self.power_mw = np.zeros((k, self.window, n, n))
        self.count = np.zeros((k, self.window, n, n))
        self.head = np.zeros(k, dtype=np.int64)
        self.rsrp_dbm = np.full((k, n, n), np.nan)
        self.age = np.zeros((k, n, n), dtype=np.int64)
        self.rx_dbm = np.zeros((k, n, n))
        self.uniform = np.zeros((k, n, n))
        self.fade = np.zeros((k, n, n))
        self.normal = np.zeros((k, n, n))
        #: each copy's ``measurement`` stream: its PCG64 state (:func:`cv2x_marl.env.pcg64.state_of`)
        self.rng_state = np.zeros((k, 4), dtype=np.uint64)
        self.jumps = jump_table(n)
        self.los = np.zeros((k, n, n), dtype=bool)
        self.gain_col_db = np.zeros((k, n))
        self.shadow_col_db = np.zeros((k, n))
        self.idx = np.full((k, n, 1), -1, dtype=np.int64)
        self.val = np.zeros((k, n, 1))
        self.slot_frac = np.zeros((k, n))
        self.sub_frac = np.zeros((k, n))
        self.horizon = np.ones(k, dtype=np.int64)
        w = 1
        # the field of each copy's mover pairs, by the other end (kernels.field.gather_mover_pairs)
        self.f_start = np.zeros((k, n, 2))
        self.f_shadow0 = np.zeros((k, n))
        self.f_sigma = np.zeros((k, n))
        self.f_k_lo = np.zeros((k, n, w, 2))
        self.f_k_hi = np.zeros((k, n, w, 2))
        self.f_phase = np.zeros((k, n, w))
        self.f_g0 = np.zeros((k, n))
        self.decorrelation_m = 1.0
        self.eirp_dbm = 0.0
        self.noise_mw = 0.0

    #: the per-copy stacks :meth:`load` fills (every entry of a copy's row; ``MoverBatch.row_of``), and those
    #: whose last axis grows (with their fill)
    ROW_ARRAYS = (
        "power_mw", "count", "head", "rsrp_dbm", "age", "rng_state", "rx_dbm", "los", "gain_col_db", "shadow_col_db",
        "idx", "val", "slot_frac", "sub_frac", "horizon", "f_start", "f_shadow0", "f_sigma", "f_k_lo", "f_k_hi",
        "f_phase", "f_g0",
    )  # fmt: skip
    WIDE_ARRAYS: dict[str, float] = {"idx": -1, "val": 0.0}  # noqa: RUF012 - a constant table

    def load(self, k: int, env: MobilityEnv, mover: int) -> None:
        """Copy env copy ``k``'s v3 state (just after its reset) into the stacks."""
        m = env.measure
        self.power_mw[k] = m.power_mw
        self.count[k] = m.count
        self.head[k] = m.head
        self.rsrp_dbm[k] = m.rsrp_dbm
        self.age[k] = m.age
        self.rng_state[k] = state_of(m.rng)
        self.rx_dbm[k] = env.rx_dbm
        links = env.links
        args = links.kernel_args
        self.eirp_dbm = float(links.eirp_dbm)
        self.noise_mw = float(links.noise_mw)
        self.los[k] = args.los
        idx, val = args.interferer_idx, args.interferer_val
        widened(self, "idx", idx.shape[1], -1)
        widened(self, "val", val.shape[1], 0.0)
        self.idx[k] = -1
        self.val[k] = 0.0
        self.idx[k, :, : idx.shape[1]] = idx
        self.val[k, :, : val.shape[1]] = val
        self.gain_col_db[k] = args.gain_db[:, mover]
        self.shadow_col_db[k] = links.shadow_db[:, mover]
        cfg = env.config
        slot, sub = np.divmod(env.resource, cfg.sps.n_subchannels)
        self.slot_frac[k] = slot / cfg.traffic.rri_ms
        self.sub_frac[k] = sub / cfg.sps.n_subchannels
        self.horizon[k] = env.horizon
        field = links.field
        if self.has_field:
            assert field is not None
            if self.f_phase.shape[2] != field.phase.shape[-1]:
                w = field.phase.shape[-1]
                self.f_k_lo = np.zeros((self.k, self.n, w, 2))
                self.f_k_hi = np.zeros((self.k, self.n, w, 2))
                self.f_phase = np.zeros((self.k, self.n, w))
            self.f_start[k] = field.start_m
            gather_mover_pairs(
                mover, field.shadow0_db, field.sigma_db, field.k_lo, field.k_hi, field.phase, field.g0,
                self.f_shadow0[k], self.f_sigma[k], self.f_k_lo[k], self.f_k_hi[k], self.f_phase[k], self.f_g0[k],
            )  # fmt: skip
            self.decorrelation_m = float(field.decorrelation_m)

    def kernel_args(self) -> V3Arrays:
        """The stacks and constants :func:`mover_steps_v3` reads, by name."""
        return V3Arrays(
            self.has_field, self.f_start, self.f_shadow0, self.f_sigma, self.decorrelation_m, self.f_k_lo, self.f_k_hi,
            self.f_phase, self.f_g0, self.eirp_dbm, self.noise_mw, self.los, self.gain_col_db, self.shadow_col_db,
            self.idx, self.val, self.power_mw, self.count, self.head, self.rsrp_dbm, self.age, self.rx_dbm,
            self.uniform, self.fade, self.normal, self.rng_state, self.jumps, ZIGGURAT_U64, ZIGGURAT_F64,
            self.error_db, self.slot_frac, self.sub_frac, self.horizon,
        )  # fmt: skip

    def sync(self, k: int, env: MobilityEnv) -> None:
        """Write copy ``k``'s measurements back into its env object."""
        m = env.measure
        m.power_mw = self.power_mw[k].copy()
        m.count = self.count[k].copy()
        m.head = int(self.head[k])
        m.rsrp_dbm = self.rsrp_dbm[k].copy()
        m.age = self.age[k].copy()
        set_state(m.rng, self.rng_state[k])
        env.rx_dbm = self.rx_dbm[k].copy()


class V3Arrays(NamedTuple):
    """The v3 step's per-copy stacks and constants (:meth:`V3Stacks.kernel_args`), K copies of N vehicles.

    Attributes:
        has_field: the shadowing field follows the vehicles; f_start [K, N, 2], f_shadow0, f_sigma [K, N],
            decorrelation_m, f_k_lo, f_k_hi [K, N, F, 2], f_phase [K, N, F], f_g0 [K, N]: the field of each copy's
            mover pairs (:func:`~cv2x_marl.sim.kernels.field.gather_mover_pairs`).
        eirp_dbm, noise_mw: the transmit EIRP (dBm) and noise power (mW).
        los [K, N, N], gain_col_db, shadow_col_db [K, N], idx, val [K, N, G]: the links of the mover's column.
        power_mw, sample_count [K, W, N, N], head [K], rsrp_dbm [K, N, N] (dBm), age [K, N, N], rx_dbm [K, N, N] (dBm):
            the measurements (:class:`~cv2x_marl.env.measurement.Measurements`).
        uniform, fade, normal: [K, N, N] scratch for a period's draws.
        rng_state [K, 4], jumps, zig_u64, zig_f64: the copies' PCG64 measurement streams and the ziggurat tables
            (:mod:`cv2x_marl.env.pcg64`).
        error_db: the RSRP report error (dB); slot_frac, sub_frac: [K, N] resource fractions; horizon: [K] steps.
    """

    has_field: bool
    f_start: FloatArray
    f_shadow0: FloatArray
    f_sigma: FloatArray
    decorrelation_m: float
    f_k_lo: FloatArray
    f_k_hi: FloatArray
    f_phase: FloatArray
    f_g0: FloatArray
    eirp_dbm: float
    noise_mw: float
    los: NDArray[np.bool_]
    gain_col_db: FloatArray
    shadow_col_db: FloatArray
    idx: NDArray[np.int64]
    val: FloatArray
    power_mw: FloatArray
    sample_count: FloatArray
    head: NDArray[np.int64]
    rsrp_dbm: FloatArray
    age: NDArray[np.int64]
    rx_dbm: FloatArray
    uniform: FloatArray
    fade: FloatArray
    normal: FloatArray
    rng_state: NDArray[np.uint64]
    jumps: NDArray[np.uint64]
    zig_u64: NDArray[np.uint64]
    zig_f64: FloatArray
    error_db: float
    slot_frac: FloatArray
    sub_frac: FloatArray
    horizon: NDArray[np.int64]


@njit(cache=True)
def mover_steps_v3(
    active: NDArray[np.bool_],
    actions: FloatArray,
    s: CopyStacks,
    links: LinkConstants,
    c: StepConstants,
    o: ObservationConstants,
    v: V3Arrays,
    out: StepOutputs,
) -> None:
    """Step every ``active`` copy k of observation version 3: ``MobilityEnv.step_mover(actions[k])``, in place:
    :func:`~cv2x_marl.env.mover_kernels.mover_steps`' move, links and record, with the field's row and the
    mover's column of links, one period of measurements (every pair's draws from the copy's stream, the mover's
    column of reports) and the measured and own v3 entries."""
    n = s.positions_m.shape[1]
    window = v.power_mw.shape[1]
    rows = np.zeros(1, dtype=np.int64)
    drift = np.empty((n, 2))
    shadow = np.empty(n)
    gain = np.empty(n)
    rsrp_scaled = np.zeros((n, n))
    age_scaled = np.zeros((n, n))
    u_now = np.empty(1)
    u_prev = np.empty(1)
    drift_one = np.empty((1, 2))
    v0_size = o.k_neighbours * FEATURES + OWN
    for k in range(actions.shape[0]):
        if not active[k]:
            continue
        i, x, y, x_old, y_old, clipped = move_mover(k, actions, s, c)
        pos = s.positions_m[k]
        # the own links' gains where the mover stands: the field's row (MoverLinksStep), or the snapshot's
        if v.has_field:
            field_pairs_row_into(
                x, y, pos, i, v.f_start[k], v.f_shadow0[k], v.f_sigma[k], v.decorrelation_m, v.f_k_lo[k],
                v.f_k_hi[k], v.f_phase[k], v.f_g0[k], shadow,
            )  # fmt: skip
            for j in range(n):
                gain[j] = v.eirp_dbm - shadow[j]
            row_gain = gain
            col_gain = gain
            col_shadow = shadow
        else:
            row_gain = s.gain_row_db[k]
            col_gain = v.gain_col_db[k]
            col_shadow = v.shadow_col_db[k]
        step.mover_row_into(
            x, y, pos, i, s.target[k, i], s.p[k, i], s.los_row[k], row_gain, s.level_db[k], links.period_m,
            links.wb1, links.range2_m2, links.link_model, links.per_sinr_db, links.per, links.threshold_db,
            links.sensitivity_dbm,
        )  # fmt: skip
        p_col, rx_col = mover_column(
            x, y, pos, i, links.period_m, v.los[k], col_gain, col_shadow, v.eirp_dbm, links.wb1, links.range2_m2,
            v.idx[k], v.val[k], v.noise_mw, links.link_model, links.per_sinr_db, links.per, links.threshold_db,
            links.sensitivity_dbm, np.ascontiguousarray(s.target[k, :, i]),
        )  # fmt: skip
        for j in range(n):
            s.p[k, j, i] = p_col[j]
            v.rx_dbm[k, j, i] = rx_col[j]
        rows[0] = i
        # this period's draws of every pair from the copy's measurement stream (Measurements.update's order)
        draw_column_into(v.rng_state[k], v.jumps, v.zig_u64, v.zig_f64, i, v.uniform[k], v.fade[k], v.normal[k])
        update_columns(
            v.power_mw[k], v.sample_count[k], v.head[k], v.rsrp_dbm[k], v.age[k], v.rx_dbm[k], s.p[k], v.uniform[k],
            v.fade[k], v.normal[k], v.error_db, rows,
        )  # fmt: skip
        v.head[k] = (v.head[k] + 1) % window
        out.reward[k] = step.record_mover_step(
            i, x, y, x_old, y_old, clipped, pos, s.p[k, i], s.target[k, i], s.scalars[k], s.best_m[k], s.disp_m[k],
            s.dist2_m2[k], links.period_m, c.p_min, c.normalise, c.improvement, True, out.info[k],
        )  # fmt: skip
        out.done[k] = s.t[k] >= c.max_cycles
        ob = observe_mover(k, s, c, o, rows, drift)
        for j in range(n):  # scaled_rsrp and age / window of the mover's column
            r = (v.rsrp_dbm[k, j, i] - RSRP_REF_DBM) / RSRP_SCALE_DB
            rsrp_scaled[j, i] = r if np.isfinite(r) else 0.0
            age_scaled[j, i] = v.age[k, j, i] / window
        measured_kernel(
            ob, s.disp_m[k], s.dist2_m2[k], s.co_table[k], rsrp_scaled, age_scaled, v.slot_frac[k], v.sub_frac[k],
            rows, o.k_neighbours, v0_size, o.scale_m, o.obs_clip,
        )  # fmt: skip
        hz = v.horizon[k]
        left = max(hz - s.t[k], 0)
        moving = max(min(hz, c.max_cycles - c.settle_steps) - s.t[k], 0)
        u_now[0] = s.scalars[k, step.U_NOW]
        u_prev[0] = s.scalars[k, step.U_PREV]
        drift_one[0, 0] = drift[i, 0]
        drift_one[0, 1] = drift[i, 1]
        own_v3_kernel(
            ob, o.own_v1_offset, o.obs_clip, o.scale_m, u_now, u_prev, drift_one, left / hz, moving * c.max_step_m
        )
        for f in range(o.size):
            out.obs[k, f] = ob[0, f]
