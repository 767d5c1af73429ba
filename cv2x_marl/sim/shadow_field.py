"""Shadowing that follows the vehicles: a spatially correlated field per link, drawn per episode.

The snapshot gives every pair of vehicles one shadowing value ``s0`` (dB, symmetric). When vehicles
move away from where the snapshot put them, the shadowing of a pair decorrelates with how far each end
moved, as in the simulator's channel model (TR 36.885 A.1.4; ``channel.shadowing_decorrelation_m``
``d``: 10 m on the grid, 25 m on the highway):

    rho_ab = exp(-(|x_a - x_a0| + |x_b - x_b0|) / d)

is the correlation between the pair's shadowing at the start positions ``(x_a0, x_b0)`` and at
``(x_a, x_b)``: exactly the simulator's ``shadowing_correlation=travelled`` rule with the displacement as
the distance travelled, and for a pair of which one end stands still, the exponential correlation with
the distance the other moved (what ``pair_distance`` gives for a receiver far away).

The field of a pair is the conditional Gaussian random field with that covariance whose value at the
start is the snapshot's:

    s_ab(x_a, x_b) = rho_ab * s0_ab + sigma_ab * (G_ab(x_a, x_b) - rho_ab * G_ab(x_a0, x_b0))

with ``G`` a unit-variance field of covariance ``exp(-|dx_a| / d) * exp(-|dx_b| / d)`` (a product of two
valid covariances) and ``sigma_ab`` the preset's shadowing standard deviation for the pair's LOS state
at the snapshot (``channel.shadowing_std_db`` / ``shadowing_nlos_std_db``). ``G`` is a sum of ``W``
random cosines (the spectral method, Shinozuka 1971):

    G(x_a, x_b) = sqrt(2 / W) * sum_w cos(k_aw . (x_a - x_a0) + k_bw . (x_b - x_b0) + phi_w)

with ``phi_w`` uniform on [0, 2 pi) and each wave vector drawn from the spectral density of the 2-D
exponential covariance, ``S(k) ~ (1 + d^2 |k|^2)^(-3/2)``: a uniform direction and the radius
``|k| = sqrt((1 - U)^-2 - 1) / d`` (the inverse of the radial CDF ``1 - (1 + d^2 k^2)^(-1/2)``). Then
``E[G(x) G(x')] = E[cos(k_a . dx_a)] E[cos(k_b . dx_b)] = exp(-|dx_a| / d) exp(-|dx_b| / d)`` exactly
over the draws; with ``W = 32`` waves the marginal is Gaussian to an excess kurtosis of ``-1.5 / W``.
Fields are continuous everywhere (no grid, no interpolation), so the reward, the measurements and the
ceiling's search read one field.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import NDArray

from cv2x_marl.config import ScenarioConfig
from cv2x_marl.sim.kernels.field import field_row_db, field_row_lattice_db, field_shadow_db

FloatArray = NDArray[np.float64]

#: cosines per pair field
N_WAVES = 32


@dataclass(frozen=True)
class ShadowField:
    """One episode's shadowing field of every pair of N vehicles (see the module docstring).

    Attributes:
        start_m: [N, 2] positions where the field equals the snapshot's shadowing (m).
        shadow0_db: [N, N] the snapshot's shadowing (symmetric, dB).
        sigma_db: [N, N] standard deviation of each pair's field (dB; symmetric).
        decorrelation_m: ``d`` of the exponential correlation (m).
        k_lo: [N, N, W, 2] wave vector of the lower-index end of each pair (rad/m; only ``a < b`` used).
        k_hi: [N, N, W, 2] wave vector of the higher-index end (rad/m).
        phase: [N, N, W] phases (rad).
    """

    start_m: FloatArray
    shadow0_db: FloatArray
    sigma_db: FloatArray
    decorrelation_m: float
    k_lo: FloatArray
    k_hi: FloatArray
    phase: FloatArray

    @classmethod
    def draw(
        cls,
        config: ScenarioConfig,
        start_m: FloatArray,
        shadow0_db: FloatArray,
        los: NDArray[np.bool_],
        rng: np.random.Generator,
        n_waves: int = N_WAVES,
    ) -> ShadowField:
        """Draw the field of every pair.

        Args:
            config: the scenario (its ``channel`` section: decorrelation distance, LOS / NLOS std).
            start_m: [N, 2] the snapshot's positions (m).
            shadow0_db: [N, N] the snapshot's shadowing (symmetric, dB).
            los: [N, N] the snapshot's LOS states (the std of each pair's field).
            rng: the episode's ``shadow_field`` stream (:func:`cv2x_marl.rng.env_stream`).
            n_waves: cosines per pair.
        """
        ch = config.channel
        n = start_m.shape[0]
        d = float(ch.shadowing_decorrelation_m)
        u = rng.random((2, n, n, n_waves))
        radius = np.sqrt((1.0 - u) ** -2.0 - 1.0) / d  # [2, N, N, W] rad/m
        angle = rng.random((2, n, n, n_waves)) * (2.0 * np.pi)
        k = np.stack((radius * np.cos(angle), radius * np.sin(angle)), axis=-1)  # [2, N, N, W, 2]
        phase = rng.random((n, n, n_waves)) * (2.0 * np.pi)
        sigma = np.where(los, ch.shadowing_std_db, ch.shadowing_nlos_std_db).astype(np.float64)
        sigma = np.minimum(sigma, sigma.T)  # symmetric (the snapshot's LOS is)
        return cls(
            np.array(start_m, dtype=np.float64),
            np.array(shadow0_db, dtype=np.float64),
            sigma,
            d,
            np.ascontiguousarray(k[0]),
            np.ascontiguousarray(k[1]),
            np.ascontiguousarray(phase),
        )

    @property
    def n(self) -> int:
        """Number of vehicles."""
        return int(self.start_m.shape[0])

    @cached_property
    def g0(self) -> FloatArray:
        """[N, N] the unit field ``G`` of each pair at the start positions (the pair ``(a, b)``'s draws
        at ``[min, max]``, mirrored)."""
        g = np.sqrt(2.0 / self.phase.shape[-1]) * np.cos(self.phase).sum(axis=-1)
        upper = np.triu(np.ones((self.n, self.n), dtype=bool), 1)
        return np.ascontiguousarray(np.where(upper, g, g.T))

    def _kernel_arrays(self) -> tuple:
        return (
            self.start_m, self.shadow0_db, self.sigma_db, float(self.decorrelation_m), self.k_lo, self.k_hi,
            self.phase, self.g0,
        )  # fmt: skip

    def shadow_db(self, positions_m: FloatArray, compiled: bool = True) -> FloatArray:
        """[N, N] shadowing of every pair with the vehicles at ``positions_m`` [N, 2] (dB, symmetric,
        0 on the diagonal); equal to ``shadow0_db`` at ``start_m`` (exactly, pair by pair: a pair
        neither of whose ends moved keeps its snapshot value).

        Args:
            positions_m: [N, 2] vehicle positions (m).
            compiled: the numba kernel :func:`cv2x_marl.sim.kernels.field.field_shadow_db` (default);
                False: the numpy reference below (equal to about 1e-12 dB: numba's and numpy's
                ``cos`` / ``exp`` differ in the last ulps).
        """
        if compiled:
            pos = np.ascontiguousarray(positions_m, dtype=np.float64)
            if pos.shape != (self.n, 2):
                raise ValueError(f"positions_m must have shape ({self.n}, 2), got {pos.shape}")
            return field_shadow_db(pos, *self._kernel_arrays())
        return self._shadow_db_numpy(positions_m)

    def row_db(self, mover: int, positions_m: FloatArray, candidates_m: FloatArray) -> FloatArray:
        """[M, N] shadowing of ``mover``'s links with it at each candidate [M, 2] (m) and every other
        vehicle at ``positions_m`` [N, 2] (dB; 0 in column ``mover``): row ``mover`` of
        :meth:`shadow_db` with the mover at each candidate, compiled
        (:func:`cv2x_marl.sim.kernels.field.field_row_db`)."""
        pos = np.ascontiguousarray(positions_m, dtype=np.float64)
        cand = np.ascontiguousarray(np.asarray(candidates_m, dtype=np.float64).reshape(-1, 2))
        return field_row_db(cand, pos, int(mover), *self._kernel_arrays())

    def rows_db(self, mover: int, positions_m: FloatArray, candidates_m: FloatArray) -> FloatArray:
        """:meth:`row_db`, by :meth:`lattice_row_db` where the candidates (all, or all but the first, as a
        search lays them: the start, then a grid) sit on a square lattice of at least 64 points that
        they fill to at least a quarter; equal to :meth:`row_db` to 1e-9 dB either way."""
        cand = np.asarray(candidates_m, dtype=np.float64).reshape(-1, 2)
        for skip in (0, 1):
            lat = square_lattice(cand[skip:])
            if lat is None:
                continue
            origin, pitch, shape, index = lat
            rows = self.lattice_row_db(mover, positions_m, origin, pitch, shape)[index]
            if skip:
                rows = np.concatenate([self.row_db(mover, positions_m, cand[:1]), rows])
            return rows
        return self.row_db(mover, positions_m, cand)

    def lattice_row_db(
        self, mover: int, positions_m: FloatArray, origin_m: FloatArray, pitch_m: float, shape: tuple[int, int]
    ) -> FloatArray:
        """[nx * ny, N] :meth:`row_db` at the lattice ``origin + (ix, iy) * pitch``, ``shape = (nx, ny)``
        (candidate ``ix * ny + iy``): the same values to 1e-9 dB at two ``cos`` per lattice column and
        wave instead of one per point (:func:`cv2x_marl.sim.kernels.field.field_row_lattice_db`)."""
        pos = np.ascontiguousarray(positions_m, dtype=np.float64)
        nx, ny = int(shape[0]), int(shape[1])
        return field_row_lattice_db(
            float(origin_m[0]), float(origin_m[1]), float(pitch_m), nx, ny, pos, int(mover), *self._kernel_arrays()
        )

    def _shadow_db_numpy(self, positions_m: FloatArray) -> FloatArray:
        """The numpy reference of :meth:`shadow_db`."""
        pos = np.asarray(positions_m, dtype=np.float64)
        n = self.n
        disp = pos - self.start_m  # [N, 2]
        moved = np.hypot(disp[:, 0], disp[:, 1])  # [N]
        # pair (a, b), a < b: the lower index's displacement with k_lo, the higher's with k_hi
        lo = np.minimum(np.arange(n)[:, None], np.arange(n)[None, :])
        hi = np.maximum(np.arange(n)[:, None], np.arange(n)[None, :])
        arg = np.einsum("abwc,abc->abw", self.k_lo, disp[lo]) + np.einsum("abwc,abc->abw", self.k_hi, disp[hi])
        scale = np.sqrt(2.0 / self.phase.shape[-1])
        g = scale * np.cos(arg + self.phase).sum(axis=-1)
        g0 = scale * np.cos(self.phase).sum(axis=-1)
        # the pair (a, b) uses the draws stored at [min, max]: mirror the upper triangle
        upper = np.triu(np.ones((n, n), dtype=bool), 1)
        g = np.where(upper, g, g.T)
        g0 = np.where(upper, g0, g0.T)
        rho = np.exp(-(moved[:, None] + moved[None, :]) / self.decorrelation_m)
        s = rho * self.shadow0_db + self.sigma_db * (g - rho * g0)
        s[np.diag_indices(n)] = 0.0
        return s


def square_lattice(
    points_m: FloatArray, min_points: int = 64, tol_m: float = 1e-9
) -> tuple[FloatArray, float, tuple[int, int], NDArray[np.int64]] | None:
    """Whether ``points_m`` [M, 2] lie on one square lattice ``origin + (ix, iy) * pitch`` (to ``tol_m``
    relative): ``(origin_m [2], pitch_m, (nx, ny), index [M] = ix * ny + iy)``, or None (fewer than
    ``min_points`` points, off a lattice, or filling less than a quarter of its bounding lattice)."""
    pts = np.asarray(points_m, dtype=np.float64)
    if pts.shape[0] < min_points:
        return None
    ux, uy = np.unique(pts[:, 0]), np.unique(pts[:, 1])
    if ux.size < 2 or uy.size < 2:
        return None
    pitch = float(min(np.diff(ux).min(), np.diff(uy).min()))
    if not pitch > 0:
        return None
    origin = np.array([ux[0], uy[0]])
    idx = np.rint((pts - origin) / pitch)
    scale = max(1.0, float(np.abs(pts).max()))
    if np.abs(origin + idx * pitch - pts).max() > tol_m * scale:
        return None
    nx, ny = int(idx[:, 0].max()) + 1, int(idx[:, 1].max()) + 1
    if nx * ny > 4 * pts.shape[0]:
        return None
    return origin, pitch, (nx, ny), (idx[:, 0] * ny + idx[:, 1]).astype(np.int64)
