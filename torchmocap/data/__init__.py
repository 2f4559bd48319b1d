"""torchmocap.data: subjects fitted to motion clips, observation sequences and their synthesis."""

from torchmocap.data.depth import DepthData
from torchmocap.data.heldout import split_heldout
from torchmocap.data.imu import ImuData, SensorPlacementError
from torchmocap.data.scenario import Scenario, ScenarioError, build_rig, load_scenario
from torchmocap.data.sequence import (
    MODALITIES,
    Frame,
    GroundTruth,
    MissingModalityError,
    Sequence,
    SequenceFormatError,
)
from torchmocap.data.synthesis import CameraVisibilityError, SynthesisError, synthesize

__all__ = [
    "MODALITIES",
    "CameraVisibilityError",
    "DepthData",
    "Frame",
    "GroundTruth",
    "ImuData",
    "MissingModalityError",
    "Scenario",
    "ScenarioError",
    "SensorPlacementError",
    "Sequence",
    "SequenceFormatError",
    "SynthesisError",
    "build_rig",
    "load_scenario",
    "split_heldout",
    "synthesize",
]
