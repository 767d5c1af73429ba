"""The C-V2X sidelink Mode 4 network simulator (no RL and no plotting imports)."""

from cv2x_marl.sim.chunk import LINK_COLUMNS
from cv2x_marl.sim.simulator import RunResult, Simulator
from cv2x_marl.sim.snapshot import Snapshot

__all__ = ["LINK_COLUMNS", "RunResult", "Simulator", "Snapshot"]
