#!/usr/bin/env bash
# The tracking runs of experiments/detector (from the repository root):
#   bash experiments/detector/run.sh [group ...]     # groups: openpose mediapipe_detector
#                                                    #         mediapipe_compute (default: all)
# One run per group and held-out camera into experiments/detector/runs/<group>/<cam>; a run
# that is complete is skipped (torchmocap-track's skip_completed). Sequential, one thread.
set -euo pipefail
REC=${REC:-../shared/data/multiview/pose2sim_balancing}
ALONE=${ALONE:-outputs/videos_alone/pose2sim_balancing}
TRACK=${TRACK:-torchmocap-track}
export OMP_NUM_THREADS=1
python experiments/detector/videos_alone.py prepare --recording "$REC" --out "$ALONE"
groups=${*:-openpose mediapipe_detector mediapipe_compute}
common="tracker=real_keypoints threads=1 progress=false glb.enabled=false"
for group in $groups; do
  case $group in
    openpose) data="data.path=$REC overlays=0" ;;
    mediapipe_detector) data="data.path=$ALONE data.keypoints.source=mediapipe data.masks=detector overlays=10" ;;
    mediapipe_compute) data="data.path=$ALONE data.keypoints.source=mediapipe data.masks=compute overlays=0" ;;
    *) echo "unknown group $group" >&2; exit 2 ;;
  esac
  for cam in cam01 cam02 cam03 cam04; do
    $TRACK data=recording $data $common evaluation.heldout_camera=$cam \
      hydra.run.dir=experiments/detector/runs/$group/$cam
  done
done
