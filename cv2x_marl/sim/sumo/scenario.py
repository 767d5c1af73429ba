"""Generated SUMO scenarios: the demand on the network of :mod:`~cv2x_marl.sim.sumo.network`
(random walks for a fixed population, highway flows or ``randomTrips.py`` trips for an open one) of the
``road`` and ``vehicles`` sections, the ``.sumocfg`` that runs them, and the check of a user's
``.sumocfg`` (issue 14).

See :mod:`cv2x_marl.sim.sumo` for the rules; every file is cached by :func:`~cv2x_marl.sim.sumo.tools.cached`.
"""

from __future__ import annotations

import hashlib
import tempfile
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from cv2x_marl.config import ConfigError, ScenarioConfig
from cv2x_marl.sim.sumo.network import (
    CFG_FILE,
    GENERATOR_VERSION,
    NET_FILE,
    ROUTE_FILE,
    SumoNet,
    build_network,
    read_net,
)
from cv2x_marl.sim.sumo.tools import SumoError, cached, run_python_tool, run_tool, sumo_version

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: seconds of driving (at the highest desired speed) each generated route covers
ROUTE_HORIZON_S = 3600.0


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


def random_walk_routes(
    net: SumoNet, cfg: ScenarioConfig, n: int, rng: np.random.Generator
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


def routes_xml(net: SumoNet, routes: IntArray, speed_factor: FloatArray) -> str:
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


def _route_lengths_m(routes: Path, net: SumoNet) -> FloatArray:
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
        "generator": GENERATOR_VERSION,
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
        "generator": GENERATOR_VERSION,
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
