"""The learned utility map: a mover that plans on a utility model it learned from its own rewards.

A spatial action map (Wu et al., *Spatial Action Maps for Mobile Manipulation*, RSS 2020) for the
movers of observation version 3: the policy scores candidate displacements on a grid over the mover's
reachable square with one small network shared over the candidates and the neighbours, and drives to the
best one. The score of a candidate ``c`` is the predicted eq. 12 utility per target receiver there,

    U(c) = sum_j target_j * u(f_j(c)) / sum_j target_j,    u = ln(p_min) * sigmoid(MLP(f)),

where ``f_j(c)`` (:data:`LINK_FEATURES`) describes the link from ``c`` to neighbour ``j`` with what the
observation carries (the CAM positions, the co-channel vehicles around ``j`` from the SCIs, the RSRP
measured from ``j`` where the mover stands). Lengths enter as ``log10(m) / 3``; a pair's *corridor
offset* ``min(|dx|, |dy|)`` tells on a street grid whether two vehicles share a street (line of sight),
and the street-grid (WINNER+ B1 NLOS) path loss reads both legs of the path. ``u`` lies in
``(ln p_min, 0)`` like a link's ``ln max(P, p_min)``. The network is trained by
:mod:`cv2x_marl.rl.utility_map` by regression on the own utility the observation carries (the running sum
of the env's rewards) at the positions the mover visits: nothing privileged, no expert. This module is
numpy only (the base install runs a trained map).

Acting: every ``replan_every`` steps the policy searches its map over the reachable square (a
``grid x grid`` grid over ``[-reach, reach]^2`` around the mover, then ``refine x refine`` grids of a third
of the pitch around the ``top`` best points; the current position is always a candidate, scored with the
utility the observation carries there instead of the map's estimate) and drives straight to the best
point, ``max_step_m`` per axis and step. An agent's action depends on its own observations alone (the map
is evaluated one agent at a time, in float64).
"""

from __future__ import annotations

import io
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cv2x_marl.env.observation import FEATURES, ObservationLayout
from cv2x_marl.policies.base import Actions, Observations

FloatArray = NDArray[np.float64]

#: the features of one (candidate, neighbour) link, in order: the first :data:`STATIC_FEATURES` do not depend
#: on the candidate (computed once per plan), the last four do
LINK_FEATURES = (
    "has_interferer",  # j has a main interferer (NSV_j > 0)
    "log_interferer_distance",  # log10(|interferer - j| / 1 m) / 3 (0 when none)
    "co1",  # the nearest co-channel vehicle to j exists
    "log_co1_distance",  # log10(|co1 - j| / 1 m) / 3 (0 when none)
    "co2",  # the second nearest exists
    "log_co2_distance",  # log10(|co2 - j| / 1 m) / 3 (0 when none)
    "nsv",  # NSV_j / 4
    "heard",  # j's RSRP was measured (1) or never heard (0)
    "rsrp",  # j's measured RSRP as the observation gives it ((dBm + 100) / 20; 0 when never heard)
    "log_distance_now",  # log10(|j - own position| / 1 m) / 3
    "log_interferer_corridor",  # log10(min(|dx|, |dy|) / 1 m) / 3 between the main interferer and j (0 when none)
    "log_co1_corridor",  # the same between co1 and j
    "log_co2_corridor",  # the same between co2 and j
    "log_corridor_now",  # the same between the mover and j
    "log_distance",  # log10(|j - c| / 1 m) / 3: the link's length at the candidate
    "log_corridor",  # log10(min(|dx|, |dy|) / 1 m) / 3 between c and j (street-grid path loss reads both legs)
    "log_along",  # log10(max(|dx|, |dy|) / 1 m) / 3 between c and j
    "moved",  # |c| / 100 m: how far the candidate is from where the RSRP was measured
)
STATIC_FEATURES = 14
#: the file format written by :meth:`UtilityMap.save`
MAP_FORMAT = "cv2x-marl utility map 2"


def _log_m(distance_m: FloatArray) -> FloatArray:
    return np.log10(np.maximum(distance_m, 1.0)) / 3.0


def static_features(obs: FloatArray, layout: ObservationLayout) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The candidate-free part of the link features and what the candidate part needs.

    Args:
        obs: [B, D] observations of version 3.
        layout: their layout.

    Returns:
        ``(static [B, K, STATIC_FEATURES], rel_m [B, K, 2] the neighbours relative to the mover (m),
        target [B, K] 1 for a target receiver)``.
    """
    if layout.version != 3:
        raise ValueError(f"the utility map reads observation version 3, got version {layout.version}")
    obs = np.asarray(obs, dtype=np.float64)
    b, k, s = obs.shape[0], layout.n_neighbours, layout.scale_m
    v0 = obs[:, : k * FEATURES].reshape(b, k, FEATURES)
    meas = layout.measured(obs)
    rel_m = v0[..., 0:2] * s
    has_int = v0[..., 4]
    out = np.empty((b, k, STATIC_FEATURES))
    pairs = ((v0[..., 5:7], has_int), (meas[..., 4:6], meas[..., 6]), (meas[..., 7:9], meas[..., 9]))
    for n, (where, present) in enumerate(pairs):  # the main interferer, co1, co2: each against j
        d = where * s - rel_m
        out[..., 2 * n] = present
        out[..., 2 * n + 1] = present * _log_m(np.hypot(d[..., 0], d[..., 1]))
        out[..., 10 + n] = present * _log_m(np.abs(d).min(axis=-1))
    out[..., 6] = v0[..., 3] / 4.0
    out[..., 7] = (meas[..., 0] != 0.0).astype(np.float64)
    out[..., 8] = meas[..., 0]
    out[..., 9] = _log_m(np.hypot(rel_m[..., 0], rel_m[..., 1]))
    out[..., 13] = _log_m(np.abs(rel_m).min(axis=-1))
    return out, rel_m, v0[..., 2].copy()


def candidate_features(rel_m: FloatArray, offsets_m: FloatArray) -> FloatArray:
    """[B, M, K, 4] the candidate part of the link features (:data:`LINK_FEATURES` from ``log_distance``).

    Args:
        rel_m: [B, K, 2] neighbours relative to the mover (m).
        offsets_m: [B, M, 2] candidate positions relative to the mover (m).
    """
    d = rel_m[:, None, :, :] - offsets_m[:, :, None, :]
    a = np.abs(d)
    out = np.empty((*d.shape[:-1], 4))
    out[..., 0] = _log_m(np.hypot(d[..., 0], d[..., 1]))
    out[..., 1] = _log_m(a.min(axis=-1))
    out[..., 2] = _log_m(a.max(axis=-1))
    out[..., 3] = (np.hypot(offsets_m[..., 0], offsets_m[..., 1]) / 100.0)[:, :, None]
    return out


@dataclass
class UtilityMap:
    """The per-link networks and how the policy searches them (see the module docstring).

    Attributes:
        members: an ensemble of networks, each a list of layers ``(W [in, out], b [out])``; the first layer
            reads :data:`LINK_FEATURES`, the last has one output. The map is the members' mean (an
            ensemble's mean is steadier to search than one network: its errors partly cancel).
        p_min: the clip of eq. 12 (``u`` lies in ``(ln p_min, 0)``).
        grid: points per axis of the coarse search grid.
        refine: points per axis of each refinement grid.
        top: coarse points refined.
        replan_every: steps between searches (the first step always searches).
        switch_margin: a search replaces the current target only where its best point's predicted utility
            beats the current target's (predicted from the same observation) by more than this.
        info: what trained it (env id, options, seed, budget); written with the weights.
    """

    members: list[list[tuple[FloatArray, FloatArray]]]
    p_min: float = 1e-3
    grid: int = 21
    refine: int = 7
    top: int = 3
    replan_every: int = 10
    switch_margin: float = 0.0
    info: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        ok = bool(self.members) and all(
            m and m[0][0].shape[0] == len(LINK_FEATURES) and m[-1][0].shape[1] == 1 for m in self.members
        )
        if not ok:
            raise ValueError(
                f"a utility map's members read {len(LINK_FEATURES)} features in their first layer and have one "
                "output in their last"
            )
        for name in ("grid", "refine", "top", "replan_every"):
            value = getattr(self, name)
            if not isinstance(value, int | np.integer) or value < 1:
                raise ValueError(f"utility map {name} must be an integer >= 1, got {value!r}")
        if not np.isfinite(self.switch_margin) or self.switch_margin < 0:
            raise ValueError(f"utility map switch_margin must be a number >= 0, got {self.switch_margin!r}")
        self.members = [
            [(np.asarray(w, dtype=np.float64), np.asarray(b, dtype=np.float64)) for w, b in m] for m in self.members
        ]

    def link_utility(self, static: FloatArray, dynamic: FloatArray) -> FloatArray:
        """[B, M, K] ``u`` per candidate and neighbour, the members' mean.

        Args:
            static: [B, K, STATIC_FEATURES] (:func:`static_features`).
            dynamic: [B, M, K, 2] (:func:`candidate_features`).
        """
        total = np.zeros(dynamic.shape[:-1])
        for member in self.members:
            (w0, b0), rest = member[0], member[1:]
            h = (static @ w0[:STATIC_FEATURES])[:, None, :, :] + dynamic @ w0[STATIC_FEATURES:] + b0
            for w, b in rest:
                h = np.maximum(h, 0.0) @ w + b
            total += np.log(self.p_min) / (1.0 + np.exp(-np.clip(h[..., 0], -60.0, 60.0)))
        return total / len(self.members)

    def utility(self, obs: FloatArray, layout: ObservationLayout, offsets_m: FloatArray) -> FloatArray:
        """[B, M] predicted utility per target receiver at candidate offsets [B, M, 2] (m) from each mover."""
        static, rel_m, target = static_features(obs, layout)
        return self._utility(static, rel_m, target, offsets_m)

    def _utility(self, static: FloatArray, rel_m: FloatArray, target: FloatArray, offsets_m: FloatArray) -> FloatArray:
        u = self.link_utility(static, candidate_features(rel_m, offsets_m))
        n = target.sum(axis=-1)
        return (u * target[:, None, :]).sum(axis=-1) / np.maximum(n, 1.0)[:, None]

    def plan(
        self, obs: FloatArray, layout: ObservationLayout, reach_m: FloatArray, current_m: FloatArray | None = None
    ) -> FloatArray:
        """[B, 2] the best candidate offset (m) of each mover within its reachable square.

        Args:
            obs: [B, D] observations.
            layout: their layout.
            reach_m: [B] half-width of each mover's reachable square (m).
            current_m: [B, 2] the offsets of the targets the movers drive to now (m; clipped to the square):
                kept unless the search's best beats them by more than ``switch_margin``. None: no target yet.
        """
        static, rel_m, target = static_features(obs, layout)
        reach_m = np.asarray(reach_m, dtype=np.float64)
        b = obs.shape[0]
        unit = np.linspace(-1.0, 1.0, self.grid)
        coarse = np.stack(np.meshgrid(unit, unit, indexing="ij"), axis=-1).reshape(-1, 2)
        coarse = np.concatenate([coarse, np.zeros((1, 2))])
        offsets = coarse[None, :, :] * reach_m[:, None, None]
        score = self._utility(static, rel_m, target, offsets)
        now = np.asarray(obs, dtype=np.float64)[:, layout.size - 6]  # the own utility, observed where it stands
        score[:, -1] = now  # staying scores what the mover observes, not the map's estimate of it
        top = min(self.top, offsets.shape[1])
        best = np.argsort(-score, axis=1, kind="stable")[:, :top]
        pitch = 2.0 * reach_m / max(self.grid - 1, 1)
        fine = np.linspace(-1.0, 1.0, self.refine)
        local = np.stack(np.meshgrid(fine, fine, indexing="ij"), axis=-1).reshape(-1, 2)
        centres = np.take_along_axis(offsets, best[:, :, None], axis=1)  # [B, top, 2]
        near = centres[:, :, None, :] + local[None, None, :, :] * (pitch / 3.0)[:, None, None, None]
        near = np.clip(near.reshape(b, -1, 2), -reach_m[:, None, None], reach_m[:, None, None])
        near_score = self._utility(static, rel_m, target, near)
        cands = np.concatenate([offsets, near], axis=1)
        scores = np.concatenate([score, near_score], axis=1)
        pick = np.argmax(scores, axis=1)
        best_m = cands[np.arange(b), pick]
        if current_m is None:
            return best_m
        kept = np.clip(np.asarray(current_m, dtype=np.float64), -reach_m[:, None], reach_m[:, None])
        kept_score = self._utility(static, rel_m, target, kept[:, None, :])[:, 0]
        kept_score = np.where(np.hypot(kept[:, 0], kept[:, 1]) < 1e-9, now, kept_score)
        switch = scores[np.arange(b), pick] > kept_score + self.switch_margin
        return np.where(switch[:, None], best_m, kept)

    def save(self, path: Path) -> None:
        """Write the map as ``.npz`` (arrays only, no pickles): the weights and a JSON header."""
        header = {
            "format": MAP_FORMAT,
            "features": list(LINK_FEATURES),
            "p_min": self.p_min,
            "grid": self.grid,
            "refine": self.refine,
            "top": self.top,
            "replan_every": self.replan_every,
            "switch_margin": self.switch_margin,
            "layers": [len(m) for m in self.members],
            "info": self.info,
        }
        arrays: dict[str, Any] = {"header": np.frombuffer(json.dumps(header).encode(), dtype=np.uint8)}
        for e, member in enumerate(self.members):
            for n, (w, b) in enumerate(member):
                arrays[f"m{e}_w{n}"], arrays[f"m{e}_b{n}"] = w, b
        buf = io.BytesIO()
        np.savez(buf, **arrays)
        Path(path).write_bytes(buf.getvalue())

    @classmethod
    def load(cls, path: Path) -> UtilityMap:
        """Read a map :meth:`save` wrote; a file that is not one raises ``ValueError`` naming it."""
        try:
            with np.load(Path(path), allow_pickle=False) as data:
                header = json.loads(bytes(data["header"]).decode())
                if header.get("format") != MAP_FORMAT:
                    raise ValueError(f"format {header.get('format')!r}, expected {MAP_FORMAT!r}")
                if header.get("features") != list(LINK_FEATURES):
                    raise ValueError("its link features differ from this version's")
                members = [
                    [(data[f"m{e}_w{n}"], data[f"m{e}_b{n}"]) for n in range(int(layers))]
                    for e, layers in enumerate(header["layers"])
                ]
        except (OSError, KeyError, ValueError, TypeError, json.JSONDecodeError) as exc:
            raise ValueError(f"cannot load the utility map {path}: {exc}") from exc
        return cls(
            members,
            p_min=float(header["p_min"]),
            grid=int(header["grid"]),
            refine=int(header["refine"]),
            top=int(header["top"]),
            replan_every=int(header["replan_every"]),
            switch_margin=float(header["switch_margin"]),
            info=dict(header.get("info", {})),
        )


def is_map_file(path: Path) -> bool:
    """Whether ``path`` is a utility map file (an ``.npz`` with the map's header)."""
    path = Path(path)
    if path.suffix != ".npz" or not path.is_file():
        return False
    try:
        with np.load(path, allow_pickle=False) as data:
            return "header" in data.files and json.loads(bytes(data["header"]).decode()).get("format") == MAP_FORMAT
    except (OSError, ValueError, json.JSONDecodeError):
        return False


def check_map_env(env: Any) -> None:
    """Refuse an env the map cannot plan in, naming what differs (observation version 3, offset actions in
    snapshot mode, movement unbounded by drift, region or a torus)."""
    layout = getattr(env, "layout", None)
    problems = []
    if layout is None or layout.version != 3 or layout.drive:
        problems.append("observation version 3 (cv2x/SingleMover-v3, cv2x/Mobility-v3)")
    if getattr(env, "mode", "snapshot") != "snapshot":
        problems.append("snapshot mode")
    if getattr(env, "max_drift_m", None) is not None or bool(getattr(env, "roi", False)):
        problems.append("no max_drift_m and no roi (the map searches the whole reachable square)")
    if np.isfinite(np.asarray(getattr(env, "period_m", [np.inf]), dtype=np.float64)).any():
        problems.append("distances that do not wrap")
    if getattr(env, "settle_steps", 0):
        problems.append("settle_steps 0")
    if problems:
        raise ValueError(f"the utility map needs {'; '.join(problems)}")


class UtilityMapPolicy:
    """Acts with a :class:`UtilityMap` (``--policy ppo:PATH`` on a ``.npz`` map file; module docstring).

    Per agent it keeps the target it drives to, as a drift from the episode's start (the observation's
    ``drift`` entries), and searches the map again every ``replan_every`` steps.

    Args:
        path: a map file, or a loaded :class:`UtilityMap`.
        env: the env it acts in (its layout and ``max_step_m``; checked by :func:`check_map_env`).
    """

    name = "utility-map"

    def __init__(self, path: Path | UtilityMap, env: Any) -> None:
        self.map = path if isinstance(path, UtilityMap) else UtilityMap.load(Path(path))
        check_map_env(env)
        self.layout: ObservationLayout = env.layout
        self.max_step_m = float(env.max_step_m)
        self.targets: dict[str, FloatArray] = {}
        self.steps = 0

    def reset(self, seed: int | None = None) -> None:
        self.targets = {}
        self.steps = 0

    def act(self, observations: Observations) -> Actions:
        agents = list(observations)
        obs = np.stack([observations[a] for a in agents]).astype(np.float64)
        drift_m = own_drift_m(obs, self.layout)
        if self.steps % self.map.replan_every == 0 or any(a not in self.targets for a in agents):
            reach_m = obs[:, self.layout.size - 1] * self.layout.scale_m
            for n, a in enumerate(agents):  # one agent at a time: its action depends on its observation alone
                now = None if a not in self.targets else (self.targets[a] - drift_m[n])[None]
                offset = self.map.plan(obs[n : n + 1], self.layout, reach_m[n : n + 1], now)[0]
                self.targets[a] = drift_m[n] + offset
        self.steps += 1
        out: Actions = {}
        for n, a in enumerate(agents):
            out[a] = np.clip((self.targets[a] - drift_m[n]) / self.max_step_m, -1.0, 1.0).astype(np.float32)
        return out


def own_drift_m(obs: FloatArray, layout: ObservationLayout) -> FloatArray:
    """[B, 2] the mover's drift from its episode start (m), from the observation's version-3 own entries."""
    k = layout.size - 4  # drift_x, drift_y, time_left, reach end the version-3 layout
    return np.asarray(obs[:, k : k + 2], dtype=np.float64) * layout.scale_m
