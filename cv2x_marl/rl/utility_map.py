"""Training the learned utility map (``cv2x-marl train`` with ``algo: utility-map``; torch).

The map (:mod:`cv2x_marl.policies.utility_map`) is learned from the mover's own experience, with no
expert and nothing privileged. Training alternates two phases over ``iterations`` of ``copies`` episodes:

1. **Collect** one episode in each of ``copies`` batched copies of the env
   (:class:`~cv2x_marl.env.vector.SingleMoverVectorEnv`, one compiled call per step for all copies), the
   episodes drawn from the protocol's first ``start_pool`` training seeds. The mover drives to a target it
   chooses every ``replan_every`` steps: a uniformly random point of its reachable square during the first
   ``random_iterations`` iterations, afterwards the current map's best point, replaced by a random point
   with probability ``explore`` (the search of :meth:`UtilityMap.plan`, batched over the copies). Every
   step stores the observation and the own utility it carries (the running sum of the rewards).
2. **Fit** the network after each iteration with ``fit_steps`` Adam steps on mini-batches of
   ``batch_size`` pairs ``(t, t')`` of one stored episode with ``t <= t'``: the features of the
   observation at ``t`` evaluated at the candidate offset ``drift(t') - drift(t)`` predict the utility
   observed at ``t'`` (squared error). In the snapshot scene the other vehicles stand still, so an earlier
   observation describes the later position's links except for what the mover measured; these pairs are
   what the policy does when it plans.

The learning curve (``curve.csv``, ``curve.png``) has one row per iteration: agent-steps, process CPU
seconds, the fit's loss, and every ``eval_every`` iterations the map policy's utility gain on
``eval_episodes`` training-list episodes after the pool (never a held-out one). One seed drives
everything: the env's episode draws, the exploration and torch's initialisation and mini-batches (named
streams of one ``SeedSequence``).
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from cv2x_marl.checks import is_int
from cv2x_marl.policies.utility_map import (
    LINK_FEATURES,
    UtilityMap,
    UtilityMapPolicy,
    check_map_env,
    own_drift_m,
    static_features,
)
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

#: the env ids the map trains on (observation version 3, one mover in a snapshot)
MAP_ENV_IDS = ("cv2x/SingleMover-v3",)
#: the widest hidden layer of ``map.hidden`` (the map is evaluated at every candidate and neighbour)
MAX_UNITS = 4096


@dataclass(frozen=True)
class MapSettings:
    """The ``map:`` mapping of a utility-map config (module docstring)."""

    #: hidden layers of the per-link network
    hidden: tuple[int, ...] = (64, 64)
    learning_rate: float = 2e-3
    #: Adam steps after each iteration
    fit_steps: int = 200
    #: (t, t') pairs per Adam step
    batch_size: int = 256
    #: iterations that explore with random targets only
    random_iterations: int = 2
    #: afterwards, the probability of a random target instead of the map's
    explore: float = 0.3
    #: share of pairs with t' = t (the utility where the RSRP was measured)
    same_step: float = 0.2
    grid: int = 21
    refine: int = 7
    top: int = 3
    replan_every: int = 10
    #: networks in the ensemble (the map is their mean)
    ensemble: int = 1
    #: utility a new search's best must gain over the current target to replace it
    switch_margin: float = 0.0

    def __post_init__(self) -> None:
        check_reals(
            self,
            "map",
            {
                "learning_rate": (lambda v: v > 0, "a number > 0"),
                "explore": (lambda v: 0 <= v <= 1, "a number in [0, 1]"),
                "same_step": (lambda v: 0 <= v <= 1, "a number in [0, 1]"),
                "switch_margin": (lambda v: 0 <= v < math.inf, "a number >= 0"),
            },
        )
        for name in ("fit_steps", "batch_size", "grid", "refine", "top", "replan_every", "ensemble"):
            object.__setattr__(self, name, count_at_least(f"map.{name}", getattr(self, name)))
        explore_first = count_at_least("map.random_iterations", self.random_iterations, low=0)
        object.__setattr__(self, "random_iterations", explore_first)
        object.__setattr__(self, "hidden", hidden_layers("map.hidden", self.hidden, MAX_UNITS))


@dataclass(frozen=True)
class MapConfig:
    """Everything a utility-map run needs besides timesteps and seed."""

    env_id: str = "cv2x/SingleMover-v3"
    #: batched env copies: one episode each per iteration
    copies: int = 32
    env: dict[str, Any] = field(default_factory=lambda: {"max_cycles": 100, "max_step_m": 5.0, "start_pool": 256})
    map: MapSettings = field(default_factory=MapSettings)
    #: iterations between two evaluations on the training list (and the last iteration)
    eval_every: int = 4
    eval_episodes: int = 8
    algo: str = "utility-map"

    def __post_init__(self) -> None:
        check_pooled_run(self, "utility-map", MAP_ENV_IDS, "the utility map")

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["map"]["hidden"] = list(self.map.hidden)
        return {"algo": d.pop("algo"), **d}


def load_map_config(path: Path | None, env_id: str | None = None, copies: int | None = None) -> MapConfig:
    """Read a utility-map file (``algo: utility-map``, ``env_id``, ``copies``, ``env``, ``map``, ``eval_*``);
    unknown keys raise :class:`TrainError` naming them with the allowed ones; CLI values override the file."""
    data, raw, env = read_sections(
        path, ("seed", "timesteps"), MapConfig, "utility-map config", "map", MapSettings, "utility-map"
    )
    cfg = MapConfig(**{**data, "env": {**MapConfig().env, **env}, "map": MapSettings(**raw)})
    return with_cli_values(cfg, env_id, copies)


class _Network:
    """The torch twin of :meth:`UtilityMap.link_utility` (same layers, same squashing) and its training."""

    def __init__(self, hidden: tuple[int, ...], p_min: float, generator: Any) -> None:
        import torch

        sizes = [len(LINK_FEATURES), *hidden, 1]
        self.layers: list[Any] = [torch.nn.Linear(a, b) for a, b in itertools.pairwise(sizes)]
        with torch.no_grad():
            for layer in self.layers:
                bound = 1.0 / math.sqrt(layer.in_features)
                layer.weight.uniform_(-bound, bound, generator=generator)
                layer.bias.uniform_(-bound, bound, generator=generator)
        self.log_p_min = math.log(p_min)

    def utility(self, static: Any, dynamic: Any, target: Any) -> Any:
        """[B] predicted utility per target receiver; static [B, K, S], dynamic [B, K, 2], target [B, K]."""
        import torch

        h = torch.cat([static, dynamic], dim=-1)
        for n, layer in enumerate(self.layers):
            h = layer(h if n == 0 else torch.relu(h))
        u = self.log_p_min * torch.sigmoid(h[..., 0])
        return (u * target).sum(-1) / target.sum(-1).clamp(min=1.0)

    def weights(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """The layers as :class:`UtilityMap` holds a member: ``(W [in, out], b [out])``, float64."""
        return [
            (layer.weight.detach().double().numpy().T.copy(), layer.bias.detach().double().numpy().copy())
            for layer in self.layers
        ]


@dataclass
class _Store:
    """The stored steps: per step its static features, neighbours, targets, drift (m) and utility."""

    static: list[np.ndarray] = field(default_factory=list)
    rel_m: list[np.ndarray] = field(default_factory=list)
    target: list[np.ndarray] = field(default_factory=list)
    drift_m: list[np.ndarray] = field(default_factory=list)
    utility: list[np.ndarray] = field(default_factory=list)

    def add(self, obs: np.ndarray, layout: Any) -> None:
        """One episode per copy: ``obs`` [T + 1, copies, D] -> ``copies`` episodes of T + 1 steps."""
        t1, c, d = obs.shape
        flat = obs.transpose(1, 0, 2).reshape(c * t1, d).astype(np.float64)
        st, rel, tgt = static_features(flat, layout)
        self.static.append(st.reshape(c, t1, *st.shape[1:]).astype(np.float32))
        self.rel_m.append(rel.reshape(c, t1, *rel.shape[1:]).astype(np.float32))
        self.target.append(tgt.reshape(c, t1, -1).astype(np.float32))
        self.drift_m.append(own_drift_m(flat, layout).reshape(c, t1, 2).astype(np.float32))
        self.utility.append(flat[:, layout.size - 6].reshape(c, t1).astype(np.float32))

    def arrays(self) -> tuple[np.ndarray, ...]:
        return tuple(np.concatenate(x) for x in (self.static, self.rel_m, self.target, self.drift_m, self.utility))


def pair_features(rel_m: Any, offsets_m: Any) -> Any:
    """[B, K, 4] the candidate features (:func:`~cv2x_marl.policies.utility_map.candidate_features`) in torch:
    ``rel_m`` [B, K, 2] neighbours relative to the mover (m), ``offsets_m`` [B, 2] one candidate each (m)."""
    import torch

    def log_m(x: Any) -> Any:
        return torch.log10(torch.clamp(x, min=1.0)) / 3.0

    d = rel_m - offsets_m[:, None, :]
    a = torch.abs(d)
    dist = log_m(torch.hypot(d[..., 0], d[..., 1]))
    moved = (torch.hypot(offsets_m[:, 0], offsets_m[:, 1]) / 100.0)[:, None].expand_as(dist)
    return torch.stack([dist, log_m(a.min(-1).values), log_m(a.max(-1).values), moved], dim=-1)


def train_map(
    cfg: MapConfig, timesteps: int, seed: int, run_dir: Path, progress: bool = True, overwrite: bool = False
) -> dict[str, Any]:
    """Train a utility map for at least ``timesteps`` agent-steps (whole iterations); write the run folder
    (``model.npz``, ``train_config.json``, ``curve.csv``, ``curve.png``, ``record.json``); return the record.

    Raises:
        TrainError: a bad configuration (before ``run_dir`` is touched).
        cv2x_marl.runs.RunFolderError: the folder is in use, or not empty without ``overwrite``.
    """
    if not is_int(timesteps) or timesteps < 1:
        raise TrainError(f"--timesteps must be an integer >= 1, got {timesteps!r}")
    run = _MapRun(cfg, seed)
    resolved = {**cfg.to_dict(), "seed": seed, "timesteps": timesteps}
    return train_in_folder(run, resolved, timesteps, seed, run_dir, progress, overwrite)


class _MapRun:
    """One training run: the batched env, the network, the store and the random streams."""

    def __init__(self, cfg: MapConfig, seed: int) -> None:
        import gymnasium
        import torch

        import cv2x_marl.env  # noqa: F401  (registers the ids)

        self.cfg, self.seed = cfg, int(seed)
        streams = np.random.SeedSequence([self.seed, 0x5A7]).spawn(3)
        self.rng = np.random.default_rng(streams[0])
        self.env_seed = int(streams[1].generate_state(1)[0] % (2**31))
        self.torch_gen = torch.Generator().manual_seed(int(streams[2].generate_state(1)[0]))
        try:
            self.vec: Any = gymnasium.make_vec(
                cfg.env_id, num_envs=cfg.copies, vectorization_mode="vector_entry_point", **cfg.env
            )
        except (ValueError, TypeError) as exc:
            raise TrainError(f"train.env of {cfg.env_id}: {exc}") from exc
        par = self.vec.unwrapped.get_attr("par")[0]
        try:
            check_map_env(par)
        except ValueError as exc:
            self.vec.close()
            raise TrainError(f"train.env of {cfg.env_id}: {exc}") from exc
        self.par = par
        self.layout = par.layout
        self.max_cycles = int(par.max_cycles)
        self.max_step_m = float(par.max_step_m)
        self.nets = [_Network(cfg.map.hidden, float(par.p_min), self.torch_gen) for _ in range(cfg.map.ensemble)]
        self.opts = [
            torch.optim.Adam([p for layer in net.layers for p in layer.parameters()], lr=cfg.map.learning_rate)
            for net in self.nets
        ]
        self.store = _Store()

    def close(self) -> None:
        self.vec.close()

    def agent_steps(self) -> int:
        return self.cfg.copies * self.max_cycles

    def current_map(self) -> UtilityMap:
        s = self.cfg.map
        info = {"env_id": self.cfg.env_id, "env": self.cfg.env, "seed": self.seed}
        members = [net.weights() for net in self.nets]
        return UtilityMap(
            members, float(self.par.p_min), s.grid, s.refine, s.top, s.replan_every, s.switch_margin, info
        )

    def collect(self, iteration: int) -> None:
        """One episode in every copy (module docstring, 1.)."""
        s = self.cfg.map
        obs, _ = self.vec.reset(seed=self.env_seed if iteration == 0 else None)
        rows = [obs]
        umap = self.current_map() if iteration >= s.random_iterations else None
        target = np.zeros((self.cfg.copies, 2))
        for t in range(self.max_cycles):
            o = np.asarray(obs, dtype=np.float64)
            drift = own_drift_m(o, self.layout)
            if t % s.replan_every == 0:
                reach = o[:, self.layout.size - 1] * self.layout.scale_m
                offset = self.rng.uniform(-1.0, 1.0, size=(self.cfg.copies, 2)) * reach[:, None]
                if umap is not None:
                    mine = self.rng.random(self.cfg.copies) >= s.explore
                    if mine.any():
                        now = None if t == 0 else (target - drift)[mine]
                        offset[mine] = umap.plan(o[mine], self.layout, reach[mine], now)
                target = drift + offset
            action = np.clip((target - drift) / self.max_step_m, -1.0, 1.0).astype(np.float32)
            obs, *_ = self.vec.step(action)
            rows.append(obs)
        self.store.add(np.stack(rows), self.layout)

    def fit(self) -> float:
        """``fit_steps`` Adam steps on (t, t') pairs (module docstring, 2.); the mean loss."""
        import torch

        s = self.cfg.map
        static, rel, target, drift, utility = (torch.from_numpy(a) for a in self.store.arrays())
        episodes, t1 = utility.shape
        total = 0.0
        for _ in range(s.fit_steps):
            for net, opt in zip(self.nets, self.opts, strict=True):  # each member its own mini-batches
                e = torch.randint(episodes, (s.batch_size,), generator=self.torch_gen)
                t = torch.randint(t1, (s.batch_size,), generator=self.torch_gen)
                later = t + (torch.rand(s.batch_size, generator=self.torch_gen) * (t1 - t)).long()
                same = torch.rand(s.batch_size, generator=self.torch_gen) < s.same_step
                t2 = torch.where(same, t, later.clamp(max=t1 - 1))
                offsets = drift[e, t2] - drift[e, t]
                dyn = pair_features(rel[e, t], offsets)
                pred = net.utility(static[e, t], dyn, target[e, t])
                loss = torch.mean((pred - utility[e, t2]) ** 2)
                opt.zero_grad()
                loss.backward()
                opt.step()
                total += float(loss.detach())
        return total / (s.fit_steps * len(self.nets))

    def evaluate(self) -> dict[str, Any]:
        from cv2x_marl.env.seeds import training_pool
        from cv2x_marl.experiments.evaluate import evaluate

        pool = int(self.cfg.env["start_pool"])
        seeds = training_pool(pool + self.cfg.eval_episodes)[pool:]
        policy = UtilityMapPolicy(self.current_map(), self.par)  # reads the env's layout and step size only
        return evaluate(self.cfg.env_id, policy, len(seeds), 0, None, self.cfg.env, progress=False, seeds=seeds)

    def train(self, timesteps: int, run_dir: Path, progress: bool) -> dict[str, Any]:
        import torch

        torch.set_num_threads(1)
        iterations = math.ceil(timesteps / self.agent_steps())

        def one_round(it: int) -> float:
            self.collect(it)
            return self.fit()

        rows, wall_s = train_rounds(
            iterations, self.agent_steps(), one_round, self.evaluate, self.cfg.eval_every,
            "utility map" if progress else None,
        )  # fmt: skip
        self.current_map().save(run_dir / "model.npz")
        write_curve(run_dir, rows, "learned utility map")
        return round_record("utility-map", self.cfg.env_id, self.seed, self.agent_steps(), rows, wall_s)


def cli_train(args: Any, default_timesteps: int, print_json: Any) -> int:
    """``cv2x-marl train`` for a utility-map config (``--algo utility-map`` or ``algo: utility-map``): ``--config``,
    ``--env``, ``--copies``, ``--timesteps`` and ``--seed`` (else the file's), ``--out``, ``--overwrite``;
    ``--resume`` is refused (a run takes minutes)."""
    timesteps, seed = cli_budget(args, default_timesteps, "a utility-map")
    cfg = load_map_config(args.config, env_id=args.env, copies=args.copies)
    record = train_map(cfg, timesteps, seed, args.out, progress=not args.quiet, overwrite=args.overwrite)
    if args.json:
        print_json(record)
    else:
        print(
            f"trained the utility map on {record['timesteps']} agent-steps ({record['iterations']} iterations) in "
            f"{record['cpu_s']:.1f} CPU-s; training-list utility gain {record['final_eval_utility_gain']:+.1%}"
        )
        model = args.out / "model.npz"
        print(f"wrote {model}, curve.csv, curve.png (evaluate with --policy ppo:{model})")
    return 0
