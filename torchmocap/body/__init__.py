"""Body surfaces: capsule skin (distances, samples, meshes) and the skinned CC0 mesh (LBS)."""

from torchmocap.body import capsules, parts, skinning
from torchmocap.body.capsules import *  # noqa: F403 - re-exports capsules.__all__
from torchmocap.body.parts import *  # noqa: F403
from torchmocap.body.skinning import *  # noqa: F403

__all__ = sorted({*capsules.__all__, *parts.__all__, *skinning.__all__})
