"""Large-scale and small-scale propagation.

* Power law, eq. 3 of the paper: ``rho = K (d0 / d)^omega``, so the loss in dB is
  ``PL = -K_dB + 10 omega log10(d / d0)``; K defaults to the free-space gain at ``d0``.
* WINNER+ B1 as specified for V2V in 3GPP TR 36.885 Table A.1.4-1 (fc in GHz, d in m):

  - LOS, ``d < d_BP``:  ``PL = 22.7 log10 d + 41.0 + 20 log10(fc / 5)``
  - LOS, ``d >= d_BP``: ``PL = 40 log10 d + 9.45 - 17.3 log10 h'_tx - 17.3 log10 h'_rx + 2.7 log10(fc / 5)``
  - ``d_BP = 4 h'_tx h'_rx fc / c`` with the effective antenna height ``h'`` an explicit parameter;
  - NLOS (Manhattan grid): ``PL = min(PL_n(d1, d2), PL_n(d2, d1))``,
    ``PL_n(dk, dl) = PL_LOS(dk) + 20 - 12.5 n + 10 n log10 dl + 3 log10(fc / 5)``,
    ``n = max(2.8 - 0.0024 dk, 1.84)``, with d1 = |dx| and d2 = |dy| the street distances;
  - floored by free space ``PL_fs = 20 log10 d + 46.4 + 20 log10(fc / 5)``.

* Shadowing (TR 36.885 A.1.4): log-normal, 3 dB LOS / 4 dB NLOS, symmetric per vehicle pair and
  correlated as ``S' = exp(-D/d_c) S + sqrt(1 - exp(-2D/d_c)) N(0, 1)``; ``D``
  (``channel.shadowing_correlation``): ``travelled``, the sum of the distances both vehicles
  travelled (the paper presets'); ``pair_distance`` (the default), the change of the link's distance
  since the pair was last read, ``D = |d(t) - d(t')|`` (TR 36.885 A.1.4: D is the change in
  distance of the link from the previous to the current time instance), so two vehicles driving
  together keep their shadowing.
* Fast fading: Rayleigh, an independent ``|h|^2 ~ Exp(1)`` per transmission and link. Packets of a
  link are an RRI (>= 20 ms) apart while the coherence time ``~0.423 / f_D`` is a few ms at
  vehicular Doppler (eq. 4), so independence between transmissions is the right model.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cv2x_marl.config import ChannelConfig
from cv2x_marl.sim import kernels
from cv2x_marl.units import SPEED_OF_LIGHT_MPS

FloatArray = NDArray[np.float64]


def doppler_hz(carrier_hz: float, relative_speed_mps: ArrayLike) -> FloatArray:
    """Eq. 4 as written in the paper: ``D = 2 c v / 3e8`` (c: carrier frequency, v: relative speed)."""
    return 2.0 * carrier_hz * np.asarray(relative_speed_mps, dtype=np.float64) / 3e8


def free_space_db(distance_m: ArrayLike, carrier_hz: float) -> FloatArray:
    """Free-space loss as written in TR 36.885: ``20 log10 d + 46.4 + 20 log10(fc/5 GHz)``."""
    d = np.asarray(distance_m, dtype=np.float64)
    return 20.0 * np.log10(d) + 46.4 + 20.0 * np.log10(carrier_hz / 5e9)


def power_law_db(
    distance_m: ArrayLike, k_db: float | None, d0_m: float, exponent: float, carrier_hz: float
) -> FloatArray:
    """Eq. 3 in dB: ``PL = -K_dB + 10 omega log10(d / d0)``.

    Args:
        distance_m: distances, any shape, metres.
        k_db: gain K at d0 in dB; None gives the free-space value ``20 log10(lambda / (4 pi d0))``.
        d0_m: reference distance, metres.
        exponent: omega.
        carrier_hz: carrier frequency (for the free-space K).
    """
    if k_db is None:
        wavelength_m = SPEED_OF_LIGHT_MPS / carrier_hz
        k_db = 20.0 * np.log10(wavelength_m / (4.0 * np.pi * d0_m))
    d = np.asarray(distance_m, dtype=np.float64)
    return -k_db + 10.0 * exponent * np.log10(d / d0_m)


def winner_b1_los_db(distance_m: ArrayLike, carrier_hz: float, effective_height_m: float) -> FloatArray:
    """WINNER+ B1 LOS path loss (TR 36.885 Table A.1.4-1) with the breakpoint, in dB (no floor)."""
    d = np.asarray(distance_m, dtype=np.float64)
    fc_ghz = carrier_hz / 1e9
    h = effective_height_m
    d_bp = 4.0 * h * h * carrier_hz / SPEED_OF_LIGHT_MPS
    near = 22.7 * np.log10(d) + 41.0 + 20.0 * np.log10(fc_ghz / 5.0)
    far = 40.0 * np.log10(d) + 9.45 - 2.0 * 17.3 * np.log10(h) + 2.7 * np.log10(fc_ghz / 5.0)
    return np.where(d < d_bp, near, far)


def winner_b1_nlos_db(d1_m: ArrayLike, d2_m: ArrayLike, carrier_hz: float, effective_height_m: float) -> FloatArray:
    """Manhattan NLOS: minimum over the two street orderings (TR 36.885 Table A.1.4-1), in dB."""
    d1 = np.asarray(d1_m, dtype=np.float64)
    d2 = np.asarray(d2_m, dtype=np.float64)
    fc_term = 3.0 * np.log10(carrier_hz / 5e9)

    def one(dk: FloatArray, dl: FloatArray) -> FloatArray:
        n = np.maximum(2.8 - 0.0024 * dk, 1.84)
        return (
            winner_b1_los_db(dk, carrier_hz, effective_height_m) + 20.0 - 12.5 * n + 10.0 * n * np.log10(dl) + fc_term
        )

    return np.minimum(one(d1, d2), one(d2, d1))


def winner_b1_db(
    dx_m: ArrayLike,
    dy_m: ArrayLike,
    los: ArrayLike,
    carrier_hz: float,
    effective_height_m: float,
    min_distance_m: float = 3.0,
) -> FloatArray:
    """WINNER+ B1 V2V path loss for displacement ``(dx, dy)``, LOS or Manhattan NLOS, with the free-space floor.

    Distances (and the street distances of NLOS) below ``min_distance_m`` are clipped to it. The
    formulas of :func:`winner_b1_los_db`, :func:`winner_b1_nlos_db` and :func:`free_space_db`,
    evaluated element by element in one compiled pass (:func:`cv2x_marl.sim.kernels.winner_b1_array_db`;
    tested equal to their numpy composition). Arguments broadcast.
    """
    wb1 = kernels.winner_b1_constants(carrier_hz, effective_height_m, min_distance_m)
    dx, dy, lo = np.broadcast_arrays(
        np.asarray(dx_m, dtype=np.float64), np.asarray(dy_m, dtype=np.float64), np.asarray(los, dtype=bool)
    )
    flat = kernels.winner_b1_array_db(dx.ravel(), dy.ravel(), lo.ravel(), wb1)  # ravel: contiguous 1-D
    return flat.reshape(dx.shape)[()]  # a numpy scalar for scalar input, as numpy ufuncs return


def path_loss_db(cfg: ChannelConfig, carrier_hz: float, disp_m: FloatArray, los: ArrayLike) -> FloatArray:
    """Path loss of displacements ``[..., 2]`` with the configured model (eq. 3 or WINNER+ B1)."""
    if cfg.pathloss == "power_law":
        d = np.maximum(np.hypot(disp_m[..., 0], disp_m[..., 1]), cfg.min_distance_m)
        return power_law_db(d, cfg.power_law_k_db, cfg.power_law_d0_m, cfg.power_law_exponent, carrier_hz)
    return winner_b1_db(disp_m[..., 0], disp_m[..., 1], los, carrier_hz, cfg.effective_height_m, cfg.min_distance_m)


def _correlation_reference(
    correlation: str,
    a: NDArray[np.int64],
    b: NDArray[np.int64],
    odometer_m: FloatArray,
    distance_m: FloatArray | None,
) -> FloatArray:
    """What the shadowing's decorrelation distance is measured on, per pair [P]: the odometer sum of
    both ends (``travelled``) or the pair's distance (``pair_distance``), m."""
    if correlation == "travelled":
        return np.asarray(odometer_m[a] + odometer_m[b], dtype=np.float64)
    if distance_m is None:
        raise ValueError("shadowing correlation pair_distance needs the pairs' distances")
    return np.asarray(distance_m, dtype=np.float64)


class Shadowing:
    """Symmetric, distance-correlated log-normal shadowing for every vehicle pair.

    A unit-variance Gaussian ``Z[a, b] = Z[b, a]`` per pair evolves as an AR(1) process in a
    distance ``D`` since the pair was last read, ``rho = exp(-D / d_c)``:

    * ``correlation="travelled"`` (default): the distance the pair's two ends travelled,
      ``D = odo_a + odo_b - odo_at_last_read``, which makes a lazy update exact: exponential
      correlation composes;
    * ``correlation="pair_distance"``: the change of the pair's distance,
      ``D = |d_ab - d_ab_at_last_read|`` (TR 36.885 A.1.4); zero at a pair's first read, which keeps
      the initial draw. The process is stepped at the reads (every period the pair is within
      ``link.max_range_m``), as the standard's per-time-instance update.

    The dB value is ``sigma(LOS/NLOS) * Z``, so a LOS change rescales it without a jump in Z.
    """

    def __init__(
        self, n: int, decorrelation_m: float, rng: np.random.Generator, correlation: str = "travelled"
    ) -> None:
        if correlation not in ("travelled", "pair_distance"):
            raise ValueError(f"unknown shadowing correlation {correlation!r}; available: travelled, pair_distance")
        w = rng.standard_normal((n, n))
        self._z = np.triu(w, 1) + np.triu(w, 1).T  # symmetric, unit variance off the diagonal
        # travelled: odometer sum at the last read; pair_distance: the pair's distance then (NaN: never read)
        self._last_odo = np.zeros((n, n)) if correlation == "travelled" else np.full((n, n), np.nan)
        self._dc = decorrelation_m
        self._rng = rng
        self.correlation = correlation

    def sample(
        self,
        a: NDArray[np.int64],
        b: NDArray[np.int64],
        odometer_m: FloatArray,
        distance_m: FloatArray | None = None,
    ) -> FloatArray:
        """Unit-variance shadowing of unordered pairs ``(a, b)``, updated to now.

        Args:
            a, b: [P] the pairs' vehicles.
            odometer_m: [N] distance each vehicle travelled since reset (``travelled``).
            distance_m: [P] the pairs' current distances (needed by ``pair_distance``).
        """
        n = self._z.shape[0]
        reference = _correlation_reference(self.correlation, a, b, odometer_m, distance_m)
        normals = np.asarray(self._rng.standard_normal(a.shape[0]), dtype=np.float64)
        return kernels.shadowing_update_dense(
            self._z.reshape(-1),
            self._last_odo.reshape(-1),
            np.ascontiguousarray(a, dtype=np.int64),
            np.ascontiguousarray(b, dtype=np.int64),
            n,
            np.ascontiguousarray(reference, dtype=np.float64),
            normals,
            float(self._dc),
            self.correlation == "pair_distance",
        )

    def renew(self, vehicles: NDArray[np.int64], odometer_m: FloatArray) -> None:
        """New vehicles in the slots ``vehicles`` (``vehicles.population=open``): their pairs get fresh,
        independent ``Z`` (the old vehicle's shadowing does not carry over), read as of now.

        Args:
            vehicles: [V] the renewed slots.
            odometer_m: [N] the odometers now (``travelled``: the pairs' reference sums).
        """
        n = self._z.shape[0]
        w = self._rng.standard_normal((vehicles.shape[0], n))
        blk = np.triu(w[:, vehicles], 1)  # pairs of two renewed slots: one draw each, symmetric, 0 on the diagonal
        w[:, vehicles] = blk + blk.T
        self._z[vehicles, :] = w
        self._z[:, vehicles] = w.T
        if self.correlation == "travelled":
            ref = odometer_m[vehicles][:, None] + odometer_m[None, :]
            self._last_odo[vehicles, :] = ref
            self._last_odo[:, vehicles] = ref.T
        else:
            self._last_odo[vehicles, :] = np.nan
            self._last_odo[:, vehicles] = np.nan


def rayleigh_power_gain(rng: np.random.Generator, size: int) -> FloatArray:
    """``|h|^2`` of Rayleigh fading: exponential with mean 1."""
    return rng.standard_exponential(size)


class SparseShadowing:
    """:class:`Shadowing` kept only for the pairs within ``link.max_range_m`` (corridor scale).

    The same AR(1) process per unordered pair, with the state in three arrays over the pairs of the
    last read, sorted by the key ``a * n + b`` (``a < b``): unit-variance ``Z``, and the odometer sum
    (``travelled``) or the pair's distance (``pair_distance``) at that read. Memory is 24 bytes per
    pair in range instead of 16 bytes per vehicle pair (``N x N``).

    What differs from the dense :class:`Shadowing` (same marginal law, N(0, 1) per pair):

    * a pair's initial ``Z`` is drawn at its first read (one normal per new pair, in key order,
      before the update's normals), not in an ``N x N`` draw at construction; a pair read at its
      first period is then updated exactly as the dense state updates it (``travelled``: from the
      odometers at reset, 0; ``pair_distance``: no change at the first read);
    * a pair not read in a period (out of range) is forgotten: when it comes back in range its ``Z``
      is a fresh draw, where the dense state would carry the old value (``travelled``: correlation
      ``exp(-D / d_c)`` with D the distance both travelled meanwhile, negligible on a highway;
      ``pair_distance``: the correlation with the old value is lost).

    Each :meth:`sample` must get every pair of the period in one call (the simulator does).
    """

    def __init__(
        self, n: int, decorrelation_m: float, rng: np.random.Generator, correlation: str = "travelled"
    ) -> None:
        if correlation not in ("travelled", "pair_distance"):
            raise ValueError(f"unknown shadowing correlation {correlation!r}; available: travelled, pair_distance")
        self._n = n
        self._keys = np.empty(0, dtype=np.int64)  # [P] sorted pair keys a * n + b, a < b
        self._z = np.empty(0)  # [P] unit-variance shadowing
        self._last = np.empty(0)  # [P] odometer sum (travelled) or pair distance (pair_distance), m
        self._dc = decorrelation_m
        self._rng = rng
        self.correlation = correlation

    @property
    def n_pairs(self) -> int:
        """Pairs whose state is kept (those of the last read)."""
        return int(self._keys.shape[0])

    @property
    def nbytes(self) -> int:
        """Bytes of the kept state."""
        return int(self._keys.nbytes + self._z.nbytes + self._last.nbytes)

    def sample(
        self,
        a: NDArray[np.int64],
        b: NDArray[np.int64],
        odometer_m: FloatArray,
        distance_m: FloatArray | None = None,
    ) -> FloatArray:
        """Unit-variance shadowing of the unordered pairs ``(a, b)`` (``a < b``), updated to now.

        Args:
            a, b: [P] the pairs' vehicles, ``a < b``, all pairs of the period.
            odometer_m: [N] distance each vehicle travelled since reset (``travelled``), m.
            distance_m: [P] the pairs' current distances, m (needed by ``pair_distance``).

        Returns:
            [P] the pairs' unit-variance shadowing (``Z``); the state then holds these pairs only.
        """
        keys = a * self._n + b
        m = keys.shape[0]
        odo = _correlation_reference(self.correlation, a, b, odometer_m, distance_m)
        ascending = m < 2 or bool(np.all(keys[1:] > keys[:-1]))
        if ascending:  # the simulator's pairs: a compiled merge with the state, the same draws and values
            z = kernels.shadowing_update_sparse(
                self._keys,
                self._z,
                self._last,
                np.ascontiguousarray(keys, dtype=np.int64),
                np.ascontiguousarray(odo, dtype=np.float64),
                float(self._dc),
                self.correlation == "pair_distance",
                self._rng,
            )
        else:
            z = self._step_numpy(keys, odo)
        if m > 1 and not np.all(keys[1:] > keys[:-1]):
            order = np.argsort(keys, kind="stable")
            self._keys, self._z, self._last = keys[order], z[order], odo[order]
        else:
            self._keys, self._z, self._last = keys, z.copy(), odo.copy()
        return z

    def _step_numpy(self, keys: NDArray[np.int64], odo: FloatArray) -> FloatArray:
        """The AR(1) step in numpy (any key order): :func:`cv2x_marl.sim.kernels.shadowing_update_sparse`'s
        reference, which the tests compare it with."""
        m = keys.shape[0]
        if self._keys.shape[0]:
            pos = np.minimum(np.searchsorted(self._keys, keys), self._keys.shape[0] - 1)
            found = self._keys[pos] == keys
        else:
            pos = np.zeros(m, dtype=np.int64)
            found = np.zeros(m, dtype=bool)
        new = ~found
        z_prev = np.empty(m)
        z_prev[found] = self._z[pos[found]]
        z_prev[new] = self._rng.standard_normal(int(new.sum()))
        last = np.empty(m)
        last[found] = self._last[pos[found]]
        if self.correlation == "travelled":
            last[new] = 0.0
            rho = np.exp(-(odo - last) / self._dc)
        else:
            last[new] = np.nan
            change_m = np.abs(odo - last)
            rho = np.exp(-np.where(np.isnan(change_m), 0.0, change_m) / self._dc)
        return np.asarray(rho * z_prev + np.sqrt(1.0 - rho * rho) * self._rng.standard_normal(m))

    def renew(self, vehicles: NDArray[np.int64], odometer_m: FloatArray) -> None:
        """New vehicles in the slots ``vehicles`` (``vehicles.population=open``): their pairs are
        forgotten, so each gets a fresh draw at its next read.

        Args:
            vehicles: [V] the renewed slots.
            odometer_m: [N] the odometers now (unused: a new pair starts from its first read).
        """
        del odometer_m
        a, b = self._keys // self._n, self._keys % self._n
        mark = np.zeros(self._n, dtype=bool)
        mark[vehicles] = True
        keep = ~(mark[a] | mark[b])
        self._keys, self._z, self._last = self._keys[keep], self._z[keep], self._last[keep]
