#!/usr/bin/env bash
# The lockstep study of docs/frontend.md ("Lockstep runs"): repeats, seeds, throughput, the gap to paced
# runs, and how well two rules pair. Every command is resumable (re-run this script after a stop).
#
#   sweeps/lockstep_study.sh BUILD DATA OUT
#
# BUILD: `jsve frontend build`'s folder; DATA: holds voc.txt and the rendered EuRoC-format sequences
# V1_01, MH_01 and V2_02 (`jsve render`, see docs/frontend.md); OUT: the study's folder. ORB-SLAM3's
# settings come from $SETTINGS (default: ../shared/data/euroc/orbslam3_config/Monocular-Inertial.yaml).
# Then `python analysis/lockstep_study.py OUT` writes the tables.
set -euo pipefail
BUILD=$1 DATA=$2 OUT=$3
SETTINGS=${SETTINGS:-../shared/data/euroc/orbslam3_config/Monocular-Inertial.yaml}
SEEDS=${SEEDS:-10} REPEATS=${REPEATS:-5} WORKERS=${WORKERS:-2}
SEQUENCES=(V1_01 MH_01 V2_02)
mkdir -p "$OUT"
run() {  # run NAME ARGS...: one `jsve frontend run` batch, its wall time appended to OUT/batches.jsonl
    local name=$1
    shift
    local start end
    start=$(date +%s.%N)
    jsve frontend run "$BUILD" "$@" --vocabulary "$DATA/voc.txt" --settings "$SETTINGS" \
        --workers "$WORKERS" --no-progress
    end=$(date +%s.%N)
    printf '{"batch": "%s", "seconds": %s, "workers": %s}\n' "$name" "$(echo "$end - $start" | bc)" \
        "$WORKERS" >>"$OUT/batches.jsonl"
}
# The datasets: each sequence undisturbed and blurred (kernel 20 px).
datasets=()
for s in "${SEQUENCES[@]}"; do
    jsve disturb "$DATA/$s" --disturbances blur=20 -o "$OUT/disturbed" --no-progress --yes
    datasets+=("$DATA/$s" "$OUT/disturbed/$s/blur-20")
done
# 1. Lockstep runs of ORB-SLAM3's rule, seeds 0..SEEDS-1.
run "${datasets[@]}" --lockstep --runs "$SEEDS" -o "$OUT/lockstep"
# 2. Repeats of one seed per dataset, byte for byte: REPEAT_SEEDS names the seed of each sequence
# (chosen from step 1 so that one run has a reset at initialisation and one a loop closure).
REPEAT_SEEDS=${REPEAT_SEEDS:-"V1_01:3 MH_01:3 V2_02:3"}
for r in $(seq 0 $((REPEATS - 1))); do
    for pair in $REPEAT_SEEDS; do
        s=${pair%%:*} seed=${pair##*:}
        run "$DATA/$s" --lockstep --seed "$seed" --runs 1 -o "$OUT/repeats/rep$r"
    done
    run "$DATA/V1_01" --lockstep --seed 3 --runs 1 --rule sve-option2 --switch-model imu-coast \
        -o "$OUT/repeats/rep$r"
done
# 3. Lockstep runs of sve-option2 on the same seeds (paired with step 1), and paced runs of ORB-SLAM3's
# rule (the same RANSAC seeds; their threads' timing still varies).
run "${datasets[@]}" --lockstep --runs "$SEEDS" --rule sve-option2 -o "$OUT/lockstep"
run "${datasets[@]}" --seed 0 --runs "$SEEDS" -o "$OUT/paced"
