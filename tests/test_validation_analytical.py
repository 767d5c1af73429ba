"""Reference values of the analytical Mode 4 model (cv2x_marl.validation.mode4_analytical).

No MATLAB/Octave is available here, so the authors' code (github.com/msepulcre/C-V2X) cannot be
run; the checks are: closed forms against hand-derived values (exact to rounding), limiting
cases, the composition of eq. 6, and the vectorised implementation against a slow, loop-by-loop
evaluation of the same equations in the order of the paper (one interferer and one distance at a
time, the SINR density built explicitly by cross-correlation, eqs. 13-33).
"""

from __future__ import annotations

import itertools
import json
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.signal import correlate
from scipy.stats import norm

from cv2x_marl.validation import mode4_analytical as m4
from cv2x_marl.validation.mode4_analytical import (
    BLER_190B_R05,
    BLER_190B_R07,
    alpha_weight,
    analytical_pdr,
    excluded_resources,
    noise_power_dbm,
    path_loss_db,
)

PAPER = {"packets_per_s": 10.0, "tx_power_dbm": 20.0, "n_subchannels": 4, "packet_bytes": 190}


@pytest.fixture(scope="module")
def run_100() -> dict[str, np.ndarray]:
    return analytical_pdr(np.array([0.0, 50.0, 150.0, 300.0, 400.0]), 100.0, **PAPER)


# ----------------------------------------------------------------------------- closed forms
def test_path_loss_hand_values() -> None:
    f = 5.91
    # below the breakpoint (4 * 1.5 * 1.5 * 5.91e9 / 3e8 = 177.3 m) and above free space
    pl, std = path_loss_db(150.0)
    assert pl == pytest.approx(22.7 * math.log10(150.0) + 27.0 + 20.0 * math.log10(f), abs=1e-12)
    assert std == 3.0
    # beyond the breakpoint
    pl = path_loss_db(300.0)[0]
    assert pl == pytest.approx(
        40.0 * math.log10(300.0) + 7.56 - 34.6 * math.log10(1.5) + 2.7 * math.log10(f), abs=1e-12
    )
    # the free-space floor binds below ~102 m: 20 log10 d + 46.4 + 20 log10(5.91 / 5)
    pl = path_loss_db(50.0)[0]
    assert pl == pytest.approx(20.0 * math.log10(50.0) + 46.4 + 20.0 * math.log10(f / 5.0), abs=1e-12)
    # clipping at 3 m, sign ignored
    assert path_loss_db(-1.0)[0] == path_loss_db(3.0)[0]


def test_noise_over_data_rbs() -> None:
    assert noise_power_dbm(10) == pytest.approx(-95.0 - 10.0 * math.log10(5.0), abs=1e-12)
    assert noise_power_dbm(12) == pytest.approx(-95.0 - 10.0 * math.log10(50.0 / 12.0), abs=1e-12)
    assert noise_power_dbm(50) == -95.0


def test_half_duplex_is_lambda_over_1000(run_100: dict[str, np.ndarray]) -> None:
    assert np.all(run_100["p_hd"] == 10.0 / 1000.0)
    assert np.all(run_100["delta_hd"] == 0.01)
    out = analytical_pdr([100.0], 100.0, 20.0, 20.0, 4, 190)
    assert out["delta_hd"][0] == 20.0 / 1000.0
    assert float(out["n_resources"]) == 4 * 1000.0 / 20.0  # eq. 28


def test_sensing_loss_closed_form(run_100: dict[str, np.ndarray]) -> None:
    for k, d in enumerate(run_100["distance_m"]):
        pl = path_loss_db(d)[0]
        arg = (20.0 - pl + 90.5) / (3.0 * math.sqrt(2.0))
        want = 0.5 * math.erfc(arg)  # eq. 10; erfc keeps the far tail that 1 - erf rounds to 0
        assert run_100["p_sen"][k] == pytest.approx(want, rel=1e-12, abs=1e-300)
        assert run_100["p_sen"][k] == pytest.approx(0.5 * (1.0 - math.erf(arg)), abs=1e-16)
        assert run_100["delta_sen"][k] == pytest.approx(want * (1.0 - 0.01), rel=1e-12, abs=1e-300)
    # at 400 m: PL = 40 log10 400 + 7.56 - 34.6 log10 1.5 + 2.7 log10 5.91 = 107.633 dB, so the mean received
    # power is 20 - 107.633 = -87.633 dBm, 2.867 dB above P_SEN: delta_SEN = Q(2.867 / 3)
    assert path_loss_db(400.0)[0] == pytest.approx(107.633, abs=1e-3)
    assert run_100["p_sen"][-1] == pytest.approx(norm.sf(2.867 / 3.0), abs=1e-4)


def test_eq29_excluded_resources_by_hand() -> None:
    # S_PSR = 10 sensed vehicles, N = 400: 5 + sum_{k=1..5} (1 - k / 395)
    assert excluded_resources(10.0, 400.0) == pytest.approx(10.0 - 15.0 / 395.0, abs=1e-12)
    # S_PSR / 2 = 2.5: k = 1, 2
    assert excluded_resources(5.0, 100.0) == pytest.approx(2.5 + 2.0 - 3.0 / 97.5, abs=1e-12)
    assert excluded_resources(0.0, 100.0) == 0.0
    with pytest.raises(ValueError, match="S_PSR / 2 < N"):
        excluded_resources(800.0, 400.0)


def test_eq22_alpha() -> None:
    assert alpha_weight(0.0) == 0.0
    assert alpha_weight(0.1999) == 0.0
    assert alpha_weight(0.2) == pytest.approx(0.0, abs=1e-15)
    assert alpha_weight(0.45) == pytest.approx(0.5, abs=1e-15)
    assert alpha_weight(0.7) == pytest.approx(1.0, abs=1e-15)
    assert alpha_weight(0.9) == 1.0


def test_bler_curves_are_r1_160284_tables() -> None:
    # the same points as the simulator's PER tables (both from R1-160284); the reference extends
    # the last value 1e-3 to 20 dB and 1e-4 above
    assert BLER_190B_R07(np.array([-5.0, 0.0, 1.0, 8.0, 16.0, 19.0, 25.0])).tolist() == pytest.approx(
        [1.0, 1.0, 0.95, 0.13, 1e-3, 1e-3, 1e-4]
    )
    assert BLER_190B_R05(np.array([-3.0, 3.0, 10.0, 30.0])).tolist() == pytest.approx([1.0, 0.5, 0.002, 1e-4])
    from cv2x_marl.sim.link import load_per_curve

    for curve, name in ((BLER_190B_R07, "r1-160284-190b-r0.7"), (BLER_190B_R05, "r1-160284-190b-r0.5")):
        ours = load_per_curve(name, "linear")
        np.testing.assert_array_equal(curve(ours.sinr_db), ours.per)


# ----------------------------------------------------------------------------- composition, limits
def test_eq6_composition(run_100: dict[str, np.ndarray]) -> None:
    o = run_100
    total = o["pdr"] + o["delta_hd"] + o["delta_sen"] + o["delta_pro"] + o["delta_col"]
    np.testing.assert_allclose(total, 1.0, atol=1e-14)
    product = (1 - o["p_hd"]) * (1 - o["p_sen"]) * (1 - o["p_pro"]) * (1 - o["p_col"])
    np.testing.assert_allclose(o["pdr"], product, atol=1e-14)
    a = float(o["alpha"])
    np.testing.assert_allclose(o["p_col"], a * o["p_col_step2"] + (1 - a) * o["p_col_step3"], atol=1e-15)
    for k in ("delta_hd", "delta_sen", "delta_pro", "delta_col", "pdr"):
        assert np.all(o[k] >= -1e-15) and np.all(o[k] <= 1.0)


def test_short_distance_bounded_by_half_duplex(run_100: dict[str, np.ndarray]) -> None:
    assert run_100["pdr"][0] <= 1.0 - 0.01
    assert run_100["pdr"][0] > 0.98  # nothing else matters at 0 m at this density
    assert np.all(np.diff(run_100["pdr"]) < 0.0)  # PDR falls with distance


def test_collisions_vanish_as_density_falls() -> None:
    d = np.array([100.0, 300.0])
    col = [analytical_pdr(d, rho, **PAPER)["delta_col"] for rho in (300.0, 100.0, 10.0, 1.0)]
    for hi, lo in itertools.pairwise(col):
        assert np.all(lo < hi)
    assert np.all(col[-1] < 1e-3)
    # below 0.5 veh/km there is no interferer within 1000 m: exactly no collision
    o = analytical_pdr(d, 0.4, **PAPER)
    assert np.all(o["delta_col"] == 0.0)
    np.testing.assert_allclose(o["pdr"], (1 - o["p_hd"]) * (1 - o["p_sen"]) * (1 - o["p_pro"]), atol=1e-15)


def test_density_does_not_change_the_link_terms() -> None:
    a = analytical_pdr([200.0], 100.0, **PAPER)
    b = analytical_pdr([200.0], 300.0, **PAPER)
    for k in ("delta_hd", "delta_sen", "delta_pro"):
        assert a[k][0] == b[k][0]
    assert float(b["cbr"]) > float(a["cbr"])


# ----------------------------------------------------------------------------- argument checks
@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"density_veh_per_km": 0.0}, "density_veh_per_km must be in \\(0, 1000\\]"),
        ({"packets_per_s": 0.5}, "packets_per_s must be in \\[1, 100\\]"),
        ({"tx_power_dbm": 60.0}, "tx_power_dbm must be in"),
        ({"n_subchannels": 3}, "not one of the paper's formats"),
        ({"n_subchannels": 2.5}, "n_subchannels must be an integer"),
        ({"packet_bytes": 300}, "not one of the paper's formats"),
        ({"distance_m": [-1.0]}, "distance_m must be in \\[0, 1500\\]"),
        ({"grid_step_db": 0.0}, "grid_step_db must be in \\(0, 1\\]"),
    ],
)
def test_bad_arguments(kwargs: dict[str, object], match: str) -> None:
    args: dict[str, object] = {"distance_m": [100.0], "density_veh_per_km": 100.0} | PAPER
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        analytical_pdr(**args)  # type: ignore[arg-type]


def test_other_formats_need_a_curve() -> None:
    o = analytical_pdr([100.0], 100.0, 10.0, 20.0, 3, 300, bler_curve=BLER_190B_R05, data_rbs=14)
    assert float(o["noise_dbm"]) == pytest.approx(-95.0 - 10.0 * math.log10(50.0 / 14.0))


# ----------------------------------------------------------------------------- slow reference
def _slow_reference(distances: list[float], beta: float, lam: float, pt: float, s: int) -> dict[str, list[float]]:
    """The equations evaluated one distance and one interferer at a time, densities built
    explicitly and cross-correlated into the SINR density (the paper's formulation)."""
    step, psen, noise = 0.1, -90.5, -95.0 - 10.0 * math.log10(50.0 / 10.0)
    x = np.round(np.arange(-2000, 2001) * step, 10)
    sinr_axis = np.round(np.arange(-4000, 4001) * step, 10)

    def pl(dist: float) -> float:
        return float(path_loss_db(dist)[0])

    def f_rx(mean: float) -> np.ndarray:
        f = norm.pdf(x, mean, 3.0)
        f[x < psen] = 0.0
        return f / f.sum() / step

    def f_in(mean: float) -> np.ndarray:
        f = np.zeros_like(x)
        above = x > noise
        lin = 10 ** (x[above] / 10)
        ex = lin - 10 ** (noise / 10)
        f[above] = lin / (ex * 3.0 * math.sqrt(2 * math.pi)) * np.exp(-((10 * np.log10(ex) - mean) ** 2) / 18.0)
        return f / f.sum() / step

    def mean_bler(fa: np.ndarray, fb: np.ndarray) -> float:
        pdf = correlate(fa, fb, mode="full", method="direct")  # lag k: x_a - x_b = SINR
        pdf = pdf / pdf.sum() / step
        return float(pdf @ BLER_190B_R07(sinr_axis) * step)

    def psr(dist: np.ndarray | float, th: float) -> np.ndarray:
        return 0.5 * (1 + np.vectorize(math.erf)((pt - path_loss_db(dist)[0] - th) / (3.0 * math.sqrt(2))))

    n = s * 1000 / lam
    nc = 0.2 * n
    grid = np.arange(-1500, 1501, dtype=float)
    p = psr(grid, psen)
    spsr = beta * p.sum()
    ne2 = excluded_resources(spsr, n)
    cbr = ne2 / n
    th3 = psen
    while True:
        ne3 = excluded_resources(2 * beta * psr(grid, th3).sum(), n)
        if n - ne3 >= nc:
            break
        th3 += step
    r = np.array([np.dot(p[k:], p[: p.size - k]) for k in range(p.size)])
    kint = round(1000 * beta)
    ints = [k / beta for k in range(-kint, kint + 1) if k != 0]

    def cc(ne: float) -> np.ndarray:
        ce = (r / r[0]) * (beta * ne * r[0] / spsr - ne * ne / n) + ne * ne / n
        return (n - 2 * ne + ce) * (nc / (n - ne)) ** 2

    cc2, cc3 = cc(ne2), cc(ne3)
    alpha = alpha_weight(cbr)
    out: dict[str, list[float]] = {"pdr": [], "p_pro": [], "p_col": []}
    for d in distances:
        fr = f_rx(pt - pl(d))
        ppro = mean_bler(fr, f_in(-180.0))
        col2 = col3 = 1.0
        for xi in ints:
            pint = (mean_bler(fr, f_in(pt - pl(xi))) - ppro) / (1 - ppro)
            lag = math.floor(abs(xi + d) + 0.5)
            ps2 = 1 - (1 - 1 / lam) * float(psr(xi + d, psen))
            ps3 = 1 - (1 - 1 / lam) * float(psr(xi + d, th3))
            col2 *= 1 - ps2 * cc2[lag] / nc**2 * pint
            col3 *= 1 - ps3 * cc3[lag] / nc**2 * pint
        pcol = alpha * (1 - col2) + (1 - alpha) * (1 - col3)
        phd = lam / 1000
        psen_d = 0.5 * math.erfc((pt - pl(d) - psen) / (3 * math.sqrt(2)))
        out["pdr"].append((1 - phd) * (1 - psen_d) * (1 - ppro) * (1 - pcol))
        out["p_pro"].append(ppro)
        out["p_col"].append(pcol)
    return out


def test_matches_slow_reference() -> None:
    distances = [0.0, 120.0, 350.0]
    beta_per_km = 50.0  # 100 interferers within 1000 m keeps the slow loop short
    want = _slow_reference(distances, beta_per_km / 1000.0, 10.0, 20.0, 4)
    got = analytical_pdr(distances, beta_per_km, **PAPER)
    np.testing.assert_allclose(got["p_pro"], want["p_pro"], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(got["p_col"], want["p_col"], rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(got["pdr"], want["pdr"], rtol=1e-9, atol=1e-12)


def test_reference_format_table() -> None:
    assert m4.PAPER_FORMATS[(190, 4)] == (10, BLER_190B_R07)
    assert m4.PAPER_FORMATS[(190, 2)] == (12, BLER_190B_R05)


# ----------------------------------------------------------------------------- comparison driver
def test_simulator_overrides_match_the_model() -> None:
    from cv2x_marl.config import from_dict, preset
    from cv2x_marl.units import noise_power_dbm as sim_noise_dbm
    from cv2x_marl.validation.compare import simulator_overrides

    cfg = from_dict(simulator_overrides(0.2, 20.0, 23.0, 2, 190, 1000), preset("highway"))
    assert cfg.n_vehicles == 400
    assert cfg.traffic.rri_ms == 50 and cfg.sps.selection_window_subframes == 50
    assert sim_noise_dbm(cfg.radio.noise_dbm, cfg.radio.noise_figure_db) == pytest.approx(noise_power_dbm(12))
    assert cfg.radio.tx_power_dbm + cfg.radio.tx_antenna_gain_dbi + cfg.radio.rx_antenna_gain_dbi == 23.0
    # the RSRP threshold per resource element is P_SEN over the 12 x 12 resource elements of the data RBs
    assert cfg.sps.rsrp_threshold_dbm + 10 * math.log10(12 * 12) == pytest.approx(-90.5)
    assert cfg.radio.sensitivity_dbm == -90.5
    assert cfg.link.per_curve == "r1-160284-190b-r0.5"
    with pytest.raises(ValueError, match="paper's formats"):
        simulator_overrides(0.2, 10.0, 20.0, 3, 190, 1000)


def test_run_validation_writes_outputs(tmp_path: object) -> None:
    import json
    from pathlib import Path

    from cv2x_marl.validation.compare import run_validation

    out = Path(str(tmp_path)) / "val"
    assert len(run_validation(out, [0.02], n_subframes=200, seeds=[3])) == 4
    doc = json.loads((out / "validation.json").read_text())
    (res,) = doc["densities"]
    assert res["n_vehicles"] == 40
    assert [t["distance_m"] for t in res["table"]] == [50.0, 100.0, 200.0, 300.0, 400.0]
    assert len(res["curve"]["simulator"]) == len(res["curve"]["analytical"]) == 50
    assert (out / "pdr_0.02.png").stat().st_size > 0
    rows = (out / "table.csv").read_text().splitlines()
    assert rows[0] == "density_veh_per_m,distance_m,source,pdr,delta_hd,delta_sen,delta_pro,delta_col"
    assert len(rows) == 1 + 5 * 2
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no temporary file left


def test_cli_validate_writes_a_run_folder(tmp_path: Path) -> None:
    """`cv2x-marl validate` runs the comparison into a run folder (run.json, refused when not empty)."""
    from cv2x_marl.cli import main as cli_main

    out = tmp_path / "val"
    args = ["validate", "--out", str(out), "--densities", "0.02", "--subframes", "200", "--seeds", "3"]
    assert cli_main(args) == 0
    names = sorted(p.name for p in out.iterdir())
    assert names == ["pdr_0.02.png", "pdr_vs_distance.csv", "run.json", "table.csv", "validation.json"]
    run = json.loads((out / "run.json").read_text())
    assert run["command"] == "validate" and run["parameters"]["densities"] == [0.02]
    assert cli_main(args) == 2  # a second run does not mix into the first without --overwrite


def test_empty_bins_are_written_as_null_and_cli_errors_name_the_command(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from cv2x_marl.cli import main as cli_main
    from cv2x_marl.validation.compare import _json_safe

    assert _json_safe({"a": [1.0, math.nan], "b": {"c": math.inf}, "d": "x"}) == {
        "a": [1.0, None],
        "b": {"c": None},
        "d": "x",
    }
    assert cli_main(["validate", "--out", str(tmp_path / "v"), "--packets-per-s", "3"]) == 2
    assert not (tmp_path / "v").exists()  # the run folder was rolled back
    err = capsys.readouterr().err
    assert err.startswith("cv2x-marl: error: packets_per_s must give a whole reservation interval")
