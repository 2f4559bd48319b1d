"""torchmocap.evaluation: what a run is scored by — with ground truth (orientation error,
MPJPE, held DoFs, hypotheses, marker error) or without it (a held-out camera's detections,
bone-length constancy, jitter, silhouette agreement). Library functions that the command line
and the experiments both call.
"""
