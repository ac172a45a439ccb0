"""`fpcc part-info`: a part's size, geometric center and d_max (the runtime part_radius)."""
from __future__ import annotations

import argparse
import sys

import numpy as np

from fpcc_ros.commands.synth import add_part_arguments, load_part


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_part_arguments(parser, positional_mesh=True)


def run(args: argparse.Namespace) -> int:
    from fpcc_ros.training.mesh import MeshError
    if not args.mesh and not args.builtin:
        print("fpcc part-info: give a MESH file or --builtin NAME", file=sys.stderr)
        return 2
    try:
        part = load_part(args)
    except (MeshError, KeyError) as exc:
        print(f"fpcc part-info: {exc.args[0] if exc.args else exc}", file=sys.stderr)
        return 2
    fmt = lambda v: " ".join(f"{x:.4f}" for x in np.asarray(v))  # noqa: E731
    kind = ("centroid of the solid" if part.center_kind == "volume"
            else "centroid of the surface (mesh not closed)")
    print(f"part:        {part.name} ({part.source})")
    print(f"triangles:   {len(part.faces)}")
    print(f"extents:     {fmt(part.extents)} m")
    print(f"center:      {fmt(part.center)} m in the mesh frame ({kind})")
    if part.volume > 0:
        print(f"volume:      {part.volume * 1e6:.1f} cm^3")
    print(f"d_max:       {part.d_max:.4f} m (farthest vertex from the center)")
    print(f"part_radius: {part.d_max:.4f}  (suggested: d_max)")
    print(f"run:         ros2 run fpcc_ros segmenter --ros-args -p part_radius:={part.d_max:.4f}")
    return 0
