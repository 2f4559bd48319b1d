"""``torchmocap-track batch_seeds=[0,1,2]``: several seeds tracked in one process.

The job tracks every seed of ``batch_seeds`` with :func:`torchmocap.filters.track_groups`
and writes one run directory per seed, ``<run dir>/seed_<s>/``, with the files a separate run
with ``seed=<s>`` writes (``.hydra/overrides.yaml`` with ``seed=<s>``, so
``torchmocap-aggregate`` groups the seeds like the jobs of a seed sweep).
``<run dir>/batch.json`` lists the seeds.

A batched track is not bit-identical to the separate run of its seed: the energy of ``B x P``
particles is evaluated in one call, whose kernels may round the last bit of a row differently
than a call with ``P`` rows (by CPU, SIMD path and batch size), and a particle tracker amplifies
such differences over frames (the local descent of the refined presets most). What is promised
is that each seed's energies equal the separate run's to float rounding, so the tracks agree on
short horizons and are statistically equivalent. Hence a batched seed's ``metrics.json``
carries a fingerprint of its own (the seed's config plus the batch's seeds): rerunning the same
batch skips the complete seeds, but a separate ``seed=<s>`` run is never taken as up to date
from a batch's result, nor the other way round.

Which tracks share one energy batch: the run's seed also seeds the synthesised observations
unless the data node pins its own (``data.seed=<n>``). With a pinned data seed (or a recording,
which has none) every seed tracks the same sequence with one tracker, and the particles of all
seeds are evaluated together; otherwise each seed synthesises its own sequence, exactly as its
separate run would, and the seeds are tracked side by side in the process, each with its own
energy (the log says so).
"""

from __future__ import annotations

import sys
from pathlib import Path

from omegaconf import DictConfig, OmegaConf, open_dict

from torchmocap.atomic import write_json_atomic
from torchmocap.cli.runs import (
    completed_run,
    config_fingerprint,
    run_fingerprint,
)

__all__ = ["batch_fingerprint", "batch_seeds", "run_batch"]


def batch_seeds(cfg) -> list[int]:
    """The validated ``batch_seeds`` list (distinct integers)."""
    seeds = cfg.get("batch_seeds")
    if OmegaConf.is_config(seeds):
        seeds = OmegaConf.to_container(seeds)
    if isinstance(seeds, (int, str)) or not isinstance(seeds, (list, tuple)) or not seeds or \
            not all(isinstance(s, int) and not isinstance(s, bool) for s in seeds):
        raise ValueError(f"batch_seeds: expected a non-empty list of integer seeds, got {seeds!r}")
    if len(set(seeds)) != len(seeds):
        raise ValueError(f"batch_seeds: a seed is listed twice: {seeds}")
    return list(seeds)


def _seed_config(cfg: DictConfig, seed: int) -> DictConfig:
    c = cfg.copy()
    with open_dict(c):
        c.seed = seed
        c.batch_seeds = None
    return c


def batch_fingerprint(cfg: DictConfig, seed: int) -> str:
    """Fingerprint of seed ``seed``'s track in the batch ``cfg.batch_seeds``: the config of the
    separate run with that seed plus the batch's seeds, so it differs from the separate run's
    (whose arithmetic differs in the last bits; see the module docstring)."""
    c = _seed_config(cfg, seed)
    with open_dict(c):
        c.batch_seeds = batch_seeds(cfg)
    return config_fingerprint(c)


def _sequence_key(cfg) -> str:
    """What decides a run's sequence: its resolved data node and, when the node names no seed
    of its own and its source takes one, the run's seed (as
    :func:`~torchmocap.assembly.load_sequence` passes it)."""
    import json

    from hydra.utils import get_object

    from torchmocap.assembly import _accepts

    node = OmegaConf.to_container(cfg.data, resolve=True)
    injected = None
    if "seed" not in cfg.data and _accepts(get_object(cfg.data._target_), "seed")[0]:
        injected = int(cfg.seed)
    return json.dumps({"data": node, "seed": injected}, sort_keys=True, default=str)


def _write_hydra_records(out: Path, cfg: DictConfig, seed: int) -> None:
    """``.hydra/config.yaml`` and ``overrides.yaml`` of a seed's directory, as its separate
    run would have them."""
    import yaml

    overrides: list[str] = []
    try:
        from hydra.core.hydra_config import HydraConfig

        if HydraConfig.initialized():
            overrides = [str(o) for o in HydraConfig.get().overrides.task]
    except ValueError:
        pass
    keys = ("seed", "batch_seeds")
    overrides = [o for o in overrides if o.lstrip("+~").split("=", 1)[0] not in keys]
    overrides.append(f"seed={seed}")
    d = out / ".hydra"
    d.mkdir(parents=True, exist_ok=True)
    (d / "overrides.yaml").write_text(yaml.safe_dump(overrides), encoding="utf-8")
    (d / "config.yaml").write_text(OmegaConf.to_yaml(cfg), encoding="utf-8")


def run_batch(cfg: DictConfig, out: Path) -> dict:
    """Track every seed of ``cfg.batch_seeds`` in one process (see the module docstring);
    returns (and writes to ``out/batch.json``) the seeds, their run directories and, where
    known, each one's mean orientation error; every seed's metrics are in its directory."""
    from torchmocap.assembly import Runtime, build_tracker, load_sequence
    from torchmocap.cli.jobs import finish, thread_policy, validate_tracker
    from torchmocap.cli.outputs import print_summary, validate_outputs
    from torchmocap.cli.runs import reported_warnings
    from torchmocap.data import split_heldout
    from torchmocap.filters.tracking.batched import BatchGroup, track_groups

    seeds = batch_seeds(cfg)
    if cfg.get("checkpoint"):
        raise ValueError("checkpoint: not supported with batch_seeds (track the seeds as "
                         "separate runs to checkpoint them)")
    runs: dict[int, dict] = {}
    todo = []
    for s in seeds:
        cs = _seed_config(cfg, s)
        fp = batch_fingerprint(cfg, s)
        so = out / f"seed_{s}"
        done = completed_run(so, fp) if cfg.get("skip_completed", True) else None
        if done is not None:
            print(f"torchmocap-track: {so} is complete and up to date (fingerprint "
                  f"{done['fingerprint']}); skipped", file=sys.stderr)
            runs[s] = done
            continue
        for stale in ("failure.json", "metrics.json"):
            (so / stale).unlink(missing_ok=True)
        todo.append((s, cs, fp, so))
    if todo:
        governor = thread_policy(cfg)
        validate_tracker(todo[0][1])
        validate_outputs(cfg)
        keys = [_sequence_key(cs) for _, cs, _, _ in todo]
        shared = len(set(keys)) == 1
        if not shared:
            print("torchmocap-track: batch_seeds: the observations are synthesised with the "
                  "run's seed, so each seed tracks its own sequence (energies not batched); "
                  "set data.seed=<n> to track one sequence with every seed", file=sys.stderr)
        with reported_warnings("torchmocap-track") as warned:
            jobs, groups = [], []
            built: dict[str, tuple] = {}  # one sequence, runtime and tracker per sequence key
            for (s, cs, fp, so), key in zip(todo, keys):
                if key not in built:
                    seq = load_sequence(cs, min_frames=2, min_views=2)
                    tracked, _ = split_heldout(seq)
                    runtime = Runtime.from_sequence(tracked)
                    tracker = build_tracker(cs.tracker, runtime, seed=s)
                    tracker.check_sequence(tracked)
                    built[key] = (seq, tracked, runtime, tracker)
                seq, tracked, runtime, tracker = built[key]
                groups.append(BatchGroup(tracker, tracked, seed=s))
                jobs.append((s, cs, fp, so, seq, runtime, tracker))
            tracks = track_groups(groups, progress=bool(cfg.get("progress", True)),
                                  callbacks=[governor])
        batch = {"seeds": seeds, "size": len(groups), "shared_sequence": shared}
        for (s, cs, fp, so, seq, runtime, tracker), track in zip(jobs, tracks):
            so.mkdir(parents=True, exist_ok=True)
            _write_hydra_records(so, cs, s)
            tracker.seed = s  # the seed of this track (metrics, checkpoints)
            inputs = seq.meta.inputs
            runs[s] = finish(cs, so, seq, runtime, tracker, track, run_fingerprint(fp, inputs),
                             {"threads": governor.summary(), "batch": batch, "inputs": inputs,
                              "warnings": warned})
            print(f"seed {s} ({so}):")
            print_summary(runs[s])
    summary = {"batch_seeds": seeds,
               "run_dirs": {str(s): str(out / f"seed_{s}") for s in seeds},
               "orientation_error_deg_mean": {
                   str(s): runs[s].get("orientation_error_deg", {}).get("mean")
                   for s in seeds}}
    write_json_atomic(summary, out / "batch.json")
    return summary
