"""`fpcc train`: train FPCC-Net on scene NPZ files (see fpcc_ros.training.train)."""
from __future__ import annotations

import argparse
import json
import sys

from fpcc_ros.training.model import TINY, NetConfig
from fpcc_ros.training.train import TRAIN_ALPHA


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", nargs="+", default=[], metavar="DIR",
                        help="folders (or files) of scene NPZ files to train on (with --resume: "
                        "default the run's own)")
    parser.add_argument("--val", nargs="+", default=[], metavar="DIR",
                        help="folders of validation scenes (precision/recall per epoch)")
    parser.add_argument("--out", required=True, metavar="RUN_DIR",
                        help="run folder: checkpoints, history.csv, history.png")
    parser.add_argument("--epochs", type=int, default=30)
    parser.add_argument("--init", default=None, metavar="MODEL",
                        help="start from weights: a .pt checkpoint, an exported .onnx (uses the .pt "
                        "beside it), or 'default' (models/fpcc_default.pt)")
    parser.add_argument("--teacher", default=None, metavar="MODEL",
                        help="also learn to match this trained net's embedding and center score "
                        "at every point (distillation; same forms as --init), e.g. for a "
                        "narrower net cut from it by scripts/slice_net.py")
    parser.add_argument("--distill", type=float, default=1.0,
                        help="weight of the teacher-matching term (default 1)")
    parser.add_argument("--resume", action="store_true",
                        help="continue RUN_DIR/checkpoint_last.pt (same data, same batches)")
    parser.add_argument("--lr", type=float, default=1e-3)
    parser.add_argument("--weight-decay", type=float, default=1e-4,
                        help="decoupled (AdamW) decay of the weight matrices; norm scales and "
                        "biases never decay (default: %(default)g)")
    parser.add_argument("--batch", type=int, default=4)
    inherited = " (default: the --init model's, else the shipped model's {})"
    parser.add_argument("--block-size", type=int, default=None,
                        help="points per block; the card records it" + inherited.format(2048))
    parser.add_argument("--k", type=int, default=None,
                        help="neighbours per point in the kNN graph" + inherited.format(16))
    parser.add_argument("--knn-near", type=int, default=None,
                        help="dilated neighbourhood: this many nearest, the rest spread over "
                        "--knn-reach nearest (0 = plain kNN)" + inherited.format(8))
    parser.add_argument("--knn-reach", type=int, default=None, help=inherited.format(48).strip())
    parser.add_argument("--normals", action="store_const", const=True, default=None,
                        help="surface normals as three more input columns (touching parts "
                        "meet at creases); with --init of weights without them, those weights "
                        "are widened to take them, computing the same until trained (default: "
                        "the --init weights' choice, else off)")
    parser.add_argument("--voxel-factor", type=float, default=None,
                        help="voxel size as a fraction of the part radius" + inherited.format(0.1))
    parser.add_argument("--alpha", type=float, default=TRAIN_ALPHA,
                        help=f"weight of the center-score loss (default {TRAIN_ALPHA:g}; the "
                             "paper's 3 goes with its unnormalised embedding loss)")
    parser.add_argument("--prototype", type=float, default=0.0,
                        help="weight of a cross-entropy that puts every part point nearest its "
                        "own part's center prototype (default 0: off)")
    parser.add_argument("--no-augment", action="store_true",
                        help="no rotation / scale / voxel-size / dropout augmentation")
    parser.add_argument("--net", choices=("full", "tiny"), default="full",
                        help="layer widths: the paper's, or a tiny net for tests")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    parser.add_argument("--precision", choices=("auto", "fp32", "bf16"), default="auto",
                        help="the forward pass in bf16 autocast (weights and loss stay fp32): "
                        "~1.5x faster steps on CPUs with native bf16, same validation loss; "
                        "auto = bf16 where the CPU has AVX512-BF16 or AMX, else fp32")
    parser.add_argument("--val-every", type=int, default=1, metavar="N",
                        help="validate after every N-th epoch and after the last (default 1); "
                        "each validation of 12 piles takes about a tenth of a 100-scene epoch")
    parser.add_argument("--time-limit", type=float, default=0.0, metavar="MIN",
                        help="stop cleanly (checkpoint saved) after MIN minutes; 0 = no limit")
    parser.add_argument("--anneal-by-time", action="store_true",
                        help="with --time-limit: the learning rate's cosine decay ends by the "
                        "limit when the epochs would not fit in it (a fixed-budget fine-tune); "
                        "without it the decay follows the epochs, so a cut run resumes exactly")


def run(args: argparse.Namespace) -> int:
    from fpcc_ros.training.train import TrainConfig, data_config_for, train

    try:
        data = data_config_for(None if args.resume else args.init, k=args.k,
                               block_size=args.block_size, voxel_factor=args.voxel_factor,
                               knn_near=args.knn_near, knn_reach=args.knn_reach,
                               normals=args.normals)
        config = TrainConfig(
            epochs=args.epochs, lr=args.lr, weight_decay=args.weight_decay, batch=args.batch,
            alpha=args.alpha, prototype=args.prototype, augment=not args.no_augment,
            seed=args.seed, threads=args.threads,
            time_limit_min=args.time_limit, anneal_by_time=args.anneal_by_time,
            val_every=args.val_every, precision=args.precision, data=data,
            teacher=str(args.teacher or ""), distill=args.distill,
            net=TINY if args.net == "tiny" else NetConfig())
        summary = train(config, args.data, args.out, val=args.val, init=args.init,
                        resume=args.resume, command=["fpcc", *sys.argv[1:]])
    except (FileNotFoundError, ValueError) as exc:
        print(f"fpcc train: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(summary, indent=2))
    return 0
