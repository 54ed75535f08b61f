"""Semantic segmentation of X-ray angiography frames with the bundled gated U-Net (onnxruntime).

Every frame is labelled pixel by pixel as 0 background, 1 vessel, 2 catheter,
3 balloon or 4 pacing lead (:data:`CLASSES`). The model was trained with
PyTorch (``segmentation_onnx/``, see its MODEL_CARD.md) and ships as an ONNX
file; only onnxruntime runs here.

Frames of any size and integer or float dtype are accepted: each frame is
normalized on its own (robust percentiles of its exposed pixels, so black
collimator or image-intensifier borders do not squash the contrast), frames
larger than ``max_side`` are scaled down for the network and the result is
scaled back, and each batch is padded to a multiple of 16 by reflection.
With ``tta=True`` the class probabilities are averaged over the frame and its
three mirror images (left-right, up-down, both), each at the frame's own size
and at 0.75 of it (``tta_scales``): eight network calls per frame for better
labels (docs/segmentation.md, "Test-time augmentation").
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from .errors import ArgumentError, InputFileError

__all__ = ["Segmenter", "CLASSES", "CLASS_COLOURS", "BUNDLED_MODELS", "TTA_SCALES", "normalize_frames",
           "overlay_labels", "bundled_model_path"]

#: Class index -> name of the label maps.
CLASSES: tuple[str, ...] = ("background", "vessel", "catheter", "balloon", "lead")
_MULTIPLE = 16
_BUNDLED = "gated_unet.onnx"
#: Names accepted as ``Segmenter(model=...)`` for the bundled gated U-Nets: fp32 and its static int8
#: quantization (7-bit weights; the default on the CPU: the same accuracy, 1.6x faster on AVX2 CPUs
#: and 2.4-11x on CPUs with VNNI, see MODEL_CARD.md), and the half-width network distilled from it
#: ("fast", ~3x faster, a little less accurate) and its int8 file.
BUNDLED_MODELS: dict[str, str] = {"fp32": _BUNDLED, "int8": "gated_unet_int8.onnx",
                                  "fast": "gated_unet_fast.onnx", "fast-int8": "gated_unet_fast_int8.onnx"}
#: The bundled model ``Segmenter()`` loads when onnxruntime runs on the CPU (fp32 with other
#: execution providers, whose int8 kernels are not what they are fast at).
DEFAULT_CPU_MODEL = "int8"
#: Memory layouts of onnxruntime's CPU convolutions (``Segmenter(layout=...)``).
LAYOUTS = ("auto", "nchwc", "nchw")
#: Default ``Segmenter(tta_scales=...)``: test-time augmentation runs the network on the frame
#: (and its mirror images) at its own size and at 0.75 of it. Held-out phantom frames, int8 model:
#: vessel / catheter / balloon IoU 0.837 / 0.747 / 0.838 with the mirrors at one size,
#: 0.847 / 0.775 / 0.870 with both sizes (docs/results.md, 2026-12-04).
TTA_SCALES: tuple[float, ...] = (1.0, 0.75)
#: The faster layout per (model file, threads), timed once per process.
_LAYOUT_CHOICE: dict[tuple[str, int | None], str] = {}


def bundled_model_path(name: str = _BUNDLED) -> Path:
    """Path of a model file shipped in the ``segmentation_onnx`` package data.

    Parameters
    ----------
    name : str
        File name inside the package (``'gated_unet.onnx'``, ``'unet.onnx'``, ...).
    """
    from importlib import resources

    try:
        ref = resources.files("segmentation_onnx") / name
    except ModuleNotFoundError as exc:  # pragma: no cover - broken install
        raise InputFileError("segmentation_onnx: the package holding the bundled model is not "
                             "installed; reinstall vesselcad") from exc
    path = Path(str(ref))
    if not path.is_file():
        raise InputFileError(f"{path}: bundled segmentation model not found; reinstall vesselcad "
                             "or pass model='path/to/model.onnx'")
    return path


def normalize_frames(frames: np.ndarray) -> np.ndarray:
    """Per-frame robust normalization to the network's input range (float32, about -1..1).

    Each frame is mapped linearly so that the 1st and 99th percentiles of its
    exposed pixels go to -1 and 1 (clipped to -2..2). Pixels at the frame's
    minimum or maximum value (black collimator blades, the corners outside an
    image intensifier's circle, saturated lung) are left out of the
    percentiles when they cover less than half the frame.

    Parameters
    ----------
    frames : ndarray, shape (N, H, W)
        Any real dtype.

    Returns
    -------
    ndarray of float32, shape (N, H, W)
    """
    x = np.asarray(frames)
    if x.ndim != 3:
        raise ArgumentError(f"frames: expected shape (N, H, W), got {x.shape}")
    x = x.astype(np.float32, copy=False)
    n = x.shape[0]
    step = max(1, int(np.sqrt(x.shape[1] * x.shape[2] / 40_000)))  # ~40k samples per frame
    sub = x[:, ::step, ::step].reshape(n, -1)
    lo_v = sub.min(axis=1, keepdims=True)
    hi_v = sub.max(axis=1, keepdims=True)
    exposed = (sub > lo_v) & (sub < hi_v)
    use = np.where(exposed.mean(axis=1, keepdims=True) >= 0.5, exposed, True)
    masked = np.where(use, sub, np.nan)
    lo, hi = np.nanpercentile(masked, [1.0, 99.0], axis=1)
    scale = np.maximum(hi - lo, 1e-6 * np.maximum(np.abs(hi), 1.0))
    out = (x - lo[:, None, None]) / scale[:, None, None] * 2.0 - 1.0
    return np.clip(out, -2.0, 2.0, out=out).astype(np.float32, copy=False)


@dataclass(frozen=True)
class _ModelIO:
    input: str
    output: str
    n_classes: int


class Segmenter:
    """Label X-ray angiography frames with the bundled (or a given) ONNX segmentation model.

    Parameters
    ----------
    model : path-like or {'fp32', 'int8', 'fast', 'fast-int8'}, optional
        An ``.onnx`` file with one input ``(N, 1, H, W)`` float32 and one
        output ``(N, C, H, W)`` of class logits (C >= 2; class order as in
        :data:`CLASSES`), or the name of a bundled model
        (:data:`BUNDLED_MODELS`). Default: the bundled gated U-Net, as its
        static int8 quantization (``'int8'``) when onnxruntime runs on the
        CPU and in fp32 (``'fp32'``) with any other execution provider. The
        int8 file gives the same labels on 99 % of the pixels and the same
        scores (phantom IoU, real Dice, the reconstruction end to end; its
        7-bit weights cannot saturate on CPUs without VNNI), 1.6x faster
        than fp32 on AVX2 CPUs and 2.4-11x on CPUs with VNNI (Intel since
        2019, AMD Zen 4); docs/segmentation.md. ``'fast'`` is a network of
        half the width (channels 8-16-32-64-128, distilled from the default
        one): about 3x faster, 0.02-0.03 lower IoU on vessels and catheters,
        fewer real guiding catheters labelled catheter (MODEL_CARD.md);
        ``'fast-int8'`` its int8 quantization.
    threads : int, optional
        CPU threads in all (default: onnxruntime's own choice, all physical
        cores, for a lone network call; the cores this process may run on,
        shared among ``workers``, for calls side by side).
    batch_size : int
        Frames per network call.
    workers : int, optional
        Network calls run side by side when a call has several to make
        (batches of frames, test-time augmentation's mirror images), each on
        ``threads // workers`` threads of one session (onnxruntime's ``run``
        is thread-safe and leaves the GIL). Default: 2 on the CPU where two
        or more threads are allowed, else 1. A convolution network spread
        over two threads of one call keeps them busy less than two calls on
        one thread each: 80 phantom frames of 512² took 4.8 s against 5.5 s
        on a 2-core AMD EPYC (int8; the same labels and probabilities, bit
        for bit; docs/segmentation.md). A lone call (one batch) runs on all
        ``threads``.
    max_side : int
        Frames whose longer side exceeds this are scaled down for the
        network (vessel widths then match what it was trained on) and the
        results scaled back to the input size. ``0`` disables scaling.
    providers : sequence of str, optional
        onnxruntime execution providers (default CPU), by name or as (name,
        options) pairs; one this onnxruntime does not have is refused (its
        own fallback to the CPU would hide the mistake).
    layout : {'auto', 'nchwc', 'nchw'}
        Memory layout of onnxruntime's CPU convolutions. ``'nchwc'`` is
        onnxruntime's default (its blocked-layout direct convolutions);
        ``'nchw'`` turns that transformation off (im2col and GEMM), which is
        2.8x faster for these networks on some CPUs (an Intel Xeon with
        AVX-512: 0.73 against 2.07 s per 512² frame on 2 cores; onnxruntime
        issue 26992) and may be slower on others. ``'auto'`` (default) times
        both once per process on a 128² frame and keeps the faster
        (``Segmenter.layout`` tells which); other providers than the CPU's
        keep onnxruntime's default.
    tta : bool
        Test-time augmentation by default (a call's ``tta=`` overrides it):
        the class probabilities are the mean over the frame and its
        left-right, up-down and doubly mirrored copies, each at every scale
        of ``tta_scales``, run through the network and mirrored and scaled
        back. Eight times the work at the default scales; on the 240 held-out
        phantom frames (int8 model) vessel / catheter / balloon IoU 0.822 /
        0.718 / 0.802 -> 0.847 / 0.775 / 0.870 (the mirrors at one size:
        0.837 / 0.747 / 0.838; docs/results.md). Off by default: whole runs
        are segmented for the phase matching, where speed counts;
        :func:`vesselcad.reconstruct` re-segments its two chosen frames with it.
    tta_scales : sequence of float
        Sizes, relative to the frame as the network sees it (after
        ``max_side``), at which test-time augmentation runs the network;
        default :data:`TTA_SCALES` ``(1.0, 0.75)``. The network was trained
        on crops scaled 0.55-1.9 times; at 0.75 thin vessels are found less
        well but catheters and balloons better, and the mean beats both.
        ``(1.0,)``: mirror images only (four network calls a frame).

    Examples
    --------
    >>> seg = Segmenter()
    >>> labels = seg(frames)                       # (N, H, W) uint8
    >>> labels, proba = seg(frames, return_proba=True)   # proba (N, 5, H, W) float32
    >>> labels = seg(frames, tta=True)             # mean over 4 mirror images x 2 sizes
    """

    def __init__(self, model: str | os.PathLike | None = None, *, threads: int | None = None,
                 batch_size: int = 4, max_side: int = 768, providers: Sequence[str] | None = None,
                 layout: str = "auto", tta: bool = False,
                 tta_scales: Sequence[float] = TTA_SCALES, workers: int | None = None):
        import onnxruntime as ort

        providers, names = self._check_providers(providers, ort.get_available_providers())
        cpu = names == ["CPUExecutionProvider"]
        if model is None:
            model = DEFAULT_CPU_MODEL if cpu else "fp32"
        if isinstance(model, str) and model in BUNDLED_MODELS:
            path = bundled_model_path(BUNDLED_MODELS[model])
        else:
            path = Path(model)
        if not path.is_file():
            raise InputFileError(f"{path}: segmentation model file not found")
        for name, value in (("batch_size", batch_size), ("threads", threads), ("workers", workers)):
            whole = isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))
            if (value is not None or name == "batch_size") and not (whole and value >= 1):
                raise ArgumentError(f"{name}: expected a whole number >= 1, got {value!r}")
        if int(max_side) != 0 and int(max_side) < 64:
            raise ArgumentError(f"max_side: expected 0 or >= 64, got {max_side}")
        if layout not in LAYOUTS:
            raise ArgumentError(f"layout: expected one of {LAYOUTS}, got {layout!r}")
        if not isinstance(tta, (bool, np.bool_)):
            raise ArgumentError(f"tta: expected True or False, got {tta!r}")
        try:
            if isinstance(tta_scales, (str, bytes)):
                raise TypeError
            scales = tuple(float(v) for v in tta_scales)
        except (TypeError, ValueError):
            raise ArgumentError(f"tta_scales: expected a sequence of numbers, got {tta_scales!r}") from None
        if not scales or not all(0.25 <= v <= 2.0 for v in scales):
            raise ArgumentError(f"tta_scales: expected one or more scales in [0.25, 2], got {tta_scales!r}")
        cores = int(threads) if threads is not None else _usable_cores()
        if workers is None:
            workers = 2 if cpu and cores >= 2 else 1
        workers = max(1, min(int(workers), cores))

        def session(nchwc: bool, n_threads: int | None = threads) -> Any:
            opts = ort.SessionOptions()
            if n_threads is not None:
                opts.intra_op_num_threads = int(n_threads)
            opts.inter_op_num_threads = 1
            opts.log_severity_level = 3
            try:
                return ort.InferenceSession(str(path), opts, providers=providers,
                                            disabled_optimizers=None if nchwc else ["NchwcTransformer"])
            except Exception as exc:  # onnxruntime raises its own exception types
                raise InputFileError(f"{path}: not a loadable ONNX model ({exc})") from exc

        self._session = session(True)
        self._io = self._check_io(path)
        plain = None
        if not cpu:
            layout = "nchwc"
        elif layout == "auto":
            key = (str(path.resolve()), threads)
            if key not in _LAYOUT_CHOICE:
                plain = session(False)
                try:
                    faster = self._probe(plain) < self._probe(self._session)
                except Exception:  # noqa: BLE001 - e.g. a model of fixed input size: keep the default
                    faster = False
                _LAYOUT_CHOICE[key] = "nchw" if faster else "nchwc"
            layout = _LAYOUT_CHOICE[key]
        if layout == "nchw":
            self._session = plain if plain is not None else session(False)
        # the session the workers share, each call on its share of the threads (same layout)
        self._shared = self._session if workers == 1 else session(layout != "nchw", cores // workers)
        self.workers = workers
        self.layout = layout
        self.path = path
        self.batch_size = int(batch_size)
        self.max_side = int(max_side)
        self.threads = threads
        self.tta = bool(tta)
        self.tta_scales = scales

    @staticmethod
    def _check_providers(providers: Any, available: Sequence[str]) -> tuple[list[Any], list[str]]:
        """The execution providers as onnxruntime takes them, and their names; unknown or unavailable
        ones refused.

        onnxruntime itself only warns and falls back to the CPU, which would also pick
        the model meant for another provider.
        """
        if providers is None:
            return ["CPUExecutionProvider"], ["CPUExecutionProvider"]

        def name(p: Any) -> str | None:
            if isinstance(p, str):
                return p
            pair = isinstance(p, tuple) and len(p) == 2 and isinstance(p[1], dict)
            return p[0] if pair and isinstance(p[0], str) else None

        seq = isinstance(providers, Sequence) and not isinstance(providers, (str, bytes))
        items = list(providers) if seq else []
        names = [name(p) for p in items]
        if not items or None in names:
            raise ArgumentError("providers: expected a list of onnxruntime execution provider names (or "
                                f"(name, options) pairs), e.g. ['CPUExecutionProvider'], got {providers!r}")
        missing = [n for n in names if n not in available]
        if missing:
            raise ArgumentError(f"providers: {', '.join(missing)} not available in this onnxruntime "
                                f"(available: {', '.join(available)})")
        return items, names

    def _probe(self, sess: Any, side: int = 128) -> float:
        """Seconds one call of ``sess`` takes on a ``side``² frame (after a first call)."""
        x = np.random.default_rng(0).random((1, 1, side, side), dtype=np.float32)
        sess.run([self._io.output], {self._io.input: x})
        t0 = time.perf_counter()
        sess.run([self._io.output], {self._io.input: x})
        return time.perf_counter() - t0

    def _check_io(self, path: Path) -> _ModelIO:
        ins, outs = self._session.get_inputs(), self._session.get_outputs()
        if len(ins) != 1 or len(outs) < 1:
            raise InputFileError(f"{path}: expected a model with one input and one output, got "
                                 f"{len(ins)} inputs and {len(outs)} outputs")
        i, o = ins[0], outs[0]
        if len(i.shape) != 4 or i.shape[1] not in (1, "1") or "float" not in i.type:
            raise InputFileError(f"{path}: input {i.name!r} must be float (N, 1, H, W), "
                                 f"got {i.type} {i.shape}")
        if len(o.shape) != 4 or "float" not in o.type:
            raise InputFileError(f"{path}: output {o.name!r} must be float (N, C, H, W), "
                                 f"got {o.type} {o.shape}")
        c = o.shape[1]
        if not isinstance(c, int) or c < 2:
            raise InputFileError(f"{path}: output {o.name!r} must have a fixed class count >= 2, got {c!r}")
        return _ModelIO(i.name, o.name, int(c))

    @property
    def n_classes(self) -> int:
        """Number of classes the model predicts."""
        return self._io.n_classes

    def __repr__(self) -> str:
        return (f"Segmenter(model={str(self.path)!r}, classes={self.n_classes}, max_side={self.max_side}, "
                f"layout={self.layout!r}, workers={self.workers}, tta={self.tta}, "
                f"tta_scales={self.tta_scales})")

    # ------------------------------------------------------------------ running
    def __call__(self, frames: Any, *, return_proba: bool = False, progress: bool = False,
                 tta: bool | None = None) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
        """Label frames.

        Parameters
        ----------
        frames : array-like, shape (N, H, W) or (H, W)
            uint8, uint16 (10-12 bits stored are fine: each frame is
            normalized on its own) or float.
        return_proba : bool
            Also return the per-class probabilities.
        progress : bool
            Show a progress bar over the batches.
        tta : bool, optional
            Test-time augmentation (mirror images at ``tta_scales``) for this
            call (default: the segmenter's ``tta``).

        Returns
        -------
        labels : ndarray of uint8, shape (N, H, W) (or (H, W) for one frame)
        proba : ndarray of float32, shape (N, C, H, W), only with ``return_proba``
        """
        x = np.asarray(frames)
        single = x.ndim == 2
        if single:
            x = x[None]
        if x.ndim != 3 or x.shape[0] == 0 or min(x.shape[1:]) < 8:
            raise ArgumentError(f"frames: expected (N, H, W) or (H, W) with H, W >= 8, got shape {x.shape}")
        if not (np.issubdtype(x.dtype, np.integer) or np.issubdtype(x.dtype, np.floating)
                or x.dtype == bool):
            raise ArgumentError(f"frames: expected integer or float pixels, got dtype {x.dtype}")
        if tta is None:
            tta = self.tta
        elif not isinstance(tta, (bool, np.bool_)):
            raise ArgumentError(f"tta: expected True, False or None, got {tta!r}")
        n, h, w = x.shape
        labels = np.empty((n, h, w), np.uint8)
        proba = np.empty((n, self.n_classes, h, w), np.float32) if return_proba else None
        size = self.batch_size
        side = self.workers > 1 and n > 1
        if side:  # as many batches for each worker, of at most batch_size frames (12 frames: 4 x 3)
            rounds = -(-n // (self.workers * size))
            size = -(-n // (self.workers * rounds))
        starts = range(0, n, size)
        if len(starts) == 1:
            side = False

        def run(s: int) -> int:
            p = self._run_batch(x[s:s + size], bool(tta), proba is not None,
                                self._shared if side else None)
            labels[s:s + len(p)] = p.argmax(axis=1)
            if proba is not None:
                proba[s:s + len(p)] = p
            return s

        from tqdm.auto import tqdm

        with _pool(self.workers if side else 1) as pool, tqdm(
                total=len(starts), desc="segment", unit="batch", disable=not progress) as bar:
            for _ in pool(run, starts):
                bar.update()
        if single:
            labels = labels[0]
            proba = proba[0] if proba is not None else None
        return (labels, proba) if return_proba else labels

    def _run_batch(self, frames: np.ndarray, tta: bool = False, proba: bool = True,
                   session: Any = None) -> np.ndarray:
        """Class probabilities (N, C, H, W) of raw frames; with ``proba=False`` only their
        arg-max is needed, and where nothing is averaged or resampled the network's scores are
        returned as they are (the softmax keeps their order: ~5 % of a frame's time saved).

        ``session`` is the one a worker of a call with several batches runs on; without it
        the batch is the call's only one, and test-time augmentation's network calls run side
        by side on the workers' shared session (or one by one on the lone one).
        """
        n, h, w = frames.shape
        z = normalize_frames(frames)
        f = 1.0
        if self.max_side and max(h, w) > self.max_side:
            f = self.max_side / max(h, w)
            hs, ws = max(16, round(h * f)), max(16, round(w * f))
            z = np.stack([cv2.resize(im, (ws, hs), interpolation=cv2.INTER_AREA) for im in z])
        hh, ww = z.shape[1:]
        if tta:
            # at each scale the padded frames and their mirror images (mirrored back
            # after the network, before the padding is cut off, then scaled back);
            # probabilities averaged
            flips = ((), (-1,), (-2,), (-2, -1))
            sized = []
            for scale in self.tta_scales:
                zs = z
                if scale != 1.0:
                    hs, ws = max(16, round(hh * scale)), max(16, round(ww * scale))
                    zs = np.stack([cv2.resize(im, (ws, hs), interpolation=cv2.INTER_AREA if scale < 1
                                              else cv2.INTER_LINEAR) for im in z])
                sized.append((_pad(zs), zs.shape[1:]))
            side = session is None and self.workers > 1
            sess = session if session is not None else (self._shared if side else self._session)

            def net(job: tuple[int, tuple[int, ...]]) -> np.ndarray:
                k, axes = job
                zs, (h1, w1) = sized[k]
                zi = np.ascontiguousarray(np.flip(zs, axes)) if axes else zs
                pi = self._proba(zi, sess)
                return (np.flip(pi, axes) if axes else pi)[:, :, :h1, :w1]

            jobs = [(k, axes) for k in range(len(sized)) for axes in flips]
            p = np.zeros((len(z), self.n_classes, hh, ww), np.float32)
            with _pool(self.workers if side else 1) as pool:
                out = pool(net, jobs)  # in order: the same sums as one call after another
                for _, (h1, w1) in sized:
                    ps = np.zeros((len(z), self.n_classes, h1, w1), np.float32)
                    for _ in flips:
                        ps += next(out)
                    if (h1, w1) != (hh, ww):
                        ps = _resize_proba(ps, hh, ww)
                    p += ps
            p /= len(flips) * len(self.tta_scales)
        elif not proba and f == 1.0:
            return self._logits(_pad(z), session)[:, :, :hh, :ww]
        else:
            p = self._proba(_pad(z), session)[:, :, :hh, :ww]
        if f != 1.0:
            p = _resize_proba(p, h, w)
        return p

    def _logits(self, z: np.ndarray, session: Any = None) -> np.ndarray:
        """The network's class scores (N, C, H, W) of normalized, padded frames (N, H, W)."""
        sess = self._session if session is None else session
        return sess.run([self._io.output], {self._io.input: z[:, None]})[0]

    def _proba(self, z: np.ndarray, session: Any = None) -> np.ndarray:
        """Class probabilities (N, C, H, W) of normalized, padded frames (N, H, W)."""
        logits = self._logits(z, session)
        e = np.exp(logits - logits.max(axis=1, keepdims=True))
        return (e / e.sum(axis=1, keepdims=True)).astype(np.float32)


def _usable_cores() -> int:
    """CPU cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - macOS, Windows
        return os.cpu_count() or 1


@contextmanager
def _pool(workers: int) -> Iterator[Callable[[Callable[[Any], Any], Iterable[Any]], Iterator[Any]]]:
    """``map`` over ``workers`` threads (results in order), or the plain one for one worker."""
    if workers <= 1:
        yield map
        return
    with ThreadPoolExecutor(workers, thread_name_prefix="vesselcad-segment") as ex:
        yield ex.map


def _pad(z: np.ndarray) -> np.ndarray:
    """Frames (N, H, W) padded at the bottom and right to a multiple of 16 (reflection)."""
    hh, ww = z.shape[1:]
    ph, pw = (-hh) % _MULTIPLE, (-ww) % _MULTIPLE
    if not (ph or pw):
        return z
    mode = "reflect" if min(hh, ww) > max(ph, pw) else "edge"
    return np.pad(z, ((0, 0), (0, ph), (0, pw)), mode=mode)


def _resize_proba(p: np.ndarray, h: int, w: int) -> np.ndarray:
    """Class probabilities (N, C, h0, w0) resampled (bilinear) to (N, C, h, w)."""
    return np.stack([np.stack([cv2.resize(c, (w, h), interpolation=cv2.INTER_LINEAR) for c in fr])
                     for fr in p])


#: Overlay colours (RGB) of the classes 1..4: vessel red, catheter green, balloon blue, lead yellow.
CLASS_COLOURS = np.array([[0, 0, 0], [230, 40, 40], [40, 200, 60], [60, 110, 255], [250, 210, 0]], np.uint8)


def overlay_labels(frame: np.ndarray, labels: np.ndarray, alpha: float = 0.45,
                   truth: np.ndarray | None = None) -> np.ndarray:
    """RGB picture of a frame with its label map blended in (and a truth outline, if given).

    Parameters
    ----------
    frame : ndarray (H, W)
        Any dtype; shown with the same normalization the model sees.
    labels : ndarray (H, W) of int
        Class per pixel (0..4).
    alpha : float
        Opacity of the class colours.
    truth : ndarray (H, W) of bool, optional
        A reference vessel mask drawn as a white outline.

    Returns
    -------
    ndarray of uint8, shape (H, W, 3)
    """
    frame, labels = np.asarray(frame), np.asarray(labels)
    if frame.ndim != 2 or labels.shape != frame.shape:
        raise ArgumentError(f"frame/labels: expected two (H, W) arrays of one shape, got {frame.shape} "
                            f"and {labels.shape}")
    g = np.clip((normalize_frames(frame[None])[0] + 1.0) * 127.5, 0, 255).astype(np.uint8)
    rgb = np.repeat(g[..., None], 3, axis=2)
    lab = np.clip(labels.astype(np.intp), 0, len(CLASS_COLOURS) - 1)
    m = lab > 0
    rgb[m] = ((1 - alpha) * rgb[m] + alpha * CLASS_COLOURS[lab[m]]).astype(np.uint8)
    if truth is not None:
        t = np.asarray(truth, bool).astype(np.uint8)
        edge = cv2.morphologyEx(t, cv2.MORPH_GRADIENT, np.ones((3, 3), np.uint8)) > 0
        rgb[edge] = 255
    return rgb
