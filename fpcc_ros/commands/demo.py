"""`fpcc demo`: the main job end to end, as a user would run it.

Starts the segmenter node in its own process, replays the demo bag into it over DDS (one frame
at a time, waiting for its outputs), records input and outputs to a new bag, prints a per-frame
summary and writes a PNG per frame.

SIGINT or SIGTERM stop it at any point: the node is stopped (SIGINT, then waited for), the
recorded bag is either complete or absent (its temporary folder removed), exit 130 / 143.
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

from fpcc_ros.commands._interrupt import StopSignal

DEFAULT_BAG = Path(__file__).resolve().parents[2] / "bags" / "demo"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--bag", type=Path, default=DEFAULT_BAG, help="input rosbag2 directory")
    parser.add_argument("--topic", default=None, help="cloud topic in the bag (default: the only one)")
    parser.add_argument("--out", type=Path, default=Path("demo_output"),
                        help="folder for the recorded bag, PNGs and the node log")
    parser.add_argument("--model", default="", help="ONNX model (default: the shipped one)")
    parser.add_argument("--part-radius", type=float, default=None, help="part d_max in metres")
    parser.add_argument("--timeout", type=float, default=60.0, help="seconds to wait per frame")


def run(args: argparse.Namespace) -> int:
    from fpcc_ros.commands._interrupt import exit_code, interruptible

    try:
        with interruptible() as stop:
            return _run(args, stop)
    except KeyboardInterrupt as exc:   # SIGINT or SIGTERM: the with blocks stopped the node
        print(f"fpcc demo: interrupted ({exc or 'SIGINT'}); the node was stopped and no "
              "partial bag was left", file=sys.stderr)
        return exit_code(exc)


def _run(args: argparse.Namespace, stop: StopSignal) -> int:
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    from msg_tools.bag import BagError, BagWriter
    from msg_tools.point_cloud2 import read_points, read_xyz
    from fpcc_ros.render import render_segmentation
    from fpcc_ros.replay import CloudClient, NodeProcess, bag_clouds_as_rclpy, isolated_ros_env

    try:
        clouds = bag_clouds_as_rclpy(args.bag, args.topic)
    except BagError as exc:
        print(f"fpcc demo: {exc}", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    ros_args = ["-r", "points:=/fpcc_demo/points", "-r", "segmented_points:=/fpcc_demo/segmented_points",
                "-r", "instances:=/fpcc_demo/instances",
                "-r", "instance_markers:=/fpcc_demo/instance_markers"]
    if args.model:
        ros_args += ["-p", f"model:={Path(args.model).resolve()}"]
    info_path = args.bag.with_suffix(".json")
    if args.part_radius is None and info_path.is_file():
        import json
        args.part_radius = json.loads(info_path.read_text()).get("part_radius")
        print(f"part_radius {args.part_radius} m from {info_path}")
    if args.part_radius is not None:
        ros_args += ["-p", f"part_radius:={args.part_radius}"]
    env = isolated_ros_env()
    for key in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE"):  # the player joins the node
        os.environ[key] = env[key]
    print(f"starting the segmenter node (ROS_DOMAIN_ID={env['ROS_DOMAIN_ID']}), "
          f"{len(clouds)} frames from {args.bag}")
    # rclpy's own handlers would shut the context down from another thread under the client
    # (see fpcc_ros.node_shutdown); interruptible() turns the signals into an exception instead
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    records = []
    with NodeProcess(ros_args, env=env, log_path=args.out / "node.log") as node:
        client = CloudClient(namespace="/fpcc_demo")
        try:
            if not client.wait_connected(timeout=90):
                print("fpcc demo: the node did not come up; its log:\n" + node.log(), file=sys.stderr)
                return 1
            for _, cloud in clouds:
                stop.check()
                record = client.send(cloud)
                if not client.wait_complete(record, args.timeout):
                    print(f"fpcc demo: no output within {args.timeout} s; node log:\n{node.log()}",
                          file=sys.stderr)
                    return 1
                records.append(record)
        finally:
            client.close()
            rclpy.try_shutdown()
        exit_code = node.stop()
    print(f"node stopped cleanly (exit {exit_code})" if exit_code == 0 else
          f"node exited with {exit_code}; see {args.out / 'node.log'}")

    bag_out = args.out / "segmented_bag"
    in_topic = "/camera/points"
    with BagWriter(bag_out, force=True) as writer:
        for (ts, _), rec in zip(clouds, records):
            writer.write(in_topic, ts, rec.input)
            for name, msg in rec.outputs.items():
                writer.write(f"/{name}", ts, msg)
        stop.check()   # a signal whose exception was lost must not commit the bag

    print(f"\n{'frame':>5} {'points':>8} {'valid':>8} {'instances':>9} {'latency ms':>10}")
    for i, rec in enumerate(records):
        out = rec.outputs["segmented_points"]
        points = read_points(out)
        labels, scores = points["label"], points["center_score"]
        xyz = read_xyz(rec.input)
        valid = int(np.isfinite(xyz).all(axis=1).sum())
        print(f"{i:>5} {len(xyz):>8} {valid:>8} {len(rec.outputs['instances'].poses):>9} "
              f"{rec.latency_s * 1e3:>10.0f}")
        render_segmentation(args.out / f"frame_{i:02d}.png", xyz, labels, scores,
                            shape=(rec.input.height, rec.input.width),
                            title=f"demo frame {i}: {len(rec.outputs['instances'].poses)} instances")
    lat = [r.latency_s * 1e3 for r in records]
    print(f"\nmedian latency {np.median(lat):.0f} ms over {len(records)} frames "
          f"(send -> all three outputs received, over DDS)")
    print(f"wrote {bag_out} and {len(records)} PNGs in {args.out}/")
    return 0 if exit_code == 0 else 1
