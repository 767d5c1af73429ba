"""MAPPO and independent PPO for masked discrete actions (``cv2x/Resource-v0``; :mod:`cv2x_marl.rl.mappo`'s other
path, picked by the env's ``Discrete`` action space; docs/rl.md, "Resource choice").

Every vehicle is an agent; in a step only the few that reselected at the last period's end *decide* (their
``env.action_masks()`` row has a 1); the others' actions are ignored by the env. So:

* **Actor**: :class:`~cv2x_marl.policies.mappo_nets.MaskedActor` gives logits over the n entries; TorchRL's
  ``MaskedCategorical`` (through a ``ProbabilisticActor``) sets the entries outside the mask to ``-inf``, so a
  sampled action is always a valid entry. It runs on the deciding agents' rows only.
* **Critic** (``mappo.critic``): ``observation``: each agent's value from its own observation (independent PPO with
  parameter sharing); ``state``: MAPPO's centralised critic on ``env.state()``, one value per step with the team
  reward (``env.reward: team``), or, with individual rewards, per agent on ``state()`` followed by the agent's own
  observation (Yu et al. 2022's agent-specific global state).
* **GAE** per agent over its own reward sequence (or the step's with the team critic), every step of the episode:
  a decision's effect lasts until the vehicle's next reselection, 5-15 periods, and the values of the steps between
  (where it does not decide) carry it.
* **Loss**: the clipped PPO objective (TorchRL's ``ClipPPOLoss``, advantages normalised per mini-batch, the entropy
  term when ``ent_coef`` > 0) on the decision samples only (agent-steps whose mask has a 1: the rest carry no
  decision); the squared value error times ``vf_coef`` on every value sample (agent-steps, or steps for the team
  critic). One epoch shuffles both sets into the same number of mini-batches, ``ceil(K T / minibatch_steps)``, and
  each Adam step takes one of each.

The random streams, checkpoints, resume and the run folder are :mod:`cv2x_marl.rl.mappo`'s.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict
from torch import nn

from cv2x_marl.rl.errors import TrainError
from cv2x_marl.rl.mappo_config import GROUP
from cv2x_marl.rl.ppo_step import LOSS_KEYS, ppo_minibatch_step

#: a :class:`cv2x_marl.rl.mappo.Mappo` run (not imported: it imports this module for its discrete path)
Mappo = Any

#: the critic of each ``mappo.critic`` and reward: its inputs (``critic_kind`` of ``model.pt``)
CRITIC_KINDS = ("observation", "state", "state+observation")


def critic_kind(critic: str, team: bool) -> str:
    """What the critic reads: ``observation`` (IPPO), ``state`` (team reward: one value per step) or
    ``state+observation`` (MAPPO with individual rewards: per agent)."""
    if critic == "observation":
        return "observation"
    return "state" if team else "state+observation"


def build_masked(run: Mappo, first: Any, torch_seed: int) -> None:
    """The masked actor, the critic, TorchRL's modules, the loss and Adam of ``run`` (:class:`Mappo.__init__`'s
    discrete path)."""
    from tensordict.nn import TensorDictModule
    from torchrl.modules import MaskedCategorical, ProbabilisticActor
    from torchrl.objectives import ClipPPOLoss

    from cv2x_marl.policies.mappo_nets import MaskedActor, ObservationCritic, StateCritic, candidate_spec

    cfg, m = run.cfg, run.cfg.mappo
    if not callable(getattr(first, "action_masks", None)):
        raise TrainError(f"{cfg.env_id} has Discrete actions but no action_masks(); MAPPO's masked actor needs them")
    try:
        spec = candidate_spec(first.layout)
    except ValueError as exc:
        raise TrainError(f"train.env of {cfg.env_id}: {exc}") from exc
    run.n_actions = int(first.action_space(run.agents[0]).n)
    run.team = getattr(first.options, "reward", "individual") == "team"
    run.critic_kind = critic_kind(m.critic, run.team)
    n_in = {"observation": run.obs_size, "state": run.state_size, "state+observation": run.state_size + run.obs_size}
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(torch_seed)
        run.actor = MaskedActor(
            run.obs_size, run.n_actions, m.actor_net, m.encoder, m.encoder_units, spec, dither=m.dither
        )
        if run.critic_kind == "state":
            inner: Any = StateCritic(run.state_size, m.critic_net)
        else:
            inner = ObservationCritic(n_in[run.critic_kind], m.critic_net)
        run.critic = NormalisedCritic(inner)
        run.torch_state = torch.random.get_rng_state()
    run.policy = ProbabilisticActor(
        TensorDictModule(run.actor, in_keys=[(GROUP, "observation")], out_keys=[(GROUP, "logits")]),
        in_keys={"logits": (GROUP, "logits"), "mask": (GROUP, "mask")},
        out_keys=[(GROUP, "action")],
        distribution_class=MaskedCategorical,
        return_log_prob=True,
        log_prob_key=(GROUP, "sample_log_prob"),
    )
    actor_loss = ClipPPOLoss(
        run.policy,
        None,
        clip_epsilon=m.clip_range,
        entropy_bonus=m.ent_coef > 0,
        entropy_coeff=m.ent_coef if m.ent_coef > 0 else None,
        normalize_advantage=True,
    )
    actor_loss.set_keys(
        action=(GROUP, "action"), sample_log_prob=(GROUP, "sample_log_prob"), advantage=(GROUP, "advantage")
    )
    run.loss = MaskedPpoLoss(actor_loss, run.critic, m.vf_coef)
    run.params = [*run.actor.parameters(), *run.critic.parameters()]
    run.optim = torch.optim.Adam(run.params, lr=m.learning_rate, eps=1e-5)


class NormalisedCritic(nn.Module):
    """A critic whose network predicts the value standardised by running statistics of the value targets (value
    normalisation, as MAPPO's ``ValueNorm``, Yu et al. 2022): the returns here are about -25 to -50 (a utility of
    about -2.5 per step over the discounted horizon), far from a fresh network's 0. :meth:`value` is the value in
    reward units; the statistics are buffers (saved with the weights and in checkpoints).

    Args:
        net: the critic's network (its output: the standardised value).
        momentum: the weight of each new batch of targets in the statistics (the first batch sets them).
    """

    def __init__(self, net: nn.Module, momentum: float = 0.1) -> None:
        super().__init__()
        self.net = net
        self.n_in = int(getattr(net, "n_in", getattr(net, "state_size", 0)))
        self.momentum = float(momentum)
        self.mean: torch.Tensor
        self.sq: torch.Tensor
        self.seen: torch.Tensor
        self.register_buffer("mean", torch.zeros(()))
        self.register_buffer("sq", torch.ones(()))
        self.register_buffer("seen", torch.zeros((), dtype=torch.bool))

    def std(self) -> torch.Tensor:
        return (self.sq - self.mean**2).clamp(min=1e-4).sqrt()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """The standardised value (what the loss compares with :meth:`normalise` of the targets)."""
        out: torch.Tensor = self.net(x)
        return out

    def value(self, x: torch.Tensor) -> torch.Tensor:
        """The value in reward units."""
        return self(x) * self.std() + self.mean

    def normalise(self, target: torch.Tensor) -> torch.Tensor:
        return (target - self.mean) / self.std()

    @torch.no_grad()
    def observe(self, target: torch.Tensor) -> None:
        """Move the statistics towards a batch of targets (the first batch sets them)."""
        mean, sq = target.mean(), (target**2).mean()
        if not bool(self.seen):
            self.mean.copy_(mean)
            self.sq.copy_(sq)
            self.seen.fill_(True)
            return
        self.mean.lerp_(mean, self.momentum)
        self.sq.lerp_(sq, self.momentum)


class MaskedPpoLoss(nn.Module):
    """The clipped objective (and entropy) on a mini-batch of decision samples, the value loss on one of value samples:
    ``batch["decisions"]`` (TorchRL's ``ClipPPOLoss`` keys), ``batch["value_input"]`` and ``batch["value_target"]``
    (standardised); returns the ``loss_*`` terms (:data:`~cv2x_marl.rl.ppo_step.LOSS_KEYS`).

    Args:
        actor_loss: TorchRL's ``ClipPPOLoss`` on the actor alone (no critic).
        critic: the :class:`NormalisedCritic`.
        vf_coef: the weight of the squared value error.
    """

    def __init__(self, actor_loss: Any, critic: NormalisedCritic, vf_coef: float) -> None:
        super().__init__()
        self.actor_loss = actor_loss
        self.critic = critic
        self.vf_coef = float(vf_coef)

    def forward(self, batch: Any) -> Any:
        out = self.actor_loss(batch["decisions"])
        value = self.critic(batch["value_input"])
        terms = {"loss_objective": out["loss_objective"]}
        if "loss_entropy" in out.keys():
            terms["loss_entropy"] = out["loss_entropy"]
        terms["loss_critic"] = self.vf_coef * (value - batch["value_target"]).pow(2).mean()
        return TensorDict(terms, [])


def collect_masked(run: Mappo, stop: Any = None) -> dict[str, Any] | None:
    """One episode of every copy (:meth:`Mappo.collect` for masked actions): arrays [T, K, N, ...] (observations and
    states [T + 1, ...]: the last ones bootstrap the time limit); None when ``stop`` holds a signal."""
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    k_, t_, n_, a_ = run.cfg.copies, run.steps, run.n_agents, run.n_actions
    obs = np.empty((t_ + 1, k_, n_, run.obs_size), np.float32)
    state = np.empty((t_ + 1, k_, run.state_size), np.float32)
    mask = np.zeros((t_, k_, n_, a_), bool)
    act = np.zeros((t_, k_, n_), np.int64)
    logp = np.zeros((t_, k_, n_), np.float32)
    rew = np.empty((t_, k_, n_), np.float32)
    current = []
    for k, env in enumerate(run.envs):
        o, _ = env.reset(seed=run.pool[int(run.episode_rngs[k].integers(len(run.pool)))])
        current.append(o)
        state[0, k] = env.state()
    with torch.random.fork_rng(devices=[]), torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        torch.random.set_rng_state(run.torch_state)
        for t in range(t_):
            if stop is not None and stop.signal is not None:
                return None
            obs[t] = [[o[a] for a in run.agents] for o in current]
            for k, env in enumerate(run.envs):
                masks = env.action_masks()
                assert masks is not None  # a Discrete env with masks (build_masked checked it)
                mask[t, k] = masks > 0
            decides = mask[t].any(-1)  # [K, N]
            d = int(decides.sum())
            if d:
                td = TensorDict(
                    {
                        GROUP: TensorDict(
                            {
                                "observation": torch.from_numpy(obs[t][decides]),
                                "mask": torch.from_numpy(mask[t][decides]),
                            },
                            [d],
                        )
                    },
                    [d],
                )
                run.policy(td)
                act[t][decides] = td[GROUP, "action"].numpy()
                logp[t][decides] = td[GROUP, "sample_log_prob"].numpy()
            for k, env in enumerate(run.envs):
                o, r, term, trunc, _ = env.step({a: act[t, k, i] for i, a in enumerate(run.agents)})
                rew[t, k] = [r[a] for a in run.agents]
                state[t + 1, k] = env.state()
                current[k] = o
                if any(term.values()) or (t < t_ - 1 and any(trunc.values())):
                    raise RuntimeError(f"{run.cfg.env_id} ended an episode before max_cycles; MAPPO expects T steps")
        obs[t_] = [[o[a] for a in run.agents] for o in current]
        run.torch_state = torch.random.get_rng_state()
    return {"obs": obs, "state": state, "mask": mask, "action": act, "log_prob": logp, "reward": rew}


def critic_inputs(run: Mappo, obs: np.ndarray, state: np.ndarray) -> np.ndarray:
    """The critic's inputs of ``obs`` [T', K, N, O] and ``state`` [T', K, S]: [T', K, N, .] per agent, [T', K, S]
    for the team critic."""
    if run.critic_kind == "observation":
        return obs
    if run.critic_kind == "state":
        return state
    wide = np.broadcast_to(state[:, :, None, :], (*obs.shape[:3], state.shape[-1]))
    return np.concatenate((wide, obs), axis=-1)


def advantages(run: Mappo, batch: dict[str, Any]) -> tuple[Any, Any, Any]:
    """GAE of a collected batch: advantages and value targets [T, K, N] (per agent) or [T, K] (team critic), and the
    critic's inputs of the T steps."""
    from torchrl.objectives.value.functional import generalized_advantage_estimate

    m = run.cfg.mappo
    x = torch.from_numpy(critic_inputs(run, batch["obs"], batch["state"]))  # [T + 1, K, (N,) .]
    with torch.no_grad():
        values = run.critic.value(x)  # [T + 1, K, (N,) 1]
    reward = torch.from_numpy(batch["reward"])  # [T, K, N]
    if run.critic_kind == "state":
        reward = reward.mean(-1)  # the team reward: every agent's is the same
    # time last: [K, (N,) T, 1]
    v = values.squeeze(-1).movedim(0, -1).unsqueeze(-1)
    r = reward.movedim(0, -1).unsqueeze(-1)
    done = torch.zeros_like(r, dtype=torch.bool)
    done[..., -1, :] = True  # the time limit: done, not terminated (the last value is bootstrapped)
    with torch.no_grad():
        adv, target = generalized_advantage_estimate(
            m.gamma, m.gae_lambda, v[..., :-1, :], v[..., 1:, :], r, done, torch.zeros_like(done), time_dim=-2
        )
    return adv.squeeze(-1).movedim(-1, 0), target.squeeze(-1).movedim(-1, 0), x[:-1]


def update_masked(run: Mappo, batch: dict[str, Any]) -> dict[str, float]:
    """GAE and the PPO epochs of the masked path (module docstring); the mean losses."""

    m = run.cfg.mappo
    t_, k_, n_ = batch["reward"].shape
    adv, target, x = advantages(run, batch)
    if run.critic_kind == "state":
        adv = adv.unsqueeze(-1).expand(t_, k_, n_)  # the step's advantage is every agent's
    decides = torch.from_numpy(batch["mask"].any(-1))  # [T, K, N]
    d = int(decides.sum())
    agents = TensorDict(
        {
            "observation": torch.from_numpy(batch["obs"][:-1])[decides],
            "mask": torch.from_numpy(batch["mask"])[decides],
            "action": torch.from_numpy(batch["action"])[decides],
            "sample_log_prob": torch.from_numpy(batch["log_prob"])[decides],
            "advantage": adv[decides].unsqueeze(-1).contiguous(),
        },
        [d],
    )
    decisions = TensorDict({GROUP: agents}, [d])
    value_input = x.reshape(-1, x.shape[-1])
    run.critic.observe(target)
    value_target = run.critic.normalise(target.reshape(-1, 1)).contiguous()
    n_values = value_input.shape[0]
    n_batches = max(1, math.ceil(t_ * k_ / m.minibatch_steps))
    sums = dict.fromkeys(LOSS_KEYS, 0.0)
    count = 0
    with torch.random.fork_rng(devices=[]):
        torch.random.set_rng_state(run.torch_state)
        for _ in range(m.n_epochs):
            order_d = np.array_split(run.batch_rng.permutation(d), n_batches)
            order_v = np.array_split(run.batch_rng.permutation(n_values), n_batches)
            for idx_d, idx_v in zip(order_d, order_v, strict=True):
                if idx_d.size < 2:  # the advantage is normalised over the mini-batch
                    continue
                iv = torch.from_numpy(idx_v)
                mb = TensorDict(
                    {
                        "decisions": decisions[torch.from_numpy(idx_d)],
                        "value_input": value_input[iv],
                        "value_target": value_target[iv],
                    },
                    [],
                )
                ppo_minibatch_step(run.loss, mb, run.optim, run.params, m.max_grad_norm, sums)
                count += 1
        run.torch_state = torch.random.get_rng_state()
    out = {k: v / max(count, 1) for k, v in sums.items()}
    out["decisions"] = float(d)
    return out
