#!/usr/bin/env bash
# Train narrower (faster) networks on a GPU machine by distillation from the bundled gated U-Net
# (the run recorded in MODEL_CARD.md, "Round 15").
# Renders one phantom pool, then trains every network of $CONFIGS side by side on the one GPU,
# each starting from the strongest channels of a wider network (train.py --shrink) and learning
# from the labels and from the teacher's per-pixel class probabilities (train.py --teacher), until
# $SECONDS_TOTAL seconds after this script started. The run folders are packed into $OUT/<name>.tgz
# every minute and at the end, so a run stopped from outside still leaves its latest checkpoints.
# Every command here also runs on CPU (--device cpu --threads N), only slower.
set -euo pipefail
export PYTHONUNBUFFERED=1
OUT=${OUT:-out}; RUNS=${RUNS:-/tmp/runs}; POOL=${POOL:-/tmp/pool.npz}
PHANTOMS=${PHANTOMS:-500}; FIRST_SEED=${FIRST_SEED:-22000}; SECONDS_TOTAL=${SECONDS_TOTAL:-480}
AMP=${AMP-1}; REAL=${REAL:-.data/xca-real}; TEACHER=${TEACHER:-segmentation_onnx/weights/gated_unet.pt}
# name:arch:widths:shrink-source
CONFIGS=${CONFIGS:-"g8:gated:8,16,32,64,128:$TEACHER g8b192:gated:8,16,32,64,192:$TEACHER p8:plain:8,16,32,64,128:segmentation_onnx/weights/unet.pt"}
t0=$(date +%s)
mkdir -p "$RUNS" "$OUT"
python3 -c "import torch; print('torch', torch.__version__, 'cuda', torch.cuda.is_available())"
[ -f "$POOL" ] || python3 -m segmentation_onnx.data --out "$POOL" --phantoms "$PHANTOMS" \
  --first-seed "$FIRST_SEED" --frames 6 2>&1 | tail -1
echo "pool: $(( $(date +%s) - t0 )) s"
pack() {  # one archive per network (each stays under the device tool's 16 MB a file)
  for d in "$RUNS"/*/; do
    n=$(basename "$d")
    tar czf "$OUT/.$n.tgz" -C "$RUNS" "$n" "$n.txt" && mv "$OUT/.$n.tgz" "$OUT/$n.tgz"
  done
}
left=$(( SECONDS_TOTAL - ($(date +%s) - t0) - 20 ))
for cfg in $CONFIGS; do
  IFS=: read -r name arch widths src <<< "$cfg"
  python3 -m segmentation_onnx.train --arch "$arch" --widths "$widths" --out "$RUNS/$name" --pool "$POOL" \
    --steps 400000 --batch "${BATCH:-16}" --lr "${LR:-5e-4}" --val-every "${VAL_EVERY:-1000}" \
    --time-limit "$left" --real-dir "$REAL" --quiet ${AMP:+--amp} --real-fraction "${REAL_FRACTION:-0.5}" \
    --catheter-labels --labelled-fraction "${LABELLED_FRACTION:-0.34}" \
    --focus-fraction "${FOCUS_FRACTION:-0.35}" --teacher "$TEACHER" --distill "${DISTILL:-1.0}" \
    --temperature "${TEMPERATURE:-2.0}" --shrink "$src" --revive --seed "${SEED:-3}" ${DEVICE:+--device "$DEVICE" --threads 1} \
    > "$RUNS/$name.txt" 2>&1 &
done
( while sleep 60; do pack || true; done ) &
packer=$!
wait $(jobs -p | grep -v "^$packer$") || true
kill "$packer" 2>/dev/null || true
for d in "$RUNS"/*/; do echo "$(basename "$d")"; tail -2 "$d/log.csv"; done
pack
echo "total: $(( $(date +%s) - t0 )) s"
