"""Recurrent PPO (``ppo.recurrent: true``: sb3-contrib's RecurrentPPO): training, the LSTM state an evaluated
policy carries over an episode, reproducibility, resume and the config's checks."""

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from cv2x_marl.env.registry import make_parallel_env
from cv2x_marl.experiments.evaluate import evaluate
from cv2x_marl.policies.ppo import PpoPolicy
from cv2x_marl.rl.errors import TrainError
from cv2x_marl.rl.train import PpoConfig, TrainConfig, load_train_config, parameters_digest, train

FAST_ENV = {"max_cycles": 5, "normalise_reward": True, "overrides": ["sim.warmup_subframes=200"]}
TINY = TrainConfig(
    env_id="cv2x/SingleMover-v0",
    copies=2,
    env=FAST_ENV,
    ppo=PpoConfig(n_steps=16, batch_size=32, n_epochs=2, net_arch=(16, 16), recurrent=True, lstm_units=8),
    checkpoint_every=32,
    eval_every=10_000,
    eval_episodes=2,
)


def test_same_seed_same_parameters_and_resume_keeps_the_recurrent_model(tmp_path: Path) -> None:
    from sb3_contrib import RecurrentPPO

    first = train(TINY, 64, seed=3, run_dir=tmp_path / "a", progress=False)
    train(TINY, 64, seed=3, run_dir=tmp_path / "b", progress=False)
    digests = [parameters_digest(RecurrentPPO.load(tmp_path / r / "model.zip", device="cpu")) for r in ("a", "b")]
    assert first["timesteps"] == 64 and digests[0] == digests[1]
    again = train(TINY, 128, seed=3, run_dir=tmp_path / "a", resume=True, progress=False)
    assert again["resumed_from"] == 64 and again["timesteps"] == 128
    assert isinstance(PpoPolicy(tmp_path / "a" / "model.zip").model, RecurrentPPO)
    saved = load_train_config(tmp_path / "a" / "train_config.json")
    assert saved.ppo.recurrent is True and saved.ppo.lstm_units == 8


def test_the_policy_carries_one_lstm_state_per_agent_over_an_episode(tmp_path: Path) -> None:
    """PpoPolicy's actions equal RecurrentPPO.predict fed each agent's row alone with that agent's own state
    (a batch of one, the batch-invariance rule), episode_start at the first step; reset() starts from zeros
    again; a plain PPO save stays a plain (stateless) policy."""
    train(TINY, 32, seed=1, run_dir=tmp_path / "r", progress=False)
    policy = PpoPolicy(tmp_path / "r" / "model.zip")
    assert policy.recurrent
    model = policy.model
    env = make_parallel_env("cv2x/Mobility-v0", **{**FAST_ENV, "max_cycles": 4})
    for episode in range(2):
        obs, _ = env.reset(seed=11)
        policy.reset(seed=episode)
        alone = PpoPolicy(tmp_path / "r" / "model.zip")
        states: dict[str, object] = dict.fromkeys(obs)
        first_step = True
        while env.agents:
            acts = policy.act(obs)
            assert len(obs) > 1  # several agents, each its own batch of one
            for a in obs:
                row = obs[a][None]
                want, states[a] = model.predict(
                    row, state=states[a], episode_start=np.array([first_step]), deterministic=True
                )
                np.testing.assert_array_equal(acts[a], np.asarray(want, dtype=np.float32).reshape(2))
            # a policy that sees the first agent alone acts for it as among the others
            first = next(iter(obs))
            np.testing.assert_array_equal(alone.act({first: obs[first]})[first], acts[first])
            if not first_step:  # the memory matters: without its state the same observations act otherwise
                batch = np.stack([obs[a] for a in obs])
                stateless, _ = model.predict(
                    batch, state=None, episode_start=np.ones(len(obs), bool), deterministic=True
                )
                assert not np.array_equal(stateless, np.stack([acts[a] for a in obs]))
            first_step = False
            obs, *_ = env.step(acts)
    plain = dataclasses.replace(TINY, ppo=dataclasses.replace(TINY.ppo, recurrent=False))
    train(plain, 32, seed=1, run_dir=tmp_path / "p", progress=False)
    assert not PpoPolicy(tmp_path / "p" / "model.zip").recurrent


def test_short_recurrent_training_beats_random(tmp_path: Path) -> None:
    kw = {"max_cycles": 20, "max_step_m": 10.0, "normalise_reward": True}
    cfg = TrainConfig(
        env_id="cv2x/SingleMover-v0",
        copies=4,
        env=kw,
        ppo=PpoConfig(n_steps=32, batch_size=128, n_epochs=5, net_arch=(64, 64), recurrent=True, lstm_units=32),
        checkpoint_every=10**9,
        eval_every=10**9,
        eval_episodes=2,
    )
    train(cfg, 8000, seed=0, run_dir=tmp_path / "r", progress=False)
    ppo = evaluate(cfg.env_id, PpoPolicy(tmp_path / "r" / "model.zip"), 16, 123, None, kw, progress=False)
    rnd = evaluate(cfg.env_id, "random", 16, 123, None, kw, progress=False)
    # measured: recurrent PPO +3.9 % utility gain, random -2.8 % on these 16 episodes (seed 0)
    assert ppo["mean_return"] > rnd["mean_return"]
    assert ppo["mean_utility_gain"] > rnd["mean_utility_gain"] + 0.04


@pytest.mark.parametrize(
    ("key", "value", "message"),
    [("recurrent", "yes", "ppo.recurrent must be true or false"), ("lstm_units", 0, "ppo.lstm_units must be")],
)
def test_recurrent_settings_are_checked(key: str, value: object, message: str) -> None:
    with pytest.raises(TrainError, match=message):
        PpoConfig(**{key: value})  # type: ignore[arg-type]
