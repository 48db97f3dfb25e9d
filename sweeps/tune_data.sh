#!/usr/bin/env bash
# The datasets and vocabulary of the tunings in docs/tuning.md: five rendered EuRoC trajectories (frames
# 0-599, 30 s each), three of them for training and two held out, each blurred, occluded and downsampled.
# Every step is resumable (re-run the script after a stop).
#
#   sweeps/tune_data.sh DATA
#
# DATA/<SEQ> the rendered sequences, DATA/disturbed/<SEQ>/<disturbance>-<level> their disturbed copies,
# DATA/voc.txt the vocabulary. The EuRoC files come from $EUROC (default ../shared/data/euroc).
set -euo pipefail
DATA=$1
EUROC=${EUROC:-../shared/data/euroc}
WORKERS=${WORKERS:-2}
LEVELS=${LEVELS:-blur=20,occlusion=350,downsample=0.25}
for seq in V1_01:V101 V1_02:V102 V2_01:V201 V2_02:V202 MH_01:MH01; do
    name=${seq%%:*} stem=${seq##*:}
    jsve render --trajectory "$EUROC/groundtruth_left_cam/${stem}_GT.txt" \
        --timestamps "$EUROC/timestamps/$stem.txt" --imu-noise datasheet \
        --texture "$EUROC/V1_01_first95/mav0/cam0/data" --frames 0:600 --workers "$WORKERS" \
        -o "$DATA/$name" --yes --no-progress
    jsve disturb "$DATA/$name" --disturbances "$LEVELS" -o "$DATA/disturbed" --workers "$WORKERS" \
        --no-progress --yes
done
[ -f "$DATA/voc.txt" ] || jsve frontend vocabulary "$EUROC/V1_01_first95/mav0/cam0/data" -o "$DATA/voc.txt" \
    --no-progress
