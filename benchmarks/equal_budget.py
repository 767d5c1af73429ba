"""The learnability comparison on ``cv2x/SingleMover-v3`` at one budget of agent-steps (docs/benchmark.md, "Learners at
equal budget"): every learner variant trained for the same agent-steps, five seeds each, then scored on the task's
48 held-out episodes next to the scripts and the ceiling.

    python benchmarks/equal_budget.py [--timesteps 38400] [--seeds 0 1 2 3 4] [--workers 2]
                                      [--runs runs/equal-budget] [--out docs/benchmark/equal-budget]

Variants (``VARIANTS``: label -> training config):

    map            the learned utility map (agents/configs/map_single_v3.yaml; its shipped budget is 38,400)
    ppo-deepsets   SB3 PPO, the deepsets encoder (ppo_single_v3_deepsets.yaml, the shipped PPO's configuration)
    ppo-mlp        SB3 PPO on the flat observation (ppo_single_v3_mlp.yaml)
    bc             behaviour cloning of ``sensing`` (imitation_single_v3_bc.yaml; learns from an expert)
    dagger         DAgger of ``sensing`` (imitation_single_v3_dagger.yaml; learns from an expert)

Each run is one ``cv2x-marl train`` process (``--runs/<label>_seed<k>``; an existing run folder with a model is
kept, not trained again); its CPU seconds are the process's user + system time (``os.wait4``). A variant whose
config, seed and budget match a shipped model (``agents/models/shipped.csv``: the utility map at 38,400) uses
that model and its recorded CPU seconds instead. Then one
``cv2x-marl benchmark --tasks singlemover`` scores every variant's runs pooled (``--model``), taking the scripts'
and the ceiling's rows from ``docs/benchmark/benchmark.csv`` (``--rows-from``). Writes ``budget.csv`` (label, seed,
agent-steps, CPU-s) and the benchmark's files (``benchmark.csv``, ``table.md``, ``summary.json``,
``benchmark.png``) to ``--out``.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "agents" / "configs"
VARIANTS = {
    "map": ("map_single_v3.yaml", "model.npz"),
    "ppo-deepsets": ("ppo_single_v3_deepsets.yaml", "model.zip"),
    "ppo-mlp": ("ppo_single_v3_mlp.yaml", "model.zip"),
    "bc": ("imitation_single_v3_bc.yaml", "model.pt"),
    "dagger": ("imitation_single_v3_dagger.yaml", "model.pt"),
}
CLI = [sys.executable, "-m", "cv2x_marl.cli"]
SHIPPED = ROOT / "agents" / "models"


def shipped_run(label: str, seed: int, timesteps: int) -> tuple[Path, float] | None:
    """A shipped model trained with this variant's config, seed and budget (``agents/models/shipped.csv``), and
    its recorded CPU seconds; None when there is none (the variant is trained)."""
    config = f"agents/configs/{VARIANTS[label][0]}"
    with (SHIPPED / "shipped.csv").open(newline="") as f:
        for r in csv.DictReader(f):
            if r["config"] == config and int(r["seed"]) == seed and int(r["timesteps"]) == timesteps:
                return SHIPPED / r["name"], float(r["cpu_s"])
    return None


def train(label: str, seed: int, timesteps: int, runs: Path) -> dict[str, object]:
    """Train one run in its own process (kept when its model exists); its CPU seconds (user + system)."""
    config, model = VARIANTS[label]
    shipped = shipped_run(label, seed, timesteps)
    if shipped is not None:  # the same config, seed and budget: the shipped run (same seed, same model)
        run = str(shipped[0].relative_to(ROOT)) if Path.cwd() == ROOT else str(shipped[0])
        return {"label": label, "seed": seed, "timesteps": timesteps, "cpu_s": shipped[1], "run": run}
    out = runs / f"{label}_seed{seed}"
    budget_file = out / "budget.json"
    if (out / model).exists() and budget_file.exists():
        return json.loads(budget_file.read_text())
    cmd = [*CLI, "train", "--config", str(CONFIGS / config), "--timesteps", str(timesteps), "--seed", str(seed)]
    cmd += ["--out", str(out), "--quiet", "--overwrite"]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    err = proc.stderr.read().decode() if proc.stderr else ""
    if proc.returncode != 0:
        raise SystemExit(f"training {label} seed {seed} failed ({proc.returncode}):\n{err[-2000:]}")
    cpu_s = round(usage.ru_utime + usage.ru_stime, 2)
    row = {"label": label, "seed": seed, "timesteps": timesteps, "cpu_s": cpu_s, "run": str(out)}
    budget_file.write_text(json.dumps(row))
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--timesteps", type=int, default=38_400, help="agent-steps of every run")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    ap.add_argument("--workers", type=int, default=2, help="training processes at once")
    ap.add_argument("--runs", type=Path, default=Path("runs/equal-budget"))
    ap.add_argument("--out", type=Path, default=Path("docs/benchmark/equal-budget"))
    ap.add_argument("--episodes", type=int, default=None, help="only the first N held-out episodes (quick look)")
    args = ap.parse_args()
    if args.timesteps < 1 or args.workers < 1:
        sys.exit("--timesteps and --workers must be >= 1")
    args.runs.mkdir(parents=True, exist_ok=True)
    jobs = [(label, seed) for label in args.variants for seed in args.seeds]
    with ThreadPoolExecutor(args.workers) as pool:
        rows = list(pool.map(lambda j: train(j[0], j[1], args.timesteps, args.runs), jobs))
    for r in rows:
        print(f"{r['label']} seed {r['seed']}: {r['timesteps']} agent-steps, {r['cpu_s']} CPU-s", flush=True)
    cmd = [*CLI, "benchmark", "--tasks", "singlemover", "--out", str(args.out), "--overwrite", "--quiet"]
    cmd += ["--rows-from", str(ROOT / "docs" / "benchmark" / "benchmark.csv")]
    cmd += ["--workers", str(args.workers), "--backend", "processes"]
    if args.episodes:
        cmd += ["--episodes", str(args.episodes)]
    for label in args.variants:
        for r in rows:
            if r["label"] == label:
                cmd += ["--model", f"singlemover/{label}=ppo:{r['run']}/{VARIANTS[label][1]}"]
    subprocess.run(cmd, check=True)
    with (args.out / "budget.csv").open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["label", "seed", "timesteps", "cpu_s", "run"])
        w.writeheader()
        w.writerows(rows)
    print((args.out / "table.md").read_text())


if __name__ == "__main__":
    main()
