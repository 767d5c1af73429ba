"""The scripted baselines as users run them: one YAML file per baseline in ``baselines/``.

A baseline file names a scripted policy and its settings::

    # GBMU, the paper's algorithm (steps 1-5), steered by the paper's Table 2 model
    policy: gbmu            # static | random | greedy | gbmu | oracle | planner | sensing | optimum
    model: paper-table2     # two-distance model (gbmu, greedy, planner): paper-table2, a shipped
                            # model (linear-fit, logistic-fit) or a model file / fit folder
    delta: 100.0            # step size per env step (gbmu, greedy, oracle)
    step_schedule: constant # gbmu, greedy: constant (the paper) | decay | backtracking
    decay_k0: 100.0         # step_schedule decay: delta_k = delta / (1 + k / decay_k0), k = env step
    env_id: cv2x/SingleMover-v2   # the env it runs on when --env is not given
    env: {}                 # env arguments (e.g. replan_every for sensing on Mobility-v2)

The shipped models (:data:`SHIPPED_MODELS`, package data ``cv2x_marl/regression/data/NAME.json``)
were fitted on the same stage-1 data, the paper preset's ``cv2x-marl dataset --runs 10 --seed 0``,
by ``cv2x-marl fit --model linear`` and ``--model logistic`` (the command is in each file's
provenance). The step schedules are :class:`~cv2x_marl.policies.gbmu.StepSchedule`'s.

``cv2x-marl evaluate --policy baselines/gbmu.yaml`` runs one; ``cv2x-marl baselines`` runs all of a
folder on the same held-out episodes and writes ``results.json`` and ``results.md`` there (the
table is rendered from the JSON by :func:`render_table`, so a test can check it is current).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cv2x_marl.checks import is_real
from cv2x_marl.io import atomic_write, write_json
from cv2x_marl.policies.gbmu import SCHEDULES, StepSchedule
from cv2x_marl.runs import locked

SCRIPTED = ("static", "random", "greedy", "gbmu", "oracle", "planner", "sensing", "optimum")
KEYS = ("policy", "model", "delta", "step_schedule", "decay_k0", "env_id", "env", "description")
#: two-distance models shipped as package data (``cv2x_marl/regression/data/NAME.json``)
SHIPPED_MODELS = ("linear-fit", "logistic-fit")
#: the policies that take a step schedule
SCHEDULED = ("gbmu", "greedy")
#: the policies that read the two-distance model of their file
MODELLED = ("gbmu", "greedy", "planner", "sensing")


def resolve_model(model: str) -> str:
    """A model name as :func:`~cv2x_marl.experiments.dataset.load_model` reads it: a shipped model's
    name (:data:`SHIPPED_MODELS`) becomes its package-data path; anything else is returned as is."""
    if model not in SHIPPED_MODELS:
        return model
    from importlib.resources import files

    return str(files("cv2x_marl.regression") / "data" / f"{model}.json")


def load_shipped_model(name: str) -> Any:
    """The shipped :class:`~cv2x_marl.regression.model.TwoDistanceModel` ``name`` (:data:`SHIPPED_MODELS`)."""
    from cv2x_marl.regression.model import TwoDistanceModel

    if name not in SHIPPED_MODELS:
        raise ValueError(f"unknown shipped model {name!r}; shipped models: {', '.join(SHIPPED_MODELS)}")
    return TwoDistanceModel.load(resolve_model(name))


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
    step_schedule: str = "constant"
    decay_k0: float = 100.0

    def schedule(self) -> StepSchedule | None:
        """The GBMU step schedule (None: the paper's constant step)."""
        if self.step_schedule == "constant":
            return None
        return StepSchedule(self.step_schedule, decay_k0=self.decay_k0)


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
        raise ValueError(
            f"baseline file {path}: model must be paper-table2, {', '.join(SHIPPED_MODELS)} or a model file, "
            f"got {model!r}"
        )
    if policy in MODELLED:  # the model is read now, so a missing one names this file too
        from cv2x_marl.experiments.dataset import load_model

        try:
            load_model(resolve_model(model))
        except (ValueError, OSError) as exc:
            raise ValueError(f"baseline file {path}: model {model!r}: {exc}") from None
    schedule = data.get("step_schedule", "constant")
    if schedule not in SCHEDULES:
        raise ValueError(f"baseline file {path}: step_schedule must be one of {', '.join(SCHEDULES)}, got {schedule!r}")
    if schedule != "constant" and policy not in SCHEDULED:
        raise ValueError(
            f"baseline file {path}: step_schedule applies to policies {', '.join(SCHEDULED)} only, not {policy!r}"
        )
    k0 = data.get("decay_k0", 100.0)
    if not is_real(k0) or not math.isfinite(k0) or k0 <= 0:
        raise ValueError(f"baseline file {path}: decay_k0 must be a finite number > 0 (env steps), got {k0!r}")
    return Baseline(
        path.stem,
        policy,
        model,
        float(delta),
        env_id,
        dict(env),
        str(data.get("description", "")),
        str(schedule),
        float(k0),
    )


def make_baseline_policy(spec: Baseline, env: Any) -> Any:
    """The policy a baseline file describes, for ``env`` (its model resolved, its step schedule set)."""
    from cv2x_marl.experiments.evaluate import make_policy

    model = resolve_model(spec.model)
    if spec.policy in SCHEDULED:
        from cv2x_marl.experiments.dataset import load_model
        from cv2x_marl.policies.scripted import GbmuPolicy

        return GbmuPolicy(
            load_model(model), env.layout, env.max_step_m, spec.delta, spec.policy == "gbmu", spec.schedule()
        )
    return make_policy(spec.policy, env, model, spec.delta)


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
    from cv2x_marl.experiments.evaluate import evaluate

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
