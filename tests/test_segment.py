"""Segmentation: the bundled ONNX model run with onnxruntime (vc.Segmenter), its input handling,
scores against the phantom's ground truth and real manual masks, and torch/ONNX parity."""

from __future__ import annotations

import subprocess
import sys
import threading
from pathlib import Path

import cv2
import numpy as np
import pytest

import vesselcad as vc
from vesselcad.errors import ArgumentError, InputFileError
from vesselcad.segment import CLASSES, normalize_frames, overlay_labels

REAL = Path(__file__).parent / "data" / "xca-real-val"
REAL_IDS = (4, 8, 12, 16, 20, 24, 28, 32, 36, 40)


@pytest.fixture(scope="module")
def seg() -> vc.Segmenter:
    return vc.Segmenter("fp32", threads=2)


@pytest.fixture(scope="module")
def phantom_frames():
    # The first three phantoms of the held-out test set (never trained on): the most opacified
    # frame and one random frame of each.
    from segmentation_onnx.data import TEST_SEED0, _test_one

    frames, labels = [], []
    for s in range(TEST_SEED0, TEST_SEED0 + 3):
        f, lab = _test_one(s)
        frames += f
        labels += lab
    return np.stack(frames), np.stack(labels)


def test_bundled_model_runs_without_torch():
    code = (
        "import sys; sys.modules['torch'] = None\n"
        "import numpy as np, vesselcad as vc\n"
        "seg = vc.Segmenter(threads=1)\n"
        "lab = seg(np.full((2, 64, 80), 100, np.uint8))\n"
        "assert lab.shape == (2, 64, 80) and lab.dtype == np.uint8, (lab.shape, lab.dtype)\n"
        "assert seg.n_classes == 5\n"
        "print('ok')\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and "ok" in r.stdout, r.stderr


def test_phantom_scores_against_ground_truth(seg, phantom_frames):
    from segmentation_onnx.evaluate import iou_per_class

    frames, labels = phantom_frames
    pred = seg(frames)
    iou = dict(zip(CLASSES, iou_per_class(pred, labels), strict=True))
    # These 6 frames: vessel 0.865, catheter 0.754, lead 0.949 (2026-12-04). The whole 240-frame test
    # set: vessel 0.82, catheter 0.72, lead 0.94 (docs/results.md; issue 12's goal there is 0.85).
    assert iou["background"] > 0.97
    assert iou["vessel"] >= 0.8
    assert iou["catheter"] > 0.65
    assert iou["lead"] > 0.85
    # the catheter is found mostly as catheter; the contrast-filled catheter taken for vessel is the
    # model's known weakness (about 30% of the catheter pixels of the test set)
    cath = labels == 2
    assert (pred[cath] == 2).mean() > 0.6
    assert (pred[cath] == 1).mean() < 0.3


def test_real_validation_dice(seg):
    dices = []
    for i in REAL_IDS:
        im = cv2.imread(str(REAL / f"{i}.png"), cv2.IMREAD_GRAYSCALE)
        gt = cv2.imread(str(REAL / f"{i}_gt.png"), cv2.IMREAD_GRAYSCALE) > 127
        p = seg(im) == 1
        dices.append(2 * (p & gt).sum() / (p.sum() + gt.sum()))
    # real angiograms the model never saw, manual masks: measured mean 0.745 (goal 0.80)
    assert np.mean(dices) > 0.70
    assert min(dices) > 0.6


def test_mirror_tta_is_mirror_equivariant(seg, phantom_frames):
    # Averaging over the frame and its three mirror images (at each of the two sizes) makes the
    # result commute with mirroring (sides of 256 and 192, multiples of 16: no padding to break
    # the symmetry); one network call alone does not (its convolutions are not mirror symmetric).
    frame = phantom_frames[0][0][128:384, 96:352]
    _, p = seg(frame, return_proba=True, tta=True)
    for axes in ((1,), (0,), (0, 1)):
        _, q = seg(np.ascontiguousarray(np.flip(frame, axes)), return_proba=True, tta=True)
        np.testing.assert_allclose(np.flip(q, tuple(a + 1 for a in axes)), p, atol=2e-5)
    _, p1 = seg(frame, return_proba=True)
    _, q1 = seg(np.ascontiguousarray(frame[:, ::-1]), return_proba=True)
    assert np.abs(q1[:, :, ::-1] - p1).max() > 1e-3
    # the mean of the four single calls at each size, by hand: the frame's own (256) and 0.75 of
    # it, which is what max_side=192 gives (the frame scaled down, the result scaled back)
    flips = ((), (1,), (0,), (0, 1))
    hand = np.mean([np.flip(seg(np.ascontiguousarray(np.flip(frame, a)), return_proba=True)[1],
                            tuple(x + 1 for x in a)) for a in flips], axis=0)
    mirror_only = vc.Segmenter("fp32", threads=2, tta=True, tta_scales=(1.0,))
    np.testing.assert_allclose(mirror_only(frame, return_proba=True)[1], hand, atol=1e-5)
    seg192 = vc.Segmenter("fp32", threads=2, max_side=192)
    small = np.mean([np.flip(seg192(np.ascontiguousarray(np.flip(frame, a)), return_proba=True)[1],
                             tuple(x + 1 for x in a)) for a in flips], axis=0)
    np.testing.assert_allclose(p, (hand + small) / 2, atol=1e-5)
    assert seg.tta_scales == (1.0, 0.75)
    # odd sizes: padded, mirrored, cut back to the frame
    lab, pr = seg(frame[:101, :77], return_proba=True, tta=True)
    assert lab.shape == (101, 77) and pr.shape == (5, 101, 77)
    np.testing.assert_allclose(pr.sum(axis=0), 1.0, atol=1e-5)
    assert vc.Segmenter(threads=2, tta=True).tta
    with pytest.raises(ArgumentError, match="tta"):
        seg(frame, tta="yes")
    with pytest.raises(ArgumentError, match="tta"):
        vc.Segmenter(tta=1)
    for bad in ((), (0.1,), "big", "1", (1.0, None)):
        with pytest.raises(ArgumentError, match="tta_scales"):
            vc.Segmenter(tta_scales=bad)


def test_mirror_tta_scores(seg, phantom_frames):
    from segmentation_onnx.evaluate import iou_per_class

    frames, labels = phantom_frames
    iou = iou_per_class(seg(frames, tta=True), labels)
    # Whole 240-frame test set (fp32): vessel 0.824 -> 0.848, catheter 0.719 -> 0.777 with the
    # mirrors at two sizes (docs/results.md); on these six frames at least as good as the vessel
    # goal of the tests
    assert iou[1] > 0.8
    assert iou[2] > 0.5


def test_any_size_and_dtype(seg, phantom_frames):
    frames, _ = phantom_frames
    f8 = frames[0]
    lab8 = seg(f8)
    assert lab8.shape == f8.shape and lab8.dtype == np.uint8
    # 12 bits stored in uint16: per-frame normalization makes the scale irrelevant
    f12 = f8.astype(np.uint16) * 16 + 7
    assert (seg(f12) == lab8).mean() > 0.995
    # odd sizes come back at their own size
    odd = f8[:301, :299]
    lab_odd, proba = seg(odd[None], return_proba=True)
    assert lab_odd.shape == (1, 301, 299) and proba.shape == (1, 5, 301, 299)
    np.testing.assert_allclose(proba.sum(axis=1), 1.0, atol=1e-5)
    np.testing.assert_array_equal(proba.argmax(axis=1), lab_odd)
    # labels alone come from the network's scores without the softmax: the same arg-max
    # (up to pixels whose two best probabilities round to one float)
    alone, (_, p3) = seg(frames[:3]), seg(frames[:3], return_proba=True)
    assert (alone == p3.argmax(axis=1)).mean() >= 1.0 - 1e-5
    # a 1024 x 1024 frame is run at max_side and scaled back; vessels still where they were
    big = cv2.resize(f8, (1024, 1024), interpolation=cv2.INTER_LINEAR)
    lab_big = seg(big)
    assert lab_big.shape == (1024, 1024)
    small = cv2.resize(lab_big, (512, 512), interpolation=cv2.INTER_NEAREST)
    v8, vb = lab8 == 1, small == 1
    if v8.sum() > 500:
        assert (v8 & vb).sum() / (v8 | vb).sum() > 0.6
    # batching does not change results
    seg1 = vc.Segmenter("fp32", threads=2, batch_size=1)
    np.testing.assert_array_equal(seg1(frames[:3]), seg(frames[:3]))


def test_normalize_frames_is_a_robust_linear_map():
    ramp = np.tile(np.arange(1000, dtype=np.float32), (100, 1))  # uniform 0..999
    z = normalize_frames(ramp[None])[0]
    lo, hi = np.percentile(ramp[:, ::1], [1, 99])
    # the 1st and 99th percentiles go to -1 and +1, linearly in between
    np.testing.assert_allclose(z[0, [10, 500, 989]], (np.array([10, 500, 989]) - lo) / (hi - lo) * 2 - 1,
                               atol=0.03)
    # a black border (shutter, intensifier corners) is left out of the percentiles
    framed = np.zeros((100, 1400), np.float32)
    framed[:, 400:] = ramp
    zf = normalize_frames(framed[None])[0]
    np.testing.assert_allclose(zf[:, 400:], z, atol=0.03)
    # constant frame: no division by zero
    assert np.isfinite(normalize_frames(np.full((1, 20, 20), 7, np.uint16))).all()


def test_overlay_picture(phantom_frames):
    frames, labels = phantom_frames
    rgb = overlay_labels(frames[0], labels[0], truth=labels[0] == 1)
    assert rgb.shape == (*frames[0].shape, 3) and rgb.dtype == np.uint8
    vessel = labels[0] == 1
    if vessel.any():  # vessel pixels are tinted red
        r, g = rgb[..., 0].astype(int), rgb[..., 1].astype(int)
        assert (r[vessel] - g[vessel]).mean() > 20


def test_bad_input_is_rejected(tmp_path, seg):
    with pytest.raises(InputFileError, match="nope.onnx"):
        vc.Segmenter(tmp_path / "nope.onnx")
    junk = tmp_path / "junk.onnx"
    junk.write_bytes(b"not a model")
    with pytest.raises(InputFileError, match="junk.onnx"):
        vc.Segmenter(junk)
    with pytest.raises(ArgumentError, match="frames"):
        seg(np.zeros((1, 1, 32, 32)))
    with pytest.raises(ArgumentError, match="frames"):
        seg(np.zeros((2, 32, 32), complex))
    with pytest.raises(ArgumentError, match="batch_size"):
        vc.Segmenter(batch_size=0)
    with pytest.raises(ArgumentError, match="layout"):
        vc.Segmenter(layout="nhwc")
    for name in ("workers", "threads", "batch_size"):
        for bad in (0, -2, True, "2", 1.5):
            with pytest.raises(ArgumentError, match=name):
                vc.Segmenter(**{name: bad})
    with pytest.raises(ArgumentError, match="batch_size"):
        vc.Segmenter(batch_size=None)
    # onnxruntime would only warn and fall back to the CPU (with the model meant for another provider)
    for bad in ("CPUExecutionProvider", [], [3], [("CPUExecutionProvider", 1)]):
        with pytest.raises(ArgumentError, match="providers: expected"):
            vc.Segmenter(providers=bad)
    with pytest.raises(ArgumentError, match="NoSuchExecutionProvider not available"):
        vc.Segmenter(providers=["NoSuchExecutionProvider", "CPUExecutionProvider"])
    assert vc.Segmenter(providers=[("CPUExecutionProvider", {})]).path.name == "gated_unet_int8.onnx"


class _Meeting:
    """A session whose first call in each of two threads waits for the other's: calls that do
    not overlap in time break the barrier (after 60 s) instead of passing."""

    def __init__(self, session):
        self.session, self.barrier, self.threads = session, threading.Barrier(2, timeout=60), set()

    def run(self, *args, **kwargs):
        me = threading.get_ident()
        if me not in self.threads:
            self.threads.add(me)
            self.barrier.wait()
        return self.session.run(*args, **kwargs)


class _Refuse:
    def run(self, *args, **kwargs):
        raise AssertionError("the workers' shared session was called")


def test_workers_run_network_calls_side_by_side(phantom_frames):
    # two calls on one thread each keep two cores busier than one call on two threads; the
    # labels and probabilities are those of one call after another
    frames = np.ascontiguousarray(phantom_frames[0][:5, 100:260, 80:272])  # 160 x 192
    one = vc.Segmenter("fp32", threads=2, workers=1)
    two = vc.Segmenter("fp32", threads=2, workers=2)
    assert (one.workers, two.workers) == (1, 2) and "workers=2" in repr(two)
    assert vc.Segmenter("fp32", threads=2).workers == 2  # the default where two threads are allowed
    assert vc.Segmenter("fp32", threads=1).workers == 1
    assert vc.Segmenter("fp32", threads=1, workers=4).workers == 1  # at most one per thread
    shared = two._shared
    # five frames: batches of 3 and 2, one per worker; with test-time augmentation each batch's
    # eight network calls run in its worker; one frame: its eight calls spread over both workers
    for x, tta in ((frames, False), (frames, True), (frames[0], True)):
        lab1, p1 = one(x, return_proba=True, tta=tta)
        two._shared = _Meeting(shared)
        lab2, p2 = two(x, return_proba=True, tta=tta)
        assert len(two._shared.threads) == 2 and not two._shared.barrier.broken
        assert np.array_equal(lab1, lab2)
        np.testing.assert_allclose(p2, p1, rtol=0, atol=1e-5)
        assert np.array_equal(lab2, two(x, tta=tta))  # labels alone (the scores' arg-max)
    # a call with one network call to make runs it on all the threads (the lone session)
    two._shared = _Refuse()
    assert np.array_equal(two(frames[1]), one(frames[1]))
    two._shared = shared


def test_both_convolution_layouts_compute_the_same_network(phantom_frames):
    # onnxruntime's blocked NCHWc convolutions and its plain im2col/GEMM ones are two
    # implementations of the same network: same labels, probabilities equal to float rounding.
    frames = phantom_frames[0][:2]
    out = {lay: vc.Segmenter("fp32", threads=2, layout=lay)(frames, return_proba=True)
           for lay in ("nchwc", "nchw")}
    assert np.array_equal(out["nchwc"][0], out["nchw"][0])
    assert np.abs(out["nchwc"][1] - out["nchw"][1]).max() < 1e-4
    assert vc.Segmenter("fp32", threads=2).layout in ("nchwc", "nchw")  # 'auto' picked one


def test_int8_model_keeps_the_labels(seg, phantom_frames):
    from segmentation_onnx.evaluate import iou_per_class

    frames, labels = phantom_frames
    q = vc.Segmenter("int8", threads=2)
    assert q.path.name == "gated_unet_int8.onnx" and q.path.stat().st_size < 3e6
    pred8, pred32 = q(frames), seg(frames)
    # against the phantom's truth as the fp32 model, and the same label on almost every pixel
    iou8 = dict(zip(CLASSES, iou_per_class(pred8, labels), strict=True))
    iou32 = dict(zip(CLASSES, iou_per_class(pred32, labels), strict=True))
    assert iou8["vessel"] > 0.5 and iou8["vessel"] > iou32["vessel"] - 0.03
    assert (pred8 == pred32).mean() > 0.98


def test_the_default_on_the_cpu_is_the_int8_model(seg):
    # the int8 file labels as the fp32 one does (test above) in a fraction of the time on CPUs;
    # other execution providers get the fp32 file (their int8 kernels are not what they are fast at)
    default = vc.Segmenter(threads=2)
    assert default.path.name == "gated_unet_int8.onnx"
    assert vc.Segmenter(threads=2, providers=["CPUExecutionProvider"]).path == default.path
    assert seg.path.name == "gated_unet.onnx"


@pytest.mark.parametrize("name", ["fast", "fast-int8"])
def test_fast_models_against_ground_truth(seg, phantom_frames, name):
    """The half-width networks (distilled from the default one) label vessels and devices nearly as well."""
    from segmentation_onnx.evaluate import iou_per_class

    frames, labels = phantom_frames
    fast = vc.Segmenter(name, threads=2)
    assert fast.path.name == ("gated_unet_fast.onnx" if name == "fast" else "gated_unet_fast_int8.onnx")
    assert fast.path.stat().st_size < 2.5e6 and fast.n_classes == 5
    pred = fast(frames)
    iou = dict(zip(CLASSES, iou_per_class(pred, labels), strict=True))
    ref = dict(zip(CLASSES, iou_per_class(seg(frames), labels), strict=True))
    # these 6 frames: vessel 0.834 / 0.832 (int8), catheter 0.713 / 0.717; the whole 240-frame test
    # set: vessel 0.80 / catheter 0.70 against 0.82 / 0.72 for the default network (MODEL_CARD.md)
    assert iou["background"] > 0.97
    assert iou["vessel"] >= 0.8 and iou["vessel"] > ref["vessel"] - 0.06
    assert iou["catheter"] > 0.6
    dices = []
    for i in REAL_IDS:  # real angiograms never trained on: measured mean 0.742 (fp32), 0.748 (int8)
        im = cv2.imread(str(REAL / f"{i}.png"), cv2.IMREAD_GRAYSCALE)
        gt = cv2.imread(str(REAL / f"{i}_gt.png"), cv2.IMREAD_GRAYSCALE) > 127
        p = fast(im) == 1
        dices.append(2 * (p & gt).sum() / (p.sum() + gt.sum()))
    assert np.mean(dices) > 0.70


def test_int8_weights_cannot_saturate_without_vnni():
    # x86 CPUs without VNNI multiply uint8 activations by int8 weights with vpmaddubsw, which adds
    # two products into a saturating int16: 2 * 255 * |w| must stay <= 32767, i.e. |w| <= 64.
    onnx = pytest.importorskip("onnx")
    from onnx import numpy_helper

    from vesselcad.segment import bundled_model_path

    m = onnx.load(str(bundled_model_path("gated_unet_int8.onnx")))
    ints = {i.name: numpy_helper.to_array(i) for i in m.graph.initializer}
    deq = [ints[n.input[0]] for n in m.graph.node if n.op_type == "DequantizeLinear" and n.input[0] in ints]
    weights = [w for w in deq if w.dtype == np.int8]
    assert len(weights) >= 20  # every convolution
    assert max(int(np.abs(w.astype(np.int32)).max()) for w in weights) <= 64
    assert 2 * 255 * 64 <= 32767


def test_revive_dead_blocks_keeps_the_output():
    torch = pytest.importorskip("torch")
    from segmentation_onnx.model import build_model, revive_dead_blocks

    torch.manual_seed(0)
    m = build_model("gated", (4, 8, 8, 8, 8)).eval()
    with torch.no_grad():  # what coupled L2 decay under Adam did to the bundled models' bottleneck
        for bn in (m.bottleneck[1], m.bottleneck[4]):
            bn.weight.zero_()
            bn.bias.zero_()
        m.ups[0].weight.zero_()
    x = torch.randn(1, 1, 32, 32)
    before = m(x)
    enc = m.encoders[0][0].weight.clone()
    assert revive_dead_blocks(m) == ["bottleneck"]
    assert torch.all(m.bottleneck[1].weight == 1) and m.bottleneck[0].weight.abs().sum() > 0
    assert torch.equal(m.encoders[0][0].weight, enc)  # live blocks untouched
    torch.testing.assert_close(m(x), before)  # its consumer still weighs it 0: same network
    assert revive_dead_blocks(m) == []


def test_model_with_wrong_outputs_is_rejected(tmp_path):
    torch = pytest.importorskip("torch")

    class OneChannel(torch.nn.Module):
        def forward(self, x):
            return x * 2.0

    p = tmp_path / "one_class.onnx"
    torch.onnx.export(OneChannel(), torch.zeros(1, 1, 16, 16), str(p), input_names=["image"],
                      output_names=["logits"], dynamo=False)
    with pytest.raises(InputFileError, match="class count"):
        vc.Segmenter(p)


def test_gate_and_torch_onnx_parity(tmp_path):
    torch = pytest.importorskip("torch")
    from segmentation_onnx.export import export
    from segmentation_onnx.model import Gate, build_model

    # the gate is f' = sigmoid(W f + b) * f with W a 1x1 convolution
    g = Gate(2)
    with torch.no_grad():
        g.proj.weight[:] = torch.tensor([[1.0, 0.0], [2.0, -1.0]])[:, :, None, None]
        g.proj.bias[:] = torch.tensor([0.5, 0.0])
    f = torch.tensor([1.0, 3.0]).reshape(1, 2, 1, 1)
    s = torch.sigmoid(torch.tensor([1.0 + 0.5, 2.0 - 3.0]))
    torch.testing.assert_close(g(f).flatten(), s * torch.tensor([1.0, 3.0]))
    for arch in ("gated", "plain"):
        torch.manual_seed(0)
        m = build_model(arch, (4, 8, 8, 8, 8))
        info = export(m, tmp_path / f"{arch}.onnx")  # raises if onnxruntime and torch disagree
        assert info["max_abs_diff"] <= 1e-4
        lab = vc.Segmenter(tmp_path / f"{arch}.onnx")(np.zeros((37, 45), np.uint8))
        assert lab.shape == (37, 45)


def test_partial_label_loss():
    torch = pytest.importorskip("torch")
    from segmentation_onnx.data import NOT_VESSEL
    from segmentation_onnx.train import seg_loss

    # uniform logits: p = 0.2 for each class; a real "not vessel" pixel costs -log(0.8) plus Dice
    logits = torch.zeros(1, 5, 1, 2)
    target = torch.tensor([[[NOT_VESSEL, NOT_VESSEL]]])
    assert abs(float(seg_loss(logits, target)) - float(-np.log(0.8))) < 1e-5
    # a confident vessel prediction on a "not vessel" pixel is penalised, a confident background one is not
    good = torch.full((1, 5, 1, 2), -10.0)
    good[:, 0] = 10.0
    bad = torch.full((1, 5, 1, 2), -10.0)
    bad[:, 1] = 10.0
    assert float(seg_loss(good, target)) < 1e-3 < 10 < float(seg_loss(bad, target))


def test_torch_normalization_matches_inference():
    torch = pytest.importorskip("torch")
    from segmentation_onnx.torch_aug import normalize

    rng = np.random.default_rng(3)
    f = rng.gamma(2.0, 100.0, (3, 300, 280)).astype(np.float32)
    f[0, :40] = 0.0  # black shutter
    f[1, :, :30] = f[1].max()  # saturated strip
    got = normalize(torch.from_numpy(f)[:, None])[:, 0].numpy()
    assert np.abs(got - normalize_frames(f)).max() < 1e-4


def test_torch_warp_matches_opencv():
    torch = pytest.importorskip("torch")
    from segmentation_onnx.torch_aug import warp

    rng = np.random.default_rng(4)
    x = rng.random((2, 1, 120, 150)).astype(np.float32)
    t = rng.integers(0, 5, (2, 120, 150))
    centre = np.array([[70.3, 50.2], [10.0, 100.0]])
    scale, angle, flip = np.array([1.3, 0.7]), np.array([0.4, 2.5]), np.array([1.0, -1.0])
    xi, ti = warp(torch.from_numpy(x), torch.from_numpy(t),
                  *(torch.tensor(v, dtype=torch.float32) for v in (centre, scale, angle, flip)), crop=64)
    for i in range(2):
        c, s = np.cos(angle[i]) * scale[i], np.sin(angle[i]) * scale[i]
        m = np.array([[c * flip[i], -s, 0.0], [s * flip[i], c, 0.0]])
        m[:, 2] = np.array([32.0, 32.0]) - m[:, :2] @ centre[i]
        ref = cv2.warpAffine(x[i, 0], m, (64, 64), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101)
        ref_t = cv2.warpAffine(t[i].astype(np.float32), m, (64, 64), flags=cv2.INTER_NEAREST,
                               borderMode=cv2.BORDER_REFLECT_101)
        assert np.abs(ref - xi[i, 0].numpy()).max() < 1e-3
        assert (ref_t == ti[i].numpy()).mean() > 0.99


def test_training_batches(phantom_frames):
    torch = pytest.importorskip("torch")
    from segmentation_onnx.data import NOT_VESSEL, Pool
    from segmentation_onnx.torch_aug import BatchAugmenter

    frames, labels = phantom_frames
    real = [cv2.imread(str(REAL / f"{i}.png"), cv2.IMREAD_GRAYSCALE) for i in REAL_IDS[:2]]
    masks = [cv2.imread(str(REAL / f"{i}_gt.png"), cv2.IMREAD_GRAYSCALE) > 127 for i in REAL_IDS[:2]]
    pool = Pool(list(frames), list(labels), [8] * len(frames))
    aug = BatchAugmenter(pool, real, masks, crop=128, real_fraction=0.5, seed=0)
    x, t = aug.batch(12)
    assert x.shape == (12, 1, 128, 128) and t.shape == (12, 128, 128) and x.dtype == torch.float32
    assert float(x.min()) >= -2.0 and float(x.max()) <= 2.0
    assert set(torch.unique(t).tolist()) <= {0, 1, 2, 3, 4, NOT_VESSEL}
    # phantom crops come first, real crops (vessel / not vessel only) after them
    is_real = (t == NOT_VESSEL).flatten(1).any(1)
    assert 0 < int(is_real.sum()) < 12
    assert not bool(((t >= 2) & (t <= 4))[is_real].any())
    # without augmentation, centre crops of one frame reproduce it (normalized) pixel for pixel
    one = Pool([frames[0]], [labels[0]], [8])
    plain = BatchAugmenter(one, [], [], crop=64, seed=1, augment=False)
    z = normalize_frames(frames[:1])[0]
    xi, ti = plain.batch(4)
    for k in range(4):
        offset = _find_offset(z, xi[k, 0].numpy())
        assert offset is not None
        cx, cy = offset
        assert (ti[k].numpy() == labels[0][cy:cy + 64, cx:cx + 64]).all()


def test_training_batches_with_hand_labelled_real_images(phantom_frames):
    torch = pytest.importorskip("torch")
    from segmentation_onnx.data import IGNORE, NOT_VESSEL, Pool
    from segmentation_onnx.torch_aug import BatchAugmenter
    from segmentation_onnx.train import seg_loss

    frames, labels = phantom_frames
    pool = Pool(list(frames), list(labels), [8] * len(frames))
    real = [cv2.imread(str(REAL / f"{i}.png"), cv2.IMREAD_GRAYSCALE) for i in REAL_IDS[:2]]
    masks = [cv2.imread(str(REAL / f"{i}_gt.png"), cv2.IMREAD_GRAYSCALE) > 127 for i in REAL_IDS[:2]]
    # a 'catheter' drawn on a real image: a band labelled 2, background 0 elsewhere, a ring unlabelled
    target = np.zeros((96, 96), np.uint8)
    target[:, 40:60] = IGNORE
    target[:, 46:54] = 2
    image = np.full((96, 96), 180, np.uint8)
    image[:, 46:54] = 60
    aug = BatchAugmenter(pool, real, masks, crop=64, real_fraction=1.0, seed=2,
                         labelled_images=[image], labelled_targets=[target], labelled_fraction=0.5)
    x, t = aug.batch(16)
    values = set(torch.unique(t).tolist())
    assert values <= {0, 1, 2, NOT_VESSEL, IGNORE} and {2, IGNORE} <= values
    labelled = (t == IGNORE).flatten(1).any(1) | (t == 2).flatten(1).any(1)
    from_cimat = (t == NOT_VESSEL).flatten(1).any(1)
    assert 0 < int(labelled.sum()) < 16 and not bool((labelled & from_cimat).any())
    # the drawn catheter is dark in the crops too (the warp keeps images and targets together)
    for k in np.nonzero(labelled.numpy())[0]:
        xi, ti = x[k, 0], t[k]
        if (ti == 2).sum() > 20 and (ti == 0).sum() > 20:
            assert float(xi[ti == 2].mean()) < float(xi[ti == 0].mean())
    # no loss at all from unlabelled pixels, whatever the network says there
    logits = torch.randn(1, 5, 4, 4)
    tgt = torch.full((1, 4, 4), IGNORE)
    tgt[0, 0, 0] = 2
    other = logits.clone()
    other[:, :, 1:] = torch.randn(1, 5, 3, 4) * 10
    assert abs(float(seg_loss(logits, tgt)) - float(seg_loss(other, tgt))) < 1e-6
    with pytest.raises(ValueError, match="labelled_fraction"):
        BatchAugmenter(pool, [], [], labelled_fraction=2.0)


def _one_frame_pool(labels: np.ndarray):
    """A pool of one 8-bit frame: bright background, labelled pixels dark."""
    from segmentation_onnx.data import Pool

    frame = np.full(labels.shape, 200, np.uint8)
    frame[labels > 0] = 60
    return Pool([frame], [labels], [8])


def test_focus_crops():
    """Catheter pixels within 12 px of a vessel and balloons are focus pixels; focused crops show them."""
    torch = pytest.importorskip("torch")
    from segmentation_onnx.torch_aug import FOCUS_RADIUS, BatchAugmenter, focus_grid

    assert FOCUS_RADIUS == 12
    lab = torch.zeros(2, 64, 64, dtype=torch.uint8)
    lab[:, 28, 28] = 1
    lab[:, 28, 40] = 2  # 12 px (Chebyshev) from the vessel pixel: focus
    lab[:, 40, 40] = 2  # 12 px diagonally: focus
    lab[:, 28, 44] = 2  # 16 px: not
    lab[:, 60, 4] = 2  # far: not
    lab[1, 0, 60] = 3  # a balloon anywhere: focus
    g = focus_grid(lab)
    assert g.shape == (2, 16, 16)
    assert sorted(map(tuple, g[0].nonzero().tolist())) == [(7, 10), (10, 10)]
    assert sorted(map(tuple, g[1].nonzero().tolist())) == [(0, 15), (7, 10), (10, 10)]
    # a 256 px frame with a short catheter piece next to a vessel far from the rest of the foreground
    labels = np.zeros((256, 256), np.uint8)
    labels[20:200, 200:206] = 1
    labels[240:252, 8:12] = 1
    labels[236:240, 14:18] = 2
    pool = _one_frame_pool(labels)
    share = []
    for f in (0.0, 1.0):
        aug = BatchAugmenter(pool, [], [], crop=32, focus_fraction=f, seed=3)
        _, t = aug.batch(64)
        share.append(float((t == 2).flatten(1).any(1).float().mean()))
    assert share[0] < 0.2 and share[1] > 0.8, share
    with pytest.raises(ValueError, match="focus_fraction"):
        BatchAugmenter(pool, [], [], focus_fraction=1.5)


def test_hard_focus_cells_and_crops(tmp_path):
    """Device disagreements (not vessel/background ones) are hard cells; focused crops then show them."""
    from segmentation_onnx.hard_focus import device_errors, hard_grid, load_hard

    truth = np.zeros((1, 16, 16), np.uint8)
    pred = np.zeros_like(truth)
    truth[0, 1, 1] = 2
    pred[0, 1, 1] = 1  # catheter labelled vessel: hard
    truth[0, 5, 9] = 1  # vessel missed: not a device error
    pred[0, 14, 3] = 4  # lead where there is none: hard
    truth[0, 9, 9] = pred[0, 9, 9] = 3  # balloon right: not
    err = device_errors(truth, pred)
    assert sorted(map(tuple, np.argwhere(err[0]).tolist())) == [(1, 1), (14, 3)]
    g = hard_grid(err, min_width=1)
    assert g.shape == (1, 4, 4) and sorted(map(tuple, np.argwhere(g[0]).tolist())) == [(0, 0), (3, 0)]
    assert not hard_grid(err).any()  # single pixels are no hard cells by default
    # a tube drawn a pixel too wide is no hard cell; a stretch of it labelled vessel is
    wide = np.zeros((1, 32, 32), bool)
    wide[0, 4:28, 10] = True  # 1 px sliver along a catheter's edge
    wide[0, 20:26, 20:26] = True  # 6 x 6 block
    assert sorted(map(tuple, np.argwhere(hard_grid(wide)[0]).tolist())) == [(5, 5), (5, 6), (6, 5), (6, 6)]
    assert hard_grid(np.ones((1, 5, 9), bool)).shape == (1, 2, 3)
    with pytest.raises(ValueError, match="shape"):
        device_errors(truth, pred[:, :8])
    np.savez(tmp_path / "h.npz", bits=np.packbits(g, axis=-1), cols=g.shape[-1])
    assert np.array_equal(load_hard(tmp_path / "h.npz", 1), g)
    with pytest.raises(ValueError, match="1 frames, the pool 2"):
        load_hard(tmp_path / "h.npz", 2)

    pytest.importorskip("torch")
    from segmentation_onnx.torch_aug import BatchAugmenter

    # a frame with a vessel-adjacent catheter piece (focus) at the top left and a lone lead piece at the
    # bottom right that no focus rule picks: marked hard, the focused crops show it
    labels = np.zeros((256, 256), np.uint8)
    labels[10:30, 10:14] = 1
    labels[10:30, 16:20] = 2
    labels[236:248, 236:240] = 4
    pool = _one_frame_pool(labels)
    hard = np.zeros((1, 64, 64), bool)
    hard[0, 59:62, 59] = True
    share = []
    for h in (None, hard):
        aug = BatchAugmenter(pool, [], [], crop=32, focus_fraction=1.0, seed=5, hard=h, hard_weight=20.0)
        _, t = aug.batch(64)
        share.append(float((t == 4).flatten(1).any(1).float().mean()))
    assert share[0] < 0.2 and share[1] > 0.6, share
    with pytest.raises(ValueError, match="focus_fraction"):
        BatchAugmenter(pool, [], [], hard=hard)
    with pytest.raises(ValueError, match="does not fit"):
        BatchAugmenter(pool, [], [], focus_fraction=0.5, hard=hard[:, :8])


def _find_offset(z: np.ndarray, crop: np.ndarray) -> tuple[int, int] | None:
    """Top-left (x, y) where ``crop`` sits in ``z`` (exact match up to float noise)."""
    res = cv2.matchTemplate(z, crop, cv2.TM_SQDIFF)
    _, _, (x, y), _ = cv2.minMaxLoc(res)
    return (x, y) if np.abs(z[y:y + crop.shape[0], x:x + crop.shape[1]] - crop).max() < 1e-4 else None


def test_soup_averages_two_checkpoints_of_one_network(tmp_path):
    """A soup is the weighted mean of two checkpoints (integers from the second); other networks refused."""
    torch = pytest.importorskip("torch")
    from segmentation_onnx.model import build_model
    from segmentation_onnx.soup import main, soup

    widths = (4, 8, 8, 8, 8)
    cks = []
    for seed in (0, 1):
        torch.manual_seed(seed)
        m = build_model("gated", widths)
        for bn in (x for x in m.modules() if isinstance(x, torch.nn.BatchNorm2d)):
            bn.num_batches_tracked.fill_(10 * seed + 3)
        cks.append({"model": m.state_dict(), "arch": "gated", "widths": widths})
    out = soup(cks[0], cks[1], 0.25)["model"]
    for k, v in out.items():
        a, b = cks[0]["model"][k], cks[1]["model"][k]
        if v.is_floating_point():
            assert torch.allclose(v, 0.75 * a + 0.25 * b, atol=1e-7), k
        else:
            assert torch.equal(v, b), k
    m = build_model("gated", widths)
    m.load_state_dict(out)  # loads as the same network
    with pytest.raises(ValueError, match="different networks"):
        soup(cks[0], {**cks[1], "widths": (4, 8, 8, 8, 16)})
    with pytest.raises(ValueError, match="weight"):
        soup(cks[0], cks[1], 1.5)
    for i, ck in enumerate(cks):
        torch.save(ck, tmp_path / f"{i}.pt")
    assert main([str(tmp_path / "0.pt"), str(tmp_path / "1.pt"), "--out", str(tmp_path / "s.pt")]) == 0
    s = torch.load(tmp_path / "s.pt")["model"]
    k = next(k for k in s if s[k].is_floating_point())
    assert torch.allclose(s[k], 0.5 * (cks[0]["model"][k] + cks[1]["model"][k]), atol=1e-7)


def test_shrink_drops_only_silent_channels():
    """A wide network whose extra channels are silent (batch-norm scale and shift 0, so ReLU gives 0,
    and no decoder reads the extra up-convolution outputs) computes exactly what its shrunk copy does."""
    torch = pytest.importorskip("torch")
    from segmentation_onnx.model import build_model, shrink

    wide_w, small_w = (6, 8, 10, 12, 14), (4, 5, 7, 9, 11)
    torch.manual_seed(0)
    for arch in ("gated", "plain"):
        m = build_model(arch, wide_w).eval()
        g = torch.Generator().manual_seed(1)
        with torch.no_grad():
            for bn in (x for x in m.modules() if isinstance(x, torch.nn.BatchNorm2d)):
                bn.weight.uniform_(0.5, 1.5, generator=g)
                bn.bias.uniform_(-0.2, 0.2, generator=g)
                bn.running_mean.uniform_(-0.1, 0.1, generator=g)
                bn.running_var.uniform_(0.5, 2.0, generator=g)
                n = bn.num_features
                keep = small_w[wide_w.index(n)]
                drop = torch.randperm(n, generator=g)[: n - keep]  # scattered, not the last channels
                bn.weight[drop] = 0.0
                bn.bias[drop] = 0.0
            for dec, w, ws in zip(m.decoders, reversed(wide_w[:4]), reversed(small_w[:4]), strict=True):
                drop = torch.randperm(w, generator=g)[: w - ws]
                dec[0].weight[:, drop] = 0.0  # the decoder never reads these up-convolution outputs
            if arch == "gated":
                for gate in m.gates:
                    gate.proj.weight.normal_(0.0, 0.3, generator=g)
                    gate.proj.bias.normal_(0.0, 0.3, generator=g)
        x = torch.randn(2, 1, 32, 48, generator=g)
        s = shrink(m, small_w)
        assert s.widths == small_w and s.gated == (arch == "gated")
        assert sum(p.numel() for p in s.parameters()) < sum(p.numel() for p in m.parameters())
        with torch.no_grad():
            torch.testing.assert_close(s(x), m(x), atol=1e-5, rtol=1e-5)
        with torch.no_grad():
            torch.testing.assert_close(shrink(m, wide_w)(x), m(x))  # same widths: the same network
    with pytest.raises(ValueError, match="widths"):
        shrink(m, (8, 8, 8, 8, 8))  # wider than the source


def test_distillation_loss_is_the_softened_kl_divergence():
    torch = pytest.importorskip("torch")
    from segmentation_onnx.train import distill_loss

    # two classes, one pixel: teacher logits (0, ln 3) -> p = (1/4, 3/4) at T = 1
    teacher = torch.tensor([0.0, float(np.log(3.0))]).reshape(1, 2, 1, 1)
    student = torch.zeros(1, 2, 1, 1)  # q = (1/2, 1/2)
    kl = 0.25 * np.log(0.25 / 0.5) + 0.75 * np.log(0.75 / 0.5)
    assert abs(float(distill_loss(student, teacher, temperature=1.0)) - kl) < 1e-6
    # T = 2: p = softmax(0, ln 3 / 2) = (1, sqrt 3) / (1 + sqrt 3), scaled by T^2
    p = np.array([1.0, np.sqrt(3.0)]) / (1 + np.sqrt(3.0))
    kl2 = float(np.sum(p * np.log(p / 0.5))) * 4
    assert abs(float(distill_loss(student, teacher, temperature=2.0)) - kl2) < 1e-6
    assert float(distill_loss(teacher, teacher)) == pytest.approx(0.0, abs=1e-7)
