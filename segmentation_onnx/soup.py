"""Weight averaging ("model soup") of two checkpoints of one network.

Fine-tuning rounds that trade one class or one domain for another can be
blended by averaging their weights (Wortsman et al., 2022, "Model soups");
the model card's rounds 8, 11 and 13 measure such averages (the shipped
weights are the equal average of rounds 12 and 13). Floating-point
tensors (weights, biases, batch-norm statistics) are averaged; integer ones
(``num_batches_tracked``) are taken from the second checkpoint.

Usage::

    python -m segmentation_onnx.soup a.pt b.pt --out soup.pt [--weight 0.5]
    python -m segmentation_onnx.export soup.pt soup.onnx --int8 soup_int8.onnx
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import torch

__all__ = ["soup", "main"]


def soup(a: dict, b: dict, weight: float = 0.5) -> dict:
    """``(1 - weight) * a + weight * b`` of two checkpoints (dicts with ``model``, ``arch``, ``widths``).

    Raises
    ------
    ValueError
        The two are not the same network, or ``weight`` lies outside [0, 1].
    """
    if not 0.0 <= weight <= 1.0:
        raise ValueError(f"weight must lie in [0, 1], got {weight}")
    if (a.get("arch"), list(a.get("widths", []))) != (b.get("arch"), list(b.get("widths", []))):
        raise ValueError(f"different networks: {a.get('arch')} {a.get('widths')} and "
                         f"{b.get('arch')} {b.get('widths')}")
    sa, sb = a["model"], b["model"]
    if sa.keys() != sb.keys() or any(sa[k].shape != sb[k].shape for k in sa):
        raise ValueError("the checkpoints' tensors differ in names or shapes")
    model = {k: ((1.0 - weight) * sa[k].float() + weight * sb[k].float()).to(sa[k].dtype)
             if sa[k].is_floating_point() else sb[k].clone() for k in sa}
    return {"model": model, "step": 0, "arch": a["arch"], "widths": a["widths"]}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("a", help="first checkpoint (.pt)")
    ap.add_argument("b", help="second checkpoint (.pt)")
    ap.add_argument("--out", required=True, help="averaged checkpoint (.pt)")
    ap.add_argument("--weight", type=float, default=0.5, help="share of the second checkpoint")
    args = ap.parse_args(argv)
    ck = soup(torch.load(args.a, map_location="cpu"), torch.load(args.b, map_location="cpu"), args.weight)
    out = Path(args.out)
    tmp = out.with_name(f".{out.name}.tmp")
    torch.save(ck, tmp)
    os.replace(tmp, out)
    print(f"{args.a} x {1 - args.weight:g} + {args.b} x {args.weight:g} -> {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
