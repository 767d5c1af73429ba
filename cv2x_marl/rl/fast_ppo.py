"""PPO on the batched vector env with TorchRL's loss (``ppo.backend: torchrl``; docs/rl.md).

The same algorithm and network as the SB3 path (:mod:`cv2x_marl.rl.train`) for the ``SingleMover`` ids, with
the Python work per env step cut to one vector call. One iteration:

1. **Collect** ``n_steps`` steps of the K copies (``copies``) of
   :class:`~cv2x_marl.env.vector.SingleMoverVectorEnv` (all copies in one compiled call, ``SameStep``
   autoreset): per step one forward pass of the actor on the observations [K, D] (torch tensors), actions
   ``mu + sigma * eps`` with ``eps`` drawn from the run's own ``torch.Generator``, their log-probability
   (TorchRL's ``IndependentNormal``), and the actions clipped to the Box [-1, 1]^2 for the env (SB3's
   ``clip_actions``; the unclipped sample is what the loss sees, as in SB3). A copy whose episode ended
   (by its time limit, ``max_cycles``) is reset in the same call; its last observation (``final_obs``) is
   kept as the step's next observation, so its value is bootstrapped (SB3's ``TimeLimit.truncated``).
2. **GAE** (Schulman et al. 2016): TorchRL's :class:`~torchrl.objectives.value.GAE` on the rollout
   [K, n_steps] with ``("next", "done")`` set at a time limit and ``("next", "terminated")`` never: ``delta_t =
   r_t + gamma V(s'_t) - V(s_t)``, ``A_t = sum_l (gamma lambda)^l delta_{t+l}`` within an episode, the value
   target ``A_t + V(s_t)``.
3. **Update**: ``n_epochs`` passes over the K n_steps samples in shuffled mini-batches of ``batch_size``
   (a last mini-batch of one sample is skipped: its advantage cannot be normalised), TorchRL's
   :class:`~torchrl.objectives.ClipPPOLoss`: ``-min(rho A, clip(rho, 1 - eps, 1 + eps) A)`` with ``A``
   normalised over the mini-batch, plus ``vf_coef`` times the squared error of ``V(s_t)`` against the target
   (plus ``-ent_coef`` times the entropy when ``ent_coef`` > 0); Adam (eps 1e-5, as SB3; torch's fused
   kernel), gradients clipped to ``max_grad_norm``. The shared features run once per mini-batch: the actor
   writes them into the mini-batch and the critic's head reads them (TorchRL's documented single-call layout).

The network is :class:`cv2x_marl.policies.ppo_nets.ActorCritic` (SB3's ``MlpPolicy`` layout and initialisation
for ``net_arch``, ``encoder``, ``encoder_units``, ``log_std_init``).

Seeding: one seed, named streams spawned from ``SeedSequence(seed)`` in the order of :data:`STREAMS`: ``init``
(the initial weights, a ``torch.Generator``), ``actions`` (the action noise, a ``torch.Generator``),
``episodes`` (one numpy generator per copy, spawned from it: each copy's episode seeds, drawn from the
protocol's training seeds with the env option ``start_pool``) and ``minibatches`` (the shuffling, a
``torch.Generator``). The global torch and numpy generators are left as they were (the network is built on a
forked copy of torch's, :class:`~cv2x_marl.policies.ppo_nets.ActorCritic`): the same seed gives the same learning
curve and identical parameters (tested).

The run folder: ``train_config.json`` (the configuration, seed, timesteps), ``model.pt`` (the network's
keyword arguments and weights: ``--policy ppo:PATH`` loads it, :class:`cv2x_marl.policies.torch_ppo.
TorchPpoPolicy`), ``curve.csv`` (one row per iteration: agent-steps, process CPU seconds, wall seconds, the
mean return of the last 100 training episodes, the losses), ``curve.png`` (that return against CPU seconds),
``eval.csv`` (the deterministic policy and GBMU on ``eval_episodes`` fixed episodes every ``eval_every``
agent-steps, as the SB3 path), ``record.json`` and ``run.json``.
"""

from __future__ import annotations

import csv
import hashlib
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from cv2x_marl.checks import is_int
from cv2x_marl.experiments.evaluate import evaluate
from cv2x_marl.extras import require
from cv2x_marl.io import atomic_write, write_json
from cv2x_marl.policies.base import BatchPolicy
from cv2x_marl.policies.torch_ppo import model_contents
from cv2x_marl.rl.errors import TrainError
from cv2x_marl.rl.ppo_step import LOSS_KEYS, ppo_minibatch_step
from cv2x_marl.rl.train_checks import check_training_config
from cv2x_marl.rl.train_config import TrainConfig
from cv2x_marl.runs import RunFolder

#: the named random streams of a run, spawned from ``SeedSequence(seed)`` in this order
STREAMS = ("init", "actions", "episodes", "minibatches")
#: the finished training episodes ``curve.csv``'s ``train_mean_return`` averages (SB3's ``ep_rew_mean`` keeps 100)
RETURN_WINDOW = 100
#: the columns of ``curve.csv``
CURVE_COLUMNS = (
    "iteration",
    "agent_steps",
    "cpu_s",
    "wall_s",
    "episodes",
    "train_mean_return",
    "loss_objective",
    "loss_critic",
    "loss_entropy",
)


def torch_seed(ss: np.random.SeedSequence) -> int:
    """A ``torch.Generator`` seed (an int in [0, 2^63 - 1)) from a seed sequence."""
    return int(ss.generate_state(1, dtype=np.uint64)[0] % (2**63 - 1))


class FastPpo:
    """The vector env, network, TorchRL loss and optimiser of one run (module docstring).

    Args:
        cfg: a training configuration with ``ppo.backend: torchrl`` (or any: the backend is not read here).
        seed: the run's one seed.

    Raises:
        TrainError: env arguments the env refuses.
    """

    def __init__(self, cfg: TrainConfig, seed: int) -> None:
        import torch
        from tensordict.nn import TensorDictModule, TensorDictSequential
        from torchrl.modules import IndependentNormal, ProbabilisticActor
        from torchrl.objectives import ClipPPOLoss
        from torchrl.objectives.value import GAE

        from cv2x_marl.env.vector import SingleMoverVectorEnv
        from cv2x_marl.policies.encoders import layout_spec
        from cv2x_marl.policies.ppo_nets import ActorCritic

        self.cfg = cfg
        p = cfg.ppo
        try:
            self.vec = SingleMoverVectorEnv(cfg.copies, autoreset_mode="SameStep", env_id=cfg.env_id, **cfg.env)
        except (ValueError, TypeError) as exc:
            raise TrainError(f"train.env of {cfg.env_id}: {exc}") from exc
        init_ss, actions_ss, episodes_ss, batches_ss = np.random.SeedSequence(int(seed)).spawn(len(STREAMS))
        for env, ss in zip(self.vec.envs, episodes_ss.spawn(cfg.copies), strict=True):
            env.np_random = np.random.default_rng(ss)  # each copy's episode seeds (Gymnasium's own generator)
        self.action_gen = torch.Generator().manual_seed(torch_seed(actions_ss))
        self.batch_gen = torch.Generator().manual_seed(torch_seed(batches_ss))
        par = self.vec.envs[0].par
        self.obs_size = int(np.prod(par.observation_space(par.possible_agents[0]).shape))
        self.net = ActorCritic(
            self.obs_size,
            int(np.prod(par.action_space(par.possible_agents[0]).shape or (1,))),
            p.net_arch,
            p.encoder,
            p.encoder_units,
            layout_spec(par.layout) if p.encoder != "mlp" else None,
            p.log_std_init,
        )
        self.net.init_weights(torch.Generator().manual_seed(torch_seed(init_ss)))
        net = self.net

        class Features(torch.nn.Module):
            def forward(self, obs: torch.Tensor) -> torch.Tensor:
                return net.features(obs)

        class ActorHead(torch.nn.Module):
            def forward(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
                return net.actor_head(features)

        class CriticHead(torch.nn.Module):
            def forward(self, features: torch.Tensor) -> torch.Tensor:
                return net.critic_head(features)

        class Critic(torch.nn.Module):
            def forward(self, obs: torch.Tensor) -> torch.Tensor:
                return net.value(obs)

        # the loss's actor writes the shared features ("hidden") into the mini-batch; the critic's head reads them
        self.actor = ProbabilisticActor(
            TensorDictSequential(
                TensorDictModule(Features(), in_keys=["observation"], out_keys=["hidden"]),
                TensorDictModule(ActorHead(), in_keys=["hidden"], out_keys=["loc", "scale"]),
            ),
            in_keys=["loc", "scale"],
            out_keys=["action"],
            distribution_class=IndependentNormal,
            return_log_prob=False,
        )
        critic_head = TensorDictModule(CriticHead(), in_keys=["hidden"], out_keys=["state_value"])
        self.loss = ClipPPOLoss(
            self.actor,
            critic_head,
            clip_epsilon=p.clip_range,
            entropy_bonus=p.ent_coef > 0,
            entropy_coeff=p.ent_coef if p.ent_coef > 0 else None,
            critic_coeff=p.vf_coef,
            loss_critic_type="l2",
            normalize_advantage=True,
            functional=False,
        )
        self.loss.set_keys(sample_log_prob="sample_log_prob")
        self.critic = TensorDictModule(Critic(), in_keys=["observation"], out_keys=["state_value"])
        # the values come with the rollout (value_network None): GAE's own pass over both observations is skipped
        self.gae = GAE(gamma=p.gamma, lmbda=p.gae_lambda, value_network=None, average_gae=False)
        # SB3's Adam settings; the fused kernel (one pass over every parameter) is the same update, cheaper on CPU
        self.optim = torch.optim.Adam(self.net.parameters(), lr=p.learning_rate, eps=1e-5, fused=True)
        k, t = cfg.copies, p.n_steps
        self.obs_buf = np.zeros((k, t, self.obs_size), np.float32)
        self.next_buf = np.zeros((k, t, self.obs_size), np.float32)
        self.act_buf = np.zeros((k, t, 2), np.float32)
        self.logp_buf = np.zeros((k, t), np.float32)
        self.rew_buf = np.zeros((k, t), np.float32)
        self.value_buf = np.zeros((k, t), np.float32)
        self.next_value_buf = np.zeros((k, t), np.float32)
        self.done_buf = np.zeros((k, t), bool)
        self.obs: np.ndarray | None = None
        self.episode_return = np.zeros(k)
        #: the returns of the finished training episodes, in the order they ended
        self.returns: list[float] = []
        self.agent_steps = 0

    def rollout_steps(self) -> int:
        """Agent-steps of one iteration: ``n_steps`` x copies (one mover each)."""
        return self.cfg.ppo.n_steps * self.cfg.copies

    def collect(self) -> Any:
        """``n_steps`` vector steps (module docstring, step 1) -> the rollout as a TensorDict [K, n_steps]."""
        import torch
        from tensordict import TensorDict

        if self.obs is None:
            self.obs, _ = self.vec.reset()
        obs = self.obs
        for t in range(self.cfg.ppo.n_steps):
            obs_t = torch.from_numpy(obs)
            with torch.no_grad():
                features = self.net.features(obs_t)
                loc, scale = self.net.actor_head(features)
                value = self.net.critic_head(features)
                action = loc + scale * torch.randn(loc.shape, generator=self.action_gen)
                # IndependentNormal's log-probability (the Normal's, summed over the action), unvalidated
                logp = torch.distributions.Normal(loc, scale, validate_args=False).log_prob(action).sum(-1)
            self.obs_buf[:, t] = obs
            self.value_buf[:, t] = value[:, 0].numpy()
            self.act_buf[:, t] = action.numpy()
            self.logp_buf[:, t] = logp.numpy()
            obs, reward, term, trunc, infos = self.vec.step(action.clamp(-1.0, 1.0).numpy())
            done = term | trunc
            self.rew_buf[:, t] = reward
            self.done_buf[:, t] = done
            self.next_buf[:, t] = obs
            self.episode_return += reward
            if done.any():
                ended = np.flatnonzero(done)
                self.next_buf[ended, t] = np.stack([infos["final_obs"][i] for i in ended])
                self.returns.extend(self.episode_return[ended].tolist())
                self.episode_return[ended] = 0.0
        self.obs = obs
        # V(s'_t): the next step's V(s_{t+1}), except where s'_t is a final observation or the rollout's last
        self.next_value_buf[:, :-1] = self.value_buf[:, 1:]
        redo = self.done_buf.copy()
        redo[:, -1] = True
        with torch.no_grad():
            self.next_value_buf[redo] = self.net.value(torch.from_numpy(self.next_buf[redo]))[:, 0].numpy()
        self.agent_steps += self.rollout_steps()
        k, n = self.cfg.copies, self.cfg.ppo.n_steps
        done_t = torch.from_numpy(self.done_buf.copy()).unsqueeze(-1)
        return TensorDict(
            {
                "observation": torch.from_numpy(self.obs_buf.copy()),
                "action": torch.from_numpy(self.act_buf.copy()),
                "sample_log_prob": torch.from_numpy(self.logp_buf.copy()),
                "state_value": torch.from_numpy(self.value_buf.copy()).unsqueeze(-1),
                "next": {
                    "observation": torch.from_numpy(self.next_buf.copy()),
                    "state_value": torch.from_numpy(self.next_value_buf.copy()).unsqueeze(-1),
                    "reward": torch.from_numpy(self.rew_buf.copy()).unsqueeze(-1),
                    "done": done_t,
                    "terminated": torch.zeros_like(done_t),  # episodes end only by their time limit
                },
            },
            batch_size=[k, n],
        )

    def advantages(self, rollout: Any) -> Any:
        """GAE on a rollout (module docstring, step 2): the flat samples [K n_steps] the loss reads."""
        import torch

        with torch.no_grad():
            self.gae(rollout)
        return rollout.select("observation", "action", "sample_log_prob", "advantage", "value_target").reshape(-1)

    def update(self, data: Any) -> dict[str, float]:
        """The clipped PPO epochs on the flat samples ``data`` (module docstring, step 3); the mean losses."""
        import torch

        p = self.cfg.ppo
        n = data.batch_size[0]
        sums = dict.fromkeys(LOSS_KEYS, 0.0)
        count = 0
        params = list(self.net.parameters())
        for _ in range(p.n_epochs):
            order = torch.randperm(n, generator=self.batch_gen)
            for start in range(0, n, p.batch_size):
                idx = order[start : start + p.batch_size]
                if idx.numel() < 2:  # the advantage is normalised over the mini-batch
                    continue
                ppo_minibatch_step(self.loss, data[idx], self.optim, params, p.max_grad_norm, sums)
                count += 1
        return {k: v / max(count, 1) for k, v in sums.items()}

    def iterate(self) -> dict[str, float]:
        """One iteration: collect, GAE, update; the mean losses."""
        return self.update(self.advantages(self.collect()))

    def recent_return(self) -> float:
        """The mean return of the last :data:`RETURN_WINDOW` finished training episodes (NaN before the first)."""
        last = self.returns[-RETURN_WINDOW:]
        return float(np.mean(last)) if last else float("nan")

    def act_fn(self) -> Any:
        """The deterministic actor (``clip(mu, -1, 1)``) as a :class:`~cv2x_marl.policies.base.BatchPolicy` function."""
        import torch

        def act(obs: np.ndarray) -> np.ndarray:
            with torch.no_grad():
                return self.net.deterministic(torch.from_numpy(np.ascontiguousarray(obs))).numpy()

        return act

    def model(self) -> dict[str, Any]:
        """What ``model.pt`` holds (:class:`cv2x_marl.policies.torch_ppo.TorchPpoPolicy` reads it)."""
        return model_contents(self.cfg.env_id, self.net)

    def digest(self) -> str:
        """A short hash of the network's parameters (to compare two runs)."""
        h = hashlib.sha256()
        for _, v in sorted(self.net.state_dict().items()):
            h.update(np.ascontiguousarray(v.detach().numpy()).tobytes())
        return h.hexdigest()[:16]

    def close(self) -> None:
        self.vec.close()


def build_fast_ppo(cfg: TrainConfig, seed: int) -> FastPpo:
    """Check ``cfg`` (:func:`~cv2x_marl.rl.train_checks.check_training_config`) and build the run, before any
    folder is touched.

    Raises:
        TrainError: a bad configuration or seed, naming the key.
    """
    for module in ("torch", "tensordict", "torchrl"):
        require(module, "cv2x-marl train with ppo.backend: torchrl")
    if not is_int(seed) or seed < 0:
        raise TrainError(f"--seed must be an integer >= 0, got {seed!r}")
    if cfg.ppo.backend != "torchrl":
        raise TrainError(f"the fast PPO loop runs ppo.backend: torchrl, got {cfg.ppo.backend!r}")
    check_training_config(cfg)
    return FastPpo(cfg, int(seed))


def write_rows(path: Path, rows: list[dict[str, Any]]) -> None:
    """Rewrite a CSV of ``rows`` atomically (a crash leaves the previous version, never a torn row)."""

    def write(tmp: Path) -> None:
        with tmp.open("w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)

    if rows:
        atomic_write(path, write)


def train_fast(
    cfg: TrainConfig,
    timesteps: int,
    seed: int,
    run_dir: Path,
    resume: bool = False,
    progress: bool = True,
    overwrite: bool = False,
) -> dict[str, Any]:
    """Train PPO with ``ppo.backend: torchrl`` for at least ``timesteps`` agent-steps (whole iterations); write
    the run folder (module docstring); return the record. Torch runs on one thread (``torch.set_num_threads(1)``).

    Raises:
        TrainError: bad arguments or configuration, or ``resume`` (checked before ``run_dir`` is touched).
        cv2x_marl.runs.RunFolderError: the folder is in use, or not empty without ``overwrite``.
    """
    import torch

    cpu0 = time.process_time()
    if not is_int(timesteps) or timesteps < 1:
        raise TrainError(f"--timesteps must be an integer >= 1, got {timesteps!r}")
    if resume:
        raise TrainError("--resume: ppo.backend: torchrl writes no checkpoints; train again, or use ppo.backend: sb3")
    torch.set_num_threads(1)
    run_dir = Path(run_dir)
    resolved = {**cfg.to_dict(), "seed": seed, "timesteps": timesteps}
    run = build_fast_ppo(cfg, seed)
    try:
        params = {"env_id": cfg.env_id, "seed": seed, "timesteps": timesteps, "algo": "ppo", "backend": "torchrl"}
        with RunFolder(run_dir, "train", overwrite=overwrite, keep_on_failure=True, parameters=params):
            return _train_fast(run, cfg, resolved, timesteps, run_dir, progress, cpu0)
    finally:
        run.close()


def _train_fast(
    run: FastPpo,
    cfg: TrainConfig,
    resolved: dict[str, Any],
    timesteps: int,
    run_dir: Path,
    progress: bool,
    cpu0: float,
) -> dict[str, Any]:
    import torch
    import torchrl
    from tqdm import tqdm

    from cv2x_marl.plotting import plot_return_vs_cpu

    write_json(run_dir / "train_config.json", resolved)
    env = cfg.env_for_training()
    gbmu_env = {**env, "action_mode": "offset"}  # GBMU moves by offsets, whatever the learner's actions are
    eval_cpu0 = time.process_time()
    gbmu = evaluate(cfg.env_id, "gbmu", cfg.eval_episodes, cfg.eval_seed, None, gbmu_env, progress=False)
    eval_cpu = time.process_time() - eval_cpu0
    iterations = math.ceil(timesteps / run.rollout_steps())
    curve: list[dict[str, Any]] = []
    evals: list[dict[str, Any]] = []
    next_eval = cfg.eval_every
    t0 = time.perf_counter()
    bar = tqdm(total=iterations * run.rollout_steps(), unit="step", desc="train", file=sys.stderr, disable=not progress)
    final: dict[str, Any] = {}
    for it in range(1, iterations + 1):
        losses = run.iterate()
        bar.update(run.rollout_steps())
        curve.append(
            {
                "iteration": it,
                "agent_steps": run.agent_steps,
                "cpu_s": time.process_time() - cpu0 - eval_cpu,
                "wall_s": time.perf_counter() - t0,
                "episodes": len(run.returns),
                "train_mean_return": run.recent_return(),
                **losses,
            }
        )
        if run.agent_steps >= next_eval or it == iterations:
            next_eval = run.agent_steps + cfg.eval_every
            eval_cpu0 = time.process_time()
            final = evaluate(
                cfg.env_id,
                BatchPolicy(run.act_fn(), "ppo"),
                cfg.eval_episodes,
                cfg.eval_seed,
                None,
                env,
                progress=False,
            )
            eval_cpu += time.process_time() - eval_cpu0
            evals.append(
                {
                    "timesteps": run.agent_steps,
                    "cpu_s": curve[-1]["cpu_s"],
                    "ppo_mean_utility_gain": final["mean_utility_gain"],
                    "ppo_effectiveness": final["effectiveness"],
                    "ppo_mean_prr_gain": final["mean_prr_gain"],
                    "ppo_mean_return": final["mean_return"],
                    "gbmu_mean_utility_gain": gbmu["mean_utility_gain"],
                    "gbmu_effectiveness": gbmu["effectiveness"],
                    "gbmu_mean_prr_gain": gbmu["mean_prr_gain"],
                }
            )
            write_rows(run_dir / "eval.csv", evals)
            write_rows(run_dir / "curve.csv", curve)
    bar.close()
    wall = time.perf_counter() - t0
    write_rows(run_dir / "curve.csv", curve)
    plot_return_vs_cpu(curve, run_dir / "curve.png", f"PPO (torchrl) on {cfg.env_id}, seed {resolved['seed']}")
    atomic_write(run_dir / "model.pt", lambda tmp: torch.save(run.model(), tmp))
    cpu = curve[-1]["cpu_s"]
    record = {
        "algo": "ppo",
        "backend": "torchrl",
        "env_id": cfg.env_id,
        "seed": resolved["seed"],
        "timesteps": run.agent_steps,
        "iterations": iterations,
        "wall_s": wall,
        "cpu_s": cpu,
        "eval_cpu_s": eval_cpu,
        "steps_per_s": run.agent_steps / wall if wall > 0 else float("nan"),
        "steps_per_cpu_s": run.agent_steps / cpu if cpu > 0 else float("nan"),
        "train_mean_return": curve[-1]["train_mean_return"],
        "n_sub_envs": cfg.copies,
        "final_eval": {
            k: final[k] for k in ("mean_utility_gain", "effectiveness", "mean_prr_gain", "jain_fairness", "mean_return")
        },
        "parameters_digest": run.digest(),
        "torch": torch.__version__,
        "torchrl": torchrl.__version__,
        "torch_threads": torch.get_num_threads(),
    }
    write_json(run_dir / "record.json", record)
    return record
