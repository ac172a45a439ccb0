#!/usr/bin/env python3
"""Cut a trained FPCC-Net down to narrower layers, as a warm start for training a faster one.

The network's time on a CPU follows its EdgeConv width (scripts/time_net_widths.py): width 32
with a 512-d global feature runs a block in about half the time of the paper's 64 / 1,024. A
narrower net trained from scratch needs the hours the shipped one took; cut from the shipped
one it starts with its strongest channels. Per layer this keeps the output channels with the
largest effective scale (|batch-norm gamma| / sqrt(running variance)) times the norm of the
weights that read them downstream, and the matching input columns of every later layer. The
result is an fpcc_ros checkpoint for `fpcc train --init` (the network widths follow it); it must
be trained before use (a cut net scores nothing as it is).

    .venv/bin/python scripts/slice_net.py models/fpcc_default.pt narrow.pt --edge 32 --global 512
    .venv/bin/python -m fpcc_ros.cli train --init narrow.pt --data DIR ... --out runs/narrow
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import torch  # noqa: E402 - after the checkout is on the path

from fpcc_ros.training.model import FPCCNet, NetConfig  # noqa: E402
from fpcc_ros.training.train import load_checkpoint, model_from_checkpoint  # noqa: E402

DENSE_KEYS = ("weight", "bias", "running_mean", "running_var")


def slice_state(state: dict, edge: int, glob: int) -> dict:
    """A checkpoint ``state`` cut to EdgeConv width ``edge`` and global width ``glob``."""
    old = NetConfig.from_dict(state.get("net", {}))
    e = old.edge_dim
    if not (1 <= edge <= e and 1 <= glob <= old.global_dim):
        raise ValueError(f"--edge {edge} / --global {glob}: must be 1..{e} / 1..{old.global_dim}, "
                         "the widths of the net being cut")
    sd = model_from_checkpoint(state).state_dict()

    def weight(name: str) -> torch.Tensor:
        return sd[f"{name}.linear.weight"]

    def scale(name: str) -> torch.Tensor:
        return sd[f"{name}.bn.weight"].abs() / torch.sqrt(sd[f"{name}.bn.running_var"] + 1e-5)

    def strongest(importance: torch.Tensor, n: int) -> torch.Tensor:
        return torch.sort(torch.topk(importance, n).indices).values

    def edge_reads(name: str) -> torch.Tensor:
        """How strongly an EdgeConv's first layer reads each input channel: it sees
        [x_i, x_j - x_i], so each channel has a column in both halves."""
        w = weight(name)
        return w[:, :e].norm(dim=0) + w[:, e:].norm(dim=0)

    glob_reads = weight("glob").norm(dim=0)                  # over the 3e local channels
    e1a = strongest(scale("edge1a") * weight("edge1b").norm(dim=0), edge)
    e1b = strongest(scale("edge1b") * (edge_reads("edge2a") + glob_reads[:e]), edge)
    e2a = strongest(scale("edge2a") * weight("edge2b").norm(dim=0), edge)
    e2b = strongest(scale("edge2b") * (edge_reads("edge3") + glob_reads[e:2 * e]), edge)
    e3 = strongest(scale("edge3") * glob_reads[2 * e:], edge)
    g = strongest(scale("glob") * weight("point1").norm(dim=0)[3 * e:], glob)
    local = torch.cat([e1b, e + e2b, 2 * e + e3])

    cut: dict[str, torch.Tensor] = {}

    def keep(name: str, rows: torch.Tensor | None = None, cols: torch.Tensor | None = None) -> None:
        w = weight(name)
        w = w[rows] if rows is not None else w
        cut[f"{name}.linear.weight"] = (w[:, cols] if cols is not None else w).contiguous()
        for key in DENSE_KEYS:
            value = sd[f"{name}.bn.{key}"]
            cut[f"{name}.bn.{key}"] = (value[rows] if rows is not None else value).contiguous()
        cut[f"{name}.bn.num_batches_tracked"] = sd[f"{name}.bn.num_batches_tracked"]

    keep("edge1a", rows=e1a)                     # reads the raw features: every column
    keep("edge1b", rows=e1b, cols=e1a)
    keep("edge2a", rows=e2a, cols=torch.cat([e1b, e + e1b]))
    keep("edge2b", rows=e2b, cols=e2a)
    keep("edge3", rows=e3, cols=torch.cat([e2b, e + e2b]))
    keep("glob", rows=g, cols=local)
    keep("point1", cols=torch.cat([local, 3 * e + g]))
    for name in ("point2", "emb_hidden", "score_hidden"):
        keep(name)
    for key in ("emb_out.weight", "emb_out.bias", "score_out.weight", "score_out.bias"):
        cut[key] = sd[key]

    config = NetConfig(edge_dim=edge, global_dim=glob, point_dims=old.point_dims,
                       head_dim=old.head_dim, embedding_dim=old.embedding_dim)
    narrow = FPCCNet(config)
    narrow.load_state_dict(cut)
    out = dict(state)
    out["model"] = narrow.state_dict()
    out["net"] = config.to_dict()
    out["sliced_from"] = {"net": old.to_dict()}
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("src", help="a checkpoint or the .pt beside an exported model")
    parser.add_argument("dst", help="the cut checkpoint to write")
    parser.add_argument("--edge", type=int, default=32, help="EdgeConv width (default 32)")
    parser.add_argument("--global", dest="glob", type=int, default=512,
                        help="global feature width (default 512)")
    args = parser.parse_args()
    state = load_checkpoint(args.src)
    try:
        cut = slice_state(state, args.edge, args.glob)
    except ValueError as exc:
        print(f"slice_net: {exc}", file=sys.stderr)
        return 2
    torch.save(cut, args.dst)
    params = sum(t.numel() for k, t in cut["model"].items() if not k.endswith("num_batches_tracked")
                 and "running" not in k)
    print(f"wrote {args.dst}: EdgeConv {args.edge}, global {args.glob}, {params} parameters; "
          "train it (fpcc train --init) before use")
    return 0


if __name__ == "__main__":
    sys.exit(main())
