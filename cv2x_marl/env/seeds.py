"""The protocol's episode seeds (docs/benchmark.md): each task's held-out list and the training list.

Package constants, drawn at import from named ``SeedSequence`` s (:data:`PROTOCOL_ENTROPY`, the task's
name, the list's kind), so they are the same on every machine and in every version of the package. A
learner trains on :data:`TRAIN_SEEDS` (one list for every task, disjoint from every held-out list;
the env's ``start_pool`` draws from its head) and is scored on its task's :data:`HELDOUT_SEEDS`. The
tasks themselves are in :mod:`cv2x_marl.env.tasks`. Numpy only (the env's reset reads the pool).
"""

from __future__ import annotations

import zlib
from collections.abc import Mapping
from types import MappingProxyType

import numpy as np

#: the root entropy of every task's seed lists (issue 27's protocol; never change it: it defines them)
PROTOCOL_ENTROPY = 2027_0027
#: episodes of each held-out list
N_HELDOUT = 48
#: episodes of each training list
N_TRAIN = 4096


def seed_list(task: str, kind: str, n: int, exclude: tuple[int, ...] = ()) -> tuple[int, ...]:
    """``n`` distinct 32-bit episode seeds of list ``kind`` (``train`` | ``heldout``) of ``task``, none
    in ``exclude``: the state of ``SeedSequence(PROTOCOL_ENTROPY, spawn_key=(crc32(task), k))`` (k = 0
    held-out, 1 training), in order, repeats and excluded values skipped."""
    kinds = ("heldout", "train")
    if kind not in kinds:
        raise ValueError(f"kind must be one of {', '.join(kinds)}, got {kind!r}")
    ss = np.random.SeedSequence(PROTOCOL_ENTROPY, spawn_key=(zlib.crc32(task.encode()), kinds.index(kind)))
    words = ss.generate_state(n + 64 + len(exclude), dtype=np.uint32)
    out: list[int] = []
    seen = set(exclude)
    for w in words.tolist():
        if w not in seen:
            seen.add(w)
            out.append(int(w))
            if len(out) == n:
                return tuple(out)
    raise AssertionError("unreachable: 64 spare words cover the repeats")  # pragma: no cover


#: every task's name, the pending ones included: their held-out lists exist before the task does, so
#: the training list (:data:`TRAIN_SEEDS`) never changes when a pending task is built
TASK_NAMES = ("singlemover", "cooperative", "traffic", "resource")
#: each task's held-out episode seeds (:data:`N_HELDOUT`)
HELDOUT_SEEDS: Mapping[str, tuple[int, ...]] = MappingProxyType(
    {name: seed_list(name, "heldout", N_HELDOUT) for name in TASK_NAMES}
)
#: the training episode seeds of every task (:data:`N_TRAIN`): one list, disjoint from every held-out
#: list; the env's ``start_pool`` draws its starts from its head (:func:`training_pool`)
TRAIN_SEEDS: tuple[int, ...] = seed_list(
    "protocol", "train", N_TRAIN, exclude=tuple(s for held in HELDOUT_SEEDS.values() for s in held)
)


def training_pool(n: int) -> tuple[int, ...]:
    """The first ``n`` training seeds (:data:`TRAIN_SEEDS`), 1 <= ``n`` <= :data:`N_TRAIN`: the env's
    ``start_pool``."""
    if isinstance(n, bool) or not isinstance(n, int | np.integer) or not 1 <= n <= N_TRAIN:
        raise ValueError(f"invalid start_pool={n!r}; allowed: an integer in [1, {N_TRAIN}] (0: no pool)")
    return TRAIN_SEEDS[: int(n)]
