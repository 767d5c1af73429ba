"""The permutation-invariant neighbour encoders (``ppo.encoder``): the split of the flat observation against
hand-built observations, invariance to the order of the neighbour blocks, refusals, and a short training run."""

import numpy as np
import pytest
import torch
from gymnasium import spaces

from cv2x_marl.env.observation import (
    FEATURES,
    FEATURES_V3,
    FEATURES_V4,
    OWN,
    OWN_DRIVE,
    OWN_V1,
    OWN_V3,
    OWN_V4,
    ObservationLayout,
)
from cv2x_marl.policies.encoders import NeighbourEncoder, layout_spec, split_indices
from cv2x_marl.policies.ppo import PpoPolicy
from cv2x_marl.rl.errors import TrainError
from cv2x_marl.rl.train import PpoConfig, TrainConfig, build_training, load_train_config


def _layout(k: int, version: int, drive: bool = False, privileged: bool = False) -> ObservationLayout:
    return ObservationLayout(k, 100.0, 450.0, 200.0, version=version, drive=drive, privileged=privileged)


def _encoder(layout: ObservationLayout, pool: str = "deepsets", units: int = 8) -> NeighbourEncoder:
    torch.manual_seed(0)
    return NeighbourEncoder(spaces.Box(-10, 10, (layout.size,), np.float32), layout_spec(layout), pool, units)


def _hand_built(version: int, k: int, drive: bool, privileged: bool = False) -> tuple[np.ndarray, ...]:
    """An observation assembled from its parts as the module docstring of env/observation.py lays them out,
    with distinct values, and the neighbour rows / own entries the encoder must read."""
    rng = np.random.default_rng(7)
    v0 = rng.normal(size=(k, FEATURES))
    own0 = rng.normal(size=OWN)
    drive_own = rng.normal(size=OWN_DRIVE if drive else 0)
    if version == 3:
        extra, own_v = rng.normal(size=(k, FEATURES_V3)), rng.normal(size=OWN_V3)
        flat_extra = extra.ravel()  # neighbour-major: [10k + f]
    elif version == 4:
        extra, own_v = rng.normal(size=(k, FEATURES_V4)), rng.normal(size=OWN_V4)
        flat_extra = extra.ravel()  # neighbour-major: [8k + f]
    elif version in (1, 2):
        extra = rng.normal(size=(k, 1 + int(privileged)))
        flat_extra = extra.T.ravel()  # feature-major: model P of every neighbour, then the true P
        own_v = rng.normal(size=OWN_V1)
    else:
        extra, flat_extra, own_v = np.zeros((k, 0)), np.zeros(0), np.zeros(0)
    obs = np.concatenate((v0.ravel(), own0, flat_extra, own_v, drive_own)).astype(np.float32)
    rows = np.concatenate((v0, extra), axis=1).astype(np.float32)
    own = np.concatenate((own0, own_v, drive_own)).astype(np.float32)
    return obs, rows, own


@pytest.mark.parametrize(
    ("version", "drive", "privileged"),
    [(3, False, False), (0, True, False), (0, False, False), (1, False, True), (4, True, False)],
)
def test_split_equals_independent_slicing_of_a_hand_built_observation(
    version: int, drive: bool, privileged: bool
) -> None:
    k = 3
    layout = _layout(k, version, drive, privileged)
    obs, rows, own = _hand_built(version, k, drive, privileged)
    assert obs.size == layout.size
    nb_t, own_t = _encoder(layout).split(torch.as_tensor(obs[None]))
    np.testing.assert_array_equal(nb_t[0].numpy(), rows)
    np.testing.assert_array_equal(own_t[0].numpy(), own)
    idx_rows, idx_own = split_indices(layout)
    assert idx_rows.shape == rows.shape and idx_own.shape == own.shape


def test_traffic_and_v3_layouts_of_the_envs() -> None:
    """The shapes the Traffic-v0 (v0 + driving) and v3 layouts give with K = 20 (docs/env.md: 152 and 351)."""
    rows, own = split_indices(_layout(20, 0, drive=True))
    assert rows.shape == (20, FEATURES) and own.tolist() == list(range(140, 152))
    rows, own = split_indices(_layout(20, 3))
    assert rows.shape == (20, FEATURES + FEATURES_V3)
    assert rows[1].tolist() == [*range(7, 14), *range(155, 165)]
    assert own.tolist() == [*range(140, 145), *range(345, 351)]
    rows, own = split_indices(_layout(20, 4, drive=True))  # Traffic-v1: 145 + 8 x 20 + 6 + 7 = 318
    assert rows.shape == (20, FEATURES + FEATURES_V4)
    assert rows[1].tolist() == [*range(7, 14), *range(153, 161)]
    assert own.tolist() == [*range(140, 145), *range(305, 318)]


@pytest.mark.parametrize("pool", ["deepsets", "attention"])
@pytest.mark.parametrize(("version", "drive"), [(3, False), (0, True), (4, True)])
def test_features_are_invariant_to_the_order_of_the_neighbours(pool: str, version: int, drive: bool) -> None:
    layout = _layout(6, version, drive)
    enc = _encoder(layout, pool)
    rows, _ = split_indices(layout)
    obs = np.random.default_rng(1).normal(size=(4, layout.size)).astype(np.float32)
    perm = np.array([3, 0, 5, 1, 4, 2])
    permuted = obs.copy()
    permuted[:, rows] = obs[:, rows[perm]]  # neighbour k's block takes neighbour perm[k]'s
    assert not np.array_equal(permuted, obs)
    with torch.no_grad():
        a = enc(torch.as_tensor(obs)).numpy()
        b = enc(torch.as_tensor(permuted)).numpy()
        changed = obs.copy()
        changed[:, rows[2]] += 0.5  # one neighbour's block only
        c = enc(torch.as_tensor(changed)).numpy()
    assert a.shape == (4, 3 * 8)
    np.testing.assert_allclose(b, a, rtol=0, atol=1e-5)
    assert np.all(np.abs(c - a).max(axis=1) > 1e-3)


def test_the_flat_mlp_is_not_invariant() -> None:
    """The contrast: the SB3 flat MLP on the whole observation sees the order (a linear map of it)."""
    layout = _layout(4, 0, drive=True)
    rows, _ = split_indices(layout)
    torch.manual_seed(0)
    lin = torch.nn.Linear(layout.size, 8)
    obs = np.random.default_rng(2).normal(size=(1, layout.size)).astype(np.float32)
    permuted = obs.copy()
    permuted[:, rows] = obs[:, rows[[1, 0, 2, 3]]]
    with torch.no_grad():
        assert not torch.allclose(lin(torch.as_tensor(obs)), lin(torch.as_tensor(permuted)))


def test_wrong_observation_size_and_bad_arguments_are_refused() -> None:
    layout = _layout(20, 3)
    spec = layout_spec(layout)
    with pytest.raises(ValueError, match=r"observation_space has shape \(152,\), but the layout .* has 351 entries"):
        NeighbourEncoder(spaces.Box(-10, 10, (152,), np.float32), spec)
    with pytest.raises(ValueError, match="pool must be one of deepsets, attention"):
        NeighbourEncoder(spaces.Box(-10, 10, (351,), np.float32), spec, pool="mean")
    with pytest.raises(ValueError, match="units must be an integer >= 1"):
        NeighbourEncoder(spaces.Box(-10, 10, (351,), np.float32), spec, units=0)
    with pytest.raises(ValueError, match="layout must be a mapping with the keys"):
        NeighbourEncoder(spaces.Box(-10, 10, (351,), np.float32), {"n_neighbours": 20})


def test_config_refuses_unknown_encoders_and_keeps_old_configs_unchanged(tmp_path) -> None:
    with pytest.raises(TrainError, match=r"ppo\.encoder must be one of mlp, deepsets, attention, got 'lstm'"):
        PpoConfig(encoder="lstm")
    with pytest.raises(TrainError, match=r"ppo\.encoder_units must be an integer >= 1"):
        PpoConfig(encoder="deepsets", encoder_units=0)
    path = tmp_path / "c.yaml"
    path.write_text("env_id: cv2x/SingleMover-v3\nppo:\n  encoder: Deepsets\n")
    with pytest.raises(TrainError, match=r"ppo\.encoder must be one of"):
        load_train_config(path)
    path.write_text("env_id: cv2x/SingleMover-v3\nppo:\n  encoder: attention\n  encoder_units: 1e2\n")
    cfg = load_train_config(path)
    assert (cfg.ppo.encoder, cfg.ppo.encoder_units) == ("attention", 100)
    assert cfg.to_dict()["ppo"]["encoder"] == "attention"
    # the default (mlp) is left out of train_config.json: earlier run folders compare equal on --resume
    assert "encoder" not in TrainConfig().to_dict()["ppo"] and "encoder_units" not in TrainConfig().to_dict()["ppo"]


def test_training_with_the_deepsets_encoder_on_singlemover_v3(tmp_path) -> None:
    """build_training (what ``cv2x-marl train`` runs before the run folder) with ``ppo.encoder=deepsets``, a
    few hundred PPO steps, then the saved model reloads as ``ppo:PATH`` with the same encoder and actions."""
    env = {"max_cycles": 10, "max_step_m": 5.0, "normalise_reward": True, "overrides": ["sim.warmup_subframes=200"]}
    cfg = TrainConfig(
        env_id="cv2x/SingleMover-v3",
        copies=2,
        env=env,
        ppo=PpoConfig(n_steps=64, batch_size=64, n_epochs=2, net_arch=(16,), encoder="deepsets", encoder_units=8),
        eval_episodes=1,
    )
    vec, model = build_training(cfg, seed=0)
    try:
        enc = model.policy.features_extractor
        assert isinstance(enc, NeighbourEncoder) and enc.pool == "deepsets"
        assert (enc.n_neighbours, enc.n_features, enc.features_dim) == (20, FEATURES + FEATURES_V3, 24)
        # parameters: phi (17 -> 8 -> 8) over the neighbour rows, rho (11 own entries -> 8 -> 8), closed form
        assert sum(p.numel() for p in enc.parameters()) == (17 * 8 + 8) + (8 * 8 + 8) + (11 * 8 + 8) + (8 * 8 + 8)
        before = [p.detach().clone() for p in model.policy.parameters()]
        model.learn(256)
        assert model.num_timesteps == 256
        assert any(not torch.equal(a, b) for a, b in zip(before, model.policy.parameters(), strict=True))
        model.save(tmp_path / "model.zip")
        obs = vec.reset()
    finally:
        vec.close()
    loaded = PpoPolicy(tmp_path / "model.zip")
    assert isinstance(loaded.model.policy.features_extractor, NeighbourEncoder)
    np.testing.assert_array_equal(loaded._predict(obs), model.predict(obs, deterministic=True)[0])
