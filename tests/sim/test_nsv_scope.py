"""metrics.nsv_scope (issue 15): NSV counted over the link's resource (co_channel) or over every
transmitter of its subframe (concurrent). The physics is the same; only NSV and l change."""

from __future__ import annotations

import numpy as np
import pytest

from cv2x_marl.config import ConfigError, apply_overrides, preset
from cv2x_marl.sim import Simulator

BASE = ["sim.warmup_subframes=200", "vehicles.n_vehicles=40"]


def _links(*extra: str) -> dict[str, np.ndarray]:
    sim = Simulator(apply_overrides(preset("paper"), [*BASE, *extra]))
    sim.reset(11)
    links = sim.run(600).links
    assert links is not None
    return links


def test_concurrent_counts_every_transmitter_of_the_subframe() -> None:
    co, cc = _links("metrics.nsv_scope=co_channel"), _links("metrics.nsv_scope=concurrent")
    for col in ("tx", "rx", "subframe", "p_success", "outcome", "sinr_db"):  # same run, same physics
        np.testing.assert_array_equal(co[col], cc[col])
    assert np.all(cc["nsv"] >= co["nsv"]) and np.any(cc["nsv"] > co["nsv"])
    assert np.all(cc["interferer_distance_m"] <= co["interferer_distance_m"])
    # with one subchannel per subframe the two scopes are the same set of transmitters
    one_co = _links("sps.n_subchannels=1", "metrics.nsv_scope=co_channel")
    one_cc = _links("sps.n_subchannels=1", "metrics.nsv_scope=concurrent")
    np.testing.assert_array_equal(one_co["nsv"], one_cc["nsv"])


def test_group_terms_against_brute_force() -> None:
    sim = Simulator(apply_overrides(preset("paper"), BASE))
    sim.reset(3)
    rng = np.random.default_rng(0)
    active = rng.uniform(size=sim.n) < 0.5
    tx = np.flatnonzero(active).repeat(3)
    rx = rng.integers(0, sim.n, size=tx.size)
    for group in (sim.resource, sim.slot):
        rep, partner = sim.chunks.group_terms(tx, rx, active, group)
        got = sorted(zip(rep.tolist(), partner.tolist(), strict=True))
        want = sorted(
            (k, c)
            for k, (t, r) in enumerate(zip(tx, rx, strict=True))
            for c in np.flatnonzero(active)
            if c != t and c != r and group[c] == group[t]
        )
        assert got == want


def test_unknown_scope_is_refused_by_name() -> None:
    with pytest.raises(ConfigError, match=r"metrics\.nsv_scope: 'all' is not allowed"):
        apply_overrides(preset("paper"), ["metrics.nsv_scope=all"])


def test_gbmu_inputs_and_env_observations_follow_the_scope() -> None:
    from cv2x_marl.env import MobilityEnv
    from cv2x_marl.experiments.gbmu_study import gbmu_inputs
    from cv2x_marl.sim.ground_truth import MoverLinks

    cfg = apply_overrides(preset("paper"), [*BASE, "metrics.nsv_scope=concurrent"])
    th_i = cfg.metrics.interferer_range_m
    env = MobilityEnv(config=cfg, n_neighbours=5)
    obs, _ = env.reset(seed=5)
    snap = env.snapshot
    pos = snap.positions_m
    others = np.flatnonzero((snap.slot == snap.slot[0]) & (np.arange(env.n) != 0))  # concurrent with vehicle 0
    links = MoverLinks.from_snapshots(cfg, [snap], [0])
    inputs = gbmu_inputs([snap], [0], links, th_i)
    for j in range(1, env.n):
        near = [c for c in others if c != j and np.hypot(*(pos[c] - pos[j])) <= th_i]
        assert inputs.nsv[0, j] == len(near)
    # the env's neighbour features: [dx, dy, target, NSV, ...] for the 5 nearest, nearest first
    d = np.hypot(*(pos - pos[0]).T)
    d[0] = np.inf
    for kk, j in enumerate(np.argsort(d, kind="mergesort")[:5]):
        near = [c for c in others if c != j and np.hypot(*(pos[c] - pos[j])) <= th_i]
        assert obs["vehicle_0"][kk * 7 + 3] == len(near)
