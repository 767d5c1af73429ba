"""MAPPO on TorchRL for ``cv2x/Cooperative-v0`` (``cv2x-marl train`` with ``algo: mappo``; docs/rl.md).

Multi-agent PPO with a centralised critic (Yu et al., NeurIPS 2022): one actor shared by every vehicle reads
the vehicle's own observation; the critic reads the env's global ``state()`` (:mod:`cv2x_marl.policies.mappo_nets`).
The env rewards every vehicle with the team objective, so the critic gives one value per env step and every
agent of that step shares its advantage.

One iteration:

1. **Collect** one episode of each of the K copies (``copies``), ``T = env.max_cycles`` steps each: the episode
   seed of copy k is drawn by its own generator from the protocol's first ``env.start_pool`` training seeds
   (:func:`cv2x_marl.env.seeds.training_pool`; never a held-out seed). The actor (TorchRL's
   ``ProbabilisticActor`` with a ``TanhNormal``) samples every agent's action and its log-probability.
2. **GAE** (Schulman et al. 2016) with TorchRL's ``generalized_advantage_estimate`` on the critic's values
   ``V(s_0 .. s_T)`` [K, T, 1]: ``delta_t = r_t + gamma V(s_{t+1}) - V(s_t)``, ``A_t = sum_l (gamma lambda)^l
   delta_{t+l}``. Episodes end only by the time limit: the last step is ``done`` but not ``terminated``, so the
   value of the final state is bootstrapped (as SB3 does with ``TimeLimit.truncated``).
3. **Update**: ``n_epochs`` passes over the K T steps in shuffled mini-batches of ``minibatch_steps`` steps (all
   agents of a step together), TorchRL's ``ClipPPOLoss``: ``-min(rho A, clip(rho, 1 - eps, 1 + eps) A)`` with
   ``rho`` the agent's probability ratio and ``A`` normalised over the mini-batch, plus ``vf_coef`` times the
   squared error of ``V(s_t)`` against the GAE target (plus the entropy term when ``ent_coef`` > 0); Adam,
   gradients clipped to ``max_grad_norm``.

Seeding: one seed, named streams spawned from ``SeedSequence(seed)`` in the order of :data:`STREAMS`: ``torch``
(the networks' initial weights and the action samples, drawn under ``torch.random.fork_rng`` so the global
torch state is left as it was), ``episodes`` (one generator per copy, spawned from it) and ``minibatches``
(the shuffling). The same seed gives the same learning curve and identical parameters (tested).

The run folder: ``train_config.json`` (``algo: mappo``, the configuration, seed, timesteps), ``model.pt``
(the actor's and the critic's weights and the keyword arguments that rebuild them: ``--policy ppo:PATH``
loads it, :class:`cv2x_marl.policies.mappo.MappoPolicy`), ``eval.csv`` (the learning curve: MAPPO
deterministic and GBMU on ``eval_episodes`` fixed episodes from ``eval_seed``), ``record.json`` and ``run.json``.
"""

from __future__ import annotations

import copy
import hashlib
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from gymnasium import spaces

from cv2x_marl.checks import is_int
from cv2x_marl.env.mobility_env import check_copies
from cv2x_marl.env.registry import make_parallel_env
from cv2x_marl.env.seeds import training_pool
from cv2x_marl.experiments.evaluate import evaluate
from cv2x_marl.extras import require
from cv2x_marl.io import atomic_write, write_json
from cv2x_marl.policies.base import BatchPolicy
from cv2x_marl.policies.mappo import MODEL_FORMAT
from cv2x_marl.rl.errors import TrainError
from cv2x_marl.rl.mappo_config import GROUP, MappoConfig, load_mappo_config
from cv2x_marl.rl.ppo_step import LOSS_KEYS, ppo_minibatch_step
from cv2x_marl.rl.train import StopRequest, TrainingInterrupted, check_resume_config, run_settings, write_eval_rows
from cv2x_marl.runs import RunFolder

#: the named random streams of a run, spawned from ``SeedSequence(seed)`` in this order
STREAMS = ("torch", "episodes", "minibatches")
#: the ``format`` of a MAPPO checkpoint (``checkpoints/mappo_<iteration>.pt``)
CHECKPOINT_FORMAT = "cv2x_marl.mappo_checkpoint"


def checkpoint_path(run_dir: Path, iteration: int) -> Path:
    """``run_dir/checkpoints/mappo_<iteration>.pt``."""
    return Path(run_dir) / "checkpoints" / f"mappo_{int(iteration)}.pt"


def latest_checkpoint(run_dir: Path) -> Path | None:
    """The MAPPO checkpoint with the most iterations in ``run_dir/checkpoints`` (None when there is none)."""
    found = [
        (int(p.stem.split("_")[1]), p)
        for p in (Path(run_dir) / "checkpoints").glob("mappo_*.pt")
        if p.stem.split("_")[1].isdigit()
    ]
    return max(found)[1] if found else None


def streams(seed: int, copies: int) -> tuple[int, list[np.random.Generator], np.random.Generator]:
    """The run's streams (module docstring): the torch seed, K episode generators, the mini-batch generator."""
    torch_ss, episodes_ss, batches_ss = np.random.SeedSequence(int(seed)).spawn(len(STREAMS))
    torch_seed = int(torch_ss.generate_state(1, dtype=np.uint64)[0] % (2**63 - 1))
    return torch_seed, [np.random.default_rng(s) for s in episodes_ss.spawn(copies)], np.random.default_rng(batches_ss)


def eval_env_options(cfg: MappoConfig) -> dict[str, Any]:
    """The env arguments of the evaluation episodes: the training ones without the start pool (seeds given)."""
    return {k: v for k, v in cfg.env.items() if k != "start_pool"}


class Mappo:
    """The envs, networks, TorchRL loss and optimiser of one run (built by :func:`build_mappo`)."""

    def __init__(self, cfg: MappoConfig, seed: int) -> None:
        import torch
        from tensordict.nn import TensorDictModule
        from torch import nn
        from torchrl.modules import ProbabilisticActor, TanhNormal
        from torchrl.objectives import ClipPPOLoss

        from cv2x_marl.policies.encoders import layout_spec
        from cv2x_marl.policies.mappo_nets import SharedActor, StateCritic

        self.cfg = cfg
        try:
            first = make_parallel_env(cfg.env_id, **cfg.env)
            check_copies(first, cfg.copies)
        except (ValueError, TypeError) as exc:
            raise TrainError(f"train.env of {cfg.env_id}: {exc}") from exc
        self.envs = [first, *(make_parallel_env(cfg.env_id, **cfg.env) for _ in range(cfg.copies - 1))]
        self.agents = list(first.possible_agents)
        self.n_agents = len(self.agents)
        self.steps = int(first.max_cycles)
        self.pool = [int(s) for s in training_pool(int(cfg.env["start_pool"]))]
        self.obs_size = int(first.observation_space(self.agents[0]).shape[0])
        self.state_size = int(first.state_space.shape[0])
        torch_seed, self.episode_rngs, self.batch_rng = streams(seed, cfg.copies)
        m = cfg.mappo
        self.actor: Any
        self.critic: Any
        self.discrete = isinstance(first.action_space(self.agents[0]), spaces.Discrete)
        #: the vehicles decide in turns (``cv2x/Cooperative-v1``): collection samples subframe by subframe
        self.turns = first.options.decision_order == "subframe"
        if self.turns and [first.agent_index[a] for a in self.agents] != list(range(self.n_agents)):
            raise TrainError(f"{cfg.env_id}: the agents must be the vehicles in index order to act in turns")
        #: the masked path's list length, reward and critic inputs (:mod:`cv2x_marl.rl.mappo_masked`)
        self.n_actions, self.team, self.critic_kind = 0, True, "state"
        if self.discrete:  # masked choices (cv2x/Resource-v0): rl.mappo_masked
            from cv2x_marl.rl.mappo_masked import build_masked

            build_masked(self, first, torch_seed)
            return
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(torch_seed)
            self.actor = SharedActor(
                self.obs_size,
                2,
                m.actor_net,
                m.encoder,
                m.encoder_units,
                layout_spec(first.layout) if m.encoder != "mlp" else None,
                m.log_std_init,
            )
            self.critic = StateCritic(self.state_size, m.critic_net)
            self.torch_state = torch.random.get_rng_state()
        n_agents = self.n_agents
        critic = self.critic

        class PerAgent(nn.Module):
            """The critic's value of the step, repeated for each agent [..., N, 1] (the team reward)."""

            def __init__(self) -> None:
                super().__init__()
                self.critic = critic

            def forward(self, state: torch.Tensor) -> torch.Tensor:
                v = self.critic(state).unsqueeze(-2)
                return v.expand(*v.shape[:-2], n_agents, 1)

        self.policy = ProbabilisticActor(
            TensorDictModule(self.actor, in_keys=[(GROUP, "observation")], out_keys=[(GROUP, "loc"), (GROUP, "scale")]),
            in_keys=[(GROUP, "loc"), (GROUP, "scale")],
            out_keys=[(GROUP, "action")],
            distribution_class=TanhNormal,
            distribution_kwargs={"low": -1.0, "high": 1.0},
            return_log_prob=True,
            log_prob_key=(GROUP, "sample_log_prob"),
        )
        value = TensorDictModule(PerAgent(), in_keys=["state"], out_keys=[(GROUP, "state_value")])
        self.loss = ClipPPOLoss(
            self.policy,
            value,
            clip_epsilon=m.clip_range,
            entropy_bonus=m.ent_coef > 0,
            entropy_coeff=m.ent_coef if m.ent_coef > 0 else None,
            critic_coeff=m.vf_coef,
            loss_critic_type="l2",
            normalize_advantage=True,
            normalize_advantage_exclude_dims=(-2,),  # per agent: the same statistics (one shared advantage)
        )
        self.loss.set_keys(
            action=(GROUP, "action"),
            sample_log_prob=(GROUP, "sample_log_prob"),
            value=(GROUP, "state_value"),
            advantage=(GROUP, "advantage"),
            value_target=(GROUP, "value_target"),
        )
        self.params = [*self.actor.parameters(), *self.critic.parameters()]
        self.optim = torch.optim.Adam(self.params, lr=m.learning_rate, eps=1e-5)

    def agent_steps(self) -> int:
        """Agent-steps of one iteration: K copies x T steps x N agents."""
        return self.cfg.copies * self.steps * self.n_agents

    def collect(self, stop: Any = None) -> dict[str, Any] | None:
        """One episode of every copy (module docstring, step 1): arrays [T, K, ...] and the last states [K, S].

        ``stop``: a :class:`cv2x_marl.rl.train.StopRequest`; once it holds a signal, the collection is given up at
        the next step and None returned (the random streams have moved on: :meth:`rng_state` taken before the
        call is the state to save)."""
        if self.discrete:
            from cv2x_marl.rl.mappo_masked import collect_masked

            return collect_masked(self, stop)
        import torch
        from tensordict import TensorDict
        from torchrl.envs.utils import ExplorationType, set_exploration_type

        k_, t_, n_ = self.cfg.copies, self.steps, self.n_agents
        obs = np.empty((t_, k_, n_, self.obs_size), np.float32)
        state = np.empty((t_ + 1, k_, self.state_size), np.float32)
        act = np.empty((t_, k_, n_, 2), np.float32)
        logp = np.empty((t_, k_, n_), np.float32)
        rew = np.empty((t_, k_), np.float32)
        current = []
        for k, env in enumerate(self.envs):
            o, _ = env.reset(seed=self.pool[int(self.episode_rngs[k].integers(len(self.pool)))])
            current.append(o)
            state[0, k] = env.state()
        with torch.random.fork_rng(devices=[]), torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
            torch.random.set_rng_state(self.torch_state)
            for t in range(t_):
                if stop is not None and stop.signal is not None:
                    return None
                if self.turns:  # Cooperative-v1: each copy's vehicles sample at their turns, subframe by subframe
                    for k, env in enumerate(self.envs):
                        obs[t, k], act[t, k], logp[t, k] = self._sample_in_turns(env)
                else:
                    obs[t] = [[o[a] for a in self.agents] for o in current]
                    td = TensorDict({GROUP: TensorDict({"observation": torch.from_numpy(obs[t])}, [k_, n_])}, [k_])
                    self.policy(td)
                    act[t] = td[GROUP, "action"].numpy()
                    logp[t] = td[GROUP, "sample_log_prob"].numpy()
                for k, env in enumerate(self.envs):
                    o, r, term, trunc, _ = env.step(dict(zip(self.agents, act[t, k], strict=True)))
                    rew[t, k] = np.mean([r[a] for a in self.agents])  # the team's: equal for every agent
                    state[t + 1, k] = env.state()
                    current[k] = o
                    if any(term.values()) or (t < t_ - 1 and any(trunc.values())):
                        raise RuntimeError(
                            f"{self.cfg.env_id} ended an episode before max_cycles; MAPPO expects T steps"
                        )
            self.torch_state = torch.random.get_rng_state()
        return {"obs": obs, "state": state, "action": act, "log_prob": logp, "reward": rew}

    def _sample_in_turns(self, env: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One period of a turn-order env (``cv2x/Cooperative-v1``): the vehicles of each subframe sample their
        actions on their observations at their turn (:func:`~cv2x_marl.env.turns.decide_in_turns`), in one actor
        call per subframe; returns the observations [N, D], actions [N, 2] and log-probabilities [N]."""
        import torch
        from tensordict import TensorDict

        from cv2x_marl.env.turns import decide_in_turns

        logp = np.zeros(self.n_agents, np.float32)
        act = np.zeros((self.n_agents, 2), np.float32)

        def decide(rows: np.ndarray, o: np.ndarray) -> np.ndarray:
            td = TensorDict({GROUP: TensorDict({"observation": torch.from_numpy(o)}, [rows.size])}, [])
            self.policy(td)
            act[rows] = td[GROUP, "action"].numpy()
            logp[rows] = td[GROUP, "sample_log_prob"].numpy()
            return act[rows]

        _, turn_obs = decide_in_turns(env, decide)
        return turn_obs, act, logp

    def update(self, batch: dict[str, Any]) -> dict[str, float]:
        """GAE and the clipped PPO epochs (module docstring, steps 2-3); the mean losses."""
        if self.discrete:
            from cv2x_marl.rl.mappo_masked import update_masked

            return update_masked(self, batch)
        import torch
        from tensordict import TensorDict
        from torchrl.objectives.value.functional import generalized_advantage_estimate

        m = self.cfg.mappo
        t_, k_, n_ = batch["obs"].shape[:3]
        states = torch.from_numpy(batch["state"]).transpose(0, 1)  # [K, T + 1, S]
        with torch.no_grad():
            values = self.critic(states)  # [K, T + 1, 1]
            done = torch.zeros(k_, t_, 1, dtype=torch.bool)
            done[:, -1] = True  # the time limit: done, not terminated (the last value is bootstrapped)
            adv, target = generalized_advantage_estimate(
                m.gamma,
                m.gae_lambda,
                values[:, :-1],
                values[:, 1:],
                torch.from_numpy(batch["reward"]).transpose(0, 1).unsqueeze(-1),
                done,
                torch.zeros_like(done),
                time_dim=-2,
            )
        b = k_ * t_

        def flat(x: np.ndarray) -> torch.Tensor:  # [T, K, ...] -> [K T, ...], copy-major like the GAE tensors
            return torch.from_numpy(np.ascontiguousarray(np.swapaxes(x, 0, 1))).reshape(b, *x.shape[2:])

        agents = TensorDict(
            {
                "observation": flat(batch["obs"]),
                "action": flat(batch["action"]),
                "sample_log_prob": flat(batch["log_prob"]),
                "advantage": adv.reshape(b, 1, 1).expand(b, n_, 1).clone(),
                "value_target": target.reshape(b, 1, 1).expand(b, n_, 1).clone(),
            },
            [b, n_],
        )
        data = TensorDict({GROUP: agents, "state": states[:, :-1].reshape(b, -1)}, [b])
        sums = dict.fromkeys(LOSS_KEYS, 0.0)
        count = 0
        with torch.random.fork_rng(devices=[]):
            torch.random.set_rng_state(self.torch_state)
            for _ in range(m.n_epochs):
                order = torch.from_numpy(self.batch_rng.permutation(b))
                for start in range(0, b, m.minibatch_steps):
                    idx = order[start : start + m.minibatch_steps]
                    if idx.numel() < 2:  # the advantage is normalised over the mini-batch
                        continue
                    ppo_minibatch_step(self.loss, data[idx], self.optim, self.params, m.max_grad_norm, sums)
                    count += 1
            self.torch_state = torch.random.get_rng_state()
        return {k: v / max(count, 1) for k, v in sums.items()}

    def act_fn(self) -> Any:
        """The deterministic actor as a :class:`~cv2x_marl.policies.base.BatchPolicy` function (masked actions: the
        most probable valid entry per row, int64)."""
        import torch

        def act(obs: np.ndarray) -> np.ndarray:
            with torch.no_grad():
                return self.actor.deterministic(torch.from_numpy(obs)).numpy()

        return act

    def eval_policy(self) -> Any:
        """The deterministic actor as a policy, one agent's row at a time (what ``model.pt`` loads as)."""
        if self.discrete:
            from cv2x_marl.policies.mappo import MaskedChoicePolicy

            return MaskedChoicePolicy(self.actor, "mappo")
        policy = BatchPolicy(self.act_fn(), "mappo")
        if self.turns:  # it acts at its turns in the evaluation env too
            from cv2x_marl.policies.sequential import InTurns

            return InTurns.deferred(policy)
        return policy

    def model(self) -> dict[str, Any]:
        """What ``model.pt`` holds (plain values and tensors: ``torch.load(weights_only=True)`` reads it)."""
        if self.discrete:
            return {
                "format": MODEL_FORMAT,
                "version": 1,
                "env_id": self.cfg.env_id,
                "actor_kind": "categorical",
                "actor_kwargs": self.actor.spec(),
                "actor_state": self.actor.state_dict(),
                "critic_kind": self.critic_kind,
                "critic_kwargs": {"n_in": int(self.critic.n_in), "net": list(self.cfg.mappo.critic_net)},
                "critic_state": self.critic.state_dict(),
            }
        return {
            "format": MODEL_FORMAT,
            "version": 1,
            "env_id": self.cfg.env_id,
            "actor_kwargs": self.actor.spec(),
            "actor_state": self.actor.state_dict(),
            "critic_kwargs": {"state_size": self.state_size, "net": list(self.cfg.mappo.critic_net)},
            "critic_state": self.critic.state_dict(),
        }

    def rng_state(self) -> dict[str, Any]:
        """A copy of the run's random streams now (torch, the K episode generators, the mini-batch one)."""
        return {
            "torch": self.torch_state.clone(),
            "episodes": [copy.deepcopy(g.bit_generator.state) for g in self.episode_rngs],
            "minibatches": copy.deepcopy(self.batch_rng.bit_generator.state),
        }

    def training_state(self, iteration: int, rows: list[dict[str, Any]], rngs: dict[str, Any]) -> dict[str, Any]:
        """A checkpoint: everything the next iteration reads (networks, Adam's moments, the streams ``rngs``),
        the iterations done and the learning-curve rows so far (``torch.load(weights_only=True)`` reads it)."""
        return {
            "format": CHECKPOINT_FORMAT,
            "iteration": int(iteration),
            "actor_state": self.actor.state_dict(),
            "critic_state": self.critic.state_dict(),
            "optim_state": self.optim.state_dict(),
            "rng": rngs,
            "rows": [dict(r) for r in rows],
        }

    def load_training_state(self, data: dict[str, Any]) -> tuple[int, list[dict[str, Any]]]:
        """Restore a :meth:`training_state`; returns its iterations done and its learning-curve rows."""
        self.actor.load_state_dict(data["actor_state"])
        self.critic.load_state_dict(data["critic_state"])
        self.optim.load_state_dict(data["optim_state"])
        rng = data["rng"]
        self.torch_state = rng["torch"].clone()
        for g, state in zip(self.episode_rngs, rng["episodes"], strict=True):
            g.bit_generator.state = state
        self.batch_rng.bit_generator.state = rng["minibatches"]
        return int(data["iteration"]), [dict(r) for r in data["rows"]]

    def digest(self) -> str:
        """A short hash of the actor's and the critic's parameters (to compare two runs)."""
        h = hashlib.sha256()
        for module in (self.actor, self.critic):
            for _, v in sorted(module.state_dict().items()):
                h.update(np.ascontiguousarray(v.detach().numpy()).tobytes())
        return h.hexdigest()[:16]

    def close(self) -> None:
        for env in self.envs:
            env.close()


def build_mappo(cfg: MappoConfig, seed: int) -> Mappo:
    """The run's envs and networks, before any folder is touched (bad env arguments raise :class:`TrainError`)."""
    for module in ("torch", "tensordict", "torchrl"):
        require(module, "cv2x-marl train with algo: mappo")
    if not is_int(seed) or seed < 0:
        raise TrainError(f"--seed must be an integer >= 0, got {seed!r}")
    return Mappo(cfg, int(seed))


def train_mappo(
    cfg: MappoConfig,
    timesteps: int,
    seed: int,
    run_dir: Path,
    progress: bool = True,
    overwrite: bool = False,
    resume: bool = False,
) -> dict[str, Any]:
    """Train (or resume) MAPPO for at least ``timesteps`` agent-steps (whole iterations); write the run folder;
    return the record.

    Checkpoints (:meth:`Mappo.training_state`: networks, Adam's moments, the random streams, the learning
    curve) are written every ``checkpoint_every`` iterations and at the end. SIGINT / SIGTERM stop training at
    the next step (a second signal at once): an iteration whose collection was cut short is not counted (its
    episodes are collected again on resume), one cut during its update is finished; the checkpoint of the
    iterations done is saved and :class:`~cv2x_marl.rl.train.TrainingInterrupted` raised. ``resume`` continues
    from the newest checkpoint: the parameters, the learning curve and the checkpoints then equal those of an
    uninterrupted run (tested).

    Raises:
        TrainError: bad arguments or configuration, a resume whose configuration differs or that has nothing
            left to train (checked before ``run_dir`` is touched).
        cv2x_marl.runs.RunFolderError: the folder is in use, or not empty without ``overwrite`` or ``resume``.
    """
    import torch

    if not is_int(timesteps) or timesteps < 1:
        raise TrainError(f"--timesteps must be an integer >= 1, got {timesteps!r}")
    resolved = {**cfg.to_dict(), "seed": seed, "timesteps": timesteps}
    if resume:
        check_resume_config(run_dir, resolved)
    torch.set_num_threads(1)
    run = build_mappo(cfg, seed)
    try:
        iterations = math.ceil(timesteps / run.agent_steps())
        ckpt = latest_checkpoint(run_dir) if resume else None
        state = _read_checkpoint(ckpt) if ckpt is not None else None
        if state is not None and int(state["iteration"]) >= iterations:
            raise TrainError(
                f"--resume: {run_dir} already has {int(state['iteration']) * run.agent_steps()} agent-steps "
                f"(>= --timesteps {timesteps}); ask for more steps to continue it (its model.pt is kept as it is)"
            )
        params = {"env_id": cfg.env_id, "seed": seed, "timesteps": timesteps, "algo": "mappo"}
        with RunFolder(run_dir, "train", overwrite=overwrite, resume=resume, keep_on_failure=True, parameters=params):
            return _train_mappo(run, cfg, resolved, iterations, Path(run_dir), state, progress)
    finally:
        run.close()


def _read_checkpoint(path: Path) -> dict[str, Any]:
    import torch

    try:
        data = torch.load(path, weights_only=True)
    except Exception as exc:  # any load failure is reported with the file name
        raise TrainError(f"--resume: cannot read the checkpoint {path}: {type(exc).__name__}: {exc}") from exc
    if not isinstance(data, dict) or data.get("format") != CHECKPOINT_FORMAT:
        raise TrainError(f"--resume: {path} is not a MAPPO checkpoint of cv2x-marl train")
    return data


def _train_mappo(
    run: Mappo,
    cfg: MappoConfig,
    resolved: dict[str, Any],
    iterations: int,
    run_dir: Path,
    state: dict[str, Any] | None,
    progress: bool,
) -> dict[str, Any]:
    import torch

    write_json(run_dir / "train_config.json", resolved)
    done, rows = run.load_training_state(state) if state is not None else (0, [])
    if state is not None:  # the learning curve goes back to the checkpoint; later checkpoints go with it
        write_eval_rows(run_dir / "eval.csv", rows)
        for path in (run_dir / "checkpoints").glob("mappo_*.pt"):
            if path.stem.split("_")[1].isdigit() and int(path.stem.split("_")[1]) > done:
                path.unlink()

    def save(iteration: int, rngs: dict[str, Any]) -> None:
        snapshot = run.training_state(iteration, rows, rngs)
        atomic_write(checkpoint_path(run_dir, iteration), lambda tmp: torch.save(snapshot, tmp))

    cpu0 = time.process_time()
    eval_env = eval_env_options(cfg)
    n_ep, e_seed = cfg.eval_episodes, cfg.eval_seed
    # the script each learning-curve row is compared with: gbmu moves; a resource choice has its sensing-aware script
    base = "farthest" if run.discrete else "gbmu"
    gbmu = evaluate(cfg.env_id, base, n_ep, e_seed, None, eval_env, progress=False)
    t0 = time.perf_counter()
    before, batch = run.rng_state(), None
    with StopRequest() as stop:
        for it in range(done + 1, iterations + 1):
            before = run.rng_state()
            batch = run.collect(stop)
            if batch is None:  # cut short: this iteration is not counted
                break
            losses = run.update(batch)
            if it % cfg.eval_every == 0 or it == iterations:
                res = evaluate(cfg.env_id, run.eval_policy(), n_ep, e_seed, None, eval_env, progress=False)
                rows.append(
                    {
                        "iteration": it,
                        "timesteps": it * run.agent_steps(),
                        "train_mean_return": float(batch["reward"].sum(0).mean()),
                        "mappo_mean_utility_gain": res["mean_utility_gain"],
                        "mappo_mean_prr_gain": res["mean_prr_gain"],
                        "mappo_mean_return": res["mean_return"],
                        f"{base}_mean_utility_gain": gbmu["mean_utility_gain"],
                        **losses,
                    }
                )
                if run.discrete:  # the process's CPU seconds so far (env copies and evaluations included)
                    rows[-1]["cpu_s"] = time.process_time() - cpu0
                write_eval_rows(run_dir / "eval.csv", rows)
                if progress:
                    r = rows[-1]
                    print(
                        f"iteration {it}/{iterations}: team utility gain {r['mappo_mean_utility_gain']:+.1%} "
                        f"({base} {r[f'{base}_mean_utility_gain']:+.1%})",
                        file=sys.stderr,
                    )
            done = it
            if it % cfg.checkpoint_every == 0 or it == iterations:
                save(it, run.rng_state())
            if stop.signal is not None:
                break
        wall = time.perf_counter() - t0
        if stop.signal is not None:
            if not checkpoint_path(run_dir, done).exists():
                save(done, before if batch is None else run.rng_state())
            cut = " (the iteration being collected is not counted)" if batch is None else ""
            raise TrainingInterrupted(
                f"training stopped after {done} of {iterations} iterations ({done * run.agent_steps()} agent-steps)"
                f"{cut}; checkpoint saved in {run_dir / 'checkpoints'} (continue with --resume)"
            )
    atomic_write(run_dir / "model.pt", lambda tmp: torch.save(run.model(), tmp))
    start = int(state["iteration"]) if state is not None else 0
    record = {
        "algo": "mappo",
        "env_id": cfg.env_id,
        "seed": resolved["seed"],
        "timesteps": iterations * run.agent_steps(),
        "iterations": iterations,
        "resumed_from": start * run.agent_steps() if state is not None else None,
        "wall_s": wall,
        "steps_per_s": (iterations - start) * run.agent_steps() / wall if wall > 0 else float("nan"),
        "final_eval": {k: v for k, v in rows[-1].items() if k.startswith("mappo_")},
        "parameters_digest": run.digest(),
        "torch": torch.__version__,
    }
    write_json(run_dir / "record.json", record)
    return record


def cli_train(args: Any, default_timesteps: int, print_json: Any) -> int:
    """``cv2x-marl train`` for a MAPPO config (``--algo mappo`` or ``algo: mappo``): ``--config``, ``--env``,
    ``--copies``, ``--timesteps`` and ``--seed`` (else the file's, as for PPO), ``--out``, ``--overwrite``."""
    cfg = load_mappo_config(args.config, env_id=args.env, copies=args.copies)
    from_file = run_settings(args.config)  # a run folder's train_config.json names its seed and length
    timesteps = args.timesteps if args.timesteps is not None else from_file.get("timesteps", default_timesteps)
    seed = args.seed if args.seed is not None else from_file.get("seed", 0)
    record = train_mappo(
        cfg, timesteps, seed, args.out, progress=not args.quiet, overwrite=args.overwrite, resume=args.resume
    )
    if args.json:
        print_json(record)
    else:
        fe = record["final_eval"]
        print(
            f"trained MAPPO {record['timesteps']} agent-steps ({record['iterations']} iterations) in "
            f"{record['wall_s']:.1f} s; eval: team utility gain {fe['mappo_mean_utility_gain']:+.1%}, "
            f"PRR gain {fe['mappo_mean_prr_gain']:+.1%}"
        )
        print(
            f"wrote {args.out / 'model.pt'}, record.json, eval.csv (evaluate with --policy ppo:{args.out / 'model.pt'})"
        )
    return 0
