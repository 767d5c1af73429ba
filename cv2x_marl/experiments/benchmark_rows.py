"""The rows of `cv2x-marl benchmark` and what is made of them: ``benchmark.csv``'s columns, an earlier file's rows
read back and reused (``--rows-from``), the protocol's statistics per task and method (``summary.json``) and
``table.md``. :mod:`cv2x_marl.experiments.benchmark` plans and runs the jobs that make the rows and re-exports
these names.

Like :mod:`cv2x_marl.experiments.benchmark`, this module imports only the standard library at its top (the CLI
builds its parser from that module, which imports this one): numpy, the statistics and the policy registry are
imported in the functions that use them.
"""

from __future__ import annotations

import csv
import io
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from cv2x_marl.env.tasks import Task


#: the per-episode columns of ``benchmark.csv`` (means over the episode's movers)
CSV_FIELDS = (
    "task",
    "env_id",
    "method",
    "run",
    "policy",
    "episode",
    "seed",
    "utility_start",
    "utility_end",
    "utility_gain",
    "prr_start",
    "prr_end",
    "prr_gain",
    "ceiling_gain",
    "share_of_ceiling",
)


def read_rows(path: Path) -> dict[tuple[str, str, str, int], dict[str, Any]]:
    """The episode rows of an earlier ``benchmark.csv`` (``--rows-from``), keyed by (task, env id, method,
    seed), for scripted methods and ceilings only (run 0; a learned model's file may have changed since).

    Raises:
        ValueError: naming ``--rows-from``, the file and, for a bad value, its line and column: not a file,
            not UTF-8 text, other columns, a row cut short or too long, a value that is not a number.
    """
    from cv2x_marl.policies.registry import PPO_PREFIX

    path = Path(path)
    where = f"--rows-from {path}"
    if not path.is_file():
        raise ValueError(f"--rows-from: no file {path}" + (" (it is a folder)" if path.is_dir() else ""))
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise ValueError(f"{where}: not a benchmark.csv (not UTF-8 text: byte {exc.start} is not valid)") from None
    if text and not text.endswith("\n"):
        last = text.count("\n") + 1
        raise ValueError(
            f"{where}, line {last}: the last row does not end the line (a file cut short?); run the benchmark "
            "without --rows-from, or with an intact file"
        )
    reader = csv.DictReader(io.StringIO(text, newline=""))
    try:
        fields = tuple(reader.fieldnames or ())
    except csv.Error as exc:
        raise ValueError(f"{where}: not a benchmark.csv ({exc})") from None
    if fields != CSV_FIELDS:
        raise ValueError(f"{where}: not a benchmark.csv; its columns must be {', '.join(CSV_FIELDS)}")
    out = {}
    try:
        for r in reader:
            line = reader.line_num
            extra = r.pop(None, None) or []  # a row too long: its extra values
            missing = sum(v is None for v in r.values())
            if extra or missing:
                n = len(CSV_FIELDS) - missing + len(extra)
                raise ValueError(
                    f"{where}, line {line}: {n} values, a row has {len(CSV_FIELDS)} (a file cut short or "
                    "edited?); run the benchmark without --rows-from, or with an intact file"
                )
            if r["policy"].startswith(PPO_PREFIX) or r["run"] != "0":
                continue
            row: dict[str, Any] = dict(r)
            for k in CSV_FIELDS:
                kind = int if k in ("run", "episode", "seed") else float if k in CSV_FIELDS[7:] else None
                if kind is None:
                    continue
                try:
                    row[k] = kind(r[k])
                except ValueError:
                    want = "an integer" if kind is int else "a number"
                    raise ValueError(f"{where}, line {line}, column {k}: {r[k]!r} is not {want}") from None
            out[(r["task"], r["env_id"], r["method"], row["seed"])] = row
    except csv.Error as exc:
        raise ValueError(f"{where}, line {reader.line_num}: not a benchmark.csv ({exc})") from None
    return out


def sha256_of(path: Path) -> str:
    """The SHA-256 of a file (what ``--rows-from`` read: recorded in the run's ``run.json``)."""
    import hashlib

    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def reuse_rows(
    jobs: list[dict[str, Any]], earlier: Mapping[tuple[str, str, str, int], dict[str, Any]]
) -> tuple[list[dict[str, Any]], dict[int, list[dict[str, Any]]]]:
    """Split ``jobs`` into those still to run and, per job index, the rows taken from ``earlier`` (a scripted
    method or ceiling with a row for every one of its seeds; the episode numbering is the job's)."""
    todo, reused = [], {}
    for i, job in enumerate(jobs):
        keys = [(job["task"], job["env_id"], job["method"], s) for s in job["seeds"]]
        if job["policy"] == job["method"] and all(k in earlier for k in keys):
            first = job.get("first_episode", 0)
            reused[i] = [{**earlier[k], "episode": first + e} for e, k in enumerate(keys)]
        else:
            todo.append(job)
    return todo, reused


def summarise(rows: list[dict[str, Any]], tasks: Mapping[str, Task]) -> dict[str, Any]:
    """Per task and method the protocol's statistics from the episode rows (which gain their
    ``ceiling_gain`` and ``share_of_ceiling`` here); per method in every task the aggregate share."""
    import numpy as np

    from cv2x_marl import stats
    from cv2x_marl.experiments.protocol import BOOTSTRAP_SEED, interval

    out: dict[str, Any] = {"tasks": {}}
    shares: dict[str, dict[str, np.ndarray]] = {}
    for name in dict.fromkeys(r["task"] for r in rows):
        task = tasks[name]
        mine = [r for r in rows if r["task"] == name]
        episodes = max(r["episode"] for r in mine) + 1
        ceiling = np.full(episodes, np.nan)
        for r in mine:
            if r["method"] == task.ceiling and r["run"] == 0:
                ceiling[r["episode"]] = r["utility_gain"]
        for r in mine:
            c = ceiling[r["episode"]]
            r["ceiling_gain"] = float(c)
            r["share_of_ceiling"] = float(r["utility_gain"] / c) if c != 0 and np.isfinite(c) else float("nan")
        methods: dict[str, Any] = {}
        for method in dict.fromkeys(r["method"] for r in mine):
            sel = [r for r in mine if r["method"] == method]
            runs = max(r["run"] for r in sel) + 1
            grid = {k: np.full((runs, episodes), np.nan) for k in ("utility_gain", "share_of_ceiling", "prr_end")}
            for r in sel:
                for k, g in grid.items():
                    g[r["run"], r["episode"]] = r[k]
            shares.setdefault(method, {})[name] = grid["share_of_ceiling"]
            entry: dict[str, Any] = {
                "runs": runs,
                "episodes": episodes,
                "policy": sel[0]["policy"],
                "env_id": sel[0]["env_id"],
            }
            entry["iqm_utility_gain"], entry["ci95_utility_gain"] = interval(grid["utility_gain"])
            entry["iqm_share_of_ceiling"], entry["ci95_share_of_ceiling"] = interval(grid["share_of_ceiling"])
            entry["mean_utility_gain"] = float(np.nanmean(grid["utility_gain"]))
            entry["mean_prr"] = float(np.nanmean(grid["prr_end"]))
            methods[method] = entry
        out["tasks"][name] = {
            "env_id": task.env_id,
            "ceiling": task.ceiling,
            "episodes": episodes,
            "seeds": [r["seed"] for r in mine if r["method"] == task.ceiling and r["run"] == 0],
            "methods": methods,
        }
    if len(out["tasks"]) > 1:  # rliable's aggregate: the tasks are the strata
        agg = {}
        for method, per_task in shares.items():
            if set(per_task) == set(out["tasks"]):
                point, lo, hi = stats.bootstrap_ci(list(per_task.values()), np.random.default_rng(BOOTSTRAP_SEED))
                agg[method] = {"iqm_share_of_ceiling": point, "ci95_share_of_ceiling": [lo, hi]}
        out["all_tasks"] = agg
    out["bootstrap"] = {
        "statistic": "iqm",
        "resamples": stats.N_RESAMPLES,
        "level": stats.LEVEL,
        "seed": BOOTSTRAP_SEED,
        "resampled": "runs and episodes (crossed) within each task; tasks are strata",
    }
    return out


def _pct(v: float, sign: str = "+") -> str:
    """A fraction as a percentage of one decimal (``n/a`` for NaN)."""
    return "n/a" if v != v else format(100 * v, sign + ".1f")


def _ci(ci: Sequence[float], sign: str = "+") -> str:
    return "n/a" if ci[0] != ci[0] else f"[{_pct(ci[0], sign)}, {_pct(ci[1], sign)}]"


def table_markdown(summary: dict[str, Any]) -> str:
    """``table.md``: per task one table of its methods (IQM and 95 % CI of the utility gain and of the
    share of the ceiling, in %, and the mean PRR at the end of the episodes)."""
    lines = []
    for name, task in summary["tasks"].items():
        lines += [
            f"### {name} (`{task['env_id']}`), {task['episodes']} held-out episodes, ceiling `{task['ceiling']}`",
            "",
            "| method | runs | utility gain, IQM (%) | 95 % CI | share of the ceiling, IQM (%) | 95 % CI | mean PRR |",
            "|---|---|---|---|---|---|---|",
        ]
        for method, m in task["methods"].items():
            lines.append(
                f"| {method} | {m['runs']} | {_pct(m['iqm_utility_gain'])} | {_ci(m['ci95_utility_gain'])} | "
                f"{_pct(m['iqm_share_of_ceiling'], '')} | {_ci(m['ci95_share_of_ceiling'], '')} | {m['mean_prr']:.4f} |"
            )
        lines.append("")
        variant = [
            f"`{method}` on `{m['env_id']}`"
            for method, m in task["methods"].items()
            if m.get("env_id", task["env_id"]) != task["env_id"]
        ]
        if variant:
            lines += [f"On a variant of the task (the same episodes): {', '.join(variant)}.", ""]
    if summary.get("all_tasks"):
        lines += [
            "### All tasks (share of the ceiling, the tasks as strata)",
            "",
            "| method | IQM (%) | 95 % CI |",
            "|---|---|---|",
        ]
        for method, m in summary["all_tasks"].items():
            lines.append(
                f"| {method} | {_pct(m['iqm_share_of_ceiling'], '')} | {_ci(m['ci95_share_of_ceiling'], '')} |"
            )
        lines.append("")
    return "\n".join(lines)
