"""Learning curves of the shipped models of issue 28: one figure per task from the ``eval.csv`` of each
``agents/models/<task>_seed<k>/`` (the run's own evaluations during training: the learner, deterministic, and
GBMU on the same ``eval_episodes`` episodes from ``eval_seed``, outside the held-out lists).

    python benchmarks/learning_curves.py [--models agents/models] [--out docs/benchmark/learners]

Writes ``learning-<task>.png`` for every task with shipped models, and the learned utility maps' curves
(their ``curve.csv``: utility gain against CPU seconds) as ``docs/benchmark/learners-map/learning-singlemover-map.png``
(``--maps-out``).
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

from cv2x_marl import plotting

#: the shipped models' folder prefixes, per task
PREFIXES = {
    "singlemover": "singlemover-v3",
    "cooperative": "cooperative",
    "cooperative-v1": "cooperative-v1",
    "traffic": "traffic",
}


def curves_of(models: Path, prefix: str) -> tuple[dict[str, list[dict[str, float]]], str]:
    """The rows of every ``<prefix>_seed<k>/eval.csv`` (float values) and the env id the runs trained on."""
    curves, env_ids = {}, set()
    for run in sorted(models.glob(f"{prefix}_seed*")):
        with (run / "eval.csv").open(newline="") as fh:
            curves[run.name] = [{k: float(v) for k, v in r.items()} for r in csv.DictReader(fh)]
        env_ids.add(json.loads((run / "train_config.json").read_text())["env_id"])
    return curves, ", ".join(sorted(env_ids))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--models", type=Path, default=Path("agents/models"))
    p.add_argument("--out", type=Path, default=Path("docs/benchmark/learners"))
    p.add_argument("--maps-out", type=Path, default=Path("docs/benchmark/learners-map"))
    args = p.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    for task, prefix in PREFIXES.items():
        curves, env_id = curves_of(args.models, prefix)
        if curves:
            path = plotting.plot_learning_curves(
                curves, args.out / f"learning-{task}.png", f"{task}: training on {env_id}"
            )
            print(f"wrote {path} ({len(curves)} runs)")
    maps = {}
    for run in sorted(args.models.glob("singlemover-map_seed*")):
        with (run / "curve.csv").open(newline="") as fh:
            maps[run.name] = list(csv.DictReader(fh))
    if maps:
        args.maps_out.mkdir(parents=True, exist_ok=True)
        title = "singlemover: the learned utility map on cv2x/SingleMover-v3"
        path = plotting.plot_gain_vs_cpu(maps, args.maps_out / "learning-singlemover-map.png", title)
        print(f"wrote {path} ({len(maps)} runs)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
