"""A procedural tote (floor plate and four walls) on a floor, as static pybullet boxes.

World frame: z up, the cell floor's top at z = 0, the tote centered on the origin with its long
side along x. Sizes are randomised around a common 600 x 400 x 200 mm Euro container.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

NOMINAL_INNER = (0.6, 0.4, 0.2)  # metres: inner length, width, height


@dataclass(frozen=True)
class ToteSpec:
    """Inner size (m) of an open box and its wall/floor thickness."""
    inner: tuple[float, float, float]
    wall: float = 0.012
    bottom: float = 0.01

    @property
    def floor_z(self) -> float:
        """Height of the inside floor (where parts rest)."""
        return self.bottom

    @property
    def rim_z(self) -> float:
        return self.bottom + self.inner[2]

    @property
    def outer_half(self) -> tuple[float, float]:
        return self.inner[0] / 2 + self.wall, self.inner[1] / 2 + self.wall

    def contains_xy(self, xy: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """True where (N, 2) points lie inside the inner walls (shrunk by ``margin``)."""
        xy = np.atleast_2d(xy)
        return ((np.abs(xy[:, 0]) <= self.inner[0] / 2 - margin)
                & (np.abs(xy[:, 1]) <= self.inner[1] / 2 - margin))


def random_tote(rng: np.random.Generator, scale: float = 1.0, jitter: float = 0.2) -> ToteSpec:
    """Tote with each inner dimension within +-``jitter`` of nominal, times ``scale``
    (a smaller bin for small parts, as real cells use)."""
    inner = tuple(float(d * scale * rng.uniform(1 - jitter, 1 + jitter)) for d in NOMINAL_INNER)
    return ToteSpec(inner=inner, wall=float(rng.uniform(0.008, 0.02)),
                    bottom=float(rng.uniform(0.005, 0.015)))


def _static_box(p, client: int, half: np.ndarray, pos: np.ndarray, friction: float) -> int:
    col = p.createCollisionShape(p.GEOM_BOX, halfExtents=half.tolist(), physicsClientId=client)
    vis = p.createVisualShape(p.GEOM_BOX, halfExtents=half.tolist(), physicsClientId=client)
    body = p.createMultiBody(0.0, col, vis, basePosition=pos.tolist(), physicsClientId=client)
    p.changeDynamics(body, -1, lateralFriction=friction, restitution=0.05, physicsClientId=client)
    return body


def build_tote(client: int, tote: ToteSpec, friction: float = 0.5, floor_size: float = 8.0) -> list[int]:
    """Create the cell floor and the tote in a pybullet client; returns their body ids."""
    import pybullet as p  # training-only dependency
    L, W, H = tote.inner
    t, b = tote.wall, tote.bottom
    bodies = [_static_box(p, client, np.array([floor_size / 2, floor_size / 2, 0.05]),
                          np.array([0.0, 0.0, -0.05]), friction)]
    boxes = [
        ([L / 2 + t, W / 2 + t, b / 2], [0, 0, b / 2]),                         # bottom plate
        ([L / 2 + t, t / 2, H / 2], [0, W / 2 + t / 2, b + H / 2]),            # long walls
        ([L / 2 + t, t / 2, H / 2], [0, -W / 2 - t / 2, b + H / 2]),
        ([t / 2, W / 2, H / 2], [L / 2 + t / 2, 0, b + H / 2]),                # short walls
        ([t / 2, W / 2, H / 2], [-L / 2 - t / 2, 0, b + H / 2]),
    ]
    for half, pos in boxes:
        bodies.append(_static_box(p, client, np.array(half, float), np.array(pos, float), friction))
    return bodies
