"""Mobility policies: GBMU (Sec. 5), the greedy eq. 9 variant and the true-gradient oracle."""

from cv2x_marl.policies.gbmu import ClimbResult, GbmuInputs, climb, gbmu_direction, oracle_direction

__all__ = ["ClimbResult", "GbmuInputs", "climb", "gbmu_direction", "oracle_direction"]
