#!/bin/sh
# `dstereo calibrate --cross-validate 4` on the four shared real cameras as a user runs it (defaults; fisheye640 with
# its fisheye model), and rig640 R again with --model fisheye; prints each verdict (cv_rig640_right.md quotes them).
# Run from the repository root: sh experiments/cv_real_verdicts.sh [OUT_DIR]
OUT=${1:-/tmp/dstereo_cv_verdicts}
D=../shared/data
run() { name=$1; shift; DSTEREO_SERVE=0 nice .venv/bin/dstereo calibrate "$@" --pattern 9x6 --square 10 --cross-validate 4 \
  -q --force --out "$OUT/$name" 2>/dev/null; python3 -c "import json,sys; x=json.load(open('$OUT/$name/summary.json'))['cross_validation']; print('$name:', x['verdict'])"; }
run opencv_stereo_L --images $D/opencv_stereo --glob 'left*.jpg'
run rig640_L --images $D/rig640 --glob 'left*.jpg'
run rig640_R --images $D/rig640 --glob 'right*.jpg'
run fisheye640 --images $D/fisheye640 --glob 'view*.jpg' --model fisheye
run rig640_R_fisheye --images $D/rig640 --glob 'right*.jpg' --model fisheye
