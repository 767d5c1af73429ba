"""The episode state of :class:`~cv2x_marl.env.mobility_env.MobilityEnv`, named: what its parts read and write.

The parts (:mod:`~cv2x_marl.env.observation_models`, :mod:`~cv2x_marl.env.dynamics`, :mod:`~cv2x_marl.env.rewards`,
:mod:`~cv2x_marl.env.mover_step`, :mod:`~cv2x_marl.env.infos`) sit below the env class that holds them, so they
type the env as :class:`EpisodeEnv`, this protocol, and the env satisfies it (mypy checks each call).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
from numpy.typing import NDArray

from cv2x_marl.env.planning import PlanningEnv

if TYPE_CHECKING:
    from cv2x_marl.config import ScenarioConfig
    from cv2x_marl.env.measurement import Measurements
    from cv2x_marl.env.options import EnvOptions
    from cv2x_marl.sim import Simulator
    from cv2x_marl.sim.ground_truth import PairGeometry
    from cv2x_marl.sim.snapshot import Snapshot

FloatArray = NDArray[np.float64]


class EpisodeEnv(PlanningEnv, Protocol):
    """The env as its parts see it (besides :class:`~cv2x_marl.env.planning.PlanningEnv`'s positions, reach and
    plan).

    Attributes:
        n: vehicles; config, options: the scenario and the env's options.
        sim, snapshot: the simulator and the episode's stage-1 snapshot.
        resource: [N] SPS resources; offsets_m: [N, 2] traffic mode's radio offsets (m).
        link_p, target: [N(tx), N(rx)] link success and target receivers now.
        utility, prr, jain, target_count, u0, prr0: [N] the eq. 12 utility, PRR, Jain's index, target receivers
            now, utility and PRR at the start.
        u_sum, prr_sum, jain_sum: [N] sums over the episode's steps.
        geometry: the pair geometry now; co_table: the co-channel table of the resources; rx_dbm: [N, N] mean
            received powers (observation models with ``needs_rx``).
        own: the own state (observation versions >= 1), measure / traffic_measure: the measurements (3, 4).
        observer, dynamics, rewarder: the parts.
        agents, possible_agents, agent_index, _live, mover_mask: the agents now, all of them, their vehicle
            indices, the names that must act this step, who moves.
        pending: ``traffic_action="resource"``: the decisions of the coming step
            (:class:`~cv2x_marl.env.resource.PendingChoices`).
        step_scale_m: [N] the step of a full action (m); drift_m: the drift bound (inf: none); horizon: steps.
    """

    n: int
    config: ScenarioConfig
    options: EnvOptions
    sim: Simulator
    snapshot: Snapshot
    resource: NDArray[np.int64]
    offsets_m: FloatArray
    link_p: FloatArray
    target: NDArray[np.bool_]
    utility: FloatArray
    prr: FloatArray
    jain: FloatArray
    target_count: NDArray[np.int64]
    u0: FloatArray
    prr0: FloatArray
    u_sum: FloatArray
    prr_sum: FloatArray
    jain_sum: FloatArray
    tracks: list[FloatArray]
    geometry: PairGeometry | None
    co_table: NDArray[np.int64] | None
    rx_dbm: FloatArray
    own: Any
    measure: Measurements
    traffic_measure: Any
    observer: Any
    dynamics: Any
    rewarder: Any
    model: Any
    step_scale_m: FloatArray
    drift_m: float
    horizon: int
    wrap_road: Any
    possible_agents: list[str]
    agents: list[str]
    agent_index: dict[str, int]
    mover_mask: NDArray[np.bool_]
    _live: set[str]
    pending: Any
    info_keys: tuple[str, ...]
    mover_links: Any
    mover_rows: NDArray[np.int64]
    normalise_reward: bool
    truth_los: str
    replan_every: int | None
    render_mode: str | None

    @property
    def reward_kind(self) -> str: ...

    @property
    def model_name(self) -> str: ...

    @property
    def fast_mover(self) -> int | None: ...

    def build(self, rows: NDArray[np.int64] | None = None) -> NDArray[np.float32]: ...

    def reach_m(self) -> float: ...

    def finish(self) -> None: ...
