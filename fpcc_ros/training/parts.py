"""Procedural library of industrial parts for synthetic bin-picking scenes.

Each factory takes a numpy ``Generator`` and returns a closed ``trimesh.Trimesh`` in metres whose
dimensions are drawn from realistic ranges (largest extent 3-25 cm). The pinned environment has no
boolean backend (no manifold3d, blender or shapely), so parts are built without booleans: every
part is a concatenation of closed sub-solids -- revolved profiles, prisms with round holes
(triangulated here), swept tubes and boxes -- that abut each other (shared faces, so the summed
volume is exact) or, where noted, overlap slightly (eye bolt collar, tee branch; the doubled
overlap moves the volume centroid by well under a millimetre). Every sub-solid is watertight, so
the concatenation is too and its volume centroid is a well-defined geometric center.

``BUILTIN_PARTS`` maps a name to a ``PartSpec``; ``make_part(name, seed)`` builds a
``PartModel`` (center, d_max) from it.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import trimesh
from scipy.spatial import Delaunay

from fpcc_ros.training.mesh import PartModel, part_from_trimesh

SECTIONS = 48  # facets around revolved parts: smooth at the camera's ~1-2 mm/pixel


# --------------------------------------------------------------------------------------------
# geometry helpers (pure numpy; no booleans)
# --------------------------------------------------------------------------------------------

def _solid(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Outward normals: flip a closed mesh whose signed volume came out negative."""
    if mesh.volume < 0:
        mesh.invert()
    return mesh


def _revolve(profile_rz: np.ndarray, sections: int = SECTIONS) -> trimesh.Trimesh:
    """Revolve an (r, z) profile about the z axis.

    The profile either starts and ends on the axis (r = 0, a solid of revolution) or is closed
    (first point repeated, an annular solid); both give a watertight mesh.
    """
    return _solid(trimesh.creation.revolve(np.asarray(profile_rz, float), sections=sections))


def _cross2(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """z component of the cross product of 2D vectors."""
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _circle(cx: float, cy: float, r: float, n: int) -> np.ndarray:
    """Polygon (n, 2) on a circle, counter-clockwise."""
    a = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    return np.column_stack([cx + r * np.cos(a), cy + r * np.sin(a)])


def _densify_convex(poly: np.ndarray, step: float) -> np.ndarray:
    """Subdivide the edges of a convex counter-clockwise polygon to at most ``step`` long.

    New points bulge outward by 1e-4 of their edge's length (a 10 um sagitta on a 10 cm
    edge), so the boundary stays strictly convex: every boundary edge is then a convex-hull
    edge, which Delaunay always keeps, and no triangle degenerates on collinear points.
    """
    out = []
    for p, q in zip(poly, np.roll(poly, -1, axis=0)):
        d = q - p
        length = float(np.linalg.norm(d))
        k = max(1, int(np.ceil(length / step)))
        t = np.arange(k)[:, None] / k
        normal = np.array([d[1], -d[0]]) / length  # outward for a counter-clockwise polygon
        out.append(p + t * d + 1e-4 * length * 4 * t * (1 - t) * normal)
    return np.vstack(out)


def _prism(outer: np.ndarray, holes: list[tuple[float, float, float]], z0: float, z1: float,
           step: float = 0.01) -> trimesh.Trimesh:
    """Extrude a convex polygon with round through-holes between heights z0 and z1.

    Triangulation without shapely: Delaunay of the densified boundary points, then drop the
    triangles whose centroid lies outside the polygon or inside a hole. The boundary spacing is
    kept below 0.6 x the narrowest gap between features, so every hole chord is a Gabriel edge
    and survives; the outer edges survive as convex-hull edges.
    """
    outer = np.asarray(outer, float)
    if _cross2(outer[1] - outer[0], outer[2] - outer[1]) < 0:
        outer = outer[::-1]
    edge = np.roll(outer, -1, axis=0) - outer
    normal_in = np.column_stack([-edge[:, 1], edge[:, 0]]) / np.linalg.norm(edge, axis=1)[:, None]
    gaps = []
    for k, (cx, cy, r) in enumerate(holes):
        gaps.append(np.min(((np.array([cx, cy]) - outer) * normal_in).sum(axis=1)) - r)
        for cx2, cy2, r2 in holes[k + 1:]:
            gaps.append(np.hypot(cx - cx2, cy - cy2) - r - r2)
    if gaps:
        if min(gaps) <= 0:
            raise ValueError(f"prism holes overlap or cut the outline (gap {min(gaps):.4g} m)")
        step = min(step, 0.6 * min(gaps))
    loops = [_densify_convex(outer, step)]
    for cx, cy, r in holes:
        n = max(16, int(np.ceil(2 * np.pi * r / step)))
        loops.append(_circle(cx, cy, r, n)[::-1])  # clockwise: walls face into the hole
    pts = np.vstack(loops)
    tri = Delaunay(pts).simplices
    cen = pts[tri].mean(axis=1)
    rel = cen[:, None, :] - outer[None, :, :]
    keep = np.all(edge[None, :, 0] * rel[..., 1] - edge[None, :, 1] * rel[..., 0] > 0, axis=1)
    for cx, cy, r in holes:
        keep &= np.hypot(cen[:, 0] - cx, cen[:, 1] - cy) > r
    tri = tri[keep]
    a, b, c = pts[tri[:, 0]], pts[tri[:, 1]], pts[tri[:, 2]]
    cw = _cross2(b - a, c - a) < 0
    tri[cw] = tri[cw][:, ::-1]
    n = len(pts)
    verts = np.vstack([np.column_stack([pts, np.full(n, z0)]),
                       np.column_stack([pts, np.full(n, z1)])])
    faces = [tri[:, ::-1], tri + n]
    off = 0
    for loop in loops:
        m = len(loop)
        i = off + np.arange(m)
        j = off + (np.arange(m) + 1) % m
        faces.append(np.column_stack([i, j, j + n]))
        faces.append(np.column_stack([i, j + n, i + n]))
        off += m
    return _solid(trimesh.Trimesh(verts, np.vstack(faces), process=True))


def _star_prism(outline: np.ndarray, z0: float, z1: float) -> trimesh.Trimesh:
    """Extrude a polygon that is star-shaped about the origin (gear teeth): fan-triangulated."""
    outline = np.asarray(outline, float)
    m = len(outline)
    verts = np.vstack([np.column_stack([outline, np.full(m, z0)]),
                       np.column_stack([outline, np.full(m, z1)]),
                       [[0, 0, z0], [0, 0, z1]]])
    i = np.arange(m)
    j = (i + 1) % m
    faces = np.vstack([
        np.column_stack([np.full(m, 2 * m), j, i]),            # bottom, facing -z
        np.column_stack([np.full(m, 2 * m + 1), i + m, j + m]),  # top, facing +z
        np.column_stack([i, j, j + m]),
        np.column_stack([i, j + m, i + m]),
    ])
    return _solid(trimesh.Trimesh(verts, faces, process=True))


def _tube(path: np.ndarray, r_out: float, r_in: float, sections: int = 32) -> trimesh.Trimesh:
    """Hollow tube of wall r_in..r_out swept along a 3D polyline (parallel-transport frames)."""
    path = np.asarray(path, float)
    tang = np.gradient(path, axis=0)
    tang /= np.linalg.norm(tang, axis=1, keepdims=True)
    ref = np.array([0.0, 0.0, 1.0]) if abs(tang[0, 2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    u = np.cross(tang[0], ref)
    u /= np.linalg.norm(u)
    us = [u]
    for t in tang[1:]:
        u = u - np.dot(u, t) * t
        u /= np.linalg.norm(u)
        us.append(u)
    us = np.array(us)
    vs = np.cross(tang, us)
    a = np.linspace(0, 2 * np.pi, sections, endpoint=False)
    ring = np.cos(a)[None, :, None] * us[:, None, :] + np.sin(a)[None, :, None] * vs[:, None, :]
    m = len(path)
    outer = (path[:, None, :] + r_out * ring).reshape(-1, 3)
    inner = (path[:, None, :] + r_in * ring).reshape(-1, 3)
    verts = np.vstack([outer, inner])
    k = np.arange(sections)
    kn = (k + 1) % sections
    faces = []
    no = m * sections
    for s in range(m - 1):
        p0, p1 = s * sections, (s + 1) * sections
        faces += [np.column_stack([p0 + k, p0 + kn, p1 + kn]), np.column_stack([p0 + k, p1 + kn, p1 + k])]
        faces += [np.column_stack([no + p0 + k, no + p1 + kn, no + p0 + kn]),
                  np.column_stack([no + p0 + k, no + p1 + k, no + p1 + kn])]
    e0, e1 = 0, (m - 1) * sections
    faces += [np.column_stack([e0 + k, no + e0 + kn, e0 + kn]),           # start cap (annulus)
              np.column_stack([e0 + k, no + e0 + k, no + e0 + kn])]
    faces += [np.column_stack([e1 + k, e1 + kn, no + e1 + kn]),           # end cap
              np.column_stack([e1 + k, no + e1 + kn, no + e1 + k])]
    return _solid(trimesh.Trimesh(verts, np.vstack(faces), process=True))


def _thread_profile(r_major: float, r_minor: float, z0: float, z1: float, pitch: float) -> list:
    """Saw-tooth (r, z) points of a threaded section, as axial ridges (no helix needed at
    the camera's resolution)."""
    n = max(1, int((z1 - z0) / pitch))
    z = np.linspace(z0, z1, 2 * n + 1)
    r = np.where(np.arange(2 * n + 1) % 2 == 0, r_minor, r_major)
    return list(zip(r, z))


def _box(lo, hi) -> trimesh.Trimesh:
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    move = trimesh.transformations.translation_matrix((lo + hi) / 2)
    return trimesh.creation.box(extents=hi - lo, transform=move)


def _concat(meshes: list[trimesh.Trimesh]) -> trimesh.Trimesh:
    return trimesh.util.concatenate(meshes)


def _rot(axis: str, angle: float) -> np.ndarray:
    v = {"x": [1, 0, 0], "y": [0, 1, 0], "z": [0, 0, 1]}[axis]
    return trimesh.transformations.rotation_matrix(angle, v)


# --------------------------------------------------------------------------------------------
# part factories
# --------------------------------------------------------------------------------------------

def stepped_shaft(rng: np.random.Generator) -> trimesh.Trimesh:
    """Turned shaft with 2-4 diameter steps and chamfered ends."""
    length = rng.uniform(0.08, 0.25)
    r_max = rng.uniform(0.1, 0.2) * length
    r_max = min(r_max, 0.03)
    n = int(rng.integers(2, 5))
    seg = rng.dirichlet(np.full(n, 3.0)) * length
    radii = r_max * rng.uniform(0.5, 1.0, n)
    radii[int(rng.integers(n))] = r_max
    z = np.concatenate([[0.0], np.cumsum(seg)])
    ch = 0.1 * radii.min()
    prof = [(0.0, 0.0), (radii[0] - ch, 0.0), (radii[0], ch)]
    for k in range(n):
        prof.append((radii[k], z[k + 1] - (ch if k == n - 1 else 0.0)))
        if k < n - 1:
            prof.append((radii[k + 1], z[k + 1]))
    prof += [(radii[-1] - ch, length), (0.0, length)]
    return _revolve(np.array(prof))


def gear_shaft(rng: np.random.Generator) -> trimesh.Trimesh:
    """Shaft with a spur gear section (teeth cut on a wider cylinder), like the IPA gear shaft."""
    length = rng.uniform(0.10, 0.25)
    r_s = rng.uniform(0.05, 0.08) * length
    r_tip = min(r_s * rng.uniform(1.8, 2.8), 0.05)
    teeth = int(rng.integers(12, 31))
    module = 2 * r_tip / (teeth + 2)
    r_root = r_tip - 2.25 * module
    width = rng.uniform(0.15, 0.3) * length
    z1 = rng.uniform(0.2, 0.55) * length
    z2 = z1 + width
    r_step = r_s * rng.uniform(0.6, 0.85)
    z_step = rng.uniform(0.4, 0.8) * (length - z2) + z2
    ch = 0.1 * r_step
    left = _revolve(np.array([(0, 0), (r_step - ch, 0), (r_step, ch), (r_step, 0.3 * z1), (r_s, 0.3 * z1),
                              (r_s, z1), (0, z1)]))
    right = _revolve(np.array([(0, z2), (r_s, z2), (r_s, z_step), (r_step, z_step),
                               (r_step, length - ch), (r_step - ch, length), (0, length)]))
    pitch = 2 * np.pi / teeth
    ang = np.concatenate([k * pitch + pitch * np.array([0.0, 0.15, 0.45, 0.6]) for k in range(teeth)])
    rad = np.tile([r_root, r_tip, r_tip, r_root], teeth)
    gear = _star_prism(np.column_stack([rad * np.cos(ang), rad * np.sin(ang)]), z1, z2)
    return _concat([left, gear, right])


def ring(rng: np.random.Generator) -> trimesh.Trimesh:
    """Thick ring (bearing race / spacer) with chamfered edges."""
    r_out = rng.uniform(0.02, 0.10)
    r_in = r_out * rng.uniform(0.55, 0.85)
    h = r_out * rng.uniform(0.2, 0.6)
    ch = 0.1 * min(r_out - r_in, h)
    prof = np.array([(r_in + ch, 0), (r_out - ch, 0), (r_out, ch), (r_out, h - ch), (r_out - ch, h),
                     (r_in + ch, h), (r_in, h - ch), (r_in, ch), (r_in + ch, 0)])
    return _revolve(prof)


def washer(rng: np.random.Generator) -> trimesh.Trimesh:
    """Flat washer: thin annulus."""
    r_out = rng.uniform(0.015, 0.06)
    r_in = r_out * rng.uniform(0.35, 0.6)
    t = rng.uniform(0.002, 0.006)
    return _revolve(np.array([(r_in, 0), (r_out, 0), (r_out, t), (r_in, t), (r_in, 0)]))


def eye_bolt(rng: np.random.Generator) -> trimesh.Trimesh:
    """Lifting eye bolt: torus eye, collar and threaded shank (collar overlaps the eye a little)."""
    r_eye = rng.uniform(0.015, 0.035)
    r_wire = r_eye * rng.uniform(0.2, 0.32)
    d = min(2 * r_wire * rng.uniform(0.9, 1.2), 0.03)
    shank = min(rng.uniform(1.2, 2.5) * r_eye * 2, 0.24 - 2 * (r_eye + r_wire))
    eye = trimesh.creation.torus(r_eye, r_wire, major_sections=SECTIONS, minor_sections=16)
    eye.apply_transform(_rot("x", np.pi / 2))                  # eye in the xz plane, centered at 0
    top = -(r_eye + 0.5 * r_wire)
    collar_h = 0.6 * r_wire
    r_col = 1.6 * d / 2
    collar = _revolve(np.array([(0, top - collar_h), (r_col, top - collar_h), (r_col, top), (0, top)]))
    pitch = max(0.003, 0.15 * d)  # coarser than real threads: ridges finer than a pixel add only triangles
    z_top = top - collar_h
    z_end = z_top - shank
    prof = [(0.0, z_top), (d / 2, z_top)]
    prof += _thread_profile(d / 2, 0.85 * d / 2, z_end, z_top, pitch)[::-1]
    prof += [(0.0, z_end)]
    rod = _revolve(np.array(prof))
    return _concat([eye, collar, rod])


def _plate_with_holes(length: float, width: float, t: float, holes_x: list, r_hole: float) -> trimesh.Trimesh:
    """Plate [0,length] x [0,width] x [0,t] with round holes on its center line."""
    rect = np.array([(0, 0), (length, 0), (length, width), (0, width)])
    return _prism(rect, [(x, width / 2, r_hole) for x in holes_x], 0.0, t)


def _bracket(rng: np.random.Generator, legs: int) -> trimesh.Trimesh:
    width = rng.uniform(0.03, 0.08)
    t = rng.uniform(0.003, 0.008)
    base = rng.uniform(0.05, 0.2) if legs == 1 else rng.uniform(0.05, 0.16)
    leg = rng.uniform(0.04, 0.15) if legs == 1 else rng.uniform(0.03, 0.09)
    r_hole = min(width * rng.uniform(0.12, 0.25), 0.2 * min(base - 2 * t, leg))

    def holes(end: float, start: float) -> list:
        """One or two holes, centered between start and end, >= one radius from everything."""
        two = (end - start) / 3 >= 3 * r_hole + 0.005
        n = 2 if two else 1
        return list(np.linspace(start, end, n + 2)[1:-1])

    x1 = base - t if legs == 2 else base  # the base's free span, between the legs
    plate = _plate_with_holes(base, width, t, holes(x1, t), r_hole)
    pieces = [plate]
    up = _plate_with_holes(leg, width, t, holes(leg, 0.0), r_hole)
    # vertical leg in the yz plane at x in [0, t], from z = t to z = t + leg (abuts the base)
    m = np.eye(4)
    m[:3, :3] = [[0, 0, 1], [0, 1, 0], [-1, 0, 0]]  # plate x -> world z, plate z -> world -x
    m[:3, 3] = [t, 0, t]
    pieces.append(up.copy().apply_transform(m))
    if legs == 2:
        m2 = m.copy()
        m2[:3, 3] = [base, 0, t]
        pieces.append(up.copy().apply_transform(m2))
    return _concat(pieces)


def l_bracket(rng: np.random.Generator) -> trimesh.Trimesh:
    """Bent sheet-metal angle bracket with round holes in both legs."""
    return _bracket(rng, 1)


def u_bracket(rng: np.random.Generator) -> trimesh.Trimesh:
    """U (channel) bracket: base and two upright legs, all with holes."""
    return _bracket(rng, 2)


def hex_nut(rng: np.random.Generator) -> trimesh.Trimesh:
    """Hex nut M20-M48: hexagonal prism with a round bore."""
    s = rng.uniform(0.027, 0.075)  # width across flats
    d = s / 1.5
    h = d * rng.uniform(0.7, 0.9)
    hexagon = _circle(0, 0, s / np.sqrt(3), 6)
    r_b = 0.85 * d / 2
    return _prism(hexagon, [(0.0, 0.0, r_b)], 0.0, h)


def flange(rng: np.random.Generator) -> trimesh.Trimesh:
    """Pipe flange: disc with a bore and a bolt circle of 4-8 holes, plus a raised hub."""
    r = rng.uniform(0.04, 0.125)
    t = r * rng.uniform(0.12, 0.22)
    r_bore = r * rng.uniform(0.25, 0.4)
    r_hub = r_bore + (r - r_bore) * rng.uniform(0.25, 0.4)
    n = int(rng.choice([4, 6, 8]))
    r_bc = (r_hub + r) / 2
    r_h = min((r - r_hub) * rng.uniform(0.2, 0.3), r_bc * np.sin(np.pi / n) * 0.6)
    a = np.arange(n) * 2 * np.pi / n + rng.uniform(0, np.pi)
    holes = [(0.0, 0.0, r_bore)] + [(r_bc * np.cos(x), r_bc * np.sin(x), r_h) for x in a]
    disc = _prism(_circle(0, 0, r, 96), holes, 0.0, t)
    hub_h = t * rng.uniform(0.6, 1.4)
    hub = _revolve(np.array([(r_bore, t), (r_hub, t), (r_hub, t + hub_h), (r_bore, t + hub_h), (r_bore, t)]))
    return _concat([disc, hub])


def pipe_elbow(rng: np.random.Generator) -> trimesh.Trimesh:
    """Pipe elbow (45 or 90 degrees) with short straight ends."""
    r_out = rng.uniform(0.012, 0.035)
    r_in = r_out * (1 - rng.uniform(0.1, 0.2))
    bend = r_out * rng.uniform(1.5, 2.5)
    angle = float(rng.choice([np.pi / 4, np.pi / 2]))
    stub = r_out * rng.uniform(0.4, 1.5)
    n_arc = 24
    a = np.linspace(0, angle, n_arc)
    arc = np.column_stack([bend * (1 - np.cos(a)), np.zeros(n_arc), bend * np.sin(a)])
    d_end = np.array([np.sin(angle), 0.0, np.cos(angle)])
    path = np.vstack([[[0, 0, -stub]], arc, [arc[-1] + stub * d_end]])
    return _tube(path, r_out, r_in)


def pipe_tee(rng: np.random.Generator) -> trimesh.Trimesh:
    """Equal or reducing pipe tee (the branch starts inside the run's wall; no through-bore)."""
    r_out = rng.uniform(0.012, 0.035)
    r_in = r_out * (1 - rng.uniform(0.12, 0.2))
    half = r_out * rng.uniform(1.6, 3.0)
    r_b = r_out * rng.uniform(0.6, 1.0)
    r_b_in = r_b * r_in / r_out
    run = _revolve(np.array([(r_in, -half), (r_out, -half), (r_out, half), (r_in, half), (r_in, -half)]))
    z0 = np.sqrt(max(r_out ** 2 - r_b ** 2, 0.0)) * 0.98
    z1 = r_out + r_out * rng.uniform(1.0, 2.0)
    branch = _revolve(np.array([(r_b_in, z0), (r_b, z0), (r_b, z1), (r_b_in, z1), (r_b_in, z0)]))
    branch.apply_transform(_rot("y", np.pi / 2))  # branch along +x, run along z
    return _concat([run, branch])


def box_housing(rng: np.random.Generator) -> trimesh.Trimesh:
    """Open-top cast/sheet housing: floor and four walls with rectangular cut-outs."""
    a, b = rng.uniform(0.05, 0.2), rng.uniform(0.04, 0.15)
    c = rng.uniform(0.03, 0.1)
    t = rng.uniform(0.003, 0.008)
    parts = [_box([0, 0, 0], [a, b, t])]

    def wall(lo, hi, axis: int, cut: bool) -> list:
        """Wall box; with ``cut`` it is made of four boxes around a window."""
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        if not cut:
            return [_box(lo, hi)]
        span = hi[axis] - lo[axis]
        hz = hi[2] - lo[2]
        u0, u1 = np.sort(rng.uniform(0.2, 0.8, 2)) * span
        u1 = max(u1, u0 + 0.15 * span)
        w0, w1 = 0.25 * hz, rng.uniform(0.55, 0.8) * hz
        out = []
        for (s0, s1, h0, h1) in [(0, u0, 0, hz), (u1, span, 0, hz), (u0, u1, 0, w0), (u0, u1, w1, hz)]:
            l2, h2 = lo.copy(), hi.copy()
            l2[axis], h2[axis] = lo[axis] + s0, lo[axis] + s1
            l2[2], h2[2] = lo[2] + h0, lo[2] + h1
            out.append(_box(l2, h2))
        return out

    cuts = rng.random(4) < 0.5
    cuts[int(rng.integers(4))] = True
    parts += wall([0, 0, t], [a, t, c], 0, cuts[0])
    parts += wall([0, b - t, t], [a, b, c], 0, cuts[1])
    parts += wall([0, t, t], [t, b - t, c], 1, cuts[2])
    parts += wall([a - t, t, t], [a, b - t, c], 1, cuts[3])
    return _concat(parts)


def hex_bolt(rng: np.random.Generator) -> trimesh.Trimesh:
    """Hex head bolt M8-M24 with a threaded shank."""
    d = rng.uniform(0.008, 0.024)
    s = 1.5 * d
    k = 0.65 * d
    length = min(d * rng.uniform(3.5, 10.0), 0.2)
    head = _prism(_circle(0, 0, s / np.sqrt(3), 6), [], 0.0, k, step=s)
    pitch = max(0.003, 0.15 * d)
    z_thread = -rng.uniform(0.4, 1.0) * length
    prof = [(0.0, 0.0), (d / 2, 0.0), (d / 2, z_thread)]
    prof += _thread_profile(d / 2, 0.85 * d / 2, -length, z_thread, pitch)[::-1][1:]
    prof += [(0.0, -length)]
    shank = _revolve(np.array(prof))
    return _concat([head, shank])


def pulley(rng: np.random.Generator) -> trimesh.Trimesh:
    """V-belt pulley: rim with one or two V grooves, web and bored hub."""
    r = rng.uniform(0.03, 0.1)
    w = r * rng.uniform(0.35, 0.7)
    r_bore = r * rng.uniform(0.12, 0.25)
    r_hub = r_bore + r * rng.uniform(0.12, 0.2)
    grooves = int(rng.integers(1, 3))
    depth = r * rng.uniform(0.12, 0.2)
    web = w * rng.uniform(0.25, 0.45)
    r_web = r - depth - 0.1 * r
    # profile (r, z) walking the outline counter-clockwise in the (r, z) half plane
    prof = [(r_bore, 0.0), (r_hub, 0.0), (r_hub, (w - web) / 2), (r_web, (w - web) / 2), (r_web, 0.0),
            (r, 0.0)]
    gw = w / grooves
    for g in range(grooves):
        z0 = g * gw
        prof += [(r, z0 + 0.12 * gw), (r - depth, z0 + 0.38 * gw), (r - depth, z0 + 0.62 * gw),
                 (r, z0 + 0.88 * gw)]
    prof += [(r, w), (r_web, w), (r_web, (w + web) / 2), (r_hub, (w + web) / 2), (r_hub, w),
             (r_bore, w), (r_bore, 0.0)]
    return _revolve(np.array(prof))


# --------------------------------------------------------------------------------------------
# registry
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class PartSpec:
    """A built-in part: its factory and the ranges its size is drawn from.

    ``extent`` bounds the largest bounding-box side, ``d_max`` the distance from the geometric
    center to the farthest vertex (both metres), worked out from the factory's dimension ranges:
    d_max is at least half the largest extent and at most the bounding-box diagonal.
    """
    factory: Callable[[np.random.Generator], trimesh.Trimesh]
    extent: tuple[float, float]
    d_max: tuple[float, float]
    description: str


BUILTIN_PARTS: dict[str, PartSpec] = {
    # length 0.08-0.25, diameter <= 0.4 * length
    "stepped_shaft": PartSpec(stepped_shaft, (0.08, 0.25), (0.04, 0.27), "turned shaft, 2-4 steps"),
    # length 0.10-0.25, gear tip diameter <= 0.1
    "gear_shaft": PartSpec(gear_shaft, (0.10, 0.25), (0.05, 0.28), "shaft with a spur gear section"),
    # diameter 0.04-0.20, height <= 0.6 r
    "ring": PartSpec(ring, (0.04, 0.20), (0.02, 0.11), "thick ring / bearing race"),
    # diameter 0.03-0.12, thickness 2-6 mm
    "washer": PartSpec(washer, (0.03, 0.12), (0.015, 0.061), "flat washer"),
    # eye 0.03-0.09 across plus shank: total 0.06-0.25
    "eye_bolt": PartSpec(eye_bolt, (0.05, 0.25), (0.03, 0.18), "lifting eye bolt (ring screw)"),
    # legs 0.05-0.2 and 0.04-0.15
    "l_bracket": PartSpec(l_bracket, (0.05, 0.21), (0.03, 0.27), "angle bracket with holes"),
    "u_bracket": PartSpec(u_bracket, (0.05, 0.17), (0.03, 0.2), "U channel bracket with holes"),
    # across corners 0.031-0.087
    "hex_nut": PartSpec(hex_nut, (0.03, 0.09), (0.015, 0.06), "hex nut M20-M48"),
    # diameter 0.08-0.25
    "flange": PartSpec(flange, (0.08, 0.25), (0.04, 0.14), "flange with bolt holes and hub"),
    "pipe_elbow": PartSpec(pipe_elbow, (0.03, 0.25), (0.02, 0.2), "45/90 degree pipe elbow"),
    "pipe_tee": PartSpec(pipe_tee, (0.03, 0.25), (0.02, 0.2), "pipe tee"),
    "box_housing": PartSpec(box_housing, (0.04, 0.2), (0.025, 0.17), "open housing with cut-outs"),
    "hex_bolt": PartSpec(hex_bolt, (0.03, 0.22), (0.015, 0.21), "hex head bolt M8-M24"),
    "pulley": PartSpec(pulley, (0.06, 0.2), (0.03, 0.12), "V-belt pulley"),
}


def make_part(name: str, seed: int = 0) -> PartModel:
    """Build the built-in part ``name`` with dimensions drawn from ``seed`` (same seed, same part)."""
    if name not in BUILTIN_PARTS:
        raise KeyError(f"unknown built-in part {name!r}; choose one of: {', '.join(sorted(BUILTIN_PARTS))}")
    mesh = BUILTIN_PARTS[name].factory(np.random.default_rng(seed))
    return part_from_trimesh(mesh, name=name)
