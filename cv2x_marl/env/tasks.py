"""The benchmark's tasks (docs/benchmark.md): per task its env id, its fixed env options, the
scripted methods that apply, its ceiling, its training and held-out episode seeds, and the policies it
refuses.

    singlemover   cv2x/SingleMover-v3   one mover (Gymnasium), plan-free observation, shadowing that follows it
    cooperative   cv2x/Cooperative-v0   every vehicle moves (PettingZoo), reward = the team objective
    traffic       cv2x/Traffic-v0       vehicles drive (Gymnasium), the mover commands its speed and lane
                  (variant cv2x/Traffic-v1: the same task observing what the mover measured, :data:`VARIANTS`);
                  the control task: no causal policy beats holding the speed there
    resource      cv2x/Resource-v0      vehicles drive (PettingZoo), every vehicle that reselects picks its SPS
                  resource from its sensed candidate list; gains against ``sps`` (the standard's choice)
    (variant of cooperative: cv2x/Cooperative-v1, the same task with the coordination channel: the vehicles
     decide in the order of their transmission subframes, each seeing the moves announced before it)

The episode seeds are package constants, drawn once at import from named ``SeedSequence`` s
(:data:`PROTOCOL_ENTROPY`, the task's name, the list's kind), so they are the same on every machine
and in every version of the package; a learner trains on :attr:`Task.train_seeds` only and is scored
on :attr:`Task.heldout_seeds`, a disjoint list. The seed of an episode draws its scenario (density,
placement, SPS state: the env's ``reset(seed=...)``).

A task is available when its env id is registered (:data:`cv2x_marl.env.registry.ENV_IDS`).

This module imports numpy and the registry only (no env code).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from types import MappingProxyType
from typing import Any

from cv2x_marl.env.registry import ENV_IDS
from cv2x_marl.env.seeds import (  # noqa: F401 - the protocol's lists, re-exported with the tasks
    HELDOUT_SEEDS,
    N_HELDOUT,
    N_TRAIN,
    PROTOCOL_ENTROPY,
    TASK_NAMES,
    TRAIN_SEEDS,
    seed_list,
    training_pool,
)

#: the env ids of the tasks, in one place
TASK_ENV_IDS: Mapping[str, str] = MappingProxyType(
    {
        "singlemover": "cv2x/SingleMover-v3",
        "cooperative": "cv2x/Cooperative-v0",
        "traffic": "cv2x/Traffic-v0",
        "resource": "cv2x/Resource-v0",
    }
)
#: the control task: kept, run on request (``--tasks traffic``), not by default: within an episode a car cannot move far
#: enough relative to its receivers and interferers for its speed to matter, so no causal policy beats holding the
#: speed there (its ceiling's edge is foresight of future SPS draws); docs/benchmark.md
CONTROL_TASKS = ("traffic",)
#: tasks announced but not built yet: name -> what is missing (refused by name, never run; none today)
PENDING_TASKS: Mapping[str, str] = MappingProxyType({})
#: the fixed env options of every task: the CLI's `evaluate` defaults (paper preset, 100 steps of 5 m)
BASE_OPTIONS: Mapping[str, Any] = MappingProxyType({"preset": "paper", "max_cycles": 100, "max_step_m": 5.0})
#: the scripted methods every offset-action task runs (docs/benchmark.md)
SCRIPTED_METHODS = ("static", "random", "gbmu", "sensing")
#: the scripted methods of the resource task (its reference, ``sps``, first: the gains are against it)
RESOURCE_METHODS = ("sps", "lowest-rssi", "random", "farthest")
#: the ceiling's policy name (``--policy optimum``: the task's privileged search)
CEILING = "optimum"


@dataclass(frozen=True)
class Task:
    """One task of the benchmark.

    Attributes:
        name: the task's name (``--tasks``).
        env_id: its env id (:data:`TASK_ENV_IDS`).
        options: env options fixed by the task (passed to the env; ``--env-option`` may not change them
            in ``cv2x-marl benchmark``).
        methods: the scripted methods the benchmark runs on it, its ceiling excluded.
        ceiling: the policy whose utility gain is the task's 100 % (``share_of_optimum``).
        refused: policy name -> why the task refuses it (a policy that cannot act in its action space).
        train_seeds: training episode seeds (:data:`N_TRAIN`).
        heldout_seeds: held-out episode seeds (:data:`N_HELDOUT`), disjoint from the training ones.
    """

    name: str
    env_id: str
    options: Mapping[str, Any]
    methods: tuple[str, ...]
    ceiling: str = CEILING
    refused: Mapping[str, str] = field(default_factory=dict)
    train_seeds: tuple[int, ...] = ()
    heldout_seeds: tuple[int, ...] = ()

    @property
    def available(self) -> bool:
        """Whether the env id is registered in this version of the package."""
        return self.env_id in ENV_IDS

    def seeds(self, which: str) -> tuple[int, ...]:
        """The ``train`` or ``heldout`` list."""
        if which == "train":
            return self.train_seeds
        if which == "heldout":
            return self.heldout_seeds
        raise ValueError(f"seed list must be train or heldout, got {which!r}")

    def check_policy(self, spec: str) -> None:
        """Refuse a policy the task cannot run (:attr:`refused`), naming it, the task and the allowed ones.

        Args:
            spec: a policy name or ``ppo:PATH`` (learned models act in every task's action space they
                were trained on; the env checks the observation and action shapes when it loads them).
        """
        if spec in self.refused:
            allowed = [m for m in (*self.methods, self.ceiling) if m not in self.refused]
            raise ValueError(
                f"policy {spec!r} cannot run on task {self.name} ({self.env_id}): {self.refused[spec]}; "
                f"allowed: {', '.join(allowed)}, ppo:PATH"
            )


def make_task(
    name: str,
    env_id: str,
    methods: tuple[str, ...],
    refused: Mapping[str, str] | None = None,
    options: Mapping[str, Any] | None = None,
) -> Task:
    """A :class:`Task` with its held-out list (:data:`HELDOUT_SEEDS`) and the training list
    (:data:`TRAIN_SEEDS`, disjoint from every held-out list)."""
    return Task(
        name=name,
        env_id=env_id,
        options=MappingProxyType(dict(BASE_OPTIONS if options is None else options)),
        methods=methods,
        refused=MappingProxyType(dict(refused or {})),
        train_seeds=TRAIN_SEEDS,
        heldout_seeds=HELDOUT_SEEDS[name],
    )


#: the tasks, by name (docs/benchmark.md); the pending ones (:data:`PENDING_TASKS`) are not here
TASKS: Mapping[str, Task] = MappingProxyType(
    {
        "singlemover": make_task(
            "singlemover",
            TASK_ENV_IDS["singlemover"],
            SCRIPTED_METHODS,
            refused={"best-response": "one mover: its best response is the ceiling, run `optimum`"},
        ),
        "cooperative": make_task("cooperative", TASK_ENV_IDS["cooperative"], (*SCRIPTED_METHODS, "best-response")),
        "traffic": make_task(
            "traffic",
            TASK_ENV_IDS["traffic"],
            SCRIPTED_METHODS,
            refused={
                "best-response": "one mover: its best response is the ceiling, run `optimum`",
                **{
                    p: "it moves by position offsets and has no road version (actions are speed and lane commands)"
                    for p in ("greedy", "oracle", "planner")
                },
            },
        ),
        "resource": make_task(
            "resource",
            TASK_ENV_IDS["resource"],
            RESOURCE_METHODS,
            refused={
                p: "its action picks an SPS resource from the vehicle's candidate list, not a move"
                for p in ("static", "gbmu", "greedy", "oracle", "planner", "sensing", "best-response")
            },
            options={"max_cycles": 100},
        ),
    }
)


#: env ids that are variants of a task (the same episodes, dynamics, reward, methods and refusals; another
#: observation or another order of decisions) without being tasks of the benchmark themselves: ``evaluate --seeds
#: heldout | train`` runs the task's lists on them, so their scores compare with the task's episode by episode; the
#: lists stay the task's own (no new list, nothing else changes)
VARIANTS: Mapping[str, str] = MappingProxyType({"cv2x/Traffic-v1": "traffic", "cv2x/Cooperative-v1": "cooperative"})


def get_task(name: str, tasks: Mapping[str, Task] | None = None) -> Task:
    """The task ``name`` of ``tasks`` (default :data:`TASKS`); a pending or unknown name is refused."""
    tasks = TASKS if tasks is None else tasks
    if name in tasks:
        return tasks[name]
    if name in PENDING_TASKS:
        raise ValueError(f"task {name!r} is not available: {PENDING_TASKS[name]}; tasks: {', '.join(tasks)}")
    raise ValueError(f"unknown task {name!r}; tasks: {', '.join(tasks)}")


def task_of_env(env_id: str, tasks: Mapping[str, Task] | None = None) -> Task | None:
    """The task whose env id is ``env_id`` (None: no task's); a :data:`VARIANTS` id gets its task with
    ``env_id`` in place of the task's own."""
    table = TASKS if tasks is None else tasks
    for task in table.values():
        if task.env_id == env_id:
            return task
    if env_id in VARIANTS and VARIANTS[env_id] in table:
        return replace(table[VARIANTS[env_id]], env_id=env_id)
    return None
