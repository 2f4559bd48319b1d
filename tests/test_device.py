"""Device- and dtype-agnostic code, proved on the CPU (the CUDA runs are tests/cuda/).

* No tensor is created off the input's device: a tracker frame runs with every tensor factory
  called without ``device=`` (``torch.zeros``, ``arange``, ``tensor`` of Python data, ...)
  redirected to the ``meta`` device — such a tensor in the hot path fails the frame
  (data-dependent ops on it, or mixing it with the CPU inputs).
* No hidden round trip to the host: ``Tensor.cpu`` / ``Tensor.numpy`` are not called by
  torchmocap during a frame (deliberate exceptions: :data:`HOST_ON_PURPOSE`).
* Everything follows ``tracker.to(...)``: a float32 tracker moved with ``.double()`` tracks in
  float64 (the same mechanism moves it to a GPU), and the main components (FK, projection, the
  likelihood energy, proposals) give float64 outputs that agree with float32.
* The depth criterion's device path (brute-force nearest neighbours) equals its k-d tree.
"""

from __future__ import annotations

import traceback

import pytest
import torch
from torch.overrides import TorchFunctionMode

from torchmocap.assembly import Runtime, build_tracker, tracker_config
from torchmocap.data.synthetic.clips import synthesized_sequence

#: preset, scenario, overrides — every inference kind and the main proposals and likelihoods
PRESETS = [
    ("p", "studio", ["tracker.num_particles=12", "tracker.inference.layers=2"]),
    ("g", "studio", ["tracker.num_particles=12", "tracker.inference.layers=2"]),
    ("gs", "studio", ["tracker.num_particles=12", "tracker.inference.layers=2"]),
    ("rs", "studio", ["tracker.num_particles=12", "tracker.inference.layers=2"]),
    ("p", "studio", ["tracker.num_particles=12", "inference@tracker.inference=sir"]),
    ("ls", "studio", ["tracker.inference.iterations=3"]),
    ("hauberg_silhouette", "stereo", ["tracker.num_particles=12"]),
    ("hauberg_depth", "stereo", ["tracker.num_particles=12"]),
    ("kjs", "monocular", ["tracker.num_particles=8"]),
    ("p_prior_refined_fit", "studio", ["tracker.num_particles=12", "tracker.inference.layers=2",
                                       "tracker.inference.refine.iterations=2",
                                       "tracker.body_fit.iterations=3"]),
]
IDS = ["p", "g", "gs", "rs", "p_sir", "ls", "hauberg_silhouette", "hauberg_depth", "kjs",
       "p_fit"]
#: (file, function) allowed to copy to the host: the mixture tracker's greedy assignment of
#: modes is a Python loop over a K x K0 (8 x 8) distance matrix — one copy instead of 64 syncs
#: the mixture's greedy matching loop; the ESS β solve's numpy path, taken only for CPU tensors
#: (``.numpy()`` shares their memory; a GPU tensor takes the torch solver)
HOST_ON_PURPOSE = {("modes.py", "bhattacharyya_reweight"), ("schedules.py", "ess_target_beta")}

_FACTORIES = {torch.zeros, torch.ones, torch.empty, torch.full, torch.arange, torch.tensor,
              torch.as_tensor, torch.randn, torch.rand, torch.randint, torch.linspace,
              torch.logspace, torch.eye, torch.randperm, torch.scalar_tensor, torch.empty_strided}


class _FactoriesOnMeta(TorchFunctionMode):
    """Tensor factories called without ``device=`` make ``meta`` tensors (``as_tensor`` and
    ``tensor`` of an existing tensor keep its device, as they do outside this mode)."""

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = dict(kwargs or {})
        if func in _FACTORIES and kwargs.get("device") is None and \
                not (args and isinstance(args[0], torch.Tensor)):
            kwargs["device"] = "meta"
        return func(*args, **kwargs)


@pytest.fixture(scope="module")
def sequences():
    cache = {}

    def get(scenario):
        if scenario not in cache:
            cache[scenario] = synthesized_sequence({"frames": 3}, scenario,
                                                   {"image_size": [80, 60]}, seed=0)
        return cache[scenario]

    return get


def _started(name, scenario, overrides, sequences, dtype=torch.float32):
    seq = sequences(scenario)
    tr = build_tracker(tracker_config(name, overrides), Runtime.from_sequence(seq), seed=0)
    if dtype != torch.float32:
        tr = tr.to(dtype)
    tracking = None if seq.imu is None else seq.imu.tracking.nonzero()[:, 0]
    st = tr.init(seq.ground_truth.theta[0].to(dtype), tr.observe(seq.frame(0), tracking))
    # one frame outside the checks: per-skeleton plans and caches are built once, on the host
    st, _, _ = tr.step(st, tr.observe(seq.frame(1), tracking))
    return tr, st, tr.observe(seq.frame(2), tracking)


@pytest.mark.parametrize("name,scenario,overrides", PRESETS, ids=IDS)
def test_no_tensor_created_off_the_input_device(name, scenario, overrides, sequences):
    tr, st, frame = _started(name, scenario, overrides, sequences)
    with _FactoriesOnMeta():  # a factory call without device= makes a meta tensor
        st, est, info = tr.step(st, frame)
    assert est.device.type == "cpu" and st.history.device.type == "cpu"
    assert bool(torch.isfinite(est).all())


@pytest.mark.parametrize("name,scenario,overrides",
                         [p for p in PRESETS if p[0] != "hauberg_depth"],
                         ids=[i for i in IDS if i != "hauberg_depth"])
def test_no_host_round_trip(name, scenario, overrides, sequences, monkeypatch):
    """``hauberg_depth`` is left out: on the CPU its criterion uses scipy's k-d tree (on a GPU
    the brute-force path, :func:`test_nearest_distance_matches_kdtree`)."""
    tr, st, frame = _started(name, scenario, overrides, sequences)
    calls = []

    def spy(method):
        orig = getattr(torch.Tensor, method)

        def wrapped(self, *a, **k):
            here = [f for f in traceback.extract_stack()[:-1] if "/torchmocap/" in f.filename]
            if here and (here[-1].filename.rsplit("/", 1)[-1], here[-1].name) \
                    not in HOST_ON_PURPOSE:
                calls.append(f"{method} at {here[-1].filename}:{here[-1].lineno}")
            return orig(self, *a, **k)

        return wrapped

    for m in ("cpu", "numpy"):
        monkeypatch.setattr(torch.Tensor, m, spy(m))
    tr.step(st, frame)
    monkeypatch.undo()
    assert calls == []


@pytest.mark.parametrize("name,scenario,overrides", PRESETS, ids=IDS)
def test_tracker_follows_to(name, scenario, overrides, sequences):
    """A float32 tracker moved with ``.to(torch.float64)`` computes in float64 throughout."""
    tr, st, frame = _started(name, scenario, overrides, sequences, dtype=torch.float64)
    assert tr.dtype == torch.float64
    st, est, _ = tr.step(st, frame)
    assert est.dtype == torch.float64 and st.history.dtype == torch.float64
    if st.particles is not None:
        assert st.particles.dtype == torch.float64


def test_components_dtype_sweep(sequences):
    """FK, projection, the likelihood energy and proposals in float64 agree with float32."""
    from torchmocap.proposals.base import ProposalContext

    seq = sequences("studio")
    tracking = seq.imu.tracking.nonzero()[:, 0]
    out = {}
    g = torch.Generator().manual_seed(0)
    theta = seq.ground_truth.theta[1].double() + 0.05 * torch.randn(
        16, seq.ground_truth.theta.shape[1], generator=g, dtype=torch.float64)
    for dt in (torch.float32, torch.float64):
        rt = Runtime.from_sequence(seq, dtype=dt)
        tr = build_tracker(tracker_config("p"), rt, seed=0)
        frame = tr.observe(seq.frame(1), tracking)
        tr.init(seq.ground_truth.theta[0].to(dt), tr.observe(seq.frame(0), tracking))
        th = theta.to(dt)
        kin = rt.skeleton(th)
        pix, depth, vis = rt.rig.project(kin.positions)
        with torch.no_grad():
            energy = tr.frame_energy(frame)(th)
        ctx = ProposalContext(previous=th[0], sensors=tr._sensors(frame))
        prop = tr.proposal.sample(ctx, 16, torch.Generator().manual_seed(1)).particles
        for name, x in (("fk", kin.positions), ("pix", pix), ("energy", energy),
                        ("proposal", prop)):
            assert x.dtype == dt, (name, x.dtype)
            assert bool(torch.isfinite(x).all()), name
        out[dt] = {"fk": kin.positions, "pix": pix[vis], "energy": energy}
    lo, hi = out[torch.float32], out[torch.float64]
    torch.testing.assert_close(lo["fk"], hi["fk"].float(), atol=1e-5, rtol=0)
    torch.testing.assert_close(lo["pix"], hi["pix"].float(), atol=1e-2, rtol=0)
    # pixel lookups may round to a neighbouring pixel at a boundary: compare the bulk
    rel = (lo["energy"].double() - hi["energy"]).abs() / hi["energy"].abs().clamp_min(1e-6)
    assert float(rel.median()) < 1e-3


def test_nearest_distance_matches_kdtree():
    from scipy.spatial import cKDTree

    from torchmocap.proposals.spatial import nearest_distance

    g = torch.Generator().manual_seed(0)
    cloud = torch.randn(1000, 3, generator=g, dtype=torch.float64)
    pts = torch.randn(50, 3, generator=g, dtype=torch.float64)
    d, _ = cKDTree(cloud.numpy()).query(pts.numpy(), k=1)
    torch.testing.assert_close(nearest_distance(pts, cloud, chunk=128),
                               torch.as_tensor(d), atol=1e-12, rtol=0)
