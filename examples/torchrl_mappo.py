"""MAPPO with TorchRL on ``cv2x/Cooperative-v0``: a shared actor, a centralised critic on ``state()``.

    python examples/torchrl_mappo.py [--iterations 20] [--seed 0] [--quick]

TorchRL's ``PettingZooWrapper`` takes the ParallelEnv with ``return_state=True``, so every step
carries the env's global ``state()`` (positions and velocities of all vehicles) next to each
vehicle's own observation. The actor is one MLP shared by all 21 vehicles (decentralised execution:
it sees only a vehicle's observation); the critic is centralised (centralised training): it reads
``state`` and gives one value per vehicle. PPO's clipped loss with GAE trains both. The learned
mover is then judged on held-out episodes (seed 2026) next to GBMU with the package's own
evaluation loop. Needs the ``[torchrl]`` extra.
"""

from __future__ import annotations

import argparse
from typing import Any

import numpy as np

GROUP = "vehicles"


def torchrl_actor(actor_net: Any, n_agents: int) -> Any:
    """The shared actor's deterministic action (the TanhNormal's mode) for one vehicle's observation [1, obs].

    TorchRL's ``MultiAgentMLP`` takes exactly ``n_agents`` rows, so the row is repeated ``n_agents`` times: the
    action then reads this vehicle's observation alone, whoever else is in the step (``BatchPolicy``'s rule).
    """

    def act(obs: np.ndarray) -> np.ndarray:
        import torch

        with torch.no_grad():
            rows = torch.from_numpy(obs).expand(n_agents, -1)[None]  # [1, n_agents, obs]: the one row repeated
            loc, _ = actor_net(rows)  # [1, n_agents, 2]
        return torch.tanh(loc[0, :1]).numpy()

    return act


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--iterations", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--episodes", type=int, default=12, help="held-out evaluation episodes")
    ap.add_argument("--quick", action="store_true", help="one small iteration on short episodes (for tests)")
    args = ap.parse_args()

    import torch
    from tensordict.nn import NormalParamExtractor, TensorDictModule
    from torch import nn
    from torchrl.collectors import Collector
    from torchrl.data import LazyTensorStorage, ReplayBuffer
    from torchrl.data.replay_buffers.samplers import SamplerWithoutReplacement
    from torchrl.envs import PettingZooWrapper
    from torchrl.modules import MLP, MultiAgentMLP, ProbabilisticActor, TanhNormal
    from torchrl.objectives import ClipPPOLoss, ValueEstimators

    from cv2x_marl.env import parallel_env_cooperative
    from cv2x_marl.experiments.evaluate import evaluate
    from cv2x_marl.policies.base import BatchPolicy

    torch.manual_seed(args.seed)  # the example's own process: seeding torch is the script's choice
    env_config: dict[str, Any] = {"max_cycles": 100}
    iterations, episodes, frames, minibatch, epochs = args.iterations, args.episodes, 2000, 400, 5
    if args.quick:
        env_config.update(max_cycles=5, overrides=["sim.warmup_subframes=200"])
        iterations, episodes, frames, minibatch, epochs = 1, 1, 20, 10, 1

    pz = parallel_env_cooperative(**env_config)
    agents = list(pz.possible_agents)
    env = PettingZooWrapper(
        pz, return_state=True, group_map={GROUP: agents}, use_mask=False, categorical_actions=False, seed=args.seed
    )
    n_agents = len(agents)
    obs_dim = env.observation_spec[GROUP, "observation"].shape[-1]
    state_dim = env.observation_spec["state"].shape[-1]

    actor_net = nn.Sequential(
        MultiAgentMLP(obs_dim, 2 * 2, n_agents, centralized=False, share_params=True, depth=2, num_cells=64),
        NormalParamExtractor(),  # [loc, scale] of each of the 2 action dimensions
    )
    actor = ProbabilisticActor(
        TensorDictModule(actor_net, in_keys=[(GROUP, "observation")], out_keys=[(GROUP, "loc"), (GROUP, "scale")]),
        spec=env.full_action_spec[GROUP, "action"],
        in_keys=[(GROUP, "loc"), (GROUP, "scale")],
        out_keys=[(GROUP, "action")],
        distribution_class=TanhNormal,
        distribution_kwargs={"low": -1.0, "high": 1.0},
        return_log_prob=True,
        log_prob_key=(GROUP, "sample_log_prob"),
    )

    class StateCritic(nn.Module):
        """Centralised critic: the global state -> one value per vehicle, [..., n_agents, 1]."""

        def __init__(self) -> None:
            super().__init__()
            self.mlp = MLP(in_features=state_dim, out_features=n_agents, depth=2, num_cells=64)

        def forward(self, state: torch.Tensor) -> torch.Tensor:
            return self.mlp(state).unsqueeze(-1)

    critic = TensorDictModule(StateCritic(), in_keys=["state"], out_keys=[(GROUP, "state_value")])

    collector = Collector(
        env, actor, frames_per_batch=frames, total_frames=frames * iterations, auto_register_policy_transforms=False
    )
    buffer = ReplayBuffer(storage=LazyTensorStorage(frames), sampler=SamplerWithoutReplacement(), batch_size=minibatch)
    loss = ClipPPOLoss(actor_network=actor, critic_network=critic, clip_epsilon=0.2, entropy_coeff=0.0)
    loss.set_keys(
        reward=(GROUP, "reward"),
        action=(GROUP, "action"),
        sample_log_prob=(GROUP, "sample_log_prob"),
        value=(GROUP, "state_value"),
        done=(GROUP, "done"),
        terminated=(GROUP, "terminated"),
    )
    loss.make_value_estimator(ValueEstimators.GAE, gamma=0.95, lmbda=0.95)
    optim = torch.optim.Adam(loss.parameters(), lr=3e-4)

    for i, batch in enumerate(collector):
        with torch.no_grad():  # GAE over the batch, with the centralised critic
            loss.value_estimator(
                batch, params=loss.critic_network_params, target_params=loss.target_critic_network_params
            )
        buffer.extend(batch.reshape(-1))
        for _ in range(epochs * max(1, frames // minibatch)):
            sample = buffer.sample()
            out = loss(sample)
            total = out["loss_objective"] + out["loss_critic"] + out["loss_entropy"]
            optim.zero_grad()
            total.backward()
            torch.nn.utils.clip_grad_norm_(loss.parameters(), 0.5)
            optim.step()
        collector.update_policy_weights_()
        reward = batch.get(("next", GROUP, "reward")).mean().item()
        print(f"iteration {i + 1}: mean step reward {reward:.3f}")
    collector.shutdown()

    policy = BatchPolicy(torchrl_actor(actor_net, n_agents), "torchrl-mappo")
    learned = evaluate("cv2x/Cooperative-v0", policy, episodes, 2026, env_kwargs=env_config, progress=False)
    gbmu = evaluate("cv2x/Cooperative-v0", "gbmu", episodes, 2026, env_kwargs=env_config, progress=False)
    print(f"TorchRL MAPPO  utility gain {learned['mean_utility_gain']:+.1%}  PRR gain {learned['mean_prr_gain']:+.1%}")
    print(f"GBMU           utility gain {gbmu['mean_utility_gain']:+.1%}  PRR gain {gbmu['mean_prr_gain']:+.1%}")


if __name__ == "__main__":
    main()
