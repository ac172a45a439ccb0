#!/usr/bin/env python3
"""The live `segmenter` node over DDS at fixed camera rates (same as `fpcc bench --scenes none --dds`).

A fresh node per rate; this process publishes the demo bag's 640x480 frames at the rate and
subscribes to the outputs. Prints latency (publish -> last output), output rate, dropped frames,
the age of the newest processed frame and its trend (a queue makes it grow), and node RSS.

    .venv/bin/python scripts/bench_dds.py                         # shipped model, 5 and 10 Hz
    .venv/bin/python scripts/bench_dds.py --rates 10 --seconds 30 --model models/x.onnx
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from fpcc_ros.bench_dds import dds_table, run_dds  # noqa: E402
from fpcc_ros.onnx_model import default_model_path  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", type=Path, default=None, help="default: the shipped model")
    ap.add_argument("--rates", type=float, nargs="+", default=[5.0, 10.0], metavar="HZ")
    ap.add_argument("--seconds", type=float, default=20.0, help="per rate")
    ap.add_argument("--threads", type=int, default=0, help="onnxruntime threads (0 = all)")
    ap.add_argument("--provider", choices=["cpu", "cuda"], default="cpu")
    ap.add_argument("--voxel-size", type=float, default=None)
    ap.add_argument("--transport", choices=["shm", "default"], default="shm")
    ap.add_argument("--json", type=Path, default=None, help="write the results as JSON")
    args = ap.parse_args()
    result = run_dds(args.model or default_model_path(), rates=args.rates, seconds=args.seconds,
                     threads=args.threads, provider=args.provider, voxel_size=args.voxel_size,
                     transport=args.transport, progress=lambda m: print(m, file=sys.stderr))
    print(dds_table(result))
    if args.json:
        args.json.write_text(json.dumps(result, indent=2) + "\n")
        print(f"wrote {args.json}")
    return 0 if all(r["no_queue"] for r in result["rates"]) else 1


if __name__ == "__main__":
    sys.exit(main())
