"""SUMO mobility: generated scenarios, libsumo lockstep and FCD trace replay (issue 14).

Three pieces (the simulator imports this module only when ``vehicles.mobility`` is ``sumo`` or
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
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import xml.etree.ElementTree as ET
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cv2x_marl.config import ConfigError, ScenarioConfig
from cv2x_marl.extras import missing_extra, require
from cv2x_marl.sim.mobility import TrackedState

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: environment variable that overrides where generated scenarios are cached
CACHE_ENV = "CV2X_MARL_SUMO_CACHE"
#: seconds of driving (at the highest desired speed) each generated route covers
ROUTE_HORIZON_S = 3600.0
#: SUMO seconds the lockstep waits for ``N`` vehicles to be in the network before giving up
MAX_FILL_S = 3600.0
#: most ``<vehicle>`` rows (vehicles x SUMO steps) ``sumo export`` writes to ``fcd.xml`` (and then reads back)
MAX_FCD_ROWS = 10_000_000
#: bytes of one FCD row at 6 decimals (``<vehicle id=... x=... y=... angle=... type=... speed=... pos=...
#: lane=... slope=.../>``), for the size figure
FCD_ROW_BYTES = 150
#: file names of a generated (or exported) scenario
NET_FILE, ROUTE_FILE, CFG_FILE = "net.net.xml", "routes.rou.xml", "scenario.sumocfg"
#: format version of the generated files (part of every cache key)
_GENERATOR_VERSION = 4

# TraCI variable ids (traci.constants), fixed by the protocol
_VAR_SPEED, _VAR_POSITION, _VAR_ANGLE = 0x40, 0x42, 0x43


class SumoError(ValueError):
    """A SUMO scenario or trace cannot be used (the message names the file or key)."""


# ------------------------------------------------------------------------------------------ install
def sumo_home() -> Path:
    """The SUMO installation of the ``eclipse-sumo`` wheel (binaries under ``bin/``).

    Raises:
        MissingExtraError: the ``sumo`` extra is not installed.
    """
    mod = require("sumo", "vehicles.mobility=sumo")
    home = getattr(mod, "SUMO_HOME", None)
    if home is None:
        raise missing_extra(
            "sumo", "vehicles.mobility=sumo (the importable 'sumo' module is not the eclipse-sumo wheel)"
        )
    return Path(home)


def sumo_version() -> str:
    """Version of the installed ``eclipse-sumo`` wheel."""
    import importlib.metadata

    try:
        return importlib.metadata.version("eclipse-sumo")
    except importlib.metadata.PackageNotFoundError:
        sumo_home()  # raises the missing-extra error
        return "unknown"


def _tool(name: str) -> Path:
    path = sumo_home() / "bin" / name
    if not path.is_file():
        raise SumoError(f"SUMO tool {name} not found at {path}; reinstall the 'sumo' extra")
    return path


def _die_with_parent() -> None:  # pragma: no cover - runs in the child
    """Linux: the child gets SIGKILL when this process dies, so no SUMO process outlives ours."""
    if sys.platform.startswith("linux"):
        import ctypes

        with contextlib.suppress(OSError, AttributeError):
            ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG


def run_tool(name: str, args: Sequence[str], cwd: Path | None = None) -> None:
    """Run a SUMO binary (``netgenerate``, ``sumo``) to completion.

    The child dies with this process (Linux, ``PR_SET_PDEATHSIG``; set only while this process has a
    single thread, because code run between fork and exec can deadlock in a threaded parent), and
    ``subprocess.run`` kills it on an interrupt.

    Raises:
        SumoError: the tool failed (its error output is in the message).
    """
    cmd = [str(_tool(name)), *args]
    _run(name, cmd, cwd)


def run_python_tool(name: str, args: Sequence[str], cwd: Path | None = None) -> None:
    """Run one of SUMO's Python tools (``randomTrips.py``) with this interpreter, like :func:`run_tool`."""
    script = sumo_home() / "tools" / name
    if not script.is_file():
        raise SumoError(f"SUMO tool {name} not found at {script}; reinstall the 'sumo' extra")
    _run(name, [sys.executable, str(script), *args], cwd)


def _run(name: str, cmd: list[str], cwd: Path | None) -> None:
    env = dict(os.environ, SUMO_HOME=str(sumo_home()))
    import threading

    preexec = _die_with_parent if threading.active_count() == 1 else None
    proc = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, preexec_fn=preexec)
    if proc.returncode != 0:
        tail = (proc.stderr or proc.stdout).strip()[-2000:]
        raise SumoError(f"{name} failed (exit {proc.returncode}): {' '.join(cmd)}\n{tail}")


def import_libsumo() -> Any:
    """``libsumo``, imported quietly (its import prints a pyarrow ABI note we do not need:
    libsumo's own parquet output is not used)."""
    if "libsumo" in sys.modules:
        return sys.modules["libsumo"]
    with contextlib.redirect_stdout(io.StringIO()):
        return require("libsumo", "vehicles.mobility=sumo")


# ------------------------------------------------------------------------------------------- cache
def cache_dir() -> Path:
    """Where generated scenarios are cached: ``$CV2X_MARL_SUMO_CACHE``, else the user cache dir; an
    absolute path (SUMO's tools run in temporary folders and are handed paths into it)."""
    env = os.environ.get(CACHE_ENV)
    if env:
        return Path(env).resolve()
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return (Path(base) / "cv2x_marl" / "sumo").resolve()


def content_key(data: Any) -> str:
    """Hex SHA-256 (24 digits) of ``data`` as canonical JSON."""
    return hashlib.sha256(json.dumps(data, sort_keys=True).encode()).hexdigest()[:24]


def cached(kind: str, key_data: Any, build: Callable[[Path], None]) -> Path:
    """The cache folder for ``key_data``, built by ``build(folder)`` when absent.

    ``build`` writes into a temporary folder, renamed into place when it returns, so a folder in
    the cache is always complete; of two processes building the same key, one rename wins.
    """
    root = cache_dir()
    final = root / f"{kind}-{content_key(key_data)}"
    if final.is_dir():
        return final
    root.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}.", suffix=".tmp", dir=root))
    try:
        build(tmp)
        (tmp / "key.json").write_text(json.dumps(key_data, sort_keys=True, indent=1) + "\n")
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o777 & ~umask)  # mkdtemp creates 0700; give the folder the usual mode
        try:
            os.rename(tmp, final)
        except OSError:
            if not final.is_dir():
                raise
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return final


# ---------------------------------------------------------------------------------------- scenario
@dataclass(frozen=True)
class Scenario:
    """A SUMO scenario ready to run.

    Attributes:
        sumocfg: the ``.sumocfg`` file.
        seed: SUMO's ``--seed`` (drawn from our seed).
        step_s: SUMO step length (the reservation period).
        generated: True when built from the ``road`` section (else the user's ``vehicles.sumo_config``).
    """

    sumocfg: Path
    seed: int
    step_s: float
    generated: bool


def check_generated(cfg: ScenarioConfig) -> None:
    """Refuse (ConfigError, naming the keys) a ``road`` / ``vehicles`` combination with no generated
    scenario. The grid has two demands: random walks for a fixed population, ``randomTrips.py`` trips for
    an open one; the highway's flows need an open population; open demands are sized by the slowest
    desired speed."""
    road, veh = cfg.road, cfg.vehicles
    if veh.speed_max_mps <= 0:
        raise ConfigError("vehicles.mobility=sumo needs vehicles.speed_max_mps > 0 (the network's speed limit)")
    if road.kind == "highway" and veh.population != "open":
        raise ConfigError(
            "a generated SUMO highway (road.kind=highway, vehicles.sumo_config null) has vehicles entering at one "
            "end and leaving at the other: set vehicles.population=open (the sumo-highway preset does)"
        )
    if veh.population == "open" and veh.speed_min_mps <= 0:
        raise ConfigError(
            "a generated open population needs vehicles.speed_min_mps > 0 (its demand is sized by the slowest "
            "desired speed)"
        )


def netgenerate_args(cfg: ScenarioConfig) -> list[str]:
    """``netgenerate`` arguments for the ``road`` section (the grid).

    Raises:
        ConfigError: a road kind without a generated SUMO grid network.
    """
    road, veh = cfg.road, cfg.vehicles
    if road.kind != "grid":
        raise ConfigError(f"netgenerate builds the grid network only (road.kind=grid, got {road.kind!r})")
    check_generated(cfg)
    spacing = road.length_m / road.n_roads_per_axis
    return [
        "--grid",
        f"--grid.x-number={road.n_roads_per_axis}",
        f"--grid.y-number={road.n_roads_per_axis}",
        f"--grid.length={spacing!r}",
        f"--grid.attach-length={spacing / 2!r}",
        f"--default.lanenumber={road.lanes_per_direction}",
        f"--default.lanewidth={road.lane_width_m!r}",
        f"--default.speed={veh.speed_max_mps!r}",
        "--default-junction-type=priority",
        "--no-turnarounds.except-deadend=true",
        "--seed=0",
    ]


def highway_plain_xml(cfg: ScenarioConfig) -> tuple[str, str]:
    """Plain ``(nodes, edges)`` XML of the highway (``netconvert`` input): one straight two-way road
    along x from 0 to ``road.length_m`` with its centre line at ``y = lanes_per_direction *
    lane_width_m`` (as :class:`cv2x_marl.sim.road.Road`); each direction's lanes lie to its right
    (``spreadType="right"``): eastbound in ``[0, c]``, westbound in ``[c, 2c]``."""
    road, veh = cfg.road, cfg.vehicles
    c = road.lanes_per_direction * road.lane_width_m
    nodes = (
        "<nodes>\n"
        f'    <node id="west" x="0" y="{c!r}" type="dead_end"/>\n'
        f'    <node id="east" x="{road.length_m!r}" y="{c!r}" type="dead_end"/>\n'
        "</nodes>\n"
    )
    common = (
        f'numLanes="{road.lanes_per_direction}" width="{road.lane_width_m!r}" speed="{veh.speed_max_mps!r}" '
        'spreadType="right"'
    )
    edges = (
        "<edges>\n"
        f'    <edge id="eastbound" from="west" to="east" {common}/>\n'
        f'    <edge id="westbound" from="east" to="west" {common}/>\n'
        "</edges>\n"
    )
    return nodes, edges


def build_network(cfg: ScenarioConfig) -> Path:
    """The cached ``net.net.xml`` for the ``road`` section (``netgenerate`` for the grid, ``netconvert``
    of :func:`highway_plain_xml` for the highway; run on a cache miss only)."""
    if cfg.road.kind == "highway":
        check_generated(cfg)
        nodes, edges = highway_plain_xml(cfg)
        hkey = {"what": "net", "generator": _GENERATOR_VERSION, "sumo": sumo_version(), "nodes": nodes, "edges": edges}

        def build_highway(folder: Path) -> None:
            (folder / "net.nod.xml").write_text(nodes)
            (folder / "net.edg.xml").write_text(edges)
            run_tool(
                "netconvert",
                [
                    "--node-files=net.nod.xml",
                    "--edge-files=net.edg.xml",
                    f"--output-file={NET_FILE}",
                    "--offset.disable-normalization=true",
                    "--no-turnarounds=true",
                    "--no-warnings=true",
                ],
                cwd=folder,
            )

        return cached("net", hkey, build_highway) / NET_FILE
    args = netgenerate_args(cfg)
    key = {"what": "net", "generator": _GENERATOR_VERSION, "sumo": sumo_version(), "netgenerate": args}

    def build(folder: Path) -> None:
        run_tool("netgenerate", [*args, f"--output-file={NET_FILE}", "--no-warnings=true"], cwd=folder)

    return cached("net", key, build) / NET_FILE


@dataclass(frozen=True)
class _Net:
    """The parts of a SUMO network the random walk needs."""

    edges: list[str]
    length_m: FloatArray
    speed_mps: FloatArray
    # per edge: {direction code: [successor edge index]}
    successors: list[dict[str, list[int]]]


def read_net(path: Path) -> _Net:
    """Edges (not internal), their lengths and their successors by turn direction."""
    edges: list[str] = []
    length: list[float] = []
    speed: list[float] = []
    conns: list[tuple[str, str, str]] = []
    try:
        for _, el in ET.iterparse(path):
            if el.tag == "edge" and el.get("function") != "internal" and not el.get("id", ":").startswith(":"):
                lanes = el.findall("lane")
                edges.append(el.get("id", ""))
                length.append(float(lanes[0].get("length", "nan")))
                speed.append(float(lanes[0].get("speed", "nan")))
            elif el.tag == "connection" and not el.get("from", ":").startswith(":"):
                conns.append((el.get("from", ""), el.get("to", ""), el.get("dir", "s").lower()))
            if el.tag in ("edge", "junction", "connection"):
                el.clear()
    except (ET.ParseError, OSError) as exc:
        raise SumoError(f"cannot read the SUMO network {path}: {exc}") from exc
    index = {e: i for i, e in enumerate(edges)}
    succ: list[dict[str, list[int]]] = [{} for _ in edges]
    for a, b, d in conns:
        if a in index and b in index:
            lst = succ[index[a]].setdefault(d, [])
            if index[b] not in lst:
                lst.append(index[b])
    return _Net(edges, np.array(length), np.array(speed), succ)


def random_walk_routes(
    net: _Net, cfg: ScenarioConfig, n: int, rng: np.random.Generator
) -> tuple[IntArray, FloatArray, FloatArray]:
    """``n`` random-walk routes over ``net`` with the paper's turning probabilities.

    All vehicles walk together, one edge per step and one uniform draw per vehicle per step: at the
    end of an edge a vehicle goes straight / left / right with ``road.p_straight`` / ``p_left`` /
    ``p_right``, renormalised over the turns that exist there; where none exists (a dead end) it
    turns back. Every route covers at least ``vehicles.speed_max_mps * ROUTE_HORIZON_S`` metres.

    Returns:
        (routes [n, edges] as edge indices, desired speeds [n] in m/s, speed factors [n] = desired
        speed / ``vehicles.speed_max_mps``, the network's speed limit).
    """
    road, veh = cfg.road, cfg.vehicles
    n_edges = len(net.edges)
    succ = np.zeros((n_edges, 3), dtype=np.int64)
    cum = np.ones((n_edges, 3))
    for e, options in enumerate(net.successors):
        turns: list[tuple[int, float]] = []
        for d, p in (("s", road.p_straight), ("l", road.p_left), ("r", road.p_right)):
            if options.get(d) and p > 0:
                turns.append((options[d][0], p))
        if not turns:  # a dead end (or only zero-probability turns): turn back
            back = options.get("t") or [x for lst in options.values() for x in lst]
            if not back:
                raise SumoError(f"edge {net.edges[e]} of the generated network has no successor")
            turns = [(back[0], 1.0)]
        w = np.array([p for _, p in turns])
        k = len(turns)
        succ[e, :k] = [t for t, _ in turns]
        succ[e, k:] = turns[-1][0]
        cum[e, :k] = np.cumsum(w / w.sum())
    first = rng.choice(n_edges, size=n, p=net.length_m / net.length_m.sum())
    desired = rng.uniform(veh.speed_min_mps, veh.speed_max_mps, size=n)
    horizon_m = veh.speed_max_mps * ROUTE_HORIZON_S
    steps = [first]
    driven = np.zeros(n)  # the first edge is not counted: the vehicle may start at its end
    while driven.min() < horizon_m:
        cur = steps[-1]
        u = rng.random(n)
        pick = np.minimum((u[:, None] >= cum[cur]).sum(axis=1), 2)
        nxt = succ[cur, pick]
        steps.append(nxt)
        driven += net.length_m[nxt]
    return np.stack(steps, axis=1), desired, desired / veh.speed_max_mps


def routes_xml(net: _Net, routes: IntArray, speed_factor: FloatArray) -> str:
    """The ``.rou.xml`` text: one vType and a vehicle per route, all departing at t = 0 from a free
    random position of their first edge (``departPos="random_free"``: SUMO draws it with its seed)."""
    width = max(3, len(str(len(routes) - 1)))
    names = np.asarray(net.edges, dtype=object)
    lines = [
        "<routes>",
        '    <vType id="car" vClass="passenger" speedDev="0"/>',
    ]
    for k, route in enumerate(routes):
        edges = " ".join(names[route].tolist())
        lines.append(
            f'    <vehicle id="veh{k:0{width}d}" type="car" depart="0" departPos="random_free" '
            f'departSpeed="max" departLane="best" speedFactor="{speed_factor[k]:.6f}">'
        )
        lines.append(f'        <route edges="{edges}"/>')
        lines.append("    </vehicle>")
    lines.append("</routes>")
    return "\n".join(lines) + "\n"


def sumocfg_xml(net_file: str, route_file: str, step_s: float, seed: int) -> str:
    """A ``.sumocfg`` for the generated files (teleports off: a stuck vehicle would vanish)."""
    return (
        "<configuration>\n"
        "    <input>\n"
        f'        <net-file value="{net_file}"/>\n'
        f'        <route-files value="{route_file}"/>\n'
        "    </input>\n"
        "    <time>\n"
        '        <begin value="0"/>\n'
        f'        <step-length value="{step_s!r}"/>\n'
        "    </time>\n"
        "    <processing>\n"
        '        <time-to-teleport value="-1"/>\n'
        "    </processing>\n"
        "    <random_number>\n"
        f'        <seed value="{seed}"/>\n'
        "    </random_number>\n"
        "    <report>\n"
        '        <no-step-log value="true"/>\n'
        "    </report>\n"
        "</configuration>\n"
    )


#: desired-speed classes of the highway flows (a uniform speed law on [speed_min, speed_max] in equal bins)
HIGHWAY_SPEED_CLASSES = 8


#: SUMO seconds over which a generated open demand's vehicle count is measured to calibrate it
CALIBRATION_WINDOW_S = 120.0


def count_in_network(cfg: ScenarioConfig, net_path: Path, routes_xml_text: str, seed: int) -> float:
    """Mean number of vehicles in the network over :data:`CALIBRATION_WINDOW_S` seconds from
    ``cfg.sumo_begin_s``, from a headless ``sumo`` run of the demand (``--summary-output``, the run's steps)."""
    begin = cfg.sumo_begin_s
    with tempfile.TemporaryDirectory(prefix="cv2x-calibrate-") as tmp:
        t = Path(tmp)
        (t / "demand.rou.xml").write_text(routes_xml_text)
        run_tool(
            "sumo",
            ["-n", str(net_path), "-r", "demand.rou.xml", "--begin", "0", "--end", repr(begin + CALIBRATION_WINDOW_S),
             "--step-length", repr(cfg.traffic.rri_ms / 1000.0), "--seed", str(seed), "--time-to-teleport", "-1",
             "--summary-output", "summary.xml", "--no-step-log", "true", "--no-warnings", "true"],
            cwd=t,
        )  # fmt: skip
        running = [
            float(el.get("running", "0"))
            for el in ET.parse(t / "summary.xml").getroot().iter("step")
            if float(el.get("time", "0")) >= begin - 1e-9
        ]
    return float(np.mean(running)) if running else 0.0


def highway_flows_xml(
    cfg: ScenarioConfig, horizon_s: float = ROUTE_HORIZON_S, q: float | None = None
) -> tuple[str, float]:
    """The highway demand: Poisson flows entering at either end, leaving at the other.

    Desired speeds are uniform on ``[speed_min_mps, speed_max_mps]``, discretised into
    :data:`HIGHWAY_SPEED_CLASSES` equal bins (one vType per bin, its midpoint as ``speedFactor`` of
    the speed limit ``speed_max_mps``). A vehicle at desired speed ``v`` stays ``L / v`` on the road,
    so the flow per direction that gives the resolved vehicle count ``N`` (half per direction) in
    free flow is ``q = (N / 2) / (L * mean(1 / v_k))`` vehicles per second, split equally over the
    classes; SUMO draws the Poisson departures (``period="exp(rate)"``) with its seed.
    :func:`build_scenario` then corrects ``q`` once by the count measured in SUMO
    (:func:`count_in_network`), since car following and insertion change it.

    Args:
        cfg: the scenario.
        horizon_s: SUMO time until which vehicles enter.
        q: flow per direction, vehicles per second (None: the free-flow value above).

    Returns:
        ``(routes XML, q)``: the ``.rou.xml`` text and the flow per direction in vehicles per second.
    """
    k = HIGHWAY_SPEED_CLASSES
    if q is None:
        q = 0.5 * cfg.n_vehicles / (cfg.road.length_m * float(np.mean(1.0 / speed_classes(cfg))))
    lines = ["<routes>", *_vtypes_xml(cfg)]
    lines.append('    <route id="east" edges="eastbound"/>')
    lines.append('    <route id="west" edges="westbound"/>')
    for way in ("east", "west"):
        for c in range(k):
            lines.append(
                f'    <flow id="{way}{c}" type="v{c}" route="{way}" begin="0" end="{horizon_s!r}" '
                f'period="exp({q / k:.9f})" departLane="free" departSpeed="desired" departPos="base"/>'
            )
    lines.append("</routes>")
    return "\n".join(lines) + "\n", q


def speed_classes(cfg: ScenarioConfig) -> FloatArray:
    """[K] desired speeds (m/s) of the open demands' vTypes: the midpoints of
    :data:`HIGHWAY_SPEED_CLASSES` equal bins of ``[speed_min_mps, speed_max_mps]``."""
    veh = cfg.vehicles
    edges = np.linspace(veh.speed_min_mps, veh.speed_max_mps, HIGHWAY_SPEED_CLASSES + 1)
    return np.asarray(0.5 * (edges[:-1] + edges[1:]))


def _vtypes_xml(cfg: ScenarioConfig) -> list[str]:
    factors = speed_classes(cfg) / cfg.vehicles.speed_max_mps
    return [
        f'    <vType id="v{c}" vClass="passenger" speedFactor="{f:.6f}" speedDev="0"/>' for c, f in enumerate(factors)
    ]


def _route_lengths_m(routes: Path, net: _Net) -> FloatArray:
    """[V] length of every ``<route edges=...>`` of a route file (edge lengths summed)."""
    length = dict(zip(net.edges, net.length_m.tolist(), strict=True))
    out = [sum(length[e] for e in el.get("edges", "").split()) for el in ET.parse(routes).getroot().iter("route")]
    return np.array(out)


def random_trips_xml(
    cfg: ScenarioConfig,
    net_path: Path,
    seeds: Sequence[int],
    horizon_s: float,
    sumo_seed: int,
) -> tuple[str, float]:
    """The open grid's demand: SUMO's ``randomTrips.py`` (origin and destination edges drawn with
    probability proportional to their length, ``--length``; routed by ``duarouter``), sized for the
    resolved vehicle count ``N``. A vehicle departs at a free random position of its first edge
    (``departPos="random_free"``) and leaves the network at the end of its last.

    Little's law sizes it: a trip of length ``l`` at desired speed ``v`` lasts ``l / v``, so the
    departure period that keeps ``N`` vehicles in free flow is ``mean(l) * mean(1 / v) / N``; the
    mean route length comes from a first ``randomTrips`` sample of 1,000 trips. Junctions, turns and
    queues slow vehicles, so the period is then corrected once by the count measured in SUMO
    (:func:`count_in_network` with ``sumo_seed``). Departures are uniform random over
    ``[0, horizon_s]`` (``--random-depart``); each trip gets a desired-speed class
    (:func:`speed_classes`). ``seeds`` (three, drawn from the simulator's ``mobility`` stream): the
    sample's and the trips' ``randomTrips`` seeds and the seed of the speed-class draws.

    Returns:
        ``(routes XML, period_s)``.
    """
    net = read_net(net_path)
    common = ["-n", str(net_path)]
    with tempfile.TemporaryDirectory(prefix="cv2x-trips-") as tmp:
        t = Path(tmp)
        run_python_tool(
            "randomTrips.py",
            [*common, "-o", "sample.trips.xml", "-r", "sample.rou.xml", "--seed", str(seeds[0]), "-b", "0",
             "-e", "1000", "--period", "1", "--length"],
            cwd=t,
        )  # fmt: skip
        mean_len_m = float(np.mean(_route_lengths_m(t / "sample.rou.xml", net)))
    period_s = mean_len_m * float(np.mean(1.0 / speed_classes(cfg))) / cfg.n_vehicles
    kinds = np.random.default_rng(seeds[2]).integers(
        0, HIGHWAY_SPEED_CLASSES, size=int(horizon_s / (0.25 * period_s)) + 16
    )
    text = _random_trips(cfg, net_path, seeds[1], horizon_s, period_s, kinds)
    # one correction by SUMO's count (within a factor 4 either way)
    period_s *= float(np.clip(count_in_network(cfg, net_path, text, sumo_seed) / cfg.n_vehicles, 0.25, 4.0))
    return _random_trips(cfg, net_path, seeds[1], horizon_s, period_s, kinds), period_s


def _random_trips(
    cfg: ScenarioConfig, net_path: Path, seed: int, horizon_s: float, period_s: float, kinds: IntArray
) -> str:
    """``randomTrips.py`` routes at ``period_s``, trip ``i`` of desired-speed class ``kinds[i]``."""
    with tempfile.TemporaryDirectory(prefix="cv2x-trips-") as tmp:
        t = Path(tmp)
        run_python_tool(
            "randomTrips.py",
            ["-n", str(net_path), "-o", "trips.xml", "-r", "trips.rou.xml", "--seed", str(seed), "-b", "0",
             "-e", repr(float(horizon_s)), "--period", repr(period_s), "--random-depart", "--length"],
            cwd=t,
        )  # fmt: skip
        root = ET.parse(t / "trips.rou.xml").getroot()
    vehicles = list(root.iter("vehicle"))
    if len(vehicles) > kinds.size:
        raise SumoError(f"randomTrips.py wrote {len(vehicles)} trips, more than the {kinds.size} speed classes drawn")
    lines = ["<routes>", *_vtypes_xml(cfg)]
    for el, c in zip(vehicles, kinds.tolist(), strict=False):
        route = el.find("route")
        edges = "" if route is None else route.get("edges", "")
        lines.append(
            f'    <vehicle id="trip{el.get("id")}" type="v{c}" depart="{el.get("depart")}" departLane="best" '
            f'departSpeed="desired" departPos="random_free">'
        )
        lines.append(f'        <route edges="{edges}"/>')
        lines.append("    </vehicle>")
    lines.append("</routes>")
    return "\n".join(lines) + "\n"


def draw_sumo_seed(rng: np.random.Generator) -> int:
    """SUMO's ``--seed``: the first draw of the mobility stream."""
    return int(rng.integers(0, 2**31 - 1))


def build_scenario(cfg: ScenarioConfig, rng: np.random.Generator) -> Scenario:
    """The scenario of ``cfg``: the user's ``vehicles.sumo_config``, or one generated from the road.

    Args:
        cfg: the scenario configuration (``vehicles.mobility=sumo``).
        rng: the simulator's ``mobility`` stream (SUMO's seed, then the demand, are drawn from it).
    """
    step_s = cfg.traffic.rri_ms / 1000.0
    seed = draw_sumo_seed(rng)
    user = cfg.vehicles.sumo_config
    if user is not None:
        path = check_sumocfg(user)
        return Scenario(path, seed, step_s, generated=False)
    net_path = build_network(cfg)
    if cfg.road.kind == "highway" or cfg.vehicles.population == "open":
        return _open_demand_scenario(cfg, net_path, seed, [int(x) for x in rng.integers(0, 2**31 - 1, size=3)])
    else:
        net = read_net(net_path)
        routes, _, factor = random_walk_routes(net, cfg, cfg.n_vehicles, rng)
        rou = routes_xml(net, routes, factor)
    # the network stays in its own cache folder (shared by every seed); export copies it
    sumocfg = sumocfg_xml(f"../{net_path.parent.name}/{NET_FILE}", ROUTE_FILE, step_s, seed)
    key = {
        "what": "scenario",
        "generator": _GENERATOR_VERSION,
        "net": net_path.parent.name,
        "routes": hashlib.sha256(rou.encode()).hexdigest(),
        "sumocfg": hashlib.sha256(sumocfg.encode()).hexdigest(),
    }

    def build(folder: Path) -> None:
        (folder / ROUTE_FILE).write_text(rou)
        (folder / CFG_FILE).write_text(sumocfg)

    return Scenario(cached("scenario", key, build) / CFG_FILE, seed, step_s, generated=True)


def _open_demand_scenario(cfg: ScenarioConfig, net_path: Path, seed: int, demand_seeds: list[int]) -> Scenario:
    """The generated open-population scenario (highway flows or grid random trips), cached under a key
    of its inputs: generating it runs SUMO (the calibration) and ``randomTrips.py``, about a second."""
    step_s = cfg.traffic.rri_ms / 1000.0
    horizon_s = cfg.sumo_begin_s + ROUTE_HORIZON_S
    demand = "flows" if cfg.road.kind == "highway" else "random_trips"
    sumocfg = sumocfg_xml(f"../{net_path.parent.name}/{NET_FILE}", ROUTE_FILE, step_s, seed)
    v = cfg.vehicles
    key = {
        "what": "scenario",
        "generator": _GENERATOR_VERSION,
        "sumo": sumo_version(),
        "net": net_path.parent.name,
        "demand": demand,
        "inputs": [cfg.n_vehicles, v.speed_min_mps, v.speed_max_mps, cfg.sumo_begin_s, horizon_s, step_s],
        "seeds": [seed, *demand_seeds],
        "sumocfg": hashlib.sha256(sumocfg.encode()).hexdigest(),
    }

    def build(folder: Path) -> None:
        if demand == "flows":
            rou, q = highway_flows_xml(cfg, horizon_s)
            # one correction by SUMO's count (within a factor 4 either way)
            count = count_in_network(cfg, net_path, rou, seed)
            rou, _ = highway_flows_xml(cfg, horizon_s, q * float(np.clip(cfg.n_vehicles / max(count, 1.0), 0.25, 4.0)))
        else:
            rou, _ = random_trips_xml(cfg, net_path, demand_seeds, horizon_s, seed)
        (folder / ROUTE_FILE).write_text(rou)
        (folder / CFG_FILE).write_text(sumocfg)

    return Scenario(cached("scenario", key, build) / CFG_FILE, seed, step_s, generated=True)


def check_sumocfg(path: str | Path) -> Path:
    """``path`` as an existing, parseable ``.sumocfg`` whose net and route files exist.

    Raises:
        ConfigError: naming ``vehicles.sumo_config`` and the file.
    """
    p = Path(path).expanduser()
    if not p.is_file():
        raise ConfigError(f"vehicles.sumo_config: {str(path)!r} does not exist or is not a file")
    try:
        root = ET.parse(p).getroot()
    except ET.ParseError as exc:
        raise ConfigError(f"vehicles.sumo_config: {p} is not a valid SUMO configuration (XML: {exc})") from exc
    if root.tag != "configuration":
        raise ConfigError(f"vehicles.sumo_config: {p} is not a SUMO configuration (root <{root.tag}>)")
    for option in ("net-file", "route-files"):
        el = root.find(f".//{option}")
        if el is None:
            if option == "net-file":
                raise ConfigError(f"vehicles.sumo_config: {p} names no <net-file>")
            continue
        for name in (el.get("value") or "").split(","):
            name = name.strip()
            if name and not (p.parent / name).is_file():
                raise ConfigError(f"vehicles.sumo_config: {p}: its {option} {name!r} does not exist")
    return p.resolve()


# ------------------------------------------------------------------------------------------ states
def tracked_state(pos_m: FloatArray, speed_mps: FloatArray, angle_deg: FloatArray, time_s: float) -> TrackedState:
    """A :class:`TrackedState` from SUMO's position, speed and angle (degrees clockwise from north)."""
    a = np.deg2rad(angle_deg)
    vel = np.stack([speed_mps * np.sin(a), speed_mps * np.cos(a)], axis=1)
    return TrackedState(np.asarray(pos_m, dtype=np.float64), vel, np.zeros(pos_m.shape[0]), time_s)


def _moved(prev: TrackedState, new: TrackedState) -> TrackedState:
    """``new`` with the odometer of ``prev`` advanced by the straight distance between them.

    Both sources count the odometer this way (it drives the shadowing decorrelation), so a
    replayed trace gives the same run as live stepping.
    """
    step = np.hypot(*(new.pos_m - prev.pos_m).T)
    return TrackedState(new.pos_m, new.vel_mps, prev.odometer_m + step, new.time_s)


def _select(ids_present: Sequence[str], first_seen: dict[str, float], n: int) -> list[str]:
    """The first ``n`` vehicles present, by (first time seen, ID)."""
    return sorted(ids_present, key=lambda v: (first_seen[v], v))[:n]


def assign_slots(slots: list[str | None], now: Sequence[str], what: str) -> NDArray[np.bool_]:
    """``vehicles.population=open``: update the slot table ``slots`` (in place) to the vehicles ``now``
    present: the slots of vehicles gone are freed, then the new vehicles take the lowest free slots in
    the order given (the same rule for the lockstep and a trace, so a replay gives the lockstep run).

    Args:
        slots: [capacity] the vehicle ID in each slot, None where empty.
        now: the IDs present now, new ones in the order they take slots.
        what: the source, for the error message.

    Returns:
        [capacity] the slots whose vehicle is new.

    Raises:
        SumoError: more vehicles present than slots (naming ``vehicles.capacity``).
    """
    here = set(now)
    for k, v in enumerate(slots):
        if v is not None and v not in here:
            slots[k] = None
    held = {v for v in slots if v is not None}
    new = [v for v in now if v not in held]
    entered = np.zeros(len(slots), dtype=bool)
    if not new:
        return entered
    free = [k for k, v in enumerate(slots) if v is None]
    if len(new) > len(free):
        raise SumoError(
            f"{what} has {len(held) + len(new)} vehicles in the network at once, more than vehicles.capacity = "
            f"{len(slots)} slots; raise vehicles.capacity"
        )
    for k, v in zip(free, new, strict=False):
        slots[k] = v
        entered[k] = True
    return entered


def _open_state(
    slots: list[str | None],
    entered: NDArray[np.bool_],
    values: dict[str, tuple[float, float, float, float]],
    time_s: float,
    prev: TrackedState | None,
) -> TrackedState:
    """The :class:`TrackedState` of an open population from ``values`` (ID -> x, y, vx, vy) of the
    vehicles in ``slots``; the odometer goes on for a vehicle that stays and starts at 0 for a new one."""
    n = len(slots)
    rows = np.full((n, 4), np.nan)
    present = np.array([v is not None for v in slots], dtype=bool)
    for k in np.flatnonzero(present).tolist():
        rows[k] = values[slots[k]]  # type: ignore[index]
    pos, vel = rows[:, :2].copy(), rows[:, 2:].copy()
    odo = np.zeros(n)
    if prev is not None:
        stay = present & ~entered
        step = np.hypot(*(pos[stay] - prev.pos_m[stay]).T)
        odo[stay] = prev.odometer_m[stay] + step
    return TrackedState(pos, vel, odo, time_s, present, entered)


def _first_seen_order(ids: Sequence[str], first_seen: dict[str, float]) -> list[str]:
    """``ids`` by (first time seen, ID): the order in which the vehicles present at time zero take slots."""
    return sorted(ids, key=lambda v: (first_seen.get(v, np.inf), v))


# ---------------------------------------------------------------------------------------- lockstep
_ACTIVE: SumoLockstep | None = None


class SumoLockstep:
    """A SUMO scenario run through libsumo in this process, one step per call to :meth:`advance`.

    libsumo holds one simulation per process: starting a second lockstep closes the first (which
    then refuses to step). SUMO runs inside this process, so it cannot outlive it.

    Args:
        scenario: the scenario to run.
        n: vehicles to track (``open_population``: the slots, the most vehicles present at once).
        extra_args: further SUMO options (e.g. ``["--fcd-output", "fcd.xml"]``).
        begin_s: SUMO time at which the run may start (``vehicles.sumo_begin_s``).
        open_population: track every vehicle in the network as it enters and leaves
            (``vehicles.population=open``) instead of the first ``n``.
    """

    def __init__(
        self,
        scenario: Scenario,
        n: int,
        extra_args: Sequence[str] = (),
        begin_s: float = 0.0,
        open_population: bool = False,
    ) -> None:
        global _ACTIVE
        self.scenario = scenario
        self.n = n
        self.begin_s = begin_s
        self.open_population = open_population
        self.slots: list[str | None] = [None] * n
        self.closed = False
        self._ls = import_libsumo()
        if _ACTIVE is not None:
            _ACTIVE.close()
        args = [
            "sumo",
            "-c",
            str(scenario.sumocfg),
            "--seed",
            str(scenario.seed),
            "--step-length",
            repr(scenario.step_s),
            "--no-step-log",
            "true",
            "--no-warnings",
            "true",
            *extra_args,
        ]
        try:
            with contextlib.redirect_stdout(io.StringIO()):
                self._ls.start(args)
        except self._ls.TraCIException as exc:
            key = "" if scenario.generated else "vehicles.sumo_config: "
            raise SumoError(
                f"{key}SUMO cannot load {scenario.sumocfg}: {str(exc).strip()} (SUMO's own messages are on stderr)"
            ) from exc
        _ACTIVE = self
        if open_population:
            first_seen, present = self._step_until(1)
            self.state = self._read_open(_first_seen_order(present, first_seen), None)
        else:
            first_seen, present = self._step_until(self.n)
            self.fixed_ids = _select(present, first_seen, self.n)
            self.slots = list(self.fixed_ids)
            for vid in self.fixed_ids:
                self._ls.vehicle.subscribe(vid, [_VAR_POSITION, _VAR_SPEED, _VAR_ANGLE])
            self.state = self._read()
        self.t0_s = self.time_s

    @property
    def ids(self) -> list[str | None]:
        """The vehicle in each slot (vehicle ``i`` of the simulator), None where a slot is empty."""
        return list(self.slots)

    def _read_open(self, now: Sequence[str], prev: TrackedState | None) -> TrackedState:
        """Open population: slots updated to the vehicles ``now`` present (new ones in slot order),
        new ones subscribed, every present vehicle read back."""
        entered = assign_slots(self.slots, now, f"the SUMO scenario {self.scenario.sumocfg}")
        veh = self._ls.vehicle
        for k in np.flatnonzero(entered).tolist():
            veh.subscribe(self.slots[k], [_VAR_POSITION, _VAR_SPEED, _VAR_ANGLE])
        res = veh.getAllSubscriptionResults()
        values: dict[str, tuple[float, float, float, float]] = {}
        for vid in self.slots:
            if vid is not None:
                r = res[vid]
                (x, y), sp, a = r[_VAR_POSITION], r[_VAR_SPEED], np.deg2rad(r[_VAR_ANGLE])
                values[vid] = (x, y, sp * np.sin(a), sp * np.cos(a))
        return _open_state(self.slots, entered, values, self.time_s, prev)

    @property
    def time_s(self) -> float:
        """SUMO time of the state last read (the FCD ``time`` of the same instant)."""
        return float(self._ls.simulation.getTime()) - self.scenario.step_s

    def _step_until(self, need: int) -> tuple[dict[str, float], list[str]]:
        """Step until ``begin_s`` has passed and at least ``need`` vehicles are in the network (``n``
        with a fixed population, 1 with an open one); the time each vehicle was first seen and the IDs
        present."""
        first_seen: dict[str, float] = {}
        sim = self._ls.simulation
        while True:
            self._ls.simulationStep()
            t = self.time_s
            for vid in sim.getDepartedIDList():
                first_seen.setdefault(vid, t)
            present = list(self._ls.vehicle.getIDList())
            if len(present) >= need and t >= self.begin_s - 1e-9:
                return first_seen, present
            if sim.getMinExpectedNumber() == 0 or t >= self.begin_s + MAX_FILL_S:
                self.close()
                where = f"the SUMO scenario {self.scenario.sumocfg}"
                if self.open_population:
                    raise SumoError(
                        f"{where} has no vehicle in the network at or after vehicles.sumo_begin_s = "
                        f"{self.begin_s:g} s (looked until t = {t:g} s)"
                    )
                raise SumoError(
                    f"{where} never has {self.n} vehicles in the network at once (by t = {t:g} s it has "
                    f"{len(present)}); lower vehicles.n_vehicles or add demand to the scenario"
                )

    def _read(self) -> TrackedState:
        res = self._ls.vehicle.getAllSubscriptionResults()
        missing = [v for v in self.fixed_ids if v not in res]
        if missing:
            t = self.time_s
            self.close()
            raise SumoError(
                f"vehicle {missing[0]!r} of {self.scenario.sumocfg} left the network at t = {t:g} s "
                f"({len(missing)} of the {self.n} tracked vehicles gone); with vehicles.population=fixed every "
                "tracked vehicle must stay until the run ends (longer routes, fewer subframes, or "
                "vehicles.population=open)"
            )
        rows = [res[v] for v in self.fixed_ids]
        pos = np.array([r[_VAR_POSITION] for r in rows], dtype=np.float64)
        speed = np.array([r[_VAR_SPEED] for r in rows], dtype=np.float64)
        angle = np.array([r[_VAR_ANGLE] for r in rows], dtype=np.float64)
        return tracked_state(pos, speed, angle, self.time_s)

    def advance(self) -> TrackedState:
        """One SUMO step (one reservation period); the new state."""
        if self.closed:
            raise RuntimeError(
                "this SUMO run is closed (libsumo runs one simulation per process: a newer Simulator with "
                "vehicles.mobility=sumo took it over, or close() was called); reset() the simulator"
            )
        self._ls.simulationStep()
        if self.open_population:
            ids = self._ls.vehicle.getIDList()
            held = set(self.slots)
            now = [v for v in ids if v in held] + sorted(v for v in ids if v not in held)  # new ones in ID order
            self.state = self._read_open(now, self.state)
        else:
            self.state = _moved(self.state, self._read())
        return self.state

    def command(self, target_speed_mps: FloatArray, lane_change: NDArray[np.int64], duration_s: float) -> None:
        """Commands for the next step, honoured by SUMO within its own limits (the env's
        ``traffic_action="speed"``).

        Args:
            target_speed_mps: [N] speed each tracked vehicle should drive at (``vehicle.setSpeed``:
                SUMO approaches it within the vehicle type's acceleration and deceleration, and its
                car-following model still keeps the vehicle safe); a negative value hands the vehicle
                back to its own driver model; NaN leaves it as it is (no command).
            lane_change: [N] -1 (one lane to the right), 0 (stay), +1 (one lane to the left)
                (``vehicle.changeLaneRelative`` for ``duration_s``; ignored where no such lane exists).
            duration_s: how long a lane-change request holds (s).
        """
        if self.closed:
            raise RuntimeError("this SUMO run is closed; reset() the simulator")
        target = np.asarray(target_speed_mps, dtype=np.float64)
        lanes = np.asarray(lane_change, dtype=np.int64)
        if target.shape != (self.n,) or lanes.shape != (self.n,):
            raise ValueError(f"target_speed_mps and lane_change must have shape ({self.n},)")
        if self.open_population:
            raise ValueError("commands need vehicles.population=fixed (the env's agents are a fixed set of vehicles)")
        veh = self._ls.vehicle
        for vid, v, dl in zip(self.fixed_ids, target.tolist(), lanes.tolist(), strict=True):  # libsumo: per vehicle
            if v == v:  # not NaN
                veh.setSpeed(vid, -1.0 if v < 0 else v)  # -1: SUMO's own driver again
            if dl != 0:
                veh.changeLaneRelative(vid, int(dl), float(duration_s))

    def close(self) -> None:
        """Stop the SUMO simulation (idempotent)."""
        global _ACTIVE
        if self.closed:
            return
        self.closed = True
        if _ACTIVE is self:
            _ACTIVE = None
            with contextlib.suppress(Exception), contextlib.redirect_stdout(io.StringIO()):
                self._ls.close()


# ------------------------------------------------------------------------------------------- trace
@dataclass(frozen=True)
class Trace:
    """An FCD trace as flat records (one per vehicle and timestep present).

    Attributes:
        time_s: [T] sorted distinct timesteps.
        ids: [V] sorted distinct vehicle IDs.
        ti, vi: [R] timestep index and vehicle index of every record.
        x_m, y_m, speed_mps, angle_deg: [R] the records' values (angle: degrees clockwise from north).
    """

    time_s: FloatArray
    ids: list[str]
    ti: IntArray
    vi: IntArray
    x_m: FloatArray
    y_m: FloatArray
    speed_mps: FloatArray
    angle_deg: FloatArray

    def dense(self, cols: Sequence[int] | IntArray) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """(x, y, speed, angle) of the vehicles ``cols`` as [T, len(cols)] arrays, NaN where absent."""
        cols = np.asarray(cols, dtype=np.int64)
        where = np.full(len(self.ids), -1, dtype=np.int64)
        where[cols] = np.arange(cols.size)
        keep = where[self.vi] >= 0
        out = [np.full((self.time_s.size, cols.size), np.nan) for _ in range(4)]
        for arr, val in zip(out, (self.x_m, self.y_m, self.speed_mps, self.angle_deg), strict=True):
            arr[self.ti[keep], where[self.vi[keep]]] = val[keep]
        return out[0], out[1], out[2], out[3]


_COLUMNS = {
    "time": ("time", "timestep_time"),
    "id": ("id", "vehicle_id"),
    "x": ("x", "vehicle_x"),
    "y": ("y", "vehicle_y"),
    "angle": ("angle", "vehicle_angle"),
    "speed": ("speed", "vehicle_speed"),
}


def read_trace(path: str | Path) -> Trace:
    """Read a SUMO FCD trace: XML (``--fcd-output``, streamed) or parquet (columns ``time, id, x, y,
    angle, speed``, or SUMO's ``timestep_time, vehicle_id, vehicle_x, ...``).

    Raises:
        ConfigError: naming ``vehicles.trace_file`` and the file (missing, unreadable, no vehicles).
    """
    p = Path(path).expanduser()
    if not p.is_file():
        raise ConfigError(f"vehicles.trace_file: {str(path)!r} does not exist or is not a file")
    if p.suffix.lower() == ".parquet":
        t, vid, x, y, ang, spd = _read_parquet(p)
    else:
        t, vid, x, y, ang, spd = _read_fcd_xml(p)
    if t.size == 0:
        raise ConfigError(f"vehicles.trace_file: {p} holds no vehicle positions")
    times, ti = np.unique(t, return_inverse=True)
    ids, vi = np.unique(vid, return_inverse=True)
    return Trace(times, [str(v) for v in ids], ti.astype(np.int64), vi.astype(np.int64), x, y, spd, ang)


def _read_fcd_xml(p: Path) -> tuple[FloatArray, NDArray[np.str_], FloatArray, FloatArray, FloatArray, FloatArray]:
    t: list[float] = []
    vid: list[str] = []
    vals: list[tuple[float, float, float, float]] = []
    now = float("nan")
    try:
        for event, el in ET.iterparse(p, events=("start", "end")):
            if event == "start":
                if el.tag == "timestep":
                    now = float(el.get("time", "nan"))
                continue
            if el.tag == "vehicle":
                t.append(now)
                vid.append(el.get("id", ""))
                vals.append(
                    (
                        float(el.get("x", "nan")),
                        float(el.get("y", "nan")),
                        float(el.get("angle", "0")),
                        float(el.get("speed", "0")),
                    )
                )
            elif el.tag == "timestep":
                el.clear()
    except (ET.ParseError, ValueError) as exc:
        raise ConfigError(f"vehicles.trace_file: {p} is not a readable SUMO FCD XML trace: {exc}") from exc
    v = np.array(vals, dtype=np.float64).reshape(-1, 4)
    return np.array(t), np.array(vid, dtype=str), v[:, 0], v[:, 1], v[:, 2], v[:, 3]


def _read_parquet(p: Path) -> tuple[FloatArray, NDArray[np.str_], FloatArray, FloatArray, FloatArray, FloatArray]:
    import pyarrow.parquet as pq

    try:
        table = pq.read_table(p)
    except Exception as exc:
        raise ConfigError(f"vehicles.trace_file: {p} is not a readable parquet file: {exc}") from exc
    cols: dict[str, np.ndarray] = {}
    for name, options in _COLUMNS.items():
        hit = next((c for c in options if c in table.column_names), None)
        if hit is None:
            if name in ("angle", "speed"):
                cols[name] = np.zeros(table.num_rows)
                continue
            have = ", ".join(table.column_names)
            raise ConfigError(f"vehicles.trace_file: {p} has no column {' or '.join(options)} (columns: {have})")
        cols[name] = table.column(hit).to_numpy(zero_copy_only=False)
    return (
        cols["time"].astype(np.float64),
        cols["id"].astype(str),
        cols["x"].astype(np.float64),
        cols["y"].astype(np.float64),
        cols["angle"].astype(np.float64),
        cols["speed"].astype(np.float64),
    )


class TraceReplay:
    """Replay of an FCD trace, linearly interpolated to a period of ``step_s``.

    The tracked vehicles and time zero follow the rule of the lockstep (module docstring).
    Positions and velocity vectors are interpolated between the two samples around each time.

    With ``open_population`` every vehicle of the trace is tracked while it is in it: a vehicle is
    present at a time when the trace has it at both samples around that time (at the sample, on
    one), and takes a slot as in the lockstep (:func:`assign_slots`).

    Args:
        path: the trace file (``vehicles.trace_file``).
        n: vehicles to track (``open_population``: the slots).
        step_s: the period (``traffic.rri_ms`` in seconds).
        begin_s: trace time at which the run may start (``vehicles.sumo_begin_s``).
        open_population: ``vehicles.population=open``.
    """

    def __init__(
        self, path: str | Path, n: int, step_s: float, begin_s: float = 0.0, open_population: bool = False
    ) -> None:
        self.path = Path(path)
        self.trace = tr = read_trace(path)
        self.n = n
        self.step_s = step_s
        self.open_population = open_population
        self.k = 0
        if open_population:
            self._init_open(begin_s)
            return
        counts = np.bincount(tr.ti, minlength=tr.time_s.size)
        full = np.flatnonzero((counts >= n) & (tr.time_s >= begin_s - 1e-9))
        if full.size == 0:
            raise ConfigError(
                f"vehicles.trace_file: {self.path} never has {n} vehicles at once (at most {int(counts.max())}); "
                "lower vehicles.n_vehicles"
            )
        k0 = int(full[0])
        first = np.full(len(tr.ids), tr.time_s.size, dtype=np.int64)
        np.minimum.at(first, tr.vi, tr.ti)
        first_seen = {tr.ids[j]: float(tr.time_s[first[j]]) for j in np.unique(tr.vi[tr.ti == k0])}
        self.fixed_ids = _select(list(first_seen), first_seen, n)
        self.slots: list[str | None] = list(self.fixed_ids)
        col = {v: j for j, v in enumerate(tr.ids)}
        self._x, self._y, s, ang = tr.dense([col[v] for v in self.fixed_ids])  # only the tracked vehicles
        a = np.deg2rad(ang)
        self._vx, self._vy = s * np.sin(a), s * np.cos(a)
        self.t0_s = float(tr.time_s[k0])
        self.state = self._at(self.t0_s)

    def _init_open(self, begin_s: float) -> None:
        tr = self.trace
        order = np.lexsort((tr.vi, tr.ti))  # records by time, then vehicle
        self._rec = {
            "vi": tr.vi[order],
            "x": tr.x_m[order],
            "y": tr.y_m[order],
            "vx": tr.speed_mps[order] * np.sin(np.deg2rad(tr.angle_deg[order])),
            "vy": tr.speed_mps[order] * np.cos(np.deg2rad(tr.angle_deg[order])),
        }
        self._starts = np.searchsorted(tr.ti[order], np.arange(tr.time_s.size + 1))
        after = np.flatnonzero(tr.time_s >= begin_s - 1e-9)
        if after.size == 0:
            raise ConfigError(
                f"vehicles.trace_file: {self.path} ends at t = {tr.time_s[-1]:g} s, before vehicles.sumo_begin_s = "
                f"{begin_s:g} s"
            )
        self.t0_s = float(tr.time_s[after[0]])
        first = np.full(len(tr.ids), np.inf)
        np.minimum.at(first, tr.vi, tr.time_s[tr.ti])
        ids, _ = self._open_values(self.t0_s)
        col = {v: j for j, v in enumerate(tr.ids)}
        first_seen = {v: float(first[col[v]]) for v in ids}
        self.slots = [None] * self.n
        self.state = self._open_at(self.t0_s, _first_seen_order(ids, first_seen), None)

    @property
    def ids(self) -> list[str | None]:
        """The vehicle in each slot (vehicle ``i`` of the simulator); None where a slot is empty."""
        return list(self.slots)

    def _open_values(self, t: float) -> tuple[list[str], dict[str, tuple[float, float, float, float]]]:
        """The vehicles in the trace at ``t`` and their interpolated (x, y, vx, vy)."""
        times = self.trace.time_s
        hi = self._sample_at(t)
        r, st = self._rec, self._starts
        cols = ("x", "y", "vx", "vy")
        if abs(times[hi] - t) <= 1e-9:
            sl = slice(st[hi], st[hi + 1])
            vi = r["vi"][sl]
            vals = np.stack([r[c][sl] for c in cols], axis=1)
        else:
            lo = hi - 1
            w = float((t - times[lo]) / (times[hi] - times[lo]))
            a, b = slice(st[lo], st[lo + 1]), slice(st[hi], st[hi + 1])
            vi, ia, ib = np.intersect1d(r["vi"][a], r["vi"][b], assume_unique=True, return_indices=True)
            va = np.stack([r[c][a][ia] for c in cols], axis=1)
            vb = np.stack([r[c][b][ib] for c in cols], axis=1)
            vals = np.asarray((1.0 - w) * va + w * vb, dtype=np.float64)
        names = [self.trace.ids[j] for j in vi.tolist()]
        return names, {v: (row[0], row[1], row[2], row[3]) for v, row in zip(names, vals.tolist(), strict=True)}

    def _open_at(self, t: float, order: Sequence[str] | None, prev: TrackedState | None) -> TrackedState:
        ids, values = self._open_values(t)
        if order is None:
            held = set(self.slots)
            order = [v for v in ids if v in held] + sorted(v for v in ids if v not in held)
        entered = assign_slots(self.slots, order, f"vehicles.trace_file {self.path}")
        return _open_state(self.slots, entered, values, t, prev)

    @property
    def time_s(self) -> float:
        return self.t0_s + self.k * self.step_s

    def _sample_at(self, t: float) -> int:
        """Index of the first trace sample at or after ``t`` (s); an error naming the file past its end."""
        times = self.trace.time_s
        if t > times[-1] + 1e-9:
            raise SumoError(
                f"vehicles.trace_file: {self.path} ends at t = {times[-1]:g} s; the run needs t = {t:g} s "
                f"({t - self.t0_s:g} s from its start at {self.t0_s:g} s); record a longer trace or run fewer subframes"
            )
        return int(np.searchsorted(times, t - 1e-9))

    def _at(self, t: float) -> TrackedState:
        times = self.trace.time_s
        hi = self._sample_at(t)
        if abs(times[hi] - t) <= 1e-9:
            lo, w = hi, 0.0
        else:
            lo, w = hi - 1, float((t - times[hi - 1]) / (times[hi] - times[hi - 1]))
        rows = [self._x, self._y, self._vx, self._vy]
        x, y, vx, vy = (r[lo] if w == 0.0 else (1.0 - w) * r[lo] + w * r[hi] for r in rows)
        gone = ~np.isfinite(x)
        if np.any(gone):
            j = int(np.flatnonzero(gone)[0])
            raise SumoError(
                f"vehicles.trace_file: vehicle {self.fixed_ids[j]!r} of {self.path} is not in the trace at t = {t:g} s "
                f"({int(gone.sum())} of the {self.n} tracked vehicles gone); this version keeps N fixed"
            )
        return TrackedState(np.stack([x, y], axis=1), np.stack([vx, vy], axis=1), np.zeros(self.n), t)

    def advance(self) -> TrackedState:
        """The state one period later."""
        self.k += 1
        if self.open_population:
            self.state = self._open_at(self.time_s, None, self.state)
        else:
            self.state = _moved(self.state, self._at(self.time_s))
        return self.state

    def close(self) -> None:
        """Nothing to release (for symmetry with :class:`SumoLockstep`)."""


MobilitySource = SumoLockstep | TraceReplay


def lockstep_of(simulator: Any) -> SumoLockstep:
    """The running :class:`SumoLockstep` of a simulator with ``vehicles.mobility=sumo`` (after reset)."""
    source = getattr(simulator, "_source", None)
    if not isinstance(source, SumoLockstep):
        raise ValueError("this simulator does not run SUMO in lockstep (vehicles.mobility must be sumo)")
    return source


def check_source(cfg: ScenarioConfig) -> None:
    """Fail early (at simulator construction) on a source that cannot work: SUMO not installed,
    a missing or broken ``.sumocfg`` or trace file, a road without a generated network."""
    mob = cfg.vehicles.mobility
    if mob == "sumo":
        sumo_home()
        import_libsumo()
        if cfg.vehicles.sumo_config is not None:
            check_sumocfg(cfg.vehicles.sumo_config)
        else:
            check_generated(cfg)
    elif mob == "trace":
        assert cfg.vehicles.trace_file is not None  # the config checks it
        p = Path(cfg.vehicles.trace_file).expanduser()
        if not p.is_file():
            raise ConfigError(f"vehicles.trace_file: {cfg.vehicles.trace_file!r} does not exist or is not a file")


def open_source(cfg: ScenarioConfig, rng: np.random.Generator) -> MobilitySource:
    """The mobility source of ``cfg`` (``vehicles.mobility`` = ``sumo`` or ``trace``), started.

    Args:
        cfg: the scenario.
        rng: the simulator's ``mobility`` stream (SUMO: seed and generated demand).
    """
    step_s = cfg.traffic.rri_ms / 1000.0
    is_open = cfg.vehicles.population == "open"
    if cfg.vehicles.mobility == "trace":
        assert cfg.vehicles.trace_file is not None
        return TraceReplay(cfg.vehicles.trace_file, cfg.n_slots, step_s, cfg.sumo_begin_s, is_open)
    return SumoLockstep(build_scenario(cfg, rng), cfg.n_slots, begin_s=cfg.sumo_begin_s, open_population=is_open)


# ------------------------------------------------------------------------------------------ export
def trace_table(trace: Trace) -> Any:
    """The trace as a long Arrow table (``time, id, x, y, angle, speed``; one row per record)."""
    import pyarrow as pa

    return pa.table(
        {
            "time": pa.array(trace.time_s[trace.ti]),
            "id": pa.array(np.asarray(trace.ids, dtype=object)[trace.vi].tolist(), type=pa.string()),
            "x": pa.array(trace.x_m),
            "y": pa.array(trace.y_m),
            "angle": pa.array(trace.angle_deg),
            "speed": pa.array(trace.speed_mps),
        }
    )


def export_seconds(cfg: ScenarioConfig, seconds: float | None) -> float:
    """The SUMO seconds :func:`export_scenario` records (``seconds``, or its default), checked: a finite
    number > 0 whose FCD trace, ``n_vehicles x (seconds / step + 1)`` rows, is at most :data:`MAX_FCD_ROWS`
    (a ValueError naming ``--seconds``, the estimate and the largest accepted value otherwise)."""
    if seconds is None:
        seconds = cfg.sumo_begin_s + (cfg.sim.warmup_subframes + cfg.sim.n_subframes) / 1000.0 + 60.0
    if isinstance(seconds, bool) or not isinstance(seconds, int | float) or not np.isfinite(seconds) or seconds <= 0:
        raise ValueError(f"--seconds must be a finite number > 0, got {seconds!r}")
    step_s = cfg.traffic.rri_ms / 1000.0
    n = cfg.n_vehicles
    rows = n * (int(np.ceil(seconds / step_s)) + 1)
    if rows > MAX_FCD_ROWS:
        most = (MAX_FCD_ROWS // n - 1) * step_s
        raise ValueError(
            f"--seconds {seconds:g} would write an FCD trace of about {rows:,} rows ({n} vehicles x one row per "
            f"{step_s:g} s step; about {rows * FCD_ROW_BYTES / 1e9:,.1f} GB of fcd.xml), above the limit of "
            f"{MAX_FCD_ROWS:,} rows; lower --seconds to at most {most:,.0f} for this scenario"
        )
    return float(seconds)


def export_scenario(
    cfg: ScenarioConfig, seed: int, out_dir: Path, seconds: float | None = None, parquet: bool = False
) -> dict[str, Any]:
    """Write the generated scenario of ``cfg`` for ``seed`` and SUMO's own FCD trace of it into ``out_dir``.

    The files are those :meth:`cv2x_marl.sim.Simulator.reset` runs for the same configuration and
    seed: ``net.net.xml``, ``routes.rou.xml``, ``scenario.sumocfg`` (usable as
    ``vehicles.sumo_config``) and ``fcd.xml`` from ``sumo --fcd-output`` (usable as
    ``vehicles.trace_file``; 6 decimals), plus ``fcd.parquet`` when ``parquet``.

    Args:
        cfg: the scenario (``vehicles.sumo_config`` must be null: the scenario is generated).
        seed: the run seed (as for ``simulate --seed``).
        out_dir: an existing folder.
        seconds: SUMO seconds to record; default: the run (``sim.warmup_subframes + sim.n_subframes``)
            plus 60 s for the vehicles to enter; at most what keeps the trace within
            :data:`MAX_FCD_ROWS` (:func:`export_seconds`).
        parquet: also write the trace as parquet.

    Returns:
        A summary: files, SUMO seed and version, seconds, vehicles and timesteps of the trace.
    """
    from cv2x_marl.io import atomic_write
    from cv2x_marl.rng import RngStreams

    if cfg.vehicles.sumo_config is not None:
        raise ConfigError(
            "sumo export generates a scenario from the road section; vehicles.sumo_config is set "
            f"({cfg.vehicles.sumo_config!r}): run that scenario with SUMO directly"
        )
    seconds = export_seconds(cfg, seconds)
    scenario = build_scenario(cfg, RngStreams.from_seed(seed).mobility)
    atomic_write(out_dir / NET_FILE, partial(shutil.copyfile, build_network(cfg)))
    atomic_write(out_dir / ROUTE_FILE, partial(shutil.copyfile, scenario.sumocfg.parent / ROUTE_FILE))
    text = sumocfg_xml(NET_FILE, ROUTE_FILE, scenario.step_s, scenario.seed)
    atomic_write(out_dir / CFG_FILE, lambda p: p.write_text(text))
    fcd = "fcd.xml"
    atomic_write(
        out_dir / fcd,
        lambda p: run_tool(
            "sumo",
            ["-c", CFG_FILE, "--fcd-output", str(p), "--precision", "6", "--end", repr(float(seconds))],
            cwd=out_dir,
        ),
    )
    trace = read_trace(out_dir / fcd)
    files = [NET_FILE, ROUTE_FILE, CFG_FILE, fcd]
    if parquet:
        import pyarrow.parquet as pq

        table = trace_table(trace)
        atomic_write(out_dir / "fcd.parquet", lambda p: pq.write_table(table, p))
        files.append("fcd.parquet")
    return {
        "files": files,
        "seed": seed,
        "sumo_seed": scenario.seed,
        "sumo_version": sumo_version(),
        "step_s": scenario.step_s,
        "seconds": float(seconds),
        "n_vehicles": len(trace.ids),
        "n_timesteps": int(trace.time_s.size),
    }
