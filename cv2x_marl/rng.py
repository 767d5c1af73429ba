"""One root seed, independent named random streams.

The library never reads or seeds the global ``numpy.random`` (or ``random``/torch) state: every
random draw comes from a :class:`numpy.random.Generator` obtained here. Streams are spawned from a
single :class:`numpy.random.SeedSequence` in a fixed order of names, so adding draws to one stream
never changes another (e.g. turning fading on leaves the SPS choices and the mobility unchanged).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

STREAM_NAMES: tuple[str, ...] = ("placement", "mobility", "shadowing", "fading", "sps", "traffic", "link")


@dataclass(frozen=True)
class RngStreams:
    """Named generators for the simulator's independent sources of randomness."""

    placement: np.random.Generator
    mobility: np.random.Generator
    shadowing: np.random.Generator
    fading: np.random.Generator
    sps: np.random.Generator
    traffic: np.random.Generator
    link: np.random.Generator

    @classmethod
    def from_seed(cls, seed: int | np.random.SeedSequence) -> RngStreams:
        """Spawn one child ``SeedSequence`` per name, in the fixed order of ``STREAM_NAMES``."""
        root = seed if isinstance(seed, np.random.SeedSequence) else np.random.SeedSequence(int(seed))
        children = root.spawn(len(STREAM_NAMES))
        return cls(**{name: np.random.default_rng(child) for name, child in zip(STREAM_NAMES, children, strict=True)})


def derive_seeds(seed: int, n: int) -> list[int]:
    """``n`` independent 32-bit seeds derived from ``seed`` (for independent runs)."""
    return [int(s.generate_state(1)[0]) for s in np.random.SeedSequence(int(seed)).spawn(n)]


#: the env's own streams of an episode (after the simulator's :data:`STREAM_NAMES`, so they never
#: change a simulator draw): the shadowing field that follows the movers, the vehicles' measurements
ENV_STREAM_NAMES: tuple[str, ...] = ("shadow_field", "measurement")


def env_stream(seed: int, name: str) -> np.random.Generator:
    """The env's named stream ``name`` (:data:`ENV_STREAM_NAMES`) of episode seed ``seed``: the child
    ``SeedSequence(seed, spawn_key=(len(STREAM_NAMES) + k,))``, a sibling of the simulator's streams of
    the same seed that none of them equals."""
    if name not in ENV_STREAM_NAMES:
        raise ValueError(f"unknown env stream {name!r}; allowed: {', '.join(ENV_STREAM_NAMES)}")
    key = len(STREAM_NAMES) + ENV_STREAM_NAMES.index(name)
    return np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(key,)))
