"""Optional dependencies: which extra brings what, and the error that names it.

The base install (``pip install cv2x_marl``) is the simulator and the envs (numpy, numba, scipy,
gymnasium, pettingzoo, ...). Training and loading learned movers need the ``train`` extra (torch,
stable-baselines3, tensorboard); sweeps and ``dataset --ray`` need the ``ray`` extra (Ray Tune and
RLlib); the TorchRL example the ``torchrl`` extra; SUMO mobility (``vehicles.mobility=sumo``) the
``sumo`` extra (eclipse-sumo, libsumo, sumolib, traci); ``make install`` installs every extra under ``constraints.txt``.
"""

from __future__ import annotations

import importlib
from types import ModuleType

#: the extra that provides each optional top-level module
EXTRA_OF = {
    "torch": "train",
    "stable_baselines3": "train",
    "sb3_contrib": "train",
    "tensorboard": "train",
    "pandas": "train",
    "ray": "ray",
    "torchrl": "torchrl",
    "sumo": "sumo",
    "libsumo": "sumo",
    "sumolib": "sumo",
    "traci": "sumo",
}


class MissingExtraError(ImportError):
    """An optional dependency is not installed; the message names the extra to install."""


def missing_extra(module: str, what: str, exc: ImportError | None = None) -> MissingExtraError:
    """The error for ``what`` needing ``module`` (``exc``: the ImportError that revealed it)."""
    extra = EXTRA_OF.get(module.split(".")[0], "train")
    detail = f" ({exc})" if exc is not None else ""
    return MissingExtraError(
        f"{what} needs {module}, which the base install leaves out{detail}; "
        f"install the {extra!r} extra: pip install 'cv2x_marl[{extra}]'"
    )


def require(module: str, what: str) -> ModuleType:
    """Import ``module`` or raise :class:`MissingExtraError` naming the extra that provides it."""
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise missing_extra(module, what, exc) from exc
