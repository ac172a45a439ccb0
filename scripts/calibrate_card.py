#!/usr/bin/env python3
"""Pick score_threshold, feature_gate and screening_factor for MODEL on validation scenes; --write puts them in its
card (with the table's best F1 recorded under metrics.calibration).
    .venv/bin/python scripts/calibrate_card.py models/fpcc_default.onnx --data VAL_DIR --write
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from tqdm import tqdm  # noqa: E402

from fpcc_ros.calibrate import calibrate  # noqa: E402
from fpcc_ros.model_card import card_path_for  # noqa: E402
from fpcc_ros.onnx_model import FpccModel  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("model", type=Path)
    parser.add_argument("--data", type=Path, nargs="+", required=True)
    parser.add_argument("--thresholds", type=float, nargs="+",
                        default=[0.3, 0.35, 0.4, 0.45, 0.5, 0.55, 0.6])
    parser.add_argument("--gates", type=float, nargs="+", default=[0.75, 1.0, 1.5, 3.0])
    parser.add_argument("--screening", type=float, nargs="+", default=None,
                        help="screening factors to try (default: keep the card's)")
    parser.add_argument("--limit", type=int, default=0)
    parser.add_argument("--write", action="store_true")
    args = parser.parse_args()
    scenes = sorted(p for d in args.data for p in (d.rglob("*.npz") if d.is_dir() else [d]))
    if args.limit:
        scenes = scenes[:args.limit]
    model = FpccModel(args.model, threads=0)
    rows = calibrate(model, scenes, args.thresholds, args.gates, progress=tqdm,
                     screening_factors=args.screening)
    rows.sort(key=lambda r: -r.f1)
    print(f"{'theta':>6} {'gate':>6} {'gamma':>6} {'P':>6} {'R':>6} {'F1':>6}")
    for r in rows:
        print(f"{r.score_threshold:>6.2f} {r.feature_gate:>6.2f} {r.screening_factor:>6.2f} "
              f"{r.counts.precision:>6.3f} {r.counts.recall:>6.3f} {r.f1:>6.3f}")
    best = rows[0]
    print(f"best: score_threshold {best.score_threshold}, feature_gate {best.feature_gate}, "
          f"screening_factor {best.screening_factor} (F1 {best.f1:.3f} on {len(scenes)} scenes)")
    if args.write:
        path = card_path_for(args.model)
        card = json.loads(path.read_text())
        card["score_threshold"], card["feature_gate"] = best.score_threshold, best.feature_gate
        card["screening_factor"] = best.screening_factor
        card.setdefault("metrics", {})["calibration"] = {
            "scenes": [str(s) for s in scenes], "protocol": "visible",
            "score_threshold": best.score_threshold, "feature_gate": best.feature_gate,
            "screening_factor": best.screening_factor,
            "precision": best.counts.precision, "recall": best.counts.recall, "f1": best.f1}
        path.write_text(json.dumps(card, indent=2) + "\n")
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
