#!/bin/bash
# The experiment's runs, from the repository root (the recording is the default data.path,
# ../shared/data/multiview/pose2sim_balancing): per held-out camera a training on the first 60
# frames of the other three, the preset tracked with the hand-set and with the learned keypoint
# term; the weights of all four cameras (shipped); then the report.
set -euo pipefail
cd "$(dirname "$0")/../.."
OUT=experiments/learned_real/runs
export OMP_NUM_THREADS=1
CAMS=(cam01 cam02 cam03 cam04)
torchmocap-train --config-name train_keypoints -m "evaluation.heldout_camera=$(IFS=,; echo "${CAMS[*]}")" \
    progress=false "hydra.sweep.dir=$OUT/train" 'hydra.sweep.subdir=${evaluation.heldout_camera}'
torchmocap-train --config-name train_keypoints progress=false "hydra.run.dir=$OUT/shipped" \
    export=torchmocap/assets/learned/keypoints_pose2sim_balancing.pt
TRACK=(data=recording data.masks=none tracker=real_local overlays=0 progress=false)
for cam in "${CAMS[@]}"; do   # hand-set and learned back to back (comparable seconds per frame)
    torchmocap-track "${TRACK[@]}" "evaluation.heldout_camera=$cam" "hydra.run.dir=$OUT/hand/$cam"
    torchmocap-track "${TRACK[@]}" "evaluation.heldout_camera=$cam" "hydra.run.dir=$OUT/learned/$cam" \
        term@tracker.likelihood.terms.keypoints=keypoints_learned \
        "tracker.likelihood.terms.keypoints.weights=$OUT/train/$cam/keypoints.pt"
done
python experiments/learned_real/report.py
# a tracker setting, chosen after the table above: the learned term's overall scale x3
for cam in "${CAMS[@]}"; do
    torchmocap-track "${TRACK[@]}" "evaluation.heldout_camera=$cam" "hydra.run.dir=$OUT/learned_scale24/$cam" \
        term@tracker.likelihood.terms.keypoints=keypoints_learned \
        "tracker.likelihood.terms.keypoints.weights=$OUT/train/$cam/keypoints.pt" \
        tracker.likelihood.terms.keypoints.scale_px=24.0
done
