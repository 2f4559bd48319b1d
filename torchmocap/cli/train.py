"""``torchmocap-train``: train a learned likelihood term (Hydra; config ``conf/train.yaml``).

Builds the training and validation clips (synthesised, with negatives from the configured
tracker; cached), the term of ``term`` (bound to every clip's body and rig, one shared network),
and runs :class:`~torchmocap.learning.trainer.Trainer`. Outputs in the run directory:
``metrics.csv``, ``tb/`` (TensorBoard), ``checkpoints/last.pt`` and ``best.pt`` (resumable with
``resume=<file>``), ``weights.pt`` (the best network, weights only; ``export=<path>`` writes a
copy, e.g. into ``torchmocap/assets/learned/``) and ``summary.json``.

``--config-name train_keypoints`` trains the keypoint likelihood on a recording instead
(:mod:`torchmocap.cli.train_keypoints`; the config's ``runner`` names that training).

The default clips (``training_set: bundled``) are the packaged walk, so the command runs from
any directory; ``training_set=mocap`` trains on the real HDM05 and CMU clips (from the
repository root).
"""

from __future__ import annotations

import sys
from pathlib import Path

import hydra
from omegaconf import DictConfig, OmegaConf

from torchmocap.cli.runs import console_main, hydra_task


def _check_learned_term(cfg: DictConfig, base: type) -> None:
    """Refuse a ``term`` whose class is not a learned likelihood term (naming the options)."""
    from importlib import resources

    import yaml
    from hydra.utils import get_object

    target = cfg.term.get("_target_")
    try:
        cls = get_object(str(target))
    except Exception:
        cls = None
    if isinstance(cls, type) and issubclass(cls, base):
        return
    learned = []
    for p in sorted((resources.files("torchmocap") / "conf" / "term").iterdir()):
        if p.name.endswith(".yaml"):
            t = (yaml.safe_load(p.read_text(encoding="utf-8")) or {}).get("_target_")
            try:
                if issubclass(get_object(str(t)), base):
                    learned.append(p.name[:-5])
            except Exception:
                continue
    from hydra.core.hydra_config import HydraConfig

    choice = HydraConfig.get().runtime.choices.get("term") if HydraConfig.initialized() \
        else None
    raise ValueError(f"term{'=' + choice if choice else ''}: {target} is not a learned "
                     f"likelihood term (nothing of it is trained); torchmocap-train trains "
                     f"term={' | '.join(learned)}")


def run(cfg: DictConfig, out: Path) -> dict:
    """Train as configured; returns the summary written to ``out/summary.json``."""
    import time

    import torch

    from torchmocap.assembly import build
    from torchmocap.atomic import write_json_atomic
    from torchmocap.filters.tracking.tracker import check_seed
    from torchmocap.learning import NegativeSettings, load_clip_set
    from torchmocap.learning.trainer import EndToEndSettings, Trainer, TrainSettings
    from torchmocap.likelihoods.learned import LearnedLikelihood

    seed = check_seed(cfg.seed)
    _check_learned_term(cfg, LearnedLikelihood)  # before any synthesis
    o = cfg.objective
    settings = TrainSettings(
        objective=str(o.name), err_scale=float(o.err_scale),
        err_rotation=float(o.get("err_rotation", 0.0)), base=str(o.base),
        max_negatives=int(o.max_negatives), optimizer=str(cfg.optim.name),
        lr=float(cfg.optim.lr), weight_decay=float(cfg.optim.weight_decay),
        schedule=str(cfg.optim.schedule), grad_clip=float(cfg.optim.grad_clip),
        batch_size=int(cfg.batch_size), epochs=int(cfg.epochs), seed=int(seed),
        device=str(cfg.device),
        end_to_end=EndToEndSettings(**OmegaConf.to_container(o.end_to_end, resolve=True)))
    settings.check()  # settings errors before any synthesis
    n = cfg.data.negatives
    neg = NegativeSettings(tracker=str(n.tracker), num_particles=int(n.num_particles),
                           proposal_negatives=int(n.proposal_negatives),
                           scales=tuple(float(s) for s in n.scales),
                           hard_negatives=int(n.hard_negatives), stride=int(n.stride),
                           overrides=tuple(str(x) for x in n.get("overrides") or ()))
    t0 = time.perf_counter()
    d = cfg.data
    common = dict(scenarios=list(d.scenarios), seeds=list(d.seeds), negatives=neg,
                  cache_dir=d.cache_dir, progress=bool(cfg.progress),
                  scenario_overrides=OmegaConf.to_container(d.scenario_overrides, resolve=True))
    clips = OmegaConf.to_container(d.train_clips, resolve=True) if d.train_clips else []
    if not isinstance(clips, list) or not clips:
        raise ValueError(f"data.train_clips: expected a list of at least one clip, got {clips!r}")
    val_clips = OmegaConf.to_container(d.val_clips, resolve=True) if d.val_clips else []
    train = load_clip_set(clips, **common)
    mining = cfg.data.get("mining")
    if mining:  # more negatives: particle sets of another tracker (e.g. the last round's)
        import dataclasses

        mined = dataclasses.replace(neg, overrides=tuple(str(x) for x in mining.overrides),
                                    proposal_negatives=int(mining.get("proposal_negatives", 0)))
        extra = load_clip_set(clips, **{**common, "negatives": mined})
        for c in extra:
            for f in c.frames:
                f.clip += len(train)
        train = train + extra
    val = load_clip_set(val_clips, **common) if val_clips else []
    t_data = time.perf_counter() - t0
    torch.manual_seed(int(seed))  # the network's initialisation
    term = build(cfg.term, train[0].runtime, _path="term")
    if not isinstance(term, LearnedLikelihood):
        raise ValueError(f"term: {cfg.term._target_} is not a learned likelihood term")
    if cfg.get("init_weights"):
        term.load_weights(str(cfg.init_weights))
    trainer = Trainer(term, train, val, settings, out,
                      train_config=OmegaConf.to_container(cfg, resolve=True),
                      tensorboard=bool(cfg.get("tensorboard", True)),
                      progress=bool(cfg.progress),
                      base_likelihood=o.get("base_likelihood"))
    if cfg.get("resume"):
        trainer.resume(str(cfg.resume))
    t1 = time.perf_counter()
    metrics = trainer.fit()
    t_train = time.perf_counter() - t1
    weights = trainer.export(out / "weights.pt")
    if cfg.get("export"):
        trainer.export(Path(str(cfg.export)))
    summary = {"term": type(term).__name__, "config": term.config,
               "parameters": sum(p.numel() for p in term.net.parameters()),
               "train_frames": sum(len(c.frames) for c in train),
               "val_frames": sum(len(c.frames) for c in val),
               "seconds_data": t_data, "seconds_training": t_train,
               "epochs": trainer.epoch, "final": metrics[-1] if metrics else {},
               "weights": str(weights)}
    write_json_atomic(summary, out / "summary.json")
    return summary


@hydra.main(config_path="../conf", config_name="train", version_base="1.3")
@hydra_task("torchmocap-train")
def _hydra_main(cfg: DictConfig, out: Path) -> None:
    if cfg.get("runner"):  # another training (e.g. --config-name train_keypoints)
        from hydra.utils import get_method

        s = get_method(str(cfg.runner))(cfg, out)
        print(f"torchmocap-train: {s['report']}", file=sys.stderr)
        return
    s = run(cfg, out)
    f = s["final"]
    print(f"torchmocap-train: {s['epochs']} epochs in {s['seconds_training']:.0f} s "
          f"(data {s['seconds_data']:.0f} s); val ranking {f.get('val_ranking', float('nan')):.4f}"
          f", pairwise accuracy {f.get('val_pair_acc', float('nan')):.3f}; weights "
          f"{s['weights']}", file=sys.stderr)


def main() -> None:
    """Console entry point (exit status 2 when the run, or any job of a sweep, failed)."""
    console_main(_hydra_main)


if __name__ == "__main__":
    main()
