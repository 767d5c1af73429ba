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
