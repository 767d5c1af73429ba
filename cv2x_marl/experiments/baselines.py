"""``cv2x-marl baselines``: every baseline file of a folder on the same held-out episodes.

The files themselves (their keys, how they are read, the policy each describes) are
:mod:`cv2x_marl.policies.baselines`'s. :func:`run_baselines` evaluates each with
:func:`cv2x_marl.experiments.evaluate.evaluate` and writes ``results.json`` and ``results.md`` in the
folder (the table is rendered from the JSON by :func:`render_table`, so a test can check it is current).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from cv2x_marl.experiments.evaluate import evaluate
from cv2x_marl.io import atomic_write, write_json
from cv2x_marl.policies.baselines import Baseline, baseline_files, load_baseline
from cv2x_marl.runs import locked

#: the columns of the results table, in order
COLUMNS = (
    "mean_utility_gain",
    "share_of_optimum",
    "effectiveness",
    "mean_prr_gain",
    "n_prr_drop",
    "jain_fairness",
)


def run_baselines(
    folder: str | Path, episodes: int, seed: int, env_id: str | None = None, progress: bool = True
) -> dict[str, Any]:
    """Evaluate every baseline of ``folder`` on the same episodes; write ``results.json`` and
    ``results.md`` there; return the results. ``env_id`` overrides the files' own env ids."""
    specs = [(p, load_baseline(p)) for p in baseline_files(folder)]
    with locked(folder, "baselines"):  # one run at a time writes the folder's results
        result = _run(specs, folder, episodes, seed, env_id, progress)
        write_json(Path(folder) / "results.json", result)
        atomic_write(Path(folder) / "results.md", lambda p: p.write_text(render_table(result)))
    return result


def _run(
    specs: list[tuple[Path, Baseline]],
    folder: str | Path,
    episodes: int,
    seed: int,
    env_id: str | None,
    progress: bool,
) -> dict[str, Any]:
    rows = []
    for path, spec in specs:  # the file itself: evaluate reads its policy, model, schedule and env
        res = evaluate(env_id or spec.env_id, str(path), episodes, seed, None, progress=progress)
        metrics = {k: res[k] for k in COLUMNS if k != "share_of_optimum"}
        rows.append({"baseline": spec.name, "policy": spec.policy, "env": res["env"], **metrics})
    optimum = {r["env"]: r["mean_utility_gain"] for r in rows if r["policy"] == "optimum"}
    for r in rows:
        best = optimum.get(r["env"])
        r["share_of_optimum"] = r["mean_utility_gain"] / best if best else None
    result = {"episodes": episodes, "seed": seed, "command": _command(folder, episodes, seed, env_id), "rows": rows}
    return result


def _command(folder: str | Path, episodes: int, seed: int, env_id: str | None) -> str:
    env = f" --env {env_id}" if env_id else ""
    return f"cv2x-marl baselines --dir {folder} --episodes {episodes} --seed {seed}{env}"


def render_table(result: dict[str, Any]) -> str:
    """The markdown table of :func:`run_baselines`'s results (deterministic in its input)."""

    def pct(v: Any) -> str:
        return "-" if v is None else f"{100 * v:+.1f} %"

    lines = [
        "# Scripted baselines on held-out episodes",
        "",
        f"Written by `{result['command']}` ({result['episodes']} episodes per env, seed {result['seed']}); "
        "share of the optimum: the method's mean utility gain over the `optimum` baseline's on the same episodes.",
        "",
        "| baseline | policy | env | mean utility gain | share of the optimum | effectiveness | mean PRR gain "
        "| PRR drops | Jain |",
        "|---|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in result["rows"]:
        share = "-" if r.get("share_of_optimum") is None else f"{100 * r['share_of_optimum']:.1f} %"
        lines.append(
            f"| {r['baseline']} | {r['policy']} | {r['env']} | {pct(r['mean_utility_gain'])} | {share} | "
            f"{100 * r['effectiveness']:.1f} % | {pct(r['mean_prr_gain'])} | {r['n_prr_drop']} | "
            f"{r['jain_fairness']:.3f} |"
        )
    return "\n".join(lines) + "\n"
