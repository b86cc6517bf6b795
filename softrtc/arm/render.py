"""Drawing an arm scene with matplotlib, for inspection (no requirement depends on it)."""

from __future__ import annotations

import numpy as np

from .geometry import OBJECT_TARGET_BOX, ArmConfig
from .scene import Scene

__all__ = ["render_scene"]


def render_scene(scene: Scene, cfg: ArmConfig, ax=None):
    """Table, box walls, arm and parts of ``scene`` on ``ax`` (a new figure's axes when None); returns ``ax``."""
    import matplotlib.pyplot as plt

    if ax is None:
        _, ax = plt.subplots(figsize=(8, 4))
    ax.plot([-cfg.table_half_width, cfg.table_half_width], [0, 0], "k-")
    top = cfg.tray_rim_height if scene.box_bodies else cfg.box_wall_height  # moving trays have low rims ([A-27])
    for cx, inner, color in zip(scene.box_centers, cfg.box_inner_widths, ("tab:blue", "gray")):
        for side in (-1, 1):
            x = cx + side * (inner / 2 + cfg.box_wall_thickness / 2)
            ax.plot([x, x], [0, top], color=color, lw=3)
        if scene.box_bodies:
            ax.plot([x - inner - cfg.box_wall_thickness, x], [0, 0], color=color, lw=2)
    pts = [np.array(cfg.base)]
    for b, length in zip(scene.links, cfg.link_lengths):
        p = b.local_to_world((length, 0))
        pts.append(np.array([p.x, p.y]))
    pts = np.array(pts)
    ax.plot(pts[:, 0], pts[:, 1], "o-", color="k")
    for i, (body, shape) in enumerate(scene.objects):
        v = np.array([body.local_to_world(p) for p in shape.get_vertices()])
        ax.fill(v[:, 0], v[:, 1], color="tab:blue" if OBJECT_TARGET_BOX[i] == 0 else "silver",
                ec="k")
    ax.set_aspect("equal")
    return ax
