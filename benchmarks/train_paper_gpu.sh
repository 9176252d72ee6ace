#!/usr/bin/env bash
# Train the `paper` variant on one GPU inside a fixed wall-clock budget, from nothing but this
# repository: synthesise the same data set as benchmarks/checkpoints/paper/recipe.md (seed 3,
# 12 sequences; held-out seed 2), prepare it at 192 x 256, time a short probe run, then train
# for as many steps as the budget leaves (the cosine schedule ends on the last step), and write
# the model alone (no optimiser state) in this project's checkpoint format.
#
#   OUT=out BUDGET_S=540 WORKERS=15 bash benchmarks/train_paper_gpu.sh
#
# benchmarks/checkpoints/paper/recipe.md gives the run behind the committed `paper` (the same
# script with STEPS fixed, so that it is repeatable; the budget only chose that number).
#
# Writes to $OUT: train_log.jsonl, train_report.json, data_digest.json (a digest per prepared
# sequence, to check that another machine synthesised the same data), and the model
# split into parts of 15 MB (checkpoint.pt.part-aa, ...; `cat` them back together) so that a
# transfer limited to 16 MiB per file carries it.
set -euo pipefail
OUT=${OUT:-out}
BUDGET_S=${BUDGET_S:-540}
WORKERS=${WORKERS:-14}
WORK=${WORK:-/tmp/e3dpsm_gpu}
# For a smoke test of this script on a CPU: DEVICE=cpu VARIANT=tiny SEQUENCES=3 SEQ_SECONDS=2 ...
DEVICE=${DEVICE:-cuda} VARIANT=${VARIANT:-paper} SEQUENCES=${SEQUENCES:-12} SEQ_SECONDS=${SEQ_SECONDS:-20}  # not SECONDS: bash counts elapsed time in it
BATCH=${BATCH:-8} SEQ_LEN=${SEQ_LEN:-32}
STARTED=$(date +%s)
export PYTHONUNBUFFERED=1  # needs e3dpsm installed (pip install .): quantize/ maps to e3dpsm.quantize
E3=e3dpsm  # the console script: from the repository root, python -m would import the unbuilt tree
mkdir -p "$OUT" "$WORK"
left() { echo $(( BUDGET_S - ($(date +%s) - STARTED) )); }
stamp() { echo "[$(( $(date +%s) - STARTED )) s] $*"; }

{ nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader || true
  python3 -c "import torch, numpy, sys; print('python', sys.version.split()[0], 'torch', torch.__version__, 'numpy', numpy.__version__, 'cuda', torch.cuda.is_available())"
  echo "cores $(nproc)"; } 2>&1

stamp "synthesising (train seed 3 and held-out seed 2 side by side)"
$E3 synth --out "$WORK/data192" --sequences "$SEQUENCES" --seconds "$SEQ_SECONDS" --seed 3 --render-scale 0.5 \
    --workers $(( WORKERS > 3 ? WORKERS - 3 : 1 )) --force --no-progress > "$WORK/synth.log" 2>&1 &
TRAIN_DATA=$!
$E3 synth --out "$WORK/data192_test" --sequences 3 --seconds "$SEQ_SECONDS" --seed 2 --render-scale 0.5 \
    --workers 3 --force --no-progress > "$WORK/synth_test.log" 2>&1 &
TEST_DATA=$!
wait $TRAIN_DATA && wait $TEST_DATA || { cat "$WORK"/synth*.log; exit 1; }
stamp "preparing"
$E3 prepare --data "$WORK/data192" --out "$WORK/prep192" --height 192 --width 256 --workers "$WORKERS" --force --no-progress
$E3 prepare --data "$WORK/data192_test" --out "$WORK/prep192_test" --height 192 --width 256 --workers 3 --force --no-progress
python3 benchmarks/data_digest.py "$OUT/data_digest.json" "$WORK/prep192" "$WORK/prep192_test"

TRAIN=(--variant "$VARIANT" --data "$WORK/prep192" --split all --seq-len "$SEQ_LEN" --batch-size "$BATCH" --device "$DEVICE"
       --num-workers 6 --log-every 10 --no-progress --force)
if [ -z "${STEPS:-}" ]; then  # STEPS=N trains exactly N steps (a recipe); else the budget decides
    stamp "probe: 20 steps"
    $E3 train "${TRAIN[@]}" --out "$WORK/probe" --steps 20 --save-every 1000
    RATE=$(python3 -c "import json; print(json.loads(open('$WORK/probe/log.jsonl').read().splitlines()[-1])['steps_per_s'])")
    STEPS=$(python3 -c "print(max(50, int(0.85 * $RATE * ($(left) - 45))))")
    stamp "training $STEPS steps at about $RATE steps/s"
fi
$E3 train "${TRAIN[@]}" --out "$WORK/run" --steps "$STEPS" --save-every 200
cp "$WORK/run/log.jsonl" "$OUT/train_log.jsonl"
cp "$WORK/run/report.json" "$OUT/train_report.json"
python3 - "$WORK/run/checkpoint.pt" "$WORK/model.pt" <<'EOF'
import sys, torch
payload = torch.load(sys.argv[1], map_location="cpu", weights_only=True)
for key in ("optimizer", "scheduler", "rng_torch"):  # training state: the model alone travels
    payload.pop(key, None)
torch.save(payload, sys.argv[2])
print("model alone:", sys.argv[2], "step", payload["step"])
EOF
sha256sum "$WORK/model.pt"
split -b 15000000 "$WORK/model.pt" "$OUT/checkpoint.pt.part-"
stamp "done"
