"""The scripts and the ceiling of ``cv2x/Resource-v0`` (:mod:`cv2x_marl.env.resource`): an action picks an entry of
the vehicle's candidate list, which its observation describes (``observation`` version 5, the candidate block:
:data:`~cv2x_marl.env.observation.CANDIDATE_NAMES`).

    sps           the standard's choice: uniformly among the entries of step 8's list (TS 36.213 14.1.1.6), the
                  ``standard_list`` entries; the simulator's own behaviour, drawn from the policy's own stream
    lowest-rssi   the entry of lowest S-RSSI over the sensing window: the list's first
    random        uniformly among every valid entry of the list (the survivors of the exclusion, up to 20)
    farthest      sensing-aware: the entry whose nearest sensed user (a neighbour whose decoded SCI reserves
                  it) is farthest away, an unreserved one first; ties to the fewest neighbours heard in its
                  subframe (they could not hear the vehicle: half duplex), then to the lower S-RSSI
    optimum       the ceiling (privileged): a centralised choice at each reselection that knows every vehicle's
                  position and reservation now (not the future SPS draws): the deciding vehicles' entries that
                  maximise the expected team objective of the coming period, every combination tried for one or
                  two deciders, coordinate ascent beyond (:class:`ResourceCeiling`)

Every script reads only its own observation; the ceiling reads the env.
"""

from __future__ import annotations

import copy
import itertools
import math
import zlib
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from cv2x_marl.env.observation import CANDIDATE_NAMES, FEATURES_CANDIDATE, N_CANDIDATES, OWN_V4, OWN_V5_EXTRA
from cv2x_marl.env.traffic_measurement import period_rx_dbm
from cv2x_marl.policies.base import Actions, Observations

if TYPE_CHECKING:
    from cv2x_marl.env.mobility_env import MobilityEnv

FloatArray = NDArray[np.float64]
#: the scripts of the task and its ceiling (:func:`make_resource_policy`)
RESOURCE_POLICIES = ("sps", "lowest-rssi", "random", "farthest", "optimum")
_C = {name: i for i, name in enumerate(CANDIDATE_NAMES)}


def is_resource_env(env: Any) -> bool:
    """Whether ``env``'s action picks an SPS resource (``traffic_action="resource"``: ``cv2x/Resource-v0``)."""
    return getattr(getattr(env, "options", None), "traffic_action", None) == "resource"


def resource_reference(start: MobilityEnv, make: Any) -> tuple[FloatArray, FloatArray]:
    """[N] each vehicle's episode-mean utility and PRR under the policy ``make`` builds (``sps``: the reference of the
    task's gains) on the episode ``start`` has just started: a copy of it is run to the end, ``start`` is untouched.
    """
    if start.t != 0:
        raise ValueError("resource_reference needs an env at the start of its episode (just reset)")
    env = copy.deepcopy(start)
    policy = make(env)
    policy.reset(env.seed_used)
    obs: dict[str, Any] = env.observations()
    while env.agents:
        obs, *_ = env.step(policy.act(obs))
    t = max(env.t, 1)
    return env.u_sum / t, env.prr_sum / t


def check_resource_env(env: Any, name: str) -> None:
    """Refuse an env whose action is not a resource choice (``traffic_action="resource"``, observation 5)."""
    if not is_resource_env(env):
        raise ValueError(
            f"policy {name!r} picks an SPS resource: it needs cv2x/Resource-v0 (traffic_action resource, "
            f"observation 5); this env's traffic_action is {env.options.traffic_action!r}"
        )


def candidate_block(obs: NDArray[np.floating], env: Any) -> NDArray[np.floating]:
    """[K, F] the candidate block of one observation (:data:`~cv2x_marl.env.observation.CANDIDATE_NAMES`)."""
    start = env.layout.own_v1_offset + OWN_V4 + len(OWN_V5_EXTRA)
    return obs[start : start + N_CANDIDATES * FEATURES_CANDIDATE].reshape(N_CANDIDATES, FEATURES_CANDIDATE)


class ResourceScript:
    """A script of the task (module docstring): each agent's choice from its own candidate block."""

    def __init__(self, env: MobilityEnv, name: str) -> None:
        if name not in RESOURCE_POLICIES or name == "optimum":
            raise ValueError(f"unknown resource script {name!r}; scripts: sps, lowest-rssi, random, farthest")
        check_resource_env(env, name)
        self.env = env
        self.name = name
        self.rng = np.random.default_rng(0)

    def reset(self, seed: int | None = None) -> None:
        """A fresh stream per episode: ``SeedSequence([seed, crc32(name)])`` (the entropy of the OS without a seed)."""
        entropy = None if seed is None else [int(seed), zlib.crc32(self.name.encode())]
        self.rng = np.random.default_rng(np.random.SeedSequence(entropy))

    def choose(self, cand: NDArray[np.floating]) -> int:
        """The entry this script picks from a candidate block [K, F] (0 when the list is empty)."""
        valid = cand[:, _C["valid"]] > 0.5
        n_valid = int(valid.sum())
        if n_valid == 0:
            return 0
        if self.name == "lowest-rssi":
            return 0
        if self.name == "random":
            return int(self.rng.integers(n_valid))
        if self.name == "sps":
            n_std = max(int((cand[:, _C["standard_list"]] > 0.5).sum()), 1)
            return int(self.rng.integers(n_std))
        # farthest, within the standard's list: the entries with the fewest neighbours heard in their subframe (half
        # duplex: they could not hear the vehicle) and, among those, no sensed user or the farthest one; one of
        # them uniformly (as the standard draws, so that vehicles sensing alike do not all pick the same one)
        n_std = max(int((cand[:, _C["standard_list"]] > 0.5).sum()), 1)
        c = cand[:n_std]
        dist = np.where(c[:, _C["users"]] > 0, np.hypot(c[:, _C["user_dx"]], c[:, _C["user_dy"]]), np.inf)
        half = c[:, _C["subframe_users"]]
        best = np.flatnonzero(half == half.min())
        far = best[dist[best] == dist[best].max()]
        return int(far[self.rng.integers(far.size)])

    def act(self, observations: Observations) -> Actions:
        return {a: np.int64(self.choose(candidate_block(o, self.env))) for a, o in observations.items()}  # type: ignore[misc]


def expected_success(
    mean_rx_mw: FloatArray, resource: NDArray[np.int64], n_sub: int, noise_mw: float, curve: Any
) -> FloatArray:
    """[N(tx), N(rx)] expected success of every link of a period with resources ``resource`` [N] and mean received
    powers ``mean_rx_mw`` [N(tx), N(rx)] (mW, 0 out of range): the link curve at the mean SINR, the co-channel
    transmitters (same resource) summed as interference, 0 where the receiver sends in the same subframe (half
    duplex) and on the diagonal (the ceiling's model: no fading, no in-band emission)."""
    same_res = resource[:, None] == resource[None, :]  # [tx, tx']
    # interference at rx on tx's resource: sum over tx' != tx on the same resource of P[tx', rx]
    total = same_res.astype(np.float64) @ mean_rx_mw  # [tx, rx]: sum over the resource's users, tx included
    interference = np.maximum(total - mean_rx_mw, 0.0)
    with np.errstate(divide="ignore"):
        sinr_db = 10.0 * np.log10(mean_rx_mw / (interference + noise_mw))
    p = np.asarray(curve.success(sinr_db), dtype=np.float64)
    slot = resource // n_sub
    p = np.where(slot[:, None] == slot[None, :], 0.0, p)
    p = np.where(mean_rx_mw > 0.0, p, 0.0)
    np.fill_diagonal(p, 0.0)
    return p


def team_objective(p: FloatArray, target: NDArray[np.bool_], p_min: float) -> float:
    """The mean over the vehicles of the eq. 12 utility per target receiver of links ``p`` [N, N] over ``target``."""
    terms = np.where(target, np.log(np.maximum(p, p_min)), 0.0)
    count = np.maximum(target.sum(axis=1), 1)
    return float(np.mean(terms.sum(axis=1) / count))


class ResourceCeiling:
    """The task's ceiling (privileged; module docstring): at each step, the deciding vehicles' entries that maximise
    the expected team objective of the coming period (:func:`expected_success` with the mean received powers of the
    period just run, everyone's reservations now). Every combination of the deciders' entries is tried when there
    are at most ``exhaustive`` of them (one or two deciders, as in most periods; ties: the first in the lists'
    order); otherwise coordinate ascent, starting from each one's lowest-S-RSSI entry and sweeping the deciders in
    index order until no single change raises it (at most ``sweeps`` times).

    It is the best *found* at each step (exact per step with few deciders), not an optimum over the episode, and it
    does not know the future SPS draws (other vehicles' later reselections) or the fading.

    With ``joint=False`` (a diagnostic, ``benchmarks/resource_coordination.py``) every decider instead maximises the
    same objective alone, the other deciders on the resources the standard drew for them: the same knowledge
    without the coordination between vehicles that reselect in the same period.

    Args:
        env: a ``cv2x/Resource-v0`` env (read, never stepped).
        sweeps: coordinate-ascent sweeps beyond ``exhaustive`` combinations.
        exhaustive: the most combinations of the deciders' entries tried one by one.
        joint: choose the deciders' entries together (the ceiling) or each alone (the diagnostic).
    """

    name = "optimum"

    def __init__(self, env: MobilityEnv, sweeps: int = 3, exhaustive: int = 400, joint: bool = True) -> None:
        check_resource_env(env, "optimum")
        self.env = env
        self.sweeps = sweeps
        self.exhaustive = exhaustive
        self.joint = bool(joint)

    def reset(self, seed: int | None = None) -> None:
        return None

    def choices(self) -> NDArray[np.int64]:
        """[N] the entry of every vehicle (0 for those without a decision)."""
        env = self.env
        pending = env.pending
        out = np.zeros(env.n, dtype=np.int64)
        deciders = np.flatnonzero(pending.decides & env.mover_mask)
        if not deciders.size:
            return out
        sim = env.sim
        assert sim.last_geometry is not None
        rx_dbm = period_rx_dbm(sim.last_geometry, env.n)
        with np.errstate(over="ignore"):
            mean_mw = np.where(np.isfinite(rx_dbm), 10.0 ** (rx_dbm / 10.0), 0.0)
        resource = sim.scheduler.resource.copy()
        resource[deciders] = pending.resources[deciders, 0]
        target = mean_mw > 0.0
        n_sub, noise, curve = sim.config.sps.n_subchannels, sim.scheduler.noise_mw, sim.chunks.curve
        p_min = env.p_min

        def score(res: NDArray[np.int64]) -> float:
            return team_objective(expected_success(mean_mw, res, n_sub, noise, curve), target, p_min)

        if not self.joint:  # each decider alone, the others on the standard's draw
            drawn = resource.copy()
            drawn[deciders] = pending.standard[deciders]
            for i in deciders:
                alone, best = drawn.copy(), -np.inf
                for entry in range(int(pending.n_valid[i])):
                    alone[i] = pending.resources[i, entry]
                    value = score(alone)
                    if value > best + 1e-12:
                        best, out[i] = value, entry
            return out
        sizes = [int(pending.n_valid[i]) for i in deciders]
        if math.prod(sizes) <= self.exhaustive:
            best = -np.inf
            for combo in itertools.product(*(range(k) for k in sizes)):
                resource[deciders] = pending.resources[deciders, list(combo)]
                value = score(resource)
                if value > best + 1e-12:
                    best, out[deciders] = value, combo
            return out
        best = score(resource)
        for _ in range(self.sweeps):
            changed = False
            for i in deciders:
                current = resource[i]
                for entry in range(int(pending.n_valid[i])):
                    resource[i] = pending.resources[i, entry]
                    value = score(resource)
                    if value > best + 1e-12:
                        best, current, out[i], changed = value, resource[i], entry, True
                resource[i] = current
            if not changed:
                break
        return out

    def act(self, observations: Observations) -> Actions:
        choice = self.choices()
        return {a: np.int64(choice[self.env.agent_index[a]]) for a in observations}  # type: ignore[misc]


def make_resource_policy(spec: str, env: MobilityEnv) -> Any:
    """The task's script or ceiling named ``spec`` (:data:`RESOURCE_POLICIES`)."""
    if spec == "optimum":
        return ResourceCeiling(env)
    return ResourceScript(env, spec)
