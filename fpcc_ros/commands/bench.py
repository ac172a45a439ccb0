"""`fpcc bench`: latency per stage and end to end, peak memory and accuracy of the same runs.

Runs the node's per-frame path (PointCloud2 in -> labels -> PointCloud2/PoseArray/markers out)
on the demo bag's frames and on generated 640x480 bins with 5 to 40 parts, several warm runs
each, and prints median and p90 per stage, peak RSS and precision/recall (visible protocol).
``--dds`` also measures the live node over DDS at fixed camera rates (fpcc_ros.bench_dds).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from fpcc_ros.commands._pipeline_options import (add_pipeline_arguments, build_pipeline,
                                                 positive_int)

SCENE_SETS = ("demo", "synth")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from fpcc_ros.bench import (DEFAULT_CACHE, DEFAULT_CROPS, DEFAULT_PART, DEFAULT_PART_SEED,
                                DEFAULT_PARTS)

    parser.add_argument("--scenes", type=_scene_sets, default=list(SCENE_SETS),
                        metavar="demo,synth", help="scene sets, comma separated, or 'none' "
                        "(with --dds: only the DDS measurement)")
    parser.add_argument("--parts", type=int, nargs="+", default=list(DEFAULT_PARTS), metavar="N",
                        help="parts per generated bin (default: %(default)s)")
    parser.add_argument("--part", default=DEFAULT_PART,
                        help="built-in part for the generated bins (default: %(default)s)")
    parser.add_argument("--part-seed", type=int, default=DEFAULT_PART_SEED,
                        help="its dimension draw (default: %(default)s, the demo bag's)")
    parser.add_argument("--crops", type=float, nargs="*", default=list(DEFAULT_CROPS),
                        metavar="F", help="also time central crops of the 20-part bin with "
                        "these fractions of the image area (latency vs valid points); none: "
                        "--crops with no value")
    parser.add_argument("--runs", type=positive_int, default=5,
                        help="timed runs per scene after one warm-up run (default: %(default)s)")
    parser.add_argument("--full-res", action="store_true",
                        help="also run every labelled scene once at full resolution (voxel "
                        "size 0) and compare precision/recall (slow)")
    parser.add_argument("--json", type=Path, default=None, metavar="OUT",
                        help="write the full report as JSON")
    parser.add_argument("--plot", type=Path, default=None, metavar="PNG",
                        help="latency vs number of instances and vs number of valid points")
    parser.add_argument("--from-json", type=Path, default=None, metavar="REPORT",
                        help="do not measure: print (and --plot/--markdown) a saved --json report")
    parser.add_argument("--markdown", type=Path, default=None, metavar="MD",
                        help="write the per-scene table and the goals as Markdown")
    parser.add_argument("--cache", type=Path, default=DEFAULT_CACHE,
                        help="generated scenes are kept here (default: %(default)s)")
    parser.add_argument("--block-halo", type=float, default=None,
                        help="context around each block in part radii (default: pipeline's)")
    parser.add_argument("--block-size", type=int, default=None,
                        help="points per block (default: the model card's)")
    parser.add_argument("--variants", nargs="+", default=[], metavar="KEY=VALUE[,KEY=VALUE]",
                        help="also run the scenes with these pipeline settings and compare "
                        "latency and accuracy, e.g. block_halo=0.5 block_size=4096")
    dds = parser.add_argument_group("live node over DDS (--dds)")
    dds.add_argument("--dds", action="store_true",
                     help="also start the node and send it the demo frames at fixed rates")
    dds.add_argument("--dds-rates", type=float, nargs="+", default=[5.0, 10.0], metavar="HZ")
    dds.add_argument("--dds-seconds", type=float, default=20.0,
                     help="seconds per rate (default: %(default)s)")
    add_pipeline_arguments(parser)


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from fpcc_ros import bench
    from fpcc_ros.onnx_model import ModelLoadError
    from fpcc_ros.pipeline import ConfigError

    def fail(message: str) -> int:
        print(f"fpcc bench: {message}", file=sys.stderr)
        return 2

    if args.from_json is not None:
        import json
        try:
            report = bench.report_from_json(json.loads(args.from_json.read_text()))
        except (OSError, ValueError, KeyError) as exc:
            return fail(f"--from-json {args.from_json}: {exc}")
        return _output(report, args, fail)
    extra = {k: v for k, v in (("block_halo", args.block_halo), ("block_size", args.block_size))
             if v is not None}
    try:
        pipeline = build_pipeline(args, **extra)
    except (ModelLoadError, ConfigError) as exc:
        return fail(str(exc))

    def bar(desc: str):
        return lambda it: tqdm(it, desc=desc, unit="scene", file=sys.stderr, leave=False)

    scenes: list = []
    try:
        if "demo" in args.scenes:
            scenes += bench.demo_scenes(cache=args.cache)
        if "synth" in args.scenes:
            scenes += bench.synth_scenes(sorted(set(args.parts)), part=args.part,
                                         part_seed=args.part_seed, cache=args.cache,
                                         crops=args.crops, progress=bar("scenes"))
    except ImportError as exc:
        return fail(f"generating the benchmark scenes needs the training dependencies ({exc}); "
                    "install requirements/train.txt or use --scenes demo")
    except Exception as exc:  # noqa: BLE001 - a bag or cache problem: say which
        return fail(f"cannot prepare the scenes ({type(exc).__name__}: {exc})")
    if args.part_radius is not None:
        for scene in scenes:
            scene.part_radius = args.part_radius

    try:
        for text in args.variants:
            pipeline.config.replace(**bench.parse_variant(text))
    except (ValueError, TypeError) as exc:
        return fail(f"--variants: {exc}")
    synth = [s for s in scenes if s.kind == "synth" and s.center_score is not None]
    post_scene = max(synth, key=lambda s: s.num_parts or 0) if synth else None
    report = bench.run_bench(pipeline, scenes, runs=args.runs, full_res=args.full_res,
                             postprocess_scene=post_scene, progress=bar("bench"))
    if args.variants:
        bench.run_variants(report, pipeline, scenes, args.variants, args.runs,
                           progress=bar("variants"))
    if args.dds:
        from fpcc_ros.bench_dds import run_dds
        report.dds = run_dds(model=pipeline.model.path, rates=args.dds_rates,
                             seconds=args.dds_seconds, threads=args.threads,
                             provider=args.provider, voxel_size=args.voxel_size,
                             progress=lambda msg: print(msg, file=sys.stderr, flush=True))

    return _output(report, args, fail)


def _output(report, args: argparse.Namespace, fail) -> int:
    from fpcc_ros import bench

    if report.scenes:
        print(report.table())
        print()
    if report.variants or any(r.full_res for r in report.scenes):
        print(report.variants_table())
        print()
    if report.dds:
        from fpcc_ros.bench_dds import dds_table
        print(dds_table(report.dds))
        print()
    print(report.summary())
    try:
        if args.json:
            print(f"wrote {bench.write_json(report, args.json)}")
        if args.markdown:
            args.markdown.parent.mkdir(parents=True, exist_ok=True)
            args.markdown.write_text(report.markdown())
            print(f"wrote {args.markdown}")
        if args.plot and report.scenes:
            print(f"wrote {bench.plot(report, args.plot)}")
    except OSError as exc:
        return fail(f"cannot write the output ({exc})")
    return 0


def _scene_sets(text: str) -> list[str]:
    names = [t.strip() for t in text.split(",") if t.strip()]
    if names == ["none"]:
        return []
    unknown = [n for n in names if n not in SCENE_SETS]
    if unknown or not names:
        raise argparse.ArgumentTypeError(f"--scenes {text!r}: use a comma-separated subset of "
                                         f"{', '.join(SCENE_SETS)}, or 'none'")
    return names
