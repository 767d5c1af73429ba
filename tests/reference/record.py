"""Record the behaviour references of issue 26 into ``tests/data/reference_26/``.

RECORDED AT COMMIT b9b8a2c (the code before the refactor of issue 26). Do NOT rerun this script after
the refactor, except on purpose (a deliberate change of behaviour, stated in its commit): the point of
the data is that the refactored code is compared with the code before it.

    PYTHONPATH=$PWD python tests/reference/record.py                 # env trajectories, PRR, held-out slice
    PYTHONPATH=$PWD python tests/reference/record.py env prr         # some parts only
    PYTHONPATH=$PWD python tests/reference/record.py parts           # test_references_parts.py's cases, recorded
                                                                     # at 265a803, before the env-as-parts refactor
    PYTHONPATH=$PWD python tests/reference/record.py parts=NAME,...  # only these cases (a new id), the others kept
    PYTHONPATH=$PWD python tests/reference/record.py heldout=multi-ppo0,multi-ppo1   # some held-out rows only
    PYTHONPATH=$PWD python benchmarks/check_references.py --record   # the full held-out tables (~30 min)

Recorded again on purpose since: the ``multi-ppo0`` ... ``multi-ppo4`` rows of ``heldout_slice.json`` and of
``heldout/`` (``benchmarks/check_references.py --record --only multi-ppo0 ...``), when the learned policies came
to run their networks on one agent's observation at a time (the batch-invariance rule of
``cv2x_marl.policies.base``; the 21 movers of ``cv2x/Mobility-v2`` had been one batch).

The cases themselves (env ids, options, seeds, presets, policies) are defined in ``test_references.py``
next to this file, which replays them; this script only writes what they give.
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import test_references as t


def record_env() -> None:
    arrays: dict[str, np.ndarray] = {}
    for name in t.ENV_CASES:
        t0 = time.perf_counter()
        for k, v in t.play_env_case(name).items():
            arrays[f"{name}/{k}"] = v
        print(f"env {name}: {time.perf_counter() - t0:.1f} s", flush=True)
    np.savez_compressed(t.DATA / "env_trajectories.npz", **arrays)
    (t.DATA / "env_cases.json").write_text(json.dumps(t.ENV_CASES, indent=1) + "\n")


def record_prr() -> None:
    runs = {}
    with tempfile.TemporaryDirectory() as tmp:
        for preset in t.PRESETS:
            if preset in t.SUMO_PRESETS and not t.HAVE_SUMO:
                raise SystemExit("SUMO is needed to record the SUMO presets")
            for seed in t.PRR_SEEDS:
                t0 = time.perf_counter()
                runs[f"{preset}/seed{seed}"] = t.simulate_summary(preset, seed, Path(tmp) / f"{preset}-{seed}")
                print(f"prr {preset} seed {seed}: {time.perf_counter() - t0:.1f} s", flush=True)
    doc = {"subframes": t.PRR_SUBFRAMES, "seeds": list(t.PRR_SEEDS), "runs": runs}
    (t.DATA / "prr.json").write_text(json.dumps(doc, indent=1) + "\n")


def record_heldout(only: list[str] | None = None) -> None:
    """Every held-out row, or those named in ``only`` (the others kept as recorded)."""
    path = t.DATA / "heldout_slice.json"
    runs = json.loads(path.read_text())["runs"] if only else {}
    wanted = {name: args for name, args in t.heldout_runs().items() if not only or name in only}
    if only and sorted(wanted) != sorted(only):
        raise SystemExit(f"no held-out rows {sorted(set(only) - set(wanted))}; rows: {', '.join(t.heldout_runs())}")
    with tempfile.TemporaryDirectory() as tmp:
        for name, args in wanted.items():
            t0 = time.perf_counter()
            runs[name] = {"args": args, **t.evaluate_run(args, Path(tmp) / name)}
            print(f"heldout {name}: {time.perf_counter() - t0:.1f} s", flush=True)
    path.write_text(json.dumps({"runs": runs}, indent=1) + "\n")


def record_parts(only: list[str] | None = None) -> None:
    """The references of ``test_references_parts.py`` (the env ids the first set does not cover), recorded
    before the env is split into parts (``tests/data/reference_38/``); ``only``: record these cases (an id added
    later) and keep every other case's arrays as they are."""
    import test_references_parts as p

    arrays: dict[str, np.ndarray] = {}
    if only is not None:
        unknown = sorted(set(only) - set(p.CASES))
        if unknown:
            raise SystemExit(f"unknown parts case(s) {unknown}; cases: {', '.join(p.CASES)}")
        with np.load(p.DATA / "trajectories.npz") as old:
            arrays = {k: old[k] for k in old.files if k.split("/", 1)[0] not in only}
    for name in only if only is not None else p.CASES:
        t0 = time.perf_counter()
        for k, v in p.play_case(name).items():
            arrays[f"{name}/{k}"] = v
        print(f"parts {name}: {time.perf_counter() - t0:.1f} s", flush=True)
    p.DATA.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(p.DATA / "trajectories.npz", **arrays)
    (p.DATA / "cases.json").write_text(json.dumps(p.CASES, indent=1) + "\n")


def main() -> None:
    parts = sys.argv[1:] or ["env", "prr", "heldout"]
    t.DATA.mkdir(parents=True, exist_ok=True)
    os.environ.setdefault(t.SUMO_ENV, tempfile.mkdtemp(prefix="sumo-cache-"))
    for part in parts:
        if part.startswith("heldout="):
            record_heldout(part.split("=", 1)[1].split(","))
            continue
        if part.startswith("parts="):
            record_parts(part.split("=", 1)[1].split(","))
            continue
        {"env": record_env, "prr": record_prr, "heldout": record_heldout, "parts": record_parts}[part]()


if __name__ == "__main__":
    main()
