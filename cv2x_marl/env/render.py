"""Headless rendering of the env with matplotlib's Agg canvas (no display needed)."""

from __future__ import annotations

from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from numpy.typing import NDArray


def draw(env: Any, size_px: int = 480) -> NDArray[np.uint8]:
    """Roads, vehicles (movers highlighted), co-channel pairs, and the movers' tracks, as RGB."""
    fig = Figure(figsize=(size_px / 100, size_px / 100), dpi=100)
    canvas = FigureCanvasAgg(fig)
    ax = fig.add_axes((0.02, 0.02, 0.96, 0.96))
    road = env.sim.road
    w, h = env.box_m
    if road.kind == "grid":
        for c in road.road_pos_m:
            ax.axhline(c, color="#d0d0d0", lw=2 * road.lanes_per_direction, zorder=0)
            ax.axvline(c, color="#d0d0d0", lw=2 * road.lanes_per_direction, zorder=0)
    else:
        ax.axhline(road.road_pos_m[0], color="#d0d0d0", lw=6, zorder=0)
    pos = env.positions_m
    tracks = np.array(env.tracks)
    for i in np.flatnonzero(env.mover_mask):
        ax.plot(tracks[:, i, 0], tracks[:, i, 1], "-", color="#e15759", lw=1, alpha=0.7, zorder=1)
    res = env.resource
    for r in np.unique(res):
        members = np.flatnonzero(res == r)
        for a in range(members.size):
            for b in range(a + 1, members.size):
                p, q = pos[members[a]], pos[members[b]]
                if np.hypot(*(p - q)) <= env.config.metrics.interferer_range_m:
                    ax.plot([p[0], q[0]], [p[1], q[1]], ":", color="#f28e2b", lw=1.2, zorder=1)
    prr = env.prr
    sc = ax.scatter(pos[:, 0], pos[:, 1], c=prr, cmap="RdYlGn", vmin=0, vmax=1, s=40, edgecolors="k", zorder=2)
    del sc
    ax.set_xlim(-0.05 * w, 1.05 * w)
    ax.set_ylim(-0.05 * max(h, w) if road.kind == "grid" else -0.5 * w, 1.05 * h if road.kind == "grid" else 0.5 * w)
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])
    ax.set_title(f"t = {env.t}  (colour: per-node PRR; dotted: co-channel within th_I)", fontsize=8)
    canvas.draw()
    rgba = np.asarray(canvas.buffer_rgba())
    return np.ascontiguousarray(rgba[..., :3])


def show(img: NDArray[np.uint8], fig: Any) -> Any:
    """Show a frame in a matplotlib window (no-op under a non-interactive backend)."""
    import matplotlib.pyplot as plt

    if fig is None:
        fig = plt.figure("cv2x_mobility_v0")
        fig.add_subplot(1, 1, 1).imshow(img)
    else:
        fig.axes[0].images[0].set_data(img)
    plt.pause(0.001)
    return fig


def render_env(env: Any, mode: str | None = None) -> NDArray[np.uint8] | None:
    """:meth:`MobilityEnv.render <cv2x_marl.env.mobility_env.MobilityEnv.render>`: the scene as an image
    (``rgb_array``) or in a window (``human``, the figure kept on ``env._fig``)."""
    if mode is not None and mode != env.render_mode:
        raise ValueError(
            f"invalid render mode {mode!r}: this env was made with render_mode={env.render_mode!r}; "
            "pass render_mode to the constructor"
        )
    if env.render_mode is None:
        return None
    if not hasattr(env, "positions_m"):
        raise RuntimeError("render() called before reset(): call reset() first")
    img = draw(env)
    if env.render_mode == "human":
        env._fig = show(img, env._fig)
        return None
    return img
