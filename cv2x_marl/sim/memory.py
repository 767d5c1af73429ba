"""Memory limits up front: estimate a run's peak memory from the configuration, refuse early.

The simulator keeps dense ``N x N`` state (shadowing, its pair index; with ``link.max_range_m`` and
:data:`SPARSE_STATE_MIN_VEHICLES` vehicles or more, state over the pairs in range only:
:func:`uses_sparse_state`), per-period arrays over the vehicle pairs in range, and, with
``metrics.record_links``, a links table that grows by one row per (transmission, receiver).
:func:`estimate_memory_bytes` adds these up from the configuration alone (no array is allocated),
with per-element byte counts read off :mod:`cv2x_marl.sim.simulator` and the modules it drives,
:mod:`cv2x_marl.sim.channel` and :mod:`cv2x_marl.sim.sps` and checked against tracemalloc peaks of
real runs (``tests/sim/test_memory.py``). :func:`check_memory` compares the estimate with the
memory available and raises :class:`~cv2x_marl.config.ConfigError` naming the keys to change.

Sizes used below, for N vehicles:

* ``P_all = N (N - 1) / 2`` unordered vehicle pairs; ``P`` of them within ``link.max_range_m``
  (all of them when it is null); ``L = 2 P`` links (ordered pairs) per reservation period, since
  every vehicle transmits once per period.
* Links-table rows: ``L`` per period, ``ceil(n_subframes / traffic.rri_ms)`` periods.
* Co-channel terms K (one per link and other transmitter on its resource, built for the links
  table and for ``link.model=rayleigh``): ``K = L (N - 1) / R`` with R the resources in use (the
  selection window's ``sps.selection_window_subframes x sps.n_subchannels`` when
  ``traffic.synchronous``, else ``traffic.rri_ms x sps.n_subchannels``).

Example:
    >>> from cv2x_marl.config import preset
    >>> est = estimate_memory_bytes(preset("paper"))
    >>> est["total"] < 256 * 2**20
    True
"""

from __future__ import annotations

import math
import os
import sys

from cv2x_marl.config import ConfigError, ScenarioConfig

__all__ = [
    "ENV_LIMIT",
    "LINK_ROW_BYTES",
    "SPARSE_STATE_MIN_VEHICLES",
    "available_memory_bytes",
    "check_memory",
    "estimate_memory_bytes",
    "uses_sparse_state",
]

#: environment variable overriding the memory limit, in GB (10^9 bytes)
ENV_LIMIT = "CV2X_MARL_MEMORY_LIMIT_GB"
GB = 1e9

#: bytes of one links-table row: the dtypes of the columns the simulator appends
#: (``tx``/``rx`` int32, ``subframe`` int64, ``subchannel``/``nsv`` int16, float64 distances, SINR,
#: power, P, Doppler, bool ``outcome``/``los``, int8 ``cause``)
LINK_ROW_BYTES = 4 + 4 + 8 + 2 + 8 + 2 + 8 + 8 + 8 + 8 + 1 + 1 + 1 + 8

# Bytes per element of the arrays the simulator allocates (see the module docstring for P, L, K).
_PAIR_INDEX_PER_PAIR = 16  # PairList.all_pairs (sim/geometry.py): two int64 [P_all], always built
_PAIR_INDEX_BUILD_PER_PAIR = 32  # ... while built: np.triu_indices output and its astype copies
_SHADOWING_PER_CELL = 16  # Shadowing._z and ._last_odo: float64 [N, N] each
_SHADOWING_INIT_PER_CELL = 25  # Shadowing.__init__: draw w, triu(w) (+ in-place .T sum), triu mask (bool)
_SNAPSHOT_PER_CELL = 9  # Snapshot.los (bool) and .shadowing_db (float64) [N, N], returned by reset
_SNAPSHOT_BUILD_PER_PAIR = 170  # snapshot(): path loss and shadowing of the P pairs (measured 150-170)
_GEOMETRY_PER_PAIR = 81  # geometry.Geometry: rx, tx, distance, power [2P] (8 B); LOS (1 B), mean power, rel. speed [P]
_PERIOD_PER_LINK = 130  # ChunkRunner.run (numpy): ~15 arrays of 8 B, ~8 of 1 B over the period's L links (measured 124)
# ChunkRunner._run_compiled (no links table, no Rayleigh; kernels.period_chunk): no array over the links but its outputs
# (last_links); the scratch for the power per receiver and resource [N * R] (float64), kept between chunks
_COMPILED_PERIOD_PER_CELL = 8
_COMPILED_PERIOD_PER_LINK = 9  # kernels.period_chunk while it runs: each link's uniform, then P (8 B), cause (1 B)
_CHUNK_SUBSET_PER_LINK = 12  # kernels.links_by_transmitter's index (8 B) and a chunk's links (at most half)
_SCI_DECODING_PER_LINK = 33  # sps.sci_decoding=sinr: uniforms, SINR + offset, linear SINR, P (8 B), decoded (1 B)
_LAST_LINKS_PER_LINK = 25  # Simulator.last_links: tx, rx, p (8 B) and cause (1 B) of the last chunk
_CO_CHANNEL_PER_TERM = 66  # _co_channel_terms + NSV/interferer distance of the links table (measured 60-66)
_CO_CHANNEL_GRID_WRAP_PER_TERM = 110  # ... with minimum-image displacements on both axes (measured 108)
_RAYLEIGH_PER_TERM = 50  # link.model=rayleigh without the links table: the terms and their powers (measured 47)
_VEHICLE_BYTES = 400  # per-vehicle vectors (state, resources, counters, accumulators)
_SELECT_PER_CANDIDATE = 70  # sps.select and the S-RSSI average, per (reselecting vehicle, candidate)

#: with ``link.max_range_m`` set and at least this many vehicles, the simulator keeps its pair state
#: sparse (shadowing over the pairs in range, no all-pairs index, the snapshot's N x N matrices built
#: when read): docs/model.md, "Scale". Below it the dense state, so smaller runs keep their draws.
SPARSE_STATE_MIN_VEHICLES = 2500

# Sparse pair state, bytes per unordered pair in range P:
_SPARSE_SHADOWING_PER_PAIR = 24  # SparseShadowing: keys (int64), Z and last read (float64)
_SPARSE_SHADOWING_UPDATE_PER_PAIR = 41  # ... while updated: keys, reference, positions, last Z, new Z, order check
_LAZY_SNAPSHOT_PER_PAIR = 25  # snapshot.LazySnapshot until read: i, j (int64), LOS (bool), mean power (float64)
_PAIR_LIST_PER_PAIR = 8.4  # PairList.built (sim/geometry.py): the Verlet list's i, j (int32) at the cut-off + 5 %

#: below this estimate, check_memory does not read /proc/meminfo (the env builds small simulators often)
QUICK_PASS_BYTES = 256 * 2**20

# (configuration, subframes) that passed against the available memory in this process: not checked
# against it again, since a previous Simulator of the same run loop may still hold its arrays
_PASSED: set[tuple[ScenarioConfig, int]] = set()


def uses_sparse_state(cfg: ScenarioConfig) -> bool:
    """Whether the simulator keeps the sparse pair state: ``link.max_range_m`` set and
    ``link.pair_state`` ``sparse``, or ``auto`` with at least :data:`SPARSE_STATE_MIN_VEHICLES` vehicle
    slots (the vehicle count, or ``vehicles.capacity`` with an open population)."""
    if cfg.link.max_range_m is None or cfg.link.pair_state == "dense":
        return False
    return cfg.link.pair_state == "sparse" or cfg.n_slots >= SPARSE_STATE_MIN_VEHICLES


def _pairs_in_range(cfg: ScenarioConfig, n: int, length: float) -> float:
    """Expected unordered pairs of ``n`` vehicles within ``link.max_range_m`` on a road of ``length`` m."""
    p_all = n * (n - 1) / 2.0
    r = cfg.link.max_range_m
    if r is None:
        return p_all
    road = cfg.road
    if road.kind == "highway":
        # uniform positions along the road; lanes add at most a few metres across it
        x = min(1.0, (r + 2.0 * road.lanes_per_direction * road.lane_width_m) / length)
        share = 2.0 * x if road.wrap_distances else 2.0 * x - x * x
    else:
        # expected road length within distance r of a vehicle: its own road and the parallel roads
        # (chords 2 sqrt(r^2 - d^2) at d = spacing, spacing, 2 spacing, ...), and the crossing
        # roads (on average the disc's area over the spacing)
        n_roads = road.n_roads_per_axis
        spacing = length / n_roads
        parallel = min(2.0 * r, length)
        for k in range(1, n_roads):
            d = ((k + 1) // 2) * spacing
            if d < r:
                parallel += min(2.0 * math.sqrt(r * r - d * d), length)
        crossing = min(math.pi * r * r / spacing, n_roads * min(2.0 * r, length))
        share = (parallel + crossing) / (2.0 * n_roads * length)
    return p_all * min(1.0, share)


def estimate_memory_bytes(cfg: ScenarioConfig, n_subframes: int | None = None) -> dict[str, int]:
    """Peak memory of a :class:`~cv2x_marl.sim.simulator.Simulator` run, per component, in bytes.

    The run is ``Simulator(cfg)``, ``reset`` (the warm-up and the snapshot it returns, kept by the
    caller) and ``run(n_subframes)``. Arithmetic on the configuration only: nothing is allocated
    (about 10 microseconds). Numpy arrays only: the interpreter and its modules (some 180 MB
    resident) come on top. Measured: 1.0-1.2x the tracemalloc peak of small runs (grid and highway,
    links table on and off, Rayleigh, in-band emission, range cut-off), 1.04-1.07x the peak resident
    size minus the interpreter's for runs of 800 to 10,000 vehicles; with the sparse pair state
    (:func:`uses_sparse_state`) 1.0-1.3x of that for 5,000 to 20,000 vehicles on the highway at
    0.1 veh/m, 2.8 km cut-off (``benchmarks/bench_scale.py``).

    Args:
        cfg: the scenario; ``cfg.n_vehicles`` is the resolved vehicle count (density x road length
            when ``vehicles.density_veh_per_m`` is set).
        n_subframes: subframes of the measured run (links-table rows); None: ``sim.n_subframes``.

    Returns:
        Bytes per component, each at the largest it gets during the run (they do not all peak at
        once, so they do not add up to the total):

        * ``pair_index``: the all-pairs index (two int64 per vehicle pair; twice that while built);
        * ``pair_list``: with a cut-off, the Verlet list of the pairs in range (two int32 per pair);
        * ``shadowing``: the dense N x N shadowing state (while initialised: the draw and its copies);
        * ``snapshot``: the N x N LOS and shadowing matrices of the snapshot ``reset`` returns;
        * ``sensing``: the sensing window of S-RSSI per vehicle and resource, and reselection;
        * ``pair_geometry``: per-period arrays over the ordered pairs in range;
        * ``period_temporaries``: per-period link arrays (SINR, outcomes, sensing updates);
        * ``co_channel``: (link, co-channel transmitter) terms for NSV and ``link.model=rayleigh``;
        * ``links_table``: the recorded links (lists and their concatenation at the end of the run);
        * ``total``: the peak of the components alive at the same time.
    """
    n_sub = cfg.sim.n_subframes if n_subframes is None else max(0, int(n_subframes))
    est = _estimate(cfg, cfg.n_vehicles, n_sub, cfg.metrics.record_links, cfg.road.length_m, cfg.n_slots)
    return {k: math.ceil(v) for k, v in est.items()}


def _estimate(
    cfg: ScenarioConfig, n: int, n_sub: int, record: bool, length: float, slots: int | None = None
) -> dict[str, float]:
    """:func:`estimate_memory_bytes` for ``n`` vehicles, ``n_sub`` subframes, links table or not, road length.

    ``slots`` (None: ``n``): the size of the per-vehicle arrays, ``vehicles.capacity`` with an open
    population: the dense N x N state and the sensing window are per slot, the pairs and links per
    vehicle present (``n`` on average)."""
    rri = cfg.traffic.rri_ms
    sps = cfg.sps
    n_arr = n if slots is None else max(n, slots)
    cells = float(n_arr) * n_arr
    p_all = n * (n - 1) / 2.0
    p = _pairs_in_range(cfg, n, length)
    links = 2.0 * p  # per period
    n_res = rri * sps.n_subchannels
    used_res = sps.selection_window_subframes * sps.n_subchannels if cfg.traffic.synchronous else n_res
    terms = links * (n - 1) / max(1, min(used_res, n_res))
    rayleigh = cfg.link.model == "rayleigh"
    record = record and n_sub > 0
    rows = links * math.ceil(n_sub / rri) if record else 0.0

    sparse = cfg.link.max_range_m is not None and n_arr >= SPARSE_STATE_MIN_VEHICLES  # uses_sparse_state for n
    all_pairs = cfg.link.max_range_m is None  # PairList.all_pairs only without a cut-off
    pair_index = _PAIR_INDEX_PER_PAIR * p_all if all_pairs else 0.0
    pair_index_build = _PAIR_INDEX_BUILD_PER_PAIR * p_all if all_pairs else 0.0
    if sparse:
        shadowing = _SPARSE_SHADOWING_PER_PAIR * p
        shadowing_peak = shadowing + _SPARSE_SHADOWING_UPDATE_PER_PAIR * p
        snapshot = _LAZY_SNAPSHOT_PER_PAIR * p
        snapshot_build = 0.0
    else:
        shadowing = _SHADOWING_PER_CELL * cells
        shadowing_peak = max(shadowing, _SHADOWING_INIT_PER_CELL * cells)
        snapshot = _SNAPSHOT_PER_CELL * cells
        snapshot_build = _SNAPSHOT_BUILD_PER_PAIR * p
    periods = max(1, sps.sensing_window_ms // rri)
    compiled = not record and not rayleigh  # as Simulator._chunk: the compiled chunk (ChunkRunner._run_compiled)
    # in-band emission: flat, the per-(receiver, subframe) sums [N, RRI] (the compiled chunk's scratch, or
    # the numpy chunk's); 3gpp, the numpy chunk's leakage per (receiver, resource) (the kernel sums it per link)
    inband = 8 * n_arr * n_res if cfg.link.inband_emission_model == "3gpp" and not compiled else 0
    inband += 8 * n_arr * rri if cfg.link.inband_emission_db is not None else 0
    sensing = (4 * periods + 16) * n_arr * n_res + inband
    if sps.reselection_timing == "per_ue":  # the previous period's SCI RSRP map, float64 [N, R]
        sensing += 8 * n_arr * n_res
    lo, hi = round(sps.counter_min * max(1.0, 100.0 / rri)), round(sps.counter_max * max(1.0, 100.0 / rri))
    reselecting = min(n, math.ceil(4.0 * n / (lo + hi)))  # twice the mean number of expiries per period
    candidates = sps.selection_window_subframes * sps.n_subchannels
    select = reselecting * candidates * (_SELECT_PER_CANDIDATE + 9 * periods) + 4 * n * n_res
    geometry = _GEOMETRY_PER_PAIR * p
    period = (
        _COMPILED_PERIOD_PER_CELL * n_arr * n_res + _COMPILED_PERIOD_PER_LINK * links
        if compiled
        else _PERIOD_PER_LINK * links
    )
    if sps.sci_decoding == "sinr" and not compiled:  # numpy: SCI draws, PSCCH SINR, probability (8 B), decoded (1 B)
        period += _SCI_DECODING_PER_LINK * links
    if sps.reselection_timing == "per_ue" and compiled:  # chunks of a few senders: links by sender, the chunk's
        period += _CHUNK_SUBSET_PER_LINK * links
    # per_ue cuts periods: the parts of the last period are kept, then concatenated (two copies at once)
    last = _LAST_LINKS_PER_LINK * links * (2 if sps.reselection_timing == "per_ue" else 1)
    if rayleigh:
        # mean-power lookup: dense N x N, or (sparse) a search of the pairs per co-channel term; fading gains
        period += (40 * terms if sparse else 8 * cells) + 32 * links
    grid_wrap = cfg.road.kind == "grid" and cfg.road.wrap_distances
    per_term = _CO_CHANNEL_GRID_WRAP_PER_TERM if grid_wrap else _CO_CHANNEL_PER_TERM
    co_channel = (per_term if record else _RAYLEIGH_PER_TERM if rayleigh else 0) * terms
    table = LINK_ROW_BYTES * rows

    pair_list = _PAIR_LIST_PER_PAIR * p if cfg.link.max_range_m is not None else 0.0
    state = pair_index + pair_list + shadowing + sensing + _VEHICLE_BYTES * n_arr + last
    phases = (
        pair_index_build,  # Simulator.__init__ (its PairList)
        pair_index + (shadowing if sparse else _SHADOWING_INIT_PER_CELL * cells),  # reset: Shadowing.__init__
        state + geometry + snapshot + snapshot_build,  # reset: snapshot()
        state + snapshot + geometry + shadowing_peak - shadowing,  # period geometry: shadowing update
        state + snapshot + geometry + period + co_channel + table,  # run: last period
        state + snapshot + geometry + period + select + table,  # run: end of a period, reselection
        state + snapshot + geometry + 2 * table,  # run: links concatenated at the end
    )
    return {
        "pair_index": pair_index_build,
        "pair_list": pair_list,
        "shadowing": shadowing_peak,
        "snapshot": snapshot + snapshot_build,
        "sensing": sensing + select,
        "pair_geometry": geometry,
        "period_temporaries": period + last,
        "co_channel": co_channel,
        "links_table": 2 * table,
        "total": max(phases),
    }


def available_memory_bytes() -> int:
    """Memory available to a new allocation now, in bytes.

    ``MemAvailable`` of ``/proc/meminfo`` (Linux); else free physical pages from ``os.sysconf``;
    else no limit (``sys.maxsize``).
    """
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024  # kB
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (AttributeError, OSError, ValueError):
        return sys.maxsize


def _env_limit_bytes() -> int | None:
    text = os.environ.get(ENV_LIMIT)
    if text is None or not text.strip():
        return None
    try:
        gb = float(text)
    except ValueError:
        gb = math.nan
    if not math.isfinite(gb) or gb <= 0:
        raise ConfigError(f"{ENV_LIMIT}={text!r}: expected a memory limit in GB, a number > 0 (e.g. 8 or 0.5)")
    return int(gb * GB)


def _gb(x: float) -> str:
    gb = x / GB
    return f"{gb:,.0f} GB" if gb >= 100 else f"{gb:.3g} GB"


def format_bytes(x: float) -> str:
    """A byte count for messages: ``1,234 GB`` from 100 GB, ``4.76 GB`` down to 10 MB, ``3.2 MB`` below."""
    return _gb(x) if x >= 0.01 * GB else f"{x / 1e6:.3g} MB"


def memory_limit(total_bytes: int) -> tuple[int, str] | None:
    """The limit an estimate of ``total_bytes`` is checked against, with where it comes from.

    ``CV2X_MARL_MEMORY_LIMIT_GB`` (GB) when set; else the memory available now
    (:func:`available_memory_bytes`), which is not read for estimates below 256 MiB: None then
    (nothing to check). Shared by every estimate made before allocating (datasets, training).

    Raises:
        ConfigError: ``CV2X_MARL_MEMORY_LIMIT_GB`` is not a number > 0.
    """
    limit = _env_limit_bytes()
    if limit is not None:
        return limit, ENV_LIMIT
    if total_bytes <= QUICK_PASS_BYTES:
        return None
    return available_memory_bytes(), "the memory available now, MemAvailable"


def check_memory(cfg: ScenarioConfig, n_subframes: int | None = None, limit_bytes: int | None = None) -> dict[str, int]:
    """Refuse a configuration whose estimated peak memory exceeds the limit, before allocating.

    Args:
        cfg: the scenario.
        n_subframes: subframes of the measured run; None: ``sim.n_subframes``.
        limit_bytes: the limit in bytes; None: ``CV2X_MARL_MEMORY_LIMIT_GB`` (GB, 10^9 bytes) when
            set, else the memory available now (:func:`available_memory_bytes`). That is not read
            when the estimate is below 256 MiB (small configurations cost some 15 microseconds),
            nor again for a configuration that already passed in this process (a loop of runs
            builds the next Simulator while the previous one still holds its arrays).

    Returns:
        The estimate (:func:`estimate_memory_bytes`), bytes per component.

    Raises:
        ConfigError: the estimate exceeds the limit (the message names the vehicle count, the
            estimate, the limit, the largest components, the keys to change and the environment
            variable), or ``CV2X_MARL_MEMORY_LIMIT_GB`` is not a number > 0.
    """
    est = estimate_memory_bytes(cfg, n_subframes)
    total = est["total"]
    source = "limit_bytes"
    if limit_bytes is None:
        limit_bytes = _env_limit_bytes()
        source = ENV_LIMIT
    n_sub = cfg.sim.n_subframes if n_subframes is None else max(0, int(n_subframes))
    if limit_bytes is None:
        if total <= QUICK_PASS_BYTES or (cfg, n_sub) in _PASSED:
            return est
        limit_bytes = available_memory_bytes()
        source = "memory available now, MemAvailable"
        if total <= limit_bytes:
            if len(_PASSED) >= 64:
                _PASSED.clear()
            _PASSED.add((cfg, n_sub))
    if total <= limit_bytes:
        return est
    raise ConfigError(_refusal(cfg, est, n_sub, limit_bytes, source))


def _road_length_for(cfg: ScenarioConfig, n: int) -> float:
    """``road.length_m`` of ``n`` vehicles: as configured, or from the density when it is set."""
    density = cfg.vehicles.density_veh_per_m
    if density is None:
        return cfg.road.length_m
    return n / density / (2 * cfg.road.n_roads_per_axis if cfg.road.kind == "grid" else 1)


def _max_vehicles(cfg: ScenarioConfig, n_sub: int, record: bool, limit: float) -> int:
    """Largest vehicle count below ``cfg.n_vehicles`` whose estimate fits ``limit`` (0: none).

    With ``vehicles.density_veh_per_m`` the road shortens with the count (same density).
    """

    def fits(n: int) -> bool:
        return _estimate(cfg, n, n_sub, record, _road_length_for(cfg, n))["total"] <= limit

    if not fits(2):
        return 0
    lo, hi = 2, cfg.n_vehicles  # fits(lo), not fits(hi)
    while hi - lo > 1:
        mid = (lo + hi) // 2
        lo, hi = (mid, hi) if fits(mid) else (lo, mid)
    return lo


def _refusal(cfg: ScenarioConfig, est: dict[str, int], n_sub: int, limit: int, source: str) -> str:
    n = cfg.n_vehicles
    parts = sorted(((v, k) for k, v in est.items() if k != "total"), reverse=True)
    largest = ", ".join(f"{k} {_gb(v)}" for v, k in parts[:3] if v > 0)
    density = cfg.vehicles.density_veh_per_m
    if density is not None:
        grid = cfg.road.kind == "grid"
        road = f"road.length_m={cfg.road.length_m:g}" + (
            f" x 2 x road.n_roads_per_axis={cfg.road.n_roads_per_axis}" if grid else ""
        )
        count = f"{n} vehicles (vehicles.density_veh_per_m={density:g} x {road})"
        size_keys = "lower vehicles.density_veh_per_m or road.length_m" + (" or road.n_roads_per_axis" if grid else "")
    else:
        count = f"{n} vehicles (vehicles.n_vehicles={n})"
        size_keys = "lower vehicles.n_vehicles"
    record = cfg.metrics.record_links and n_sub > 0
    fit = _max_vehicles(cfg, n_sub, record, limit)
    if fit < 2:
        fits = "no vehicle count fits with these settings"
    elif density is not None and _road_length_for(cfg, fit) >= 50.0:
        fits = f"about {fit} vehicles fit: road.length_m <= {_road_length_for(cfg, fit):.0f} at this density"
    else:
        fits = f"about {fit} vehicles fit"
    fixes = [f"{size_keys} ({fits}; the dense N x N state grows as N^2)"]
    if cfg.vehicles.population == "open":
        fixes.insert(
            0,
            f"lower vehicles.capacity (the {cfg.n_slots} vehicle slots size the dense state and the sensing "
            "window; the most vehicles present at once is enough)",
        )
    if record and est["links_table"] + est["co_channel"] > 0.1 * est["total"]:
        without = _estimate(cfg, n, n_sub, False, cfg.road.length_m)["total"]
        fixes.append(
            f"set metrics.record_links=false (estimate without the links table: {_gb(without)}) "
            f"or lower sim.n_subframes (now {n_sub}; the links table grows with it)"
        )
    if cfg.link.max_range_m is None and est["pair_geometry"] + est["period_temporaries"] > 0.1 * est["total"]:
        fixes.append("set link.max_range_m (vehicle pairs farther apart are not computed)")
    return (
        f"estimated peak memory {_gb(est['total'])} for {count} exceeds the limit {_gb(limit)} ({source}); "
        f"largest parts: {largest}. To fit: {'; '.join(fixes)}; or set {ENV_LIMIT}=<GB> to raise the "
        "limit (the estimate is approximate, see cv2x_marl.sim.memory)."
    )
