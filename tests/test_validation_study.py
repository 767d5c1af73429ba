"""The validation study (issue 29): the authors' figures, the two-sub-channel candidate set, the grid driver.

* The authors' MATLAB curves (read from their .fig files, ``cv2x_marl/validation/data``) against our
  independent implementation of the analytical model: equal to the CSV's 6 significant digits.
* The mechanism behind the two-sub-channel gap at 0.3 veh/m (docs/validation.md, "High load"): with
  fewer than 20 % of the resources free, TS 36.213 14.1.1.6 step 7 raises the threshold in 3 dB steps and
  re-admits resources that sensed vehicles reserve, while the model's eq. 23 (its only branch when the CBR
  exceeds 0.7) lets a vehicle choose among those free resources alone. Both sides counted by hand.
* The standard error over seeds, the worker pool and the grid's files.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from cv2x_marl.config import SpsConfig
from cv2x_marl.sim.sps import candidate_resources, select
from cv2x_marl.validation.compare import (
    STUDY_CONFIGURATIONS,
    STUDY_DENSITIES,
    authors_figures,
    pool_counts,
    run_grid,
    simulate_many,
    simulator_overrides,
    standard_error_pct,
)
from cv2x_marl.validation.mode4_analytical import analytical_pdr


@pytest.mark.parametrize("config", [(2, 10.0, 20.0, 0.3), (4, 20.0, 20.0, 0.3), (4, 10.0, 23.0, 0.1)])
def test_authors_matlab_pdr_equals_our_analytical_model(config: tuple[int, float, float, float]) -> None:
    """The PDR of the authors' MATLAB code (their figures) and of mode4_analytical, at 0, 25, ..., 500 m."""
    n_sub, lam, pt, rho = config
    fig = authors_figures(n_sub, lam, pt, rho)
    assert fig is not None
    ours = analytical_pdr(fig["distance_m"], 1000.0 * rho, lam, pt, n_sub, 190)["pdr"]
    np.testing.assert_allclose(ours, fig["matlab_pdr"], rtol=6e-6, atol=1e-6)  # the CSV keeps 6 digits


def test_authors_figures_cover_the_study_and_add_up() -> None:
    """Every configuration of the study is in the table; the Veins PDR and its four loss shares sum to 1
    (to the figures' rounding); no figure for another configuration."""
    for n_sub, lam, pt in STUDY_CONFIGURATIONS:
        for rho in STUDY_DENSITIES:
            fig = authors_figures(n_sub, lam, pt, rho)
            assert fig is not None
            np.testing.assert_array_equal(fig["distance_m"], np.arange(0.0, 501.0, 25.0))
            total = fig["pdr"] + fig["delta_hd"] + fig["delta_sen"] + fig["delta_pro"] + fig["delta_col"]
            np.testing.assert_allclose(total, 1.0, atol=2e-4)
            assert np.all((fig["sci_lost"] >= 0.0) & (fig["sci_lost"] <= 1.0 - fig["pdr"]))
    assert authors_figures(2, 20.0, 20.0, 0.3) is None
    assert authors_figures(4, 10.0, 20.0, 0.25) is None


def _hand_scene() -> tuple[np.ndarray, np.ndarray, SpsConfig]:
    """Two sub-channels, a selection window of 10 slots: M = 20 candidates, 20 % = 4.

    Slot 0 is the vehicle's own (not monitored: both sub-channels +inf). Free (no SCI): 3 resources.
    Reserved, RSRP over the threshold Th0 = -110 dBm: +1 dB and +2.5 dB (re-admitted at Th0 + 3 dB),
    +4 dB (at Th0 + 6 dB) and eleven at +10 dB or more.
    """
    cfg = SpsConfig(n_subchannels=2, selection_window_subframes=10, selection="3gpp", rsrp_threshold_dbm=-110.0)
    th0 = cfg.rsrp_threshold_dbm
    rsrp = np.full(20, th0 + 10.0) + np.arange(20) * 0.1
    rsrp[[0, 1]] = np.inf  # the own subframe, both sub-channels (TS 36.213 14.1.1.6 step 5)
    rsrp[[4, 9, 15]] = -np.inf  # free
    rsrp[6], rsrp[13], rsrp[18] = th0 + 1.0, th0 + 2.5, th0 + 4.0
    rssi = np.linspace(2e-9, 1e-9, 20)  # falling with the index: the later the resource, the quieter
    rssi[13] = 5e-9  # the loudest of the survivors
    return rsrp[None, :], rssi[None, :], cfg


def test_two_subchannel_candidate_set_counted_by_hand() -> None:
    """Step 7 with two sub-channels: 3 free < 4 = ceil(0.2 x 20), so the threshold rises once by 3 dB and
    re-admits the two resources reserved at +1 and +2.5 dB (5 survivors); step 8 keeps the 4 lowest S-RSSI
    of them (all but index 13), and the MAC picks one of those 4 uniformly."""
    rsrp, rssi, cfg = _hand_scene()
    cand = candidate_resources(np.array([0]), cfg, 100)
    np.testing.assert_array_equal(cand[0], np.arange(2, 22))  # slots 1..10 (T1 = 1) x sub-channels 0, 1
    rng = np.random.default_rng(7)
    picks = np.array([select(rsrp, rssi, cfg, rng).choice[0] for _ in range(4000)])
    out = select(rsrp, rssi, cfg, np.random.default_rng(0))
    assert out.threshold_dbm[0] == pytest.approx(-107.0)
    assert out.n_kept[0] == 5
    assert set(picks.tolist()) == {4, 6, 9, 15}
    counts = np.bincount(picks, minlength=20)[[4, 6, 9, 15]]
    assert np.all(np.abs(counts / 4000 - 0.25) < 0.03)  # uniform: 4 sigma = 0.027
    # the model's eq. 23 branch (Step 2 alone) would choose among the 3 free resources only
    assert int(np.sum(np.isneginf(rsrp))) == 3 < math.ceil(0.2 * 20)


def test_the_model_chooses_among_fewer_than_20_percent_at_two_subchannels_and_high_load() -> None:
    """At 0.3 veh/m, 10 Hz, 20 dBm the model's CBR exceeds 0.7, so eq. 21 weighs Step 2 alone (alpha = 1),
    whose assignable resources N - N_e (eq. 29) fall below the N_c = 0.2 N candidates with S = 2 (28.7 of
    200 < 40) but not with S = 4 (153.5 of 400 >= 80): the standard's step 7 would raise the threshold."""
    two = analytical_pdr([200.0], 300.0, 10.0, 20.0, 2, 190)
    four = analytical_pdr([200.0], 300.0, 10.0, 20.0, 4, 190)
    for out, n_res in ((two, 200.0), (four, 400.0)):
        assert float(out["n_resources"]) == n_res
    assert float(two["alpha"]) == 1.0
    assert float(two["n_resources"] - two["n_excluded_step2"]) == pytest.approx(28.7, abs=0.05)
    assert float(two["n_resources"] - two["n_excluded_step2"]) < 0.2 * 200.0
    assert float(four["n_resources"] - four["n_excluded_step2"]) == pytest.approx(153.5, abs=0.05)


def test_standard_error_over_seeds_by_hand() -> None:
    pdr = np.array([[0.5, 0.9, np.nan], [0.7, 0.9, 0.4], [0.6, 0.6, np.nan]])
    se = standard_error_pct(pdr)
    assert se[0] == pytest.approx(100.0 * 0.1 / math.sqrt(3))  # std(0.5, 0.7, 0.6; ddof 1) = 0.1
    assert se[1] == pytest.approx(100.0 * math.sqrt(0.03) / math.sqrt(3))  # deviations 0.1, 0.1, -0.2
    assert math.isnan(se[2])  # one seed with samples
    assert np.all(np.isnan(standard_error_pct(pdr[:1])))


def test_worker_pool_gives_the_single_process_counts() -> None:
    """Two processes give each seed's counts bit for bit, in task order; the pooled counts add up."""
    ov = simulator_overrides(0.02, 10.0, 20.0, 4, 190, 200)
    tasks = [(ov, 3, ()), (ov, 4, ())]
    one = simulate_many(tasks, workers=1)
    two = simulate_many(tasks, workers=2)
    for a, b in zip(one, two, strict=True):
        for k in ("n", "decoded", "half_duplex", "sensitivity", "propagation", "collision"):
            np.testing.assert_array_equal(a[k], b[k])
    pooled = pool_counts(one)
    np.testing.assert_array_equal(pooled["n"], one[0]["n"] + one[1]["n"])
    assert pooled["pdr_per_seed"].shape == (2, 50)
    with pytest.raises(ValueError, match="workers must be >= 1"):
        simulate_many(tasks, workers=0)


def test_run_grid_writes_a_folder_per_configuration_and_the_summary(tmp_path: Path) -> None:
    out = tmp_path / "grid"
    paths = run_grid(out, configurations=[(4, 10.0, 20.0)], densities=[0.02], n_subframes=200, seeds=[3, 4])
    assert paths[-2:] == [out / "grid.csv", out / "grid.md"]
    assert sorted(p.name for p in (out / "s4_l10_p20").iterdir()) == [
        "pdr_0.02.png",
        "pdr_vs_distance.csv",
        "table.csv",
        "validation.json",
    ]
    header, row = (out / "grid.csv").read_text().splitlines()
    cols = dict(zip(header.split(","), row.split(","), strict=True))
    assert cols["n_subchannels"] == "4" and cols["density_veh_per_m"] == "0.02"
    assert cols["mad_pdr_pct_vs_veins"] == "nan"  # no figure of the authors at 0.02 veh/m
    doc = json.loads((out / "s4_l10_p20" / "validation.json").read_text())
    (res,) = doc["densities"]
    assert res["seeds"] == [3, 4] and res["authors_veins"] is None
    assert res["se_pct_0_500m"]["mean"] >= 0.0
    with pytest.raises(ValueError, match="paper's formats"):
        run_grid(tmp_path / "bad", configurations=[(3, 10.0, 20.0)], densities=[0.1])
    assert not (tmp_path / "bad").exists()
