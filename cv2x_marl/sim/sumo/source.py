"""The mobility source of a scenario (``vehicles.mobility`` = ``sumo`` or ``trace``): checked at
simulator construction, started at reset (issue 14)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cv2x_marl.config import ConfigError, ScenarioConfig
from cv2x_marl.sim.sumo.lockstep import SumoLockstep
from cv2x_marl.sim.sumo.network import check_generated
from cv2x_marl.sim.sumo.scenario import build_scenario, check_sumocfg
from cv2x_marl.sim.sumo.tools import import_libsumo, sumo_home
from cv2x_marl.sim.sumo.trace import TraceReplay

MobilitySource = SumoLockstep | TraceReplay


def check_source(cfg: ScenarioConfig) -> None:
    """Fail early (at simulator construction) on a source that cannot work: SUMO not installed,
    a missing or broken ``.sumocfg`` or trace file, a road without a generated network."""
    mob = cfg.vehicles.mobility
    if mob == "sumo":
        sumo_home()
        import_libsumo()
        if cfg.vehicles.sumo_config is not None:
            check_sumocfg(cfg.vehicles.sumo_config)
        else:
            check_generated(cfg)
    elif mob == "trace":
        assert cfg.vehicles.trace_file is not None  # the config checks it
        p = Path(cfg.vehicles.trace_file).expanduser()
        if not p.is_file():
            raise ConfigError(f"vehicles.trace_file: {cfg.vehicles.trace_file!r} does not exist or is not a file")


def open_source(cfg: ScenarioConfig, rng: np.random.Generator) -> MobilitySource:
    """The mobility source of ``cfg`` (``vehicles.mobility`` = ``sumo`` or ``trace``), started.

    Args:
        cfg: the scenario.
        rng: the simulator's ``mobility`` stream (SUMO: seed and generated demand).
    """
    step_s = cfg.traffic.rri_ms / 1000.0
    is_open = cfg.vehicles.population == "open"
    if cfg.vehicles.mobility == "trace":
        assert cfg.vehicles.trace_file is not None
        return TraceReplay(cfg.vehicles.trace_file, cfg.n_slots, step_s, cfg.sumo_begin_s, is_open)
    return SumoLockstep(build_scenario(cfg, rng), cfg.n_slots, begin_s=cfg.sumo_begin_s, open_population=is_open)
