"""The open grid (issue 14): SUMO's randomTrips.py demand on the paper's grid (``sumo-grid-trips``).

Checked against SUMO's own files and counts: every route is a connected path of the generated
network, the trips are the ones randomTrips.py wrote for the seed, the demand calibrated by
Little's law and one SUMO count keeps about N vehicles in the region, vehicles enter and leave,
the same seed builds the same scenario, and the desired-speed classes are the documented ones.
"""

from __future__ import annotations

import itertools
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("libsumo")
pytest.importorskip("sumo")

from cv2x_marl.config import apply_overrides, preset
from cv2x_marl.experiments.sumo_export import export_scenario
from cv2x_marl.sim import Simulator, sumo

SEED = 5
SHORT = ["sim.warmup_subframes=0", "metrics.record_links=true"]


def _cfg(*over: str):
    return apply_overrides(preset("sumo-grid-trips"), [*SHORT, *over])


def _routes(folder: Path) -> ET.Element:
    return ET.parse(folder / "routes.rou.xml").getroot()


def test_routes_are_connected_paths_of_the_network_and_classes_as_documented(tmp_path: Path) -> None:
    cfg = _cfg()
    export_scenario(cfg, SEED, tmp_path, seconds=cfg.sumo_begin_s + 1.0)
    net = ET.parse(tmp_path / "net.net.xml").getroot()
    # SUMO's connections (from edge -> to edge), internal edges left out
    joins = {(c.get("from"), c.get("to")) for c in net.iter("connection") if not c.get("from", "").startswith(":")}
    length = {
        e.get("id"): float(e.find("lane").get("length"))  # type: ignore[union-attr]
        for e in net.iter("edge")
        if e.get("function") != "internal"
    }
    root = _routes(tmp_path)
    vehicles = list(root.iter("vehicle"))
    assert len(vehicles) > 100
    departs = np.array([float(v.get("depart", "nan")) for v in vehicles])
    assert np.all(np.diff(departs) >= 0) and departs[0] >= 0  # SUMO's order: by departure
    for v in vehicles:
        edges = v.find("route").get("edges", "").split()  # type: ignore[union-attr]
        assert edges and all(e in length for e in edges)
        assert all((a, b) in joins for a, b in itertools.pairwise(edges)), edges
    # the vTypes: speedFactor = class midpoint / limit, K equal bins of [speed_min, speed_max]
    v = cfg.vehicles
    edges_k = np.linspace(v.speed_min_mps, v.speed_max_mps, sumo.HIGHWAY_SPEED_CLASSES + 1)
    expected = 0.5 * (edges_k[:-1] + edges_k[1:]) / v.speed_max_mps
    factors = {t.get("id"): float(t.get("speedFactor", "nan")) for t in root.iter("vType")}
    np.testing.assert_allclose([factors[f"v{c}"] for c in range(sumo.HIGHWAY_SPEED_CLASSES)], expected, atol=1e-6)
    kinds = np.array([int(str(v.get("type"))[1:]) for v in vehicles])
    counts = np.bincount(kinds, minlength=sumo.HIGHWAY_SPEED_CLASSES)
    assert counts.min() > 0.5 * counts.mean()  # uniform draws over the classes


def test_count_in_region_is_calibrated_and_vehicles_enter_and_leave() -> None:
    cfg = _cfg()
    sim = Simulator(cfg)
    sim.reset(SEED)
    counts = []
    for _ in range(400):  # 40 s: trips last about a minute
        assert sim.present is not None
        counts.append(int(sim.present.sum()))
        sim.run(sim.rri, record=False)
    n = cfg.n_vehicles
    # Little's law plus one correction by SUMO's count: the mean count near N (21), not 2N or N/2
    assert 0.7 * n <= np.mean(counts) <= 1.4 * n, np.mean(counts)
    # trips last about a minute: some 0.3 vehicles a second enter and leave
    assert sim.n_entries >= 8 and sim.n_departures >= 5, (sim.n_entries, sim.n_departures)
    sim.close()


def test_same_seed_same_scenario_other_seed_other(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    cfg = _cfg()
    texts = []
    for k, seed in enumerate((SEED, SEED, SEED + 1)):
        monkeypatch.setenv(sumo.CACHE_ENV, str(tmp_path / f"cache{k}"))  # built afresh each time
        out = tmp_path / f"out{k}"
        export_scenario(cfg, seed, out, seconds=cfg.sumo_begin_s + 1.0)
        texts.append((out / "routes.rou.xml").read_text())
    assert texts[0] == texts[1]
    assert texts[0] != texts[2]


def test_simulate_writes_who_held_each_slot(tmp_path: Path) -> None:
    """``slots.parquet`` attributes every link of ``links.parquet`` to the vehicle in its slots at that
    subframe; the summary's population figures are those of the table."""
    import pyarrow.parquet as pq

    from cv2x_marl.experiments.simulate import simulate

    n_sub = 30_000
    cfg = _cfg(f"sim.n_subframes={n_sub}")
    summary = simulate(cfg, SEED, n_sub, tmp_path / "run", progress=False)
    occ = pq.read_table(tmp_path / "run" / "slots.parquet").to_pandas()
    links = pq.read_table(tmp_path / "run" / "links.parquet", columns=["tx", "rx", "subframe"]).to_pandas()
    assert summary["n_vehicles"] == 21 and summary["n_slots"] == cfg.n_slots
    pop = summary["population"]
    assert pop["n_vehicles_seen"] == occ["vehicle_id"].nunique() == len(occ)  # one interval per vehicle here
    assert pop["n_entered"] == int((occ["first_subframe"] > 0).sum()) > 0
    assert pop["n_left"] == int((occ["end_subframe"] < n_sub).sum()) > 0
    assert pop["present_min"] <= pop["present_mean"] <= pop["present_max"]
    # intervals of one slot never overlap; they are whole periods
    for _, g in occ.sort_values("first_subframe").groupby("slot"):
        assert np.all(g["first_subframe"].to_numpy()[1:] >= g["end_subframe"].to_numpy()[:-1])
    assert np.all(occ["first_subframe"] % cfg.traffic.rri_ms == 0)
    # every link's transmitter and receiver held their slots at the link's subframe
    for col in ("tx", "rx"):
        m = links.merge(occ, left_on=col, right_on="slot")
        held = (m["subframe"] >= m["first_subframe"]) & (m["subframe"] < m["end_subframe"])
        assert held.groupby([m[col], m["subframe"], m["tx" if col == "rx" else "rx"]]).any().all()


def test_relative_cache_path_and_dataset_refusal(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from cv2x_marl.experiments.dataset import DatasetError, build_dataset

    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv(sumo.CACHE_ENV, "relcache")  # SUMO's tools run in temporary folders
    cfg = _cfg()
    export_scenario(cfg, SEED, tmp_path / "out", seconds=cfg.sumo_begin_s + 1.0)
    assert sumo.cache_dir() == (tmp_path / "relcache").resolve()
    with pytest.raises(DatasetError, match=r"vehicles\.population=open a slot is reused"):
        build_dataset(cfg, 1, 0, tmp_path / "ds", aggregate_window_ms=1000, progress=False)
