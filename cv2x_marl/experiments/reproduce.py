"""`cv2x-marl reproduce`: the whole story in one command (what `make run` runs).

stage-1 dataset -> stage-2 fit (Tables 2-3) -> GBMU study (Fig. 9-10) -> evaluation of the
shipped PPO movers against static, random, GBMU, greedy and the oracle on the same held-out
episodes of both envs -> the benchmark (every task's scripts, shipped learners and ceiling on its
held-out episodes, :mod:`cv2x_marl.experiments.benchmark`) -> ``REPORT.md`` with the figures and
tables, and ``report.json``.

The PPO models are an input, checked before anything runs or is written (:func:`check_models`):
a folder that does not exist or lacks the models of either env is refused; ``models_dir=None``
(``--models none``) leaves PPO out on purpose, and then the report has no PPO rows. ``REPORT.md``
cites only the figures and tables that were written.
"""

from __future__ import annotations

import re
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from cv2x_marl.config import preset
from cv2x_marl.experiments.benchmark import run_benchmark
from cv2x_marl.experiments.dataset import build_dataset, run_fit
from cv2x_marl.experiments.evaluate import evaluate
from cv2x_marl.experiments.gbmu_study import run_study
from cv2x_marl.extras import missing_extra
from cv2x_marl.io import atomic_write, write_json
from cv2x_marl.parallel import usable_cpus
from cv2x_marl.regression.model import load_model
from cv2x_marl.runs import RunFolder

SCRIPTED = ("static", "random", "greedy", "gbmu", "oracle", "planner", "sensing", "optimum")
ENVS = {"single": "cv2x/SingleMover-v2", "multi": "cv2x/Mobility-v2"}
#: env options of the scripted methods: those of the shipped models' training configs that change
#: what a scripted method does (the sensing planner follows the env's plan, replanned halfway)
ENV_OPTIONS: dict[str, dict[str, Any]] = {"single": {}, "multi": {"replan_every": 50}}
KEYS = ("mean_utility_gain", "effectiveness", "mean_prr_gain", "jain_fairness", "n_prr_drop")


#: what ``--models`` says to leave the PPO models out
NO_MODELS = "none"
#: the shipped learners of each benchmark task, under the models folder (a glob: the training runs of one method);
#: ``TASK`` (the default label) or ``TASK/LABEL``
BENCHMARK_MODELS = {
    "singlemover": "singlemover-v3_seed*/model.zip",
    "singlemover/map": "singlemover-map_seed*/model.npz",
    "cooperative": "cooperative_seed*/model.pt",
    "resource/ippo": "resource-ippo_seed*/model.pt",
}


def benchmark_models(models_dir: Path | None) -> list[str]:
    """``TASK[/LABEL]=ppo:GLOB`` of every benchmark task whose shipped learners ``models_dir`` holds (none: scripts
    only)."""
    if models_dir is None:
        return []
    return [
        f"{task}=ppo:{Path(models_dir) / pattern}"
        for task, pattern in BENCHMARK_MODELS.items()
        if any(Path(models_dir).glob(pattern))
    ]


def shipped_models(models_dir: Path, kind: str) -> list[Path]:
    """``agents/models/<kind>_seed<N>/model.zip``, sorted by seed (other folder names are not models)."""
    pattern = re.compile(rf"{re.escape(kind)}_seed(\d+)")
    found = [p for p in Path(models_dir).glob(f"{kind}_seed*/model.zip") if pattern.fullmatch(p.parent.name)]
    return sorted(found, key=lambda p: int(p.parent.name.split("seed")[1]))


def check_models(models_dir: Path | None) -> dict[str, list[Path]]:
    """The PPO models of each env (:data:`ENVS`) in ``models_dir``, checked before any work.

    Args:
        models_dir: the folder of ``single_seed<N>/model.zip`` and ``multi_seed<N>/model.zip``
            (``cv2x-marl train`` run folders; ``agents/models`` ships them); None: no PPO rows.

    Raises:
        ValueError: the folder does not exist, or holds no model for one of the envs (the message
            names the folder and what it expected).
        MissingExtraError: stable-baselines3, which loads the models, is not installed.
    """
    if models_dir is None:
        return {}
    models_dir = Path(models_dir)
    expected = " and ".join(f"{kind}_seed<N>/model.zip" for kind in ENVS)
    hint = (
        f"(PPO models saved by `cv2x-marl train`, as agents/models ships them), or --models {NO_MODELS} to leave "
        "PPO out"
    )
    if not models_dir.is_dir():
        raise ValueError(f"--models {models_dir}: no such folder; expected one holding {expected} {hint}")
    models = {kind: shipped_models(models_dir, kind) for kind in ENVS}
    missing = [f"{kind}_seed<N>/model.zip" for kind, found in models.items() if not found]
    if missing:
        raise ValueError(f"--models {models_dir} holds no {' and no '.join(missing)}; expected {expected} {hint}")
    import importlib.util

    if importlib.util.find_spec("stable_baselines3") is None:
        raise missing_extra("stable_baselines3", f"evaluating the PPO models of --models {models_dir}")
    return models


def written_files(out: Path) -> list[str]:
    """The figures and tables under ``out`` (paths relative to it, sorted): what ``REPORT.md`` may cite."""
    return sorted(p.relative_to(out).as_posix() for p in Path(out).rglob("*") if p.suffix in (".png", ".md"))


def _row(method: str, results: list[dict[str, Any]]) -> dict[str, Any]:
    row: dict[str, Any] = {"method": method, "n_seeds": len(results)}
    for k in KEYS:
        vals = np.array([r[k] for r in results], dtype=float)
        row[k] = float(vals.mean())
        row[k + "_std"] = float(vals.std(ddof=1)) if vals.size > 1 else 0.0
    return row


def reproduce(
    out: Path,
    quick: bool = False,
    seed: int = 0,
    models_dir: Path | None = Path("agents/models"),
    progress: bool = True,
    overwrite: bool = False,
) -> dict[str, Any]:
    """Run every stage into the run folder ``out`` (one run folder per stage inside it); return the report.

    ``models_dir`` is checked first (:func:`check_models`; None: no PPO rows): a missing folder or
    missing models are refused before ``out`` is touched."""
    models = check_models(models_dir)
    learners = benchmark_models(models_dir)
    params = {"quick": quick, "seed": seed, "models_dir": None if models_dir is None else str(models_dir)}
    inputs = [] if models_dir is None else [models_dir]
    with RunFolder(out, "reproduce", overwrite=overwrite, parameters=params, inputs=inputs):
        return _reproduce(Path(out), quick, seed, models, progress, learners)


def _reproduce(
    out: Path, quick: bool, seed: int, models: dict[str, list[Path]], progress: bool, learners: list[str]
) -> dict[str, Any]:
    from cv2x_marl import plotting

    t0 = time.perf_counter()
    settings: dict[str, Any] = {
        "runs": 4 if quick else 10,
        "realizations": 48 if quick else 144,
        "iterations": 2000 if quick else 10_000,
        "episodes_single": 48 if quick else 144,
        "episodes_multi": 12 if quick else 144,
        "episodes_benchmark": 4 if quick else None,  # per task; None: every held-out episode
    }
    log = (lambda msg: print(msg, file=sys.stderr)) if progress else (lambda msg: None)
    cfg = preset("paper")
    log(f"[1/5] stage-1 dataset: {settings['runs']} paper runs")
    build_dataset(cfg, settings["runs"], seed, out / "dataset", progress=False)
    log("[2/5] stage-2 fit (linear eq. 15, compared with logistic)")
    fit = run_fit(out / "dataset", out / "fit", compare=True)
    log(f"[3/5] GBMU study: {settings['realizations']} realisations x {settings['iterations']} iterations")
    study = {}
    for name, model_path in (("paper-table2", "paper-table2"), ("ours", str(out / "fit"))):
        study[name] = run_study(
            "realizations",
            cfg,
            load_model(Path(model_path)),
            out / f"gbmu-{name}",
            seed=seed,
            realizations=settings["realizations"],
            iterations=settings["iterations"],
            progress=False,
        )
    log("[4/5] movers on the env: scripted policies and the shipped PPO models")
    tables: dict[str, list[dict[str, Any]]] = {}
    for kind, env_id in ENVS.items():
        episodes = settings[f"episodes_{kind}"]
        rows = []
        for method in SCRIPTED:
            res = evaluate(
                env_id, method, episodes, seed, out / f"eval-{kind}-{method}", ENV_OPTIONS[kind], progress=False
            )
            rows.append(_row(method, [res]))
            log(f"  {kind} {method}: utility gain {res['mean_utility_gain']:+.1%}")
        ppo_models = models.get(kind, [])
        if ppo_models:
            per_seed = [
                evaluate(None, f"ppo:{m}", episodes, seed, out / f"eval-{kind}-ppo-{m.parent.name}", progress=False)
                for m in ppo_models
            ]
            rows.append(_row(f"ppo ({len(ppo_models)} seeds)", per_seed))
            log(f"  {kind} ppo: utility gain {rows[-1]['mean_utility_gain']:+.1%} over {len(ppo_models)} seeds")
        best = next((r for r in rows if r["method"] == "optimum"), None)
        for r in rows:  # every method against the optimum on the same episodes
            r["share_of_optimum"] = r["mean_utility_gain"] / best["mean_utility_gain"] if best else float("nan")
        tables[kind] = rows
        plotting.plot_method_comparison(
            rows, out / f"comparison-{kind}.png", f"{env_id}: {episodes} held-out episodes (seed {seed})"
        )
        curves = {}
        for m in ppo_models:
            csv_path = m.parent / "eval.csv"
            if csv_path.exists():
                lines = csv_path.read_text().splitlines()
                head = lines[0].split(",")
                curves[m.parent.name] = [dict(zip(head, map(float, ln.split(",")), strict=True)) for ln in lines[1:]]
        if curves:
            plotting.plot_learning_curves(curves, out / f"learning-{kind}.png", f"PPO training on {env_id}")
    n_bench = settings["episodes_benchmark"]
    log(f"[5/5] the benchmark: scripts, shipped learners and ceiling on {n_bench or 'all'} held-out episodes per task")
    workers = min(2, usable_cpus())
    bench = run_benchmark(
        out / "benchmark", models=learners, episodes=n_bench, workers=workers, progress=False,
        backend="processes", episodes_per_job=n_bench,
    )  # fmt: skip
    report = {
        "quick": quick,
        "seed": seed,
        "settings": settings,
        "fit": {"per_nsv": fit["per_nsv"], "comparison": fit.get("comparison")},
        "gbmu_study": {k: {m: v["methods"][m] for m in v["methods"]} for k, v in study.items()},
        "movers": tables,
        "benchmark": {"tasks": list(bench["tasks"]), "learners": learners, "wall_s": bench["wall_s"]},
        "ppo": bool(models),
        "runtime_s": time.perf_counter() - t0,
    }
    report["benchmark_table"] = (out / "benchmark" / "table.md").read_text(encoding="utf-8")
    report["files"] = written_files(out)  # what the markdown may cite (REPORT.md itself comes next)
    write_json(out / "report.json", report)
    atomic_write(out / "REPORT.md", lambda p: p.write_text(_markdown(report)))
    log(f"done in {report['runtime_s']:.0f} s: {out / 'REPORT.md'}")
    return report


def _pct(x: float) -> str:
    return f"{100 * x:+.1f} %"


def _cite(files: list[str], names: list[str], what: str = "Figures") -> list[str]:
    """``What: `a`, `b`.`` for those of ``names`` that were written (none: no line)."""
    have = [n for n in names if n in files]
    return [f"{what}: " + ", ".join(f"`{n}`" for n in have) + "."] if have else []


def _markdown(r: dict[str, Any]) -> str:
    s = r["settings"]
    files = list(r.get("files", []))
    ppo = bool(r.get("ppo", True))
    models = "" if ppo else f" --models {NO_MODELS}"
    lines = [
        "# cv2x_marl report",
        "",
        f"Produced by `cv2x-marl reproduce{' --quick' if r['quick'] else ''} --seed {r['seed']}{models}` "
        f"in {r['runtime_s']:.0f} s." + ("" if ppo else " No PPO models were evaluated."),
        "",
        f"## Stage 2: two-distance model ({s['runs']} paper runs)",
        "",
        "| NSV | alpha | beta | gamma | R^2 train | R^2 held out | instances |",
        "|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for row in r["fit"]["per_nsv"]:
        fb = f" (from NSV {row['fallback_from']})" if row.get("fallback_from") is not None else ""
        lines.append(
            f"| {row['nsv']} | {row['alpha']:.2f} | {row['beta']:.2f} | {row['gamma']:.2f} | {row['r2']:.2f} | "
            f"{row['r2_test']:.2f} | {row['instances']}{fb} |"
        )
    if r["fit"]["comparison"]:
        lines += ["", "| model | R^2 held out | Brier | log-loss |", "|---|---:|---:|---:|"]
        for k, v in r["fit"]["comparison"].items():
            lines.append(f"| {k} | {v['r2']:.3f} | {v['brier']:.4f} | {v['log_loss']:.4f} |")
    cited = _cite(files, ["fit/fig2_surface.png", "fit/fit_quality.png"])
    cited += _cite(files, ["fit/table2.md", "fit/table3.md"], "Tables")
    lines += [""] + ([" ".join(cited), ""] if cited else [])
    lines += [
        f"## GBMU study ({s['realizations']} realisations, {s['iterations']} iterations, step 1)",
        "",
        "| model | method | effectiveness | mean utility gain | share of the optimum's gain | mean PRR gain "
        "| PRR drops |",
        "|---|---|---:|---:|---:|---:|---:|",
    ]
    for model, methods in r["gbmu_study"].items():
        for m, v in methods.items():
            share = v.get("share_of_optimum")
            lines.append(
                f"| {model} | {m} | {v['effectiveness']:.1%} | {_pct(v['mean_utility_gain'])} | "
                f"{'-' if share is None else f'{share:.0%}'} | {_pct(v['mean_prr_gain'])} | {v['n_prr_drop']} |"
            )
    gbmu_figures = _cite(files, [f"gbmu-{model}/fig9_fig10_gains.png" for model in r["gbmu_study"]])
    lines += ["", " ".join(["Paper (Fig. 9-10): 93 %, +15 %, +5 %, 40 of 144.", *gbmu_figures])]
    for kind, rows in r["movers"].items():
        n_ep = s[f"episodes_{kind}"]
        lines += [
            "",
            f"## Movers on `{ENVS[kind]}` ({n_ep} held-out episodes"
            + ("; PPO: mean +- std over training seeds)" if any(row["n_seeds"] > 1 for row in rows) else ")"),
            "",
            "| method | mean utility gain | share of the optimum's gain | effectiveness | mean PRR gain | Jain "
            "| PRR drops |",
            "|---|---:|---:|---:|---:|---:|---:|",
        ]
        for row in rows:
            sd = row["n_seeds"] > 1

            def cell(k: str, fmt: str, row: dict[str, Any] = row, sd: bool = sd) -> str:
                v = format(100 * row[k], fmt) + " %" if fmt else f"{row[k]:.3f}"
                if sd:
                    v += " +- " + (format(100 * row[k + "_std"], ".1f") + " %" if fmt else f"{row[k + '_std']:.3f}")
                return v

            share = 100 * row.get("share_of_optimum", float("nan"))
            lines.append(
                f"| {row['method']} | {cell('mean_utility_gain', '+.1f')} | {share:.0f} % | "
                f"{cell('effectiveness', '.1f')} | "
                f"{cell('mean_prr_gain', '+.1f')} | {cell('jain_fairness', '')} | {row['n_prr_drop']:.1f} |"
            )
        lines += ["", *_cite(files, [f"comparison-{kind}.png", f"learning-{kind}.png"])]
    bench = r.get("benchmark")
    if bench is not None and "benchmark/table.md" in files:
        n = s.get("episodes_benchmark")
        lines += [
            "",
            f"## The benchmark ({'every' if n is None else n} held-out episode{'s' if n != 1 else ''} per task)",
            "",
            "Every task's scripts, its ceiling and the shipped learners (`ppo`, and `map` on singlemover: the learned "
            "utility map; each its training runs pooled) on the "
            "same held-out episodes; utility gain and share of the ceiling as IQM with 95 % bootstrap intervals "
            "(docs/benchmark.md). With few episodes the intervals are wide: `cv2x-marl benchmark` runs them all.",
            "",
            r["benchmark_table"].strip(),
            "",
            *_cite(files, ["benchmark/benchmark.png"]),
        ]
    return "\n".join(lines) + "\n"
