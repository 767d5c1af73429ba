"""SUMO mobility: generated scenarios, libsumo lockstep and FCD trace replay (issue 14).

Three pieces (the simulator imports this package only when ``vehicles.mobility`` is ``sumo`` or
``trace``; the first two need the ``sumo`` extra, trace replay only the base install):

* **Generated scenarios.** :func:`build_scenario` turns the ``road`` section into a SUMO network
  with ``netgenerate`` (the paper's grid: ``road.n_roads_per_axis`` two-way roads per axis whose
  centre lines lie at ``(i + 1/2) * length_m / n`` like :class:`cv2x_marl.sim.road.Road`, stubs to
  the region's edge, ``road.lanes_per_direction`` lanes of ``road.lane_width_m``, speed limit
  ``vehicles.speed_max_mps``, priority junctions, U-turns only at dead ends) and writes the
  demand: ``N`` vehicles departing at t = 0 from free random spots (``departPos="random_free"``,
  SUMO's draw under our seed), each driving a random walk over the network with the paper's turning probabilities
  (``road.p_straight`` / ``p_left`` / ``p_right``; a U-turn only at the dead ends on the region's
  edge) and a desired speed drawn uniformly in ``[speed_min_mps, speed_max_mps]``. This stands in
  for SUMO's ``randomTrips.py``: its trips leave the network at the fringe, which a fixed
  vehicle count cannot follow. Every random draw comes from the generator handed in (the
  simulator's ``mobility`` stream) and SUMO's ``--seed`` is drawn from it too. Generated files
  are cached under a content-hash key in :func:`cache_dir` (``$CV2X_MARL_SUMO_CACHE``, else
  ``$XDG_CACHE_HOME/cv2x_marl/sumo`` or ``~/.cache/cv2x_marl/sumo``), written into a temporary
  folder and renamed into place.
* **Lockstep** (:class:`SumoLockstep`): libsumo runs the scenario in this process, one SUMO step
  per reservation period; after every step the tracked vehicles' positions (SUMO network
  coordinates = ours, in metres), speeds and headings are read back through a subscription.
* **Trace replay** (:class:`TraceReplay`): a recorded SUMO FCD trace (XML from ``--fcd-output``,
  or parquet with the same columns) is interpolated linearly to the reservation period.

The fixed vehicle count: both sources track the first ``N`` vehicles (ordered by departure time,
then ID) at the first instant when at least ``N`` are in the network, and that instant is time
zero. A tracked vehicle that leaves the network (arrives, or is teleported) ends the run with a
:class:`SumoError`; generated scenarios give every vehicle a route for :data:`ROUTE_HORIZON_S`
seconds of driving and disable teleports, so they keep all ``N``.

Modules (bottom to top): :mod:`~cv2x_marl.sim.sumo.tools` (finding SUMO, running its tools, the
cache), :mod:`~cv2x_marl.sim.sumo.network` (generated networks), :mod:`~cv2x_marl.sim.sumo.scenario`
(generated demand and ``.sumocfg``, a user's ``.sumocfg``),
:mod:`~cv2x_marl.sim.sumo.slots` (tracked states and the slot table both sources share),
:mod:`~cv2x_marl.sim.sumo.lockstep` (libsumo), :mod:`~cv2x_marl.sim.sumo.trace` (FCD replay) and
:mod:`~cv2x_marl.sim.sumo.source` (the source of a configuration). None imports libsumo, SUMO's
wheel or pyarrow at import time. Writing a scenario and its trace to a folder (``cv2x-marl sumo
export``) is a pipeline: :mod:`cv2x_marl.experiments.sumo_export`.
"""

from cv2x_marl.sim.sumo.lockstep import (
    MAX_FILL_S,
    SumoLockstep,
    lockstep_of,
)
from cv2x_marl.sim.sumo.network import (
    CFG_FILE,
    NET_FILE,
    ROUTE_FILE,
    build_network,
    check_generated,
    highway_plain_xml,
    netgenerate_args,
    read_net,
)
from cv2x_marl.sim.sumo.scenario import (
    CALIBRATION_WINDOW_S,
    HIGHWAY_SPEED_CLASSES,
    ROUTE_HORIZON_S,
    Scenario,
    build_scenario,
    check_sumocfg,
    count_in_network,
    draw_sumo_seed,
    highway_flows_xml,
    random_trips_xml,
    random_walk_routes,
    routes_xml,
    speed_classes,
    sumocfg_xml,
)
from cv2x_marl.sim.sumo.slots import (
    assign_slots,
    tracked_state,
)
from cv2x_marl.sim.sumo.source import (
    MobilitySource,
    check_source,
    open_source,
)
from cv2x_marl.sim.sumo.tools import (
    CACHE_ENV,
    SumoError,
    cache_dir,
    cached,
    content_key,
    import_libsumo,
    run_python_tool,
    run_tool,
    sumo_home,
    sumo_version,
)
from cv2x_marl.sim.sumo.trace import (
    Trace,
    TraceReplay,
    read_trace,
)

__all__ = [
    "CACHE_ENV",
    "CALIBRATION_WINDOW_S",
    "CFG_FILE",
    "HIGHWAY_SPEED_CLASSES",
    "MAX_FILL_S",
    "NET_FILE",
    "ROUTE_FILE",
    "ROUTE_HORIZON_S",
    "MobilitySource",
    "Scenario",
    "SumoError",
    "SumoLockstep",
    "Trace",
    "TraceReplay",
    "assign_slots",
    "build_network",
    "build_scenario",
    "cache_dir",
    "cached",
    "check_generated",
    "check_source",
    "check_sumocfg",
    "content_key",
    "count_in_network",
    "draw_sumo_seed",
    "highway_flows_xml",
    "highway_plain_xml",
    "import_libsumo",
    "lockstep_of",
    "netgenerate_args",
    "open_source",
    "random_trips_xml",
    "random_walk_routes",
    "read_net",
    "read_trace",
    "routes_xml",
    "run_python_tool",
    "run_tool",
    "speed_classes",
    "sumo_home",
    "sumo_version",
    "sumocfg_xml",
    "tracked_state",
]
