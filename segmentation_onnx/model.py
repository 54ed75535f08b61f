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

__all__ = ["GatedUNet", "Gate", "UNet", "build_model", "revive_dead_blocks", "DEFAULT_WIDTHS", "N_CLASSES"]

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
