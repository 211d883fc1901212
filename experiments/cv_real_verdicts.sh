#!/bin/sh
# `dstereo calibrate --cross-validate 4` on the shared real cameras as a user runs it (defaults; fisheye640 with
# its fisheye model), and rig640 R again with --model fisheye; prints each verdict and, from the written files, the
# ratio, its band, and the pooled ratios inside / outside the corners' fields with the quotient's band
# (docs/validation.md quotes them). Run from the repository root: sh experiments/cv_real_verdicts.sh [OUT_DIR]
OUT=${1:-/tmp/dstereo_cv_verdicts}
D=../shared/data
run() { name=$1; shift; DSTEREO_SERVE=0 nice .venv/bin/dstereo calibrate "$@" --pattern 9x6 --square 10 --cross-validate 4 \
  -q --force --out "$OUT/$name" 2>/dev/null; python3 -c "
import json; x = json.load(open('$OUT/$name/summary.json'))['cross_validation']; b = x['band_if_right']; d = x['diagnosis'] or {}
print('$name: ratio %.2f band %.2f-%.2f maha %.2f band %.2f-%.2f | pooled inside %.2f outside %.2f, quotient %.2f band %s, excess %s' % (
  x['ratio_geometric_mean'], b['ratio'][0], b['ratio'][1], x['mahalanobis_median'], b['mahalanobis'][0], b['mahalanobis'][1],
  d.get('ratio_pooled_inside_corner_field', float('nan')), d.get('ratio_pooled_outside_corner_field', float('nan')),
  d.get('outside_over_inside', float('nan')), d.get('outside_over_inside_band_if_right'), d.get('extrapolation_excess')))
print('   ', x['verdict'])"; }
run opencv_stereo_L --images $D/opencv_stereo --glob 'left*.jpg'
run opencv_stereo_R --images $D/opencv_stereo --glob 'right*.jpg'
run rig640_L --images $D/rig640 --glob 'left*.jpg'
run rig640_R --images $D/rig640 --glob 'right*.jpg'
run fisheye640 --images $D/fisheye640 --glob 'view*.jpg' --model fisheye
run rig640_R_fisheye --images $D/rig640 --glob 'right*.jpg' --model fisheye
