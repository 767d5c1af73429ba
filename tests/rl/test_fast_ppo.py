"""``ppo.backend: torchrl`` (cv2x_marl.rl.fast_ppo): the configuration's checks, one seed -> one learning curve,
the advantages against a numpy GAE of the rollout, the saved model's deterministic actions, the run folder."""

from __future__ import annotations

import csv
import dataclasses
import json

import numpy as np
import pytest

pytest.importorskip("torchrl")
import torch

from cv2x_marl.env.registry import make_parallel_env
from cv2x_marl.policies.registry import make_policy
from cv2x_marl.policies.torch_ppo import TorchPpoPolicy
from cv2x_marl.rl.errors import TrainError
from cv2x_marl.rl.fast_ppo import CURVE_COLUMNS, FastPpo, train_fast
from cv2x_marl.rl.train import train
from cv2x_marl.rl.train_config import PpoConfig, TrainConfig, load_train_config

ENV = {
    "max_cycles": 8,
    "max_step_m": 5.0,
    "normalise_reward": True,
    "start_pool": 4,
    "overrides": ["sim.warmup_subframes=200"],
}
TINY = TrainConfig(
    env_id="cv2x/SingleMover-v3",
    copies=2,
    env=ENV,
    ppo=PpoConfig(
        n_steps=12, batch_size=10, n_epochs=2, net_arch=(16,), encoder="deepsets", encoder_units=8, backend="torchrl"
    ),
    eval_every=48,
    eval_episodes=1,
)


@pytest.fixture(autouse=True)
def _one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def test_backend_values_are_checked_by_name(tmp_path):
    with pytest.raises(TrainError, match=r"ppo.backend must be one of sb3, torchrl, got 'jax'"):
        PpoConfig(backend="jax")
    with pytest.raises(TrainError, match=r"ppo.recurrent: true needs ppo.backend: sb3"):
        PpoConfig(backend="torchrl", recurrent=True)
    with pytest.raises(TrainError, match=r"Cooperative-v0 has not; env ids: .*cv2x/SingleMover-v3"):
        TrainConfig(env_id="cv2x/Cooperative-v0", ppo=PpoConfig(backend="torchrl"))
    with pytest.raises(TrainError, match=r"train.start_pool=16 is not taken by ppo.backend: torchrl.*env.start_pool"):
        dataclasses.replace(TINY, start_pool=16)
    path = tmp_path / "cfg.yaml"
    path.write_text("env_id: cv2x/SingleMover-v3\nppo: {backend: torch}\n")
    with pytest.raises(TrainError, match=r"ppo.backend must be one of sb3, torchrl, got 'torch'"):
        load_train_config(path)
    assert "backend" not in TrainConfig().to_dict()["ppo"]  # the default is left out (older files read the same)
    assert TINY.to_dict()["ppo"]["backend"] == "torchrl"
    with pytest.raises(TrainError, match=r"--resume: ppo\.backend: torchrl writes no checkpoints"):
        train(TINY, 48, 0, tmp_path / "r", resume=True, progress=False)


def _curve(seed: int, iterations: int = 3) -> tuple[list[float], list[dict[str, float]], str]:
    run = FastPpo(TINY, seed)
    try:
        losses = [run.iterate() for _ in range(iterations)]
        return run.returns, losses, run.digest()
    finally:
        run.close()


def test_one_seed_gives_one_learning_curve():
    torch_state, numpy_state = torch.random.get_rng_state(), np.random.get_state()  # noqa: NPY002
    a, b, c = _curve(5), _curve(5), _curve(6)
    # the global generators are left where they were
    assert torch.equal(torch.random.get_rng_state(), torch_state)
    assert np.random.get_state()[1].tolist() == numpy_state[1].tolist()  # noqa: NPY002
    assert len(a[0]) == 2 * (3 * 12 // 8)  # 36 steps per copy: 4 episodes of 8 each
    assert a == b  # returns, losses and parameters, bit for bit
    assert a[2] != c[2] and a[0] != c[0]


def test_advantages_are_gae_of_the_rollout_with_the_time_limit_bootstrapped():
    """A numpy GAE over the collected rollout, every value recomputed by the network: V(s'_t) of the next
    observation (the episode's final one at a time limit), the trace cut where an episode ended."""
    run = FastPpo(TINY, 1)
    try:
        rollout = run.collect()
        flat = run.advantages(rollout.clone())
        gamma, lam = TINY.ppo.gamma, TINY.ppo.gae_lambda
        with torch.no_grad():
            v = run.net.value(rollout["observation"])[..., 0].numpy().astype(np.float64)
            v_next = run.net.value(rollout["next", "observation"])[..., 0].numpy().astype(np.float64)
        r = rollout["next", "reward"][..., 0].numpy().astype(np.float64)
        done = rollout["next", "done"][..., 0].numpy()
        assert done[:, 7].all() and done.sum() == 2  # episodes of 8 steps end at t = 7 in both copies
        # the final observation is kept as the next one, not the next episode's first
        assert not np.array_equal(rollout["next", "observation"][:, 7].numpy(), rollout["observation"][:, 8].numpy())
        adv = np.zeros_like(r)
        last = np.zeros(r.shape[0])
        for t in reversed(range(r.shape[1])):
            delta = r[:, t] + gamma * v_next[:, t] - v[:, t]  # no terminal state: always bootstrapped
            last = delta + gamma * lam * np.where(done[:, t], 0.0, 1.0) * last
            adv[:, t] = last
        np.testing.assert_allclose(flat["advantage"][:, 0].numpy(), adv.reshape(-1), rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(flat["value_target"][:, 0].numpy(), (adv + v).reshape(-1), rtol=1e-5, atol=1e-6)
    finally:
        run.close()


def test_saved_model_acts_with_the_networks_clipped_mean(tmp_path):
    """``ppo:PATH`` of a saved model acts with the trained network's mean, clipped to the Box as SB3's
    ``predict(deterministic=True)``; the action head is scaled up so that some means leave the Box."""
    env = make_parallel_env(TINY.env_id, **ENV)
    run = FastPpo(TINY, 2)
    try:
        run.iterate()
        with torch.no_grad():
            run.net.action_net.weight.mul_(1e3)
            obs = torch.from_numpy(run.obs_buf.reshape(-1, run.obs_size))
            mean = run.net(obs)[0]
        torch.save(run.model(), tmp_path / "model.pt")
    finally:
        run.close()
    assert (mean.abs() > 1).any() and (mean.abs() < 1).any()
    policy = make_policy(f"ppo:{tmp_path / 'model.pt'}", env)
    assert isinstance(policy, TorchPpoPolicy)
    np.testing.assert_array_equal(policy.act_fn(obs.numpy()), mean.clamp(-1, 1).numpy())
    torch.save({"format": "other"}, tmp_path / "other.pt")
    with pytest.raises(ValueError, match=r"has format 'other'; a ppo:PATH .pt file must hold one of"):
        make_policy(f"ppo:{tmp_path / 'other.pt'}", env)


def test_train_writes_the_run_folder(tmp_path):
    rec = train(TINY, 48, 3, tmp_path / "run", progress=False)
    out = tmp_path / "run"
    assert rec["backend"] == "torchrl" and rec["timesteps"] == 48 and rec["iterations"] == 2
    for name in ("model.pt", "train_config.json", "curve.csv", "curve.png", "eval.csv", "record.json", "run.json"):
        assert (out / name).is_file(), name
    saved = json.loads((out / "train_config.json").read_text())
    assert saved["seed"] == 3 and saved["ppo"]["backend"] == "torchrl"
    assert load_train_config(out / "train_config.json") == TINY  # the run's file trains it again
    with (out / "curve.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert tuple(rows[0]) == CURVE_COLUMNS
    assert [int(r["agent_steps"]) for r in rows] == [24, 48]
    cpu = [float(r["cpu_s"]) for r in rows]
    assert 0 < cpu[0] < cpu[1] <= rec["cpu_s"] + 1e-9
    # the same run again: the same parameters and curve of returns
    again = train_fast(TINY, 48, 3, tmp_path / "again", progress=False)
    assert again["parameters_digest"] == rec["parameters_digest"]
    assert again["train_mean_return"] == rec["train_mean_return"]
