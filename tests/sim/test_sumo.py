"""SUMO mobility (issue 14): lockstep positions equal SUMO's own FCD output, same seed -> same run,
trace replay equals live stepping, config errors name the key, generated networks are cached."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("libsumo")
pytest.importorskip("sumo")

from cv2x_marl.cli import main
from cv2x_marl.config import ConfigError, apply_overrides, preset
from cv2x_marl.extras import MissingExtraError
from cv2x_marl.sim import Simulator, sumo
from cv2x_marl.sim.mobility import TrackedState

SEED = 7
PERIODS = 40


def _cfg(*over: str):
    return apply_overrides(preset("sumo-grid"), ["sim.warmup_subframes=0", "sim.n_subframes=4000", *over])


def _trajectory(sim: Simulator, seed: int, periods: int = PERIODS) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Positions and velocities [periods + 1, N, 2] at the start of every period."""
    sim.reset(seed, warmup_subframes=0)
    pos, vel = [], []
    for _ in range(periods + 1):
        assert isinstance(sim.state, TrackedState)
        pos.append(sim.state.pos_m.copy())
        vel.append(sim.state.vel_mps.copy())
        sim.run(sim.rri, record=False)
    ids = sim.vehicle_ids
    assert ids is not None
    return np.array(pos), np.array(vel), ids


@pytest.fixture(scope="module")
def live() -> dict[str, object]:
    """One lockstep run of the generated sumo-grid scenario (shared by the tests below)."""
    sim = Simulator(_cfg())
    pos, vel, ids = _trajectory(sim, SEED)
    src = sim._source
    assert isinstance(src, sumo.SumoLockstep)
    scenario, t0 = src.scenario, src.t0_s
    sim.close()
    return {"pos": pos, "vel": vel, "ids": ids, "scenario": scenario, "t0": t0}


def test_generated_grid_matches_our_geometry(live: dict[str, object]) -> None:
    scenario = live["scenario"]
    assert isinstance(scenario, sumo.Scenario) and scenario.generated
    net = sumo.build_network(_cfg()).read_text()
    assert 'convBoundary="0.00,0.00,450.00,450.00"' in net  # the 450 m region
    assert 'id="A0" type="priority" x="56.25" y="56.25"' in net  # crossings at (i + 1/2) * 112.5 m
    pos = live["pos"]
    assert isinstance(pos, np.ndarray) and pos.shape == (PERIODS + 1, 21, 2)
    assert np.all((pos >= -5.0) & (pos <= 455.0))  # a U-turn at a dead end swings out by a few metres
    # every vehicle on a lane: 1.75 m off a road centre line across its direction of travel (or in a crossing)
    centre = (np.arange(4) + 0.5) * 112.5
    off = np.abs(pos[..., :, None] - centre).min(axis=-1)  # distance of x (and y) to the nearest centre line
    assert np.all(np.min(off, axis=-1) <= 3.5 + 1e-6)


def test_positions_equal_sumo_fcd_output(live: dict[str, object], tmp_path: Path) -> None:
    """The lockstep reads back what SUMO itself writes as FCD for the same scenario and seed."""
    scenario = live["scenario"]
    assert isinstance(scenario, sumo.Scenario)
    t0 = float(live["t0"])  # type: ignore[arg-type]
    fcd = tmp_path / "fcd.xml"
    end = t0 + (PERIODS + 1) * scenario.step_s
    args = ["-c", str(scenario.sumocfg), "--seed", str(scenario.seed), "--step-length", repr(scenario.step_s)]
    sumo.run_tool("sumo", [*args, "--fcd-output", str(fcd), "--precision", "6", "--end", repr(end)])
    tr = sumo.read_trace(fcd)
    x, y, speed, angle = tr.dense([tr.ids.index(v) for v in live["ids"]])  # type: ignore[attr-defined]
    rows = [int(np.argmin(np.abs(tr.time_s - (t0 + k * scenario.step_s)))) for k in range(PERIODS + 1)]
    assert np.allclose(tr.time_s[rows], t0 + np.arange(PERIODS + 1) * scenario.step_s, atol=1e-6)
    fcd_pos = np.stack([x[rows], y[rows]], axis=-1)
    np.testing.assert_allclose(live["pos"], fcd_pos, rtol=0, atol=1e-5)  # FCD has 6 decimals
    a = np.deg2rad(angle[rows])
    s = speed[rows]
    np.testing.assert_allclose(live["vel"], np.stack([s * np.sin(a), s * np.cos(a)], axis=-1), rtol=0, atol=1e-4)
    moved = np.hypot(*(fcd_pos[-1] - fcd_pos[0]).T)
    assert np.median(moved) > 5.0  # the vehicles do drive


def test_same_seed_same_run_other_seed_other_run(live: dict[str, object]) -> None:
    sim = Simulator(_cfg())
    pos, _, ids = _trajectory(sim, SEED, periods=10)
    assert ids == live["ids"]
    np.testing.assert_array_equal(pos, live["pos"][:11])  # type: ignore[index]
    other, _, _ = _trajectory(sim, SEED + 1, periods=10)
    assert not np.allclose(other, pos)
    sim.close()
    # the whole simulator run (SPS, channel) repeats too
    a, b = Simulator(_cfg()), Simulator(_cfg())
    ra = (a.reset(3), a.run(2000).metrics.summary())[1]
    rb = (b.reset(3), b.run(2000).metrics.summary())[1]  # b's reset takes libsumo over from a
    assert ra == rb
    with pytest.raises(RuntimeError, match="one simulation per process"):
        a.run(200)
    b.close()


def test_trace_replay_equals_live_stepping(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "export"
    argv = ["sumo", "export", "--preset", "sumo-grid", "--set", "sim.warmup_subframes=0", "--set"]
    argv += ["sim.n_subframes=4000", "--seed", str(SEED), "--seconds", "30", "--parquet", "--out", str(out)]
    assert main(argv) == 0
    assert "wrote" in capsys.readouterr().out
    for name in ("net.net.xml", "routes.rou.xml", "scenario.sumocfg", "fcd.xml", "fcd.parquet", "run.json"):
        assert (out / name).is_file(), name
    runs = {}
    for label, over in {
        "live": [],
        "sumocfg": [f"vehicles.sumo_config={out / 'scenario.sumocfg'}"],
        "xml": ["vehicles.mobility=trace", f"vehicles.trace_file={out / 'fcd.xml'}"],
        "parquet": ["vehicles.mobility=trace", f"vehicles.trace_file={out / 'fcd.parquet'}"],
    }.items():
        sim = Simulator(_cfg(*over))
        sim.reset(SEED, warmup_subframes=0)
        summary = sim.run(3000).metrics.summary()
        assert isinstance(sim.state, TrackedState)
        runs[label] = (sim.state.pos_m.copy(), sim.state.odometer_m.copy(), summary)
        sim.close()
    for label in ("sumocfg", "xml", "parquet"):
        np.testing.assert_allclose(runs[label][0], runs["live"][0], rtol=0, atol=1e-5)
        np.testing.assert_allclose(runs[label][1], runs["live"][1], rtol=0, atol=1e-3)
        assert runs[label][2]["prr_mean"] == pytest.approx(runs["live"][2]["prr_mean"], abs=1e-12), label


def test_trace_interpolates_to_our_period(tmp_path: Path) -> None:
    """A 1-s FCD trace replayed at 100 ms: linear in between, exact on the samples."""
    fcd = tmp_path / "coarse.xml"
    fcd.write_text(
        "<fcd-export>\n"
        '<timestep time="0.00"><vehicle id="a" x="0" y="10" angle="90" speed="10"/>'
        '<vehicle id="b" x="100" y="20" angle="0" speed="0"/></timestep>\n'
        '<timestep time="1.00"><vehicle id="a" x="10" y="10" angle="90" speed="10"/>'
        '<vehicle id="b" x="100" y="25" angle="0" speed="5"/></timestep>\n'
        '<timestep time="2.00"><vehicle id="a" x="20" y="10" angle="90" speed="10"/></timestep>\n'
        "</fcd-export>\n"
    )
    tr = sumo.TraceReplay(fcd, 2, 0.1)
    assert tr.ids == ["a", "b"]
    xs = [tr.state.pos_m.copy()]
    for _ in range(10):
        xs.append(tr.advance().pos_m.copy())
    x = np.array(xs)
    np.testing.assert_allclose(x[:, 0, 0], np.arange(11.0), atol=1e-9)
    np.testing.assert_allclose(x[:, 1, 1], 20.0 + 0.5 * np.arange(11.0), atol=1e-9)
    np.testing.assert_allclose(tr.state.vel_mps, [[10.0, 0.0], [0.0, 5.0]], atol=1e-9)
    np.testing.assert_allclose(tr.state.odometer_m, [10.0, 5.0], atol=1e-9)
    with pytest.raises(sumo.SumoError, match=r"vehicle 'b' .* not in the trace"):
        tr.advance()
    with pytest.raises(ConfigError, match="never has 3 vehicles"):
        sumo.TraceReplay(fcd, 3, 0.1)


def test_config_errors_name_the_key(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"vehicles\.mobility: 'ns3' is not allowed; allowed values: model"):
        apply_overrides(preset("paper"), ["vehicles.mobility=ns3"])
    with pytest.raises(ConfigError, match=r"vehicles\.mobility=trace needs vehicles\.trace_file"):
        apply_overrides(preset("paper"), ["vehicles.mobility=trace"])
    with pytest.raises(ConfigError, match=r"vehicles\.sumo_config: expected path to a \.sumocfg file"):
        apply_overrides(preset("paper"), ["vehicles.sumo_config=3"])
    with pytest.raises(ConfigError, match=r"vehicles\.sumo_config: '/nonexistent/x\.sumocfg' does not exist"):
        Simulator(_cfg("vehicles.sumo_config=/nonexistent/x.sumocfg"))
    broken = tmp_path / "broken.sumocfg"
    broken.write_text("<configuration><input><net-file value='net.net.xml'/>")
    with pytest.raises(
        ConfigError, match=r"vehicles\.sumo_config: .*broken\.sumocfg is not a valid SUMO configuration"
    ):
        Simulator(_cfg(f"vehicles.sumo_config={broken}"))
    no_net = tmp_path / "no_net.sumocfg"
    no_net.write_text("<configuration><input><net-file value='missing.net.xml'/></input></configuration>")
    with pytest.raises(ConfigError, match=r"vehicles\.sumo_config: .*its net-file 'missing\.net\.xml' does not exist"):
        Simulator(_cfg(f"vehicles.sumo_config={no_net}"))
    shutil.copyfile(sumo.build_network(_cfg()), tmp_path / "net.net.xml")
    (tmp_path / "bad.rou.xml").write_text('<routes><vehicle id="a" depart="0"><route edges="NOPE"/></vehicle></routes>')
    bad_routes = tmp_path / "bad_routes.sumocfg"
    bad_routes.write_text(sumo.sumocfg_xml("net.net.xml", "bad.rou.xml", 0.1, 1))
    sim = Simulator(_cfg(f"vehicles.sumo_config={bad_routes}"))
    with pytest.raises(sumo.SumoError, match=r"vehicles\.sumo_config: SUMO cannot load .*bad_routes\.sumocfg: .*NOPE"):
        sim.reset(0)
    with pytest.raises(ConfigError, match=r"vehicles\.trace_file: '/nonexistent/fcd\.xml' does not exist"):
        Simulator(_cfg("vehicles.mobility=trace", "vehicles.trace_file=/nonexistent/fcd.xml"))
    bad = tmp_path / "bad.xml"
    bad.write_text("<fcd-export><timestep time='0'><vehicle id='a' x='1'")
    with pytest.raises(ConfigError, match=r"vehicles\.trace_file: .*bad\.xml is not a readable SUMO FCD XML trace"):
        Simulator(_cfg("vehicles.mobility=trace", f"vehicles.trace_file={bad}")).reset(0)
    with pytest.raises(ConfigError, match=r"road\.kind=highway.*set vehicles\.population=open"):
        Simulator(apply_overrides(preset("highway"), ["vehicles.mobility=sumo"]))
    with pytest.raises(ConfigError, match=r"vehicles\.population=open needs vehicles\.mobility=sumo or trace"):
        apply_overrides(preset("paper"), ["vehicles.population=open"])
    with pytest.raises(ConfigError, match=r"open population needs vehicles\.speed_min_mps > 0"):
        Simulator(_cfg("vehicles.population=open", "vehicles.speed_min_mps=0"))


def test_vehicle_count_outside_the_scenario(tmp_path: Path) -> None:
    """A user scenario whose vehicles leave, or that never holds N vehicles: errors naming what happened."""
    shutil.copyfile(sumo.build_network(_cfg()), tmp_path / "net.net.xml")
    (tmp_path / "short.rou.xml").write_text(
        "<routes>\n"
        + "".join(
            f'<vehicle id="v{k}" depart="{k}" departPos="0"><route edges="A0B0 B0C0"/></vehicle>\n' for k in range(3)
        )
        + "</routes>\n"
    )
    cfgfile = tmp_path / "short.sumocfg"
    cfgfile.write_text(sumo.sumocfg_xml("net.net.xml", "short.rou.xml", 0.1, 1))
    sim = Simulator(_cfg(f"vehicles.sumo_config={cfgfile}", "vehicles.n_vehicles=2"))
    sim.reset(0, warmup_subframes=0)
    assert sim.vehicle_ids == ["v0", "v1"]
    with pytest.raises(sumo.SumoError, match=r"vehicle 'v0' of .*short\.sumocfg left the network"):
        sim.run(100_000, record=False)
    sim = Simulator(_cfg(f"vehicles.sumo_config={cfgfile}", "vehicles.n_vehicles=5"))
    with pytest.raises(sumo.SumoError, match=r"never has 5 vehicles in the network at once"):
        sim.reset(0, warmup_subframes=0)


def test_generated_network_is_cached(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv(sumo.CACHE_ENV, str(tmp_path / "cache"))
    calls: list[str] = []
    real = sumo.run_tool

    def counting(name: str, *args: object, **kwargs: object) -> None:
        calls.append(name)
        real(name, *args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(sumo.network, "run_tool", counting)  # where build_network looks it up
    cfg = _cfg()
    first = sumo.build_network(cfg)
    assert calls == ["netgenerate"] and first.is_file()
    second = sumo.build_network(cfg)
    assert second == first and calls == ["netgenerate"]  # reused: netgenerate not run again
    s1 = sumo.build_scenario(cfg, np.random.default_rng(1))
    s2 = sumo.build_scenario(cfg, np.random.default_rng(1))
    assert s1 == s2 and calls == ["netgenerate"]
    other = sumo.build_network(apply_overrides(cfg, ["road.lane_width_m=3.0"]))
    assert other != first and calls == ["netgenerate", "netgenerate"]
    assert not list((tmp_path / "cache").glob(".*.tmp"))  # no temporary folder left behind


def test_missing_sumo_names_the_extra(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "sumo", None)  # import sumo raises ImportError
    with pytest.raises(MissingExtraError, match=r"cv2x_marl\[sumo\]"):
        Simulator(_cfg())


def test_model_mobility_does_not_import_sumo() -> None:
    code = (
        "import sys\nfrom cv2x_marl.config import preset\nfrom cv2x_marl.sim import Simulator\n"
        "s = Simulator(preset('paper')); s.reset(0, warmup_subframes=0); s.run(300)\n"
        "assert not {'cv2x_marl.sim.sumo', 'libsumo', 'sumo', 'traci'} & set(sys.modules), sys.modules.keys()\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def _children(pid: int) -> list[int]:
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid and fields[0] != "Z":  # fields: state, ppid, ...
            out.append(int(stat.parent.name))
    return out


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux-only")
def test_sumo_subprocess_dies_with_us(tmp_path: Path) -> None:
    """A SUMO program we run (here a long `sumo` export run) is killed when our process is killed."""
    import os
    import signal
    import time

    cfg = sumo.build_scenario(_cfg(), np.random.default_rng(0)).sumocfg
    code = f"from cv2x_marl.sim import sumo\nsumo.run_tool('sumo', ['-c', {str(cfg)!r}, '--end', '1e7'])\n"
    parent = subprocess.Popen([sys.executable, "-c", code])
    try:
        deadline = time.monotonic() + 30
        while not (kids := _children(parent.pid)) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert kids, "sumo did not start"
        os.kill(parent.pid, signal.SIGKILL)
        parent.wait()
        deadline = time.monotonic() + 10
        while any(Path(f"/proc/{k}").exists() and _state(k) != "Z" for k in kids) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not [k for k in kids if Path(f"/proc/{k}").exists() and _state(k) != "Z"], "sumo outlived its parent"
    finally:
        if parent.poll() is None:
            parent.kill()


def _state(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return "Z"
