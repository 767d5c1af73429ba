"""`cv2x-marl evaluate`: one evaluation loop for every policy, the same episodes for the same seed.

Episode k of seed S resets the env with ``derive_seeds(S, episodes)[k]``, which are also the
snapshots of ``cv2x-marl gbmu --case realizations --seed S``, so the env results and the GBMU
study are directly comparable.
"""

from __future__ import annotations

import csv
import json
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from cv2x_marl.checks import is_int
from cv2x_marl.env.mobility_env import MobilityEnv
from cv2x_marl.env.registry import DEFAULT_ENV_ID, make_parallel_env
from cv2x_marl.io import atomic_write, write_json
from cv2x_marl.policies.base import Policy
from cv2x_marl.policies.baselines import is_baseline_file, load_baseline, make_baseline_policy
from cv2x_marl.policies.optimum import OptimumPolicy, best_response_targets
from cv2x_marl.policies.registry import PPO_PREFIX, make_policy
from cv2x_marl.regression.model import PAPER_MODEL
from cv2x_marl.runs import run_folder

#: most per-mover rows (episodes x movers) one evaluation keeps: they stay in memory for the summary
#: and ``episodes.csv``, about :data:`ROW_BYTES` each, so about 1 GB at the limit
MAX_ROWS = 1_000_000
#: memory of one per-mover row (a dict of 12 values: 752 bytes measured, rounded up for the summary's arrays)
ROW_BYTES = 1_000


def episode_seeds(seed: int, n: int) -> Iterator[int]:
    """The seeds :func:`~cv2x_marl.rng.derive_seeds` gives, one at a time (the children of one
    ``SeedSequence`` are spawned in order, so they are the same values) without holding ``n`` of them."""
    root = np.random.SeedSequence(int(seed))
    for _ in range(n):
        yield int(root.spawn(1)[0].generate_state(1)[0])


def check_episodes(episodes: int, movers: int) -> None:
    """Refuse an evaluation whose per-mover rows (``episodes x movers``) exceed :data:`MAX_ROWS`."""
    if not is_int(episodes) or episodes < 1:
        raise ValueError(f"--episodes must be an integer >= 1, got {episodes!r}")
    rows = int(episodes) * movers
    if rows > MAX_ROWS:
        raise ValueError(
            f"--episodes {episodes:,} x {movers} mover(s) would keep {rows:,} per-mover rows in memory (about "
            f"{rows * ROW_BYTES / 1e9:,.1f} GB at {ROW_BYTES:,} bytes each), above the limit of {MAX_ROWS:,} rows; "
            f"lower --episodes to at most {MAX_ROWS // movers:,} for this env"
        )


def trained_env_options(path: Path) -> tuple[str | None, dict[str, Any]]:
    """The env id and the options that shape observations, actions and dynamics of a model saved by
    ``cv2x-marl train`` (read from ``train_config.json`` beside it; ``(None, {})`` for a bare SB3
    file). The reward options are not taken: every method is judged on the same utility."""
    cfg_path = Path(path).parent / "train_config.json"
    if not cfg_path.exists():
        return None, {}
    try:
        cfg = json.loads(cfg_path.read_text())
        keep = (
            "observation",
            "privileged",
            "model",
            "n_neighbours",
            "scale_m",
            "settle_steps",
            "reward_form",
            "action_mode",
            "replan_every",
            "max_cycles",
            "max_step_m",
            "max_drift_m",
            "roi",
        )
        return str(cfg["env_id"]), {k: v for k, v in dict(cfg.get("env", {})).items() if k in keep}
    except (ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"cannot read the training configuration {cfg_path}: {exc}") from exc


def optimum_utilities(env: MobilityEnv) -> np.ndarray:
    """[N] every vehicle's utility (env units) with the movers at the optimum policy's targets."""
    ref = OptimumPolicy(env)
    movers = [int(i) for i in np.flatnonzero(env.mover_mask)]
    targets = best_response_targets(env, movers, ref.rounds, ref.grid_m, ref.refine)
    return env._utilities(env.links.success(targets), env.target)


def evaluate(
    env_id: str | None,
    policy_spec: str | Policy,
    episodes: int,
    seed: int,
    out_dir: Path | None = None,
    env_kwargs: dict[str, Any] | None = None,
    model_path: str = PAPER_MODEL,
    delta: float = 100.0,
    progress: bool = True,
    vs_optimum: bool = False,
    overwrite: bool = False,
) -> dict[str, Any]:
    """Run ``episodes`` episodes and summarise per-mover gains (eq. 17), fairness and returns.

    ``episodes x`` the env's movers is at most :data:`MAX_ROWS` (the per-mover rows stay in memory);
    larger counts, and an optimum search (``vs_optimum``, ``optimum``) too large for
    :data:`~cv2x_marl.policies.optimum.MAX_GRID_POINTS`, are refused before ``out_dir`` is touched.

    Args:
        env_id: a registered id; None: the one a ``ppo:PATH`` model was trained on or a baseline
            file names, else ``cv2x/SingleMover-v2``.
        policy_spec: a policy name (:func:`~cv2x_marl.policies.registry.make_policy`), ``ppo:PATH``, a baseline
            file (``baselines/NAME.yaml``, :mod:`cv2x_marl.policies.baselines`: its policy, model,
            delta, env id and env options; ``env_kwargs`` override the latter) or a policy object.
        vs_optimum: also compute, on every episode, the utility at the optimum policy's targets
            (:mod:`cv2x_marl.policies.optimum`) and report ``share_of_optimum``: the method's mean
            utility gain over the optimum's on the same episodes.
        out_dir: a run folder (:class:`cv2x_marl.runs.RunFolder`) for ``episodes.csv`` and
            ``summary.json``; None writes nothing.
        overwrite: replace a previous run in ``out_dir``.
    """
    from tqdm import tqdm

    check_episodes(episodes, 1)  # the count itself; with the env's movers below
    env_kwargs = dict(env_kwargs or {})
    spec = None
    if isinstance(policy_spec, str) and is_baseline_file(policy_spec):  # baselines/NAME.yaml
        spec = load_baseline(policy_spec)
        env_id = env_id or spec.env_id
        env_kwargs = {**spec.env, **env_kwargs}
        policy_spec, model_path, delta = spec.policy, spec.model, spec.delta
    if isinstance(policy_spec, str) and policy_spec.startswith(PPO_PREFIX):
        trained_id, trained_env = trained_env_options(Path(policy_spec[len(PPO_PREFIX) :]))
        env_id = env_id or trained_id
        env_kwargs = {**trained_env, **env_kwargs}
    env_id = env_id or DEFAULT_ENV_ID
    inputs = [Path(model_path)]  # the files read: --out may not be, contain or lie inside one
    if isinstance(policy_spec, str) and policy_spec.startswith(PPO_PREFIX):
        inputs.append(Path(policy_spec[len(PPO_PREFIX) :]))
    env = make_parallel_env(env_id, **env_kwargs)
    if spec is not None:  # its model (a shipped name or a file) and its step schedule
        policy = make_baseline_policy(spec, env)
    elif isinstance(policy_spec, str):
        policy = make_policy(policy_spec, env, model_path, delta)
    else:
        policy = policy_spec
        policy_spec = policy.name
    movers = [a for a in env.possible_agents if env.mover_mask[env.agent_index[a]]]
    check_episodes(episodes, len(movers))
    if vs_optimum:  # its search is refused here, before the run folder, when too large
        OptimumPolicy(env)
    params = {"env_id": env_id, "policy": str(policy_spec), "episodes": episodes, "seed": seed}
    with run_folder(out_dir, "evaluate", overwrite=overwrite, parameters=params, inputs=inputs):
        zero = np.zeros(2, dtype=np.float32)
        rows: list[dict[str, Any]] = []
        t0 = time.perf_counter()
        steps = 0
        for ep, ep_seed in enumerate(
            tqdm(
                episode_seeds(seed, episodes),
                total=episodes,
                desc=policy.name,
                unit="ep",
                file=sys.stderr,
                disable=not progress,
            )
        ):
            obs, infos = env.reset(seed=ep_seed)
            policy.reset(ep_seed)
            u_opt = optimum_utilities(env) if vs_optimum else None
            returns = dict.fromkeys(movers, 0.0)
            last = infos
            while env.agents:
                acts = policy.act({a: obs[a] for a in movers})
                full = {a: acts.get(a, zero) for a in env.agents}
                obs, rew, _, _, last = env.step(full)
                steps += 1
                for a in movers:
                    returns[a] += rew[a]
            for a in movers:
                info = last[a]
                rows.append(
                    {
                        "episode": ep,
                        "seed": ep_seed,
                        "agent": a,
                        "utility_start": info["utility_start"],
                        "utility_end": info["utility"],
                        "prr_start": info["prr_start"],
                        "prr_end": info["prr"],
                        "jain_end": info["jain"],
                        "return": returns[a],
                    }
                )
                if u_opt is not None:
                    rows[-1]["utility_optimum"] = float(u_opt[env.agent_index[a]])
        runtime = time.perf_counter() - t0
        u0 = np.array([r["utility_start"] for r in rows])
        u1 = np.array([r["utility_end"] for r in rows])
        p0 = np.array([r["prr_start"] for r in rows])
        p1 = np.array([r["prr_end"] for r in rows])
        with np.errstate(divide="ignore", invalid="ignore"):
            ug = np.where(u0 != 0, (u1 - u0) / np.abs(u0), np.nan)
            pg = np.where(p0 != 0, (p1 - p0) / np.abs(p0), np.nan)
        for r, a, b in zip(rows, ug, pg, strict=True):
            r["utility_gain"], r["prr_gain"] = float(a), float(b)
        summary: dict[str, Any] = {
            "env": env_id,
            "policy": policy_spec,
            "episodes": episodes,
            "seed": seed,
            "movers_per_episode": len(movers),
            "mean_utility_gain": float(np.nanmean(ug)),
            "mean_prr_gain": float(np.nanmean(pg)),
            "effectiveness": float(np.mean(ug > 1e-9)),
            "n_prr_drop": int(np.sum(pg < -1e-9)),
            "jain_fairness": float(np.mean([r["jain_end"] for r in rows])),
            "mean_return": float(np.mean([r["return"] for r in rows])),
            "mean_prr_start": float(np.mean(p0)),
            "mean_prr_end": float(np.mean(p1)),
            "max_cycles": env.max_cycles,
            "max_step_m": env.max_step_m,
            "runtime_s": runtime,
            "env_steps": steps,
        }
        if vs_optimum:
            uo = np.array([r["utility_optimum"] for r in rows])
            with np.errstate(divide="ignore", invalid="ignore"):
                og = np.where(u0 != 0, (uo - u0) / np.abs(u0), np.nan)
            summary["optimum_utility_gain"] = float(np.nanmean(og))
            summary["share_of_optimum"] = summary["mean_utility_gain"] / summary["optimum_utility_gain"]
            summary["beats_optimum"] = int(np.sum(u1 > uo + 1e-9 * np.abs(uo)))
        if out_dir is not None:
            out_dir = Path(out_dir)

            def write(tmp: Path) -> None:
                with tmp.open("w", newline="") as fh:
                    w = csv.DictWriter(fh, fieldnames=list(rows[0]))
                    w.writeheader()
                    w.writerows(rows)

            atomic_write(out_dir / "episodes.csv", write)
            write_json(out_dir / "summary.json", summary)
        return summary
