"""The SUMO network of a generated scenario: ``netgenerate``'s grid, or the highway as plain XML run
through ``netconvert``, built from the ``road`` section and cached (issue 14); and the parts of a
network the random walk reads back.

See :mod:`cv2x_marl.sim.sumo` for the rules; every file is cached by :func:`~cv2x_marl.sim.sumo.tools.cached`.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from cv2x_marl.config import ConfigError, ScenarioConfig
from cv2x_marl.sim.sumo.tools import SumoError, cached, run_tool, sumo_version

FloatArray = NDArray[np.float64]

#: file names of a generated (or exported) scenario
NET_FILE, ROUTE_FILE, CFG_FILE = "net.net.xml", "routes.rou.xml", "scenario.sumocfg"
#: format version of the generated files (part of every cache key)
GENERATOR_VERSION = 4


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
        hkey = {"what": "net", "generator": GENERATOR_VERSION, "sumo": sumo_version(), "nodes": nodes, "edges": edges}

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
    key = {"what": "net", "generator": GENERATOR_VERSION, "sumo": sumo_version(), "netgenerate": args}

    def build(folder: Path) -> None:
        run_tool("netgenerate", [*args, f"--output-file={NET_FILE}", "--no-warnings=true"], cwd=folder)

    return cached("net", key, build) / NET_FILE


@dataclass(frozen=True)
class SumoNet:
    """The parts of a SUMO network the random walk needs."""

    edges: list[str]
    length_m: FloatArray
    speed_mps: FloatArray
    # per edge: {direction code: [successor edge index]}
    successors: list[dict[str, list[int]]]


def read_net(path: Path) -> SumoNet:
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
    return SumoNet(edges, np.array(length), np.array(speed), succ)
