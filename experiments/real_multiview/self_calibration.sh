#!/usr/bin/env bash
# The tracks of the self-calibration table (README "Self-calibration"): each preset tracks the
# frames a split did not refine on, each camera held out in turn, with the recording's own
# calibration and with the one refined from the subject on the other frames (every camera).
#   split a: refine on 0-59, track and score 60-99;  split b: refine on 40-99, track 0-39.
# Usage: experiments/real_multiview/self_calibration.sh [SPLIT [CALIB [PRESET ...]]] | learned
# (from the repository root; runs into experiments/real_multiview/runs_selfcal/<split>/<calib>/
# <preset>/<cam>; a finished run is skipped when nothing changed).
set -euo pipefail
export OMP_NUM_THREADS=1 MKL_NUM_THREADS=1
REC=${REC:-../shared/data/multiview/pose2sim_balancing}
OUT=${OUT:-experiments/real_multiview/runs_selfcal}
# The learned keypoint term on the refined calibration (split a): per held-out camera a training
# on frames 0-59 of the other three cameras (the refinement saw all four on 0-59), then
# real_local with the learned term on 60-99:  experiments/real_multiview/self_calibration.sh learned
if [ "${1:-}" = learned ]; then
  for cam in cam01 cam02 cam03 cam04; do
    train="$OUT/a/refined/train/$cam"
    [ -f "$train/keypoints.pt" ] || torchmocap-train --config-name train_keypoints \
      data.path="$REC" evaluation.heldout_camera=$cam data.calibration.refine=true \
      'data.calibration.frames=[0,60]' progress=false hydra.run.dir="$train"
    torchmocap-track data=recording data.path="$REC" data.start=60 data.stop=100 \
      data.calibration.refine=true 'data.calibration.frames=[0,60]' tracker=real_local \
      term@tracker.likelihood.terms.keypoints=keypoints_learned \
      tracker.likelihood.terms.keypoints.weights="$train/keypoints.pt" \
      evaluation.heldout_camera=$cam threads=1 overlays=0 glb.enabled=false progress=false \
      hydra.run.dir="$OUT/a/refined/real_local_learned/$cam" \
      || echo "failed: learned $cam" >&2
  done
  exit 0
fi
splits=${1:-"a b"}
calibs=${2:-"given refined"}
shift $(( $# > 2 ? 2 : $# )) || true
presets=${*:-"real_local real_mixture real_keypoints real_sir"}
for split in $splits; do
  case $split in
    a) range="data.start=60 data.stop=100"; refine="[0,60]" ;;
    b) range="data.start=0 data.stop=40"; refine="[40,100]" ;;
    *) echo "unknown split $split (a or b)" >&2; exit 2 ;;
  esac
  for calib in $calibs; do
    case $calib in
      given) cal="data.calibration.refine=false" ;;
      refined) cal="data.calibration.refine=true data.calibration.frames=$refine" ;;
      *) echo "unknown calibration $calib (given or refined)" >&2; exit 2 ;;
    esac
    for preset in $presets; do
      for cam in cam01 cam02 cam03 cam04; do
        torchmocap-track data=recording data.path="$REC" $range $cal tracker="$preset" \
          evaluation.heldout_camera=$cam threads=1 overlays=0 glb.enabled=false progress=false \
          hydra.run.dir="$OUT/$split/$calib/$preset/$cam" \
          || echo "failed: $split $calib $preset $cam" >&2
      done
    done
  done
done
