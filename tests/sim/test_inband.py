"""link.inband_emission_model (issue 13, defect 5): the 3GPP in-band emission mask (TS 36.101 6.5.2.3
with TR 36.843 A.2.1.5's W, X, Y, Z as WiLabV2Xsim sets them) against hand computation from the
formula, its leakage matrix, the simulator's SINR in a hand-built scene against an independent numpy
construction, the env's evaluators against the simulator, and the default (flat) unchanged."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

from cv2x_marl.config import ConfigError, apply_overrides, preset
from cv2x_marl.sim import Simulator, mobility
from cv2x_marl.sim.ground_truth import MoverLinks, SnapshotLinks
from cv2x_marl.sim.inband import general_emission_db, leakage_matrix, pool_leakage_weights, rb_emission
from cv2x_marl.sim.metrics import CAUSE_CODE

# Hand values of the general term for a 10-RB allocation in a 50-RB channel (the highway pool),
# P_RB = 23 dBm - 10 log10(10) = 13 dBm, EVM 0.175, W = 3, X = 6:
#   flat term   -25 - 10 log10(50 / 10) - 6            = -37.98970004 dB
#   EVM term    20 log10(0.175) - 3 - 5 (D - 1) / 10 - 3 = -21.13923903 - 0.5 (D - 1) dB
#   floor term  -57 - 13 - 6                            = -76 dB
FLAT_50_DB = -37.98970004
EVM_TERM_1_DB = -21.13923903


@pytest.mark.parametrize(
    ("delta_rb", "expected_db"),
    [
        (1, -21.13923903),  # EVM term at the adjacent RB
        (2, -21.63923903),
        (10, -25.63923903),
        (11, -26.13923903),
        (31, -36.13923903),
        (34, -37.63923903),  # last offset where the EVM term is above the flat term
        (35, -37.98970004),  # EVM term -38.139: the flat term binds
        (40, -37.98970004),
    ],
)
def test_general_term_matches_the_hand_computation(delta_rb: int, expected_db: float) -> None:
    assert general_emission_db(delta_rb, 10, 50, 13.0) == pytest.approx(expected_db, abs=1e-7)


def test_general_term_floor_binds_at_low_power_and_the_flat_term_scales_with_the_allocation() -> None:
    # P_RB = -40 dBm: floor -57 + 40 - 6 = -23 dB, above the EVM term -25.639 at D = 10
    assert general_emission_db(10, 10, 50, -40.0) == pytest.approx(-23.0, abs=1e-12)
    assert general_emission_db(1, 10, 50, -40.0) == pytest.approx(-21.13923903, abs=1e-7)
    # 2-RB allocation in 50 RB: flat -25 - 10 log10(25) - 6 = -44.97940009; EVM term at D = 5: -15.13924 - 3 - 10 - 3
    assert general_emission_db(5, 2, 50, 13.0) == pytest.approx(-31.13923903, abs=1e-7)
    assert general_emission_db(20, 2, 50, 13.0) == pytest.approx(-44.97940009, abs=1e-7)
    with pytest.raises(ValueError, match="delta_rb must be >= 1"):
        general_emission_db(0, 10, 50, 13.0)


def _hand_leakage(v: int, i: int, n_rb: int, s: int, p_rb_dbm: float) -> float:
    """M[v, i] from the formula, RB by RB (independent of sim/inband.py): general + IQ image
    (-28 dB where RB n_rb - 1 - r is allocated) + carrier leakage (-28 dB at the DC RBs)."""
    start, stop = i * s, i * s + s - 1
    dc = {n_rb // 2} if n_rb % 2 else {n_rb // 2 - 1, n_rb // 2}
    total = 0.0
    for r in range(v * s, v * s + s):
        d = max(start - r, r - stop)
        general = max(
            -25.0 - 10.0 * math.log10(n_rb / s) - 6.0,
            20.0 * math.log10(0.175) - 3.0 - 5.0 * (d - 1) / s - 3.0,
            -57.0 - p_rb_dbm - 6.0,
        )
        total += 10.0 ** (general / 10.0)
        if start <= n_rb - 1 - r <= stop:
            total += 10.0 ** (-28.0 / 10.0)
        if r in dc:
            total += 10.0 ** (-28.0 / 10.0)
    return total / s


def test_leakage_matrix_matches_the_hand_computation_on_the_highway_pool() -> None:
    m = leakage_matrix(n_subchannels=5, subchannel_rbs=10, tx_power_dbm=23.0)
    hand = np.array([[_hand_leakage(v, i, 50, 10, 13.0) for i in range(5)] for v in range(5)])
    np.fill_diagonal(hand, 1.0)
    np.testing.assert_allclose(m, hand, rtol=1e-12)
    db = 10.0 * np.log10(m)
    # adjacent subchannel: mean over D = 1..10 of the EVM term, no image, no DC RB
    adjacent = sum(10.0 ** ((EVM_TERM_1_DB - 0.5 * k) / 10.0) for k in range(10)) / 10.0
    assert m[1, 0] == pytest.approx(adjacent, rel=1e-8)  # constants to 8 decimals
    assert db[1, 0] == pytest.approx(-23.15, abs=0.005)
    # subchannel 0 into 4: D = 31..34 EVM term, 35..40 flat term, plus the IQ image of every RB (RBs 40-49 mirror 9-0)
    evm_part = sum(10.0 ** ((EVM_TERM_1_DB - 0.5 * (d - 1)) / 10.0) for d in range(31, 35))
    far = (evm_part + 6 * 10.0 ** (FLAT_50_DB / 10.0)) / 10
    assert m[4, 0] == pytest.approx(far + 10.0**-2.8, rel=1e-8)
    assert db[4, 0] == pytest.approx(-27.54, abs=0.005)
    # subchannel 2 holds the carrier (RBs 24, 25): two RBs of -28 dB on top of its row
    assert m[2, 0] - m[0, 2] == pytest.approx(2 * 10.0**-2.8 / 10, rel=1e-9)
    assert db[0, 2] == pytest.approx(-28.15, abs=0.005) and db[2, 0] == pytest.approx(-27.34, abs=0.005)


def test_leakage_matrix_structure() -> None:
    full = leakage_matrix(5, 10, 23.0)
    assert np.all(np.diag(full) == 1.0) and np.all(full[~np.eye(5, dtype=bool)] < 0.01)
    # mirror symmetry of the band about the carrier: M[v, i] = M[n-1-v, n-1-i]
    np.testing.assert_allclose(full, full[::-1, ::-1], rtol=1e-12)
    # the general part alone depends on the offset only: symmetric Toeplitz, falling with the offset
    general = leakage_matrix(5, 10, 23.0, components=("general",))
    np.testing.assert_allclose(general, general.T, rtol=1e-12)
    for k in range(1, 5):
        np.testing.assert_allclose(np.diag(general, k), np.diag(general, k)[0], rtol=1e-12)
    assert np.all(np.diff(general[0]) < 0)
    # the IQ image is symmetric too; the carrier leakage is a row term (the victim's DC RBs)
    iq = leakage_matrix(5, 10, 23.0, components=("general", "iq_image"))
    np.testing.assert_allclose(iq, iq.T, rtol=1e-12)
    dc_row = (np.arange(5) == 2)[:, None] * 10**-2.8 / 5  # 2 DC RBs of -28 dB over 10 RBs
    np.testing.assert_allclose(full - iq, np.where(np.eye(5, dtype=bool), 0.0, dc_row))
    # the paper's 2 x 10 RB pool: both subchannels image each other and hold one DC RB each
    paper = leakage_matrix(2, 10, 26.0)
    assert paper[0, 1] == pytest.approx(paper[1, 0], rel=1e-12)
    assert paper[0, 1] == pytest.approx(_hand_leakage(0, 1, 20, 10, 16.0), rel=1e-12)
    assert 10 * np.log10(paper[0, 1]) == pytest.approx(-21.82, abs=0.005)


def test_rb_emission_is_one_inside_the_allocation() -> None:
    e = rb_emission(10, 10, 50, 13.0)
    assert np.all(e[10:20] == 1.0) and np.all(e[:10] < 0.01) and np.all(e[20:] < 0.01)
    with pytest.raises(ValueError, match="unknown in-band emission components"):
        rb_emission(0, 10, 50, 13.0, components=("acl",))


# ----------------------------------------------------------------------------- the simulator
SCENE = [
    "vehicles.n_vehicles=4",
    "sim.warmup_subframes=0",
    "channel.pathloss=power_law",
    "channel.shadowing_std_db=0",
    "channel.shadowing_nlos_std_db=0",
    "channel.los=always",
    "link.inband_emission_model=3gpp",
]
# (x, y) m, slot, subchannel: 0, 1, 2 transmit in slot 3 (0 on subchannel 0, 1 and 2 share subchannel 1);
# 3 transmits alone in slot 7 and receives all of them
POSITIONS_M = np.array([[0.0, 0.0], [100.0, 0.0], [250.0, 30.0], [60.0, 80.0]])
RESOURCES = [(3, 0), (3, 1), (3, 1), (7, 0)]


def _scene(extra: list[str] | None = None) -> tuple[Simulator, list]:
    cfg = apply_overrides(preset("paper"), [*SCENE, *(extra or [])])
    sim = Simulator(cfg)
    sim.reset(seed=3, warmup_subframes=0)
    sim.scheduler.resource = np.array([s * cfg.sps.n_subchannels + c for s, c in RESOURCES])
    sim.set_offsets(POSITIONS_M - mobility.positions_m(sim.road, sim.state))
    snap = sim.snapshot()
    links = sim.run(cfg.traffic.rri_ms).links
    assert links is not None
    return sim, [snap, links]


def test_sinr_of_a_hand_built_scene_matches_an_independent_construction() -> None:
    sim, (snap, links) = _scene()
    cfg = sim.config
    np.testing.assert_allclose(snap.positions_m, POSITIONS_M, atol=1e-9)
    # received power: EIRP - free-space power law (eq. 3, exponent 2, d0 = 1 m at 2 GHz)
    eirp = cfg.radio.tx_power_dbm + cfg.radio.tx_antenna_gain_dbi + cfg.radio.rx_antenna_gain_dbi
    lam = 299_792_458.0 / cfg.radio.carrier_hz
    d = np.hypot(*(POSITIONS_M[:, None, :] - POSITIONS_M[None, :, :]).transpose(2, 0, 1))
    with np.errstate(divide="ignore"):
        p_mw = 10.0 ** ((eirp + 20.0 * np.log10(lam / (4 * np.pi)) - 20.0 * np.log10(d)) / 10.0)  # [tx, rx]
    # leakage between the 2 subchannels of 10 RB in a 20-RB channel, P_RB = 26 - 10 = 16 dBm
    w = _hand_leakage(0, 1, 20, 10, 16.0)
    noise_mw = 10.0 ** ((cfg.radio.noise_dbm + cfg.radio.noise_figure_db) / 10.0)
    expected = {  # (tx, rx): interference at rx
        (0, 3): w * (p_mw[1, 3] + p_mw[2, 3]),  # leakage from 1 and 2 (subchannel 1 into 0)
        (1, 3): p_mw[2, 3] + w * p_mw[0, 3],  # co-channel 2, leakage from 0
        (2, 3): p_mw[1, 3] + w * p_mw[0, 3],
        (3, 0): 0.0,
        (3, 1): 0.0,
        (3, 2): 0.0,
    }
    seen = 0
    for k in range(links["tx"].shape[0]):
        a, b = int(links["tx"][k]), int(links["rx"][k])
        if (a, b) not in expected:
            assert links["cause"][k] == CAUSE_CODE["half_duplex"]  # 0, 1, 2 share slot 3
            continue
        sinr_db = 10.0 * np.log10(p_mw[a, b] / (expected[(a, b)] + noise_mw))
        assert links["sinr_db"][k] == pytest.approx(sinr_db, abs=1e-9)
        seen += 1
    assert seen == 6
    # the leakage matters here: vehicle 0's link to 3 loses about 4 dB against no in-band emission
    flat_sinr = 10.0 * np.log10(p_mw[0, 3] / noise_mw)
    k03 = int(np.flatnonzero((links["tx"] == 0) & (links["rx"] == 3))[0])
    assert flat_sinr - links["sinr_db"][k03] == pytest.approx(
        10 * np.log10(1 + w * (p_mw[1, 3] + p_mw[2, 3]) / noise_mw), abs=1e-9
    )
    assert flat_sinr - links["sinr_db"][k03] > 1.0
    # sensing: vehicle 3's S-RSSI of slot 3 holds the leakage too (the energy in each subchannel), plus noise
    rssi = sim.scheduler.rssi_ring[0, 3].astype(np.float64)  # the period just ended, [resource]
    np.testing.assert_allclose(rssi[3 * 2 + 0], p_mw[0, 3] + w * (p_mw[1, 3] + p_mw[2, 3]) + noise_mw, rtol=1e-6)
    np.testing.assert_allclose(rssi[3 * 2 + 1], p_mw[1, 3] + p_mw[2, 3] + w * p_mw[0, 3] + noise_mw, rtol=1e-6)
    assert np.isnan(rssi[7 * 2 : 7 * 2 + 2]).all()  # its own subframe: not monitored


def test_the_simulator_weights_leakage_by_victim_row_on_an_asymmetric_pool() -> None:
    """Five subchannels of 10 RB (50 RB): the carrier-leakage RBs lie in subchannel 2, so M[2, 0] and
    M[0, 2] differ (-27.34 vs -28.15 dB) and a transposed matrix would be caught (review of issue 13)."""
    cfg = apply_overrides(preset("paper"), [*SCENE, "sps.n_subchannels=5"])
    sim = Simulator(cfg)
    sim.reset(seed=3, warmup_subframes=0)
    # 0 on subchannel 0 and 1 on subchannel 2 of slot 3; 2 and 3 receive from slot 7 / 9
    sim.scheduler.resource = np.array([3 * 5 + 0, 3 * 5 + 2, 9 * 5 + 4, 7 * 5 + 0])
    sim.set_offsets(POSITIONS_M - mobility.positions_m(sim.road, sim.state))
    links = sim.run(cfg.traffic.rri_ms).links
    assert links is not None
    eirp = cfg.radio.tx_power_dbm + cfg.radio.tx_antenna_gain_dbi + cfg.radio.rx_antenna_gain_dbi
    lam = 299_792_458.0 / cfg.radio.carrier_hz
    d = np.hypot(*(POSITIONS_M[:, None, :] - POSITIONS_M[None, :, :]).transpose(2, 0, 1))
    with np.errstate(divide="ignore"):
        p_mw = 10.0 ** ((eirp + 20.0 * np.log10(lam / (4 * np.pi)) - 20.0 * np.log10(d)) / 10.0)
    noise_mw = 10.0 ** ((cfg.radio.noise_dbm + cfg.radio.noise_figure_db) / 10.0)
    p_rb = cfg.radio.tx_power_dbm - 10.0 * math.log10(10)
    m20, m02 = _hand_leakage(2, 0, 50, 10, p_rb), _hand_leakage(0, 2, 50, 10, p_rb)
    assert m20 > m02
    for rx in (2, 3):
        k0 = int(np.flatnonzero((links["tx"] == 0) & (links["rx"] == rx))[0])
        k1 = int(np.flatnonzero((links["tx"] == 1) & (links["rx"] == rx))[0])
        # 0's packet on subchannel 0 hears 1's leakage into subchannel 0: M[0, 2]; and the other way round
        sinr0 = 10.0 * np.log10(p_mw[0, rx] / (m02 * p_mw[1, rx] + noise_mw))
        sinr1 = 10.0 * np.log10(p_mw[1, rx] / (m20 * p_mw[0, rx] + noise_mw))
        assert links["sinr_db"][k0] == pytest.approx(sinr0, abs=1e-9)
        assert links["sinr_db"][k1] == pytest.approx(sinr1, abs=1e-9)


def test_the_flat_model_leaves_sensing_co_channel() -> None:
    sim, (_snap, links) = _scene(["link.inband_emission_model=flat", "link.inband_emission_db=-20"])
    rssi = sim.scheduler.rssi_ring[0, 3].astype(np.float64)
    k = np.flatnonzero((links["tx"] == 0) & (links["rx"] == 3))[0]
    noise_mw = 10.0 ** ((sim.config.radio.noise_dbm + sim.config.radio.noise_figure_db) / 10.0)
    np.testing.assert_allclose(rssi[3 * 2 + 0], 10.0 ** (links["rx_power_dbm"][k] / 10.0) + noise_mw, rtol=1e-6)


@pytest.mark.kernel_equality
def test_the_env_evaluators_follow_the_3gpp_model() -> None:
    """SnapshotLinks (compiled and numpy) and MoverLinks give the simulator's own P with 3gpp."""
    sim, (snap, links) = _scene()
    cfg = sim.config
    ok = links["cause"] != CAUSE_CODE["half_duplex"]
    for compiled in (True, False):
        p = SnapshotLinks(cfg, snap, truth_los="always", compiled=compiled).success(snap.positions_m)
        np.testing.assert_allclose(p[links["tx"][ok], links["rx"][ok]], links["p_success"][ok], rtol=1e-9, atol=1e-12)
    for mover in range(4):
        ml = MoverLinks.from_snapshots(cfg, [snap], [mover], truth_los="always")
        p = ml.success(ml.start_m)[0]
        sel = ok & (links["tx"] == mover)
        np.testing.assert_allclose(p[links["rx"][sel]], links["p_success"][sel], rtol=1e-9, atol=1e-12)


@pytest.mark.kernel_equality
@pytest.mark.parametrize("name", ["paper", "highway-legacy"])
def test_snapshot_links_match_the_simulator_with_the_3gpp_model(name: str) -> None:
    cfg = apply_overrides(preset(name), ["sim.warmup_subframes=300", "link.inband_emission_model=3gpp"])
    sim = Simulator(cfg)
    snap = sim.reset(seed=4)
    links = sim.run(cfg.traffic.rri_ms).links
    assert links is not None
    ok = links["cause"] != CAUSE_CODE["half_duplex"]
    for compiled in (True, False):
        p = SnapshotLinks(cfg, snap, compiled=compiled).success(snap.positions_m)
        np.testing.assert_allclose(p[links["tx"][ok], links["rx"][ok]], links["p_success"][ok], rtol=1e-9, atol=1e-12)


# ------------------------------------------------------------------ defaults and configuration
def test_the_default_is_flat_and_bit_identical_to_the_code_before_the_switch() -> None:
    """Reference values: the same runs on commit 38b49f8 (before link.inband_emission_model)."""
    for extra, prr, sinr_sum, decoded in (
        ([], 0.45889578367170614, 11541.310288780112, 3449),
        (["link.inband_emission_db=-25"], 0.39730629382403315, -32813.22638196972, 2986),
    ):
        for model in ([], ["link.inband_emission_model=flat"]):
            cfg = apply_overrides(preset("paper"), ["sim.warmup_subframes=300", *extra, *model])
            assert cfg.link.inband_emission_model == "flat"
            sim = Simulator(cfg)
            sim.reset(seed=11)
            r = sim.run(2000)
            assert r.links is not None
            assert r.metrics.summary()["prr_mean"] == prr
            assert float(np.sum(r.links["sinr_db"])) == sinr_sum
            assert int(r.links["outcome"].sum()) == decoded


def test_3gpp_lowers_prr_on_the_paper_preset() -> None:
    cfg = apply_overrides(preset("paper"), ["sim.warmup_subframes=300", "link.inband_emission_model=3gpp"])
    sim = Simulator(cfg)
    sim.reset(seed=11)
    assert sim.run(2000).metrics.summary()["prr_mean"] < 0.45889578367170614  # the flat default's, above


def test_weights_of_either_model() -> None:
    cfg = apply_overrides(preset("highway-legacy"), ["link.inband_emission_model=3gpp"])
    w = pool_leakage_weights(cfg)
    assert w is not None and np.all(np.diag(w) == 0.0)
    np.testing.assert_allclose(w + np.eye(5), leakage_matrix(5, 10, 23.0))
    flat = pool_leakage_weights(apply_overrides(preset("highway-legacy"), ["link.inband_emission_db=-20"]))
    assert flat is not None and np.all(flat[~np.eye(5, dtype=bool)] == pytest.approx(0.01))
    assert pool_leakage_weights(preset("highway-legacy")) is None


def test_bad_combinations_are_refused_by_name() -> None:
    with pytest.raises(ConfigError, match=r"link\.inband_emission_db \(-25\).*link\.inband_emission_model=3gpp"):
        apply_overrides(preset("paper"), ["link.inband_emission_model=3gpp", "link.inband_emission_db=-25"])
    with pytest.raises(ConfigError, match=r"link\.inband_emission_model: '3GPP' is not allowed; allowed values: flat"):
        apply_overrides(preset("paper"), ["link.inband_emission_model=3GPP"])
    cfg = apply_overrides(
        preset("paper"), ["channel.fading=rayleigh", "link.model=rayleigh", "link.inband_emission_model=3gpp"]
    )
    with pytest.raises(ConfigError, match=r"inband_emission_model=3gpp is not supported with link\.model=rayleigh"):
        Simulator(cfg)


@pytest.mark.parametrize(
    "extra",
    [
        ["link.inband_emission_model=3gpp"],
        ["link.inband_emission_model=3gpp", "link.pair_state=sparse", "sps.reselection_timing=per_ue"],
        ["link.inband_emission_db=-25"],
        ["link.inband_emission_db=-25", "sps.reselection_timing=per_ue"],
    ],
)
def test_compiled_period_with_inband_emission_equals_the_numpy_period(
    extra: list[str], compiled_and_numpy: Callable[..., Any]
) -> None:
    """Both in-band models in the compiled chunk (kernels.period_chunk): the same leakage sums in the same
    order as Simulator._chunk, so the same outcomes, PRR sums, S-RSSI (leakage included) and reselections;
    per_ue cuts the period into chunks of a few transmitters (the subset path)."""
    base = ["vehicles.density_veh_per_m=0.1", "road.length_m=2500", "metrics.record_links=false"]
    a, ma, _, _ = compiled_and_numpy(apply_overrides(preset("highway-legacy"), [*base, *extra]), 1, 250, 440)
    assert a.n_reselections > 0
    # and the leakage is really there: the same run without it decodes more
    plain = Simulator(apply_overrides(preset("highway-legacy"), base))
    plain.reset(seed=1, warmup_subframes=250)
    assert plain.run(450).metrics.bin_decoded.sum() > ma.bin_decoded.sum()


def test_inband_leakage_sums_each_victim_row_by_hand() -> None:
    """Simulator.chunks.inband_leakage (the numpy side of the compiled chunk's sums): leak[v] = sum_i M[v, i] t[i]."""
    cfg = apply_overrides(preset("highway-legacy"), ["road.length_m=1000", "link.inband_emission_model=3gpp"])
    sim = Simulator(cfg)
    assert sim.chunks.leakage is not None
    total = np.zeros(sim.n * sim.n_res)
    row = 7 * sim.rri + 31  # receiver 7, subframe 31
    t = np.array([1e-9, 0.0, 3e-10, 0.0, 2e-11])[: sim.n_sub]
    total[row * sim.n_sub : (row + 1) * sim.n_sub] = t
    leak = sim.chunks.inband_leakage(total).reshape(sim.n * sim.rri, sim.n_sub)
    m = sim.chunks.leakage
    for v in range(sim.n_sub):
        assert leak[row, v] == pytest.approx(sum(m[v, i] * t[i] for i in range(sim.n_sub)), rel=1e-15)
    assert leak[row, 0] == pytest.approx(m[0, 2] * 3e-10 + m[0, 4] * 2e-11, rel=1e-15)  # M has a zero diagonal
    assert np.count_nonzero(leak) == np.count_nonzero(leak[row]) > 0  # only the subframe that heard something
