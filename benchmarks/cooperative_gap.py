"""Where the Cooperative ceiling's gain comes from: selfish against team-aware moves, sequential against simultaneous.

Issue 28 asks for a learned mover on ``cv2x/Cooperative-v0`` at >= 85 % of the ceiling; the learners stop near
best response (about 60 %). This script measures, on the task's held-out episodes, what moves of each kind
reach when they are computed with the ceiling's privileged knowledge (the episode's shadowing field, every
link's resources: :class:`cv2x_marl.env.team_search.TeamObjective`), so the gap can be split into what
information, what the objective and what coordination would buy:

- ``selfish, simultaneous``: every vehicle goes to its own best reachable position (its eq. 12 utility) with
  the others where they started, all at once: what decentralised selfish agents that cannot see the others'
  intentions reach at best;
- ``best response``: the same, two sequential rounds (each vehicle answers the positions already chosen):
  the ``best-response`` method's targets (checked against its rows of ``--rows``);
- ``team-aware, simultaneous``: every vehicle goes to its best position *for the team objective* J with the
  others where they started (one single move of the ceiling's search from the start), all at once: what
  decentralised agents that optimise the team's objective, each on its own, reach at best;
- ``selfish`` / ``team-aware, re-planned every 10 steps``: every vehicle re-picks its target every 10 steps with
  the others where they are by then, all at once, and steps towards it: the step-by-step dynamics of a
  decentralised policy that reacts to the others' moves (:func:`gradual_gain`);
- ``team-aware, one round``: the same moves made in turn (each sees the moves before it): one round of the
  ceiling's coordinate ascent, no pair moves;
- the ceiling (``optimum``): its rows of ``--rows`` (the published benchmark run).

The J of every target configuration is what the episode ends at when the vehicles drive there (the
reachable sets are reachable in the episode's steps). Gains are eq. 17 of J against the start, shares are
over the ceiling's gain on the same episode; IQM and 95 % bootstrap intervals as the benchmark's
(:mod:`cv2x_marl.stats`).

    python benchmarks/cooperative_gap.py [--rows docs/benchmark/benchmark.csv] [--episodes 48] \
        [--replan-every 10] [--gradual selfish,team] [--workers 1] [--out docs/benchmark/cooperative_gap]

Writes ``gap.csv`` (one row per episode), ``gap.json`` (IQM and intervals) and ``gap.png`` into ``--out``.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import time
from pathlib import Path

import numpy as np

from cv2x_marl.env.planning import best_reachable, reachable_set
from cv2x_marl.env.registry import make_parallel_env
from cv2x_marl.env.tasks import TASKS
from cv2x_marl.env.team_search import team_moves, team_objective
from cv2x_marl.experiments.evaluate import interval
from cv2x_marl.policies.optimum import best_response_targets

#: the selfish moves' grid (m): the best-response policy's with many movers (then refined 16 times)
GRID_M = 10.0
#: steps between the re-plans of the gradual variants (the sensing planner's: once per sensing window)
REPLAN_EVERY = 10


def selfish_moves(env) -> np.ndarray:
    """[N, 2] each vehicle's own best reachable position (eq. 12 utility) with the others where they are now
    (the best-response policy's grid, refined 16 times)."""
    now = np.array(env.positions_m, dtype=np.float64)
    out = now.copy()
    for i in range(env.n):
        out[i], _ = best_reachable(env.links.mover_row(i, now), reachable_set(env, i), env.p_min, GRID_M, 16)
    return out


def episode_targets(env) -> dict[str, np.ndarray]:
    """[N, 2] target positions of each computed variant, the env at its reset."""
    return {
        "selfish_simultaneous": selfish_moves(env),
        "best_response": best_response_targets(env, list(range(env.n)), 2, GRID_M, 16),
        "team_simultaneous": team_moves(env),
        "team_one_round": team_moves(env, sequential=True),
    }


def gradual_gain(env, seed: int, team: bool, every: int = REPLAN_EVERY) -> float:
    """Team-utility gain of an episode in which every vehicle, every ``every`` steps and all at once, picks its
    best reachable position with the others where they are now (for J when ``team``, for its own utility
    otherwise; privileged, as above) and steps towards it (``max_step_m`` per axis): the moves a decentralised
    policy makes step by step, each vehicle reacting to the others' positions as they move."""
    env.reset(seed=seed)
    j0 = team_objective(env.links, env.positions_m, env.p_min)
    targets = np.array(env.positions_m, dtype=np.float64)
    while env.agents:
        if env.t % every == 0:
            targets = team_moves(env) if team else selfish_moves(env)
        step = np.clip((targets - env.positions_m) / env.max_step_m, -1.0, 1.0).astype(np.float32)
        env.step({a: step[env.agent_index[a]] for a in env.agents})
    return (team_objective(env.links, env.positions_m, env.p_min) - j0) / abs(j0)


def read_rows(path: Path, seeds: list[int]) -> dict[tuple[str, int], float]:
    """(method, seed) -> utility gain of the cooperative rows of a benchmark.csv."""
    out = {}
    with path.open(newline="") as fh:
        for r in csv.DictReader(fh):
            if r["task"] == "cooperative" and r["run"] == "0" and int(r["seed"]) in seeds:
                out[(r["method"], int(r["seed"]))] = float(r["utility_gain"])
    return out


_ENV: dict[str, object] = {}


def episode_row(job: tuple[int, int, tuple[int, ...], tuple[str, ...], float]) -> dict[str, float]:
    """One episode's gains of every computed variant (a worker process builds its env once)."""
    e, seed, replan, kinds, optimum = job
    task = TASKS["cooperative"]
    if "env" not in _ENV:
        _ENV["env"] = make_parallel_env(task.env_id, **task.options)
    env = _ENV["env"]
    env.reset(seed=seed)
    j0 = team_objective(env.links, env.positions_m, env.p_min)
    row: dict[str, float] = {"episode": e, "seed": seed, "j_start": j0}
    for name, targets in episode_targets(env).items():
        row[name] = (team_objective(env.links, targets, env.p_min) - j0) / abs(j0)
    for every in replan:
        for kind in kinds:
            row[f"{kind}_gradual_{every}"] = gradual_gain(env, seed, team=kind == "team", every=every)
    row["optimum"] = optimum
    return row


def variants(replan: tuple[int, ...], kinds: tuple[str, ...]) -> dict[str, str]:
    """Column -> label, in the table's order."""
    out = {"selfish_simultaneous": "selfish, simultaneous"}
    if "selfish" in kinds:
        out.update({f"selfish_gradual_{r}": f"selfish, re-planned every {r} step(s)" for r in replan})
    out["best_response"] = "best response (selfish, 2 sequential rounds)"
    out["team_simultaneous"] = "team-aware, simultaneous"
    if "team" in kinds:
        out.update({f"team_gradual_{r}": f"team-aware, re-planned every {r} step(s)" for r in replan})
    out["team_one_round"] = "team-aware, one sequential round"
    out["optimum"] = "ceiling (team search)"
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--rows", type=Path, default=Path("docs/benchmark/benchmark.csv"), help="a benchmark.csv")
    p.add_argument("--episodes", type=int, default=48, help="the first N held-out episodes of cooperative")
    p.add_argument("--replan-every", default=str(REPLAN_EVERY), help="steps between re-plans, comma-separated")
    p.add_argument("--gradual", default="selfish,team", help="the re-planned kinds: selfish, team or both")
    p.add_argument("--workers", type=int, default=1, help="processes (spawned), one episode each at a time")
    p.add_argument("--out", type=Path, default=Path("docs/benchmark/cooperative_gap"))
    args = p.parse_args(argv)
    replan = tuple(int(x) for x in args.replan_every.split(","))
    asked = [k.strip() for k in args.gradual.split(",") if k.strip()]
    if not asked or set(asked) - {"selfish", "team"}:
        raise SystemExit(f"--gradual {args.gradual!r}: allowed: selfish, team, or both (comma-separated)")
    kinds = tuple(k for k in ("selfish", "team") if k in asked)
    if not replan or min(replan) < 1 or args.workers < 1 or not 1 <= args.episodes <= 48:
        raise SystemExit("--replan-every: integers >= 1; --workers >= 1; --episodes in 1 .. 48")
    seeds = [int(s) for s in TASKS["cooperative"].heldout_seeds[: args.episodes]]
    earlier = read_rows(args.rows, seeds)
    missing = [s for s in seeds if ("optimum", s) not in earlier]
    if missing:
        raise SystemExit(f"--rows {args.rows}: no optimum row for seed(s) {missing[:4]}")
    jobs = [(e, s, replan, kinds, earlier[("optimum", s)]) for e, s in enumerate(seeds)]
    t0 = time.perf_counter()
    rows: list[dict[str, float]] = []
    if args.workers == 1:
        for job in jobs:
            rows.append(episode_row(job))
            print(f"episode {len(rows)}/{len(jobs)} ({time.perf_counter() - t0:.0f} s)", file=sys.stderr, flush=True)
    else:
        import multiprocessing

        with multiprocessing.get_context("spawn").Pool(args.workers) as pool:
            for row in pool.imap_unordered(episode_row, jobs):
                rows.append(row)
                print(json.dumps(row), flush=True)  # a long run's rows survive an interruption in its log
                print(
                    f"episode {len(rows)}/{len(jobs)} ({time.perf_counter() - t0:.0f} s)", file=sys.stderr, flush=True
                )
        rows.sort(key=lambda r: r["episode"])
    for r in rows:
        r["best_response_rows"] = earlier.get(("best-response", int(r["seed"])), float("nan"))
    labels = variants(replan, kinds)
    ceiling = np.array([r["optimum"] for r in rows])
    summary: dict = {"episodes": len(rows), "seeds": seeds, "replan_every": list(replan), "gradual": list(kinds)}
    summary["variants"] = {}
    for name, label in labels.items():
        gain = np.array([r[name] for r in rows])
        share = np.where(ceiling != 0, gain / np.where(ceiling != 0, ceiling, 1.0), np.nan)
        g, gci = interval(gain[None, :])
        sh, sci = interval(share[None, :])
        summary["variants"][name] = {
            "label": label,
            "iqm_gain": g,
            "ci95_gain": gci,
            "iqm_share": sh,
            "ci95_share": sci,
        }
    br = np.array([r["best_response"] - r["best_response_rows"] for r in rows])
    summary["best_response_vs_rows_max_abs"] = float(np.nanmax(np.abs(br)))
    summary["wall_s"] = time.perf_counter() - t0
    args.out.mkdir(parents=True, exist_ok=True)
    with (args.out / "gap.csv").open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    (args.out / "gap.json").write_text(json.dumps(summary, indent=1) + "\n")
    plot(summary, args.out / "gap.png")
    for v in summary["variants"].values():
        print(
            f"{v['label']:48s} gain {100 * v['iqm_gain']:+5.1f} % [{100 * v['ci95_gain'][0]:+.1f}, "
            f"{100 * v['ci95_gain'][1]:+.1f}]  share {100 * v['iqm_share']:5.1f} % "
            f"[{100 * v['ci95_share'][0]:.1f}, {100 * v['ci95_share'][1]:.1f}]"
        )
    print(f"best response against its benchmark rows: max |difference| {summary['best_response_vs_rows_max_abs']:.2e}")
    print(f"wrote {args.out}/gap.csv, gap.json, gap.png ({summary['wall_s']:.0f} s)")
    return 0


def plot(summary: dict, path: Path) -> None:
    """Each variant's IQM share of the ceiling with its 95 % interval (gap.png)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    items = list(summary["variants"].values())
    fig, ax = plt.subplots(figsize=(9.0, 1.4 + 0.4 * len(items)))
    vals = [100 * v["iqm_share"] for v in items]
    errs = np.array(
        [[100 * (v["iqm_share"] - v["ci95_share"][0]), 100 * (v["ci95_share"][1] - v["iqm_share"])] for v in items]
    ).T
    colours = [
        "#246" if v["label"].startswith("ceiling") else "#4a7" if v["label"].startswith("team") else "#999"
        for v in items
    ]
    ax.barh(range(len(items)), vals, xerr=errs, color=colours)
    ax.set_yticks(range(len(items)), [v["label"] for v in items])
    ax.invert_yaxis()
    ax.axvline(85, ls="--", c="k", lw=0.8)
    ax.set_xlabel("share of the ceiling's team-utility gain, IQM (%), 95 % CI; dashed: 85 %", fontsize=9)
    ax.set_title(f"Cooperative-v0, {summary['episodes']} held-out episodes: privileged moves", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    raise SystemExit(main())
