"""``cv2x/Resource-v0``: every vehicle chooses its SPS resource from what it sensed.

The parts of the task (the env is :class:`~cv2x_marl.env.mobility_env.MobilityEnv` with them):

* the action kind ``resource`` (:class:`ResourceChoice`): vehicles drive (traffic mode, the lane model or SUMO) and
  the simulator runs its SPS with the standard's procedures, one 100-ms period per step. At the end of a period
  the vehicles whose reselection counter expired (and that do not keep their resource) reselect (TS 36.321
  5.14.1.1); the scheduler runs the standard's sensing-based selection (TS 36.213 14.1.1.6 steps 5-8) and keeps
  what it sensed (:class:`~cv2x_marl.sim.sps.SelectionRecord`). Such a vehicle *decides* in the next step: its
  action picks one entry of its candidate list, the survivors of the exclusion (steps 5-7) ranked by the
  standard's metric (ascending S-RSSI over the sensing window, step 8), at most :data:`N_CANDIDATES` of them. It
  transmits on the chosen resource from the next period until its next reselection. A vehicle without a
  decision this step (or not among ``movers``), and an entry past the list (``action_mask`` 0), keep the
  standard's own draw (the scheduler's, from step 8's list).
* observation version 5 (:class:`ResourceObservation`): observation version 4's blocks (the v0 block, per
  neighbour what the vehicle measured and decoded of its SCIs, the own SPS state), then whether it decides,
  and per candidate what it sensed on it (:data:`CANDIDATE_NAMES`): nothing a vehicle could not have sensed.
* the reward: the eq. 12 utility per target receiver of the vehicle's own transmission in the period just run
  (its target receivers: every vehicle in ``link.max_range_m``; a receiver sending in the same subframe
  cannot hear it, so that link counts as lost: the resource decides it).

The action space is ``Discrete(N_CANDIDATES)``; every agent's info carries ``action_mask`` (int8 [K]: the valid
entries of its list, all zero when it has no decision) and ``decides`` (1.0 / 0.0), and
:meth:`MobilityEnv.action_masks` gives them as one [N, K] array.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np
from gymnasium import spaces
from numpy.typing import NDArray

from cv2x_marl.env import step as step_core
from cv2x_marl.env.dynamics import Moved, Traffic, register_dynamics
from cv2x_marl.env.measurement import RSRP_REF_DBM, RSRP_SCALE_DB, scaled_rsrp
from cv2x_marl.env.observation import (
    FEATURES_CANDIDATE,
    FEATURES_V4,
    N_CANDIDATES,
    OWN_V4,
    OWN_V5,
    OWN_V5_EXTRA,
    VERSION_BLOCKS,
)
from cv2x_marl.env.observation_models import RoadMeasuredObservation, register_observation
from cv2x_marl.sim.sps import SpsScheduler

if TYPE_CHECKING:
    from cv2x_marl.env.episode import EpisodeEnv
    from cv2x_marl.sim import Simulator

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass
class PendingChoices:
    """The decisions of the next step, from the selections the scheduler ran at the period's end.

    Attributes:
        decides: [N] the vehicle reselected at the period's end (its action picks its resource).
        resources: [N, K] its candidate list in the standard's ranking (``slot * n_sub + subchannel``; -1: none).
        n_valid: [N] entries of the list (0: no decision).
        n_standard: [N] the first ``n_standard`` entries are the standard's list (step 8).
        rssi_mw: [N, K] each entry's S-RSSI over the sensing window (mW; NaN: none).
        sci_rsrp_dbm: [N, K] RSRP of the strongest SCI reserving it (dBm; ``-inf``: none).
        standard: [N] the resource the standard's draw chose (-1: no decision).
    """

    decides: NDArray[np.bool_]
    resources: IntArray
    n_valid: IntArray
    n_standard: IntArray
    rssi_mw: FloatArray
    sci_rsrp_dbm: FloatArray
    standard: IntArray

    @classmethod
    def of(cls, sched: SpsScheduler, n: int, k: int = N_CANDIDATES) -> PendingChoices:
        """The decisions the scheduler's recorded selections (:attr:`SpsScheduler.selections`) leave for ``n``
        vehicles, lists of at most ``k`` entries."""
        out = cls(
            np.zeros(n, dtype=bool), np.full((n, k), -1, dtype=np.int64), np.zeros(n, dtype=np.int64),
            np.zeros(n, dtype=np.int64), np.full((n, k), np.nan), np.full((n, k), -np.inf),
            np.full(n, -1, dtype=np.int64),
        )  # fmt: skip
        for rec in sched.selections:
            rows = rec.vehicles
            m = rec.candidates.shape[1]
            n_kept = rec.n_kept
            top = rec.order[:, : min(k, m)]
            width = top.shape[1]
            valid = np.arange(width)[None, :] < np.minimum(n_kept, k)[:, None]
            cand = np.take_along_axis(rec.candidates, top, axis=1)
            out.decides[rows] = True
            out.resources[rows, :width] = np.where(valid, cand, -1)
            out.n_valid[rows] = valid.sum(axis=1)
            out.n_standard[rows] = np.minimum(rec.n_list, out.n_valid[rows])
            out.rssi_mw[rows, :width] = np.where(valid, np.take_along_axis(rec.rssi_mw, top, axis=1), np.nan)
            out.sci_rsrp_dbm[rows, :width] = np.where(valid, np.take_along_axis(rec.rsrp_dbm, top, axis=1), -np.inf)
            out.standard[rows] = rec.chosen
        return out

    def masks(self, movers: NDArray[np.bool_] | None = None) -> NDArray[np.int8]:
        """[N, K] int8: 1 on the valid entries of each deciding vehicle's list (of ``movers`` only, when given)."""
        k = self.resources.shape[1]
        m = np.arange(k)[None, :] < self.n_valid[:, None]
        if movers is not None:
            m &= movers[:, None]
        return m.astype(np.int8)


def decode_choices(
    actions: Any, live: set[str], agents: list[str], possible_agents: list[str], agent_index: dict[str, int],
    k: int,
) -> IntArray:  # fmt: skip
    """The choices a ``step`` received, checked, as [N] list entries by vehicle index (0 where none), each an entry
    of ``Discrete(k)``.

    Every live agent gives an action (as PettingZoo asks); it must be an integer in ``[0, K)`` (the action space).
    An entry past a deciding vehicle's list (``action_mask`` 0 there) keeps the standard's own draw, as a vehicle
    without a decision does (:meth:`ResourceChoice.move`); nothing is applied when an action is refused.

    Raises:
        TypeError: ``actions`` is not a dict.
        KeyError: an unknown or finished agent, or a live agent without an action (named).
        ValueError: an action that is not an integer of the space (named, with the allowed values).
    """
    step_core.check_action_agents(actions, live, agents)
    out = np.zeros(len(possible_agents), dtype=np.int64)
    try:  # the usual case: one integer per agent, all in the space
        arr = np.asarray(list(actions.values()))
    except ValueError:  # ragged: the loop below names the culprit
        arr = np.empty(0)
    if arr.shape == (len(actions),) and arr.dtype.kind in "iu" and ((arr >= 0) & (arr < k)).all():
        out[[agent_index[a] for a in actions]] = arr
        return out
    for agent, value in actions.items():
        arr = np.asarray(value)
        if arr.size != 1 or arr.dtype.kind not in "iu":
            raise ValueError(f"action of {agent} must be an integer in [0, {k}) (a list entry), got {value!r}")
        a = int(arr.flat[0])
        if not 0 <= a < k:
            raise ValueError(f"action of {agent} must be an integer in [0, {k}) (a list entry), got {a}")
        out[agent_index[agent]] = a
    return out


@register_dynamics
class ResourceChoice(Traffic):
    """The action kind ``resource`` (module docstring): the deciding movers' choices replace the standard's draw,
    then the simulator runs the period."""

    kind = "resource"
    #: the scheduler keeps its selections' sensing (:attr:`SpsScheduler.record_selections`)
    record_selections: ClassVar[bool] = True

    def action_space(self) -> spaces.Space[Any]:
        return spaces.Discrete(N_CANDIDATES)

    @property
    def null_action(self) -> Any:
        return np.int64(0)

    def decode(self, actions: Any) -> Any:
        env = self.env
        return decode_choices(actions, env._live, env.agents, env.possible_agents, env.agent_index, N_CANDIDATES)

    def move(self, act: Any, settle: bool) -> Moved:
        env = self.env
        sched = env.sim.scheduler
        pending: PendingChoices = env.pending
        act = np.asarray(act)
        rows = np.flatnonzero(pending.decides & env.mover_mask & (act < pending.n_valid))  # past the list: the draw
        if rows.size:
            sched.resource[rows] = pending.resources[rows, act[rows]]
        self.run_period()
        return np.zeros((env.n, 2)), np.zeros(env.n, dtype=bool)

    def links(self) -> tuple[FloatArray, NDArray[np.bool_]]:
        """The period's own link outcomes; every receiver in range is a target (a half-duplex one counts as lost).
        Also the decisions of the coming step (``env.pending``, :class:`PendingChoices`)."""
        p, _ = super().links()
        env = self.env
        env.pending = PendingChoices.of(env.sim.scheduler, env.n)
        assert env.sim.last_links is not None
        tx, rx, _, _ = env.sim.last_links
        target = np.zeros((env.n, env.n), dtype=bool)
        target[tx, rx] = True
        return p, target

    def infos(self, infos: dict[str, dict[str, Any]]) -> None:
        env = self.env
        masks = env.pending.masks(env.mover_mask)
        for agent, info in infos.items():
            i = env.agent_index[agent]
            info["decides"] = float(masks[i].any())
            info["action_mask"] = masks[i]

    def action_masks(self) -> NDArray[np.int8]:
        return self.env.pending.masks(self.env.mover_mask)


def candidate_features(
    pending: PendingChoices, sim: Simulator, sci_resource: IntArray, sci_release: NDArray[np.bool_],
    rsrp_scaled: FloatArray, positions_m: FloatArray, period_m: FloatArray, scale_m: float, rows: IntArray,
) -> FloatArray:  # fmt: skip
    """[A, K, F] the candidate block of agents ``rows`` (:data:`CANDIDATE_NAMES`), zero past each list.

    Args:
        pending: the decisions of the coming step.
        sim: the simulator (its scheduler's generation slots, the SPS configuration).
        sci_resource, sci_release: [N(tx), N(rx)] the resource of the last SCI of tx decoded at rx (-1: none) and
            whether it announced a reselection (:class:`~cv2x_marl.env.traffic_measurement.SciReports`).
        rsrp_scaled: [N(tx), N(rx)] the measured RSRP of each link, scaled (0: never heard).
        positions_m: [N, 2] the positions the CAMs carry (m); period_m: [2] the torus (inf: none).
        scale_m: the observation's length unit (m).
        rows: [A] the agents.
    """
    sched = sim.scheduler
    cfg = sim.config.sps
    k, f = pending.resources.shape[1], FEATURES_CANDIDATE
    out = np.zeros((rows.size, k, f))
    n_sub = cfg.n_subchannels
    rri = sched.rri
    window_end = cfg.t1_subframes + cfg.selection_window_subframes - 1
    for a in np.flatnonzero(pending.n_valid[rows] > 0):  # the deciders: a handful per period
        i = rows[a]
        nv = int(pending.n_valid[i])
        res = pending.resources[i, :nv]
        slot = res // n_sub
        block = out[a]
        block[:nv, 0] = 1.0
        block[: pending.n_standard[i], 1] = 1.0
        with np.errstate(divide="ignore"):
            block[:nv, 2] = 10.0 * np.log10(pending.rssi_mw[i, :nv] / sched.noise_mw) / 20.0
            rsrp = (pending.sci_rsrp_dbm[i, :nv] - RSRP_REF_DBM) / RSRP_SCALE_DB
        reserved = np.isfinite(rsrp)
        block[:nv, 3] = np.where(reserved, rsrp, 0.0)
        block[:nv, 4] = reserved
        heard = sci_resource[:, i]  # [N(tx)] the resource each neighbour's last decoded SCI carried
        reserving = (heard >= 0) & ~sci_release[:, i]
        reserving[i] = False
        users = reserving[:, None] & (heard[:, None] == res[None, :])  # [N, nv]
        block[:nv, 4 + 1] = users.sum(axis=0) / 4.0
        d = positions_m - positions_m[i]
        for ax in range(2):
            if np.isfinite(period_m[ax]):
                d[:, ax] -= period_m[ax] * np.rint(d[:, ax] / period_m[ax])
        dist = np.hypot(d[:, 0], d[:, 1])
        cand_dist = np.where(users, dist[:, None], np.inf)
        nearest = np.argmin(cand_dist, axis=0)
        has = np.isfinite(cand_dist[nearest, np.arange(nv)])
        block[:nv, 6] = np.where(has, d[nearest, 0] / scale_m, 0.0)
        block[:nv, 7] = np.where(has, d[nearest, 1] / scale_m, 0.0)
        block[:nv, 8] = np.where(has, rsrp_scaled[nearest, i], 0.0)
        heard_any = heard >= 0
        heard_any[i] = False
        same_sub = heard_any[:, None] & ((heard[:, None] // n_sub) == slot[None, :])
        block[:nv, 9] = same_sub.sum(axis=0) / 4.0
        block[:nv, 10] = ((slot - sched.generation_slot[i]) % rri) / window_end
        block[:nv, 11] = (res % n_sub) / n_sub
    return out


@register_observation
class ResourceObservation(RoadMeasuredObservation):
    """Version 5 (``cv2x/Resource-v0``): version 4's entries (what the vehicle measured and decoded on the road, its
    own SPS state), whether it decides and its list's size, then per candidate what it sensed on it."""

    version = 5
    per_neighbour, own = FEATURES_V4, OWN_V5

    def fill(self, env: EpisodeEnv, obs: NDArray[np.float32], rows: IntArray) -> None:
        super().fill(env, obs, rows)
        lay = env.layout
        pending: PendingChoices = env.pending
        start = lay.own_v1_offset + OWN_V4
        obs[:, start] = (pending.decides & env.mover_mask)[rows]
        obs[:, start + 1] = pending.n_valid[rows] / N_CANDIDATES
        m, sci = env.traffic_measure.rsrp, env.traffic_measure.sci
        block = candidate_features(
            pending, env.sim, sci.resource, sci.release, scaled_rsrp(m.rsrp_dbm), env.positions_m, env.period_m,
            lay.scale_m, rows,
        )  # fmt: skip
        c0 = start + len(OWN_V5_EXTRA)
        obs[:, c0 : c0 + N_CANDIDATES * FEATURES_CANDIDATE] = np.clip(
            block.reshape(rows.size, -1), -lay.obs_clip, lay.obs_clip
        )


assert VERSION_BLOCKS[5] == (FEATURES_V4, OWN_V5)
