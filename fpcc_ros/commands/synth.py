"""`fpcc synth`: synthetic bin-picking scenes (scene NPZ) from a mesh or a built-in part."""
from __future__ import annotations

import argparse
import os
import sys

from fpcc_ros.training.mesh import UNITS


def add_part_arguments(parser: argparse.ArgumentParser, positional_mesh: bool = False) -> None:
    """--part/--mesh (or a positional MESH), --unit, --scale, --part-seed: shared with part-info."""
    group = parser.add_mutually_exclusive_group(required=not positional_mesh)
    if positional_mesh:
        parser.add_argument("mesh", nargs="?", metavar="MESH", help="part mesh (STL, OBJ, PLY, ...)")
        group.add_argument("--builtin", metavar="NAME", help="a built-in part instead of a mesh")
    else:
        group.add_argument("--part", metavar="NAME", help="built-in part (see --list-parts)")
        group.add_argument("--mesh", metavar="PATH", help="part mesh (STL, OBJ, PLY, ...)")
        group.add_argument("--list-parts", action="store_true", help="list the built-in parts and exit")
    parser.add_argument("--unit", choices=sorted(UNITS), default="m",
                        help="length unit of the mesh file (default m)")
    parser.add_argument("--scale", type=float, default=1.0, help="extra scale applied to the mesh")
    parser.add_argument("--part-seed", type=int, default=0,
                        help="seed of a built-in part's random dimensions (default 0)")


def load_part(args: argparse.Namespace):
    """The PartModel chosen on the command line (raises MeshError / KeyError with a clear text)."""
    from fpcc_ros.training.mesh import load_mesh
    from fpcc_ros.training.parts import make_part
    name = getattr(args, "part", None) or getattr(args, "builtin", None)
    if name:
        return make_part(name, args.part_seed)
    return load_mesh(args.mesh, unit=args.unit, scale=args.scale)


def list_parts() -> None:
    from fpcc_ros.training.parts import BUILTIN_PARTS
    for name, spec in sorted(BUILTIN_PARTS.items()):
        lo, hi = spec.extent
        print(f"{name:14s} {spec.description} ({lo * 100:.0f}-{hi * 100:.0f} cm)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_part_arguments(parser)
    parser.add_argument("--out", metavar="DIR", help="output folder for scene_00000.npz ... and synth.json")
    parser.add_argument("--scenes", type=int, default=100, help="number of scenes (default 100)")
    parser.add_argument("--seed", type=int, default=0, help="scene i uses seed + i (default 0)")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1,
                        help="parallel processes (default: all cores); output does not depend on it")
    parser.add_argument("--parts", type=int, nargs=2, metavar=("MIN", "MAX"), default=None,
                        help="copies per scene, drawn uniformly (default: scaled to the part size)")
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--no-noise", action="store_true",
                        help="ideal depth: no noise, dropouts or flying pixels")


def run(args: argparse.Namespace) -> int:
    if getattr(args, "list_parts", False):
        list_parts()
        return 0
    if not args.out:
        print("fpcc synth: --out DIR is required", file=sys.stderr)
        return 2
    if args.scenes < 1 or args.workers < 1 or args.width < 16 or args.height < 16:
        print("fpcc synth: --scenes and --workers must be >= 1, --width/--height >= 16", file=sys.stderr)
        return 2
    if args.parts is not None and not 1 <= args.parts[0] <= args.parts[1]:
        print(f"fpcc synth: --parts MIN MAX needs 1 <= MIN <= MAX, got {args.parts[0]} {args.parts[1]}",
              file=sys.stderr)
        return 2
    from fpcc_ros.training.mesh import MeshError
    from fpcc_ros.training.synth import default_parts_range, generate_dataset
    try:
        part = load_part(args)
    except (MeshError, KeyError) as exc:
        print(f"fpcc synth: {exc.args[0] if exc.args else exc}", file=sys.stderr)
        return 2
    parts = tuple(args.parts) if args.parts else default_parts_range(part)
    print(f"part {part.name}: d_max (part_radius) {part.d_max:.4f} m, {parts[0]}-{parts[1]} copies per scene")
    paths = generate_dataset(args.out, part, args.scenes, args.seed, workers=min(args.workers, args.scenes),
                             parts_range=parts, width=args.width, height=args.height,
                             noise=not args.no_noise, part_seed=args.part_seed)
    print(f"wrote {len(paths)} scenes to {args.out}")
    return 0
