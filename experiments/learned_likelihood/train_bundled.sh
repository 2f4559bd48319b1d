#!/usr/bin/env bash
# Train the bundled weights (torchmocap/assets/learned/) from the repository root:
#   bash experiments/learned_likelihood/train_bundled.sh
# Round 1: ranking objective on proposal draws and the hand-crafted P tracker's particle sets.
# Round 2: the same clips again with hard negatives mined by P with the round-1 learned term
# (the minima the learned energy wrongly prefers), from the round-1 network.
# Render term: the same data, 2 epochs (a cheap term for few-particle use).
set -euo pipefail
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-1}
OUT=${OUT:-outputs/train/bundled}
torchmocap-train training_set=mocap epochs=8 progress=false hydra.run.dir=$OUT/round1
torchmocap-train training_set=mocap epochs=8 progress=false hydra.run.dir=$OUT/round2 \
  init_weights=$OUT/round1/weights.pt \
  "data.mining={overrides:['likelihood@tracker.likelihood=silhouette_learned','tracker.likelihood.terms.learned.weights=$PWD/$OUT/round1/weights.pt']}" \
  export=torchmocap/assets/learned/learned_features.pt
torchmocap-train training_set=mocap term=learned_render epochs=2 objective.max_negatives=12 progress=false \
  hydra.run.dir=$OUT/render export=torchmocap/assets/learned/learned_render.pt
