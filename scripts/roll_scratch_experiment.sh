#!/usr/bin/env bash
# Issue 9's next experiment for the toilet roll: train the built-in model's recipe from
# random weights on the off-centre roll expert's demonstrations, without and with the
# held-object shift (`--held-shift-mm`), then evaluate both on the same unseen scenes and
# compare them (`equact eval compare`). Hours on a 2-core machine (about 3 h of training per
# arm and seed with both arms at once), so every step resumes: rerun the script and it goes
# on where it stopped (demonstrations, checkpoints and finished evaluations are kept).
#
#   scripts/roll_scratch_experiment.sh            # seed 0, both arms
#   SEEDS="0 1 2" scripts/roll_scratch_experiment.sh
#   EVAL_ALL=1 scripts/roll_scratch_experiment.sh # also 20 episodes of every variation
#
# Environment: OUT (runs/roll_scratch), SEEDS ("0"), SHIFT_MM (20), SIM_SPEED (16),
# NICE (19: the training yields the CPU to anything else), EQUACT (target/release/equact).
set -euo pipefail
cd "$(dirname "$0")/.."

OUT=${OUT:-runs/roll_scratch}
SEEDS=${SEEDS:-0}
SHIFT_MM=${SHIFT_MM:-20}
# Episodes are the same at any speed (the controller runs in lockstep with the driver):
# the built-in model's first two seeds of each roll at 16x gave the logs of `eval_roll_tick3`
# (4x), in 27 s instead of 31.
SIM_SPEED=${SIM_SPEED:-16}
NICE=${NICE:-19}
EQUACT=${EQUACT:-target/release/equact}
EVAL_ALL=${EVAL_ALL:-0}

[ -x "$EQUACT" ] || cargo build --release --bin equact
mkdir -p "$OUT"

# 15 demonstrations per variation (the issue's 10-15), the off-centre roll expert's.
demos="$OUT/demos"
if [ ! -f "$demos/index.json" ]; then
    for task in pick_fruit disassemble_pipe pluck_flower install_toilet_roll; do
        "$EQUACT" demos collect --task "$task" --episodes 15 --out "$OUT/demos_$task" \
            > "$OUT/demos_$task.log" 2>&1 &
    done
    wait
    "$EQUACT" demos merge --out "$demos" "$OUT"/demos_{pick_fruit,disassemble_pipe,pluck_flower,install_toilet_roll}
fi

# One arm and seed: the built-in model's three runs (`equact policy info`), each resumed
# from its checkpoint when rerun.
train_arm() {
    local arm=$1 seed=$2 shift_flag=()
    [ "$arm" = shift ] && shift_flag=(--held-shift-mm "$SHIFT_MM")
    local base="$OUT/${arm}_s$seed"
    local common=(--demos "$demos" --network cpu --mode gated --batch 2 --threads 1
        --paired --sibling-negatives --seed "$seed" "${shift_flag[@]}")
    nice -n "$NICE" "$EQUACT" train "${common[@]}" --out "$base/run1" \
        --lr 5e-4 --iterations 6000 --queries 30 >> "$base.log" 2>&1
    nice -n "$NICE" "$EQUACT" train "${common[@]}" --out "$base/run2" \
        --init "$base/run1/model.safetensors" --lr 3e-4 --schedule cosine --warmup 100 \
        --iterations 2400 --queries 99 --cloud-queries 0.5 >> "$base.log" 2>&1
    nice -n "$NICE" "$EQUACT" train "${common[@]}" --out "$base/run3" \
        --init "$base/run2/model.safetensors" --lr 2e-4 --schedule cosine --warmup 50 \
        --iterations 900 --points 1024 --queries 99 --cloud-queries 0.5 >> "$base.log" 2>&1
}

for seed in $SEEDS; do
    mkdir -p "$OUT/control_s$seed" "$OUT/shift_s$seed"
    train_arm control "$seed" &
    control=$!
    train_arm shift "$seed" &
    shifted=$!
    wait "$control"
    wait "$shifted"
done

# Evaluations one at a time (the simulated cell runs SIM_SPEED times faster than real time
# and needs the CPU); a finished one is not run again.
evaluate() {
    local model=$1 task=$2 dir=$3
    [ -f "$dir/done" ] && return 0
    rm -rf "$dir"
    "$EQUACT" eval --task "$task" --episodes 20 --model "$model" --network cpu \
        --sim-speed "$SIM_SPEED" --out "$dir" > "$dir.md" 2> "$dir.log"
    touch "$dir/done"
}
for seed in $SEEDS; do
    for arm in control shift; do
        model="$OUT/${arm}_s$seed/run3/model.safetensors"
        evaluate "$model" install_toilet_roll "$OUT/eval_roll_${arm}_s$seed"
        [ "$EVAL_ALL" = 1 ] && evaluate "$model" all "$OUT/eval_all_${arm}_s$seed"
    done
    "$EQUACT" eval compare "$OUT/eval_roll_control_s$seed" "$OUT/eval_roll_shift_s$seed"
    "$EQUACT" eval report "$OUT/eval_roll_control_s$seed" "$OUT/eval_roll_shift_s$seed"
done
