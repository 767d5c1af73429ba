"""The SB3 adapter's seeding and truncation semantics, PPO reproducibility, save/load, resume, errors."""

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from cv2x_marl.env import parallel_env
from cv2x_marl.env.registry import make_parallel_env
from cv2x_marl.experiments.evaluate import evaluate
from cv2x_marl.policies.ppo import PpoPolicy
from cv2x_marl.rl.errors import TrainError
from cv2x_marl.rl.sb3_vec_env import AgentsVecEnv
from cv2x_marl.rl.train import PpoConfig, TrainConfig, latest_checkpoint, load_train_config, parameters_digest, train
from cv2x_marl.runs import RunFolderError

FAST_ENV = {"max_cycles": 5, "normalise_reward": True, "overrides": ["sim.warmup_subframes=200"]}
TINY = TrainConfig(
    env_id="cv2x/SingleMover-v0",
    copies=2,
    env={**FAST_ENV, "max_cycles": 10},
    ppo=PpoConfig(n_steps=16, batch_size=32, n_epochs=2, net_arch=(16, 16)),
    checkpoint_every=64,
    eval_every=10_000,
    eval_episodes=2,
)


def _vec(copies: int = 2, movers: list[int] | None = None) -> AgentsVecEnv:
    return AgentsVecEnv(lambda: parallel_env(movers=movers, **FAST_ENV), copies)


def test_adapter_seeding_is_reproducible_across_auto_resets() -> None:
    def rollout(seed: int) -> list[np.ndarray]:
        v = _vec()
        v.seed(seed)
        trace = [v.reset()]
        rng = np.random.default_rng(0)
        for _ in range(12):  # crosses two auto-resets (max_cycles = 5)
            obs, rew, done, _ = v.step(rng.uniform(-1, 1, (v.num_envs, 2)).astype(np.float32))
            trace += [obs, rew, done.astype(float)]
        return trace

    a, b, c = rollout(3), rollout(3), rollout(4)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x, y)
    assert not np.array_equal(a[0], c[0])


def test_adapter_copies_get_distinct_seeds_and_layout() -> None:
    v = _vec(copies=3, movers=[0, 5])
    assert v.num_envs == 6 and v.m == 2
    v.seed(10)
    obs = v.reset()
    assert [e.seed_used for e in v.envs] != [v.envs[0].seed_used] * 3
    np.testing.assert_array_equal(obs[2], v.envs[1].observations()["vehicle_0"])
    np.testing.assert_array_equal(obs[3], v.envs[1].observations()["vehicle_5"])


def test_adapter_truncation_and_terminal_observation() -> None:
    v = _vec()
    v.seed(1)
    v.reset()
    for t in range(5):
        obs, _, done, infos = v.step(np.zeros((v.num_envs, 2), np.float32))
        assert done.all() == (t == 4) and done.any() == (t == 4)
    assert all(info["TimeLimit.truncated"] for info in infos)
    term = np.stack([info["terminal_observation"] for info in infos])
    assert np.allclose(term[:, -1], 1.0)  # last feature: elapsed share of the episode = 1 at the end
    assert np.allclose(obs[:, -1], 0.0)  # the returned observation starts the next episode
    assert not np.array_equal(term, obs)


def test_adapter_one_mover_path_is_bit_identical_to_the_full_step() -> None:
    """Three routes, one result: all copies in one compiled call (MoverBatch), one step_mover per
    copy, and the full N-vehicle step."""
    batched = _vec(movers=[0])
    per_copy = AgentsVecEnv(lambda: parallel_env(movers=[0], **FAST_ENV), 2, batched=False)
    full = AgentsVecEnv(lambda: parallel_env(movers=[0], **FAST_ENV), 2, batched=False)
    full.fast = False  # every step through MobilityEnv.step
    assert batched.fast and batched.batch is not None and per_copy.fast and per_copy.batch is None
    for v in (batched, per_copy, full):
        v.seed(2)
    first = batched.reset()
    np.testing.assert_array_equal(first, per_copy.reset())
    np.testing.assert_array_equal(first, full.reset())
    rng = np.random.default_rng(3)
    for _ in range(12):  # two auto-resets (max_cycles = 5)
        act = rng.uniform(-1.3, 1.3, (2, 2)).astype(np.float32)
        a = batched.step(act)
        for b in (per_copy.step(act), full.step(act)):
            for x, y in zip(a[:3], b[:3], strict=True):
                np.testing.assert_array_equal(x, y)
                assert x.dtype == y.dtype
            for ia, ib in zip(a[3], b[3], strict=True):
                assert ia.keys() == ib.keys()
                for key in ia:
                    np.testing.assert_array_equal(ia[key], ib[key])
    # the copies' own objects see where the batch moved them (get_attr / env_method write it back)
    np.testing.assert_array_equal(batched.get_attr("positions_m"), full.get_attr("positions_m"))
    np.testing.assert_array_equal(batched.env_method("state"), full.env_method("state"))


def test_ppo_seed_gives_identical_parameters(tmp_path: Path) -> None:
    from stable_baselines3 import PPO

    digests = []
    for k in range(2):
        env = AgentsVecEnv(lambda: make_parallel_env(TINY.env_id, **TINY.env), 2)
        model = PPO(
            "MlpPolicy",
            env,
            n_steps=16,
            batch_size=32,
            n_epochs=2,
            seed=7,
            device="cpu",
            policy_kwargs={"net_arch": [16, 16]},
        )
        model.learn(64)
        digests.append(parameters_digest(model))
        model.save(tmp_path / f"m{k}.zip")
    assert digests[0] == digests[1]
    loaded = PPO.load(tmp_path / "m0.zip", device="cpu")
    assert parameters_digest(loaded) == digests[0]
    obs = np.random.default_rng(0).uniform(-1, 1, (5, *loaded.observation_space.shape)).astype(np.float32)
    np.testing.assert_array_equal(model.predict(obs, deterministic=True)[0], loaded.predict(obs, deterministic=True)[0])


def test_a_run_trains_again_from_its_train_config(tmp_path: Path) -> None:
    """`train --config RUN/train_config.json` takes the run's seed and length from the file (flags
    still win), so a shipped run can be retrained as it was: same parameters, bit for bit."""
    import json

    from stable_baselines3 import PPO

    from cv2x_marl.cli import main

    cfg_file = tmp_path / "tiny.json"
    cfg_file.write_text(json.dumps({**TINY.to_dict(), "seed": 5, "timesteps": 64}))
    assert main(["train", "--config", str(cfg_file), "--out", str(tmp_path / "a"), "--quiet"]) == 0
    first = json.loads((tmp_path / "a" / "train_config.json").read_text())
    assert first["seed"] == 5 and first["timesteps"] == 64
    again = ["train", "--config", str(tmp_path / "a" / "train_config.json"), "--out", str(tmp_path / "b"), "--quiet"]
    assert main(again) == 0
    digest = [parameters_digest(PPO.load(tmp_path / run / "model.zip", device="cpu")) for run in ("a", "b")]
    assert digest[0] == digest[1]
    other = ["train", "--config", str(cfg_file), "--seed", "6", "--timesteps", "32", "--out", str(tmp_path / "c")]
    assert main([*other, "--quiet"]) == 0
    third = json.loads((tmp_path / "c" / "train_config.json").read_text())
    assert third["seed"] == 6 and third["timesteps"] == 32
    cfg_file.write_text(json.dumps({**TINY.to_dict(), "seed": -1}))
    assert main(["train", "--config", str(cfg_file), "--out", str(tmp_path / "d"), "--quiet"]) == 2


def test_resume_continues_the_step_count(tmp_path: Path) -> None:
    run = tmp_path / "run"
    first = train(TINY, 128, seed=1, run_dir=run, progress=False)
    assert first["timesteps"] == 128
    ckpt = latest_checkpoint(run)
    assert ckpt is not None and ckpt.name == "ppo_128_steps.zip"
    with pytest.raises(RunFolderError, match=r"not empty.*--overwrite"):
        train(TINY, 256, seed=1, run_dir=run, progress=False)
    second = train(TINY, 256, seed=1, run_dir=run, resume=True, progress=False)
    assert second["resumed_from"] == 128 and second["timesteps"] == 256
    assert latest_checkpoint(run).name == "ppo_256_steps.zip"  # type: ignore[union-attr]
    with pytest.raises(TrainError, match="differs"):
        train(dataclasses.replace(TINY, copies=3), 512, seed=1, run_dir=run, resume=True, progress=False)


def test_short_training_beats_random(tmp_path: Path) -> None:
    cfg = dataclasses.replace(
        TINY,
        copies=4,
        env={"max_cycles": 20, "max_step_m": 10.0, "normalise_reward": True},
        ppo=PpoConfig(n_steps=32, batch_size=128, n_epochs=5, net_arch=(64, 64)),
        checkpoint_every=10**9,
    )
    rec = train(cfg, 8000, seed=0, run_dir=tmp_path / "r", progress=False)
    kw = {"max_cycles": 20, "max_step_m": 10.0, "normalise_reward": True}
    ppo = evaluate(cfg.env_id, PpoPolicy(tmp_path / "r" / "model.zip"), 16, 123, None, kw, progress=False)
    rnd = evaluate(cfg.env_id, "random", 16, 123, None, kw, progress=False)
    assert rec["timesteps"] >= 8000
    # measured: PPO +4.8 % utility gain, random -2.8 % on these 16 held-out episodes (seed 0)
    assert ppo["mean_return"] > rnd["mean_return"]
    assert ppo["mean_utility_gain"] > rnd["mean_utility_gain"] + 0.04


def test_bad_model_files_and_configs(tmp_path: Path) -> None:
    bad = tmp_path / "bad.zip"
    bad.write_bytes(b"not a zip")
    env = make_parallel_env("cv2x/SingleMover-v0", **FAST_ENV)
    with pytest.raises(ValueError, match=r"bad\.zip"):
        PpoPolicy(bad, env)
    with pytest.raises(ValueError, match="does not exist"):
        PpoPolicy(tmp_path / "none.zip", env)
    run = tmp_path / "run"
    train(TINY, 32, seed=0, run_dir=run, progress=False)
    other = make_parallel_env("cv2x/SingleMover-v0", n_neighbours=5, **FAST_ENV)
    with pytest.raises(ValueError, match="expects observations of shape"):
        PpoPolicy(run / "model.zip", other)
    f = tmp_path / "c.yaml"
    f.write_text("ppo:\n  learning_rat: 0.1\n")
    with pytest.raises(TrainError, match="learning_rat"):
        load_train_config(f)
    f.write_text("copiez: 3\n")
    with pytest.raises(TrainError, match="copiez"):
        load_train_config(f)


@pytest.mark.parametrize(
    ("text", "name"),
    [
        ("ppo:\n  gamma: 5\n", "ppo.gamma"),
        ("ppo:\n  n_steps: 0\n", "ppo.n_steps"),
        ("ppo:\n  batch_size: 1.5\n", "ppo.batch_size"),
        ("ppo:\n  learning_rate: .nan\n", "ppo.learning_rate"),
        ("ppo:\n  learning_rate: fast\n", "ppo.learning_rate"),
        ("ppo:\n  net_arch: [64, 0]\n", "ppo.net_arch"),
        ("ppo:\n  clip_range: true\n", "ppo.clip_range"),
        ("checkpoint_every: 1.5\n", "train.checkpoint_every"),
        ("eval_seed: -1\n", "train.eval_seed"),
        ("env: 3\n", "train.env"),
        ("ppo: [1]\n", "train.ppo"),
    ],
)
def test_training_config_values_are_type_and_range_checked(tmp_path: Path, text: str, name: str) -> None:
    f = tmp_path / "c.yaml"
    f.write_text(text)
    with pytest.raises(TrainError, match=name.replace(".", r"\.")):
        load_train_config(f)


def test_scientific_notation_is_a_number_in_training_configs(tmp_path: Path) -> None:
    f = tmp_path / "c.yaml"
    f.write_text("ppo:\n  learning_rate: 3e-4\n  ent_coef: 1e-3\n")  # strings under YAML 1.1
    cfg = load_train_config(f)
    assert cfg.ppo.learning_rate == 3e-4 and cfg.ppo.ent_coef == 1e-3
    assert isinstance(cfg.ppo.learning_rate, float)


def test_adapter_draws_from_the_protocol_training_seeds_with_the_env_option_start_pool() -> None:
    """With the env option ``start_pool=P`` every episode of every copy starts from one of the first P training
    seeds of the protocol (``seeds.training_pool``), drawn reproducibly from PPO's seed; the adapter's own pool
    (seeds derived from PPO's seed) is refused beside it."""
    from cv2x_marl.env.seeds import HELDOUT_SEEDS, training_pool

    def episode_seeds(seed: int) -> list[int]:
        v = AgentsVecEnv(lambda: parallel_env(movers=[0], **{**FAST_ENV, "start_pool": 3}), 2)
        v.seed(seed)
        v.reset()
        used = [e.seed_used for e in v.envs]
        for _ in range(3):  # max_cycles = 5: three auto-resets of each copy
            for _ in range(5):
                v.step(np.zeros((v.num_envs, 2), dtype=np.float32))
            used += [e.seed_used for e in v.envs]
        return used

    a, b = episode_seeds(4), episode_seeds(4)
    assert a == b and set(a) <= set(training_pool(3)) and len(set(a)) > 1
    assert not set(a) & {s for seeds in HELDOUT_SEEDS.values() for s in seeds}
    with pytest.raises(ValueError, match="exclude each other"):
        AgentsVecEnv(lambda: parallel_env(**{**FAST_ENV, "start_pool": 3}), 2, start_pool=4)
