"""The C-V2X sidelink Mode 4 network simulator (no RL and no plotting imports)."""

from cv2x_marl.sim.simulator import LINK_COLUMNS, RunResult, Simulator, Snapshot

__all__ = ["LINK_COLUMNS", "RunResult", "Simulator", "Snapshot"]
