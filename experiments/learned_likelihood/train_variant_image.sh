#!/usr/bin/env bash
# Variant B (not bundled): the learned term on top of P's full hand-crafted cost (2 V_silh + 40
# V_app, which sees bone twist through the surface colours) and a ranking target that also counts
# joint rotation error (0.1 m per radian). Same two rounds as train_bundled.sh.
#   bash experiments/learned_likelihood/train_variant_image.sh
set -euo pipefail
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-1}
OUT=${OUT:-outputs/train/variant_image}
opts=(training_set=mocap objective.base_likelihood=image objective.err_rotation=0.1 epochs=8 progress=false)
torchmocap-train "${opts[@]}" hydra.run.dir=$OUT/round1
torchmocap-train "${opts[@]}" hydra.run.dir=$OUT/round2 init_weights=$OUT/round1/weights.pt \
  "data.mining={overrides:['likelihood@tracker.likelihood=image_learned','tracker.likelihood.terms.learned.weights=$PWD/$OUT/round1/weights.pt']}"
