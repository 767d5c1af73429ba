"""The training configuration of `cv2x-marl train` (:class:`TrainConfig`, :class:`PpoConfig`): its
fields, their checks and the YAML / JSON loader (:func:`load_train_config`); :mod:`cv2x_marl.rl.train`
re-exports every name."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cv2x_marl.checks import as_real, is_int
from cv2x_marl.env.options import option_names
from cv2x_marl.env.registry import ENV_IDS, SPECS
from cv2x_marl.rl.errors import TrainError
from cv2x_marl.yamlcore import load_mapping

#: the most env copies a run may ask for (``copies``, ``--copies``): each copy holds its own
#: simulator state (measured about 0.33 MB on the ``paper`` preset, 14 MB on ``highway``) and is
#: built one after the other, so 4,096 copies already take minutes to build; the default is 8
MAX_COPIES = 4096
#: the widest hidden layer of ``ppo.net_arch`` (the networks' memory is estimated as well)
MAX_LAYER_UNITS = 65_536
#: Python objects of one env copy besides its simulator arrays (measured: paper 0.33 MB per copy,
#: of which 0.32 MB are the arrays :func:`estimate_training_memory` counts)
_COPY_OVERHEAD_BYTES = 100_000
#: ``ppo.encoder``: ``mlp`` (SB3's flat MLP) or a neighbour encoder (:mod:`cv2x_marl.policies.encoders`)
ENCODERS = ("mlp", "deepsets", "attention")
#: ``ppo.backend``: ``sb3`` (stable-baselines3's PPO over :class:`~cv2x_marl.rl.sb3_vec_env.AgentsVecEnv`) or
#: ``torchrl`` (:mod:`cv2x_marl.rl.fast_ppo`: TorchRL's loss over the batched vector env, ``SingleMover`` ids)
BACKENDS = ("sb3", "torchrl")


#: the real-valued PPO settings PPO and MAPPO share: name -> (test, allowed values as the error says them)
PPO_REALS: dict[str, tuple[Any, str]] = {
    "learning_rate": (lambda v: v > 0, "a number > 0"),
    "gamma": (lambda v: 0 < v <= 1, "a number in (0, 1]"),
    "gae_lambda": (lambda v: 0 <= v <= 1, "a number in [0, 1]"),
    "clip_range": (lambda v: v > 0, "a number > 0"),
    "ent_coef": (lambda v: v >= 0, "a number >= 0"),
    "vf_coef": (lambda v: v >= 0, "a number >= 0"),
    "max_grad_norm": (lambda v: v > 0, "a number > 0"),
}


def check_reals(obj: Any, section: str, rules: dict[str, tuple[Any, str]]) -> None:
    """Check and set the real-valued fields ``rules`` names on the frozen dataclass ``obj`` (a numeric string,
    which YAML 1.1 makes of ``3e-4``, becomes a number); a bad one raises :class:`TrainError` naming
    ``section.name`` and the allowed values."""
    for name, (ok, allowed) in rules.items():
        value = as_real(getattr(obj, name))
        if value is None or not ok(value):
            raise TrainError(f"{section}.{name} must be {allowed}, got {getattr(obj, name)!r}")
        object.__setattr__(obj, name, value)


@dataclass(frozen=True)
class PpoConfig:
    """PPO hyperparameters (stable-baselines3 names)."""

    learning_rate: float = 3e-4
    n_steps: int = 64
    batch_size: int = 512
    n_epochs: int = 10
    gamma: float = 0.95
    gae_lambda: float = 0.95
    clip_range: float = 0.2
    ent_coef: float = 0.0
    vf_coef: float = 0.5
    max_grad_norm: float = 0.5
    net_arch: tuple[int, ...] = (128, 128)
    #: initial log standard deviation of the Gaussian actions (SB3's default 0: std 1)
    log_std_init: float = 0.0
    #: what the MLPs read: ``mlp`` the flat observation, ``deepsets`` / ``attention`` a NeighbourEncoder's 3 d
    encoder: str = "mlp"
    #: features (:class:`cv2x_marl.policies.encoders.NeighbourEncoder`), d = ``encoder_units``
    encoder_units: int = 64
    #: an LSTM between the features and the MLPs (sb3-contrib's ``RecurrentPPO``, ``MlpLstmPolicy``): the
    #: policy carries a memory over the episode (what it measured earlier, how the road moved)
    recurrent: bool = False
    #: hidden units of the actor's and the critic's LSTM (``recurrent: true``)
    lstm_units: int = 64
    #: the trainer (:data:`BACKENDS`): ``sb3`` or ``torchrl`` (the same network, one Python call per vector step)
    backend: str = "sb3"

    def __post_init__(self) -> None:
        """Type and range checks; a numeric string (YAML 1.1 reads ``3e-4`` as one) becomes a number."""
        check_reals(self, "ppo", {**PPO_REALS, "log_std_init": (lambda v: True, "a finite number")})
        for name in ("n_steps", "batch_size", "n_epochs"):
            object.__setattr__(self, name, check_count(f"ppo.{name}", getattr(self, name)))
        if self.batch_size < 2:  # SB3 normalises the advantages over each mini-batch
            raise TrainError(
                f"ppo.batch_size must be an integer >= 2 (PPO normalises the advantages over each "
                f"mini-batch), got {self.batch_size!r}"
            )
        arch = self.net_arch
        rule = f"a non-empty list of integers in [1, {MAX_LAYER_UNITS:,}] (units per hidden layer)"
        if not isinstance(arch, tuple | list) or not arch:
            raise TrainError(f"ppo.net_arch must be {rule}, got {arch!r}")
        try:
            units = tuple(check_count("ppo.net_arch", a) for a in arch)
        except TrainError:
            raise TrainError(f"ppo.net_arch must be {rule}, got {list(arch)!r}") from None
        if max(units) > MAX_LAYER_UNITS:
            raise TrainError(f"ppo.net_arch must be {rule}, got {list(arch)!r}")
        object.__setattr__(self, "net_arch", units)
        if not isinstance(self.encoder, str) or self.encoder not in ENCODERS:
            raise TrainError(f"ppo.encoder must be one of {', '.join(ENCODERS)}, got {self.encoder!r}")
        object.__setattr__(self, "encoder_units", check_count("ppo.encoder_units", self.encoder_units))
        if not isinstance(self.recurrent, bool):
            raise TrainError(f"ppo.recurrent must be true or false, got {self.recurrent!r}")
        object.__setattr__(self, "lstm_units", check_count("ppo.lstm_units", self.lstm_units))
        if self.lstm_units > MAX_LAYER_UNITS:
            raise TrainError(f"ppo.lstm_units must be an integer in [1, {MAX_LAYER_UNITS:,}], got {self.lstm_units}")
        if self.encoder_units > MAX_LAYER_UNITS:
            raise TrainError(
                f"ppo.encoder_units must be an integer in [1, {MAX_LAYER_UNITS:,}], got {self.encoder_units}"
            )
        if not isinstance(self.backend, str) or self.backend not in BACKENDS:
            raise TrainError(f"ppo.backend must be one of {', '.join(BACKENDS)}, got {self.backend!r}")
        if self.backend == "torchrl" and self.recurrent:
            raise TrainError("ppo.recurrent: true needs ppo.backend: sb3 (sb3-contrib's RecurrentPPO), got torchrl")


def check_count(name: str, value: Any) -> int:
    """``value`` as an int >= 1; a whole float (YAML's ``1e4``) counts, ``1.5`` and bools do not."""
    if isinstance(value, float) and math.isfinite(value) and value.is_integer():
        value = int(value)
    if not is_int(value) or value < 1:
        raise TrainError(f"{name} must be an integer >= 1, got {value!r}")
    return int(value)


@dataclass(frozen=True)
class TrainConfig:
    """Everything a run needs besides timesteps and seed."""

    env_id: str = "cv2x/SingleMover-v0"
    copies: int = 8
    env: dict[str, Any] = field(
        default_factory=lambda: {"max_cycles": 100, "max_step_m": 5.0, "normalise_reward": True}
    )
    ppo: PpoConfig = field(default_factory=PpoConfig)
    checkpoint_every: int = 50_000
    eval_every: int = 50_000
    eval_episodes: int = 16
    eval_seed: int = 10_000
    #: None: every training episode from a fresh seed; N: from N seeds, their starts cached
    start_pool: int | None = None

    def __post_init__(self) -> None:
        if self.env_id not in ENV_IDS:
            raise TrainError(f"env_id {self.env_id!r} unknown; ids: {', '.join(ENV_IDS)}")
        for name in ("copies", "checkpoint_every", "eval_every", "eval_episodes"):
            object.__setattr__(self, name, check_count(f"train.{name}", getattr(self, name)))
        if self.copies > MAX_COPIES:
            raise TrainError(
                f"train.copies (--copies) must be an integer in [1, {MAX_COPIES:,}] (each copy holds its own "
                f"simulator, built one after the other), got {self.copies!r}"
            )
        if not is_int(self.eval_seed) or self.eval_seed < 0:
            raise TrainError(f"train.eval_seed must be an integer >= 0, got {self.eval_seed!r}")
        if not isinstance(self.env, dict):
            raise TrainError(f"train.env must be a mapping of env arguments, got {self.env!r}")
        allowed = env_arguments(self.env_id)
        bad = sorted(str(k) for k in self.env if k not in allowed)
        if bad:
            raise TrainError(
                f"unknown env argument(s) {bad} in train.env of {self.env_id}; arguments: {', '.join(allowed)}"
            )
        if self.start_pool is not None:
            object.__setattr__(self, "start_pool", check_count("train.start_pool", self.start_pool))
        if self.ppo.backend == "torchrl":
            check_torchrl_backend(self)

    def env_for_training(self) -> dict[str, Any]:
        """The env arguments of training and its evaluation callbacks: ``env`` plus, with a start
        pool, a reset cache that holds the pool and the evaluation episodes (bit-identical starts)."""
        if self.start_pool is None:
            return dict(self.env)
        return {**self.env, "reset_cache": self.start_pool + self.eval_episodes}

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["ppo"]["net_arch"] = list(self.ppo.net_arch)
        for key in (
            "encoder",
            "encoder_units",
            "recurrent",
            "lstm_units",
            "backend",
        ):  # added later: left out at their defaults
            if d["ppo"][key] == getattr(PpoConfig, key):
                del d["ppo"][key]
        return d


def check_torchrl_backend(cfg: TrainConfig) -> None:
    """What ``ppo.backend: torchrl`` needs of a configuration: an id whose copies the batched vector env steps
    (:class:`~cv2x_marl.env.vector.SingleMoverVectorEnv`: the ``SingleMover`` ids) and training episodes from the
    protocol's training seeds (the env option ``start_pool``), not the top-level ``start_pool`` (seeds derived
    from the training seed, which may be anyone's).

    Raises:
        TrainError: naming the key and the values allowed.
    """
    vector_ids = [s.env_id for s in SPECS if s.vector]
    if cfg.env_id not in vector_ids:
        raise TrainError(
            f"ppo.backend: torchrl steps the batched vector env, which {cfg.env_id} has not; env ids: "
            f"{', '.join(vector_ids)} (or ppo.backend: sb3)"
        )
    if cfg.start_pool is not None:
        raise TrainError(
            f"train.start_pool={cfg.start_pool} is not taken by ppo.backend: torchrl; set the env option "
            "env.start_pool (the protocol's training seeds) instead"
        )


def env_arguments(env_id: str) -> tuple[str, ...]:
    """The keyword arguments of :class:`~cv2x_marl.env.mobility_env.MobilityEnv` a training
    config's ``env`` may set: all but ``config`` (a Python object; use ``preset`` and
    ``overrides``) and, for the ``SingleMover`` ids, ``movers`` (fixed to vehicle 0)."""
    skip = {"config"} | ({"movers"} if env_id.startswith("cv2x/SingleMover") else set())
    return tuple(n for n in option_names() if n not in skip)


def check_pooled_env(env_id: str, env: Any, trainer: str) -> None:
    """Check a ``train.env`` mapping of a trainer that draws its episodes from the start pool (MAPPO, the utility
    map): a mapping of the id's env arguments (unknown ones named with the allowed ones) with ``start_pool`` >= 1.

    Raises:
        TrainError: naming the key and the allowed values.
    """
    if not isinstance(env, dict):
        raise TrainError(f"train.env must be a mapping of env arguments, got {env!r}")
    allowed = env_arguments(env_id)
    bad = sorted(str(k) for k in env if k not in allowed)
    if bad:
        raise TrainError(f"unknown env argument(s) {bad} in train.env of {env_id}; arguments: {', '.join(allowed)}")
    pool = env.get("start_pool")
    if not is_int(pool) or int(pool) < 1:  # type: ignore[arg-type]
        raise TrainError(
            f"train.env.start_pool must be an integer >= 1 ({trainer} trains on the protocol's first start_pool "
            f"training seeds), got {pool!r}"
        )


#: what a run folder's ``train_config.json`` holds besides the configuration (and ``algo``, read by the CLI)
RUN_KEYS = ("seed", "timesteps", "algo")


def run_settings(path: Path | None) -> dict[str, int]:
    """The ``seed`` and ``timesteps`` a training file names (a run folder's ``train_config.json``
    does), checked; empty for a plain configuration. ``cv2x-marl train --config FILE`` uses them
    when ``--seed`` / ``--timesteps`` are not given, so a shipped run can be trained again as it was."""
    if path is None:
        return {}
    data = load_mapping(path, "training config", TrainError)
    out: dict[str, int] = {}
    for key, low in (("seed", 0), ("timesteps", 1)):
        if key in data:
            value = data[key]
            if not is_int(value) or value < low:
                raise TrainError(f"{path}: {key} must be an integer >= {low}, got {value!r}")
            out[key] = int(value)
    return out


def load_train_config(path: Path | None, env_id: str | None = None, copies: int | None = None) -> TrainConfig:
    """Read a YAML/JSON file ``{env_id, copies, env: {...}, ppo: {...}, checkpoint_every, ...}``.

    Unknown keys raise :class:`TrainError` naming them; CLI values override the file. A run
    folder's ``train_config.json`` is a valid file: its ``seed`` and ``timesteps`` (the run's, see
    :func:`run_settings`) are not part of the configuration and are skipped here.
    """
    data, ppo_data, env_data = read_sections(path, RUN_KEYS, TrainConfig, "training config", "ppo", PpoConfig, "PPO")
    if "net_arch" in ppo_data and isinstance(ppo_data["net_arch"], list | tuple):
        ppo_data["net_arch"] = tuple(ppo_data["net_arch"])
    cfg = TrainConfig(**{**data, "env": {**TrainConfig().env, **env_data}, "ppo": PpoConfig(**ppo_data)})
    return with_cli_values(cfg, env_id, copies)


def read_sections(
    path: Path | None,
    skip: tuple[str, ...],
    top: type,
    kind: str,
    section: str,
    section_type: type,
    section_label: str,
) -> tuple[dict[str, Any], dict[str, Any], dict[str, Any]]:
    """A training file (YAML / JSON; none: empty) split into its top-level values, its ``section`` mapping
    (``ppo`` / ``mappo``) and its ``env`` mapping, every key checked against the fields of the dataclasses
    ``top`` and ``section_type`` (unknown ones named with the allowed ones); ``skip``: run keys left out.

    Raises:
        TrainError: an unknown key, or a ``section`` / ``env`` that is not a mapping.
    """
    data = {} if path is None else load_mapping(path, "training config", TrainError)
    for key in skip:
        data.pop(key, None)
    known = {f.name for f in dataclasses.fields(top)}
    bad = sorted(set(data) - known)
    if bad:
        raise TrainError(f"unknown {kind} key(s) {bad}; keys: {', '.join(sorted(known))}")
    raw = data.pop(section, {}) or {}
    if not isinstance(raw, dict):
        raise TrainError(f"train.{section} must be a mapping of {section_label} settings, got {raw!r}")
    section_known = {f.name for f in dataclasses.fields(section_type)}
    bad = sorted(set(raw) - section_known)
    if bad:
        raise TrainError(f"unknown {section} key(s) {bad}; keys: {', '.join(sorted(section_known))}")
    env = data.pop("env", {}) or {}
    if not isinstance(env, dict):
        raise TrainError(f"train.env must be a mapping of env arguments, got {env!r}")
    return data, dict(raw), env


def with_cli_values(cfg: Any, env_id: str | None, copies: int | None) -> Any:
    """``cfg`` (a frozen dataclass with ``env_id`` and ``copies``) with the CLI's ``--env`` / ``--copies`` over the
    file's."""
    if env_id is not None:
        cfg = dataclasses.replace(cfg, env_id=env_id)
    if copies is not None:
        cfg = dataclasses.replace(cfg, copies=copies)
    return cfg
