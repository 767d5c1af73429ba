"""CleanRL-style PPO in plain torch on Gymnasium's ``vector_entry_point`` env (``cv2x/SingleMover-v3``).

    python examples/cleanrl_ppo_vector.py [--iterations 30] [--num-envs 16] [--seed 0] [--quick]

The single-file PPO that many researchers start from (CleanRL's ``ppo_continuous_action``), run on
``gymnasium.make_vec(..., vectorization_mode="vector_entry_point")``: the K env copies step in one
compiled call. Autoreset is ``SameStep``, so a truncated episode's last observation comes in
``infos["final_obs"]`` and its value is bootstrapped into the last reward (episodes end only by
their time limit). The trained mover is then judged on held-out episodes (seed 2026) next to GBMU
and the optimum with the package's own evaluation loop. Needs the ``[train]`` extra (torch).
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import numpy as np


def build_agent(obs_dim: int, hidden: int) -> Any:
    """Actor (tanh-MLP mean, state-independent log std) and critic, CleanRL's layout."""
    import torch
    from torch import nn

    class Agent(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.critic = nn.Sequential(
                nn.Linear(obs_dim, hidden), nn.Tanh(), nn.Linear(hidden, hidden), nn.Tanh(), nn.Linear(hidden, 1)
            )
            self.actor_mean = nn.Sequential(
                nn.Linear(obs_dim, hidden), nn.Tanh(), nn.Linear(hidden, hidden), nn.Tanh(), nn.Linear(hidden, 2)
            )
            self.actor_logstd = nn.Parameter(torch.full((1, 2), -1.0))

        def value(self, x: Any) -> Any:
            return self.critic(x).squeeze(-1)

        def act(self, x: Any, action: Any = None) -> tuple[Any, Any, Any, Any]:
            mean = self.actor_mean(x)
            dist = torch.distributions.Normal(mean, self.actor_logstd.expand_as(mean).exp())
            if action is None:
                action = dist.sample()
            return action, dist.log_prob(action).sum(-1), dist.entropy().sum(-1), self.value(x)

    return Agent()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--iterations", type=int, default=30)
    ap.add_argument("--num-envs", type=int, default=16)
    ap.add_argument("--steps", type=int, default=64, help="steps per env and iteration")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--episodes", type=int, default=24, help="held-out evaluation episodes")
    ap.add_argument("--quick", action="store_true", help="one small iteration on short episodes (for tests)")
    args = ap.parse_args()

    import gymnasium
    import torch

    import cv2x_marl  # noqa: F401 - registers the ids
    from cv2x_marl.experiments.evaluate import evaluate
    from cv2x_marl.policies.base import BatchPolicy

    env_kwargs: dict[str, Any] = {"max_cycles": 100}
    if args.quick:
        args.iterations, args.num_envs, args.steps, args.episodes = 1, 4, 16, 1
        env_kwargs.update(max_cycles=8, overrides=["sim.warmup_subframes=200"])
    gamma, lam, clip, epochs, minibatches = 0.95, 0.95, 0.2, 10, 4
    torch.manual_seed(args.seed)  # the example's own process: seeding torch is the script's choice
    torch.set_num_threads(1)
    envs = gymnasium.make_vec(
        "cv2x/SingleMover-v3",
        num_envs=args.num_envs,
        vectorization_mode="vector_entry_point",
        autoreset_mode="SameStep",
        **env_kwargs,
    )
    print(f"{type(envs).__name__} of {envs.env_id} with {envs.num_envs} copies, batched step: {envs.batched}")
    obs_dim = envs.single_observation_space.shape[0]
    agent = build_agent(obs_dim, 128)
    optimiser = torch.optim.Adam(agent.parameters(), lr=3e-4, eps=1e-5)
    k, n = args.num_envs, args.steps
    obs_buf = torch.zeros((n, k, obs_dim))
    act_buf = torch.zeros((n, k, 2))
    logp_buf, rew_buf, done_buf, val_buf = (torch.zeros((n, k)) for _ in range(4))
    obs_np, _ = envs.reset(seed=args.seed)
    obs = torch.from_numpy(obs_np)
    t0, steps = time.perf_counter(), 0
    for it in range(args.iterations):
        for t in range(n):
            with torch.no_grad():
                action, logp, _, value = agent.act(obs)
            obs_buf[t], act_buf[t], logp_buf[t], val_buf[t] = obs, action, logp, value
            obs_np, reward, term, trunc, infos = envs.step(action.numpy())
            reward = torch.as_tensor(reward, dtype=torch.float32)
            if "final_obs" in infos:  # bootstrap the value of a truncated episode's last state
                ended = np.flatnonzero(infos["_final_obs"])
                final = torch.from_numpy(np.stack([infos["final_obs"][i] for i in ended]))
                with torch.no_grad():
                    reward[ended] += gamma * agent.value(final)
            rew_buf[t], done_buf[t] = reward, torch.as_tensor(term | trunc, dtype=torch.float32)
            obs = torch.from_numpy(obs_np)
            steps += k
        with torch.no_grad():  # GAE; done_buf[t] = 1 cuts the trace after step t
            advantages, last, next_value = torch.zeros((n, k)), torch.zeros(k), agent.value(obs)
            for t in reversed(range(n)):
                nonterminal = 1.0 - done_buf[t]
                nv = next_value if t == n - 1 else val_buf[t + 1]
                delta = rew_buf[t] + gamma * nv * nonterminal - val_buf[t]
                last = delta + gamma * lam * nonterminal * last
                advantages[t] = last
            returns = advantages + val_buf
        b_obs, b_act = obs_buf.reshape(-1, obs_dim), act_buf.reshape(-1, 2)
        b_logp, b_adv, b_ret = logp_buf.reshape(-1), advantages.reshape(-1), returns.reshape(-1)
        size = n * k
        for _ in range(epochs):
            for idx in torch.randperm(size).chunk(minibatches):
                _, logp, _entropy, value = agent.act(b_obs[idx], b_act[idx])
                ratio = (logp - b_logp[idx]).exp()
                adv = (b_adv[idx] - b_adv[idx].mean()) / (b_adv[idx].std() + 1e-8)
                pg = torch.max(-adv * ratio, -adv * ratio.clamp(1 - clip, 1 + clip)).mean()
                loss = pg + 0.5 * ((value - b_ret[idx]) ** 2).mean()
                optimiser.zero_grad()
                loss.backward()
                torch.nn.utils.clip_grad_norm_(agent.parameters(), 0.5)
                optimiser.step()
        rate = steps / (time.perf_counter() - t0)
        print(f"iteration {it + 1}: mean step reward {rew_buf.mean().item():.3f}, {rate:,.0f} env-steps/s")
    envs.close()

    def act(observations: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return agent.actor_mean(torch.from_numpy(observations)).numpy()

    eval_kwargs = dict(env_kwargs)
    learned = evaluate(
        "cv2x/SingleMover-v3", BatchPolicy(act, "cleanrl-ppo"), args.episodes, 2026,
        env_kwargs=eval_kwargs, progress=False, vs_optimum=True,
    )  # fmt: skip
    gbmu = evaluate("cv2x/SingleMover-v3", "gbmu", args.episodes, 2026, env_kwargs=eval_kwargs, progress=False)
    print(
        f"CleanRL PPO  utility gain {learned['mean_utility_gain']:+.1%}  "
        f"share of the optimum {learned.get('share_of_optimum', float('nan')):.1%}"
    )
    print(f"GBMU         utility gain {gbmu['mean_utility_gain']:+.1%}")


if __name__ == "__main__":
    main()
