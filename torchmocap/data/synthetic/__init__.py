"""Synthetic sequences: a motion-capture clip and a scenario in, observations out.

:func:`synthesize` renders a subject (:mod:`torchmocap.data.subjects`) with the scenario's body,
cameras and corruptions (:mod:`~torchmocap.data.synthetic.scenario`): silhouettes
(:mod:`~torchmocap.data.synthetic.silhouettes`), colour images
(:mod:`~torchmocap.data.synthetic.images`), IMU orientations
(:mod:`~torchmocap.data.synthetic.imu`), depth points (:mod:`~torchmocap.data.synthetic.depth`)
and 2D joints (:mod:`~torchmocap.data.synthetic.joints2d`, self-occlusion:
:mod:`~torchmocap.data.synthetic.occlusion`), rasterised by
:mod:`~torchmocap.data.synthetic.render`. :func:`synthesized_sequence` is the ``data`` config's
source (``data=default``): a clip file, its skeleton map and a scenario by name.
"""

from torchmocap.data.synthetic.clips import DataConfigError, synthesized_sequence
from torchmocap.data.synthetic.scenario import Scenario, ScenarioError, build_rig, load_scenario
from torchmocap.data.synthetic.synthesis import CameraVisibilityError, SynthesisError, synthesize

__all__ = [
    "CameraVisibilityError",
    "DataConfigError",
    "Scenario",
    "ScenarioError",
    "SynthesisError",
    "build_rig",
    "load_scenario",
    "synthesize",
    "synthesized_sequence",
]
