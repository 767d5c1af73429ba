"""Train a PPO mover with stable-baselines3 through the package's adapter, then judge it honestly.

    python examples/sb3_ppo.py [--timesteps 50000] [--seed 0] [--quick]

The adapter (:class:`cv2x_marl.rl.sb3_vec_env.AgentsVecEnv`) exposes every mover of every env copy as
one SB3 sub-env, seeds the copies from PPO's seed and marks time-limit truncation. The mover here is
the shipped single-mover recipe (``agents/configs/ppo_single_v2_residual.yaml``); it is evaluated
on held-out episodes (seed 2026, never seen in training) next to GBMU, the plan it starts from and
the optimum. ``cv2x-marl train`` does the same with checkpoints, learning curves and resume.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from cv2x_marl.experiments.evaluate import evaluate
from cv2x_marl.policies.ppo import PpoPolicy
from cv2x_marl.rl.train import load_train_config, make_ppo, make_vec_env


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--timesteps", type=int, default=50_000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--episodes", type=int, default=48, help="held-out evaluation episodes")
    ap.add_argument("--quick", action="store_true", help="a few hundred steps on short episodes (for tests)")
    args = ap.parse_args()
    cfg = load_train_config(Path(__file__).parent.parent / "agents/configs/ppo_single_v2_residual.yaml")
    timesteps, episodes = args.timesteps, args.episodes
    if args.quick:
        import dataclasses

        env = {**cfg.env, "max_cycles": 10, "overrides": ["sim.warmup_subframes=200"]}
        cfg = dataclasses.replace(cfg, env=env, copies=2)
        timesteps, episodes = 256, 2
    vec = make_vec_env(cfg)
    model = make_ppo(vec, cfg.ppo, args.seed)
    model.learn(timesteps)
    kw = dict(cfg.env)
    learned = evaluate(cfg.env_id, PpoPolicy(model), episodes, 2026, env_kwargs=kw, progress=False, vs_optimum=True)
    offsets = {**kw, "action_mode": "offset"}  # the scripted movers act with plain offsets
    print(
        f"PPO ({timesteps} steps)  utility gain {learned['mean_utility_gain']:+.1%}  "
        f"share of the optimum {learned['share_of_optimum']:.0%}"
    )
    for policy in ("gbmu", "sensing"):
        res = evaluate(cfg.env_id, policy, episodes, 2026, env_kwargs=offsets, progress=False)
        print(f"{policy:8s}  utility gain {res['mean_utility_gain']:+.1%}")


if __name__ == "__main__":
    main()
