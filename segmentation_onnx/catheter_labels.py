"""Partial training targets for guiding catheters on real flat-panel angiograms.

The real images with manual masks (CIMAT) label vessels only, and their
catheters are mostly outside the cropped field; the model therefore called
real guiding catheters "vessel" (MODEL_CARD.md), while phase matching on real
runs needs them as catheter. ``real_labels/arcade_catheters.json`` holds a
polyline per image of ``xca-real/unlabelled`` (ARCADE, CC BY 4.0), drawn by
eye from where the catheter enters the image to its tip. Here each polyline
is snapped to the dark tube (cheapest path through ``1 / (0.03 + s)``, ``s``
the larger of the model's vessel+catheter probability and a Sato ridge
filter), widened to the tube's half width, and turned into a target map:

* ``2`` catheter: tube pixels within the half width of the snapped path;
* ``1`` vessel: pixels the labelling model calls vessel with p > 0.9 that
  belong to the vessel tree reached from the catheter tip (so leads, wires
  and other catheters the model mislabels are not taught back) and lie more
  than 10 px beyond the catheter and the image border;
* ``0`` background: pixels the model calls background with p > 0.9 that are
  not within 3 px of anything tubular (ridge response above 0.15, or vessel,
  catheter and lead probability above 0.2: the model misses thin real vessels,
  which must not be taught as background), and the
  dark vignette of the 10 px at the image border (the model drew it as vessel
  or balloon);
* :data:`~segmentation_onnx.data.IGNORE` everywhere else: the catheter's
  surroundings, 12 px around its tip (where catheter turns into vessel), and
  whatever the model is unsure of.

The file ``real_labels/arcade_catheters.npz`` holds the targets (uint8, one
per image) made with the round-7 fp32 model (shipped until round 11 took its
place); the images stay in ``../shared/data`` (their licence asks attribution,
see its README).

Run ``python -m segmentation_onnx.catheter_labels --model r7.onnx`` with that
file (``git show 7ebd024:segmentation_onnx/gated_unet.onnx > r7.onnx``) to
make the same targets again (checked identical); without ``--model`` the
shipped file labels them (needs the shared data; no torch).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np
from scipy import ndimage as ndi

from vesselcad.io.atomic import atomic_path, atomic_write_text

from .data import IGNORE, find_real_dir

HERE = Path(__file__).resolve().parent
POLYLINES = HERE / "real_labels" / "arcade_catheters.json"
TARGETS = HERE / "real_labels" / "arcade_catheters.npz"
#: Background / vessel pseudo-labels need this probability of the labelling model.
CONFIDENT = 0.9
#: Pixels around the catheter tip left unlabelled (px).
TIP_RADIUS = 12
#: Pixels whose ridge response (0..1) exceeds this, or near them, are not labelled background.
RIDGE_BG = 0.15
#: Width of the image border whose dark vignette is labelled background (px).
BORDER_PX = 10


def load_polylines(path: str | Path = POLYLINES) -> tuple[dict[str, np.ndarray], list[str]]:
    """Polylines (name -> (n, 2) x, y px) and the names kept out of training."""
    doc = json.loads(Path(path).read_text())
    lines = {k: np.asarray(v, dtype=int) for k, v in doc["catheters"].items()}
    return lines, list(doc["test"])


def snap(image: np.ndarray, fg_proba: np.ndarray, polyline: np.ndarray
         ) -> tuple[np.ndarray, float, np.ndarray]:
    """The polyline snapped to the dark tube.

    Returns the path pixels (n, 2) row, col, the tube's half width (px) and the ridge
    filter's response (0..1) over the image.
    """
    from skimage.filters import sato
    from skimage.graph import route_through_array

    im = image.astype(float) / max(float(image.max()), 1.0)
    ridge = sato(im, sigmas=[1, 2, 3], black_ridges=True)
    ridge = np.clip(ridge / max(np.percentile(ridge, 99.5), 1e-9), 0, 1)
    cost = 1.0 / (0.03 + np.maximum(fg_proba, ridge))
    path: list[tuple[int, int]] = []
    for (x0, y0), (x1, y1) in zip(polyline[:-1], polyline[1:], strict=True):
        idx, _ = route_through_array(cost, (int(y0), int(x0)), (int(y1), int(x1)),
                                     fully_connected=True, geometric=True)
        path.extend(idx if not path else idx[1:])
    rc = np.asarray(path)
    tube = (fg_proba > 0.5) | (ridge > 0.25)
    on = np.zeros(im.shape, bool)
    on[rc[:, 0], rc[:, 1]] = True
    half = float(np.clip(np.median(ndi.distance_transform_edt(tube)[on]) + 1.0, 2.0, 7.0))
    return rc, half, ridge


def make_target(image: np.ndarray, proba: np.ndarray, polyline: np.ndarray) -> np.ndarray:
    """Target map (uint8: 0, 1, 2 or IGNORE) of one image from the labelling model's probabilities.

    Parameters
    ----------
    image : ndarray (H, W) uint8
    proba : ndarray (5, H, W) float
        Class probabilities of the labelling model.
    polyline : ndarray (n, 2)
        The catheter, x, y px, from the image edge to its tip.
    """
    fg = proba[1] + proba[2]
    rc, half, ridge = snap(image, fg, polyline)
    on = np.zeros(image.shape, bool)
    on[rc[:, 0], rc[:, 1]] = True
    d_path = ndi.distance_transform_edt(~on)
    tube = (fg > 0.5) | (d_path <= 1.0)
    catheter = (d_path <= half) & tube
    yy, xx = np.mgrid[:image.shape[0], :image.shape[1]]
    tx, ty = polyline[-1]
    # the catheter ends at its tip: nothing beyond the plane through the tip across the path
    (bx, by) = polyline[-2]  # the drawn last segment gives the way in (the snapped path may hook)
    direction = np.array([ty - by, tx - bx], float)
    direction /= max(float(np.hypot(*direction)), 1e-9)
    catheter &= (yy - ty) * direction[0] + (xx - tx) * direction[1] <= 0
    near_tip = (yy - ty) ** 2 + (xx - tx) ** 2 <= TIP_RADIUS**2
    # the vessel tree the catheter feeds: foreground components reaching the tip's disk
    comp, _ = ndi.label(fg > 0.5, structure=np.ones((3, 3)))
    tree = np.isin(comp, np.unique(comp[near_tip & (comp > 0)]))
    border = np.zeros(image.shape, bool)
    border[:BORDER_PX] = border[-BORDER_PX:] = True
    border[:, :BORDER_PX] = border[:, -BORDER_PX:] = True
    dark = image <= np.percentile(image[BORDER_PX:-BORDER_PX, BORDER_PX:-BORDER_PX], 2)
    t = np.full(image.shape, IGNORE, np.uint8)
    # background only where nothing tubular is: the model misses thin real vessels, which must not
    # be taught as background
    tubular = ndi.binary_dilation((ridge > RIDGE_BG) | (proba[1] + proba[2] + proba[4] > 0.2), iterations=3)
    t[(proba[0] > CONFIDENT) & ~tubular] = 0
    t[(proba[1] > CONFIDENT) & tree & ~border & (d_path > half + 10)] = 1
    t[border & ((proba[1] > 0.5) | (proba[3] > 0.5))] = IGNORE
    t[border & dark] = 0
    t[d_path <= half + 6] = IGNORE
    t[catheter] = 2
    t[near_tip & ~catheter] = IGNORE
    return t


def load_targets(path: str | Path = TARGETS, real_dir: str | Path | None = None, *, split: str = "train"
                 ) -> tuple[list[np.ndarray], list[np.ndarray], list[str]]:
    """Images (uint8, from ``xca-real/unlabelled``) and targets of the catheter-labelled set.

    ``split`` is ``"train"`` (the images not named in the ``test`` list of the JSON file beside
    ``path``), ``"test"`` or ``"all"``.
    """
    if split not in ("train", "test", "all"):
        raise ValueError(f"split must be 'train', 'test' or 'all', got {split!r}")
    _, test = load_polylines(Path(path).with_suffix(".json"))  # the polylines lie beside the targets
    d = find_real_dir(real_dir) / "unlabelled"
    imgs, tgts, names = [], [], []
    with np.load(path) as z:
        for name in sorted(z.files, key=lambda s: int(s.split("_")[-1])):
            if (split == "train" and name in test) or (split == "test" and name not in test):
                continue
            im = cv2.imread(str(d / f"{name}.png"), cv2.IMREAD_GRAYSCALE)
            if im is None:
                raise FileNotFoundError(f"{d / (name + '.png')}: image missing")
            imgs.append(im)
            tgts.append(z[name])
            names.append(name)
    return imgs, tgts, names


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", default="fp32", help="labelling model (default: the shipped fp32 file)")
    ap.add_argument("--real-dir", help="xca-real folder (default: see data.find_real_dir)")
    ap.add_argument("--polylines", default=str(POLYLINES), help="JSON of the drawn catheters")
    ap.add_argument("--out", default=str(TARGETS), help="targets (.npz); the JSON is copied beside it")
    a = ap.parse_args(argv)
    import vesselcad as vc

    seg = vc.Segmenter(a.model, threads=2)
    lines, _ = load_polylines(a.polylines)
    d = find_real_dir(a.real_dir) / "unlabelled"
    out = {}
    for name, poly in lines.items():
        im = cv2.imread(str(d / f"{name}.png"), cv2.IMREAD_GRAYSCALE)
        if im is None:
            raise FileNotFoundError(f"{d / (name + '.png')}: image missing")
        _, p = seg(im[None], return_proba=True)
        out[name] = make_target(im, p[0], poly)
    with atomic_path(a.out) as tmp, open(tmp, "wb") as f:
        np.savez_compressed(f, **out)
    beside = Path(a.out).with_suffix(".json")
    if beside.resolve() != Path(a.polylines).resolve():
        atomic_write_text(beside, Path(a.polylines).read_text())
    print(f"{len(out)} targets -> {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
