"""`fpcc segment IN [--out OUT]`: the node's pipeline, offline, on a bag or a cloud file.

A rosbag2 directory in gives a bag out with the input topic plus `segmented_points`,
`instances` and `instance_markers` -- one output of each per input message, same stamps.
A file (NPZ / PLY / PCD / TXT) in gives an NPZ (or PLY) with labels and center scores.
Outputs are written under a temporary name and renamed when complete: interrupted by SIGINT
or SIGTERM, the command removes the temporary output and exits 130 / 143, so the output is
either complete or absent, never half-written under its final name.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from fpcc_ros.commands._interrupt import StopSignal, exit_code, interruptible
from fpcc_ros.commands._pipeline_options import add_pipeline_arguments, build_pipeline


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("input", type=Path, help="rosbag2 directory, or .npz/.ply/.pcd/.txt file")
    parser.add_argument("--out", type=Path, default=None,
                        help="output bag directory or .npz/.ply file (default: beside the input)")
    parser.add_argument("--topic", default=None, help="PointCloud2 topic (default: the only one)")
    parser.add_argument("--force", action="store_true", help="overwrite an existing output")
    parser.add_argument("--png", type=Path, default=None, help="also render the last frame here")
    add_pipeline_arguments(parser)


def run(args: argparse.Namespace) -> int:
    from msg_tools.bag import BagError
    from msg_tools.point_cloud2 import CloudFormatError
    from fpcc_ros.onnx_model import ModelLoadError
    from fpcc_ros.pipeline import ConfigError

    if not args.input.exists():
        print(f"fpcc segment: input {args.input} does not exist", file=sys.stderr)
        return 2
    try:
        with interruptible() as stop:
            pipeline = build_pipeline(args)
            if args.input.is_dir() or args.input.suffix == ".mcap":
                return _segment_bag(args, pipeline, stop)
            return _segment_file(args, pipeline, stop)
    except (ModelLoadError, ConfigError, BagError, CloudFormatError, ValueError, OSError) as exc:
        print(f"fpcc segment: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:   # SIGINT or SIGTERM: the temporary output is removed
        print(f"fpcc segment: interrupted ({exc or 'SIGINT'}); no output written",
              file=sys.stderr)
        return exit_code(exc)


def _segment_bag(args: argparse.Namespace, pipeline, stop: StopSignal) -> int:
    from msg_tools.bag import BagWriter, list_topics, pick_cloud_topic, read_messages
    from msg_tools.msg_types import ROSBAGS
    from msg_tools.point_cloud2 import CloudFormatError
    from fpcc_ros.frame import process_cloud

    topic = pick_cloud_topic(args.input, args.topic)
    out = args.out or args.input.with_name(args.input.stem + "_segmented")
    total = list_topics(args.input)  # validates the bag before we create anything
    rows, skipped, last = [], 0, None
    with BagWriter(out, force=args.force) as writer:
        writer.add_topic(topic, total[topic])
        for name, msgtype in (("/segmented_points", "sensor_msgs/msg/PointCloud2"),
                              ("/instances", "geometry_msgs/msg/PoseArray"),
                              ("/instance_markers", "visualization_msgs/msg/MarkerArray")):
            writer.add_topic(name, msgtype)
        for _, _, ts, msg in read_messages(args.input, [topic]):
            stop.check()
            writer.write(topic, ts, msg)
            try:
                frame = process_cloud(msg, pipeline, ROSBAGS)
            except CloudFormatError as exc:
                skipped += 1
                print(f"  message at {ts} ns skipped: {exc}", file=sys.stderr)
                continue
            except Exception as exc:  # noqa: BLE001 - as the node: one bad frame, not the bag
                skipped += 1
                print(f"  message at {ts} ns failed ({type(exc).__name__}: {exc}); skipped",
                      file=sys.stderr)
                continue
            writer.write("/segmented_points", ts, frame.cloud)
            writer.write("/instances", ts, frame.instances)
            writer.write("/instance_markers", ts, frame.markers)
            rows.append((ts, msg.width * msg.height, frame.result))
            last = (msg, frame)
        stop.check()   # a signal whose exception was lost must not commit the bag
    _print_table(rows)
    print(f"{len(rows) + skipped} input messages on {topic}: {len(rows)} segmented "
          f"(one output per topic each, same stamps), {skipped} malformed or failed and skipped")
    print(f"wrote {out}")
    if args.png and last:
        from msg_tools.point_cloud2 import read_xyz
        from fpcc_ros.render import render_segmentation
        msg, frame = last
        render_segmentation(args.png, read_xyz(msg), frame.result.labels, frame.result.center_score,
                            shape=(msg.height, msg.width))
        print(f"wrote {args.png}")
    return 0 if skipped == 0 else 1


def _segment_file(args: argparse.Namespace, pipeline, stop: StopSignal) -> int:
    from msg_tools.formats import read_scene, write_ply, write_npz

    xyz, extra = read_scene(args.input)
    shape = xyz.shape[:-1]
    out = args.out or args.input.with_name(args.input.stem + "_segmented.npz")
    if out.exists() and not args.force:
        print(f"fpcc segment: {out} exists; use --force to overwrite", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    result = pipeline.segment(xyz.reshape(-1, 3), tuple(shape) if len(shape) == 2 else None)
    labels = result.labels.reshape(shape)
    scores = result.center_score.reshape(shape)
    _print_table([(0, xyz.size // 3, result)])
    print(f"segmented in {(time.perf_counter() - t0) * 1e3:.0f} ms")
    stop.check()
    if out.suffix == ".ply":
        write_ply(out, xyz.reshape(-1, 3), labels=labels.reshape(-1), center_score=scores.reshape(-1))
    else:
        write_npz(out, points=xyz.astype(np.float32), instance=labels.astype(np.int32),
                  center_score=scores.astype(np.float32),
                  part_radius=np.float32(pipeline.config.part_radius))
    print(f"wrote {out}")
    if args.png:
        from fpcc_ros.render import render_segmentation
        render_segmentation(args.png, xyz, labels, scores, shape=shape if len(shape) == 2 else None,
                            ground_truth=extra.get("instance"))
        print(f"wrote {args.png}")
    return 0


def _print_table(rows) -> None:
    print(f"{'stamp ns':>20} {'points':>8} {'valid':>8} {'net pts':>8} {'instances':>9} {'ms':>7}")
    for ts, n, result in rows:
        print(f"{ts:>20} {n:>8} {result.num_valid:>8} {result.num_network_points:>8} "
              f"{result.num_instances:>9} {result.timings_ms.get('total', sum(result.timings_ms.values())):>7.0f}")
