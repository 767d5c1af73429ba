"""Road geometry: the paper's Manhattan grid (Sec. 3, Fig. 1) and a straight highway.

Coordinates are metres in a box ``[0, width_m) x [0, height_m)``. Traffic is right-hand.

Grid: ``n_roads_per_axis`` horizontal and as many vertical two-way roads, their centre lines at
``(i + 1/2) * length_m / n_roads_per_axis``; lane ``k`` of direction ``+1`` lies ``(k + 1/2) *
lane_width_m`` to the right of the centre line. Highway: one road along x, centre line at
``y = lanes_per_direction * lane_width_m``.

LOS/NLOS (TR 36.885 A.1.2 urban grid): two vehicles are in line of sight when they share a street
corridor (the band of a road, crossings included); otherwise buildings block the direct path and
the Manhattan NLOS path loss applies.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cv2x_marl.config import RoadConfig

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass(frozen=True)
class Road:
    """Road geometry derived from :class:`RoadConfig`."""

    kind: str
    length_m: float
    n_roads: int
    lanes_per_direction: int
    lane_width_m: float
    road_pos_m: FloatArray  # [n_roads] centre-line coordinate of each road (across its axis)

    @classmethod
    def from_config(cls, cfg: RoadConfig) -> Road:
        if cfg.kind == "grid":
            n = cfg.n_roads_per_axis
            spacing = cfg.length_m / n
            half_width = cfg.lanes_per_direction * cfg.lane_width_m
            if spacing <= 2 * half_width:
                raise ValueError(
                    f"road.length_m / road.n_roads_per_axis ({spacing:g} m) must exceed the road width "
                    f"2 * lanes_per_direction * lane_width_m ({2 * half_width:g} m)"
                )
            pos = (np.arange(n, dtype=np.float64) + 0.5) * spacing
        else:
            n = 1
            pos = np.array([cfg.lanes_per_direction * cfg.lane_width_m])
        return cls(cfg.kind, cfg.length_m, n, cfg.lanes_per_direction, cfg.lane_width_m, pos)

    @property
    def half_width_m(self) -> float:
        """Half the width of a two-way road (all lanes of one direction)."""
        return self.lanes_per_direction * self.lane_width_m

    @property
    def box_m(self) -> tuple[float, float]:
        """(width, height) of the simulated area; the torus used when distances wrap."""
        if self.kind == "grid":
            return (self.length_m, self.length_m)
        return (self.length_m, 2.0 * self.half_width_m)

    @property
    def periodic_box_m(self) -> FloatArray:
        """[2] period of the torus per axis (inf where the area does not wrap: across the highway)."""
        w, h = self.box_m
        return np.array([w, h if self.kind == "grid" else np.inf])

    def minimum_image(self, disp_m: FloatArray) -> FloatArray:
        """Displacements ``[..., 2]`` folded onto the torus (the shortest way round), in place."""
        box = self.periodic_box_m
        periodic = np.isfinite(box)
        disp_m[..., periodic] -= box[periodic] * np.round(disp_m[..., periodic] / box[periodic])
        return disp_m

    @property
    def n_lanes_total(self) -> int:
        """Lanes counted over every road, both directions (and both axes on the grid)."""
        axes = 2 if self.kind == "grid" else 1
        return axes * self.n_roads * 2 * self.lanes_per_direction

    def lane_offset_m(self, direction: NDArray[np.int8], lane: IntArray) -> FloatArray:
        """Offset of a lane centre from its road's centre line, along the across-road axis.

        Axis-0 (eastbound, direction +1) lanes lie at negative y offsets; axis-1 lanes of
        direction +1 (northbound) at positive x offsets: right-hand traffic in both cases.
        """
        return np.asarray((lane + 0.5) * self.lane_width_m * direction, dtype=np.float64)

    def corridors(self, positions_m: FloatArray) -> tuple[IntArray, IntArray]:
        """Street corridor of each vehicle: (horizontal road index, vertical road index), -1 if none.

        Args:
            positions_m: [N, 2] positions.
        """
        if self.kind == "highway":
            n = positions_m.shape[0]
            return np.zeros(n, dtype=np.int64), np.full(n, -1, dtype=np.int64)
        # both axes at once: horizontal roads are at fixed y (column 1), vertical ones at fixed x
        c = positions_m[:, ::-1]
        idx = np.minimum(np.maximum(np.floor(c / (self.length_m / self.n_roads)), 0), self.n_roads - 1)
        idx = idx.astype(np.int64)
        out = np.where(np.abs(c - self.road_pos_m[idx]) <= self.half_width_m + 1e-9, idx, -1)
        return out[:, 0], out[:, 1]

    @staticmethod
    def corridor_los(
        corridors_a: tuple[IntArray, IntArray], corridors_b: tuple[IntArray, IntArray]
    ) -> NDArray[np.bool_]:
        """LOS by the corridor rule: both ends in the same horizontal or the same vertical street.

        Args:
            corridors_a, corridors_b: :meth:`corridors` outputs (h, v) of the two ends (broadcast).
        """
        (ha, va), (hb, vb) = corridors_a, corridors_b
        return np.asarray(((ha == hb) & (ha >= 0)) | ((va == vb) & (va >= 0)))
