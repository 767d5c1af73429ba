"""Behaviour cloning and DAgger of the ``sensing`` planner (``cv2x-marl train`` with ``algo: imitation``; torch).

A reported variant of the learnability comparison (docs/benchmark.md, "Learners at equal budget"), not a headline
learner: it learns from an expert, the ``sensing`` planner (:class:`~cv2x_marl.policies.planner.PlannerPolicy`
with ``estimator="sensing"``), which plans on the mover's own measurements (nothing privileged) and reaches about
98 % of the ceiling on ``cv2x/SingleMover-v3``. The question it answers: can the PPO networks represent that
behaviour when they are shown it, state by state?

Training runs ``iterations`` = ceil(timesteps / (copies x max_cycles)) rounds. Each round:

1. **Collect** one episode in each of ``copies`` env copies (episodes from the protocol's first ``start_pool``
   training seeds). During the first ``expert_iterations`` rounds the expert drives (behaviour cloning's
   data); afterwards the current network drives (deterministic: ``clip(mu, -1, 1)``) and the expert only
   labels the states it meets (DAgger, Ross et al. 2011, with beta = 0 after the expert rounds). Every step
   stores the observation and the expert's action there: the direction to its planned position, as it would
   act (it replans every :data:`~cv2x_marl.env.planning.MEASURED_REPLAN_EVERY` steps from the measurements it
   reads, as when it drives).
2. **Fit** the network on every pair stored so far (the aggregate): ``epochs`` passes of Adam on
   mini-batches of ``batch_size``, squared error between the actor's mean ``mu`` and the expert's action.

``expert_iterations`` >= the number of rounds is plain behaviour cloning. The network is
:class:`~cv2x_marl.policies.ppo_nets.ActorCritic` (the ``ppo.backend: torchrl`` layout: ``net_arch``,
``encoder``, ``encoder_units``); its critic is left as initialised. ``model.pt`` has the torchrl PPO format
(:data:`~cv2x_marl.policies.torch_ppo.MODEL_FORMAT`), so ``--policy ppo:PATH/model.pt`` loads it, and PPO could
start from it. ``curve.csv`` / ``curve.png``: per round the pairs, CPU seconds, the fit's loss and, every
``eval_every`` rounds, the network's utility gain on ``eval_episodes`` training-list episodes after the pool
(never a held-out one). One seed drives the episode draws, the initialisation and the mini-batches (named
streams of one ``SeedSequence``).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from cv2x_marl.checks import is_int
from cv2x_marl.rl.errors import TrainError
from cv2x_marl.rl.mappo_config import count_at_least, hidden_layers
from cv2x_marl.rl.pooled_run import (
    check_pooled_run,
    cli_budget,
    round_record,
    train_in_folder,
    train_rounds,
    write_curve,
)
from cv2x_marl.rl.train_config import check_reals, read_sections, with_cli_values

#: the env ids imitation trains on (the ``sensing`` expert plans on observation version 3's measurements)
IMITATION_ENV_IDS = ("cv2x/SingleMover-v3",)
#: the neighbour encoders and the flat MLP of the torchrl PPO network
ENCODERS = ("mlp", "deepsets", "attention")
#: the widest hidden layer of ``imitation.net_arch``
MAX_UNITS = 4096


@dataclass(frozen=True)
class ImitationSettings:
    """The ``imitation:`` mapping of an imitation config (module docstring)."""

    #: rounds in which the expert drives (the rest: the network drives, the expert labels)
    expert_iterations: int = 2
    learning_rate: float = 1e-3
    #: passes over the aggregate after each round
    epochs: int = 4
    batch_size: int = 256
    net_arch: tuple[int, ...] = (128, 128)
    encoder: str = "deepsets"
    encoder_units: int = 64

    def __post_init__(self) -> None:
        check_reals(self, "imitation", {"learning_rate": (lambda v: v > 0, "a number > 0")})
        for name in ("epochs", "batch_size", "encoder_units"):
            object.__setattr__(self, name, count_at_least(f"imitation.{name}", getattr(self, name)))
        first = count_at_least("imitation.expert_iterations", self.expert_iterations, low=0)
        object.__setattr__(self, "expert_iterations", first)
        object.__setattr__(self, "net_arch", hidden_layers("imitation.net_arch", self.net_arch, MAX_UNITS))
        if self.encoder not in ENCODERS:
            raise TrainError(f"imitation.encoder must be one of {', '.join(ENCODERS)}, got {self.encoder!r}")


@dataclass(frozen=True)
class ImitationConfig:
    """Everything an imitation run needs besides timesteps and seed."""

    env_id: str = "cv2x/SingleMover-v3"
    #: env copies: one episode each per round
    copies: int = 32
    env: dict[str, Any] = field(default_factory=lambda: {"max_cycles": 100, "max_step_m": 5.0, "start_pool": 256})
    imitation: ImitationSettings = field(default_factory=ImitationSettings)
    #: rounds between two evaluations on the training list (and the last round)
    eval_every: int = 4
    eval_episodes: int = 8
    algo: str = "imitation"

    def __post_init__(self) -> None:
        check_pooled_run(self, "imitation", IMITATION_ENV_IDS, "imitation of sensing")

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["imitation"]["net_arch"] = list(self.imitation.net_arch)
        return {"algo": d.pop("algo"), **d}


def load_imitation_config(path: Path | None, env_id: str | None = None, copies: int | None = None) -> ImitationConfig:
    """Read an imitation file (``algo: imitation``, ``env_id``, ``copies``, ``env``, ``imitation``, ``eval_*``);
    unknown keys raise :class:`TrainError` naming them with the allowed ones; CLI values override the file."""
    data, raw, env = read_sections(
        path, ("seed", "timesteps"), ImitationConfig, "imitation config", "imitation", ImitationSettings, "imitation"
    )
    cfg = ImitationConfig(**{**data, "env": {**ImitationConfig().env, **env}, "imitation": ImitationSettings(**raw)})
    return with_cli_values(cfg, env_id, copies)


def train_imitation(
    cfg: ImitationConfig, timesteps: int, seed: int, run_dir: Path, progress: bool = True, overwrite: bool = False
) -> dict[str, Any]:
    """Clone ``sensing`` for at least ``timesteps`` agent-steps (whole rounds); write the run folder (``model.pt``,
    ``train_config.json``, ``curve.csv``, ``curve.png``, ``record.json``); return the record.

    Raises:
        TrainError: a bad configuration (before ``run_dir`` is touched).
        cv2x_marl.runs.RunFolderError: the folder is in use, or not empty without ``overwrite``.
    """
    if not is_int(timesteps) or timesteps < 1:
        raise TrainError(f"--timesteps must be an integer >= 1, got {timesteps!r}")
    run = _ImitationRun(cfg, seed)
    resolved = {**cfg.to_dict(), "seed": seed, "timesteps": timesteps}
    return train_in_folder(run, resolved, timesteps, seed, run_dir, progress, overwrite)


class _ImitationRun:
    """One run: the env copies with their experts, the network, the aggregate and the random streams."""

    def __init__(self, cfg: ImitationConfig, seed: int) -> None:
        import gymnasium
        import torch

        import cv2x_marl.env  # noqa: F401  (registers the ids)
        from cv2x_marl.policies.encoders import layout_spec
        from cv2x_marl.policies.planner import PlannerPolicy
        from cv2x_marl.policies.ppo_nets import ActorCritic

        torch.set_num_threads(1)  # before the initialisation too: its QR rounds differently on more threads
        self.cfg, self.seed = cfg, int(seed)
        streams = np.random.SeedSequence([self.seed, 0x1417]).spawn(3)
        self.episode_ss = streams[0]
        init_seed, batch_seed = (int(s.generate_state(1)[0]) for s in streams[1:])
        try:
            self.envs = [gymnasium.make(cfg.env_id, **cfg.env) for _ in range(cfg.copies)]
        except (ValueError, TypeError) as exc:
            raise TrainError(f"train.env of {cfg.env_id}: {exc}") from exc
        self.pars = [e.unwrapped.par for e in self.envs]  # type: ignore[attr-defined]
        for env, ss in zip(self.envs, self.episode_ss.spawn(cfg.copies), strict=True):
            env.unwrapped.np_random = np.random.default_rng(ss)  # each copy's episode draws
        self.experts = [PlannerPolicy(par, None, estimator="sensing") for par in self.pars]
        par = self.pars[0]
        self.agent = par.possible_agents[0]
        self.layout = par.layout
        self.max_cycles = int(par.max_cycles)
        s = cfg.imitation
        obs_size = int(np.prod(par.observation_space(self.agent).shape))
        self.net = ActorCritic(
            obs_size, 2, s.net_arch, s.encoder, s.encoder_units, layout_spec(par.layout) if s.encoder != "mlp" else None
        )
        self.net.init_weights(torch.Generator().manual_seed(init_seed))
        self.batch_gen = torch.Generator().manual_seed(batch_seed)
        self.optim = torch.optim.Adam(self.net.parameters(), lr=s.learning_rate)
        self.obs: list[np.ndarray] = []
        self.labels: list[np.ndarray] = []

    def close(self) -> None:
        for env in self.envs:
            env.close()

    def agent_steps(self) -> int:
        return self.cfg.copies * self.max_cycles

    def act(self, obs: np.ndarray) -> np.ndarray:
        """The network's deterministic actions [B, 2] for observations [B, D]."""
        import torch

        with torch.no_grad():
            return self.net.deterministic(torch.from_numpy(np.ascontiguousarray(obs, dtype=np.float32))).numpy()

    def collect(self, expert_drives: bool) -> None:
        """One episode in every copy (module docstring, 1.): the observations and the expert's actions."""
        obs = np.stack([env.reset()[0] for env in self.envs])
        for expert in self.experts:
            expert.reset()
        for _ in range(self.max_cycles):
            labels = np.stack(
                [np.asarray(ex.act({self.agent: o})[self.agent]) for ex, o in zip(self.experts, obs, strict=True)]
            ).astype(np.float32)
            self.obs.append(obs.astype(np.float32))
            self.labels.append(labels)
            actions = labels if expert_drives else self.act(obs)
            obs = np.stack([env.step(a)[0] for env, a in zip(self.envs, actions, strict=True)])

    def fit(self) -> float:
        """``epochs`` passes over the aggregate (module docstring, 2.); the mean squared error of the last pass."""
        import torch

        x = torch.from_numpy(np.concatenate(self.obs))
        y = torch.from_numpy(np.concatenate(self.labels))
        s = self.cfg.imitation
        last = 0.0
        for _ in range(s.epochs):
            order = torch.randperm(x.shape[0], generator=self.batch_gen)
            total, batches = 0.0, 0
            for start in range(0, x.shape[0], s.batch_size):
                idx = order[start : start + s.batch_size]
                mu, _ = self.net.actor_head(self.net.features(x[idx]))
                loss = torch.mean((mu - y[idx]) ** 2)
                self.optim.zero_grad()
                loss.backward()
                self.optim.step()
                total, batches = total + float(loss.detach()), batches + 1
            last = total / max(batches, 1)
        return last

    def evaluate(self) -> dict[str, Any]:
        from cv2x_marl.env.seeds import training_pool
        from cv2x_marl.experiments.evaluate import evaluate
        from cv2x_marl.policies.base import BatchPolicy

        pool = int(self.cfg.env["start_pool"])
        seeds = training_pool(pool + self.cfg.eval_episodes)[pool:]
        policy = BatchPolicy(self.act, "imitation")
        return evaluate(self.cfg.env_id, policy, len(seeds), 0, None, self.cfg.env, progress=False, seeds=seeds)

    def model(self) -> dict[str, Any]:
        """``model.pt``: the torchrl PPO format (:class:`cv2x_marl.policies.torch_ppo.TorchPpoPolicy` reads it)."""
        from cv2x_marl.policies.torch_ppo import model_contents

        return model_contents(self.cfg.env_id, self.net)

    def train(self, timesteps: int, run_dir: Path, progress: bool) -> dict[str, Any]:
        import torch

        iterations = math.ceil(timesteps / self.agent_steps())
        expert = self.cfg.imitation.expert_iterations

        def one_round(it: int) -> float:
            self.collect(expert_drives=it < expert)
            return self.fit()

        rows, wall_s = train_rounds(
            iterations, self.agent_steps(), one_round, self.evaluate, self.cfg.eval_every,
            "imitation" if progress else None,
        )  # fmt: skip
        torch.save(self.model(), run_dir / "model.pt")
        write_curve(run_dir, rows, "imitation of sensing")
        record = round_record("imitation", self.cfg.env_id, self.seed, self.agent_steps(), rows, wall_s)
        return {**record, "expert_iterations": min(expert, iterations), "pairs": int(sum(len(o) for o in self.obs))}


def cli_train(args: Any, default_timesteps: int, print_json: Any) -> int:
    """``cv2x-marl train`` for an imitation config (``--algo imitation`` or ``algo: imitation``): ``--config``,
    ``--env``, ``--copies``, ``--timesteps`` and ``--seed`` (else the file's), ``--out``, ``--overwrite``;
    ``--resume`` is refused (a run takes minutes)."""
    timesteps, seed = cli_budget(args, default_timesteps, "an imitation")
    cfg = load_imitation_config(args.config, env_id=args.env, copies=args.copies)
    record = train_imitation(cfg, timesteps, seed, args.out, progress=not args.quiet, overwrite=args.overwrite)
    if args.json:
        print_json(record)
    else:
        print(
            f"cloned sensing on {record['pairs']} labelled agent-steps ({record['iterations']} rounds, "
            f"{record['expert_iterations']} driven by the expert) in {record['cpu_s']:.1f} CPU-s; training-list "
            f"utility gain {record['final_eval_utility_gain']:+.1%}"
        )
        model = args.out / "model.pt"
        print(f"wrote {model}, curve.csv, curve.png (evaluate with --policy ppo:{model})")
    return 0
