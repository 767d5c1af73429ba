"""The scripted baselines as users run them: one YAML file per baseline in ``baselines/``.

A baseline file names a scripted policy and its settings::

    # GBMU, the paper's algorithm (steps 1-5), steered by the paper's Table 2 model
    policy: gbmu            # static | random | greedy | gbmu | oracle | planner | sensing | optimum
    model: paper-table2     # two-distance model (gbmu, greedy, planner)
    delta: 100.0            # step size per env step (gbmu, greedy, oracle)
    env_id: cv2x/SingleMover-v2   # the env it runs on when --env is not given
    env: {}                 # env arguments (e.g. replan_every for sensing on Mobility-v2)

``cv2x-marl evaluate --policy baselines/gbmu.yaml`` runs one; ``cv2x-marl baselines`` runs all of a
folder on the same held-out episodes and writes ``results.json`` and ``results.md`` there (the
table is rendered from the JSON by :func:`render_table`, so a test can check it is current).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cv2x_marl.checks import is_real
from cv2x_marl.io import atomic_write, write_json
from cv2x_marl.runs import locked

SCRIPTED = ("static", "random", "greedy", "gbmu", "oracle", "planner", "sensing", "optimum")
KEYS = ("policy", "model", "delta", "env_id", "env", "description")
#: the columns of the results table, in order
COLUMNS = (
    "mean_utility_gain",
    "share_of_optimum",
    "effectiveness",
    "mean_prr_gain",
    "n_prr_drop",
    "jain_fairness",
)


@dataclass(frozen=True)
class Baseline:
    """One baseline file, validated."""

    name: str
    policy: str
    model: str = "paper-table2"
    delta: float = 100.0
    env_id: str = "cv2x/SingleMover-v2"
    env: dict[str, Any] = field(default_factory=dict)
    description: str = ""


def is_baseline_file(spec: str) -> bool:
    """Whether a ``--policy`` value names a baseline file rather than a policy."""
    return spec.endswith((".yaml", ".yml", ".json"))


def load_baseline(path: str | Path) -> Baseline:
    """Read and validate a baseline file; errors name the file, the key and the allowed values."""
    from cv2x_marl.experiments.evaluate import ENV_IDS
    from cv2x_marl.yamlcore import load_mapping

    path = Path(path)
    data = load_mapping(path, "baseline file", ValueError)
    bad = sorted(set(data) - set(KEYS))
    if bad:
        raise ValueError(f"baseline file {path}: unknown key(s) {bad}; keys: {', '.join(KEYS)}")
    policy = data.get("policy")
    if policy not in SCRIPTED:
        raise ValueError(f"baseline file {path}: policy must be one of {', '.join(SCRIPTED)}, got {policy!r}")
    delta = data.get("delta", 100.0)
    if not is_real(delta) or delta <= 0:
        raise ValueError(f"baseline file {path}: delta must be a finite number > 0, got {delta!r}")
    env_id = data.get("env_id", "cv2x/SingleMover-v2")
    if env_id not in ENV_IDS:
        raise ValueError(f"baseline file {path}: env_id must be one of {', '.join(ENV_IDS)}, got {env_id!r}")
    env = data.get("env", {}) or {}
    if not isinstance(env, dict):
        raise ValueError(f"baseline file {path}: env must be a mapping of env arguments, got {env!r}")
    model = data.get("model", "paper-table2")
    if not isinstance(model, str):
        raise ValueError(f"baseline file {path}: model must be a model file or paper-table2, got {model!r}")
    return Baseline(path.stem, policy, model, float(delta), env_id, dict(env), str(data.get("description", "")))


def baseline_files(folder: str | Path) -> list[Path]:
    """The baseline files of a folder, by name."""
    folder = Path(folder)
    if not folder.is_dir():
        raise ValueError(f"baselines folder {folder} does not exist")
    files = sorted(p for p in folder.iterdir() if p.suffix in (".yaml", ".yml", ".json") and p.name != "results.json")
    if not files:
        raise ValueError(f"no baseline files (*.yaml) in {folder}")
    return files


def run_baselines(
    folder: str | Path, episodes: int, seed: int, env_id: str | None = None, progress: bool = True
) -> dict[str, Any]:
    """Evaluate every baseline of ``folder`` on the same episodes; write ``results.json`` and
    ``results.md`` there; return the results. ``env_id`` overrides the files' own env ids."""
    specs = [load_baseline(p) for p in baseline_files(folder)]
    with locked(folder, "baselines"):  # one run at a time writes the folder's results
        result = _run(specs, folder, episodes, seed, env_id, progress)
        write_json(Path(folder) / "results.json", result)
        atomic_write(Path(folder) / "results.md", lambda p: p.write_text(render_table(result)))
    return result


def _run(
    specs: list[Baseline], folder: str | Path, episodes: int, seed: int, env_id: str | None, progress: bool
) -> dict[str, Any]:
    from cv2x_marl.experiments.evaluate import evaluate

    rows = []
    for spec in specs:
        res = evaluate(
            env_id or spec.env_id,
            spec.policy,
            episodes,
            seed,
            None,
            spec.env,
            model_path=spec.model,
            delta=spec.delta,
            progress=progress,
        )
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
