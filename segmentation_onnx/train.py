"""Train the gated U-Net (or the plain U-Net baseline) on phantom + real frames.

Reproducible (seeded data and weights), CPU-capable (``--device cpu --threads N``,
fp32; ``--amp`` for bfloat16 autocast on a GPU or a CPU with AMX/AVX512-BF16), batch 8 by
default, Adam with lr 5e-4 and weight decay 5e-4 as in the paper (decoupled, AdamW, by
default; ``--optimizer adam`` for the coupled L2 of rounds 1-6, which killed the
bottleneck: see ``model.revive_dead_blocks``), cosine learning-rate decay, checkpoints every ``--ckpt-every``
steps and at the end (``last.pt``), resumable (``--resume``), a progress bar,
knowledge distillation from a trained network (``--teacher``, optionally with the student
initialized from the teacher's strongest channels, ``--shrink``: how a narrower, faster
network is trained),
and a log (``log.csv``) of the loss and of the validation scores: vessel Dice on
the real validation split and per-class IoU on a small phantom validation set.

Example (the bundled model's command is in MODEL_CARD.md)::

    python -m segmentation_onnx.train --arch gated --out runs/gated --steps 8000
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from .data import NOT_VESSEL, REAL_VAL_IDS, Pool, load_real, render_pool
from .evaluate import iou_per_class
from .hard_focus import load_hard
from .model import DEFAULT_WIDTHS, N_CLASSES, build_model, revive_dead_blocks, shrink
from .torch_aug import BatchAugmenter

#: Per-class weights of the cross-entropy (thin devices and balloons are rare).
CLASS_WEIGHTS = (1.0, 2.0, 2.0, 3.0, 2.0)
VAL_SEED0 = 9_000_000


def seg_loss(logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Cross-entropy + soft Dice with partial labels.

    ``target`` 0..4 are full labels (phantom); :data:`NOT_VESSEL` marks a real
    pixel known only to be "not vessel": its loss is ``-log(1 - p_vessel)``.
    Dice of the vessel class uses every pixel, Dice of the device classes only
    fully labelled ones.
    """
    logp = F.log_softmax(logits.float(), dim=1)
    w = torch.tensor(CLASS_WEIGHTS, device=logits.device)
    full = target <= 4
    t = target.clamp(max=4)
    ce_full = -logp.gather(1, t[:, None])[:, 0] * w[t]
    others = [c for c in range(N_CLASSES) if c != 1]
    ce_nv = -torch.logsumexp(logp[:, others], dim=1)
    ce = torch.where(full, ce_full, torch.where(target == NOT_VESSEL, ce_nv, torch.zeros_like(ce_nv)))
    valid = full | (target == NOT_VESSEL)
    ce = ce.sum() / valid.sum().clamp(min=1)
    p = logp.exp()
    dices = []
    for k in range(1, N_CLASSES):
        m = valid if k == 1 else full
        g = ((target == k) & m).float()
        if g.sum() < 1:
            continue
        pk = p[:, k] * m.float()
        dices.append(1 - (2 * (pk * g).sum() + 1) / (pk.sum() + g.sum() + 1))
    dice = torch.stack(dices).mean() if dices else torch.zeros((), device=logits.device)
    return ce + dice


def distill_loss(student: torch.Tensor, teacher: torch.Tensor, temperature: float = 2.0) -> torch.Tensor:
    """Mean per-pixel KL divergence of the student's from the teacher's softened class distribution.

    Scaled by ``temperature**2`` so that its gradients keep their size whatever the temperature
    (Hinton et al. 2015). Every pixel counts, also the unlabelled ones of real images.
    """
    t = temperature
    log_s = F.log_softmax(student.float() / t, dim=1)
    log_t = F.log_softmax(teacher.float() / t, dim=1)
    return (log_t.exp() * (log_t - log_s)).sum(dim=1).mean() * t * t


@torch.no_grad()
def predict(model: torch.nn.Module, frames: list[np.ndarray] | np.ndarray, device: torch.device,
            batch: int = 8) -> np.ndarray:
    """Label maps of whole frames (normalized as at inference, padded to a multiple of 16)."""
    from vesselcad.segment import normalize_frames

    model.eval()
    out = []
    for s in range(0, len(frames), batch):
        chunk = [np.asarray(f) for f in frames[s:s + batch]]
        h, w = chunk[0].shape
        z = normalize_frames(np.stack(chunk))
        ph, pw = (-h) % 16, (-w) % 16
        z = np.pad(z, ((0, 0), (0, ph), (0, pw)), mode="reflect")
        logits = model(torch.from_numpy(z[:, None]).to(device))
        out.append(logits.argmax(1)[:, :h, :w].cpu().numpy().astype(np.uint8))
    return np.concatenate(out)


def dice(pred: np.ndarray, truth: np.ndarray) -> float:
    """Dice of two boolean masks (pooled over all pixels given)."""
    inter = np.logical_and(pred, truth).sum()
    return float(2 * inter / max(pred.sum() + truth.sum(), 1))


def validate(model, device, real_val, phantom_val) -> dict[str, float]:
    imgs, masks = real_val
    per = [dice(predict(model, [im], device)[0] == 1, m) for im, m in zip(imgs, masks, strict=True)]
    pv = predict(model, phantom_val.frames, device)
    iou = iou_per_class(pv, np.stack(phantom_val.labels))
    model.train()
    return {"real_dice": float(np.mean(per)), **{f"iou_{k}": float(v) for k, v in enumerate(iou)},
            "phantom_miou": float(np.nanmean(iou))}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m segmentation_onnx.train", description=__doc__.split("\n")[0])
    ap.add_argument("--arch", choices=["gated", "plain"], default="gated")
    ap.add_argument("--widths", default=",".join(map(str, DEFAULT_WIDTHS)), help="5 channel counts")
    ap.add_argument("--out", required=True, help="run folder (checkpoints, log.csv)")
    ap.add_argument("--steps", type=int, default=8000)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--lr", type=float, default=5e-4)
    ap.add_argument("--weight-decay", type=float, default=5e-4)
    ap.add_argument("--optimizer", choices=["adamw", "adam"], default="adamw",
                    help="adamw: decoupled weight decay (default); adam: L2 added to the gradient "
                    "(rounds 1-6; drives low-gradient layers to zero)")
    ap.add_argument("--crop", type=int, default=256)
    ap.add_argument("--real-fraction", type=float, default=0.35)
    ap.add_argument("--focus-fraction", type=float, default=0.0,
                    help="share of phantom crops centred on catheter pixels next to vessels or on balloons")
    ap.add_argument("--hard-focus", help="hard-focus map of the pool (.npz from "
                    "`python -m segmentation_onnx.hard_focus`): its cells join the focus pixels")
    ap.add_argument("--hard-weight", type=float, default=4.0,
                    help="weight of a hard cell against a focus pixel when a focus centre is drawn")
    ap.add_argument("--pool", help="rendered phantom pool (.npz from `python -m segmentation_onnx.data`); "
                    "rendered here when missing")
    ap.add_argument("--pool-phantoms", type=int, default=200, help="phantoms to render when --pool is absent")
    ap.add_argument("--real-dir", help="xca-real folder (default: see data.find_real_dir)")
    ap.add_argument("--no-real", action="store_true", help="phantom only")
    ap.add_argument("--catheter-labels", nargs="?", const="default", default=None,
                    help="also train on the real flat-panel images with hand-drawn catheters "
                    "(segmentation_onnx/real_labels/arcade_catheters.npz, or this file); their test "
                    "images are kept out")
    ap.add_argument("--labelled-fraction", type=float, default=0.5,
                    help="with --catheter-labels: share of the real crops drawn from them")
    ap.add_argument("--device", default="auto", help="cpu, cuda or auto")
    ap.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    ap.add_argument("--workers", type=int, default=None, help="processes rendering the pool (default: all)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--val-every", type=int, default=500)
    ap.add_argument("--ckpt-every", type=int, default=500)
    ap.add_argument("--time-limit", type=float, default=0, help="stop (and save) after this many seconds")
    ap.add_argument("--resume", action="store_true", help="continue from OUT/last.pt")
    ap.add_argument("--init", help="start from these weights (fine-tuning)")
    ap.add_argument("--revive", action="store_true",
                    help="with --init or --shrink: re-initialize blocks whose batch norms collapsed to zero")
    ap.add_argument("--teacher", help="checkpoint of a trained network to distil from (its softened "
                    "per-pixel class probabilities join the loss)")
    ap.add_argument("--distill", type=float, default=1.0,
                    help="with --teacher: weight of the distillation term")
    ap.add_argument("--temperature", type=float, default=2.0, help="with --teacher: softmax temperature")
    ap.add_argument("--shrink", nargs="?", const="teacher", default=None,
                    help="start from the strongest channels (model.shrink) of this checkpoint of a wider "
                    "network of the same kind (default: the --teacher) instead of random weights")
    ap.add_argument("--amp", action="store_true",
                    help="bfloat16 autocast (GPUs with bf16 tensor cores; CPUs with AMX or AVX-512: ~2-4x "
                    "faster than fp32; on AVX2-only CPUs ~25x slower)")
    ap.add_argument("--quiet", action="store_true")
    a = ap.parse_args(argv)
    if a.shrink and a.init:
        ap.error("--shrink and --init both give the starting weights: pass one")
    if a.shrink == "teacher" and not a.teacher:
        ap.error("--shrink without a checkpoint shrinks the --teacher: pass one")
    if a.revive and not (a.init or a.shrink):
        ap.error("--revive needs --init or --shrink (the weights whose collapsed blocks to re-initialize)")

    t_start = time.time()
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(a.seed)
    if a.threads:
        torch.set_num_threads(a.threads)
    auto = "cuda" if torch.cuda.is_available() else "cpu"
    device = torch.device(auto if a.device == "auto" else a.device)
    if a.amp and device.type == "cpu":
        cap = torch.backends.cpu.get_cpu_capability()
        if not cap.startswith("AVX512") and cap != "AMX":
            # measured 2026-12-03 on an AVX2-only AMD EPYC VM: 66 s a step with --amp, 2.4 s without
            print(f"warning: this CPU ({cap}) has no native bfloat16; --amp runs about 25x slower "
                  "than fp32 here: leave it off", flush=True)
    widths = tuple(int(v) for v in a.widths.split(","))
    model = build_model(a.arch, widths).to(device)
    if device.type == "cuda":
        torch.backends.cudnn.benchmark = True
        model = model.to(memory_format=torch.channels_last)
    optimizer = torch.optim.AdamW if a.optimizer == "adamw" else torch.optim.Adam
    opt = optimizer(model.parameters(), lr=a.lr, weight_decay=a.weight_decay)
    step = 0
    t_limit_start = time.time()

    def learning_rate() -> float:
        # cosine decay to 2% over the steps, or over the time limit when that comes first
        # (then the schedule follows the wall clock and a run is not bit-reproducible)
        prog = step / a.steps
        if a.time_limit:
            prog = max(prog, (time.time() - t_limit_start) / max(a.time_limit - (t_limit_start - t_start), 1))
        return a.lr * (0.02 + 0.98 * 0.5 * (1 + math.cos(math.pi * min(prog, 1.0))))
    revived: list[str] = []
    teacher = None
    if a.teacher or a.shrink:
        from .export import load_checkpoint

        teacher = load_checkpoint(a.teacher) if a.teacher else None
    if a.shrink:
        wide = teacher if a.shrink == "teacher" else load_checkpoint(a.shrink)
        if wide.gated != model.gated:
            ap.error(f"--shrink: {a.shrink} is a {'gated' if wide.gated else 'plain'} network, not {a.arch}")
        try:
            model.load_state_dict(shrink(wide, widths).state_dict())
        except ValueError as exc:
            ap.error(f"--shrink {a.shrink}: {exc}")
        if a.revive:
            revived = revive_dead_blocks(model)
            print(f"revived: {', '.join(revived) or 'nothing'}")
    if teacher is not None:
        teacher = teacher.to(device)
        if device.type == "cuda":
            teacher = teacher.to(memory_format=torch.channels_last)
        for prm in teacher.parameters():
            prm.requires_grad_(False)
    if a.init:
        model.load_state_dict(torch.load(a.init, map_location=device)["model"])
        if a.revive:
            revived = revive_dead_blocks(model)
            print(f"revived: {', '.join(revived) or 'nothing'}")
    if a.resume and (out / "last.pt").is_file():
        ck = torch.load(out / "last.pt", map_location=device)
        model.load_state_dict(ck["model"])
        opt.load_state_dict(ck["opt"])
        step = int(ck["step"])

    if a.pool and Path(a.pool).is_file():
        pool = Pool.load(a.pool)
    else:
        pool = render_pool(range(a.pool_phantoms), workers=a.workers, progress=not a.quiet)
        if a.pool:
            pool.save(a.pool)
    val_path = Path(f"{a.pool}.val.npz") if a.pool else None
    if val_path is not None and val_path.is_file():
        val_pool = Pool.load(val_path)
    else:
        val_pool = render_pool(range(VAL_SEED0, VAL_SEED0 + 16), frames_per_seed=2, keep_empty=0.5,
                               workers=a.workers, progress=False)
        if val_path is not None:  # cached beside the pool (Pool.save is atomic: runs may race)
            val_pool.save(val_path)
    real_train_ids = [i for i in range(1, 41) if i not in REAL_VAL_IDS]
    real_imgs, real_masks = ([], []) if a.no_real else load_real(real_train_ids, a.real_dir)
    real_val = load_real(REAL_VAL_IDS, a.real_dir)

    lab_imgs, lab_tgts, lab_names = [], [], []
    if a.catheter_labels:
        from .catheter_labels import TARGETS, load_targets

        path = TARGETS if a.catheter_labels == "default" else a.catheter_labels
        lab_imgs, lab_tgts, lab_names = load_targets(path, a.real_dir, split="train")

    # batches are drawn and augmented on the training device; a resumed run reseeds from its step
    aug = BatchAugmenter(pool, real_imgs, real_masks, crop=a.crop, real_fraction=a.real_fraction,
                         focus_fraction=a.focus_fraction, device=device, seed=a.seed * 1_000_003 + step,
                         labelled_images=lab_imgs, labelled_targets=lab_tgts,
                         labelled_fraction=a.labelled_fraction,
                         hard=load_hard(a.hard_focus, len(pool.frames)) if a.hard_focus else None,
                         hard_weight=a.hard_weight)
    (out / "config.json").write_text(json.dumps({**vars(a), "widths": widths, "device": str(device),
                                                 "pool_frames": len(pool.frames), "revived": revived,
                                                 "real_train_ids": real_train_ids,
                                                 "real_val_ids": list(REAL_VAL_IDS),
                                                 "catheter_labelled_train": lab_names}, indent=1))
    log_path = out / "log.csv"
    new_log = not log_path.exists() or step == 0
    logf = open(log_path, "w" if new_log else "a", newline="")
    log = csv.writer(logf)
    if new_log:
        log.writerow(["step", "loss", "lr", "seconds", "real_dice", "phantom_miou", "iou_vessel",
                      "iou_catheter", "iou_balloon", "iou_lead"])

    def save(name: str) -> None:
        tmp = out / f".{name}.tmp"
        torch.save({"model": model.state_dict(), "opt": opt.state_dict(),
                    "step": step, "arch": a.arch, "widths": widths}, tmp)
        os.replace(tmp, out / name)

    from tqdm.auto import tqdm

    bar = tqdm(total=a.steps, initial=step, desc=f"train {a.arch}", unit="step", disable=a.quiet)
    model.train()
    run_loss, n_loss = torch.zeros((), device=device), 0
    t_limit_start = time.time()  # the schedule's clock starts with the first step
    while step < a.steps:
        x, t = aug.batch(a.batch)
        for g in opt.param_groups:
            g["lr"] = learning_rate()
        if device.type == "cuda":
            x = x.contiguous(memory_format=torch.channels_last)
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=a.amp):
            logits = model(x)
        loss = seg_loss(logits, t)
        if teacher is not None:
            with torch.no_grad(), torch.autocast(device.type, dtype=torch.bfloat16, enabled=a.amp):
                t_logits = teacher(x)
            loss = loss + a.distill * distill_loss(logits, t_logits, a.temperature)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        step += 1
        run_loss += loss.detach()
        n_loss += 1
        bar.update(1)
        last = step >= a.steps or (a.time_limit and time.time() - t_start > a.time_limit)
        if step % a.val_every == 0 or last:
            v = validate(model, device, real_val, val_pool)
            mean_loss = float(run_loss) / max(n_loss, 1)
            log.writerow([step, round(mean_loss, 5), f"{opt.param_groups[0]['lr']:.2e}",
                          round(time.time() - t_start, 1), round(v["real_dice"], 4),
                          round(v["phantom_miou"], 4)] + [round(v[f"iou_{k}"], 4) for k in range(1, 5)])
            logf.flush()
            bar.set_postfix(loss=f"{mean_loss:.3f}", real_dice=f"{v['real_dice']:.3f}",
                            miou=f"{v['phantom_miou']:.3f}")
            run_loss, n_loss = torch.zeros((), device=device), 0
        if step % a.ckpt_every == 0 or last:
            save("last.pt")
        if last:
            break
    bar.close()
    logf.close()
    save("last.pt")
    print(json.dumps({"step": step, "seconds": round(time.time() - t_start, 1)}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
