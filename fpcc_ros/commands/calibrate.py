"""`fpcc calibrate`: choose a model's score threshold, feature gate, screening factor, center
merge, center prototype and clustering mode (with its fragment settings) on validation scenes (never on evaluation data) and, with --write,
store them in its card."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("model", type=Path, help="the .onnx model (its card is beside it)")
    parser.add_argument("--data", type=Path, nargs="+", required=True, metavar="DIR",
                        help="validation scene NPZ files or folders of them")
    # the grid: per-part models chose θ 0.7 and gate 0.75 on the edges of the previous one
    # (θ 0.3-0.7, gate 0.75-1.5, γ 0.5-1.0); widened, the choice made on one half of the ring
    # screw's validation piles scored 0.654/0.664 on the other half instead of 0.625/0.630
    # (gear shaft: 0.542/0.611 vs 0.542/0.615); θ 0.3 and gate 1.5 were never the best
    parser.add_argument("--thresholds", type=float, nargs="+",
                        default=[0.4, 0.5, 0.6, 0.7, 0.8, 0.9])
    parser.add_argument("--gates", type=float, nargs="+", default=[0.6, 0.75, 1.0])
    parser.add_argument("--screening", type=float, nargs="+",
                        default=[0.3, 0.4, 0.5, 0.7, 0.8, 1.0],
                        help="screening factors γ to try (the paper: 0.8-1.0; elongated "
                        "parts want less, with --merges joining a part's several centers)")
    parser.add_argument("--merges", type=float, nargs="+", default=[0.0, 0.5, 0.7],
                        help="center_merge values to try (0 = off)")
    parser.add_argument("--prototypes", type=float, nargs="+", default=[0.0, 0.3, 0.6],
                        help="center_prototype values to try (part radii; 0 = the center "
                        "point's own embedding)")
    parser.add_argument("--voxel-factors", type=float, nargs="+", default=None, metavar="F",
                        help="voxel sizes to try in the grid, as fractions of the part radius "
                        "(default: the card's in the grid, then 0.1 0.08 0.07 0.06 at the best "
                        "settings). Each runs the network again on every scene; a finer voxel "
                        "gives thin or elongated parts more points and costs time (0.07 instead "
                        "of 0.1: ~1.8x a scene's time)")
    # the clustering's own settings multiply the grid (972 network settings above): by default
    # the card's mode and fragment settings are kept; give values to sweep them
    # both by default: a fresh export's card says paper, and the per-part recipe calibrated
    # on it alone left the better mode untried (gear shaft fine-tune: validation F1 0.652
    # paper, 0.750 connected; on 20 test piles 0.535 vs 0.619), at ~3.5x the time
    parser.add_argument("--clusterings", nargs="+", choices=("paper", "connected"),
                        default=["paper", "connected"],
                        help="clustering modes to try (default: both); connected: geometric "
                        "fragments decided by the centers, with the fragment settings below")
    parser.add_argument("--fragment-eps", dest="fragment_eps_values", type=float, nargs="+",
                        default=None, metavar="M",
                        help="connected: fragment radii in metres to sweep in the grid "
                        "(default: the card's in the grid, then 0.004-0.012 at the best connected "
                        "settings: models differ, a gear-shaft fine-tune wanted 0.004, the ring "
                        "screw's 0.006, ground truth 0.012)")
    parser.add_argument("--fragment-densities", type=int, nargs="+", default=None, metavar="N",
                        help="connected: DBSCAN min_samples values, input points")
    parser.add_argument("--fragment-min-points", type=int, nargs="+", default=None, metavar="N",
                        help="connected: smallest instance values, input points")
    parser.add_argument("--fragment-joins", type=float, nargs="+", default=None, metavar="J",
                        help="connected: a center's fragments join when together within a box "
                        "of this diagonal, part radii, to sweep in the grid (default: the "
                        "card's in the grid, then 1.2 2 3 at the best connected settings: the "
                        "shipped network wants 1.2, a ring-screw fine-tune 3)")
    parser.add_argument("--fragment-creases", type=float, nargs="+", default=None, metavar="C",
                        help="connected, organized clouds: concave-crease cut curvatures to "
                        "try, 1/m (0 = off; e.g. 0 60; default: the card's)")
    parser.add_argument("--objective", choices=("part-mean", "pooled"), default="part-mean",
                        help="what the best combination maximises: the mean over parts of each "
                        "part's F1 (scenes grouped by their part_name; every part counts once), "
                        "or the F1 of the counts pooled over all scenes (parts with many "
                        "instances per scene weigh most). With one part they agree")
    parser.add_argument("--limit", type=int, default=0, help="use only the first N scenes")
    parser.add_argument("--write", action="store_true", help="put the best values in the card")


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from fpcc_ros.calibrate import (REFINE_FRAGMENT_EPS, REFINE_FRAGMENT_JOINS,
                                    REFINE_VOXEL_FACTORS, SWEPT_SETTINGS, calibrate,
                                    refine_fragment_eps, refine_fragment_join,
                                    refine_voxel_factor, settings_on_grid_edge)
    from fpcc_ros.model_card import ModelCardError, card_path_for
    from fpcc_ros.onnx_model import FpccModel, ModelLoadError

    missing = [str(d) for d in args.data if not d.exists()]
    if missing:
        print(f"fpcc calibrate: --data {' '.join(missing)}: no such file or folder",
              file=sys.stderr)
        return 2
    if args.voxel_factors and min(args.voxel_factors) <= 0:
        print(f"fpcc calibrate: --voxel-factors {' '.join(map(str, args.voxel_factors))}: every "
              "value must be > 0 (a fraction of the part radius, e.g. 0.1 0.08)", file=sys.stderr)
        return 2
    scenes = sorted(p for d in args.data for p in (d.rglob("*.npz") if d.is_dir() else [d]))
    if args.limit:
        scenes = scenes[:args.limit]
    if not scenes:
        print(f"fpcc calibrate: no scene NPZ files in {' '.join(map(str, args.data))}; "
              "make some with `fpcc synth --out DIR`", file=sys.stderr)
        return 2
    try:
        model = FpccModel(args.model, threads=0)
    except (FileNotFoundError, ModelCardError, ModelLoadError) as exc:
        print(f"fpcc calibrate: {exc}", file=sys.stderr)
        return 2
    rows = calibrate(model, scenes, args.thresholds, args.gates, progress=tqdm,
                     screening_factors=args.screening, merges=args.merges,
                     prototypes=args.prototypes, voxel_factors=args.voxel_factors,
                     clusterings=args.clusterings, fragment_eps_values=args.fragment_eps_values,
                     fragment_densities=args.fragment_densities,
                     fragment_min_points=args.fragment_min_points,
                     fragment_joins=args.fragment_joins,
                     fragment_creases=args.fragment_creases)
    if args.fragment_eps_values is None and "connected" in args.clusterings:
        print("fragment_eps: " + " ".join(f"{e * 1e3:g}" for e in REFINE_FRAGMENT_EPS)
              + " mm at the best connected settings", file=sys.stderr)
        rows = refine_fragment_eps(model, scenes, rows, args.objective, progress=tqdm)
    if args.fragment_joins is None and "connected" in args.clusterings:
        print("fragment_join: " + " ".join(f"{j:g}" for j in REFINE_FRAGMENT_JOINS)
              + " part radii at the best connected settings", file=sys.stderr)
        rows = refine_fragment_join(model, scenes, rows, args.objective, progress=tqdm)
    if args.voxel_factors is None:
        print("voxel_factor: " + " ".join(f"{f:g}" for f in REFINE_VOXEL_FACTORS)
              + " at the best settings (finer: more network points, slower)", file=sys.stderr)
        rows = refine_voxel_factor(model, scenes, rows, args.objective, progress=tqdm)
    rows.sort(key=lambda r: -r.score(args.objective))
    parts = len(rows[0].part_counts) or 1
    print(f"{'theta':>6} {'gate':>6} {'gamma':>6} {'merge':>6} {'proto':>6} {'voxel':>6} "
          f"{'cluster':>9} {'eps mm':>6} {'dens':>4} {'fmin':>4} {'join':>4} {'crease':>6} "
          f"{'P':>6} {'R':>6} {'F1':>6} {'partF1':>6}")
    for r in rows[:15]:
        print(f"{r.score_threshold:>6.2f} {r.feature_gate:>6.2f} {r.screening_factor:>6.2f} "
              f"{r.center_merge:>6.2f} {r.center_prototype:>6.2f} {r.voxel_factor:>6.3f} "
              f"{r.clustering:>9} {r.fragment_eps * 1e3:>6.1f} {r.fragment_density:>4} "
              f"{r.fragment_min_points:>4} {r.fragment_join:>4.1f} {r.fragment_crease:>6.0f} "
              f"{r.counts.precision:>6.3f} {r.counts.recall:>6.3f} {r.f1:>6.3f} "
              f"{r.part_mean_f1:>6.3f}")
    best = rows[0]
    chosen = {name: getattr(best, name) for name, _ in SWEPT_SETTINGS}
    print(f"best ({args.objective}): {', '.join(f'{k} {v}' for k, v in chosen.items())} "
          f"(pooled F1 {best.f1:.3f}, mean part F1 {best.part_mean_f1:.3f}; "
          f"{len(scenes)} scenes, {parts} parts)")
    for name, option, value, side in settings_on_grid_edge(rows, best):
        print(f"note: {name} {value} is the {side} value tried; a better one may lie beyond "
              f"it: run again with more values in {option}")
    if args.write:
        path = card_path_for(args.model)
        card = json.loads(path.read_text())
        card.update(chosen)   # voxel_factor is also the density of fine-tuning from it
        card.setdefault("metrics", {})["calibration"] = {
            "scenes": [str(s) for s in scenes], "protocol": "visible", **chosen,
            "precision": best.counts.precision, "recall": best.counts.recall, "f1": best.f1,
            "objective": args.objective, "part_mean_f1": best.part_mean_f1, "parts": parts}
        path.write_text(json.dumps(card, indent=2) + "\n")
        print(f"wrote {path}")
    return 0
