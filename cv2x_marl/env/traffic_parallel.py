"""``cv2x/Traffic-v0`` and ``cv2x/Traffic-v1`` as PettingZoo ParallelEnvs (the Gymnasium classes are in
:mod:`cv2x_marl.env.single`)."""

from __future__ import annotations

from typing import Any, ClassVar

from cv2x_marl.env.mobility_env import MobilityEnv
from cv2x_marl.env.options import TRAFFIC_DEFAULTS, TRAFFIC_V1_DEFAULTS


class TrafficParallelEnv(MobilityEnv):
    """``cv2x/Traffic-v0`` as a PettingZoo ParallelEnv: :class:`MobilityEnv` with :data:`TRAFFIC_DEFAULTS`, every
    vehicle an agent; ``movers`` (default ``[0]``: the Gymnasium id's task) drive with their own speed and lane
    commands, ``movers=None`` makes every vehicle drive; each agent is rewarded with its own period's eq. 12
    utility per target receiver; keyword arguments as :class:`MobilityEnv`."""

    metadata: ClassVar[dict[str, Any]] = {**MobilityEnv.metadata, "name": "cv2x_traffic_v0"}

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**{**TRAFFIC_DEFAULTS, "movers": [0], **kwargs})


class TrafficParallelEnvV1(TrafficParallelEnv):
    """``cv2x/Traffic-v1`` as a PettingZoo ParallelEnv: :class:`TrafficParallelEnv` with
    :data:`~cv2x_marl.env.options.TRAFFIC_V1_DEFAULTS` (observation version 4: what each agent measured on the
    road); keyword arguments as :class:`MobilityEnv`."""

    metadata: ClassVar[dict[str, Any]] = {**MobilityEnv.metadata, "name": "cv2x_traffic_v1"}

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**{**TRAFFIC_V1_DEFAULTS, **kwargs})
