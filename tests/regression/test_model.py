"""Two-distance model: coefficient recovery, gradients, JSON I/O, errors, determinism."""

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from cv2x_marl.regression import FitData, FitError, ModelError, TwoDistanceModel, fit_two_distance
from cv2x_marl.regression.model import _digest

TRUE = {
    "alpha": np.array([-0.8, -0.7, -0.6]),
    "beta": np.array([0.0, 0.3, 0.2]),
    "gamma": np.array([2.2, 1.3, 1.4]),
}


def _synthetic(kind: str, n: int = 30_000, seed: int = 0, noise: float = 0.02) -> FitData:
    rng = np.random.default_rng(seed)
    nsv = rng.integers(0, 5, size=n)  # 3 and 4 pool into the cap 2
    d = rng.uniform(10, 400, size=n)
    l_m = np.where(nsv == 0, 200.0, rng.uniform(10, 200, size=n))
    truth = TwoDistanceModel(kind, TRUE["alpha"], TRUE["beta"], TRUE["gamma"])
    p = truth.predict_unclipped(d, l_m, nsv)
    group = rng.integers(0, 10, size=n)
    if kind == "logistic":
        y = rng.binomial(50, p) / 50.0  # empirical rates over 50 packets
        return FitData(d, l_m, nsv, y, group)
    # keep designs whose true P lies in [0.1, 0.9] (selection on x does not bias least squares),
    # so that y = P + N(0, 0.02^2) stays inside [0, 1] without clipping
    y = p + rng.normal(0, noise, size=n)
    k = (p >= 0.1) & (p <= 0.9)
    return FitData(d[k], l_m[k], nsv[k], y[k], group[k])


def test_linear_fit_recovers_known_coefficients() -> None:
    data = _synthetic("linear")
    m = fit_two_distance(data, "linear", nsv_cap=2)
    np.testing.assert_allclose(m.alpha, TRUE["alpha"], atol=0.02)
    np.testing.assert_allclose(m.beta, TRUE["beta"], atol=0.02)
    np.testing.assert_allclose(m.gamma, TRUE["gamma"], atol=0.05)
    assert m.beta[0] == 0.0  # l is constant (= th_I) at NSV 0: not identifiable, set to 0
    assert m.stats[2]["instances"] == int(np.sum(data.nsv >= 2))  # pooled at the cap
    assert m.stats[1]["r2_test"] > 0.9


def test_logistic_fit_recovers_known_coefficients() -> None:
    m = fit_two_distance(_synthetic("logistic"), "logistic", nsv_cap=2)
    np.testing.assert_allclose(m.alpha, TRUE["alpha"], atol=0.06)
    np.testing.assert_allclose(m.beta[1:], TRUE["beta"][1:], atol=0.06)
    np.testing.assert_allclose(m.gamma[1:], TRUE["gamma"][1:], atol=0.15)


@pytest.mark.parametrize("kind", ["linear", "logistic"])
def test_analytic_gradients_match_finite_differences(kind: str) -> None:
    m = TwoDistanceModel(kind, np.array([-0.8, -0.7]), np.array([0.0, 0.3]), np.array([2.2, 1.3]))
    rng = np.random.default_rng(1)
    d = rng.uniform(20, 300, 50)
    l_m = rng.uniform(20, 200, 50)
    nsv = rng.integers(0, 3, 50)
    h = 1e-4
    fd_d = (m.predict_unclipped(d + h, l_m, nsv) - m.predict_unclipped(d - h, l_m, nsv)) / (2 * h)
    fd_l = (m.predict_unclipped(d, l_m + h, nsv) - m.predict_unclipped(d, l_m - h, nsv)) / (2 * h)
    np.testing.assert_allclose(m.grad_d(d, l_m, nsv), fd_d, rtol=1e-6, atol=1e-10)
    np.testing.assert_allclose(m.grad_l(d, l_m, nsv), fd_l, rtol=1e-6, atol=1e-10)


def test_paper_table2_preset_matches_reading() -> None:
    m = TwoDistanceModel.paper_table2()
    # READING.md: NSV = 1, d = l = 100 m gives P = -0.71 * 2 + 0.19 * 2 + 1.42 = 0.38
    assert m.predict(100.0, 100.0, 1) == pytest.approx(0.38)
    assert m.predict(5000.0, 10.0, 1) == pytest.approx(1e-3)  # clipped at p_min
    assert m.predict(1.0, 200.0, 0) == 1.0  # clipped at 1
    assert m.predict(100.0, 100.0, 9) == m.predict(100.0, 100.0, 6)  # NSV above the cap uses the cap


def test_json_round_trip(tmp_path: Path) -> None:
    m = fit_two_distance(_synthetic("logistic", n=5000), "logistic", nsv_cap=2)
    path = m.save(tmp_path / "m.json")
    back = TwoDistanceModel.load(path)
    assert back.kind == "logistic"
    np.testing.assert_array_equal(back.alpha, m.alpha)
    np.testing.assert_array_equal(back.gamma, m.gamma)
    assert back.stats[1]["instances"] == m.stats[1]["instances"]
    d, l_m = np.array([50.0, 150.0]), np.array([80.0, 30.0])
    np.testing.assert_array_equal(back.predict(d, l_m, [1, 2]), m.predict(d, l_m, [1, 2]))


def _write_checksummed(path: Path, payload: dict[str, Any]) -> None:
    """A model file as `save` writes it: ``payload`` with the SHA-256 of its content."""
    path.write_text(json.dumps({**payload, "sha256": _digest(payload)}))


def test_bad_model_files_are_clear_errors(tmp_path: Path) -> None:
    with pytest.raises(ModelError, match="does not exist"):
        TwoDistanceModel.load(tmp_path / "missing.json")
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(ModelError, match=r"bad\.json.*not valid JSON"):
        TwoDistanceModel.load(bad)
    doc = TwoDistanceModel.paper_table2().to_dict()
    _write_checksummed(tmp_path / "v9.json", {**doc, "schema_version": 9})
    with pytest.raises(ModelError, match="schema_version 9"):
        TwoDistanceModel.load(tmp_path / "v9.json")
    _write_checksummed(tmp_path / "kind.json", {**doc, "kind": "forest"})
    with pytest.raises(ModelError, match=r"kind\.json: unknown model kind 'forest'.*linear, logistic"):
        TwoDistanceModel.load(tmp_path / "kind.json")
    _write_checksummed(tmp_path / "cut.json", {**doc, "per_nsv": [{"nsv": 0, "alpha": 1.0}]})
    with pytest.raises(ModelError, match="malformed"):
        TwoDistanceModel.load(tmp_path / "cut.json")
    with pytest.raises(ModelError, match="unknown model kind"):
        fit_two_distance(_synthetic("linear", n=1000), "forest")


def test_thin_nsv_falls_back_and_says_so() -> None:
    data = _synthetic("linear", n=8000)
    keep = ~((data.nsv == 1) & (np.arange(data.nsv.size) % 200 != 0))  # leave NSV 1 with ~5 samples
    thin = FitData(data.d_m[keep], data.l_m[keep], data.nsv[keep], data.target[keep], data.group[keep])
    m = fit_two_distance(thin, "linear", nsv_cap=2, min_samples=30)
    assert m.stats[1]["fallback_from"] == 0
    assert m.stats[2]["fallback_from"] is None
    assert m.alpha[1] == m.alpha[0]
    with pytest.raises(FitError, match="no NSV value has 10000"):
        fit_two_distance(thin, "linear", nsv_cap=2, min_samples=10_000)


def test_fit_is_deterministic() -> None:
    data = _synthetic("logistic", n=8000, seed=3)
    a = fit_two_distance(data, "logistic", nsv_cap=2, seed=5).to_dict()
    b = fit_two_distance(data, "logistic", nsv_cap=2, seed=5).to_dict()
    assert a == b


def test_held_out_split_keeps_groups_whole() -> None:
    from cv2x_marl.regression.fit import holdout_mask

    group = np.repeat(np.arange(10), 100)
    test = holdout_mask(group, 0.2, seed=0)
    assert test.sum() == 200
    for g in range(10):
        assert len(set(test[group == g].tolist())) == 1
