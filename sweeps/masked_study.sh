#!/usr/bin/env bash
# The masked study of docs/masks.md ("Table I from real runs"): ORB-SLAM3 with and without masks in the
# loop, lockstep, SEEDS seeds, on rendered sequences with cars and pedestrians moving (5 of 6) and the
# same scenes with every object parked. Every command is resumable (re-run this script after a stop);
# then `python analysis/masked_study.py OUT --data DATA/moving --csv docs/data/masked_runs.csv`.
#
#   sweeps/masked_study.sh BUILD DATA OUT
#
# BUILD: `jsve frontend build`'s folder; DATA: voc.txt, and moving/ where this script renders the
# datasets (`jsve render --cars 2 --pedestrians 4`, frames 0-1199); OUT: the study's folder. ORB-SLAM3's
# settings come from $SETTINGS (default: ../shared/data/euroc/orbslam3_config/Monocular-Inertial.yaml),
# the EuRoC files from $EUROC (default ../shared/data/euroc).
set -euo pipefail
BUILD=$1 DATA=$2 OUT=$3
EUROC=${EUROC:-../shared/data/euroc}
SETTINGS=${SETTINGS:-$EUROC/orbslam3_config/Monocular-Inertial.yaml}
SEEDS=${SEEDS:-10} WORKERS=${WORKERS:-2}
run() {  # one `jsve frontend run` batch, WORKERS drivers at once (one per core)
    jsve frontend run "$BUILD" "$@" --vocabulary "$DATA/voc.txt" --settings "$SETTINGS" --lockstep \
        --runs "$SEEDS" --workers "$WORKERS" --no-progress
}
for seq in V1_01:V101 V2_01:V201; do
    name=${seq%%:*} stem=${seq##*:}
    for scene in moving parked; do
        parked=1
        [ "$scene" = parked ] && parked=all
        jsve render --trajectory "$EUROC/groundtruth_left_cam/${stem}_GT.txt" \
            --timestamps "$EUROC/timestamps/$stem.txt" --imu-noise datasheet \
            --texture "$EUROC/V1_01_first95/mav0/cam0/data" --frames 0:1200 \
            --cars 2 --pedestrians 4 --parked "$parked" --workers "$WORKERS" \
            -o "$DATA/moving/$name-$scene" --yes --no-progress
    done
done
for scene in moving parked; do
    datasets=("$DATA/moving/V1_01-$scene" "$DATA/moving/V2_01-$scene")
    # The original runs write their keypoints, for masking them offline (jsve mask-logs).
    run "${datasets[@]}" --keypoints -o "$OUT/$scene/original"
    run "${datasets[@]}" --masks --keypoints -o "$OUT/$scene/masked"
done
