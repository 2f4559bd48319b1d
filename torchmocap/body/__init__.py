"""Body surfaces: capsule skin (distances, samples, meshes), the skinned CC0 mesh (LBS) and the
Anny parametric body (phenotype rest shapes driven by a skeleton; optional ``anny`` build)."""

from torchmocap.body import (
    capsule_fit,
    capsules,
    parametric,
    parts,
    phenotype_fit,
    phenotypes,
    skinning,
)
from torchmocap.body.capsule_fit import *  # noqa: F403
from torchmocap.body.capsules import *  # noqa: F403 - re-exports capsules.__all__
from torchmocap.body.parametric import *  # noqa: F403
from torchmocap.body.parts import *  # noqa: F403
from torchmocap.body.phenotype_fit import *  # noqa: F403
from torchmocap.body.phenotypes import *  # noqa: F403
from torchmocap.body.skinning import *  # noqa: F403

__all__ = sorted({*capsule_fit.__all__, *capsules.__all__, *parametric.__all__, *parts.__all__,
                  *phenotype_fit.__all__, *phenotypes.__all__, *skinning.__all__})
