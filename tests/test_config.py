"""Configuration: validation by key name, presets, overrides, docs in sync."""

import json
from pathlib import Path

import pytest

from cv2x_marl.config import (
    LEGACY_MODE4,
    ConfigError,
    apply_overrides,
    config_markdown,
    from_dict,
    load_config_file,
    preset,
    to_dict,
)

REQUIRED_KEYS = [
    "road.kind",
    "road.length_m",
    "road.lanes_per_direction",
    "vehicles.n_vehicles",
    "vehicles.density_veh_per_m",
    "vehicles.placement",
    "radio.tx_power_dbm",
    "radio.carrier_hz",
    "radio.noise_dbm",
    "radio.noise_figure_db",
    "radio.sensitivity_dbm",
    "channel.pathloss",
    "channel.effective_height_m",
    "channel.los",
    "channel.shadowing_std_db",
    "channel.fading",
    "traffic.rri_ms",
    "traffic.packet_bytes",
    "sps.n_subchannels",
    "sps.selection_window_subframes",
    "sps.keep_probability",
    "sps.selection",
    "link.model",
    "link.per_curve",
    "metrics.prr_bin_m",
    "metrics.interferer_range_m",
]


def test_required_keys_exist() -> None:
    flat = {f"{s}.{k}" for s, keys in to_dict(preset("paper")).items() for k in keys}
    assert set(REQUIRED_KEYS) <= flat


def test_paper_preset_is_table_1() -> None:
    cfg = preset("paper")
    assert cfg.n_vehicles == 21
    assert cfg.radio.tx_power_dbm == 26.0
    assert cfg.radio.carrier_hz == 2e9
    assert cfg.radio.noise_dbm == -112.45 and cfg.radio.noise_figure_db == 9.0
    assert cfg.sps.n_subchannels == 2 and cfg.sps.selection_window_subframes == 8
    assert cfg.sim.n_subframes == 10240
    assert cfg.metrics.interferer_range_m == 200.0
    assert cfg.channel.pathloss == "winner_b1"


def test_highway_preset_density() -> None:
    cfg = preset("highway")
    assert cfg.road.kind == "highway"
    assert cfg.n_vehicles == 200  # 0.1 veh/m on 2 km


def test_defaults_are_the_standard_and_legacy_mode4_is_their_complement() -> None:
    """The defaults are the standard's value of every issue 13 fidelity switch; ``LEGACY_MODE4`` holds the
    simplified value of exactly those keys, and ``highway`` differs from ``highway-legacy`` in exactly them
    (docs/model.md)."""
    standard = {
        ("sps", "reservation_signalling"): "standard",
        ("sps", "reselection_timing"): "per_ue",
        ("sps", "sci_decoding"): "sinr",
        ("sps", "sci_gates_pssch"): True,
        ("link", "per_interpolation"): "log",
        ("link", "inband_emission_model"): "3gpp",
        ("channel", "shadowing_correlation"): "pair_distance",
        ("sim", "warmup_mode"): "until_reselected",
    }
    defaults = to_dict(from_dict({}))
    assert {key: defaults[key[0]][key[1]] for key in standard} == standard
    assert {(sec, k) for sec, keys in LEGACY_MODE4.items() for k in keys} == set(standard)
    std, legacy = to_dict(preset("highway")), to_dict(preset("highway-legacy"))
    differs = {(sec, k): v for sec, keys in std.items() for k, v in keys.items() if legacy[sec][k] != v}
    assert differs == standard
    assert to_dict(preset("highway-3gpp")) == std  # the former name of the standard highway


@pytest.mark.parametrize("name", ["paper", "highway-legacy", "highway", "highway-3gpp", "sumo-grid", "sumo-grid-trips"])
def test_presets_resolve_as_before_the_defaults_flipped(name: str) -> None:
    """Every key a preset had at 685db59 (before the flip; tests/data/presets_685db59.json, recorded from
    that commit's ``to_dict(preset(...))`` under today's names) keeps its value: the paper presets, the env
    and the shipped models run what they ran."""
    recorded = json.loads((Path(__file__).parent / "data" / "presets_685db59.json").read_text())["presets"][name]
    now = to_dict(preset(name))
    changed = {
        f"{sec}.{k}": (v, now[sec][k]) for sec, keys in recorded.items() for k, v in keys.items() if now[sec][k] != v
    }
    assert changed == {}


def test_sumo_highway_follows_highway_to_the_standard_procedures() -> None:
    """``sumo-highway`` is the highway with SUMO traffic: at 685db59 it took the simplified procedures of the
    then ``highway``, now the standard's; it changed in exactly the eight switches, each to ``highway``'s value."""
    recorded = json.loads((Path(__file__).parent / "data" / "presets_685db59.json").read_text())["presets"]
    now, hw = to_dict(preset("sumo-highway")), to_dict(preset("highway"))
    changed = {(sec, k) for sec, keys in recorded["sumo-highway"].items() for k, v in keys.items() if now[sec][k] != v}
    assert changed == {(sec, k) for sec, keys in LEGACY_MODE4.items() for k in keys}
    assert all(now[sec][k] == hw[sec][k] for sec, k in changed)


@pytest.mark.parametrize(
    ("override", "culprit", "allowed"),
    [
        ("sps.keep_probability=0.95", "sps.keep_probability", "[0, 0.8]"),
        ("road.kind=ring", "road.kind", "grid | highway"),
        ("link.model=magic", "link.model", "per_table | rayleigh | threshold"),
        ("vehicles.n_vehicles=1", "vehicles.n_vehicles", "[2, 100000]"),
        ("sps.n_subchannels=2.5", "sps.n_subchannels", "integer"),
        ("radio.tx_power_dbm=hot", "radio.tx_power_dbm", "number"),
        ("metrics.prr_bin_m=0", "metrics.prr_bin_m", "(0, 1000]"),
    ],
)
def test_invalid_values_rejected_by_name(override: str, culprit: str, allowed: str) -> None:
    with pytest.raises(ConfigError) as err:
        apply_overrides(preset("paper"), [override])
    assert culprit in str(err.value) and allowed in str(err.value)


def test_unknown_keys_and_sections_rejected_by_name() -> None:
    with pytest.raises(ConfigError, match=r"sps\.rsrp_treshold_dbm.*rsrp_threshold_dbm"):
        from_dict({"sps": {"rsrp_treshold_dbm": -100}})
    with pytest.raises(ConfigError, match="radios"):
        from_dict({"radios": {}})
    with pytest.raises(ConfigError, match=r"section.key=value"):
        apply_overrides(preset("paper"), ["keep_probability=0.1"])


def test_cross_key_checks() -> None:
    with pytest.raises(ConfigError, match=r"channel.fading"):
        apply_overrides(preset("paper"), ["link.model=rayleigh"])
    with pytest.raises(ConfigError, match=r"traffic.rri_ms"):
        apply_overrides(preset("paper"), ["sps.selection_window_subframes=150"])
    with pytest.raises(ConfigError, match="p_straight"):
        apply_overrides(preset("paper"), ["road.p_left=0.5"])


def test_overrides_and_files(tmp_path: Path) -> None:
    cfg = apply_overrides(
        preset("paper"), ["sps.n_subchannels=4", "radio.sensitivity_dbm=-95", "channel.fading=rayleigh"]
    )
    assert cfg.sps.n_subchannels == 4 and cfg.radio.sensitivity_dbm == -95.0 and cfg.channel.fading == "rayleigh"
    f = tmp_path / "c.yaml"
    f.write_text("preset: highway\nsps:\n  keep_probability: 0.4\n")
    cfg = load_config_file(f)
    assert cfg.road.kind == "highway" and cfg.sps.keep_probability == 0.4
    bad = tmp_path / "bad.yaml"
    bad.write_text("sps: [1, 2\n")
    with pytest.raises(ConfigError, match=r"bad.yaml"):
        load_config_file(bad)
    assert from_dict(to_dict(cfg)) == cfg  # round trip


def test_docs_config_md_is_current() -> None:
    doc = Path(__file__).resolve().parents[1] / "docs" / "config.md"
    assert doc.read_text() == config_markdown(), "docs/config.md is stale: run `make docs`"
