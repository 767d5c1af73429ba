"""``cv2x/Resource-v0``: the candidate list against an independent construction of TS 36.213 14.1.1.6, the chosen
resource held until the next reselection, the standard's behaviour reproduced, the action checks, the observation's
candidate block, and the ceiling against the scripts on every episode."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest

from cv2x_marl.config import apply_overrides, preset
from cv2x_marl.env.defaults import RESOURCE_OVERRIDES
from cv2x_marl.env.observation import CANDIDATE_NAMES, FEATURES_CANDIDATE, N_CANDIDATES, OWN_V4
from cv2x_marl.env.registry import make_parallel_env
from cv2x_marl.env.resource import PendingChoices
from cv2x_marl.env.tasks import TASKS
from cv2x_marl.policies.resource import candidate_block, make_resource_policy, team_objective
from cv2x_marl.sim import Simulator
from cv2x_marl.sim.metrics import CAUSE_CODE
from cv2x_marl.sim.sps import SpsScheduler, candidate_resources

ENV_ID = "cv2x/Resource-v0"
C = {name: i for i, name in enumerate(CANDIDATE_NAMES)}


def _config():
    return apply_overrides(preset("paper"), RESOURCE_OVERRIDES)


def reference_list(rsrp_dbm, rssi_mw, th0_dbm, step_db, fraction):
    """TS 36.213 14.1.1.6 steps 5-8 written out independently: exclude a candidate whose SCI RSRP exceeds the
    threshold (unmonitored: always), raise the threshold by ``step_db`` while fewer than ``ceil(fraction M)``
    remain (a loop, not the closed form), rank the survivors by S-RSSI (ties: the lower index), and the list of
    step 8 is the first ``ceil(fraction M)`` of them."""
    m = len(rsrp_dbm)
    q = math.ceil(fraction * m)
    th = th0_dbm
    while True:
        kept = [c for c in range(m) if rsrp_dbm[c] != math.inf and rsrp_dbm[c] <= th]
        if len(kept) >= q:
            break
        th += step_db
    ranked = sorted(kept, key=lambda c: (rssi_mw[c], c))
    return ranked, q


def test_candidate_list_equals_an_independent_construction():
    """A hand-built scene: vehicle 0 reselects with most of its window reserved by strong SCIs (the threshold must
    rise twice), its own subframe unmonitored, distinct S-RSSI values; the list and the mask are the standard's."""
    cfg = _config()
    n = 3
    sched = SpsScheduler(cfg, n, noise_mw=1e-12)
    sched.record_selections = True
    rng = np.random.default_rng(5)
    sched.reset(np.random.default_rng(1), np.random.default_rng(2), None)
    sched.generation_slot[:] = [10, 40, 70]
    sched.resource[:] = [(15 * 2) + 1, 45 * 2, 75 * 2]  # vehicle 0 on slot 15, sub-channel 1
    cand = candidate_resources(sched.generation_slot[:1], cfg.sps, sched.rri)[0]  # [M] = 40
    m = cand.size
    assert m == 40
    r = sched.n_res
    last_sci = np.zeros((n, r))
    rsrp_target = np.full(m, -np.inf)
    strong = rng.choice(m, size=36, replace=False)  # 36 of 40 reserved
    rsrp_target[strong] = rng.uniform(-109.0, -103.5, size=36)  # above -110: the threshold must rise
    offset = sched.rsrp_offset_db
    with np.errstate(divide="ignore"):
        last_sci[0, cand] = np.where(np.isfinite(rsrp_target), 10 ** ((rsrp_target + offset) / 10.0), 0.0)
    rssi = rng.uniform(1e-11, 1e-9, size=m)
    sched.rssi_ring[:] = np.nan
    sched.rssi_ring[0, 0, cand] = rssi.astype(np.float32)
    chosen = sched._sensing_selection(np.array([0]), last_sci, exclude_own=True)
    pending = PendingChoices.of(sched, n)

    # the reference: the own subframe (slot 15: both sub-channels) unmonitored, RSRP from the same powers
    with np.errstate(divide="ignore"):
        rsrp = 10.0 * np.log10(last_sci[0, cand]) - offset
    rsrp = np.where(cand // 2 == 15, np.inf, rsrp)
    rssi_seen = rssi.astype(np.float32).astype(np.float64)
    ranked, q = reference_list(list(rsrp), list(rssi_seen), -110.0, 3.0, 0.2)
    assert q == 8
    want = [int(cand[c]) for c in ranked[:N_CANDIDATES]]
    assert pending.decides.tolist() == [True, False, False]
    assert pending.n_valid[0] == len(want) and len(want) > q  # survivors beyond step 8's list are shown
    assert pending.resources[0, : len(want)].tolist() == want
    assert np.all(pending.resources[0, len(want) :] == -1)
    assert pending.n_standard[0] == q
    assert int(chosen[0]) in want[:q]  # the standard's own draw is from step 8's list
    assert pending.standard[0] == chosen[0]
    mask = pending.masks()
    assert mask[0].tolist() == [1] * len(want) + [0] * (N_CANDIDATES - len(want))
    assert not mask[1:].any()


def test_chosen_resource_is_held_until_the_next_reselection():
    env = make_parallel_env(ENV_ID, max_cycles=60)
    env.reset(seed=3)
    held: dict[int, int] = {}  # vehicle -> the resource it chose
    checked = 0
    while env.agents:
        masks = env.action_masks()
        acts = {}
        for a in env.agents:
            i = env.agent_index[a]
            valid = np.flatnonzero(masks[i])
            acts[a] = np.int64(valid[-1]) if valid.size else np.int64(0)  # the last valid entry, never the draw's
            if valid.size:
                held[i] = int(env.pending.resources[i, valid[-1]])
        deciding = {i for i in held if masks[i].any()}
        env.step(acts)
        for i, res in held.items():
            if i in deciding or not env.pending.decides[i]:
                assert env.sim.resource[i] == res, f"vehicle {i}"
                checked += 1
        held = {i: r for i, r in held.items() if not env.pending.decides[i]}
    assert checked > 100


def test_nobody_choosing_reproduces_the_simulator():
    """With no mover the standard's own draws stay: the env runs the simulator exactly as it runs alone."""
    env = make_parallel_env(ENV_ID, max_cycles=30, movers=[])
    env.reset(seed=11)
    sim = Simulator(env.config)
    sim.reset(11)
    for _ in range(30):
        env.step({a: np.int64(0) for a in env.agents})
        sim.run(sim.rri, record=False)
        assert np.array_equal(env.sim.resource, sim.resource)
        assert np.array_equal(env.sim.last_links[2], sim.last_links[2])


def _team_means(name: str, seeds, env):
    """[episodes, 3]: the team's episode-mean utility and PRR of policy ``name`` (every agent of ``env``; with no
    mover, the simulator's own draws), and the share of the episode's links lost to a collision."""
    out = []
    policy = make_resource_policy(name, env)
    for s in seeds:
        obs, _ = env.reset(seed=s)
        policy.reset(s)
        lost = total = 0
        while env.agents:
            obs, *_ = env.step(policy.act(obs))
            cause = env.sim.last_links[3]
            lost += int(np.sum(cause == CAUSE_CODE["collision"]))
            total += cause.size
        out.append((env.u_sum.mean() / env.t, env.prr_sum.mean() / env.t, lost / total))
    return np.array(out)


def test_sps_script_reproduces_the_standard_statistics():
    """The ``sps`` script (its own stream) against the simulator's own draws (no mover) on the same 16 episodes: the
    mean PRR within 0.012, the utility within 5 % and the share of links lost to collisions within 0.01. The two runs
    of an episode part after the first reselection, so their means differ by chance: on the first 30 training
    episodes the differences were +0.0003 (standard error 0.0022) in PRR and +0.005 (0.016) in utility per target
    receiver, whose mean is about -2.1; on these 16 the collision shares were 0.0724 and 0.0710 (difference 0.0014,
    standard error 0.0027). The bounds are about four standard errors of a 16-episode mean."""
    seeds = TASKS["resource"].train_seeds[:16]
    script = _team_means("sps", seeds, make_parallel_env(ENV_ID, max_cycles=100))
    own = _team_means("sps", seeds, make_parallel_env(ENV_ID, max_cycles=100, movers=[]))
    assert abs(script[:, 1].mean() - own[:, 1].mean()) < 0.012
    assert abs(script[:, 0].mean() - own[:, 0].mean()) < 0.05 * abs(own[:, 0].mean())
    assert abs(script[:, 2].mean() - own[:, 2].mean()) < 0.01
    assert 0.03 < own[:, 2].mean() < 0.15  # collisions happen: the test can tell


def test_ceiling_never_below_a_script():
    seeds = TASKS["resource"].train_seeds[:3]
    env = make_parallel_env(ENV_ID, max_cycles=100)
    ceiling = _team_means("optimum", seeds, env)
    for name in ("sps", "lowest-rssi", "random", "farthest"):
        script = _team_means(name, seeds, env)
        assert np.all(ceiling[:, 0] >= script[:, 0]), name


def test_actions_are_checked_before_anything_runs():
    env = make_parallel_env(ENV_ID, max_cycles=20)
    env.reset(seed=2)
    while not env.action_masks().any():
        env.step({a: np.int64(0) for a in env.agents})
    masks = env.action_masks()
    i = int(np.flatnonzero(masks.any(axis=1))[0])
    agent = env.possible_agents[i]
    n_valid = int(masks[i].sum())
    before = (env.t, env.sim.subframe, env.sim.resource.copy())
    acts = {a: np.int64(0) for a in env.agents}
    acts[agent] = np.float32(0.5)
    with pytest.raises(ValueError, match=rf"action of {agent} must be an integer in \[0, 20\)"):
        env.step(acts)
    acts[agent] = np.int64(20)
    with pytest.raises(ValueError, match="must be an integer in"):
        env.step(acts)
    acts[agent] = np.array([1, 2])
    with pytest.raises(ValueError, match="must be an integer in"):
        env.step(acts)
    assert (env.t, env.sim.subframe) == before[:2] and np.array_equal(env.sim.resource, before[2])
    # an entry past the list keeps the standard's draw; a vehicle without a decision ignores its action
    standard = env.pending.standard[i]
    acts = {a: np.int64(0) for a in env.agents}
    j = int(np.flatnonzero(~masks.any(axis=1))[0])
    acts[env.possible_agents[j]] = np.int64(19)
    held = env.sim.resource[j]
    if n_valid < N_CANDIDATES:
        acts[agent] = np.int64(n_valid)
        env.step(acts)
        assert env.sim.resource[i] == standard
    else:
        env.step(acts)
    assert env.sim.resource[j] == held or env.pending.decides[j]


def test_candidate_block_of_the_observation():
    env = make_parallel_env(ENV_ID, max_cycles=30)
    obs, infos = env.reset(seed=4)
    while not env.action_masks().any():
        obs, _, _, _, infos = env.step({a: np.int64(0) for a in env.agents})
    i = int(np.flatnonzero(env.action_masks().any(axis=1))[0])
    agent = env.possible_agents[i]
    p = env.pending
    cand = candidate_block(obs[agent], env)
    nv = int(p.n_valid[i])
    assert cand.shape == (N_CANDIDATES, FEATURES_CANDIDATE)
    assert infos[agent]["decides"] == 1.0 and infos[agent]["action_mask"].sum() == nv
    own = env.layout.own_v1_offset + OWN_V4
    assert obs[agent][own] == 1.0 and obs[agent][own + 1] == pytest.approx(nv / N_CANDIDATES)
    assert cand[:nv, C["valid"]].tolist() == [1.0] * nv and not cand[nv:].any()
    assert cand[:, C["standard_list"]].sum() == p.n_standard[i]
    noise = env.sim.scheduler.noise_mw
    np.testing.assert_allclose(cand[:nv, C["rssi"]], 10 * np.log10(p.rssi_mw[i, :nv] / noise) / 20, rtol=1e-6)
    # users: the neighbours whose last decoded SCI (no release) reserves the entry, counted independently
    sci = env.traffic_measure.sci
    for e in range(nv):
        res = p.resources[i, e]
        users = [j for j in range(env.n) if j != i and sci.resource[j, i] == res and not sci.release[j, i]]
        assert cand[e, C["users"]] == pytest.approx(len(users) / 4)
        subframe = [
            j for j in range(env.n) if j != i and sci.resource[j, i] >= 0 and sci.resource[j, i] // 2 == res // 2
        ]
        assert cand[e, C["subframe_users"]] == pytest.approx(len(subframe) / 4)
        slot = res // 2
        delay = (slot - env.sim.scheduler.generation_slot[i]) % 100
        assert 1 <= delay <= 20 and cand[e, C["delay"]] == pytest.approx(delay / 20)


def test_team_objective_by_hand():
    p = np.array([[0.0, 0.5, 1e-6], [0.9, 0.0, 0.2], [0.0, 0.0, 0.0]])
    target = np.array([[False, True, True], [True, False, True], [False, False, False]])
    want = np.mean([(math.log(0.5) + math.log(1e-3)) / 2, (math.log(0.9) + math.log(0.2)) / 2, 0.0])
    assert team_objective(p, target, 1e-3) == pytest.approx(want, rel=1e-12)


def test_seeded_episodes_repeat():
    a = make_parallel_env(ENV_ID, max_cycles=15)
    b = copy.deepcopy(a)
    pol_a, pol_b = make_resource_policy("sps", a), make_resource_policy("sps", b)
    for env, pol in ((a, pol_a), (b, pol_b)):
        obs, _ = env.reset(seed=9)
        pol.reset(9)
        while env.agents:
            obs, *_ = env.step(pol.act(obs))
    assert np.array_equal(a.u_sum, b.u_sum) and np.array_equal(a.sim.resource, b.sim.resource)


def test_overrides_given_apply_after_the_ids_own(tmp_path, monkeypatch):
    """``cv2x/Resource-v0``'s SPS procedures are scenario overrides of the id: those a caller gives (the API, or
    ``evaluate --set``) come after them, and ``evaluate`` without ``--preset`` / ``--set`` keeps them."""
    env = make_parallel_env(ENV_ID, overrides=["sim.warmup_subframes=500"])
    assert env.options.overrides == (*RESOURCE_OVERRIDES, "sim.warmup_subframes=500")
    assert env.config.sps.selection == "3gpp" and env.config.sim.warmup_subframes == 500
    assert make_parallel_env("cv2x/Traffic-v0", overrides=["sim.warmup_subframes=500"]).options.overrides == (
        "sim.warmup_subframes=500",
    )
    import json

    from cv2x_marl.cli import main

    seen = {}
    real = make_parallel_env

    def spy(env_id, **kw):
        env = real(env_id, **kw)
        seen[env_id] = env.options.overrides
        return env

    import cv2x_marl.experiments.evaluate as ev

    monkeypatch.setattr(ev, "make_parallel_env", spy)
    rc = main(["evaluate", "--env", ENV_ID, "--policy", "sps", "--seeds", "5", "--max-cycles", "3", "--quiet", "--out",
               str(tmp_path / "e")])  # fmt: skip
    assert rc == 0 and seen[ENV_ID] == RESOURCE_OVERRIDES
    assert json.loads((tmp_path / "e" / "summary.json").read_text())["mean_utility_gain"] == 0.0  # sps against itself


def test_gymnasium_view_and_its_action_masks():
    """``gymnasium.make("cv2x/Resource-v0")`` is vehicle 0's view: the others keep the standard's draw; its
    ``action_masks()`` (sb3-contrib's convention) is vehicle 0's list when it decides, every entry otherwise."""
    import gymnasium

    import cv2x_marl  # noqa: F401 - registers the ids

    env = gymnasium.make(ENV_ID, max_cycles=40).unwrapped
    _, info = env.reset(seed=8)
    par = env.par
    assert np.flatnonzero(par.mover_mask).tolist() == [0] and env.action_space == gymnasium.spaces.Discrete(20)
    decided = 0
    while par.agents:
        mask = env.action_masks()
        if info["decides"]:
            assert mask.tolist() == info["action_mask"].astype(bool).tolist() and 0 < mask.sum() <= 20
            choice = int(np.flatnonzero(mask)[-1])
            want = int(par.pending.resources[0, choice])
            info = env.step(np.int64(choice))[4]
            assert par.sim.resource[0] == want
            decided += 1
        else:
            assert mask.all()
            info = env.step(np.int64(0))[4]
    assert decided >= 2
    with pytest.raises(ValueError, match="continuous actions"):
        gymnasium.make("cv2x/SingleMover-v3").unwrapped.action_masks()


def _objective_by_hand(mw, resource, n_sub, noise_mw, curve, p_min):
    """The ceiling's objective written out link by link: SINR with the co-channel users' mean powers summed, the
    link curve, 0 in the own subframe (half duplex) or out of range, the mean over the vehicles of the mean over
    their targets (every vehicle in range) of ln max(P, p_min)."""
    n = len(resource)
    per_vehicle = []
    for tx in range(n):
        terms = []
        for rx in range(n):
            if rx == tx or mw[tx, rx] <= 0.0:
                continue
            if resource[rx] // n_sub == resource[tx] // n_sub:
                p = 0.0
            else:
                interference = sum(mw[u, rx] for u in range(n) if u not in (tx, rx) and resource[u] == resource[tx])
                p = float(curve.success(10 * math.log10(mw[tx, rx] / (interference + noise_mw))))
            terms.append(math.log(max(p, p_min)))
        per_vehicle.append(sum(terms) / max(len(terms), 1))
    return sum(per_vehicle) / n


def test_ceiling_is_the_brute_force_best_with_one_or_two_deciders():
    """At steps with one or two deciding vehicles the ceiling's choice reaches the best expected team objective of
    every combination of their entries, the objective computed independently, link by link."""
    import itertools

    from cv2x_marl.env.traffic_measurement import period_rx_dbm

    env = make_parallel_env(ENV_ID, max_cycles=40)
    ceiling = make_resource_policy("optimum", env)
    obs, _ = env.reset(seed=TASKS["resource"].train_seeds[5])
    checked = 0
    while env.agents:
        p = env.pending
        deciders = np.flatnonzero(p.decides)
        if 1 <= deciders.size <= 2 and checked < 4:
            sim = env.sim
            rx = period_rx_dbm(sim.last_geometry, env.n)
            mw = np.where(np.isfinite(rx), 10 ** (rx / 10), 0.0)
            base = sim.scheduler.resource.copy()
            args = (2, sim.scheduler.noise_mw, sim.chunks.curve, env.p_min)
            values = []
            for combo in itertools.product(*(range(int(p.n_valid[i])) for i in deciders)):
                res = base.copy()
                res[deciders] = p.resources[deciders, list(combo)]
                values.append(_objective_by_hand(mw, res, *args))
            choice = ceiling.choices()
            res = base.copy()
            res[deciders] = p.resources[deciders, choice[deciders]]
            assert _objective_by_hand(mw, res, *args) == pytest.approx(max(values), rel=1e-9, abs=1e-12)
            checked += 1
        obs, *_ = env.step(ceiling.act(obs))
    assert checked == 4


def test_independent_ceiling_is_each_deciders_best_alone():
    """``ResourceCeiling(joint=False)`` (the coordination diagnostic): at steps with two or three deciders each one's
    entry reaches the best objective over its own entries, the other deciders on the standard's draw (link by link);
    with one decider it is the ceiling's choice."""
    from cv2x_marl.env.traffic_measurement import period_rx_dbm
    from cv2x_marl.policies.resource import ResourceCeiling

    env = make_parallel_env(ENV_ID, max_cycles=40)
    alone, joint = ResourceCeiling(env, joint=False), ResourceCeiling(env)
    obs, _ = env.reset(seed=TASKS["resource"].train_seeds[6])
    checked = single = 0
    while env.agents:
        p = env.pending
        deciders = np.flatnonzero(p.decides)
        choice = alone.choices()
        if deciders.size == 1:
            assert choice[deciders[0]] == joint.choices()[deciders[0]]
            single += 1
        elif 2 <= deciders.size <= 3 and checked < 3:
            sim = env.sim
            rx = period_rx_dbm(sim.last_geometry, env.n)
            mw = np.where(np.isfinite(rx), 10 ** (rx / 10), 0.0)
            drawn = sim.scheduler.resource.copy()
            drawn[deciders] = p.standard[deciders]
            args = (2, sim.scheduler.noise_mw, sim.chunks.curve, env.p_min)
            for i in deciders:
                values = []
                for entry in range(int(p.n_valid[i])):
                    res = drawn.copy()
                    res[i] = p.resources[i, entry]
                    values.append(_objective_by_hand(mw, res, *args))
                res = drawn.copy()
                res[i] = p.resources[i, choice[i]]
                assert _objective_by_hand(mw, res, *args) == pytest.approx(max(values), rel=1e-9, abs=1e-12)
            checked += 1
        obs, *_ = env.step(alone.act(obs))
    assert checked == 3 and single >= 1
