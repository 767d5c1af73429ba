"""Compiled (numba) kernels, one module per domain.

The env evaluates all N x N links of a 21-vehicle snapshot once per step. In numpy that is some
40 small array operations whose fixed cost (about 1 us each) dominates; these kernels fuse them
into one compiled pass. They are not a second model. :func:`winner_b1_pair_db` is the one WINNER+
B1 implementation (the simulator calls it through :func:`cv2x_marl.sim.channel.winner_b1_db`) and
is tested against the numpy LOS / NLOS / free-space formulas of ``channel`` and hand values
(``tests/sim/test_channel.py``); :func:`snapshot_links` is tested equal (to 1e-9 relative) to the
numpy composition in :class:`cv2x_marl.sim.ground_truth.SnapshotLinks` (``compiled=False``: received
power, interference sums, PER interpolation) and to the simulator's own link outcomes
(``tests/sim/test_ground_truth.py``). ``NUMBA_DISABLE_JIT=1`` runs them as plain Python for debugging.

Compiled code is cached on disk (``cache=True``): the first call in a fresh checkout compiles
(a few seconds), later processes load the cache.

Modules: :mod:`.pathloss` (WINNER+ B1), :mod:`.per` (PER curves and the threshold model), :mod:`.pairs`
(pairs within range, pair geometry, link indexing), :mod:`.shadowing` (correlated shadowing, received
powers), :mod:`.snapshot` (every link of a snapshot, one mover's row, eq. 12 summaries), :mod:`.period`
(one period of the subframe loop; its named tuples in :mod:`.period_tuples`, its passes in
:mod:`.period_passes`), :mod:`.field` (the shadowing field that follows the vehicles, its cosines by
:mod:`.trig`: fdlibm's cosine in plain IEEE arithmetic, the same bits on every x86-64 CPU),
:mod:`.team` (the team objective when one vehicle moves), :mod:`.column` (received power in the numpy
reference's arithmetic, one mover's column of the links). This package re-exports their public names.
"""

from cv2x_marl.sim.kernels.column import mover_column, pair_rx_dbm
from cv2x_marl.sim.kernels.field import field_row_db, field_row_lattice_db, field_shadow_db, pair_field_db
from cv2x_marl.sim.kernels.pairs import (
    active_links,
    filter_pairs_within_range,
    links_by_transmitter,
    pair_geometry,
    pairs_within_range,
    radix_sort,
)
from cv2x_marl.sim.kernels.pathloss import WB1_CONSTANTS, winner_b1_array_db, winner_b1_constants, winner_b1_pair_db
from cv2x_marl.sim.kernels.per import (
    LIN_MARGIN,
    MODEL_PER_TABLE,
    MODEL_PER_TABLE_LOG,
    MODEL_THRESHOLD,
    db_below,
    interp_clamped,
    per_success,
    success_of_ratio,
)
from cv2x_marl.sim.kernels.period import (
    CHUNK_TILE_BYTES,
    ChunkBuffers,
    ChunkLinks,
    ChunkResult,
    ChunkVehicles,
    DistanceBins,
    LinkModel,
    SciModel,
    chunk_tile_subframes,
    period_chunk,
)
from cv2x_marl.sim.kernels.period_passes import sci_probability
from cv2x_marl.sim.kernels.shadowing import received_powers, shadowing_update_dense, shadowing_update_sparse
from cv2x_marl.sim.kernels.snapshot import (
    levels_db,
    link_summaries,
    moved_signal_dbm,
    mover_interference,
    mover_row_success,
    mover_row_utility,
    row_utility,
    snapshot_links,
    success_at_level,
)

__all__ = [
    "CHUNK_TILE_BYTES",
    "LIN_MARGIN",
    "MODEL_PER_TABLE",
    "MODEL_PER_TABLE_LOG",
    "MODEL_THRESHOLD",
    "WB1_CONSTANTS",
    "ChunkBuffers",
    "ChunkLinks",
    "ChunkResult",
    "ChunkVehicles",
    "DistanceBins",
    "LinkModel",
    "SciModel",
    "active_links",
    "chunk_tile_subframes",
    "db_below",
    "field_row_db",
    "field_row_lattice_db",
    "field_shadow_db",
    "filter_pairs_within_range",
    "interp_clamped",
    "levels_db",
    "link_summaries",
    "links_by_transmitter",
    "moved_signal_dbm",
    "mover_column",
    "mover_interference",
    "mover_row_success",
    "mover_row_utility",
    "pair_field_db",
    "pair_geometry",
    "pair_rx_dbm",
    "pairs_within_range",
    "per_success",
    "period_chunk",
    "radix_sort",
    "received_powers",
    "row_utility",
    "sci_probability",
    "shadowing_update_dense",
    "shadowing_update_sparse",
    "snapshot_links",
    "success_at_level",
    "success_of_ratio",
    "winner_b1_array_db",
    "winner_b1_constants",
    "winner_b1_pair_db",
]
