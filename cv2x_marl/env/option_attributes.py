"""The env's options as attributes of the env class, from the schema (:class:`~cv2x_marl.env.options.EnvOptions`):
``env.max_cycles`` is ``env.options.max_cycles``. Setting one on a live env checks the new value with the schema and
replaces the env's options (PettingZoo's API test sets ``max_cycles``), except the options that shape the env's
spaces, parts or agents at construction (:data:`STRUCTURAL_OPTIONS`), which are refused: a new value is a new env.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from cv2x_marl.env.options import EnvOptions, options_signature

#: options that shape the env's spaces, parts or agents at construction (setting one is refused)
STRUCTURAL_OPTIONS = (
    "preset", "overrides", "mode", "movers", "n_neighbours", "scale_m", "observation", "privileged", "action_mode",
    "traffic_action", "speed_command", "drive_observation", "episode_metrics",
    "decision_order",
)  # fmt: skip


def option_attribute(name: str) -> property:
    """``env.<name>``: the option (``env.options.<name>``); setting it checks the new value with the schema and
    replaces the env's options, unless the option is one of :data:`STRUCTURAL_OPTIONS`."""

    def get(env: Any) -> Any:
        return getattr(env.options, name)

    def put(env: Any, value: Any) -> None:
        if name in STRUCTURAL_OPTIONS:
            raise AttributeError(
                f"{name} shapes the env's spaces and parts, fixed at construction; make a new env with {name}={value!r}"
            )
        env.options = dataclasses.replace(env.options, **{name: value})

    return property(get, put, doc=f"The ``{name}`` option.")


def install_options(cls: type, own: tuple[str, ...]) -> None:
    """Give ``cls`` a property per option (but those in ``own``, which the class holds itself) and the constructor
    signature ``(options=None, *, <every option>=<its default>)`` for ``help()``."""
    for f in dataclasses.fields(EnvOptions):
        if f.name not in own:
            setattr(cls, f.name, option_attribute(f.name))
    cls.__init__.__signature__ = options_signature()  # type: ignore[misc]
