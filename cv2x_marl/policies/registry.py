"""Policies by name: what ``--policy NAME`` builds for an env (:func:`make_policy`).

    static | random     :mod:`cv2x_marl.policies.base` (no model)
    gbmu | greedy       :class:`~cv2x_marl.policies.scripted.GbmuPolicy` on a two-distance model
                        (gbmu: the paper's steps 1-5 with its fairness term; greedy: eq. 9 without it)
    oracle              :class:`~cv2x_marl.policies.scripted.OraclePolicy` (the true gradient)
    planner | sensing   :class:`~cv2x_marl.policies.planner.PlannerPolicy` (the model's / the sensing
                        plan's best reachable position)
    optimum             :class:`~cv2x_marl.policies.optimum.OptimumPolicy` (best response under the simulator;
                        the team search where the team is rewarded and every vehicle moves)
    best-response       :class:`~cv2x_marl.policies.optimum.BestResponsePolicy` (best response always)
    sequential-best-response | sequential-sensing | sequential-team
                        :mod:`cv2x_marl.policies.sequential` (``decision_order="subframe"``, ``cv2x/Cooperative-v1``:
                        each vehicle re-plans at its subframe's turn, hearing the moves announced before it)
    sps | lowest-rssi | farthest (and random, optimum there)
                        :mod:`cv2x_marl.policies.resource`: where the action picks an SPS resource
                        (``cv2x/Resource-v0``): the standard's choice, the lowest S-RSSI, the farthest sensed user;
                        ``optimum`` the task's privileged ceiling
    ppo:PATH            a learned model file ``cv2x-marl train`` writes: a ``.zip``:
                        :class:`~cv2x_marl.policies.ppo.PpoPolicy` (stable-baselines3); a ``.pt``, by its format:
                        :class:`~cv2x_marl.policies.mappo.MappoPolicy` (a MAPPO actor) or
                        :class:`~cv2x_marl.policies.torch_ppo.TorchPpoPolicy` (``ppo.backend: torchrl``); a ``.npz``:
                        :class:`~cv2x_marl.policies.utility_map.UtilityMapPolicy` (a learned utility map)

Baseline files (``baselines/NAME.yaml``) name one of :data:`SCRIPTED` with its settings:
:mod:`cv2x_marl.policies.baselines`.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from cv2x_marl.policies import traffic
from cv2x_marl.policies.base import Policy, RandomPolicy, StaticPolicy
from cv2x_marl.policies.mappo import is_mappo_file
from cv2x_marl.policies.optimum import BestResponsePolicy, OptimumPolicy
from cv2x_marl.policies.planner import PlannerPolicy
from cv2x_marl.policies.ppo import PpoPolicy
from cv2x_marl.policies.resource import RESOURCE_POLICIES, make_resource_policy
from cv2x_marl.policies.scripted import GbmuPolicy, OraclePolicy
from cv2x_marl.policies.sequential import (
    InTurns,
    SequentialBestResponsePolicy,
    SequentialSensingPolicy,
    SequentialTeamPolicy,
)
from cv2x_marl.policies.torch_ppo import load_pt_policy
from cv2x_marl.policies.utility_map import UtilityMapPolicy, is_map_file
from cv2x_marl.regression.model import PAPER_MODEL, load_model

if TYPE_CHECKING:
    from cv2x_marl.env.mobility_env import MobilityEnv

#: the scripted policies, by name (what a baseline file's ``policy:`` may name)
SCRIPTED = (
    "static", "random", "greedy", "gbmu", "oracle", "planner", "sensing", "optimum", "best-response",
    "sequential-best-response", "sequential-sensing", "sequential-team", "sps", "lowest-rssi", "farthest",
)  # fmt: skip
#: the scripted policies that read a two-distance model
MODELLED = ("gbmu", "greedy", "planner", "sensing")
#: the prefix of a PPO model file (``ppo:PATH``)
PPO_PREFIX = "ppo:"


#: the scripted policies whose actions are position offsets (``max_step_m`` steps): refused where an
#: action means something else (traffic mode with ``traffic_action="speed"``: speed and lane commands)
OFFSET_POLICIES = (
    "gbmu", "greedy", "oracle", "planner", "sensing", "optimum", "best-response", "sequential-best-response",
    "sequential-sensing", "sequential-team",
)  # fmt: skip


#: the scripted policies with a road version (:mod:`cv2x_marl.policies.traffic`) where the movers drive with
#: speed and lane commands and observe their driving entries (``cv2x/Traffic-v0``; on SUMO ``sensing`` is
#: refused: it predicts with the lane model)
ROAD_POLICIES = ("static", "random", "gbmu", "sensing", "optimum")


def drives(env: MobilityEnv) -> bool:
    """Whether ``env``'s movers drive (the lane model or SUMO) with speed commands and observe their driving
    entries (``drive_observation``: only with traffic mode and speed actions)."""
    layout = getattr(env, "layout", None)
    return bool(layout is not None and layout.drive)


def refuse_action_space(spec: str, env: MobilityEnv) -> None:
    """Refuse a policy that cannot act in ``env``'s action space, naming it, the env's setting and the
    policies that can: an offset policy is never reinterpreted as speed and lane commands (those with a
    road version, :data:`ROAD_POLICIES`, run it where the env drives the lane model)."""
    choice = getattr(env, "mode", "snapshot") == "traffic" and getattr(env, "traffic_action", "offset") == "resource"
    if choice != (spec in RESOURCE_POLICIES and spec not in ("random", "optimum")) and spec in SCRIPTED:
        if choice and spec not in RESOURCE_POLICIES:
            raise ValueError(
                f"policy {spec!r} cannot act in this env: its action picks an SPS resource from a candidate list "
                f"(cv2x/Resource-v0); allowed here: {', '.join(RESOURCE_POLICIES)}, {PPO_PREFIX}PATH"
            )
        if not choice:
            raise ValueError(
                f"policy {spec!r} picks an SPS resource: it needs cv2x/Resource-v0 (traffic_action resource); "
                "allowed on other envs: the movers of docs/policies.md"
            )
    speed = getattr(env, "mode", "snapshot") == "traffic" and getattr(env, "traffic_action", "offset") == "speed"
    if speed and drives(env):
        if spec in SCRIPTED and spec not in ROAD_POLICIES:
            raise ValueError(
                f"policy {spec!r} moves vehicles by position offsets and has no road version, but this env's "
                "actions are speed and lane commands (cv2x/Traffic-v0); allowed here: "
                f"{', '.join(ROAD_POLICIES)}, {PPO_PREFIX}PATH (a model trained on this action space)"
            )
        return
    if speed and spec in OFFSET_POLICIES:
        raise ValueError(
            f"policy {spec!r} moves vehicles by position offsets, but this env's actions are speed and lane "
            "commands (mode='traffic', traffic_action='speed'); allowed here: static, random, "
            f"{PPO_PREFIX}PATH (a model trained on this action space)"
        )


def make_policy(spec: str, env: MobilityEnv, model_path: str = PAPER_MODEL, delta: float = 100.0) -> Policy:
    """``static | random | gbmu | greedy | oracle | planner | sensing | optimum | best-response |
    sequential-best-response | sequential-sensing | sequential-team | ppo:PATH``.

    Args:
        spec: the policy's name (:data:`SCRIPTED`) or ``ppo:PATH``.
        env: the env it acts in (its layout, step size and, for oracle, optimum and the planners, its state).
        model_path: the two-distance model of gbmu, greedy and planner
            (:func:`~cv2x_marl.regression.model.load_model`: ``paper-table2``, a fit folder or a model file).
        delta: step size per env step (gbmu, greedy, oracle).
    """
    refuse_action_space(spec, env)
    if getattr(env, "traffic_action", None) == "resource" and spec in RESOURCE_POLICIES:
        return make_resource_policy(spec, env)
    if drives(env) and spec in ROAD_POLICIES and spec != "random":
        if spec == "static":
            return traffic.HoldSpeedPolicy(env)
        if spec == "gbmu":
            gbmu = GbmuPolicy(load_model(Path(model_path)), env.layout, env.max_step_m, delta=delta, fairness=True)
            return traffic.RoadGbmuPolicy(env, gbmu)
        if spec == "sensing":
            return traffic.RoadSensingPolicy(env)
        return traffic.TrafficOptimumPolicy(env, make_policy)
    if spec == "static":
        return StaticPolicy()
    if spec == "random":
        return RandomPolicy()
    if spec in ("gbmu", "greedy"):
        model = load_model(Path(model_path))
        return GbmuPolicy(model, env.layout, env.max_step_m, delta=delta, fairness=spec == "gbmu")
    if spec == "oracle":
        return OraclePolicy(env, delta=delta)
    if spec == "optimum":
        return OptimumPolicy(env)
    if spec == "best-response":
        return BestResponsePolicy(env)
    if spec == "sequential-best-response":
        return SequentialBestResponsePolicy(env)
    if spec == "sequential-sensing":
        return SequentialSensingPolicy(env)
    if spec == "sequential-team":
        return SequentialTeamPolicy(env)
    if spec in ("planner", "sensing"):
        estimator = "model" if spec == "planner" else "sensing"
        return PlannerPolicy(env, load_model(Path(model_path)), estimator=estimator)
    if spec.startswith(PPO_PREFIX):
        raw = spec[len(PPO_PREFIX) :]
        if not raw:
            raise ValueError(f"policy {spec!r}: no path after {PPO_PREFIX!r}; give {PPO_PREFIX}PATH to a model file")
        path = Path(raw)
        if path.is_dir():
            raise ValueError(
                f"policy {spec}: {path} is a folder; give the model file in it (model.zip for PPO, model.pt for "
                "MAPPO, model.npz for a utility map)"
            )
        if is_map_file(path):
            return UtilityMapPolicy(path, env)
        learned = load_pt_policy(path, env) if is_mappo_file(path) else PpoPolicy(path, env)
        if env.options.decision_order == "subframe":
            return InTurns(learned, env)  # Cooperative-v1: it acts at its turns
        return learned
    raise ValueError(f"unknown policy {spec!r}; policies: {', '.join(SCRIPTED)}, {PPO_PREFIX}PATH")
