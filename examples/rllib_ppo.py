"""Multi-agent PPO with RLlib on ``cv2x/Cooperative-v0``: every vehicle an agent, one shared policy.

    python examples/rllib_ppo.py [--iterations 20] [--seed 0] [--quick]

RLlib takes PettingZoo ParallelEnvs through its ``ParallelPettingZooEnv`` wrapper; the env is
registered with RLlib by a factory (an import, not the PettingZoo registry, so it resolves in every
Ray worker). All agents map to the policy ``shared`` (parameter sharing). After training, the
policy's deterministic action (the mean of its Gaussian) is judged on held-out episodes (seed 2026)
next to GBMU with the package's own evaluation loop. Needs the ``[ray]`` extra.
"""

from __future__ import annotations

import argparse
import tempfile
from typing import Any

import numpy as np

ENV_NAME = "cv2x_cooperative_v0"


def env_creator(env_config: dict[str, Any]) -> Any:
    """RLlib env factory: the package's ParallelEnv in RLlib's PettingZoo wrapper."""
    from ray.rllib.env.wrappers.pettingzoo_env import ParallelPettingZooEnv

    from cv2x_marl.env import parallel_env_cooperative

    return ParallelPettingZooEnv(parallel_env_cooperative(**env_config))


def rllib_actor(module: Any) -> Any:
    """The shared RLlib policy's deterministic action (the Gaussian's mean) for a batch of observations."""

    def act(obs: np.ndarray) -> np.ndarray:
        import torch

        with torch.no_grad():
            out = module.forward_inference({"obs": torch.from_numpy(obs)})
        return np.clip(out["action_dist_inputs"].numpy()[:, :2], -1.0, 1.0)  # [mean, log_std] per dimension

    return act


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--iterations", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--episodes", type=int, default=12, help="held-out evaluation episodes")
    ap.add_argument("--quick", action="store_true", help="one small iteration on short episodes (for tests)")
    args = ap.parse_args()

    from ray.rllib.algorithms.ppo import PPOConfig
    from ray.tune.registry import register_env

    from cv2x_marl.experiments.evaluate import evaluate
    from cv2x_marl.parallel import ray_session
    from cv2x_marl.policies.base import BatchPolicy

    env_config: dict[str, Any] = {"max_cycles": 100}
    iterations, episodes, batch = args.iterations, args.episodes, 4000
    if args.quick:
        env_config.update(max_cycles=5, overrides=["sim.warmup_subframes=200"])
        iterations, episodes, batch = 1, 1, 210
    with ray_session(num_cpus=1):
        register_env(ENV_NAME, env_creator)
        config = (
            PPOConfig()
            .environment(ENV_NAME, env_config=env_config)
            .multi_agent(policies={"shared"}, policy_mapping_fn=lambda agent_id, *a, **k: "shared")
            .env_runners(num_env_runners=0)
            .training(
                train_batch_size_per_learner=batch,
                minibatch_size=min(batch, 512),
                num_epochs=5,
                gamma=0.95,
                lr=3e-4,
            )
            .debugging(seed=args.seed)
        )
        algo = config.build_algo()
        for i in range(iterations):
            result = algo.train()
            ret = result.get("env_runners", {}).get("episode_return_mean", float("nan"))
            print(f"iteration {i + 1}: mean episode return {ret:.2f}")
        module = algo.get_module("shared")
        with tempfile.TemporaryDirectory() as tmp:
            algo.save_to_path(tmp)  # the checkpoint layout RLlib restores with Algorithm.from_checkpoint
        algo.stop()
    policy = BatchPolicy(rllib_actor(module), "rllib-ppo")
    learned = evaluate("cv2x/Cooperative-v0", policy, episodes, 2026, env_kwargs=env_config, progress=False)
    gbmu = evaluate("cv2x/Cooperative-v0", "gbmu", episodes, 2026, env_kwargs=env_config, progress=False)
    print(f"RLlib PPO  utility gain {learned['mean_utility_gain']:+.1%}  PRR gain {learned['mean_prr_gain']:+.1%}")
    print(f"GBMU       utility gain {gbmu['mean_utility_gain']:+.1%}  PRR gain {gbmu['mean_prr_gain']:+.1%}")


if __name__ == "__main__":
    main()
