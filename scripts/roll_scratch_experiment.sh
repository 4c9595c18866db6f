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
#   scripts/roll_scratch_experiment.sh keep       # stop, keep unfinished runs for a later clone
#
# Environment: OUT (runs/roll_scratch), SEEDS ("0"), SHIFT_MM (20), SIM_SPEED (16),
# NICE (19: the training yields the CPU to anything else), EQUACT (target/release/equact),
# KEEP (policy/weights/candidates).
#
# Across sittings: OUT is ignored by git, so a fresh clone starts without it. Each finished
# run's weights are also copied to KEEP as roll_<arm>_s<seed>_run<N>.safetensors (2.4 MB);
# commit them, and a later clone skips that run and starts the next from the kept file (the
# demonstrations are re-collected, the same ones: they are seeded). A run that a sitting
# cannot finish is kept too: `... keep` stops the running trainings as Ctrl-C would (each
# saves a checkpoint after its current step; the script running them then stops) and copies
# each unfinished run's checkpoint to KEEP as roll_<arm>_s<seed>_run<N>.checkpoint/ (weights,
# optimiser moments, settings and log, about 7 MB, with the demonstrations' checksum). Commit
# it, and a later clone resumes that run from it, bit for bit as if never stopped, once it
# has checked that the re-collected demonstrations are the same. Run 1 of both arms is about
# 2.5 h of both cores, runs 2 and 3 about 2 h, the two roll evaluations about 20 min.
set -euo pipefail
# A failed training inside $(...) must stop the script, not pass its partial weights on.
shopt -s inherit_errexit
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
KEEP=${KEEP:-policy/weights/candidates}

# The files of a training checkpoint (`equact train --out`), all a resume reads.
CHECKPOINT_FILES=(model.safetensors optimizer.safetensors train.json log.jsonl)
demos="$OUT/demos"
# One checksum of the demonstrations' contents, so that a kept checkpoint resumes only on
# the demonstrations it was trained on. A safetensors file counts by its tensors and its
# header's meaning: re-collected demonstrations hold the same values, but binaries before
# d17d6dc wrote the header's metadata in an order of their own (a hash map's).
demos_checksum() {
    python3 - "$demos" <<'PY'
import hashlib, json, os, struct, sys
root, total = sys.argv[1], hashlib.sha256()
for path in sorted(os.path.relpath(os.path.join(d, f), root)
                   for d, _, files in os.walk(root) for f in files):
    data = open(os.path.join(root, path), "rb").read()
    if path.endswith(".safetensors"):
        n = struct.unpack("<Q", data[:8])[0]
        header = json.dumps(json.loads(data[8:8 + n]), sort_keys=True).encode()
        data = header + data[8 + n:]
    total.update(path.encode() + b"\0" + hashlib.sha256(data).digest())
print(total.hexdigest())
PY
}

if [ "${1:-}" = keep ]; then
    kept_any=0
    for seed in $SEEDS; do
        for arm in control shift; do
            for n in 1 2 3; do
                src="$OUT/${arm}_s$seed/run$n"
                kept="$KEEP/roll_${arm}_s${seed}_run$n"
                # A finished run is kept as its weights; one not started has nothing.
                if [ -f "$kept.safetensors" ] || [ ! -f "$src/model.safetensors" ]; then
                    continue
                fi
                # A running training is stopped the way Ctrl-C stops it: it saves a
                # checkpoint after its current step (seconds) and exits.
                if pkill -INT -f -- "--out $src( |\$)"; then
                    echo "stopping the training in $src (a checkpoint after its current step)"
                    for _ in $(seq 300); do
                        pgrep -f -- "--out $src( |\$)" > /dev/null || break
                        sleep 1
                    done
                    if pgrep -f -- "--out $src( |\$)" > /dev/null; then
                        echo "the training in $src did not stop within 5 minutes" >&2
                        exit 1
                    fi
                fi
                rm -rf "$kept.checkpoint.partial"
                mkdir -p "$kept.checkpoint.partial"
                for f in "${CHECKPOINT_FILES[@]}"; do
                    cp "$src/$f" "$kept.checkpoint.partial/"
                done
                demos_checksum > "$kept.checkpoint.partial/demos.sha256"
                rm -rf "$kept.checkpoint"
                mv "$kept.checkpoint.partial" "$kept.checkpoint"
                echo "kept $src (step $(tail -n 1 "$src/log.jsonl" | sed 's/.*"step":\([0-9]*\).*/\1/')) in $kept.checkpoint"
                kept_any=1
            done
        done
    done
    [ "$kept_any" = 1 ] || echo "no unfinished run in $OUT to keep"
    exit 0
elif [ $# -gt 0 ]; then
    echo "usage: $0 [keep]" >&2
    exit 2
fi

[ -x "$EQUACT" ] || cargo build --release --bin equact
mkdir -p "$OUT"

# 15 demonstrations per variation (the issue's 10-15), the off-centre roll expert's.
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
    # Run N: skipped when KEEP holds its weights (a committed earlier sitting's), else
    # trained (resuming its checkpoint, or the one an earlier sitting kept) and its weights
    # copied to KEEP; prints the weights.
    run() {
        local n=$1
        shift
        local kept="$KEEP/roll_${arm}_s${seed}_run$n.safetensors"
        local kept_checkpoint="$KEEP/roll_${arm}_s${seed}_run$n.checkpoint"
        if [ ! -f "$kept" ]; then
            if [ ! -f "$base/run$n/model.safetensors" ] && [ -d "$kept_checkpoint" ]; then
                if [ "$(demos_checksum)" != "$(cat "$kept_checkpoint/demos.sha256")" ]; then
                    echo "$kept_checkpoint was trained on other demonstrations than $demos:" \
                        "remove it to start run $n of $arm over" >&2
                    return 1
                fi
                mkdir -p "$base/run$n"
                for f in "${CHECKPOINT_FILES[@]}"; do
                    cp "$kept_checkpoint/$f" "$base/run$n/"
                done
            fi
            if ! nice -n "$NICE" "$EQUACT" train "${common[@]}" --out "$base/run$n" "$@" \
                >> "$base.log" 2>&1; then
                echo "run $n of $arm, seed $seed, failed or stopped: see $base.log" >&2
                return 1
            fi
            cp "$base/run$n/model.safetensors" "$kept"
            # The finished weights replace the kept checkpoint (commit its removal).
            rm -rf "$kept_checkpoint"
        fi
        echo "$kept"
    }
    local w1 w2
    w1=$(run 1 --lr 5e-4 --iterations 6000 --queries 30)
    w2=$(run 2 --init "$w1" --lr 3e-4 --schedule cosine --warmup 100 \
        --iterations 2400 --queries 99 --cloud-queries 0.5)
    run 3 --init "$w2" --lr 2e-4 --schedule cosine --warmup 50 \
        --iterations 900 --points 1024 --queries 99 --cloud-queries 0.5 > /dev/null
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
        model="$KEEP/roll_${arm}_s${seed}_run3.safetensors"
        evaluate "$model" install_toilet_roll "$OUT/eval_roll_${arm}_s$seed"
        [ "$EVAL_ALL" = 1 ] && evaluate "$model" all "$OUT/eval_all_${arm}_s$seed"
    done
    "$EQUACT" eval compare "$OUT/eval_roll_control_s$seed" "$OUT/eval_roll_shift_s$seed"
    "$EQUACT" eval report "$OUT/eval_roll_control_s$seed" "$OUT/eval_roll_shift_s$seed"
done
