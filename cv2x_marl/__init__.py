"""cv2x_marl: controlled mobility in C-V2X sidelink Mode 4 networks.

Importing the package registers ``cv2x/Mobility-v0``, ``-v1``, ``-v2`` with PettingZoo and
``cv2x/SingleMover-v0``, ``-v1``, ``-v2`` with Gymnasium (both are base dependencies; the simulator
itself, ``cv2x_marl.sim``, never imports them). Entry points are import strings, so a fresh process
(a Ray worker, a subprocess) resolves the Gymnasium ids with ``gymnasium.make("cv2x_marl:cv2x/
SingleMover-v2")``, which imports the package first; ``gymnasium.make_vec(id, num_envs=K,
vectorization_mode="vector_entry_point")`` gives K copies stepped by one compiled call
(:mod:`cv2x_marl.env.vector`); PettingZoo has no such syntax: frameworks take
the factories ``cv2x_marl.env.parallel_env`` / ``parallel_env_v1`` / ``parallel_env_v2`` instead.
"""

__version__ = "0.1.0"


def _register_envs() -> None:
    try:
        import gymnasium
        import pettingzoo
    except ImportError:  # pragma: no cover - base dependencies; a broken install registers nothing
        return
    for version in ("v0", "v1", "v2"):
        env_id = f"cv2x/Mobility-{version}"
        suffix = "" if version == "v0" else f"_{version}"
        for kind, entry in (("parallel", f"cv2x_marl.env:parallel_env{suffix}"), ("aec", f"cv2x_marl.env:env{suffix}")):
            registry = pettingzoo.parallel_registry if kind == "parallel" else pettingzoo.aec_registry
            if env_id not in registry:
                pettingzoo.register(kind, env_id, entry_point=entry)
    for version, cls in (("v0", "SingleMoverEnv"), ("v1", "SingleMoverEnvV1"), ("v2", "SingleMoverEnvV2")):
        if f"cv2x/SingleMover-{version}" not in gymnasium.registry:
            gymnasium.register(
                id=f"cv2x/SingleMover-{version}",
                entry_point=f"cv2x_marl.env.single:{cls}",
                vector_entry_point=f"cv2x_marl.env.vector:{cls.replace('Env', 'VectorEnv')}",
            )


_register_envs()
