"""The analytical model's assumptions as simulator switches (``validate --assumptions model``, issue 29).

Each switch against an independent construction on a tiny scene:

* ``sps.threshold_increase=model_cbr``: the weight of Step 2 (eq. 22) against the analytical module's
  ``alpha_weight``; the choice among the free candidates alone, counted by hand on the two-sub-channel
  scene of ``tests/test_validation_study.py`` (3 free of 20: CBR 0.85, alpha 1);
* ``sps.selection=uniform``: uniform among every survivor, where step 8 keeps only the lowest S-RSSI;
* ``link.interference=independent``: eq. 14's product over interferers, by hand and, in a simulator run, from
  the links table's powers (each co-channel interferer's power at the receiver is its own link's power);
* the route's switches apply to ``validate``'s base, and bad settings are refused.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from cv2x_marl.config import ConfigError, SpsConfig, apply_overrides, from_dict, preset
from cv2x_marl.sim import Simulator, link
from cv2x_marl.sim.chunk import independent_interference_success
from cv2x_marl.sim.ground_truth import MoverLinks, SnapshotLinks
from cv2x_marl.sim.metrics import CAUSE_CODE
from cv2x_marl.sim.sps import model_alpha, model_step2_alone, select
from cv2x_marl.validation.compare import MODEL_ASSUMPTION_SETS, assumption_sets, simulator_overrides
from cv2x_marl.validation.mode4_analytical import alpha_weight
from tests.test_validation_study import _hand_scene


def test_model_alpha_equals_the_analytical_modules_eq_22() -> None:
    cbr = np.array([0.0, 0.1, 0.19999, 0.2, 0.35, 0.5, 0.7, 0.70001, 0.85, 1.0])
    np.testing.assert_allclose(model_alpha(cbr), [alpha_weight(float(c)) for c in cbr], rtol=0.0, atol=1e-15)


def test_step2_alone_by_hand() -> None:
    """Ten candidates per row, threshold -110 dBm. Row 0: 3 free, CBR 0.7, alpha 1.0; row 1: 6 free, CBR 0.4,
    alpha 0.4, u = 0.39 below it; row 2: the same with u = 0.41; row 3: none free (Step 3 however alpha);
    row 4: 9 free (one unmonitored, counted excluded), CBR 0.1, alpha 0."""
    rsrp = np.full((5, 10), -100.0)
    rsrp[0, :3] = -np.inf
    rsrp[1, :6] = -120.0
    rsrp[2, :6] = -np.inf
    rsrp[4, :9] = -np.inf
    rsrp[4, 9] = np.inf
    u = np.array([0.999, 0.39, 0.41, 0.0, 0.0])
    np.testing.assert_array_equal(model_step2_alone(rsrp, -110.0, u), [True, True, False, False, False])


def test_model_cbr_chooses_among_the_free_resources_alone() -> None:
    """The two-sub-channel scene: 3 free of 20 candidates (CBR 0.85, alpha 1). The standard raises the threshold
    by 3 dB (5 survivors, step 8 keeps 4: indices 4, 6, 9, 15); Step 2 alone keeps -110 dBm and chooses among the
    3 free ones (4, 9, 15), uniformly, with either rule (3gpp: fewer survivors than ceil(0.2 M) = 4, all kept)."""
    rsrp, rssi, base = _hand_scene()
    for rule in ("3gpp", "uniform"):
        cfg = SpsConfig(**{**base.__dict__, "threshold_increase": "model_cbr", "selection": rule})
        rng = np.random.default_rng(3)
        outs = [select(rsrp, rssi, cfg, rng) for _ in range(3000)]
        assert all(o.threshold_dbm[0] == -110.0 and o.n_kept[0] == 3 for o in outs)
        counts = np.bincount([o.choice[0] for o in outs], minlength=20)
        assert set(np.flatnonzero(counts)) == {4, 9, 15}
        assert np.all(np.abs(counts[[4, 9, 15]] / 3000 - 1 / 3) < 0.035)  # 4 sigma = 0.034


def test_uniform_selection_ignores_the_s_rssi_ranking() -> None:
    """The same scene with the standard's threshold increase: 5 survivors at -107 dBm (4, 6, 9, 13, 15); step 8
    never picks index 13 (the loudest), the uniform rule picks each of the 5 with probability 1/5."""
    rsrp, rssi, base = _hand_scene()
    cfg = SpsConfig(**{**base.__dict__, "selection": "uniform"})
    rng = np.random.default_rng(4)
    picks = np.array([select(rsrp, rssi, cfg, rng).choice[0] for _ in range(4000)])
    counts = np.bincount(picks, minlength=20)
    assert set(np.flatnonzero(counts)) == {4, 6, 9, 13, 15}
    assert np.all(np.abs(counts[[4, 6, 9, 13, 15]] / 4000 - 0.2) < 0.026)  # 4 sigma = 0.0253


def test_independent_interference_by_hand() -> None:
    """Eq. 14 with a linear success curve s(x) = x / 20 on [0, 20] dB: link 0 has two interferers, link 1 none,
    link 2 one that drives its success to 0. Noise 1 mW."""

    def success(sinr_db: np.ndarray) -> np.ndarray:
        return np.clip(np.asarray(sinr_db) / 20.0, 0.0, 1.0)

    s_mw = np.array([100.0, 10.0, 10.0])  # SNR 20, 10, 10 dB
    p0 = success(10.0 * np.log10(s_mw))
    i_mw = np.array([9.0, 1.0, 1000.0])  # at link 0: SINR 10 dB and 10 log10(50) dB; at link 2: below 0 dB
    rep = np.array([0, 0, 2])
    p = independent_interference_success(p0, success, s_mw, i_mw, rep, 1.0)
    expected0 = 1.0 * (0.5 / 1.0) * ((10.0 * math.log10(50.0) / 20.0) / 1.0)
    np.testing.assert_allclose(p, [expected0, 0.5, 0.0], rtol=1e-12)


def _tiny_scene(extra: list[str]) -> Simulator:
    """Ten vehicles on 300 m, all generating in slot 0 with a two-slot window and two sub-channels: four
    resources, so most links have co-channel interferers."""
    ov = simulator_overrides(0.1, 10.0, 20.0, 2, 190, 200)
    ov["road"]["length_m"] = 300.0
    ov["traffic"]["synchronous"] = True
    ov["sps"]["selection_window_subframes"] = 2
    ov["metrics"]["record_links"] = True
    ov["sim"].update({"warmup_subframes": 0, "warmup_mode": "fixed"})
    cfg = apply_overrides(from_dict(ov, preset("highway-legacy")), extra)
    sim = Simulator(cfg)
    sim.reset(seed=5)
    return sim


def test_independent_interference_in_the_simulator_from_the_links_table() -> None:
    """Each link's success equals P0 prod_i (P_i / P0) over its co-channel interferers, with every power read
    from the links table (an interferer's power at the receiver is the power of its own link to that receiver),
    the PER curve at those SINRs and 0 for half duplex and below sensitivity; and the loss causes follow."""
    sim = _tiny_scene(MODEL_ASSUMPTION_SETS)
    links = sim.run(300).links
    assert links is not None
    curve = link.load_per_curve("r1-160284-190b-r0.5", "linear")
    noise_mw = sim.noise_mw
    rx_mw = 10.0 ** (links["rx_power_dbm"] / 10.0)
    key = list(zip(links["rx"].tolist(), links["subframe"].tolist(), links["subchannel"].tolist(), strict=True))
    groups: dict[tuple[int, int, int], list[int]] = {}
    for k, kk in enumerate(key):
        groups.setdefault(kk, []).append(k)
    n_interfered = 0
    for k, kk in enumerate(key):
        cause = int(links["cause"][k])
        if cause in (CAUSE_CODE["half_duplex"], CAUSE_CODE["sensitivity"]):
            assert links["p_success"][k] == 0.0
            continue
        p0 = float(curve.success(10.0 * math.log10(rx_mw[k] / noise_mw)))
        p = p0
        for other in groups[kk]:
            if other != k:
                p *= float(curve.success(10.0 * math.log10(rx_mw[k] / (rx_mw[other] + noise_mw)))) / p0
                n_interfered += 1
        assert links["p_success"][k] == pytest.approx(p, rel=1e-9, abs=1e-12)
    assert n_interfered > 100  # the scene has interference to check
    assert np.any(links["cause"] == CAUSE_CODE["collision"])


def test_model_route_switches_apply_to_validates_base_and_defaults_are_the_standards() -> None:
    base = preset("highway-legacy")
    assert (base.sps.threshold_increase, base.link.interference) == ("3gpp", "sum")
    assert assumption_sets("simulator") == ()
    cfg = apply_overrides(from_dict(simulator_overrides(0.3, 10.0, 20.0, 2, 190, 100), base), assumption_sets("model"))
    assert (cfg.sps.selection, cfg.sps.threshold_step_db, cfg.sps.threshold_increase) == ("uniform", 0.1, "model_cbr")
    assert cfg.link.interference == "independent"
    with pytest.raises(ValueError, match="assumptions"):
        assumption_sets("paper")


@pytest.mark.parametrize(
    "sets",
    [
        ["link.interference=independent", "link.inband_emission_model=3gpp"],
        ["link.interference=independent", "link.inband_emission_db=-30"],
        ["link.interference=independent", "channel.fading=rayleigh", "link.model=rayleigh"],
        ["link.interference=independent", "channel.fading=rayleigh"],
    ],
)
def test_independent_interference_refuses_what_it_cannot_model(sets: list[str]) -> None:
    with pytest.raises(ConfigError, match=r"link\.interference=independent"):
        apply_overrides(preset("highway-legacy"), ["link.inband_emission_model=flat", *sets])


def test_snapshot_evaluators_refuse_independent_interference() -> None:
    """The env's evaluators sum the interferers as the simulator's default does: they refuse the model route's
    switch instead of evaluating links otherwise than the simulator ran them."""
    sim = _tiny_scene([])
    snap = sim.snapshot()
    cfg = apply_overrides(sim.config, ["link.interference=independent"])
    with pytest.raises(ValueError, match=r"link\.interference must be sum"):
        SnapshotLinks(cfg, snap)
    with pytest.raises(ValueError, match=r"link\.interference must be sum"):
        MoverLinks.from_snapshots(cfg, [snap], [0])


def test_step3_in_tenth_of_a_db_steps_matches_the_literal_loop() -> None:
    """The route's ``sps.threshold_step_db=0.1``: the closed form of the threshold equals raising it 0.1 dB at a
    time until 20 % of the candidates remain (written out here), and that many survive."""
    rng = np.random.default_rng(11)
    cfg = SpsConfig(rsrp_threshold_dbm=-110.0, threshold_step_db=0.1, selection="uniform")
    rsrp = rng.uniform(-125.0, -80.0, size=(200, 30))
    rsrp[rng.random((200, 30)) < 0.1] = -np.inf
    out = select(rsrp, np.ones_like(rsrp), cfg, rng)
    for row in range(rsrp.shape[0]):
        th = -110.0
        while np.sum(rsrp[row] <= th) < 6:  # ceil(0.2 x 30)
            th += 0.1
        assert out.threshold_dbm[row] == pytest.approx(th, abs=1e-9)
        assert out.n_kept[row] == np.sum(rsrp[row] <= th) >= 6
        assert rsrp[row, out.choice[row]] <= out.threshold_dbm[row]


def test_validate_command_takes_the_route(tmp_path: Path) -> None:
    """``--assumptions`` parses to the two routes and refuses another before anything runs."""
    from cv2x_marl.cli import build_parser

    args = build_parser().parse_args(["validate", "--out", str(tmp_path / "v"), "--assumptions", "model"])
    assert args.assumptions == "model"
    assert build_parser().parse_args(["validate", "--out", str(tmp_path / "v")]).assumptions == "simulator"
    with pytest.raises(SystemExit):
        build_parser().parse_args(["validate", "--out", str(tmp_path / "v"), "--assumptions", "paper"])
    assert not (tmp_path / "v").exists()
