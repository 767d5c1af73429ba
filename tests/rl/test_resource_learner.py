"""MAPPO / independent PPO with masked discrete actions on cv2x/Resource-v0 (cv2x_marl.rl.mappo_masked): sampling
and the deterministic choice stay in the mask, the mask read from the observation is the env's, seeding, resume,
the loader refuses other action spaces, and a quick run beats random and lowest-rssi."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("torchrl")

import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from tensordict import TensorDict

from cv2x_marl.env.registry import make_parallel_env
from cv2x_marl.env.seeds import TRAIN_SEEDS, training_pool
from cv2x_marl.experiments.evaluate import trained_env_options
from cv2x_marl.policies.mappo import MappoPolicy, masked_choices
from cv2x_marl.policies.mappo_nets import MaskedActor, candidate_spec
from cv2x_marl.policies.registry import make_policy
from cv2x_marl.rl.errors import TrainError
from cv2x_marl.rl.mappo import GROUP, build_mappo, train_mappo
from cv2x_marl.rl.mappo_config import MappoConfig, MappoSettings, load_mappo_config

ENV = "cv2x/Resource-v0"
#: a small scene: 8 vehicles, a short warm-up, 10-step episodes
SCENE = ["vehicles.n_vehicles=8", "sim.warmup_subframes=200"]
TINY = MappoConfig(
    env_id=ENV,
    copies=2,
    env={"max_cycles": 10, "start_pool": 8, "overrides": SCENE},
    mappo=MappoSettings(
        n_epochs=2,
        minibatch_steps=5,
        actor_net=(16,),
        critic_net=(16,),
        encoder="candidates",
        encoder_units=8,
        critic="observation",
        ent_coef=0.01,
    ),
    eval_every=1,
    eval_episodes=2,
)


@pytest.fixture(scope="module")
def run():  # type: ignore[no-untyped-def]
    return build_mappo(TINY, seed=0)


def _masks(rng: np.random.Generator, rows: int, n: int) -> np.ndarray:
    """Random masks [rows, n] with at least one valid entry per row (a deciding agent's list)."""
    m = rng.random((rows, n)) < rng.uniform(0.05, 1.0, size=(rows, 1))
    m[np.arange(rows), rng.integers(n, size=rows)] = True
    return m


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 2**32 - 1), rows=st.integers(1, 12))
def test_masked_sampling_never_picks_an_invalid_entry(run, seed: int, rows: int) -> None:  # type: ignore[no-untyped-def]
    """Through the trainer's own ProbabilisticActor (TorchRL's MaskedCategorical): 50 samples of each random mask,
    logits scaled up so that the invalid entries would often win without the mask."""
    rng = np.random.default_rng(seed)
    mask = _masks(rng, rows, run.n_actions)
    obs = torch.from_numpy(rng.normal(scale=3.0, size=(rows, run.obs_size)).astype(np.float32))
    with torch.no_grad():
        for _ in range(50):
            td = TensorDict({GROUP: TensorDict({"observation": obs, "mask": torch.from_numpy(mask)}, [rows])}, [rows])
            run.policy(td)
            action = td[GROUP, "action"].numpy()
            assert mask[np.arange(rows), action].all()
            assert np.isfinite(td[GROUP, "sample_log_prob"].numpy()).all()


def _with_masks(actor: MaskedActor, obs: np.ndarray, mask: np.ndarray, decides: np.ndarray) -> np.ndarray:
    """``obs`` with the candidates' ``valid`` entries set to ``mask`` and ``decides`` set."""
    spec = actor.spec()["candidates"]
    out = obs.copy()
    valid = spec["start"] + spec["features"] * np.arange(spec["count"])
    out[:, valid] = mask
    out[:, spec["decides"]] = decides
    return out


def test_the_deterministic_choice_is_the_argmax_over_the_valid_entries(run) -> None:  # type: ignore[no-untyped-def]
    rng = np.random.default_rng(1)
    actor = run.actor
    for _ in range(20):
        rows = 16
        mask = _masks(rng, rows, run.n_actions)
        decides = rng.random(rows) < 0.7
        obs = _with_masks(actor, rng.normal(scale=2.0, size=(rows, run.obs_size)).astype(np.float32), mask, decides)
        with torch.no_grad():
            x = torch.from_numpy(obs)
            logits = actor(x).numpy()
            chosen = actor.deterministic(x).numpy()
            np.testing.assert_array_equal(actor.mask_of(x).numpy(), mask & decides[:, None])
        want = np.where(decides, np.where(mask, logits, -np.inf).argmax(1), 0)
        np.testing.assert_array_equal(chosen, want)
        assert mask[decides, chosen[decides]].all()
        # the policy on each agent's row alone gives the same choices
        acts = masked_choices(actor, {f"a{i}": obs[i] for i in range(rows)})
        np.testing.assert_array_equal(np.array(list(acts.values())), want)


def test_the_mask_read_from_the_observation_is_the_envs() -> None:
    env = make_parallel_env(ENV, max_cycles=30)
    actor = MaskedActor(env.observation_space("vehicle_0").shape[0], 20, candidates=candidate_spec(env.layout))
    rng = np.random.default_rng(0)
    obs, infos = env.reset(seed=int(TRAIN_SEEDS[300]))
    decided = 0
    while env.agents:
        stacked = torch.from_numpy(np.stack([obs[a] for a in env.possible_agents]))
        mask = env.action_masks()
        np.testing.assert_array_equal(actor.mask_of(stacked).numpy(), mask > 0)
        for a in env.possible_agents:
            np.testing.assert_array_equal(infos[a]["action_mask"], mask[env.agent_index[a]])
        decided += int(mask.any(1).sum())
        acts = {a: np.int64(rng.integers(20)) for a in env.agents}
        obs, _, _, _, infos = env.step(acts)
    assert decided > 20


def test_a_run_trains_on_decisions_and_the_loader_acts_with_its_actor(tmp_path: Path, run) -> None:  # type: ignore[no-untyped-def]
    batch = run.collect()
    t_, k_, n_ = batch["reward"].shape
    assert (t_, k_, n_) == (10, 2, 8) and batch["obs"].shape == (11, 2, 8, run.obs_size)
    decides = batch["mask"].any(-1)
    assert 0 < decides.sum() < decides.size  # a few agents decide per step
    # every sampled action of a decision is valid; the others are 0 with no log-probability
    chosen = np.take_along_axis(batch["mask"], batch["action"][..., None], -1)[..., 0]
    assert chosen[decides].all() and not batch["action"][~decides].any() and not batch["log_prob"][~decides].any()
    for e in run.envs:
        assert e.seed_used in training_pool(8)
    losses = run.update(batch)
    assert losses["decisions"] == decides.sum() and np.isfinite(losses["loss_objective"])
    path = tmp_path / "m.pt"
    torch.save(run.model(), path)
    env = make_parallel_env(ENV, max_cycles=10, overrides=SCENE)
    policy = MappoPolicy(path, env)
    obs, _ = env.reset(seed=3)
    while env.agents:
        acts = policy.act(obs)
        mask = env.action_masks()
        want = masked_choices(run.actor, obs)
        assert acts == want
        for a, v in acts.items():
            i = env.agent_index[a]
            assert isinstance(v, np.integer) and (mask[i, v] == 1 or not mask[i].any())
        obs, *_ = env.step(acts)
    # the actor's kind and the env's action space must match, both ways
    coop = make_parallel_env("cv2x/Cooperative-v0", max_cycles=10, overrides=SCENE)
    with pytest.raises(ValueError, match=r"Discrete\(20\)"):
        MappoPolicy(path, coop)
    gauss = build_mappo(dataclasses.replace(TINY, env_id="cv2x/Cooperative-v0", mappo=MappoSettings()), 0)
    torch.save(gauss.model(), tmp_path / "g.pt")
    with pytest.raises(ValueError, match="Box actions"):
        MappoPolicy(tmp_path / "g.pt", make_parallel_env(ENV, max_cycles=10, overrides=["vehicles.n_vehicles=8"]))


def test_same_seed_same_learning_curve_and_weights_and_resume(tmp_path: Path) -> None:
    def curve(folder: Path) -> list[str]:  # eval.csv without the CPU seconds
        lines = (folder / "eval.csv").read_text().splitlines()
        return [line.rsplit(",", 1)[0] for line in lines]

    it = 2 * 10 * 8
    a = train_mappo(TINY, 3 * it, 5, tmp_path / "a", progress=False)
    b = train_mappo(TINY, 3 * it, 5, tmp_path / "b", progress=False)
    c = train_mappo(TINY, 3 * it, 6, tmp_path / "c", progress=False)
    assert curve(tmp_path / "a")[0].endswith(
        "farthest_mean_utility_gain,loss_objective,loss_critic,loss_entropy,decisions"
    )
    assert a["parameters_digest"] == b["parameters_digest"] != c["parameters_digest"]
    assert curve(tmp_path / "a") == curve(tmp_path / "b") != curve(tmp_path / "c")
    # resume: 2 iterations, then on to 3: the same parameters and curve as the run trained at once
    train_mappo(TINY, 2 * it, 5, tmp_path / "r", progress=False)
    r = train_mappo(TINY, 3 * it, 5, tmp_path / "r", progress=False, resume=True)
    assert r["parameters_digest"] == a["parameters_digest"] and curve(tmp_path / "r") == curve(tmp_path / "a")
    saved = json.loads((tmp_path / "a" / "train_config.json").read_text())
    assert saved["mappo"]["critic"] == "observation" and load_mappo_config(tmp_path / "a" / "train_config.json") == TINY
    assert trained_env_options(tmp_path / "a" / "model.pt") == (ENV, {"max_cycles": 10})
    assert isinstance(
        make_policy(f"ppo:{tmp_path / 'a' / 'model.pt'}", make_parallel_env(ENV, max_cycles=10, overrides=SCENE)),
        MappoPolicy,
    )


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("mappo:\n  encoder: deepsets\n", "encoders there: mlp, candidates, candidates-attention"),
        ("env:\n  reward: difference\n", "individual, team, mixed"),
        ("env:\n  movers: [0]\n", "movers"),
        ("mappo:\n  critic: values\n", "state, observation"),
    ],
)
def test_bad_masked_configs_are_refused(tmp_path: Path, text: str, match: str) -> None:
    f = tmp_path / "c.yaml"
    f.write_text(f"algo: mappo\nenv_id: {ENV}\n{text}")
    with pytest.raises(TrainError, match=match):
        load_mappo_config(f)
    f.write_text("algo: mappo\nmappo:\n  critic: observation\n")  # Cooperative-v0 keeps the critic on state()
    with pytest.raises(TrainError, match="critic: observation is for cv2x/Resource-v0"):
        load_mappo_config(f)
    f.write_text("algo: mappo\nmappo:\n  encoder: candidates\n")
    with pytest.raises(TrainError, match="encoders there: mlp, deepsets, attention"):
        load_mappo_config(f)


def test_the_dithered_choice_is_a_function_of_the_row_and_stays_in_the_mask(run) -> None:  # type: ignore[no-untyped-def]
    """dither > 0: the argmax over the valid entries of the logits plus the observation's own Gumbel noise; the same
    row gives the same choice alone or stacked with others; another row, other noise."""
    from cv2x_marl.policies.mappo_nets import observation_gumbel

    spec = run.actor.spec()
    actor = MaskedActor(**{**spec, "dither": 1.0})
    actor.load_state_dict(run.actor.state_dict())
    rng = np.random.default_rng(2)
    rows = 64
    mask = _masks(rng, rows, run.n_actions)
    obs = _with_masks(actor, rng.normal(size=(rows, run.obs_size)).astype(np.float32), mask, np.ones(rows, bool))
    noise = np.stack([observation_gumbel(o, run.n_actions) for o in obs])
    assert np.array_equal(noise[0], observation_gumbel(obs[0].copy(), run.n_actions))
    assert not np.array_equal(noise[0], noise[1]) and abs(noise.mean() - 0.5772) < 0.1  # Gumbel's mean: Euler's gamma
    with torch.no_grad():
        x = torch.from_numpy(obs)
        logits = actor(x).double().numpy()
        stacked = actor.deterministic(x).numpy()
        alone = np.array([int(actor.deterministic(x[i : i + 1])[0]) for i in range(rows)])
    np.testing.assert_array_equal(stacked, alone)
    np.testing.assert_array_equal(stacked, np.where(mask, logits + noise, -np.inf).argmax(1))
    assert mask[np.arange(rows), stacked].all()
    with pytest.raises(ValueError, match="dither"):
        MaskedActor(**{**spec, "dither": -1.0})


def test_quick_training_beats_random_and_lowest_rssi(tmp_path: Path) -> None:
    """8 iterations of 4 copies x 50 steps (about 5 CPU-s), scored on 4 training-list episodes outside the pool."""
    from cv2x_marl.experiments.evaluate import evaluate

    cfg = MappoConfig(
        env_id=ENV,
        copies=4,
        env={"max_cycles": 50, "start_pool": 16},
        mappo=MappoSettings(
            n_epochs=4,
            minibatch_steps=25,
            gamma=0.9,
            actor_net=(32,),
            critic_net=(64,),
            encoder="candidates",
            encoder_units=32,
            critic="observation",
            dither=1.0,
        ),
        eval_every=1000,
        eval_episodes=1,
    )
    train_mappo(cfg, 8 * 4 * 50 * 21, 0, tmp_path / "r", progress=False)
    seeds = [int(s) for s in TRAIN_SEEDS[300:304]]
    kw = {"max_cycles": 50}
    got = {
        name: evaluate(None if name.startswith("ppo:") else ENV, name, 0, 0, None, kw, progress=False, seeds=seeds)
        for name in (f"ppo:{tmp_path / 'r' / 'model.pt'}", "random", "lowest-rssi")
    }
    learned, rnd, low = got.values()
    assert learned["env"] == ENV and learned["gains_of"] == rnd["gains_of"]
    # measured (team gains against sps on these 4 episodes): learned +12.3 % utility / +5.0 % PRR (training seeds
    # 1-3: +9.9 %, +12.2 %, +9.5 %), random -2.1 % / -1.3 %, lowest-rssi -44.2 % / -18.9 %
    assert learned["mean_utility_gain"] > rnd["mean_utility_gain"] + 0.06
    assert learned["mean_prr_gain"] > rnd["mean_prr_gain"] + 0.02
    assert learned["mean_utility_gain"] > low["mean_utility_gain"] + 0.3
    assert learned["mean_return"] > rnd["mean_return"] > low["mean_return"]
