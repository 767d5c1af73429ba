"""Sensing-aware heuristics for ``cv2x/Resource-v0`` tried against ``sps`` (docs/benchmark.md, "Resource choice: what
the scripts and the ceiling show"): the team's episode-mean utility gain against ``sps`` on the same training-list
episodes.

    python benchmarks/resource_heuristics.py [--episodes 12]

Each variant scores an entry of a deciding vehicle's list by what the vehicle sensed (the neighbours' last
decoded SCIs and their RSRP measured at it, as its observation carries them) and picks the lowest score, ties
drawn uniformly:

    std-hd     within the standard's list, the summed measured power (mW) of the neighbours heard in the entry's
               subframe (half duplex: they cannot hear the vehicle there, nor it them)
    std-hdco   the same plus the neighbours whose SCI reserves the entry itself (co-channel)
    all-hd     std-hd over every valid entry of the list (up to 20)
    all-hdco   std-hdco over every valid entry
"""

from __future__ import annotations

import argparse
import copy
from typing import Any

import numpy as np

from cv2x_marl.env.registry import make_parallel_env
from cv2x_marl.env.tasks import TRAIN_SEEDS
from cv2x_marl.policies.resource import make_resource_policy

VARIANTS = ("std-hd", "std-hdco", "all-hd", "all-hdco")


def choices(env: Any, variant: str, rng: np.random.Generator) -> dict[str, np.int64]:
    """Every agent's entry under ``variant`` (0 for those without a decision)."""
    p, m, sci = env.pending, env.traffic_measure.rsrp, env.traffic_measure.sci
    n_sub = env.config.sps.n_subchannels
    out = {}
    for a in env.agents:
        i = env.agent_index[a]
        nv = int(p.n_valid[i])
        if nv == 0:
            out[a] = np.int64(0)
            continue
        lim = nv if variant.startswith("all") else int(p.n_standard[i])
        res = p.resources[i, :lim]
        rsrp = m.rsrp_dbm[:, i]
        power = np.where(np.isfinite(rsrp), 10 ** (rsrp / 10), 0.0)
        power[i] = 0.0
        heard = sci.resource[:, i]
        score = np.array([power[(heard >= 0) & (heard // n_sub == r // n_sub)].sum() for r in res])
        if variant.endswith("co"):
            score += np.array([power[(heard == r) & ~sci.release[:, i]].sum() for r in res])
        best = np.flatnonzero(score <= score.min() * (1 + 1e-9) + 1e-30)
        out[a] = np.int64(best[rng.integers(best.size)])
    return out


def gain(variant: str, seed: int) -> float:
    """The team's episode-mean utility gain of ``variant`` against ``sps`` on episode ``seed``."""
    env = make_parallel_env("cv2x/Resource-v0")
    env.reset(seed=seed)
    ref = copy.deepcopy(env)
    sps = make_resource_policy("sps", ref)
    sps.reset(seed)
    obs = ref.observations()
    while ref.agents:
        obs, *_ = ref.step(sps.act(obs))
    rng = np.random.default_rng(seed)
    while env.agents:
        env.step(choices(env, variant, rng))
    u, u0 = env.u_sum.mean() / env.t, ref.u_sum.mean() / ref.t
    return float((u - u0) / abs(u0))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--episodes", type=int, default=12, help="the first N training-list episodes")
    args = ap.parse_args()
    seeds = TRAIN_SEEDS[: args.episodes]
    print("| variant | mean gain against sps (%) | min .. max (%) |")
    print("|---|---|---|")
    for v in VARIANTS:
        g = np.array([gain(v, s) for s in seeds])
        print(f"| {v} | {100 * g.mean():+.1f} | {100 * g.min():+.1f} .. {100 * g.max():+.1f} |", flush=True)


if __name__ == "__main__":
    main()
