#!/usr/bin/env bash
# Held-out evaluation (run from the repository root, one job at a time):
#   bash experiments/learned_likelihood/run_eval.sh [trackers...]    # default: p ls g
#   bash experiments/learned_likelihood/run_eval.sh pb   # P with variant B only (after
#                                                          train_variant_image.sh)
# Clips of subjects not used for training: walking (CMU 131), grab_high (HDM05 dg), salsa
# (CMU 60); outdoor scenario (skinned body); 40 frames; seeds 0 1 2 (each seed synthesises its
# own observations). Hand-crafted and learned runs alternate per seed (same machine load).
# Then: python experiments/learned_likelihood/summarize.py
set -euo pipefail
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-1}
HERE=experiments/learned_likelihood
TRACKERS=${*:-p ls g}
SEEDS=${SEEDS:-0,1,2}
common=(data=skinned_outdoor data/clip=walking,grab_high,salsa data.clip.frames=40
        overlays=0 progress=false sequence_cache=$HERE/runs/sequences
        'hydra.sweep.subdir=${hydra.job.num}_${data.clip.name}_${seed}')
for seed in ${SEEDS//,/ }; do
  for t in $TRACKERS; do
    if [ "$t" = pb ]; then
      torchmocap-track -m "${common[@]}" tracker=p seed=$seed \
        likelihood@tracker.likelihood=image_learned \
        tracker.likelihood.terms.learned.weights=$PWD/outputs/train/variant_image/round2/weights.pt \
        hydra.sweep.dir=$HERE/runs/p_learnedimage/seed$seed
      continue
    fi
    case $t in
      p|g) hand=(); learned=(likelihood@tracker.likelihood=silhouette_learned) ;;
      # LS's hand-crafted energy as these runs were made: the blurred silhouette term (the
      # preset now uses the distance term; the learned variant replaces the blurred one)
      ls)  hand=(likelihood@tracker.likelihood=smooth_image_orientation)
           learned=(likelihood@tracker.likelihood=smooth_image_orientation_learned
                             tracker.likelihood.weights.appearance=0) ;;
    esac
    torchmocap-track -m "${common[@]}" tracker=$t seed=$seed "${hand[@]}" \
      hydra.sweep.dir=$HERE/runs/${t}_handcrafted/seed$seed
    torchmocap-track -m "${common[@]}" tracker=$t seed=$seed "${learned[@]}" \
      hydra.sweep.dir=$HERE/runs/${t}_learned/seed$seed
  done
done
