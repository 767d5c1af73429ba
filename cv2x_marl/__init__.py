"""cv2x_marl: controlled mobility in C-V2X sidelink Mode 4 networks.

Importing the package registers ``cv2x/Mobility-v0``, ``-v1``, ``-v2`` with PettingZoo and
``cv2x/SingleMover-v0``, ``-v1``, ``-v2`` with Gymnasium (both are base dependencies; the simulator
itself, ``cv2x_marl.sim``, never imports them): at once in a package already imported, else when it
is imported (an import hook), so importing ``cv2x_marl`` alone does not import either. The ids, their
factories and the registration are :mod:`cv2x_marl.env.registry`'s. Entry points are import strings,
so a fresh process (a Ray worker, a subprocess) resolves the Gymnasium ids with
``gymnasium.make("cv2x_marl:cv2x/SingleMover-v2")``, which imports the package first;
``gymnasium.make_vec(id, num_envs=K, vectorization_mode="vector_entry_point")`` gives K copies
stepped by one compiled call (:mod:`cv2x_marl.env.vector`); PettingZoo has no such syntax:
frameworks take the factories ``cv2x_marl.env.parallel_env`` / ``parallel_env_v1`` / ``parallel_env_v2`` instead.
"""

__version__ = "0.1.0"

from cv2x_marl.env.registry import register_envs

register_envs()
