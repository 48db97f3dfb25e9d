#!/usr/bin/env bash
# The tunings of docs/tuning.md: the SVE family under imu-coast and under orbslam3, and the inlier family
# under orbslam3, on the rendered data of sweeps/tune_data.sh, every run kept in one pool (the baselines'
# held-out runs and ORB-SLAM3's own recordings are made once and shared). Resumable: re-run after a stop.
#
#   sweeps/tune_study.sh DATA OUT
#
# then `jsve report OUT/<family>-<switch model>` for each, and
# `python analysis/tune_summary.py OUT` for the pooled tables of docs/tuning.md.
set -euo pipefail
DATA=$1 OUT=$2
here=$(dirname "$0")
"$here/tune_data.sh" "$DATA"
for study in ${STUDIES:-sve-imu-coast sve-orbslam3 inliers-orbslam3}; do
    jsve tune "$here/tune/$study.toml" --root "$DATA" -o "$OUT/$study" --pool "$OUT/pool"
    jsve report "$OUT/$study"
done
