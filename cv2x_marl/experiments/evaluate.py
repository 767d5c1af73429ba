"""`cv2x-marl evaluate`: one evaluation loop for every policy, the same episodes for the same seed.

Episode k of seed S resets the env with ``derive_seeds(S, episodes)[k]``, which are also the
snapshots of ``cv2x-marl gbmu --case realizations --seed S``, so the env results and the GBMU
study are directly comparable. Given ``seeds`` (``--seeds``: a list, or a task's ``heldout`` /
``train`` list of :mod:`cv2x_marl.env.tasks`), episode k resets with ``seeds[k]`` instead.

The benchmark protocol (docs/benchmark.md): with ``seeds`` given or several policies (the training
runs of one method), the summary adds the interquartile mean and the 95 % stratified bootstrap
interval (:mod:`cv2x_marl.stats`) of the per-episode utility and PRR gains (and of the share of the
ceiling with ``vs_optimum``), pooled over runs x episodes (:data:`PROTOCOL_KEYS`). Without them the
summary and ``episodes.csv`` are what they always were. The protocol's statistics are
:mod:`cv2x_marl.experiments.protocol`'s (re-exported here).
"""

from __future__ import annotations

import csv
import dataclasses
import glob
import sys
import time
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from cv2x_marl.checks import is_int
from cv2x_marl.env import tasks
from cv2x_marl.env.mobility_env import MobilityEnv
from cv2x_marl.env.options import POLICY_ROLES, EnvOptions, options_with_role
from cv2x_marl.env.registry import DEFAULT_ENV_ID, make_parallel_env
from cv2x_marl.experiments.protocol import (  # noqa: F401 - re-exported: evaluate's names before the split
    BOOTSTRAP_SEED,
    PROTOCOL_KEYS,
    episode_means,
    format_summary,
    interval,
    protocol_summary,
    team_gain,
)
from cv2x_marl.io import atomic_write, write_json
from cv2x_marl.policies.base import Policy
from cv2x_marl.policies.baselines import Baseline, is_baseline_file, load_baseline, make_baseline_policy
from cv2x_marl.policies.optimum import uses_team_search
from cv2x_marl.policies.registry import PPO_PREFIX, make_policy
from cv2x_marl.policies.resource import is_resource_env, resource_reference
from cv2x_marl.policies.traffic import reference_means
from cv2x_marl.regression.model import PAPER_MODEL
from cv2x_marl.runs import run_folder
from cv2x_marl.yamlcore import YAMLError, parse_scalar

#: most per-mover rows (episodes x movers) one evaluation keeps: they stay in memory for the summary
#: and ``episodes.csv``, about :data:`ROW_BYTES` each, so about 1 GB at the limit
MAX_ROWS = 1_000_000
#: memory of one per-mover row (a dict of 12 values: 752 bytes measured, rounded up for the summary's arrays)
ROW_BYTES = 1_000
#: the largest episode seed ``--seeds`` takes (32-bit, as the CLI's ``--seed``)
MAX_SEED = 2**32 - 1
#: env arguments the `evaluate` command sets with its own flags (``--env-option`` refuses them)
EVALUATE_FLAGS = {
    "preset": "--preset",
    "overrides": "--set",
    "max_cycles": "--max-cycles",
    "max_step_m": "--max-step",
    "replan_every": "--replan-every",
}


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


def parse_seeds(text: str, env_id: str | None) -> tuple[int, ...]:
    """``--seeds``: integers separated by commas or spaces, or ``heldout`` / ``train``: the lists of the
    task whose env id is ``env_id`` (:mod:`cv2x_marl.env.tasks`). Repeated seeds are refused (the
    statistics would count an episode twice)."""
    word = text.strip()
    if word in ("heldout", "train"):
        task = tasks.task_of_env(env_id) if env_id else None
        if task is None:
            named = ", ".join(f"{t.name}: {t.env_id}" for t in tasks.TASKS.values())
            given = f"--env {env_id} is no task's env" if env_id else "give --env, a task's env"
            raise ValueError(f"--seeds {word}: {given}; tasks: {named}")
        return task.seeds(word)
    try:
        seeds = tuple(int(s) for s in word.replace(",", " ").split())
    except ValueError:
        raise ValueError(f"--seeds expects integers separated by commas, or heldout | train, got {text!r}") from None
    if not seeds or any(s < 0 or s > MAX_SEED for s in seeds):
        raise ValueError(f"--seeds must be integers in [0, {MAX_SEED}], or heldout | train, got {text!r}")
    if len(set(seeds)) != len(seeds):
        raise ValueError(f"--seeds: repeated seed in {text!r}")
    return seeds


def cli_seeds(
    text: str | None, episodes: int | None, seed: int | None, env_id: str | None, policies: Sequence[str]
) -> tuple[int, ...] | None:
    """``evaluate --seeds`` with ``--episodes`` and ``--seed`` as given (None: not given): the episode seeds, or None
    without ``--seeds``. ``heldout`` / ``train`` name the lists of ``env_id``'s task, or of the env a ``ppo:PATH``
    model was trained on; ``--episodes N`` takes the first N seeds (as ``benchmark --episodes``); ``--seed`` is
    refused with ``--seeds`` (it would be ignored)."""
    if text is None:
        return None
    if env_id is None and policies and policies[0].startswith(PPO_PREFIX):  # the env the model was trained on
        env_id = trained_env_options(Path(policies[0][len(PPO_PREFIX) :]))[0]
    seeds = parse_seeds(text, env_id)
    if seed is not None:
        raise ValueError("--seed does not apply with --seeds (the episodes' seeds are given); drop one of them")
    if episodes is not None:
        if episodes > len(seeds):
            raise ValueError(f"--episodes {episodes}: --seeds {text} gives only {len(seeds)} seeds")
        seeds = seeds[:episodes]
    return seeds


def parse_env_options(items: Iterable[str], reserved: dict[str, str] | None = None) -> dict[str, Any]:
    """``--env-option key=value`` items -> ``{key: value}``, values read as YAML scalars or flow lists
    (``3`` -> 3, ``[0, 1]`` -> list, ``null`` -> None). Unknown keys are refused naming the allowed ones
    (:class:`~cv2x_marl.env.options.EnvOptions`); the values are checked by the env when it is built.

    Args:
        items: the ``key=value`` texts.
        reserved: keys another flag sets, ``{key: flag}``: refused naming the flag.
    """
    names = [f.name for f in dataclasses.fields(EnvOptions)]
    out: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise ValueError(f"--env-option expects key=value, got {item!r}")
        if key not in names:
            raise ValueError(f"--env-option: unknown env argument {key!r}; allowed: {', '.join(names)}")
        if reserved and key in reserved:
            raise ValueError(f"--env-option {key}: set it with {reserved[key]}")
        if key in out:
            raise ValueError(f"--env-option {key} given twice")
        try:
            out[key] = parse_scalar(value)
        except YAMLError as exc:
            raise ValueError(f"--env-option {key}: cannot parse {value!r}: {exc}") from exc
    return out


def expand_policies(specs: Sequence[str], flag: str = "--policy") -> list[str]:
    """Repeated ``--policy`` values, a ``ppo:`` pattern (``ppo:runs/seed*/model.zip``) expanded to its
    sorted matches; a pattern that matches nothing is refused (the error names ``flag``)."""
    out: list[str] = []
    for spec in specs:
        if spec == PPO_PREFIX:
            raise ValueError(f"{flag} {spec!r}: no path after {PPO_PREFIX!r}; give {PPO_PREFIX}PATH to a model file")
        if spec.startswith(PPO_PREFIX) and glob.has_magic(spec[len(PPO_PREFIX) :]):
            found = sorted(glob.glob(spec[len(PPO_PREFIX) :]))
            if not found:
                raise ValueError(f"{flag} {spec}: no file matches the pattern")
            out.extend(PPO_PREFIX + f for f in found)
        else:
            out.append(spec)
    if len(set(out)) != len(out):
        raise ValueError(f"{flag}: a policy given twice in {out}")
    return out


def trained_env_options(path: Path) -> tuple[str | None, dict[str, Any]]:
    """The env id and the options that shape observations, actions and dynamics of a model saved by
    ``cv2x-marl train`` (read from ``train_config.json`` beside it; ``(None, {})`` for a bare SB3
    file): those of role ``observation`` and ``action`` (:data:`~cv2x_marl.env.options.POLICY_ROLES`), and
    ``reward_form`` (the ``mean_return`` column is in the model's own form). The other reward options are not
    taken: every method is judged on the same utility."""
    import json

    cfg_path = Path(path).parent / "train_config.json"
    if not cfg_path.exists():
        return None, {}
    try:
        cfg = json.loads(cfg_path.read_text())
        # what it observes and what its actions do; and its reward form, which the return column reports
        keep = (*options_with_role(*POLICY_ROLES), "reward_form")
        return str(cfg["env_id"]), {k: v for k, v in dict(cfg.get("env", {})).items() if k in keep}
    except (ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"cannot read the training configuration {cfg_path}: {exc}") from exc


def optimum_utilities(env: MobilityEnv, ref: Any = None) -> np.ndarray:
    """[N] every vehicle's utility (env units) with the movers at the ``optimum`` policy's targets
    (``ref``: that policy, built once per env; its targets are those it drives to). On an env with episode
    metrics whose ceiling is a search over the episode (``cv2x/Traffic-v0``): the search's best episode-mean
    utility at the mover (NaN elsewhere)."""
    ref = make_policy("optimum", env) if ref is None else ref
    if hasattr(ref, "ceiling_utilities"):
        ref.reset(env.seed_used)
        return np.asarray(ref.ceiling_utilities())
    ref.reset()
    ref.act({})  # computes the episode's targets (the env at its reset)
    return env.utilities(env.links.success(ref.targets_m), env.target)


def ceiling_env(env_id: str, env_kwargs: dict[str, Any], env: MobilityEnv) -> MobilityEnv:
    """The env the ceiling (``optimum``) is computed in for ``vs_optimum``: ``env`` itself, or, where ``env``'s
    action space is one the ceiling does not act in (``speed_command="change"``: a learner's own speed
    changes; the ceiling commands target speeds), the same env id and options with ``speed_command="target"``.
    The ceiling is a property of the episode: the two envs reset to the same scenario for the same seed
    (tested), as ``benchmark`` scores such a model against its task's ceiling."""
    if getattr(env.options, "speed_command", "target") == "target":
        return env
    return make_parallel_env(env_id, **{**env_kwargs, "speed_command": "target"})


@dataclasses.dataclass
class _Resolved:
    """What a policy spec resolves to: its env and options, its model, its step, the files it reads."""

    env_id: str | None
    env_kwargs: dict[str, Any]
    spec: Baseline | None
    policy: str | Policy
    model_path: str
    delta: float
    inputs: list[Path]


def _resolve(
    env_id: str | None, policy_spec: str | Policy, env_kwargs: dict[str, Any], model_path: str, delta: float
) -> _Resolved:
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
    inputs = [Path(model_path)]  # the files read: --out may not be, contain or lie inside one
    if isinstance(policy_spec, str) and policy_spec.startswith(PPO_PREFIX):
        inputs.append(Path(policy_spec[len(PPO_PREFIX) :]))
    return _Resolved(env_id, env_kwargs, spec, policy_spec, model_path, delta, inputs)


def names_of(specs: Sequence[str | Policy]) -> list[str]:
    """The names of policy specs (a policy object: its ``name``)."""
    return [s if isinstance(s, str) else s.name for s in specs]


def _build(r: _Resolved, env: MobilityEnv) -> Policy:
    if r.spec is not None:  # its model (a shipped name or a file) and its step schedule
        return make_baseline_policy(r.spec, env)
    if isinstance(r.policy, str):
        return make_policy(r.policy, env, r.model_path, r.delta)
    bind = getattr(r.policy, "bind", None)  # a policy that needs its env first (InTurns.deferred)
    return bind(env) if callable(bind) else r.policy


def evaluate(
    env_id: str | None,
    policy_spec: str | Policy | Sequence[str | Policy],
    episodes: int,
    seed: int,
    out_dir: Path | None = None,
    env_kwargs: dict[str, Any] | None = None,
    model_path: str = PAPER_MODEL,
    delta: float = 100.0,
    progress: bool = True,
    vs_optimum: bool = False,
    overwrite: bool = False,
    seeds: Sequence[int] | None = None,
) -> dict[str, Any]:
    """Run ``episodes`` episodes and summarise per-mover gains (eq. 17), fairness and returns.

    ``episodes x`` the env's movers is at most :data:`MAX_ROWS` (the per-mover rows stay in memory);
    larger counts, and an optimum search (``vs_optimum``, ``optimum``) too large for
    :data:`~cv2x_marl.policies.optimum.MAX_GRID_POINTS`, are refused before ``out_dir`` is touched.

    Args:
        env_id: a registered id; None: the one a ``ppo:PATH`` model was trained on or a baseline
            file names, else :data:`~cv2x_marl.env.registry.DEFAULT_ENV_ID`.
        policy_spec: a policy name (:func:`~cv2x_marl.policies.registry.make_policy`), ``ppo:PATH``, a baseline
            file (``baselines/NAME.yaml``, :mod:`cv2x_marl.policies.baselines`: its policy, model,
            delta, env id and env options; ``env_kwargs`` override the latter) or a policy object;
            or a list of them: the training runs of one method (each on the same episodes, their
            rows pooled; they must resolve to the same env id and options), ``episodes.csv`` then
            has a ``run`` column.
        episodes, seed: episode k resets with ``derive_seeds(seed, episodes)[k]`` (without ``seeds``).
        seeds: the episode seeds themselves (``episodes`` and ``seed`` are then not used); the
            summary adds the protocol's statistics (:data:`PROTOCOL_KEYS`).
        vs_optimum: also compute, on every episode, the utility at the optimum policy's targets
            (:mod:`cv2x_marl.policies.optimum`) and report ``share_of_optimum``: the method's mean
            utility gain over the optimum's on the same episodes.
        out_dir: a run folder (:class:`cv2x_marl.runs.RunFolder`) for ``episodes.csv`` and
            ``summary.json``; None writes nothing.
        overwrite: replace a previous run in ``out_dir``.
    """
    summary, _ = evaluate_rows(
        env_id,
        policy_spec,
        episodes,
        seed,
        out_dir,
        env_kwargs,
        model_path=model_path,
        delta=delta,
        progress=progress,
        vs_optimum=vs_optimum,
        overwrite=overwrite,
        seeds=seeds,
    )
    return summary


def evaluate_rows(
    env_id: str | None,
    policy_spec: str | Policy | Sequence[str | Policy],
    episodes: int,
    seed: int,
    out_dir: Path | None = None,
    env_kwargs: dict[str, Any] | None = None,
    model_path: str = PAPER_MODEL,
    delta: float = 100.0,
    progress: bool = True,
    vs_optimum: bool = False,
    overwrite: bool = False,
    seeds: Sequence[int] | None = None,
) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """:func:`evaluate`'s summary and its per-mover rows (those of ``episodes.csv``)."""
    if seeds is not None:
        seeds = [int(s) for s in seeds]
        if not seeds:
            raise ValueError("--seeds: give at least one seed")
        episodes = len(seeds)
    check_episodes(episodes, 1)  # the count itself; with the env's movers below
    several = isinstance(policy_spec, Sequence) and not isinstance(policy_spec, str)
    resolved = _resolve_runs(env_id, policy_spec, several, env_kwargs, model_path, delta)
    first = resolved[0]
    env_id = first.env_id or DEFAULT_ENV_ID
    task = tasks.task_of_env(env_id)
    for r in resolved:  # a policy the task cannot run: refused by name before the env is built
        if task is not None and isinstance(r.policy, str):
            task.check_policy(r.policy)
    env = make_parallel_env(env_id, **first.env_kwargs)
    policies = [_build(r, env) for r in resolved]
    names = [r.policy if isinstance(r.policy, str) else p.name for r, p in zip(resolved, policies, strict=True)]
    movers = [a for a in env.possible_agents if env.mover_mask[env.agent_index[a]]]
    check_episodes(episodes * len(policies), len(movers))
    ref_env = ceiling_env(env_id, first.env_kwargs, env) if vs_optimum else env
    ref = make_policy("optimum", ref_env) if vs_optimum else None  # too large a search: refused here
    protocol = seeds is not None or several
    params: dict[str, Any] = {
        "env_id": env_id,
        "policy": names if several else names[0],
        "episodes": episodes,
        "seed": seed if seeds is None else None,
    }
    if seeds is not None:
        params["seeds"] = seeds
    inputs = [p for r in resolved for p in r.inputs]
    with run_folder(out_dir, "evaluate", overwrite=overwrite, parameters=params, inputs=inputs):
        means = bool(getattr(env.options, "episode_metrics", False))  # episode metrics (cv2x/Traffic-v0)
        t0 = time.perf_counter()
        rows, steps = _episode_rows(env, policies, movers, episodes, seed, seeds, several, ref, ref_env, progress)
        runtime = time.perf_counter() - t0
        u0 = np.array([r["utility_start"] for r in rows])
        u1 = np.array([r["utility_end"] for r in rows])
        p0 = np.array([r["prr_start"] for r in rows])
        p1 = np.array([r["prr_end"] for r in rows])
        with np.errstate(divide="ignore", invalid="ignore"):
            ug = np.where(u0 != 0, (u1 - u0) / np.abs(u0), np.nan)
            pg = np.where(p0 != 0, (p1 - p0) / np.abs(p0), np.nan)
        # the team is rewarded and every vehicle moves, or every vehicle picks its resource: gains of the team
        team = uses_team_search(env) or is_resource_env(env)
        if team:
            ug, pg = team_gain(rows, "utility_start", "utility_end"), team_gain(rows, "prr_start", "prr_end")
        for row, a, b in zip(rows, ug, pg, strict=True):
            row["utility_gain"], row["prr_gain"] = float(a), float(b)
        summary: dict[str, Any] = {
            "env": env_id,
            "policy": names if several else names[0],
            "episodes": episodes,
            "seed": seed if seeds is None else None,
            "movers_per_episode": len(movers),
            "mean_utility_gain": float(np.nanmean(ug)),
            "mean_prr_gain": float(np.nanmean(pg)),
            "effectiveness": float(np.mean(ug > 1e-9)),
            "n_prr_drop": int(np.sum(pg < -1e-9)),
            "jain_fairness": float(np.mean([r["jain_mean" if means else "jain_end"] for r in rows])),
            "mean_return": float(np.mean([r["return"] for r in rows])),
            "mean_prr_start": float(np.mean(p0)),
            "mean_prr_end": float(np.mean(p1)),
            "max_cycles": env.max_cycles,
            "max_step_m": env.max_step_m,
            "runtime_s": runtime,
            "env_steps": steps,
        }
        if team or protocol or means:  # (the default path's summary keeps its keys: tests/reference)
            summary["gains_of"] = "the team (mean over the vehicles)" if team else "each mover (eq. 17)"
            if means:
                summary["gains_of"] = "each mover's episode means against static's on the same episode"
            if means and is_resource_env(env):
                summary["gains_of"] = (
                    "the team's episode means against sps's (the standard's choice) on the same episode"
                )
        if vs_optimum:
            _add_optimum_gains(summary, rows, u0, u1, team)
        if protocol:
            summary.update(protocol_summary(rows, len(policies), episodes, vs_optimum))
            summary["seeds"] = seeds
        if out_dir is not None:
            _write_episodes(Path(out_dir), rows, summary)
        return summary, rows


def _resolve_runs(
    env_id: str | None,
    policy_spec: str | Policy | Sequence[str | Policy],
    several: bool,
    env_kwargs: dict[str, Any] | None,
    model_path: str,
    delta: float,
) -> list[_Resolved]:
    """:func:`evaluate_rows`' policy specs resolved (:func:`_resolve`); several must be ``ppo:PATH`` runs of one
    method on one env."""
    specs: list[str | Policy] = list(policy_spec) if several else [policy_spec]  # type: ignore[arg-type,list-item]
    if not specs:
        raise ValueError("--policy: give at least one policy")
    if several and not all(isinstance(s, str) and s.startswith(PPO_PREFIX) for s in specs):
        raise ValueError(
            "--policy: several policies are the training runs of one learned method, each ppo:PATH; "
            f"got {names_of(specs)}"
        )
    resolved = [_resolve(env_id, s, dict(env_kwargs or {}), model_path, delta) for s in specs]
    first = resolved[0]
    for r in resolved[1:]:
        if (r.env_id, r.env_kwargs) != (first.env_id, first.env_kwargs):
            raise ValueError(
                f"--policy: the runs of one evaluation must share the env; {r.policy} resolves to {r.env_id} "
                f"{r.env_kwargs}, {first.policy} to {first.env_id} {first.env_kwargs}"
            )
    return resolved


def _episode_rows(
    env: MobilityEnv,
    policies: list[Policy],
    movers: list[str],
    episodes: int,
    seed: int,
    seeds: Sequence[int] | None,
    several: bool,
    ref: Any,
    ref_env: MobilityEnv,
    progress: bool,
) -> tuple[list[dict[str, Any]], int]:
    """Every policy's episodes on ``env`` (:func:`evaluate_rows`): the per-mover rows and the env steps taken."""
    from tqdm import tqdm

    zero = env.dynamics.null_action
    rows: list[dict[str, Any]] = []
    # cv2x/Resource-v0: each agent's episode means against sps's (the standard's choice) on the same episode
    choice = is_resource_env(env)
    optimum_cache: dict[int, np.ndarray] = {}
    # episode metrics (cv2x/Traffic-v0): each episode's means, gains against static's on the same episode
    means = bool(getattr(env.options, "episode_metrics", False))
    static_cache: dict[int, tuple[Any, Any]] = {}  # floats (static's), or [N] arrays per agent (sps's)
    steps = 0
    for run, policy in enumerate(policies):
        ep_seeds = iter(seeds) if seeds is not None else episode_seeds(seed, episodes)
        bar = tqdm(ep_seeds, total=episodes, desc=policy.name, unit="ep", file=sys.stderr, disable=not progress)
        for ep, ep_seed in enumerate(bar):
            obs, infos = env.reset(seed=ep_seed)
            policy.reset(ep_seed)
            if ref is not None and ep not in optimum_cache:
                if ref_env is not env:  # the same episode in the env the ceiling acts in
                    ref_env.reset(seed=ep_seed)
                optimum_cache[ep] = optimum_utilities(ref_env, ref)
            u_opt = optimum_cache.get(ep)
            if means and ep not in static_cache:
                if choice:
                    static_cache[ep] = resource_reference(env, lambda e: make_policy("sps", e))
                else:
                    static_cache[ep] = reference_means(env, lambda e: make_policy("static", e))
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
                row: dict[str, Any] = {"run": run} if several else {}
                base = static_cache.get(ep) if means else None
                if choice and base is not None:  # per agent
                    i = env.agent_index[a]
                    base = (float(base[0][i]), float(base[1][i]))
                row.update(_mover_row(last[a], ep, ep_seed, a, returns[a], base))
                if u_opt is not None:
                    row["utility_optimum"] = float(u_opt[env.agent_index[a]])
                rows.append(row)
    return rows, steps


def _mover_row(
    info: dict[str, Any], ep: int, ep_seed: int, agent: str, ret: float, static_means: tuple[float, float] | None
) -> dict[str, Any]:
    """One mover's row of an episode from its last info; ``static_means``: with episode metrics, static's
    utility and PRR means on the same episode (the start), None without."""
    u_start, u_end, p_start, p_end = info["utility_start"], info["utility"], info["prr_start"], info["prr"]
    if static_means is not None:  # the episode's means; the start: static's means on the same episode
        (u_start, p_start), u_end, p_end = static_means, info["utility_mean"], info["prr_mean"]
    row: dict[str, Any] = {
        "episode": ep,
        "seed": ep_seed,
        "agent": agent,
        "utility_start": u_start,
        "utility_end": u_end,
        "prr_start": p_start,
        "prr_end": p_end,
        "jain_end": info["jain"],
        "return": ret,
    }
    if static_means is not None:  # Jain's index of the mover's links, mean over the episode's periods
        row["jain_mean"] = info["jain_mean"]
    return row


def _add_optimum_gains(
    summary: dict[str, Any], rows: list[dict[str, Any]], u0: np.ndarray, u1: np.ndarray, team: bool
) -> None:
    """``vs_optimum``: each row's ``optimum_gain`` and the summary's optimum utility gain, share of the optimum and
    the count of rows that beat it."""
    uo = np.array([r["utility_optimum"] for r in rows])
    with np.errstate(divide="ignore", invalid="ignore"):
        og = np.where(u0 != 0, (uo - u0) / np.abs(u0), np.nan)
    if team:
        og = team_gain(rows, "utility_start", "utility_optimum")
    for row, g in zip(rows, og, strict=True):
        row["optimum_gain"] = float(g)
    summary["optimum_utility_gain"] = float(np.nanmean(og))
    summary["share_of_optimum"] = summary["mean_utility_gain"] / summary["optimum_utility_gain"]
    summary["beats_optimum"] = int(np.sum(u1 > uo + 1e-9 * np.abs(uo)))


def _write_episodes(out_dir: Path, rows: list[dict[str, Any]], summary: dict[str, Any]) -> None:
    """``episodes.csv`` (the rows, without ``optimum_gain``) and ``summary.json`` in ``out_dir``."""
    fields = [k for k in rows[0] if k != "optimum_gain"]

    def write(tmp: Path) -> None:
        with tmp.open("w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=fields, extrasaction="ignore")
            w.writeheader()
            w.writerows(rows)

    atomic_write(out_dir / "episodes.csv", write)
    write_json(out_dir / "summary.json", summary)
