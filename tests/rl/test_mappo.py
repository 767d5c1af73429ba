"""MAPPO on TorchRL (cv2x_marl.rl.mappo): the critic reads state(), the actor observations; seeding; the loader;
quick training beats random on Cooperative-v0's team utility."""

import json
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("torchrl")

import torch
from tensordict import TensorDict

from cv2x_marl.cli import main
from cv2x_marl.env.registry import make_parallel_env
from cv2x_marl.env.seeds import training_pool
from cv2x_marl.experiments.evaluate import evaluate, trained_env_options
from cv2x_marl.policies.base import act_rows
from cv2x_marl.policies.mappo import MappoPolicy
from cv2x_marl.policies.registry import make_policy
from cv2x_marl.rl.errors import TrainError
from cv2x_marl.rl.mappo import GROUP, build_mappo, train_mappo
from cv2x_marl.rl.mappo_config import MappoConfig, MappoSettings, config_algo, load_mappo_config

#: a small scene: 8 vehicles, a short warm-up, 10-step episodes
SCENE = ["vehicles.n_vehicles=8", "sim.warmup_subframes=200"]
TINY = MappoConfig(
    copies=2,
    env={"max_cycles": 10, "max_step_m": 10.0, "start_pool": 8, "overrides": SCENE},
    mappo=MappoSettings(n_epochs=2, minibatch_steps=5, actor_net=(16,), critic_net=(16,), encoder_units=8),
    eval_every=1,
    eval_episodes=2,
)


def test_critic_reads_the_state_and_the_actor_only_observations() -> None:
    run = build_mappo(TINY, seed=0)
    env = run.envs[0]
    n, size = len(env.possible_agents), env.state_space.shape[0]
    assert size == 8 * 6 + 2 * 8 * 8  # state(): 6 entries per vehicle and the N x N RSRP reports and ages
    assert run.critic.v[0].in_features == size and run.state_size == size
    assert run.actor.obs_size == env.observation_space(env.possible_agents[0]).shape[0]
    batch = run.collect()
    assert batch["state"].shape == (11, 2, size) and batch["obs"].shape == (10, 2, n, run.obs_size)
    for k, e in enumerate(run.envs):  # the last state is the env's state(); every episode from the training pool
        np.testing.assert_array_equal(batch["state"][-1, k], e.state())
        assert e.seed_used in training_pool(8)
    # through TorchRL's modules: the value depends on "state" alone, the log-probability on the observations alone
    rng = np.random.default_rng(0)
    obs = torch.from_numpy(batch["obs"][0])  # [K, N, O]
    act = torch.from_numpy(batch["action"][0])
    state = torch.from_numpy(batch["state"][0])

    def heads(o: torch.Tensor, s: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        td = TensorDict({GROUP: TensorDict({"observation": o, "action": act}, [2, n]), "state": s}, [2])
        with torch.no_grad():
            value = run.loss.critic_network(td.clone())[GROUP, "state_value"]
            logp = run.loss.actor_network.get_dist(td.clone()).log_prob(act)
        return value, logp

    v0, l0 = heads(obs, state)
    assert v0.shape == (2, n, 1) and l0.shape == (2, n)
    assert torch.equal(v0, v0[:, :1].expand_as(v0))  # one value per step, every agent's
    other_obs = obs + torch.from_numpy(rng.normal(size=obs.shape).astype(np.float32))
    other_state = state + torch.from_numpy(rng.normal(size=state.shape).astype(np.float32))
    v1, l1 = heads(other_obs, state)
    v2, l2 = heads(obs, other_state)
    assert torch.equal(v1, v0) and not torch.equal(l1, l0)
    assert torch.equal(l2, l0) and not torch.equal(v2, v0)


def test_same_seed_same_learning_curve_and_parameters(tmp_path: Path) -> None:
    before = torch.random.get_rng_state()
    a = train_mappo(TINY, 2 * 2 * 10 * 8, 3, tmp_path / "a", progress=False)  # two iterations
    assert torch.equal(torch.random.get_rng_state(), before)  # the global torch state is left alone
    cfg_file = tmp_path / "tiny.json"
    cfg_file.write_text(json.dumps(TINY.to_dict()))
    # the CLI route (algo: mappo in the file) with the same seed: the same parameters and the same curve
    argv = ["train", "--config", str(cfg_file), "--timesteps", "320", "--seed", "3", "--quiet"]
    assert main([*argv, "--out", str(tmp_path / "b")]) == 0
    b = json.loads((tmp_path / "b" / "record.json").read_text())
    c = train_mappo(TINY, 320, 4, tmp_path / "c", progress=False)
    assert a["iterations"] == 2 and a["timesteps"] == 320
    assert a["parameters_digest"] == b["parameters_digest"] != c["parameters_digest"]
    assert (tmp_path / "a" / "eval.csv").read_text() == (tmp_path / "b" / "eval.csv").read_text()
    assert (tmp_path / "a" / "eval.csv").read_text() != (tmp_path / "c" / "eval.csv").read_text()
    saved = json.loads((tmp_path / "a" / "train_config.json").read_text())
    assert (saved["algo"], saved["seed"], saved["timesteps"]) == ("mappo", 3, 320)
    assert load_mappo_config(tmp_path / "a" / "train_config.json") == TINY  # a run's config trains it again
    # the loader: ppo:PATH with a .pt file is the MAPPO actor, its env id and options from train_config.json
    path = tmp_path / "a" / "model.pt"
    assert trained_env_options(path) == ("cv2x/Cooperative-v0", {"max_cycles": 10, "max_step_m": 10.0})
    env = make_parallel_env("cv2x/Cooperative-v0", max_cycles=10, max_step_m=10.0, overrides=SCENE)
    policy = make_policy(f"ppo:{path}", env)
    assert isinstance(policy, MappoPolicy)
    obs, _ = env.reset(seed=5)
    run = build_mappo(TINY, 3)  # untrained, same seed: its initial actor differs from the trained one
    stacked = np.stack([obs[x] for x in env.possible_agents])
    loaded = np.stack(list(policy.act(obs).values()))
    data = torch.load(path, weights_only=True)
    run.actor.load_state_dict(data["actor_state"])
    np.testing.assert_array_equal(loaded, act_rows(run.act_fn(), stacked))  # each agent's row alone
    assert np.all(np.abs(loaded) <= 1.0)


def test_loader_and_config_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    env = make_parallel_env("cv2x/Cooperative-v0", max_cycles=10, overrides=SCENE)
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a torch file")
    with pytest.raises(ValueError, match=r"bad\.pt"):
        MappoPolicy(bad, env)
    with pytest.raises(ValueError, match="does not exist"):
        MappoPolicy(tmp_path / "none.pt", env)
    other = tmp_path / "other.pt"
    torch.save({"format": "something else"}, other)
    with pytest.raises(ValueError, match="not a MAPPO model"):
        MappoPolicy(other, env)
    run = build_mappo(TINY, 0)
    torch.save(run.model(), tmp_path / "m.pt")
    wide = make_parallel_env("cv2x/Cooperative-v0", max_cycles=10, overrides=["vehicles.n_vehicles=12", *SCENE[1:]])
    MappoPolicy(tmp_path / "m.pt", env)
    with pytest.raises(ValueError, match="expects observations of shape"):
        MappoPolicy(tmp_path / "m.pt", wide)
    f = tmp_path / "c.yaml"
    for text, match in [
        ("algo: mappo\nmappo:\n  learning_rat: 0.1\n", "learning_rat"),
        ("algo: mappo\ncopiez: 3\n", "copiez"),
        ("algo: mappo\nenv_id: cv2x/Mobility-v3\n", "MAPPO trains on cv2x/Cooperative-v0"),
        ("algo: mappo\nenv:\n  start_pool: 0\n", "start_pool"),
        ("algo: mappo\nenv:\n  reward: individual\n", "reward"),
        ("algo: mappo\nmappo:\n  encoder: lstm\n", "mlp, deepsets, attention"),
        ("algo: mappo\nmappo:\n  gamma: 1.5\n", r"mappo\.gamma"),
    ]:
        f.write_text(text)
        with pytest.raises(TrainError, match=match):
            load_mappo_config(f)
    f.write_text("algo: sac\n")
    with pytest.raises(TrainError, match="algorithms: ppo, mappo"):
        config_algo(f, None)
    f.write_text("algo: mappo\n")
    assert config_algo(f, None) == "mappo" and config_algo(None, None) == "ppo"
    with pytest.raises(TrainError, match="differ"):
        config_algo(f, "ppo")
    with pytest.raises(TrainError, match="start_pool"):
        train_mappo(MappoConfig(env={"start_pool": -1}), 10, 0, tmp_path / "never", progress=False)
    out = ["--out", str(tmp_path / "never")]
    assert main(["train", "--config", str(f), "--resume", *out]) == 2  # refused: nothing to resume there
    assert main(["train", "--config", str(f), "--algo", "ppo", *out]) == 2  # the file says mappo
    assert main(["train", "--algo", "sac", *out]) == 2
    assert not (tmp_path / "never").exists()
    err = capsys.readouterr().err
    assert "has no train_config.json (nothing to resume)" in err and "differ" in err and "algorithms: ppo, mappo" in err


def test_quick_training_beats_random_on_the_team_utility(tmp_path: Path) -> None:
    cfg = MappoConfig(
        copies=4,
        env={"max_cycles": 20, "max_step_m": 10.0, "start_pool": 32, "overrides": SCENE},
        mappo=MappoSettings(n_epochs=4, minibatch_steps=20, actor_net=(64, 64), critic_net=(64, 64), encoder_units=32),
        eval_every=1000,
        eval_episodes=4,
    )
    train_mappo(cfg, 25 * 4 * 20 * 8, 0, tmp_path / "r", progress=False)  # 25 iterations
    kw = {"max_cycles": 20, "max_step_m": 10.0, "overrides": SCENE}
    seeds = [101, 102, 103, 104, 105, 106]
    mappo = evaluate(None, f"ppo:{tmp_path / 'r' / 'model.pt'}", 0, 0, None, kw, progress=False, seeds=seeds)
    rnd = evaluate("cv2x/Cooperative-v0", "random", 0, 0, None, kw, progress=False, seeds=seeds)
    assert mappo["env"] == "cv2x/Cooperative-v0" and mappo["gains_of"] == rnd["gains_of"]
    # measured: MAPPO +7.9 % team utility gain, random -7.1 % on these 6 episodes (seeds 1 and 2 of training:
    # +5.1 %, +12.3 %; gbmu +23.6 %: 25 short iterations learn to move, not to beat the scripts)
    assert mappo["mean_utility_gain"] > rnd["mean_utility_gain"] + 0.10
    assert mappo["mean_return"] > rnd["mean_return"]


#: TINY on cv2x/Cooperative-v1: the vehicles sample their moves at their turns
TINY_V1 = MappoConfig(**{**TINY.__dict__, "env_id": "cv2x/Cooperative-v1"})


def test_on_cooperative_v1_each_vehicle_samples_at_its_turn() -> None:
    """Collection in turns: every stored observation is the vehicle's observation at its turn given the actions the
    earlier subframes sampled (``decide_in_turns`` replayed with them), and every stored log-probability is the
    actor's for that action at that observation."""
    from cv2x_marl.env.turns import decide_in_turns, subframes

    run = build_mappo(TINY_V1, seed=0)
    assert run.turns and not build_mappo(TINY, seed=0).turns
    env = run.envs[0]
    env.reset(seed=run.pool[0])
    with torch.no_grad():
        obs, act, logp = run._sample_in_turns(env)
    assert len(np.unique(subframes(env))) > 1  # several turns in the period
    replay, turn_obs = decide_in_turns(env, lambda rows, o: act[rows])
    np.testing.assert_array_equal(obs, turn_obs)
    np.testing.assert_array_equal(replay, act.astype(np.float64))
    first = env.observations()
    later = [i for i, a in enumerate(run.agents) if not np.array_equal(obs[i], first[a])]
    assert later  # some vehicle saw a move announced before its turn
    td = TensorDict({GROUP: TensorDict({"observation": torch.from_numpy(obs)}, [run.n_agents])}, [])
    with torch.no_grad():
        dist = run.policy.get_dist(td)
        expect = dist.log_prob(torch.from_numpy(act))
    np.testing.assert_allclose(expect.numpy(), logp, rtol=0, atol=2e-4)


def test_on_cooperative_v1_training_evaluates_in_turns(tmp_path: Path) -> None:
    """A run on Cooperative-v1 is reproducible, and its saved model, loaded with ``ppo:PATH``, acts at its turns:
    the run's last evaluation equals ``evaluate`` of the file on the same episodes."""
    from cv2x_marl.policies.sequential import InTurns

    a = train_mappo(TINY_V1, 2 * 2 * 10 * 8, 3, tmp_path / "a", progress=False)
    b = train_mappo(TINY_V1, 2 * 2 * 10 * 8, 3, tmp_path / "b", progress=False)
    assert (tmp_path / "a" / "eval.csv").read_text() == (tmp_path / "b" / "eval.csv").read_text()
    assert a["iterations"] == b["iterations"] == 2 and a["parameters_digest"] == b["parameters_digest"]
    par = make_parallel_env("cv2x/Cooperative-v1", max_cycles=10, max_step_m=10.0, overrides=SCENE)
    assert isinstance(make_policy(f"ppo:{tmp_path / 'a' / 'model.pt'}", par), InTurns)
    rows = (tmp_path / "a" / "eval.csv").read_text().splitlines()
    last = dict(zip(rows[0].split(","), rows[-1].split(","), strict=True))
    res = evaluate(
        None, f"ppo:{tmp_path / 'a' / 'model.pt'}", TINY.eval_episodes, TINY.eval_seed, None,
        {"max_cycles": 10, "max_step_m": 10.0, "overrides": SCENE}, progress=False,
    )  # fmt: skip
    assert res["env"] == "cv2x/Cooperative-v1"
    assert float(last["mappo_mean_utility_gain"]) == pytest.approx(res["mean_utility_gain"], abs=1e-12)
