"""cv2x_marl: controlled mobility in C-V2X sidelink Mode 4 networks.

Importing the package registers ``cv2x/Mobility-v0`` with PettingZoo and ``cv2x/SingleMover-v0``
with Gymnasium when those (the ``train`` extra) are installed; the simulator itself
(``cv2x_marl.sim``) never imports them.
"""

__version__ = "0.1.0"


def _register_envs() -> None:
    try:
        import gymnasium
        import pettingzoo
    except ImportError:  # the train extra is not installed: nothing to register
        return
    for kind, entry in (("parallel", "cv2x_marl.env:parallel_env"), ("aec", "cv2x_marl.env:env")):
        registry = pettingzoo.parallel_registry if kind == "parallel" else pettingzoo.aec_registry
        if "cv2x/Mobility-v0" not in registry:
            pettingzoo.register(kind, "cv2x/Mobility-v0", entry_point=entry)
    if "cv2x/SingleMover-v0" not in gymnasium.registry:
        gymnasium.register(id="cv2x/SingleMover-v0", entry_point="cv2x_marl.env.single:SingleMoverEnv")


_register_envs()
