"""`cv2x-marl benchmark`: every method of every task on the task's held-out episodes (docs/benchmark.md).

Per task (:mod:`cv2x_marl.env.tasks`) the scripted methods, its ceiling (always run: the shares need
it) and any learned models given (``--model TASK=ppo:PATH``, repeated or a glob for several training
runs) are evaluated on the task's held-out seeds by :func:`cv2x_marl.experiments.evaluate.evaluate_rows`,
the loop of `cv2x-marl evaluate` (a method's numbers are those of ``cv2x-marl evaluate --env ID
--policy METHOD --seeds heldout``). A job is one (task, method, run) on a chunk of at most
``episodes_per_job`` of its held-out episodes (an episode's numbers depend on its seed alone: the env and
the policy are reset with it, so chunks give the rows of one job, tested); with ``workers > 1`` or an
``address`` the jobs run as Ray tasks (:func:`cv2x_marl.parallel.ray_session`: an embedded local Ray
of ``workers`` CPUs, or the cluster at ``address``) or, with ``backend="processes"``, in a pool of
``workers`` spawned processes without Ray (:func:`cv2x_marl.parallel.map_in_processes`), else in this
process (no Ray import).

The run folder (:mod:`cv2x_marl.runs`) receives ``benchmark.csv`` (one row per task, method, run and
episode: the means over the episode's movers), ``summary.json`` (per task and method the IQM and 95 %
stratified bootstrap interval of the utility gain and of the share of the ceiling, the mean PRR; and
per method present in every task the share of the ceiling aggregated over the tasks, the tasks as
strata), ``table.md`` and ``benchmark.png``; the rows, the summary and the table are
:mod:`cv2x_marl.experiments.benchmark_rows`' (re-exported here).

The CLI builds its parser from this module, whose top therefore imports nothing that loads numpy (the standard
library, :mod:`cv2x_marl.env.registry`, :mod:`cv2x_marl.io`, :mod:`cv2x_marl.runs`, :mod:`cv2x_marl.parallel`,
:mod:`~cv2x_marl.experiments.benchmark_rows`; ``tests/test_install_layers.py``): the tasks, the env options, the
policies and the evaluation are imported in the functions that use them.
"""

from __future__ import annotations

import argparse
import csv
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from cv2x_marl import parallel
from cv2x_marl.env.registry import make_parallel_env
from cv2x_marl.experiments.benchmark_rows import (
    CSV_FIELDS,
    read_rows,
    reuse_rows,
    sha256_of,
    summarise,
    table_markdown,
)
from cv2x_marl.io import atomic_write, dumps_json, write_json
from cv2x_marl.runs import run_folder

if TYPE_CHECKING:
    from cv2x_marl.env.tasks import Task

#: env options that set how a vehicle measures (observation noise): a task's are the env's defaults
MEASUREMENT_OPTIONS = ("rsrp_error_db", "sensing_window")
#: the default label of a learned model given without one
LEARNED = "ppo"
#: how jobs run when ``workers > 1``: Ray tasks (an embedded local Ray, or ``address``) or spawned processes
BACKENDS = ("ray", "processes")
#: held-out episodes per job when the jobs run in parallel (``--episodes-per-job``): small enough that a
#: ceiling's 48 episodes spread over the workers, large enough that building the env and policy is amortised
EPISODES_PER_JOB = 4


def parse_models(items: Sequence[str], tasks: Mapping[str, Task]) -> dict[str, dict[str, list[str]]]:
    """``--model TASK=ppo:PATH`` / ``TASK/LABEL=ppo:PATH`` items -> ``{task: {label: [ppo:PATH, ...]}}``
    (a label's several paths, or a glob's matches, are the training runs of one method)."""
    from cv2x_marl.experiments.evaluate import expand_policies
    from cv2x_marl.policies.registry import PPO_PREFIX

    out: dict[str, dict[str, list[str]]] = {}
    for item in items:
        key, sep, spec = item.partition("=")
        task, _, label = key.partition("/")
        label = label or LEARNED
        if not sep or not spec.startswith(PPO_PREFIX):
            raise ValueError(f"--model expects TASK=ppo:PATH or TASK/LABEL=ppo:PATH, got {item!r}")
        if task not in tasks:
            raise ValueError(f"--model {item}: unknown task {task!r}; tasks: {', '.join(tasks)}")
        out.setdefault(task, {}).setdefault(label, []).extend(expand_policies([spec], flag="--model"))
    for task, labels in out.items():
        for label, specs in labels.items():
            if len(set(specs)) != len(specs):
                raise ValueError(f"--model {task}/{label}: a model given twice")
            for s in specs:
                if not Path(s[len(PPO_PREFIX) :]).is_file():
                    raise ValueError(f"--model {task}/{label}: no model file {s[len(PPO_PREFIX) :]}")
    return out


def plan_jobs(
    tasks: Mapping[str, Task],
    names: Sequence[str] | None,
    methods: Sequence[str] | None,
    models: Mapping[str, Mapping[str, list[str]]],
    episodes: int | None,
    episodes_per_job: int | None = None,
) -> list[dict[str, Any]]:
    """One job per task, method, run and chunk of at most ``episodes_per_job`` held-out episodes (None:
    all of them in one job), checked before anything runs: available tasks, methods each task accepts
    (its refusals, names :func:`~cv2x_marl.policies.registry.make_policy` knows, searches it can afford:
    each task's env and policies are built once here)."""
    from cv2x_marl.env.tasks import CONTROL_TASKS, get_task
    from cv2x_marl.policies.registry import SCRIPTED, make_policy

    default = [n for n in tasks if n not in CONTROL_TASKS] or list(tasks)  # the control task on request only
    chosen = [get_task(n, tasks) for n in (names or default)]
    if len({t.name for t in chosen}) != len(chosen):
        raise ValueError(f"--tasks: a task given twice in {list(names or [])}")
    missing = [f"{t.name} ({t.env_id})" for t in chosen if not t.available]
    if missing:
        raise ValueError(
            f"task(s) {', '.join(missing)} not available in this version (their env ids are not registered)"
        )
    if episodes is not None and (isinstance(episodes, bool) or not isinstance(episodes, int) or episodes < 1):
        raise ValueError(f"--episodes must be an integer >= 1, got {episodes!r}")
    chunk = episodes_per_job
    if chunk is not None and (isinstance(chunk, bool) or not isinstance(chunk, int) or chunk < 1):
        raise ValueError(f"--episodes-per-job must be an integer >= 1, got {chunk!r}")
    jobs: list[dict[str, Any]] = []
    for task in chosen:
        seeds = list(task.heldout_seeds[:episodes] if episodes else task.heldout_seeds)
        wanted = list(methods) if methods else list(task.methods)
        unknown = [m for m in wanted if m not in (*task.methods, task.ceiling)]
        for m in wanted:
            task.check_policy(m)
        if unknown:
            raise ValueError(
                f"--methods {', '.join(unknown)}: not a method of task {task.name}; its methods: "
                f"{', '.join((*task.methods, task.ceiling))} (learned models: --model)"
            )
        if task.ceiling not in wanted:
            wanted.append(task.ceiling)
        env = make_parallel_env(task.env_id, **task.options)
        for m in wanted:
            make_policy(m, env)  # an unknown name or too large a search: refused here
        runs = {m: [m] for m in wanted}
        env_ids = dict.fromkeys(wanted, task.env_id)
        for label, specs in models.get(task.name, {}).items():
            if label in runs or label in (*task.methods, task.ceiling, *SCRIPTED):
                raise ValueError(
                    f"--model {task.name}/{label}: the label names a scripted method; choose another (not one of "
                    f"{', '.join(dict.fromkeys((*task.methods, task.ceiling, *SCRIPTED)))})"
                )
            runs[label] = list(specs)
            env_ids[label] = model_env_id(task, label, specs)
        size = chunk or len(seeds)
        for method, specs in runs.items():
            for run, spec in enumerate(specs):
                for first in range(0, len(seeds), size):
                    jobs.append(
                        {
                            "task": task.name,
                            "env_id": env_ids[method],
                            "options": dict(task.options),
                            "method": method,
                            "run": run,
                            "policy": spec,
                            "first_episode": first,
                            "seeds": seeds[first : first + size],
                        }
                    )
    return jobs


def model_env_id(task: Task, label: str, specs: Sequence[str]) -> str:
    """The env id a learned method runs on in ``task``: the one its models were trained on (``train_config.json``
    beside them) when that is the task's id or a variant of the task (:data:`cv2x_marl.env.tasks.VARIANTS`: the
    same episodes with another observation), the task's id for a bare model file; another env is refused, as are
    training runs of one method trained on different envs and models trained with measurement options
    (:data:`MEASUREMENT_OPTIONS`) other than the env's."""
    import dataclasses

    from cv2x_marl.env.options import EnvOptions
    from cv2x_marl.env.tasks import VARIANTS
    from cv2x_marl.experiments.evaluate import trained_env_options
    from cv2x_marl.policies.registry import PPO_PREFIX

    trained = {s: trained_env_options(Path(s[len(PPO_PREFIX) :])) for s in specs}
    ids = {env_id or task.env_id for env_id, _ in trained.values()}
    if len(ids) > 1:
        raise ValueError(f"--model {task.name}/{label}: its runs were trained on different envs: {sorted(ids)}")
    env_id = ids.pop()
    defaults = {f.name: f.default for f in dataclasses.fields(EnvOptions)}
    for s, (_, options) in trained.items():  # the task's measurements: a model trained with other noise is refused
        for key in MEASUREMENT_OPTIONS:
            if key in options and options[key] != defaults[key]:
                raise ValueError(
                    f"--model {task.name}/{label}: {s} was trained with {key}={options[key]!r}; a task measures "
                    f"with the env's {key}={defaults[key]!r} (evaluate it with cv2x-marl evaluate instead)"
                )
    allowed = [task.env_id, *(v for v, t in VARIANTS.items() if t == task.name)]
    if env_id not in allowed:
        raise ValueError(
            f"--model {task.name}/{label}: trained on {env_id}, not on task {task.name}'s env; allowed: "
            f"{', '.join(allowed)}"
        )
    return env_id


def run_job(job: dict[str, Any]) -> list[dict[str, Any]]:
    """One (task, method, run) on its chunk of seeds: per episode the means over the movers (a Ray task or
    a pool process); ``episode`` counts from the task's first held-out seed."""
    from cv2x_marl.experiments.evaluate import episode_means, evaluate_rows

    seeds = job["seeds"]
    _, rows = evaluate_rows(
        job["env_id"], job["policy"], len(seeds), 0, None, dict(job["options"]), progress=False, seeds=seeds
    )
    keys = ("utility_start", "utility_end", "utility_gain", "prr_start", "prr_end", "prr_gain")
    means = {k: episode_means(rows, k, 1, len(seeds))[0] for k in keys}
    base = {k: job[k] for k in ("task", "env_id", "method", "run", "policy")}
    first = job.get("first_episode", 0)
    return [
        {**base, "episode": first + e, "seed": s, **{k: float(means[k][e]) for k in keys}} for e, s in enumerate(seeds)
    ]


def _execute(
    jobs: list[dict[str, Any]], workers: int, address: str | None, progress: bool, backend: str = "ray"
) -> list[list[dict[str, Any]]]:
    """Every job's rows, in job order: here (one worker, no address), as Ray tasks or in spawned processes."""
    from tqdm import tqdm

    total = sum(len(j["seeds"]) for j in jobs)
    with tqdm(total=total, desc="benchmark", unit="ep", file=sys.stderr, disable=not progress) as bar:
        if backend == "processes" and address is None:

            def finished(i: int, _: Any) -> None:
                bar.update(len(jobs[i]["seeds"]))

            # the ceilings first: their jobs are the longest (a search per episode)
            def cost(job: dict[str, Any]) -> float:
                return float(len(job["seeds"]) * (100 if job["method"] == "optimum" else 1))

            return list(parallel.map_in_processes(run_job, jobs, workers, cost=cost, on_done=finished))
        if workers == 1 and address is None:
            out = []
            for job in jobs:
                bar.set_postfix_str(f"{job['task']}/{job['method']}", refresh=False)
                out.append(run_job(job))
                bar.update(len(job["seeds"]))
            return out
        with parallel.ray_session(address, num_cpus=None if address else workers) as ray:
            remote = ray.remote(num_cpus=1)(run_job)
            refs = [remote.remote(j) for j in jobs]
            index = {r: i for i, r in enumerate(refs)}
            results: list[list[dict[str, Any]] | None] = [None] * len(jobs)
            pending = list(refs)
            while pending:
                done, pending = ray.wait(pending, num_returns=1)
                for ref in done:
                    results[index[ref]] = ray.get(ref)
                    bar.update(len(jobs[index[ref]]["seeds"]))
            return [r for r in results if r is not None]


#: peak memory of one worker process running scripted jobs (measured: 306-338 MB peak RSS of one
#: ``cv2x-marl evaluate`` process on each task's env with its ceiling, 2 cores, numba cache warm)
WORKER_BYTES = 350_000_000
#: the same with a learned model (torch loaded: 515-587 MB measured for a MAPPO and a PPO model)
LEARNED_WORKER_BYTES = 600_000_000


def check_workers(workers: int, jobs: Sequence[Mapping[str, Any]], address: str | None = None) -> int:
    """Refuse more local workers than CPUs, or workers whose memory would exceed the limit, before any
    folder is touched; returns the estimated peak memory in bytes (workers x :data:`WORKER_BYTES`, or
    :data:`LEARNED_WORKER_BYTES` when a learned model runs, plus this process).

    A Ray cluster (``address``) schedules on its own CPUs: only the local checks are skipped."""
    from cv2x_marl.sim.memory import format_bytes, memory_limit

    if address is not None or workers == 1:
        return 0
    cpus = parallel.usable_cpus()
    if workers > cpus:
        raise ValueError(
            f"--workers {workers}: this machine lets the run use {cpus} CPU(s); give at most {cpus} (each worker "
            "is a process busy on one CPU: more run no faster and each holds its own memory), or run on a Ray "
            "cluster with --address"
        )
    used = min(workers, max(1, len(jobs)))
    learned = any(str(j.get("policy", "")).startswith("ppo:") for j in jobs)
    per = LEARNED_WORKER_BYTES if learned else WORKER_BYTES
    total = (used + 1) * per
    limit = memory_limit(total)
    if limit is not None and total > limit[0]:
        raise ValueError(
            f"--workers {workers}: about {format_bytes(total)} ({used} worker processes and this one, "
            f"{format_bytes(per)} each{' with torch for the learned models' if learned else ''}), above "
            f"{limit[1]} ({format_bytes(limit[0])}); give fewer --workers"
        )
    return total


def run_benchmark(
    out_dir: Path,
    tasks: Sequence[str] | None = None,
    methods: Sequence[str] | None = None,
    models: Sequence[str] = (),
    episodes: int | None = None,
    workers: int = 1,
    address: str | None = None,
    overwrite: bool = False,
    progress: bool = True,
    task_table: Mapping[str, Task] | None = None,
    backend: str = "ray",
    episodes_per_job: int | None = None,
    rows_from: Path | None = None,
) -> dict[str, Any]:
    """Run the benchmark into the run folder ``out_dir``; returns ``summary.json``'s content.

    Args:
        tasks: task names (default: every task of ``task_table``).
        methods: scripted methods (default: each task's); the ceiling is always run.
        models: ``TASK=ppo:PATH`` / ``TASK/LABEL=ppo:PATH`` (:func:`parse_models`).
        episodes: only the first ``episodes`` held-out seeds (quick runs; None: all).
        workers: parallel jobs (> 1: an embedded local Ray of that many CPUs, or that many processes with
            ``backend="processes"``); address: a Ray cluster.
        task_table: the tasks (default :data:`cv2x_marl.env.tasks.TASKS`).
        backend: ``ray`` or ``processes`` (:data:`BACKENDS`; how jobs run when ``workers > 1``).
        episodes_per_job: held-out episodes per job (None: :data:`EPISODES_PER_JOB` when the jobs run in
            parallel, every episode of a (task, method, run) in one job otherwise). The rows do not depend
            on it.
        rows_from: an earlier ``benchmark.csv`` whose rows of scripted methods and ceilings are taken for the
            same (task, env id, method, seed) instead of running them again (:func:`read_rows`); what it lacks
            runs. Its rows are the code's that wrote them: the run's ``run.json`` records the file.
    """
    from cv2x_marl.env import tasks as task_module

    table = task_module.TASKS if task_table is None else task_table
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ValueError(f"--workers must be an integer >= 1, got {workers!r}")
    if backend not in BACKENDS:
        raise ValueError(f"--backend must be one of {', '.join(BACKENDS)}, got {backend!r}")
    if backend == "processes" and address is not None:
        raise ValueError("--address names a Ray cluster: it goes with --backend ray, not processes")
    in_parallel = workers > 1 or address is not None
    chunk = episodes_per_job if episodes_per_job is not None else (EPISODES_PER_JOB if in_parallel else None)
    jobs = plan_jobs(table, tasks, methods, parse_models(models, table), episodes, chunk)
    earlier = read_rows(rows_from) if rows_from is not None else {}
    todo, reused = reuse_rows(jobs, earlier)
    check_workers(workers, todo, address)
    params: dict[str, Any] = {
        "tasks": list(dict.fromkeys(j["task"] for j in jobs)),
        "methods": list(methods or []),
        "episodes": episodes,
        "models": list(models),
        "rows_from": None if rows_from is None else {"path": str(rows_from), "sha256": sha256_of(rows_from)},
        "reused_jobs": len(reused),
    }
    inputs = [Path(j["policy"][4:]) for j in jobs if j["policy"].startswith("ppo:")]
    inputs += [Path(rows_from)] if rows_from is not None else []
    with run_folder(out_dir, "benchmark", overwrite=overwrite, parameters=params, inputs=inputs):
        t0 = time.perf_counter()
        ran = iter(_execute(todo, workers, address, progress, backend) if todo else [])
        rows = [r for i in range(len(jobs)) for r in (reused[i] if i in reused else next(ran))]
        summary = summarise(rows, table)
        summary["wall_s"] = time.perf_counter() - t0
        out = Path(out_dir)

        def write_csv(tmp: Path) -> None:
            with tmp.open("w", newline="") as fh:
                w = csv.DictWriter(fh, fieldnames=list(CSV_FIELDS))
                w.writeheader()
                w.writerows(rows)

        atomic_write(out / "benchmark.csv", write_csv)
        write_json(out / "summary.json", summary)
        atomic_write(out / "table.md", lambda tmp: tmp.write_text(table_markdown(summary)))
        from cv2x_marl.plotting import plot_benchmark

        plot_benchmark(summary, out / "benchmark.png")
    return summary


def add_arguments(p: argparse.ArgumentParser, count: Callable[[str], Any], overwrite_help: str) -> None:
    """The ``cv2x-marl benchmark`` flags (``count``: the CLI's integer >= 1 type)."""
    p.add_argument("--out", type=Path, required=True, help="run folder: benchmark.csv, summary.json, table.md, .png")
    p.add_argument(
        "--tasks",
        help="tasks, comma-separated (default: singlemover, cooperative, resource; the control task traffic on "
        "request; docs/benchmark.md)",
    )
    p.add_argument("--methods", help="scripted methods, comma-separated (default: each task's; the ceiling always)")
    p.add_argument(
        "--model",
        action="append",
        metavar="TASK[/LABEL]=ppo:PATH",
        help="a learned model on a task (repeatable; several paths or a glob under one label: its training runs)",
    )
    p.add_argument("--episodes", type=count, default=None, help="only the first N held-out seeds (quick runs)")
    p.add_argument("--workers", type=count, default=1, help="parallel jobs (> 1: a local Ray; default 1, no Ray)")
    p.add_argument(
        "--backend",
        choices=BACKENDS,
        default="ray",
        help="with --workers > 1: Ray tasks (default) or spawned processes (no Ray needed)",
    )
    p.add_argument(
        "--episodes-per-job",
        type=count,
        default=None,
        help=f"held-out episodes per job (default: {EPISODES_PER_JOB} in parallel, all in one process)",
    )
    p.add_argument(
        "--rows-from",
        type=Path,
        default=None,
        help="an earlier benchmark.csv: its scripted and ceiling rows are taken instead of run again",
    )
    p.add_argument("--address", help="Ray cluster address (auto, ray://HOST:10001); default: a local Ray")
    p.add_argument("--overwrite", action="store_true", help=overwrite_help)
    p.add_argument("--json", action="store_true", help="print summary.json")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def run_from_args(args: argparse.Namespace) -> int:
    """``cv2x-marl benchmark``."""

    def split(text: str | None) -> list[str] | None:
        return [s.strip() for s in text.split(",") if s.strip()] if text else None

    summary = run_benchmark(
        args.out,
        split(args.tasks),
        split(args.methods),
        args.model or [],
        args.episodes,
        args.workers,
        args.address,
        args.overwrite,
        not args.quiet,
        backend=args.backend,
        episodes_per_job=args.episodes_per_job,
        rows_from=args.rows_from,
    )
    if args.json:
        sys.stdout.write(dumps_json(summary) + "\n")
    else:
        sys.stdout.write(table_markdown(summary))
        print(f"wrote {args.out / 'benchmark.csv'}, summary.json, table.md, benchmark.png ({summary['wall_s']:.0f} s)")
    return 0
