"""Simulated industrial depth camera: pose, intrinsics, rendering and sensor effects.

The camera is an ideal pinhole with intrinsics ``K`` (pixel centers at integer coordinates).
Rendering uses pybullet's TinyRenderer (CPU, works in DIRECT mode) with an OpenGL projection
matrix built from ``K``, so the rendered depth back-projects exactly through ``K``. Points are
returned in the camera's OPTICAL frame (x right, y down, z forward), as a ROS camera driver
publishes them.

Sensor effects (all vectorised, randomised per scene by ``random_sensor``):
* depth noise along the viewing ray with sigma = a + b z^2 (triangulation error grows with z^2);
* dropouts: isolated pixels, small clusters, and surfaces seen at grazing angles;
* mixed ("flying") pixels at depth discontinuities: the depth is interpolated between the
  foreground and background surface, so they float between parts and bridge neighbours. They
  belong to neither surface, so they get instance 0 and center score 0 -- the points a
  segmenter should leave unassigned (the paper's noise rule);
* no return (nothing hit) and anything beyond ``max_range`` is NaN.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

# optical (x right, y down, z forward) -> OpenGL camera (x right, y up, z backward)
_OPTICAL_TO_GL = np.diag([1.0, -1.0, -1.0])


@dataclass(frozen=True)
class CameraSpec:
    """Pinhole camera: image size, intrinsics and pose of the optical frame in the world."""
    width: int
    height: int
    K: np.ndarray             # (3, 3)
    T_world_cam: np.ndarray   # (4, 4) optical frame -> world
    near: float = 0.1
    far: float = 4.0

    @property
    def T_cam_world(self) -> np.ndarray:
        R, t = self.T_world_cam[:3, :3], self.T_world_cam[:3, 3]
        out = np.eye(4)
        out[:3, :3] = R.T
        out[:3, 3] = -R.T @ t
        return out

    def view_matrix(self) -> list[float]:
        """OpenGL view matrix (world -> GL camera), column-major as pybullet expects."""
        V = np.eye(4)
        V[:3, :4] = _OPTICAL_TO_GL @ self.T_cam_world[:3, :4]
        return V.T.reshape(-1).tolist()

    def projection_matrix(self) -> list[float]:
        """OpenGL projection equivalent to ``K``: image pixel (row i, col j) sees the ray
        through K^-1 (j, i, 1).

        TinyRenderer samples image pixel (i, j) at window coordinates (j, H - 1 - i) (integer,
        not pixel-center, positions; rows flipped), measured against an analytic floor plane;
        hence the principal point enters as (cx, cy + 1) in window coordinates.
        """
        fx, fy, cx, cy = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2] + 1.0
        w, h, n, f = self.width, self.height, self.near, self.far
        P = np.array([
            [2 * fx / w, 0.0, 1.0 - 2 * cx / w, 0.0],
            [0.0, 2 * fy / h, 2 * cy / h - 1.0, 0.0],
            [0.0, 0.0, -(f + n) / (f - n), -2 * f * n / (f - n)],
            [0.0, 0.0, -1.0, 0.0],
        ])
        return P.T.reshape(-1).tolist()


def look_at(position: np.ndarray, target: np.ndarray, yaw: float) -> np.ndarray:
    """Pose (4, 4) of an optical frame at ``position`` whose z axis points at ``target``;
    ``yaw`` turns the image about the optical axis (image 'down' = world azimuth ``yaw``)."""
    z = np.asarray(target, float) - np.asarray(position, float)
    z /= np.linalg.norm(z)
    d = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    y = d - np.dot(d, z) * z
    if np.linalg.norm(y) < 1e-6:  # looking horizontally along d: fall back to world down
        y = np.array([0.0, 0.0, -1.0]) - z[2] * z
    y /= np.linalg.norm(y)
    x = np.cross(y, z)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, y, z])
    T[:3, 3] = position
    return T


def intrinsics(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def random_camera(rng: np.random.Generator, target: np.ndarray, *, width: int = 640, height: int = 480,
                  height_range: tuple[float, float] = (0.9, 1.6), max_tilt_deg: float = 18.0,
                  fx_range: tuple[float, float] = (550.0, 650.0), pp_jitter: float = 8.0,
                  target_jitter: float = 0.04) -> CameraSpec:
    """A camera above ``target`` (world, z up, floor at 0): height above the floor, tilt from
    vertical and yaw random; intrinsics of a typical 640x480 3D camera, scaled to ``width``."""
    s = width / 640.0
    fx = rng.uniform(*fx_range) * s
    fy = fx * rng.uniform(0.995, 1.005)
    cx = (width - 1) / 2 + rng.uniform(-pp_jitter, pp_jitter) * s
    cy = (height - 1) / 2 + rng.uniform(-pp_jitter, pp_jitter) * s
    tgt = np.asarray(target, float) + np.append(rng.uniform(-target_jitter, target_jitter, 2), 0.0)
    cam_h = rng.uniform(*height_range)
    tilt = np.deg2rad(rng.uniform(0.0, max_tilt_deg))
    azim = rng.uniform(0.0, 2 * np.pi)
    dist = (cam_h - tgt[2]) / np.cos(tilt)
    pos = tgt + dist * np.array([np.sin(tilt) * np.cos(azim), np.sin(tilt) * np.sin(azim), np.cos(tilt)])
    T = look_at(pos, tgt, rng.uniform(0.0, 2 * np.pi))
    return CameraSpec(width=width, height=height, K=intrinsics(fx, fy, cx, cy), T_world_cam=T,
                      near=0.1, far=max(4.0, 2.5 * cam_h))


def render(client: int, cam: CameraSpec) -> tuple[np.ndarray, np.ndarray]:
    """Render metric depth (H, W) float64 along the optical axis (NaN where nothing was hit)
    and the segmentation (H, W) int of pybullet body ids (-1 = none)."""
    import pybullet as p  # training-only dependency
    _, _, _, depth_buf, seg = p.getCameraImage(
        cam.width, cam.height, viewMatrix=cam.view_matrix(), projectionMatrix=cam.projection_matrix(),
        renderer=p.ER_TINY_RENDERER, shadow=0, physicsClientId=client)
    buf = np.asarray(depth_buf, np.float64).reshape(cam.height, cam.width)
    seg = np.asarray(seg, np.int64).reshape(cam.height, cam.width)
    n, f = cam.near, cam.far
    z = f * n / (f - (f - n) * buf)  # OpenGL depth buffer -> eye-space distance along the axis
    z[(seg < 0) | (buf >= 1.0)] = np.nan
    return z, seg


def backproject(z: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Organized cloud (H, W, 3) in the optical frame from depth along the axis (H, W)."""
    h, w = z.shape
    u = (np.arange(w) - K[0, 2]) / K[0, 0]
    v = (np.arange(h) - K[1, 2]) / K[1, 1]
    return np.stack([z * u[None, :], z * v[:, None], z], axis=-1)


@dataclass(frozen=True)
class SensorModel:
    """Per-scene sensor imperfections (see the module docstring)."""
    sigma_a: float = 0.0003            # m
    sigma_b: float = 0.001             # 1/m: sigma = a + b z^2
    dropout: float = 0.003             # isolated missing pixels (fraction)
    cluster_rate: float = 0.0005       # seeds of missing blobs per pixel
    cluster_radius: float = 2.0        # px at 640 wide
    grazing_cos: float = 0.2           # surfaces with |cos(view angle)| below this ...
    grazing_drop: float = 0.7          # ... drop out with this probability
    flying_fraction: float = 0.2       # of the pixels on a depth discontinuity
    jump: float = 0.015                # m: depth step that counts as a discontinuity
    min_range: float = 0.3             # m
    max_range: float = 2.5             # m
    enabled: bool = True


def random_sensor(rng: np.random.Generator, noise: bool = True) -> SensorModel:
    """Sensor parameters spanning good industrial structured-light to mid-range ToF cameras."""
    if not noise:
        return SensorModel(enabled=False, max_range=float("inf"), min_range=0.0)
    return SensorModel(
        sigma_a=rng.uniform(0.0001, 0.0006), sigma_b=rng.uniform(0.0003, 0.0015),
        dropout=rng.uniform(0.0005, 0.008), cluster_rate=rng.uniform(0.0001, 0.0008),
        cluster_radius=rng.uniform(1.0, 3.5), grazing_cos=rng.uniform(0.1, 0.3),
        grazing_drop=rng.uniform(0.3, 0.9), flying_fraction=rng.uniform(0.05, 0.3),
        jump=rng.uniform(0.01, 0.02), min_range=0.3, max_range=rng.uniform(1.9, 2.6))


def _shift(a: np.ndarray, dy: int, dx: int, fill=np.nan) -> np.ndarray:
    """a shifted so out[i, j] = a[i + dy, j + dx] (``fill`` outside)."""
    out = np.full_like(a, fill)
    h, w = a.shape[:2]
    ys, yd = (slice(dy, h), slice(0, h - dy)) if dy >= 0 else (slice(0, h + dy), slice(-dy, h))
    xs, xd = (slice(dx, w), slice(0, w - dx)) if dx >= 0 else (slice(0, w + dx), slice(-dx, w))
    out[yd, xd] = a[ys, xs]
    return out


def grazing_cosine(points: np.ndarray) -> np.ndarray:
    """|cos| of the angle between the surface normal (from image neighbours) and the view ray."""
    dx = _shift(points, 0, 1) - _shift(points, 0, -1)
    dy = _shift(points, 1, 0) - _shift(points, -1, 0)
    n = np.cross(dx, dy)
    num = np.abs((n * points).sum(axis=-1))
    den = np.linalg.norm(n, axis=-1) * np.linalg.norm(points, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return num / den


def apply_sensor(z: np.ndarray, K: np.ndarray, sensor: SensorModel,
                 rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Measured depth (H, W) from ideal depth, and the mask of mixed (flying) pixels.

    Pixels that end up NaN have no return; flying pixels keep a (wrong) finite depth.
    """
    h, w = z.shape
    out = z.copy()
    flying = np.zeros((h, w), bool)
    if sensor.enabled:
        # mixed pixels: partner = the 4-neighbour with the largest depth step
        nbrs = np.stack([_shift(z, 0, 1), _shift(z, 0, -1), _shift(z, 1, 0), _shift(z, -1, 0)])
        step = np.abs(nbrs - z[None])
        step = np.where(np.isfinite(step), step, -1.0)
        k = step.argmax(axis=0)
        big = np.take_along_axis(step, k[None], 0)[0]
        partner = np.take_along_axis(nbrs, k[None], 0)[0]
        t = rng.uniform(0.15, 0.85, (h, w))
        flying = (big > sensor.jump) & (rng.random((h, w)) < sensor.flying_fraction)
        out = np.where(flying, z + t * (partner - z), out)
        # range noise, growing with the square of the range
        sigma = sensor.sigma_a + sensor.sigma_b * out ** 2
        out = out + rng.standard_normal((h, w)) * sigma
        # dropouts: isolated, clustered, and at grazing angles
        drop = rng.random((h, w)) < sensor.dropout
        seeds = rng.random((h, w)) < sensor.cluster_rate
        r = max(1, int(round(sensor.cluster_radius * w / 640.0)))
        yy, xx = np.mgrid[-r:r + 1, -r:r + 1]
        drop |= ndimage.binary_dilation(seeds, structure=(yy ** 2 + xx ** 2) <= r * r)
        cos = grazing_cosine(backproject(z, K))
        drop |= (cos < sensor.grazing_cos) & (rng.random((h, w)) < sensor.grazing_drop) & ~flying
        out[drop] = np.nan
    with np.errstate(invalid="ignore"):
        out[(out > sensor.max_range) | (out < sensor.min_range)] = np.nan
    flying &= np.isfinite(out)
    return out, flying
