"""`cv2x-marl evaluate`: one evaluation loop for every policy, the same episodes for the same seed.

Episode k of seed S resets the env with ``derive_seeds(S, episodes)[k]``, which are also the
snapshots of ``cv2x-marl gbmu --case realizations --seed S``, so the env results and the GBMU
study are directly comparable.
"""

from __future__ import annotations

import csv
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from cv2x_marl.checks import is_int
from cv2x_marl.env.mobility_env import MobilityEnv
from cv2x_marl.io import atomic_write, write_json
from cv2x_marl.policies.base import BatchPolicy, Policy, RandomPolicy, StaticPolicy
from cv2x_marl.runs import check_file, run_folder

ENV_IDS = (
    "cv2x/Mobility-v0",
    "cv2x/SingleMover-v0",
    "cv2x/Mobility-v1",
    "cv2x/SingleMover-v1",
    "cv2x/Mobility-v2",
    "cv2x/SingleMover-v2",
)


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


def make_eval_env(env_id: str, **kwargs: Any) -> MobilityEnv:
    """The parallel env behind a registered id (SingleMover: only vehicle 0 moves; v1, v2: their defaults)."""
    from cv2x_marl.env.options import VERSION_DEFAULTS

    if env_id not in ENV_IDS:
        raise ValueError(f"unknown env id {env_id!r}; ids: {', '.join(ENV_IDS)}")
    if env_id.startswith("cv2x/SingleMover"):
        kwargs = {**kwargs, "movers": [0]}
    kwargs = {**VERSION_DEFAULTS[env_id.rsplit("-", 1)[1]], **kwargs}
    return MobilityEnv(**kwargs)


def make_policy(spec: str, env: MobilityEnv, model_path: str = "paper-table2", delta: float = 100.0) -> Policy:
    """``static | random | gbmu | greedy | oracle | planner | sensing | optimum | ppo:PATH``."""
    from cv2x_marl.experiments.dataset import load_model
    from cv2x_marl.policies.scripted import GbmuPolicy, OraclePolicy

    if spec == "static":
        return StaticPolicy()
    if spec == "random":
        return RandomPolicy()
    if spec in ("gbmu", "greedy"):
        model = load_model(Path(model_path))
        return GbmuPolicy(model, env.layout, env.max_step_m, delta=delta, fairness=spec == "gbmu")
    if spec == "oracle":
        return OraclePolicy(env, delta=delta)
    if spec == "optimum":
        from cv2x_marl.policies.optimum import OptimumPolicy

        return OptimumPolicy(env)
    if spec in ("planner", "sensing"):
        from cv2x_marl.policies.optimum import PlannerPolicy

        estimator = "model" if spec == "planner" else "sensing"
        return PlannerPolicy(env, load_model(Path(model_path)), estimator=estimator)
    if spec.startswith("ppo:"):
        return PpoPolicy(Path(spec[4:]), env)
    raise ValueError(
        f"unknown policy {spec!r}; policies: static, random, gbmu, greedy, oracle, planner, sensing, optimum, ppo:PATH"
    )


class PpoPolicy(BatchPolicy):
    """A stable-baselines3 PPO model (shared across agents) acting deterministically.

    Args:
        path: the ``.zip`` written by ``cv2x-marl train`` (or any SB3 PPO save).
        env: the env it will act in; its observation and action spaces must match the model's.
    """

    def __init__(self, path: Path | Any, env: MobilityEnv | None = None) -> None:
        super().__init__(self._predict, "ppo")
        if not isinstance(path, str | Path):  # an already loaded model
            self.model = path
        else:
            path = Path(path)
            if not path.exists():
                raise ValueError(f"PPO model file {path} does not exist")
            check_file(path)  # against the checksum in the run folder's run.json, when it has one
            from cv2x_marl.extras import require

            PPO = require("stable_baselines3", f"loading the PPO model {path}").PPO

            try:
                self.model = PPO.load(str(path), device="cpu")
            except Exception as exc:  # any load failure is reported with the file name
                raise ValueError(f"cannot load PPO model {path}: {type(exc).__name__}: {exc}") from exc
        if env is not None:
            want = env.observation_space(env.possible_agents[0]).shape
            got = self.model.observation_space.shape
            if want != got:
                raise ValueError(
                    f"PPO model {path} expects observations of shape {got}, the env gives {want} "
                    "(another vehicle count or n_neighbours?)"
                )

    def _predict(self, obs: np.ndarray) -> np.ndarray:
        act, _ = self.model.predict(obs, deterministic=True)
        return np.asarray(act)


def trained_env_options(path: Path) -> tuple[str | None, dict[str, Any]]:
    """The env id and the options that shape observations, actions and dynamics of a model saved by
    ``cv2x-marl train`` (read from ``train_config.json`` beside it; ``(None, {})`` for a bare SB3
    file). The reward options are not taken: every method is judged on the same utility."""
    import json

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
    from cv2x_marl.policies.optimum import OptimumPolicy, best_response_targets

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
    model_path: str = "paper-table2",
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
        policy_spec: a policy name (:func:`make_policy`), ``ppo:PATH``, a baseline file
            (``baselines/NAME.yaml``, :mod:`cv2x_marl.experiments.baselines`: its policy, model,
            delta, env id and env options; ``env_kwargs`` override the latter) or a policy object.
        vs_optimum: also compute, on every episode, the utility at the optimum policy's targets
            (:mod:`cv2x_marl.policies.optimum`) and report ``share_of_optimum``: the method's mean
            utility gain over the optimum's on the same episodes.
        out_dir: a run folder (:class:`cv2x_marl.runs.RunFolder`) for ``episodes.csv`` and
            ``summary.json``; None writes nothing.
        overwrite: replace a previous run in ``out_dir``.
    """
    from tqdm import tqdm

    from cv2x_marl.experiments.baselines import is_baseline_file, load_baseline, make_baseline_policy

    check_episodes(episodes, 1)  # the count itself; with the env's movers below
    env_kwargs = dict(env_kwargs or {})
    spec = None
    if isinstance(policy_spec, str) and is_baseline_file(policy_spec):  # baselines/NAME.yaml
        spec = load_baseline(policy_spec)
        env_id = env_id or spec.env_id
        env_kwargs = {**spec.env, **env_kwargs}
        policy_spec, model_path, delta = spec.policy, spec.model, spec.delta
    if isinstance(policy_spec, str) and policy_spec.startswith("ppo:"):
        trained_id, trained_env = trained_env_options(Path(policy_spec[4:]))
        env_id = env_id or trained_id
        env_kwargs = {**trained_env, **env_kwargs}
    env_id = env_id or "cv2x/SingleMover-v2"
    inputs = [Path(model_path)]  # the files read: --out may not be, contain or lie inside one
    if isinstance(policy_spec, str) and policy_spec.startswith("ppo:"):
        inputs.append(Path(policy_spec[4:]))
    env = make_eval_env(env_id, **env_kwargs)
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
        from cv2x_marl.policies.optimum import OptimumPolicy

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
