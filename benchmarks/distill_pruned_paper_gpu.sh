#!/usr/bin/env bash
# Recover pruned `paper` students by distillation on one GPU, inside a fixed wall-clock budget,
# from nothing but this repository: the pruning itself (which units, how far) is planned on the
# target CPU by `e3dpsm prune --steps 0` (its latency model is that host's); the cuts travel as
# the prune reports' `cuts` and each student is rebuilt here from the teacher by the same
# surgery (`e3dpsm prune --replay`: a magnitude criterion, so the same channels), then
# distilled from the unpruned teacher with the labels (`distill --labels gt --device cuda`).
# Several students distil side by side on the one GPU, each its own process.
#
#   OUT=out BUDGET_S=480 WORKERS=15 CUTS="a=benchmarks/results/prune_paper_a.json b=..." \
#       bash benchmarks/distill_pruned_paper_gpu.sh
#
# The data: the training set of benchmarks/checkpoints/paper/recipe.md (12 x 10 s, seed 3,
# 192 x 256), synthesised here as train_paper_gpu.sh does. Writes to $OUT: run.log, a
# reports tarball (each student's distill report and log, the data digest), and each student
# model split into parts of 15 MB (<name>.pt.part-aa, ...; `cat` them back together).
#
# For a smoke test on a CPU: DEVICE=cpu SEQUENCES=2 SEQ_SECONDS=2 STEPS=2 BATCH=2 SEQ_LEN=4 ...
set -euo pipefail
OUT=${OUT:-out}
BUDGET_S=${BUDGET_S:-480}
WORKERS=${WORKERS:-14}
WORK=${WORK:-/tmp/e3dpsm_distill}
TEACHER=${TEACHER:-benchmarks/checkpoints/paper/checkpoint.pt}
CUTS=${CUTS:?"CUTS=\"name=prune_report.json ...\": the students to rebuild and distil"}
DEVICE=${DEVICE:-cuda} SEQUENCES=${SEQUENCES:-12} SEQ_SECONDS=${SEQ_SECONDS:-10}  # not SECONDS: bash's clock
BATCH=${BATCH:-8} SEQ_LEN=${SEQ_LEN:-32} LR=${LR:-1e-3} WARMUP=${WARMUP:-50}
STARTED=$(date +%s)
export PYTHONUNBUFFERED=1
E3=e3dpsm  # the console script (pip install . first): python -m from the root imports the unbuilt tree
mkdir -p "$OUT" "$WORK"
exec > >(tee "$OUT/run.log") 2>&1
left() { echo $(( BUDGET_S - ($(date +%s) - STARTED) )); }
stamp() { echo "[$(( $(date +%s) - STARTED )) s] $*"; }

{ nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader || true
  python3 -c "import torch, numpy, sys; print('python', sys.version.split()[0], 'torch', torch.__version__, 'numpy', numpy.__version__, 'cuda', torch.cuda.is_available())"
  echo "cores $(nproc)"; sha256sum "$TEACHER"; }

stamp "synthesising the training set (seed 3)"
$E3 synth --out "$WORK/data192" --sequences "$SEQUENCES" --seconds "$SEQ_SECONDS" --seed 3 --render-scale 0.5 \
    --workers "$WORKERS" --force --no-progress > "$WORK/synth.log" 2>&1 || { cat "$WORK/synth.log"; exit 1; }
$E3 prepare --data "$WORK/data192" --out "$WORK/prep192" --height 192 --width 256 --workers "$WORKERS" --force --no-progress
python3 benchmarks/data_digest.py "$WORK/data_digest.json" "$WORK/prep192"

stamp "rebuilding the students from their cuts"
NAMES=()
for spec in $CUTS; do
    name=${spec%%=*}; NAMES+=("$name")
    $E3 prune --checkpoint "$TEACHER" --replay "${spec#*=}" --out "$WORK/$name.replay" --force
    cp "$WORK/$name.replay/checkpoint.pt" "$WORK/$name.pruned.pt"
done

DISTILL=(--teacher "$TEACHER" --data "$WORK/prep192" --labels gt --split all --seq-len "$SEQ_LEN" --batch-size "$BATCH"
         --lr "$LR" --device "$DEVICE" --threads $(( WORKERS / ${#NAMES[@]} > 1 ? WORKERS / ${#NAMES[@]} : 1 ))
         --no-progress --force)
side_by_side() {  # $1: steps, $2: folder suffix; every student at once, each its own process
    local pids=() name
    for name in "${NAMES[@]}"; do
        $E3 distill "${DISTILL[@]}" --student "$WORK/$name.pruned.pt" --out "$WORK/$name$2" --steps "$1" \
            --warmup-steps "$(( $1 / 10 < WARMUP ? $1 / 10 + 1 : WARMUP ))" > "$WORK/$name$2.log" 2>&1 &
        pids+=($!)
    done
    for pid in "${pids[@]}"; do
        wait "$pid" || { kill "${pids[@]}" 2>/dev/null || true; tail -n 20 "$WORK"/*"$2".log; exit 1; }
    done  # one student failing stops the others: nothing keeps running on the GPU
}
if [ -z "${STEPS:-}" ]; then  # STEPS=N distils exactly N steps (a recipe); else the budget decides
    stamp "probe: 20 steps each, side by side"
    side_by_side 20 .probe
    RATE=$(python3 -c "
import json; print(min(1 / json.load(open('$WORK/' + n + '.probe/report.json'))['seconds_per_step'] for n in '${NAMES[*]}'.split()))")
    STEPS=$(python3 -c "print(max(50, int(0.85 * $RATE * ($(left) - 40))))")
    stamp "distilling $STEPS steps each at about $RATE steps/s (the slowest)"
fi
side_by_side "$STEPS" ""
for name in "${NAMES[@]}"; do
    sha256sum "$WORK/$name/checkpoint.pt"
    split -b 15000000 "$WORK/$name/checkpoint.pt" "$OUT/$name.pt.part-"
    cp "$WORK/$name/report.json" "$WORK/$name.report.json"; cp "$WORK/$name/report.md" "$WORK/$name.report.md"
done
tar -C "$WORK" -czf "$OUT/reports.tar.gz" data_digest.json $(cd "$WORK" && ls ./*.report.json ./*.report.md ./*.log)
stamp "done"
