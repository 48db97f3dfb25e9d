#!/usr/bin/env bash
# The lockstep study of docs/frontend.md ("Lockstep runs"): repeats, seeds, where a run's time goes, the
# gap to paced runs, and how well two rules pair across seeds. Every command is resumable (re-run this
# script after a stop); then `python analysis/lockstep_study.py OUT --csv docs/data/lockstep_runs.csv`.
#
#   REPEAT_SEEDS=$'DATASET SEED [OPTIONS]\n...' sweeps/lockstep_study.sh BUILD DATA OUT
#
# BUILD: `jsve frontend build`'s folder; DATA: voc.txt and the rendered EuRoC-format sequences V1_01,
# MH_01 and V2_02 (`jsve render`, docs/frontend.md); OUT: the study's folder. ORB-SLAM3's settings come
# from $SETTINGS (default: ../shared/data/euroc/orbslam3_config/Monocular-Inertial.yaml). REPEAT_SEEDS
# names the runs repeated five times, one per line (default: those of docs/frontend.md: seed 3 of MH_01,
# of V2_02, which closes a loop, and of V1_01 under a harsh inlier rule, which resets before BA2).
set -euo pipefail
BUILD=$1 DATA=$2 OUT=$3
SETTINGS=${SETTINGS:-../shared/data/euroc/orbslam3_config/Monocular-Inertial.yaml}
SEEDS=${SEEDS:-10} REPEATS=${REPEATS:-5} WORKERS=${WORKERS:-2}
REPEAT_SEEDS=${REPEAT_SEEDS:-"$DATA/MH_01 3
$DATA/V2_02 3
$DATA/V1_01 3 --rule $(dirname "$0")/rules/harsh_inliers.json"}
run() {  # one `jsve frontend run` batch, WORKERS drivers at once (one per core)
    jsve frontend run "$BUILD" "$@" --vocabulary "$DATA/voc.txt" --settings "$SETTINGS" \
        --workers "$WORKERS" --no-progress
}
# The datasets: each sequence undisturbed and blurred (kernel 20 px).
datasets=()
for s in V1_01 MH_01 V2_02; do
    jsve disturb "$DATA/$s" --disturbances blur=20 -o "$OUT/disturbed" --no-progress --yes
    datasets+=("$DATA/$s" "$OUT/disturbed/$s/blur-20")
done
# 1. Lockstep runs of ORB-SLAM3's rule, seeds 0..SEEDS-1.
run "${datasets[@]}" --lockstep --runs "$SEEDS" -o "$OUT/lockstep"
# 2. Paced runs of ORB-SLAM3's rule (the same RANSAC seeds; their threads' timing still varies), on an
# otherwise idle machine: a paced run's outcome depends on the CPU time it gets.
run "${datasets[@]}" --seed 0 --runs "$SEEDS" -o "$OUT/paced"
# 3. Lockstep runs of sve-option2 on the seeds of step 1 (V1_01 blurred), paired with them.
run "$OUT/disturbed/V1_01/blur-20" --lockstep --runs "$SEEDS" --rule sve-option2 -o "$OUT/lockstep"
# 4. Rules in the loop and record mode in lockstep, twice each.
for r in 0 1; do
    run "$DATA/V1_01" --lockstep --seed 4 --runs 1 --rule record -o "$OUT/rules/rep$r"
    run "$DATA/V1_01" --lockstep --seed 4 --runs 1 --rule sve-option2 --switch-model imu-coast -o "$OUT/rules/rep$r"
done
# 5. Repeats, byte for byte: each line of REPEAT_SEEDS ("DATASET SEED [OPTIONS]") five times, in folders
# of their own.
for r in $(seq 0 $((REPEATS - 1))); do
    while read -r dataset seed options; do
        # shellcheck disable=SC2086
        run "$dataset" --lockstep --seed "$seed" --runs 1 $options -o "$OUT/repeats/rep$r"
    done <<<"$REPEAT_SEEDS"
done
