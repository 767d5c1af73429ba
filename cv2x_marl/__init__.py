"""cv2x_marl: controlled mobility in C-V2X sidelink Mode 4 networks."""

__version__ = "0.1.0"
