"""Issue 26: re-run the shipped models' held-out tables and compare them with the recorded ones.

It also replays every run of ``tests/data/reference_26/prr.json`` (``cv2x-marl simulate`` of every preset for
seeds 0, 1 and 2, of which the test suite replays all but the slow SUMO ones), unless ``--no-prr``.

The tables are those of ``docs/results.md`` ("Every method against the optimum"): ``cv2x-marl evaluate``
on ``cv2x/SingleMover-v2`` (144 held-out episodes, ``--seed 2026``) and ``cv2x/Mobility-v2`` (48 episodes,
``--seed 2026``), every scripted policy of the tables and the ten shipped PPO models
(``agents/models/{single,multi}_seed{0..4}/model.zip``). The references were recorded at commit b9b8a2c
(before the refactor of issue 26) with ``--record`` into ``tests/data/reference_26/heldout/``: per run its
``summary.json`` (without the wall time ``runtime_s``) and ``episodes.csv`` (gzipped).

Usage (from the repository root)::

    PYTHONPATH=$PWD python benchmarks/check_references.py            # compare; exit 1 on any difference
    PYTHONPATH=$PWD python benchmarks/check_references.py --only single-gbmu multi-ppo0
    PYTHONPATH=$PWD python benchmarks/check_references.py --record   # rewrite the references (on purpose only)

Comparison is exact (every numeric cell of ``episodes.csv`` and every value of ``summary.json``): the
refactor is meant to run the same arithmetic. The largest absolute difference over all runs is printed
either way. Wall time: 15 s to 13 min per row on the 2-core development machine while shared with other
jobs (load about 7; ``heldout/walltimes.json`` has each recorded row's), about 2 h for all rows; most of it is
``multi-optimum`` and the five ``multi-ppo`` rows. ``--only NAME ...`` runs some rows.
"""

from __future__ import annotations

import argparse
import csv
import gzip
import json
import math
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "tests" / "data" / "reference_26"
REF = DATA / "heldout"
SEED = "2026"
#: values of summary.json that measure the machine, not the result
VOLATILE = ("runtime_s",)
#: the same for the simulate summaries of prr.json (wall times, versions, the resolved configuration)
PRR_VOLATILE = ("runtime_s", "total_runtime_s", "versions", "config")


def runs(single_episodes: str = "144", multi_episodes: str = "48") -> dict[str, list[str]]:
    """Name -> the ``cv2x-marl evaluate`` arguments of every row of the held-out tables (the test suite's
    slice, ``tests/reference/test_references.py``, calls it with fewer episodes)."""
    out: dict[str, list[str]] = {}
    single = ["--env", "cv2x/SingleMover-v2", "--episodes", single_episodes, "--seed", SEED]
    multi = ["--env", "cv2x/Mobility-v2", "--episodes", multi_episodes, "--seed", SEED]
    out["single-optimum"] = [*single, "--policy", "optimum", "--vs-optimum"]
    for p in ("sensing", "planner", "gbmu", "oracle", "greedy", "static", "random"):
        out[f"single-{p}"] = [*single, "--policy", p]
    for s in range(5):
        out[f"single-ppo{s}"] = [*single, "--policy", f"ppo:agents/models/single_seed{s}/model.zip"]
    out["multi-optimum"] = [*multi, "--policy", "optimum", "--vs-optimum"]
    for p in ("gbmu", "sensing"):
        out[f"multi-{p}"] = [*multi, "--policy", p, "--replan-every", "50"]
    for s in range(5):
        out[f"multi-ppo{s}"] = [*multi, "--policy", f"ppo:agents/models/multi_seed{s}/model.zip"]
    return out


def evaluate(args: list[str], out: Path) -> float:
    """Run ``python -m cv2x_marl.cli evaluate ARGS --out OUT``; returns its wall time (s)."""
    t0 = time.perf_counter()
    subprocess.run(
        [sys.executable, "-m", "cv2x_marl.cli", "evaluate", *args, "--out", str(out), "--quiet", "--overwrite"],
        cwd=ROOT,
        check=True,
        stdout=subprocess.DEVNULL,
    )
    return time.perf_counter() - t0


def load_summary(path: Path) -> dict[str, object]:
    data = json.loads(path.read_text())
    return {k: v for k, v in data.items() if k not in VOLATILE}


def load_rows(path: Path) -> list[dict[str, str]]:
    opener = gzip.open if path.suffix == ".gz" else open
    with opener(path, "rt", newline="") as f:
        return list(csv.DictReader(f))


def _num(x: object) -> float | None:
    try:
        return float(x)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return None


def compare(name: str, new_dir: Path) -> tuple[list[str], float]:
    """Differences between a fresh run and its reference, and the largest absolute numeric difference."""
    ref_dir = REF / name
    if not (ref_dir / "summary.json").exists():
        return [f"{name}: no reference recorded in {ref_dir} (record it with --record --only {name})"], 0.0
    problems: list[str] = []
    worst = 0.0
    pairs: list[tuple[str, object, object]] = []
    ref_s, new_s = load_summary(ref_dir / "summary.json"), load_summary(new_dir / "summary.json")
    if set(ref_s) != set(new_s):
        problems.append(f"{name}: summary keys differ: {sorted(set(ref_s) ^ set(new_s))}")
    pairs += [(f"summary.{k}", ref_s[k], new_s.get(k)) for k in ref_s]
    ref_r, new_r = load_rows(ref_dir / "episodes.csv.gz"), load_rows(new_dir / "episodes.csv")
    if len(ref_r) != len(new_r):
        problems.append(f"{name}: {len(new_r)} episode rows, reference {len(ref_r)}")
    for i, (a, b) in enumerate(zip(ref_r, new_r, strict=False)):
        pairs += [(f"episodes[{i}].{k}", a[k], b.get(k)) for k in a]
    for where, a, b in pairs:
        fa, fb = _num(a), _num(b)
        if fa is not None and fb is not None:
            if math.isnan(fa) and math.isnan(fb):
                continue
            if fa != fb:
                d = abs(fa - fb)
                worst = max(worst, d if math.isfinite(d) else math.inf)
                problems.append(f"{name}: {where} = {b!r}, reference {a!r} (difference {d:.3g})")
        elif a != b:
            worst = math.inf if worst == 0.0 else worst
            problems.append(f"{name}: {where} = {b!r}, reference {a!r}")
    return problems, worst


def _walk(a: object, b: object, where: str, out: list[tuple[str, object, object]]) -> None:
    if isinstance(a, dict) and isinstance(b, dict) and a.keys() == b.keys():
        for k in a:
            _walk(a[k], b[k], f"{where}.{k}", out)
    elif isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            _walk(x, y, f"{where}[{i}]", out)
    elif a != b:
        out.append((where, a, b))


def check_prr() -> tuple[list[str], float]:
    """Replay every run of prr.json with ``cv2x-marl simulate``; differences and the largest one."""
    import os

    from cv2x_marl.cli import main as cli_main

    os.environ.setdefault("CV2X_MARL_SUMO_CACHE", tempfile.mkdtemp(prefix="sumo-cache-"))
    ref = json.loads((DATA / "prr.json").read_text())
    problems: list[str] = []
    worst = 0.0
    with tempfile.TemporaryDirectory(prefix="check_prr_") as tmp:
        for key, want in ref["runs"].items():
            preset, seed = key.split("/seed")
            out = Path(tmp) / f"{preset}-{seed}"
            t0 = time.perf_counter()
            cli_main(
                [
                    *("simulate", "--preset", preset, "--seed", seed, "--subframes", str(ref["subframes"])),
                    *("--links", "off", "--out", str(out), "--quiet"),
                ]
            )
            got = json.loads((out / "summary.json").read_text())
            got = {k: v for k, v in got.items() if k not in PRR_VOLATILE}
            diffs: list[tuple[str, object, object]] = []
            _walk(want, got, key, diffs)
            for where, a, b in diffs:
                fa, fb = _num(a), _num(b)
                d = abs(fa - fb) if fa is not None and fb is not None else math.inf
                worst = max(worst, d)
                problems.append(f"prr {where} = {b!r}, reference {a!r}")
            print(f"prr {key}: {'OK' if not diffs else f'{len(diffs)} differences'} ({time.perf_counter() - t0:.1f} s)")
    return problems, worst


def _note_wall(name: str, seconds: float) -> None:
    """Add a run's wall time (s, on the recording machine) to ``heldout/walltimes.json``."""
    wall_file = REF / "walltimes.json"
    old = json.loads(wall_file.read_text()) if wall_file.exists() else {}
    old[name] = round(seconds, 1)
    wall_file.write_text(json.dumps(old, indent=2) + "\n")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--record", action="store_true", help="rewrite the references (only on purpose)")
    ap.add_argument("--only", nargs="+", help="names of the runs to do (default: all)")
    ap.add_argument("--no-prr", action="store_true", help="skip the replay of prr.json")
    a = ap.parse_args(argv)
    table = runs()
    names = a.only or list(table)
    unknown = [n for n in names if n not in table]
    if unknown:
        ap.error(f"unknown runs {unknown}; known: {list(table)}")
    all_problems: list[str] = []
    worst = 0.0
    if not a.record and not a.no_prr and not a.only:
        all_problems, worst = check_prr()
    walls: dict[str, float] = {}
    with tempfile.TemporaryDirectory(prefix="check_references_") as tmp:
        for name in names:
            out = Path(tmp) / name
            walls[name] = evaluate(table[name], out)
            if a.record:
                dest = REF / name
                dest.mkdir(parents=True, exist_ok=True)
                summary = json.loads((out / "summary.json").read_text())
                (dest / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
                with (
                    open(out / "episodes.csv", "rb") as src,
                    gzip.GzipFile(dest / "episodes.csv.gz", "wb", mtime=0) as gz,
                ):
                    shutil.copyfileobj(src, gz)
                _note_wall(name, walls[name])
                print(f"{name}: recorded in {walls[name]:.1f} s", flush=True)
                continue
            problems, w = compare(name, out)
            worst = max(worst, w)
            all_problems += problems
            print(
                f"{name}: {'OK' if not problems else f'{len(problems)} differences'} ({walls[name]:.1f} s)", flush=True
            )
    if a.record:
        return 0
    for p in all_problems[:50]:
        print(p)
    if len(all_problems) > 50:
        print(f"... and {len(all_problems) - 50} more")
    print(f"largest difference: {worst:.6g} over {len(names)} runs; total {sum(walls.values()):.0f} s")
    return 1 if all_problems else 0


if __name__ == "__main__":
    raise SystemExit(main())
