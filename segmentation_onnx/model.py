"""The gated U-Net of the paper (§2.2) and the plain U-Net baseline with the same widths.

Encoder: four blocks of (3x3 conv, BN, ReLU) x 2 followed by 2x2 max-pooling, a
bottleneck block, and a decoder of four up-convolution blocks (2x2 transposed
convolution, concatenation with the skip features, (3x3 conv, BN, ReLU) x 2).
In the gated model every encoder block's output ``f`` reaches the decoder as
``f' = sigmoid(W f + b) * f`` with ``W`` a 1x1 convolution (channel mixing,
``c x c`` weights and ``c`` biases), so the network can up-weight the channels
that carry the cues of thin devices (catheter, lead) and balloons. The plain
U-Net passes ``f`` unchanged.

The output is ``(N, n_classes, H, W)`` logits; ``H`` and ``W`` must be multiples
of 16 (four poolings).
"""

from __future__ import annotations

import torch
from torch import nn

__all__ = ["GatedUNet", "Gate", "UNet", "build_model", "revive_dead_blocks", "shrink", "DEFAULT_WIDTHS",
           "N_CLASSES"]

#: Channels of the four encoder blocks and the bottleneck. The fp32 ONNX file stays below
#: 10 MB; a 512 x 512 frame takes about 0.4 s on two CPU cores (see MODEL_CARD.md).
DEFAULT_WIDTHS: tuple[int, ...] = (16, 32, 64, 128, 192)
#: background, vessel, catheter, balloon, lead
N_CLASSES = 5


def _block(c_in: int, c_out: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(c_in, c_out, 3, padding=1, bias=False),
        nn.BatchNorm2d(c_out),
        nn.ReLU(inplace=True),
        nn.Conv2d(c_out, c_out, 3, padding=1, bias=False),
        nn.BatchNorm2d(c_out),
        nn.ReLU(inplace=True),
    )


class Gate(nn.Module):
    """Channel gating ``f' = sigmoid(W f + b) * f`` with ``W`` a 1x1 convolution."""

    def __init__(self, channels: int):
        super().__init__()
        self.proj = nn.Conv2d(channels, channels, 1, bias=True)
        # Start near the identity scaled by 1/2 (sigmoid(0)), not at a random gating.
        nn.init.zeros_(self.proj.weight)
        nn.init.zeros_(self.proj.bias)

    def forward(self, f: torch.Tensor) -> torch.Tensor:
        return torch.sigmoid(self.proj(f)) * f


class UNet(nn.Module):
    """U-Net with four encoder and four decoder blocks; ``gated=True`` adds the gating modules.

    Parameters
    ----------
    in_channels : int
        Input channels (1: one normalized grey frame).
    n_classes : int
        Output classes (5: background, vessel, catheter, balloon, lead).
    widths : sequence of 5 int
        Channels of the four encoder blocks and of the bottleneck.
    gated : bool
        Insert a :class:`Gate` on each skip connection (the paper's model).
    """

    def __init__(self, in_channels: int = 1, n_classes: int = N_CLASSES,
                 widths: tuple[int, ...] = DEFAULT_WIDTHS, gated: bool = False):
        super().__init__()
        if len(widths) != 5:
            raise ValueError(f"widths: expected 5 channel counts, got {widths!r}")
        self.widths = tuple(int(w) for w in widths)
        self.gated = bool(gated)
        self.n_classes = int(n_classes)
        enc_w = self.widths[:4]
        self.encoders = nn.ModuleList()
        c = in_channels
        for w in enc_w:
            self.encoders.append(_block(c, w))
            c = w
        self.pool = nn.MaxPool2d(2)
        self.bottleneck = _block(enc_w[-1], self.widths[4])
        self.gates = nn.ModuleList([Gate(w) if gated else nn.Identity() for w in enc_w])
        self.ups = nn.ModuleList()
        self.decoders = nn.ModuleList()
        c = self.widths[4]
        for w in reversed(enc_w):
            self.ups.append(nn.ConvTranspose2d(c, w, 2, stride=2))
            self.decoders.append(_block(2 * w, w))
            c = w
        self.head = nn.Conv2d(enc_w[0], n_classes, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        skips = []
        for enc, gate in zip(self.encoders, self.gates, strict=True):
            x = enc(x)
            skips.append(gate(x))
            x = self.pool(x)
        x = self.bottleneck(x)
        for up, dec, skip in zip(self.ups, self.decoders, reversed(skips), strict=True):
            x = dec(torch.cat([up(x), skip], dim=1))
        return self.head(x)


class GatedUNet(UNet):
    """The paper's gated U-Net (:class:`UNet` with ``gated=True``)."""

    def __init__(self, in_channels: int = 1, n_classes: int = N_CLASSES,
                 widths: tuple[int, ...] = DEFAULT_WIDTHS):
        super().__init__(in_channels, n_classes, widths, gated=True)


def build_model(arch: str, widths: tuple[int, ...] = DEFAULT_WIDTHS) -> UNet:
    """``'gated'`` -> :class:`GatedUNet`, ``'plain'`` -> :class:`UNet` with the same widths."""
    if arch == "gated":
        return GatedUNet(widths=widths)
    if arch == "plain":
        return UNet(widths=widths, gated=False)
    raise ValueError(f"arch: expected 'gated' or 'plain', got {arch!r}")


def revive_dead_blocks(model: UNet, tol: float = 1e-3) -> list[str]:
    """Re-initialize the (conv, BN, ReLU) x 2 blocks whose batch norms have collapsed.

    Adam with *coupled* L2 weight decay (``torch.optim.Adam(weight_decay=...)``,
    rounds 1-6 of the bundled models) pulls every parameter whose loss gradient
    is small towards zero by about ``lr`` per step, whatever its size; once a
    batch norm's scale reaches zero, its block outputs a constant and receives
    no gradient again. The bundled models of rounds 1-6 lost their bottleneck
    this way (scales ~1e-41). A block is revived when every scale of one of
    its batch norms is below ``tol``: both convolutions get a fresh Kaiming
    initialization and the batch norms scale 1, shift 0 and fresh running
    statistics. The block's consumer keeps its (near-zero) weights, so the
    network's output does not jump: training grows the path back.

    Parameters
    ----------
    model : UNet
    tol : float
        Largest |scale| of a batch norm counted as dead.

    Returns
    -------
    list of str
        Names of the revived blocks (e.g. ``['bottleneck']``).
    """
    blocks = [(f"encoders.{i}", b) for i, b in enumerate(model.encoders)]
    blocks += [("bottleneck", model.bottleneck)]
    blocks += [(f"decoders.{i}", b) for i, b in enumerate(model.decoders)]
    revived = []
    for name, block in blocks:
        bns = [m for m in block if isinstance(m, nn.BatchNorm2d)]
        if not any(float(bn.weight.detach().abs().max()) < tol for bn in bns):
            continue
        with torch.no_grad():
            for m in block:
                if isinstance(m, nn.Conv2d):
                    nn.init.kaiming_normal_(m.weight, nonlinearity="relu")
                elif isinstance(m, nn.BatchNorm2d):
                    m.reset_parameters()
        revived.append(name)
    return revived


def _keep(bn: nn.BatchNorm2d, n: int) -> torch.Tensor:
    """Indices (sorted) of the ``n`` channels of ``bn`` with the largest |scale|."""
    return torch.sort(torch.argsort(bn.weight.detach().abs(), descending=True)[:n]).values


def _copy_block(dst: nn.Sequential, src: nn.Sequential, keep_in: torch.Tensor, n_mid: int,
                n_out: int) -> torch.Tensor:
    """Copy the kept channels of a (conv, BN, ReLU) x 2 block; return the kept output channels."""
    conv1, bn1, _, conv2, bn2, _ = src
    mid = _keep(bn1, n_mid)
    out = _keep(bn2, n_out)
    d1, dbn1, _, d2, dbn2, _ = dst
    d1.weight.copy_(conv1.weight[mid][:, keep_in])
    d2.weight.copy_(conv2.weight[out][:, mid])
    for d, s_, k in ((dbn1, bn1, mid), (dbn2, bn2, out)):
        for name in ("weight", "bias", "running_mean", "running_var"):
            getattr(d, name).copy_(getattr(s_, name)[k])
    return out


@torch.no_grad()
def shrink(model: UNet, widths: tuple[int, ...]) -> UNet:
    """A narrower network of the same kind, initialized from the channels of ``model`` that matter most.

    Channel pruning as a starting point for training a faster network: every
    block keeps the channels whose batch-norm scales are largest in absolute
    value (a channel with a small scale carries little signal to the next
    layer), and every convolution, gate, up-convolution and the head keep the
    weights between kept channels. The result computes an approximation of
    ``model``'s output that fine-tuning (best with ``model`` as the teacher,
    ``train.py --teacher``) brings back much faster than training from scratch.

    Parameters
    ----------
    model : UNet
        Trained network.
    widths : sequence of 5 int
        Channels of the narrower network, each at most ``model``'s.

    Returns
    -------
    UNet
        New network (gated when ``model`` is), in eval mode.
    """
    widths = tuple(int(w) for w in widths)
    if len(widths) != 5 or any(w < 1 or w > v for w, v in zip(widths, model.widths, strict=True)):
        raise ValueError(f"widths: expected 5 channel counts no larger than {model.widths}, got {widths!r}")
    small = UNet(widths=widths, gated=model.gated, n_classes=model.n_classes)
    keep = torch.arange(model.encoders[0][0].weight.shape[1])
    skips = []
    for dst, src, w in zip(small.encoders, model.encoders, widths[:4], strict=True):
        keep = _copy_block(dst, src, keep, w, w)
        skips.append(keep)
    if model.gated:
        for dst, src, k in zip(small.gates, model.gates, skips, strict=True):
            dst.proj.weight.copy_(src.proj.weight[k][:, k])
            dst.proj.bias.copy_(src.proj.bias[k])
    keep = _copy_block(small.bottleneck, model.bottleneck, keep, widths[4], widths[4])
    for dst_up, src_up, dst_dec, src_dec, skip, w, w_big in zip(
            small.ups, model.ups, small.decoders, model.decoders, reversed(skips), reversed(widths[:4]),
            reversed(model.widths[:4]), strict=True):
        # the up-convolution's outputs are the decoder's first inputs: keep those the decoder reads most
        reads = src_dec[0].weight.detach().abs().sum(dim=(0, 2, 3))[:w_big]
        up = torch.sort(torch.argsort(reads, descending=True)[:w]).values
        dst_up.weight.copy_(src_up.weight[keep][:, up])
        dst_up.bias.copy_(src_up.bias[up])
        keep = _copy_block(dst_dec, src_dec, torch.cat([up, skip + w_big]), w, w)
    small.head.weight.copy_(model.head.weight[:, keep])
    small.head.bias.copy_(model.head.bias)
    return small.eval()
