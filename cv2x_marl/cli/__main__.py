"""``python -m cv2x_marl.cli``: the ``cv2x-marl`` command."""

from cv2x_marl.cli import console

console()
