#!/usr/bin/env bash
# Variant C (not bundled): the bundled network fine-tuned with the ranking + end-to-end
# objective (3 unrolled annealing layers of 48 particles with stop-gradient resampling, from a
# start drawn at twice the proposal's spread around the truth), on the round-2 data.
#   bash experiments/learned_likelihood/train_variant_e2e.sh   (after train_bundled.sh)
set -euo pipefail
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-1}
B=${B:-outputs/train/bundled}
torchmocap-train training_set=mocap objective.name=both epochs=4 optim.lr=0.001 progress=false \
  hydra.run.dir=outputs/train/variant_e2e init_weights=$B/round2/weights.pt \
  "data.mining={overrides:['likelihood@tracker.likelihood=silhouette_learned','tracker.likelihood.terms.learned.weights=$PWD/$B/round1/weights.pt']}"
