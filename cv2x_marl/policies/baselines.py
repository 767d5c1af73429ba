"""Baseline files: one YAML file per scripted baseline in ``baselines/``, read and turned into a policy.

A baseline file names a scripted policy and its settings::

    # GBMU, the paper's algorithm (steps 1-5), steered by the paper's Table 2 model
    policy: gbmu            # static | random | greedy | gbmu | oracle | planner | sensing | optimum
    model: paper-table2     # two-distance model (gbmu, greedy, planner): paper-table2, a shipped
                            # model (linear-fit, logistic-fit) or a model file / fit folder
    delta: 100.0            # step size per env step (gbmu, greedy, oracle)
    step_schedule: constant # gbmu, greedy: constant (the paper) | decay | backtracking
    decay_k0: 100.0         # step_schedule decay: delta_k = delta / (1 + k / decay_k0), k = env step
    env_id: cv2x/SingleMover-v2   # the env it runs on when --env is not given
    env: {}                 # env arguments (e.g. replan_every for sensing on Mobility-v2)

The shipped models (:data:`~cv2x_marl.regression.model.SHIPPED_MODELS`, package data
``cv2x_marl/regression/data/NAME.json``) were fitted on the same stage-1 data, the paper preset's
``cv2x-marl dataset --runs 10 --seed 0``, by ``cv2x-marl fit --model linear`` and ``--model logistic``
(the command is in each file's provenance). The step schedules are
:class:`~cv2x_marl.policies.gbmu.StepSchedule`'s.

``cv2x-marl evaluate --policy baselines/gbmu.yaml`` runs one; ``cv2x-marl baselines`` runs all of a
folder on the same held-out episodes (:mod:`cv2x_marl.experiments.baselines`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from cv2x_marl.checks import is_real
from cv2x_marl.env.registry import ENV_IDS
from cv2x_marl.policies.base import Policy
from cv2x_marl.policies.gbmu import SCHEDULES, StepSchedule
from cv2x_marl.policies.registry import MODELLED, SCRIPTED, make_policy
from cv2x_marl.policies.scripted import GbmuPolicy
from cv2x_marl.regression.model import PAPER_MODEL, SHIPPED_MODELS, load_model, resolve_model
from cv2x_marl.yamlcore import load_mapping

if TYPE_CHECKING:
    from cv2x_marl.env.mobility_env import MobilityEnv

KEYS = ("policy", "model", "delta", "step_schedule", "decay_k0", "env_id", "env", "description")
#: the policies that take a step schedule
SCHEDULED = ("gbmu", "greedy")
#: the file name endings of a baseline file
SUFFIXES = (".yaml", ".yml", ".json")


#: the env of a baseline file without ``env_id``: the one the baselines table (``baselines/results.md``) was made on
BASELINE_ENV_ID = "cv2x/SingleMover-v2"


@dataclass(frozen=True)
class Baseline:
    """One baseline file, validated."""

    name: str
    policy: str
    model: str = PAPER_MODEL
    delta: float = 100.0
    env_id: str = BASELINE_ENV_ID
    env: dict[str, Any] = field(default_factory=dict)
    description: str = ""
    step_schedule: str = "constant"
    decay_k0: float = 100.0

    def schedule(self) -> StepSchedule | None:
        """The GBMU step schedule (None: the paper's constant step)."""
        if self.step_schedule == "constant":
            return None
        return StepSchedule(self.step_schedule, decay_k0=self.decay_k0)


def is_baseline_file(spec: str) -> bool:
    """Whether a ``--policy`` value names a baseline file rather than a policy."""
    return spec.endswith(SUFFIXES)


def load_baseline(path: str | Path) -> Baseline:
    """Read and validate a baseline file; errors name the file, the key and the allowed values."""
    path = Path(path)
    data = load_mapping(path, "baseline file", ValueError)
    bad = sorted(set(data) - set(KEYS))
    if bad:
        raise ValueError(f"baseline file {path}: unknown key(s) {bad}; keys: {', '.join(KEYS)}")
    policy = data.get("policy")
    if policy not in SCRIPTED:
        raise ValueError(f"baseline file {path}: policy must be one of {', '.join(SCRIPTED)}, got {policy!r}")
    delta = data.get("delta", 100.0)
    if not is_real(delta) or delta <= 0:
        raise ValueError(f"baseline file {path}: delta must be a finite number > 0, got {delta!r}")
    env_id = data.get("env_id", BASELINE_ENV_ID)
    if env_id not in ENV_IDS:
        raise ValueError(f"baseline file {path}: env_id must be one of {', '.join(ENV_IDS)}, got {env_id!r}")
    env = data.get("env", {}) or {}
    if not isinstance(env, dict):
        raise ValueError(f"baseline file {path}: env must be a mapping of env arguments, got {env!r}")
    model = data.get("model", PAPER_MODEL)
    if not isinstance(model, str):
        raise ValueError(
            f"baseline file {path}: model must be paper-table2, {', '.join(SHIPPED_MODELS)} or a model file, "
            f"got {model!r}"
        )
    if policy in MODELLED:  # the model is read now, so a missing one names this file too
        try:
            load_model(resolve_model(model))
        except (ValueError, OSError) as exc:
            raise ValueError(f"baseline file {path}: model {model!r}: {exc}") from None
    schedule = data.get("step_schedule", "constant")
    if schedule not in SCHEDULES:
        raise ValueError(f"baseline file {path}: step_schedule must be one of {', '.join(SCHEDULES)}, got {schedule!r}")
    if schedule != "constant" and policy not in SCHEDULED:
        raise ValueError(
            f"baseline file {path}: step_schedule applies to policies {', '.join(SCHEDULED)} only, not {policy!r}"
        )
    k0 = data.get("decay_k0", 100.0)
    if not is_real(k0) or not math.isfinite(k0) or k0 <= 0:
        raise ValueError(f"baseline file {path}: decay_k0 must be a finite number > 0 (env steps), got {k0!r}")
    return Baseline(
        path.stem,
        policy,
        model,
        float(delta),
        env_id,
        dict(env),
        str(data.get("description", "")),
        str(schedule),
        float(k0),
    )


def make_baseline_policy(spec: Baseline, env: MobilityEnv) -> Policy:
    """The policy a baseline file describes, for ``env`` (its model resolved, its step schedule set)."""
    model = resolve_model(spec.model)
    if spec.policy in SCHEDULED:
        return GbmuPolicy(
            load_model(model), env.layout, env.max_step_m, spec.delta, spec.policy == "gbmu", spec.schedule()
        )
    return make_policy(spec.policy, env, model, spec.delta)


def baseline_files(folder: str | Path) -> list[Path]:
    """The baseline files of a folder, by name."""
    folder = Path(folder)
    if not folder.is_dir():
        if folder.exists():
            raise ValueError(f"baselines folder {folder} is a file, not a folder of baseline files (*.yaml)")
        raise ValueError(f"baselines folder {folder} does not exist")
    files = sorted(p for p in folder.iterdir() if p.suffix in SUFFIXES and p.name != "results.json")
    if not files:
        raise ValueError(f"no baseline files (*.yaml) in {folder}")
    return files
