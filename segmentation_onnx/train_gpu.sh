#!/usr/bin/env bash
# Train the bundled models on a GPU machine (the run recorded in MODEL_CARD.md).
# Renders one phantom pool, trains the gated and the plain U-Net side by side on the one GPU
# (each for at most $TRAIN_SECONDS; batches are augmented on the GPU, see torch_aug.py),
# exports each to ONNX, and packs the results into one $OUT/<run>.tgz per model.
# Every command here also runs on CPU (--device cpu), only slower.
set -euo pipefail
export PYTHONUNBUFFERED=1
OUT=${OUT:-out}; RUNS=${RUNS:-/tmp/runs}; POOL=${POOL:-/tmp/pool.npz}
PHANTOMS=${PHANTOMS:-700}; TRAIN_SECONDS=${TRAIN_SECONDS:-330}; STEPS=${STEPS:-20000}
REAL=${REAL:-.data/xca-real}; CONFIGS=${CONFIGS:-"gated:16,32,64,128,192 plain:16,32,64,128,192"}
mkdir -p "$RUNS" "$OUT"
python3 -c "import torch; print('torch', torch.__version__, 'cuda', torch.cuda.is_available())"
t0=$(date +%s)
[ -f "$POOL" ] || python3 -m segmentation_onnx.data --out "$POOL" --phantoms "$PHANTOMS" --first-seed "${FIRST_SEED:-0}" --frames 6 2>&1 | tail -1
echo "pool: $(( $(date +%s) - t0 )) s"
for cfg in $CONFIGS; do
  arch=${cfg%%:*}; widths=${cfg#*:}; name=${arch}_${widths%%,*}
  python3 -m segmentation_onnx.train --arch "$arch" --widths "$widths" --out "$RUNS/$name" --pool "$POOL" \
    --steps "$STEPS" --batch "${BATCH:-8}" --val-every "${VAL_EVERY:-500}" --time-limit "$TRAIN_SECONDS" \
    --real-dir "$REAL" --quiet ${AMP:+--amp} \
    ${INIT_DIR:+--init "$INIT_DIR/$name/weights.pt"} --real-fraction "${REAL_FRACTION:-0.35}" \
    > "$RUNS/$name.txt" 2>&1 &
done
wait
for d in "$RUNS"/*/; do
  n=$(basename "$d")
  python3 -m segmentation_onnx.export "$d/last.pt" "$d/$n.onnx" 2>&1 | grep -v -i warn | tail -1
  python3 -c "import torch,sys; c=torch.load(sys.argv[1],map_location='cpu'); c.pop('opt'); torch.save(c, sys.argv[2])" \
    "$d/last.pt" "$d/weights.pt"
  tail -2 "$d/log.csv"
done
for d in "$RUNS"/*/; do n=$(basename "$d"); tar czf "$OUT/$n.tgz" -C "$RUNS" --exclude=last.pt "$n" "$n.txt"; done
echo "total: $(( $(date +%s) - t0 )) s"
