"""The options each env id fixes (the rows of :data:`~cv2x_marl.env.registry.SPECS` name their set): plain data,
importable without the env (the registry reads it for the CLI's ``--env`` choices without importing numba)."""

from __future__ import annotations

from typing import Any

#: what ``cv2x/Mobility-v1`` and ``cv2x/SingleMover-v1`` change from the v0 defaults (any can be overridden)
V1_DEFAULTS: dict[str, Any] = {"observation": 1, "reward_form": "improvement", "normalise_reward": True}
#: what ``cv2x/Mobility-v2`` and ``cv2x/SingleMover-v2`` change from the v0 defaults: observation
#: version 2 (the plan from the mover's sensing estimate), improvement rewards per target receiver
V2_DEFAULTS: dict[str, Any] = {**V1_DEFAULTS, "observation": 2}
#: what ``cv2x/Mobility-v3`` and ``cv2x/SingleMover-v3`` change from the v0 defaults: v2's rewards, the
#: plan-free observation version 3 (measurements) and shadowing that follows the vehicles
V3_DEFAULTS: dict[str, Any] = {**V1_DEFAULTS, "observation": 3, "shadow_field": True}
#: ``cv2x/Cooperative-v0``: v3 with every vehicle moving for the team objective
COOPERATIVE_DEFAULTS: dict[str, Any] = {**V3_DEFAULTS, "reward": "team"}
#: ``cv2x/Cooperative-v1``: Cooperative-v0 with the coordination channel: the AEC API takes the vehicles in the
#: order of their transmission subframes, each observing the moves announced earlier in the period
COOPERATIVE_V1_DEFAULTS: dict[str, Any] = {**COOPERATIVE_DEFAULTS, "decision_order": "subframe"}
#: ``cv2x/Traffic-v0``: vehicles drive the lane model, the mover commands its speed and lane, the reward is the
#: period's utility per target receiver, the observation is v0's block plus the driving entries, and the infos
#: carry the episode's means
TRAFFIC_DEFAULTS: dict[str, Any] = {
    "mode": "traffic",
    "traffic_action": "speed",
    "normalise_reward": True,
    "drive_observation": True,
    "episode_metrics": True,
}
#: ``cv2x/Traffic-v1``: Traffic-v0 with observation version 4, what the mover measured on the road (RSRP over its
#: sensing window, the SCIs it decoded, its own SPS state; :mod:`cv2x_marl.env.traffic_measurement`)
TRAFFIC_V1_DEFAULTS: dict[str, Any] = {**TRAFFIC_DEFAULTS, "observation": 4}
#: ``cv2x/Resource-v0``'s SPS on the paper's grid (``preset="paper"``): the standard's procedures (TS 36.213 14.1.1.6:
#: the 3GPP rule's list of ``ceil(0.2 M)`` lowest-S-RSSI survivors, SCIs of a vehicle about to reselect reserve
#: nothing, SCIs decoded by SINR and gating the PSSCH) with the selection window T2 = 20 (the standard's shortest for
#: a 100-ms period: 40 candidates on two sub-channels), reselections at the period's end (the paper preset's)
RESOURCE_OVERRIDES: tuple[str, ...] = (
    "sps.selection=3gpp",
    "sps.selection_window_subframes=20",
    "sps.reservation_signalling=standard",
    "sps.sci_decoding=sinr",
    "sps.sci_gates_pssch=true",
)
#: ``cv2x/Resource-v0``: vehicles drive and every vehicle that reselects its SPS resource picks it from its candidate
#: list (:mod:`cv2x_marl.env.resource`): observation version 5, the period's utility per target receiver as the
#: reward, the episode's means in the infos; the paper's grid (21 vehicles driving) with the standard's SPS
#: procedures (:data:`RESOURCE_OVERRIDES`), the vehicles deciding at the period's end
RESOURCE_DEFAULTS: dict[str, Any] = {
    "preset": "paper",
    "overrides": RESOURCE_OVERRIDES,
    "mode": "traffic",
    "traffic_action": "resource",
    "observation": 5,
    "normalise_reward": True,
    "episode_metrics": True,
}
#: the defaults of each env version (v0: :class:`EnvOptions`' own; ``cooperative-v0`` / ``-v1``:
#: ``cv2x/Cooperative-v0`` / ``-v1``; ``traffic-v0``, ``traffic-v1``: ``cv2x/Traffic-v0``, ``cv2x/Traffic-v1``)
VERSION_DEFAULTS: dict[str, dict[str, Any]] = {
    "v0": {},
    "v1": V1_DEFAULTS,
    "v2": V2_DEFAULTS,
    "v3": V3_DEFAULTS,
    "cooperative-v0": COOPERATIVE_DEFAULTS,
    "cooperative-v1": COOPERATIVE_V1_DEFAULTS,
    "traffic-v0": TRAFFIC_DEFAULTS,
    "traffic-v1": TRAFFIC_V1_DEFAULTS,
    "resource-v0": RESOURCE_DEFAULTS,
}
